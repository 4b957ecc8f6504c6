"""Writes the foreign CAD test set: small industrial-style meshes in millimetres, binary STL, that are not the
built-in parts and that carry the problems of real CAD exports.

    python scripts/make_foreign_parts.py [--out tests/fixtures/foreign_parts] [--seed 0]

Parts (file stem: what it is, what makes it hard):

- ``strap_clamp``: a sheet-metal P-clip, its strap a loop whose end comes back over the tab 1 mm above it,
  exported as a zero-thickness open surface (the sheet's mid-surface).
- ``nozzle``: a revolved thin wall (1 mm) of a cone with a collar, inner and outer surfaces but no end caps (open).
- ``bolt_nut_pair``: an M8 hex bolt and a nut on its shank that does not touch it: two closed bodies in one file.
- ``plate_bracket``: an angle bracket made of three separate 2 mm plates (base, upright, gusset) that overlap one
  another: three closed bodies, never unioned, so they intersect.
- ``duct_cover``: a U-shaped cable-duct cover with 1 mm walls and snap lips: closed, thin-walled.
- ``spacer_block``: a block with a counterbored through hole: a plain closed part.

The same seed gives the same files byte for byte; another seed varies each dimension by up to 5 %.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path

import numpy as np
import shapely.geometry
import trimesh

JITTER = 0.05  # each dimension is scaled by a factor drawn in [1 - JITTER, 1 + JITTER]


def _ribbon(centreline_xz: np.ndarray, width: float) -> trimesh.Trimesh:
    """An open surface: the polyline ``centreline_xz`` (n, 2) swept along y over ``width``."""
    n = len(centreline_xz)
    x, z = centreline_xz[:, 0], centreline_xz[:, 1]
    vertices = np.concatenate(
        [np.column_stack([x, np.full(n, -width / 2), z]), np.column_stack([x, np.full(n, width / 2), z])]
    )
    i = np.arange(n - 1)
    faces = np.concatenate([np.column_stack([i, i + 1, n + i + 1]), np.column_stack([i, n + i + 1, n + i])])
    return trimesh.Trimesh(vertices, faces, process=False)


def strap_clamp(s: Callable[[float], float]) -> trimesh.Trimesh:
    radius, width, tab, gap = s(12.0), s(10.0), s(22.0), 1.0
    # lower tab from x = tab to 0, then the loop about (0, radius) from the bottom, round to the top of the tab
    lower = np.column_stack([np.linspace(tab, 0.0, 8), np.zeros(8)])
    # the loop ends where it meets the level z = gap again on its way back (just past a full turn)
    end = 2 * np.pi + np.arcsin(gap / radius)
    angle = np.linspace(0.0, end, 72)[1:]
    loop = np.column_stack([-radius * np.sin(angle), radius - radius * np.cos(angle)])
    loop[-1] = [loop[-1, 0], gap]
    upper = np.column_stack([np.linspace(loop[-1, 0], tab, 9)[1:], np.full(8, gap)])
    return _ribbon(np.concatenate([lower, loop, upper]), width)


def _revolve_surface(profile_rz: np.ndarray, sections: int) -> trimesh.Trimesh:
    """The open surface of revolution of the polyline ``profile_rz`` (n, 2) about z (no caps)."""
    n = len(profile_rz)
    theta = 2 * np.pi * np.arange(sections) / sections
    r, z = profile_rz[:, 0], profile_rz[:, 1]
    vertices = np.stack(
        [np.outer(np.cos(theta), r), np.outer(np.sin(theta), r), np.tile(z, (sections, 1))], axis=-1
    ).reshape(-1, 3)
    a = np.arange(sections)[:, None] * n + np.arange(n - 1)[None, :]
    b = ((np.arange(sections)[:, None] + 1) % sections) * n + np.arange(n - 1)[None, :]
    faces = np.concatenate([np.stack([a, b, b + 1], -1).reshape(-1, 3), np.stack([a, b + 1, a + 1], -1).reshape(-1, 3)])
    return trimesh.Trimesh(vertices, faces, process=False)


def nozzle(s: Callable[[float], float]) -> trimesh.Trimesh:
    wall, base_r, tip_r = 1.0, s(11.0), s(4.0)
    collar, length = s(8.0), s(34.0)
    z = np.array([0.0, collar * 0.5, collar, collar + 0.25 * length, collar + 0.6 * length, collar + length])
    r_out = np.array([base_r, base_r, base_r * 0.92, base_r * 0.7, 0.45 * (base_r + tip_r), tip_r])
    outer = _revolve_surface(np.column_stack([r_out, z]), 40)
    inner = _revolve_surface(np.column_stack([r_out - wall, z])[::-1], 40)  # reversed: its normals face the bore
    return trimesh.util.concatenate([outer, inner])


def _hex_prism(across_flats: float, height: float, z0: float) -> trimesh.Trimesh:
    prism = trimesh.creation.cylinder(radius=across_flats / np.sqrt(3.0), height=height, sections=6)
    prism.apply_translation([0.0, 0.0, z0 + height / 2])
    return prism


def bolt_nut_pair(s: Callable[[float], float]) -> trimesh.Trimesh:
    af, head_h, shank_r, shank_l = s(13.0), s(5.3), 4.0, s(30.0)
    head = _hex_prism(af, head_h, 0.0)
    shank = trimesh.creation.cylinder(radius=shank_r, height=shank_l + 1.0, sections=32)
    shank.apply_translation([0.0, 0.0, head_h - 1.0 + (shank_l + 1.0) / 2])
    bolt = trimesh.boolean.union([head, shank], engine="manifold")
    nut_h, hole_r = s(6.5), shank_r + 0.4  # 0.4 mm radial clearance: the nut does not touch the shank
    nut_body = _hex_prism(af, nut_h, head_h + 0.55 * shank_l)
    hole = trimesh.creation.cylinder(radius=hole_r, height=nut_h + 2.0, sections=32)
    hole.apply_translation([0.0, 0.0, head_h + 0.55 * shank_l + nut_h / 2])
    nut = trimesh.boolean.difference([nut_body, hole], engine="manifold")
    return trimesh.util.concatenate([bolt, nut])


def _plate(size: tuple[float, float, float], centre: tuple[float, float, float], hole_r: float) -> trimesh.Trimesh:
    plate = trimesh.creation.box(size)
    if hole_r > 0:
        axis = int(np.argmin(size))
        hole = trimesh.creation.cylinder(radius=hole_r, height=size[axis] + 2.0, sections=24)
        if axis != 2:
            turn = [1, 0, 0] if axis == 1 else [0, 1, 0]
            hole.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, turn))
        plate = trimesh.boolean.difference([plate, hole], engine="manifold")
    plate.apply_translation(centre)
    return plate


def plate_bracket(s: Callable[[float], float]) -> trimesh.Trimesh:
    length, depth, height, t = s(40.0), s(30.0), s(26.0), 2.0
    base = _plate((length, depth, t), (0.0, 0.0, t / 2), s(3.2))
    # the upright sinks 1.4 mm into the base along its edge, 0.3 mm in from the base's side: no shared faces
    upright = _plate((length, t, height), (0.0, -depth / 2 + 0.3 + t / 2, 0.6 + height / 2), s(3.2))
    # a triangle in the (y, z) plane from the inside corner, 2 mm thick along x, overlapping both plates
    corner_y = -depth / 2 + 0.7
    gusset_yz = shapely.geometry.Polygon([(corner_y, 1.1), (corner_y + 0.6 * depth, 1.1), (corner_y, 0.8 * height)])
    gusset = trimesh.creation.extrude_polygon(gusset_yz, t)  # vertices (y, z, x)
    gusset.vertices = gusset.vertices[:, [2, 0, 1]] - [t / 2, 0.0, 0.0]  # a cyclic permutation: a rotation
    return trimesh.util.concatenate([base, upright, gusset])


def duct_cover(s: Callable[[float], float]) -> trimesh.Trimesh:
    width, height, length, wall, lip = s(20.0), s(12.0), s(50.0), 1.0, s(2.0)
    w, h = width / 2, height
    outline = [
        (-w, 0.0), (-w + wall + lip, 0.0), (-w + wall + lip, wall), (-w + wall, wall), (-w + wall, h - wall),
        (w - wall, h - wall), (w - wall, wall), (w - wall - lip, wall), (w - wall - lip, 0.0), (w, 0.0), (w, h),
        (-w, h),
    ]  # fmt: skip
    profile = shapely.geometry.Polygon(outline)
    if not profile.is_valid:
        raise ValueError("duct_cover: invalid profile")
    return trimesh.creation.extrude_polygon(profile, length)


def spacer_block(s: Callable[[float], float]) -> trimesh.Trimesh:
    size = (s(30.0), s(20.0), s(15.0))
    block = trimesh.creation.box(size)
    hole = trimesh.creation.cylinder(radius=s(4.5), height=size[2] + 2.0, sections=32)
    counterbore = trimesh.creation.cylinder(radius=s(7.5), height=6.0, sections=32)
    counterbore.apply_translation([0.0, 0.0, size[2] / 2])
    return trimesh.boolean.difference([block, hole, counterbore], engine="manifold")


PARTS: dict[str, Callable[[Callable[[float], float]], trimesh.Trimesh]] = {
    "strap_clamp": strap_clamp,
    "nozzle": nozzle,
    "bolt_nut_pair": bolt_nut_pair,
    "plate_bracket": plate_bracket,
    "duct_cover": duct_cover,
    "spacer_block": spacer_block,
}


def make_parts(out_dir: Path, seed: int = 0) -> list[Path]:
    """Writes every part of ``PARTS`` to ``out_dir/<name>.stl`` (binary, millimetres); returns the paths."""
    rng = np.random.default_rng(seed)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    for name, build in PARTS.items():
        factors = iter(rng.uniform(1.0 - JITTER, 1.0 + JITTER, size=16)) if seed else None

        def scaled(value: float, factors=factors) -> float:
            return value * next(factors) if factors is not None else value

        mesh = build(scaled)
        path = out_dir / f"{name}.stl"
        path.write_bytes(trimesh.exchange.stl.export_stl(mesh))
        paths.append(path)
    return paths


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, default=Path("tests/fixtures/foreign_parts"))
    parser.add_argument("--seed", type=int, default=0, help="0: the nominal dimensions (the committed set)")
    args = parser.parse_args()
    for path in make_parts(args.out, args.seed):
        mesh = trimesh.load(path, force="mesh")
        print(
            f"{path}: {len(mesh.faces)} faces, {path.stat().st_size / 1024:.0f} KiB, watertight={mesh.is_watertight}, "
            f"bodies={mesh.body_count}, extents {np.round(mesh.extents, 1).tolist()} mm"
        )


if __name__ == "__main__":
    main()
