"""A SyGRID scene (bin, floor, parts at their poses, lights, camera) as Mitsuba objects.

Every part instance is its own Mitsuba mesh (vertices already in the world frame) so that the ``shape_index`` AOV
tells instances apart; scenes are loaded with ``optimize=False`` so Mitsuba does not merge shapes that share a BSDF.
``shape_index`` is the Dr.Jit registry id of the shape in the JIT variants and the 1-based position in
``scene.shapes()`` in ``scalar_rgb``; ``shape_index_values`` gives it per shape, so ids never rely on an order.

Camera: ``T_world_camera`` is an OpenCV camera (x right, y down, z forward); a Mitsuba sensor looks along its +z
with +x to the image's left and +y up, so ``T_world_sensor = T_world_camera @ diag(-1, -1, 1)``.

Non-square pixels: Mitsuba's perspective sensor has square pixels and refuses a scale in its pose. A camera with
``fx != fy`` is rendered as the sensor with focal length ``fy`` on both axes looking at the scene stretched by
``fx / fy`` along the camera's x axis about the camera centre (``anamorphic_warp``, applied to every shape and lamp):
every point then lands on the pixel ``K`` projects it to, and its camera-frame depth (z) is unchanged, so the RGB,
depth, ids and masks are exact in geometry; only the shading sees the stretched geometry's normals (and the
environment map, at infinity, is not stretched).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh

from sygrid.camera import CameraIntrinsics
from sygrid.mjspec import open_box_parts
from sygrid.objects.model import ObjectModel
from sygrid.physics import Instance
from sygrid.randomise.clutter import ClutterPiece
from sygrid.randomise.draws import FinishDraw, ItemDraws
from sygrid.render.materials import floor_bsdf, material_bsdf
from sygrid.render.randomised import box_projected_uv, finish_bsdf, finish_needs_uv, surface_bsdf
from sygrid.scene import ContainerSpec, EnvironmentSpec

_CV_TO_MITSUBA = np.diag([-1.0, -1.0, 1.0, 1.0])
NEAR_CLIP_M = 0.01
FAR_CLIP_M = 100.0
FLOOR_HALF_SIZE_M = 3.0
BIN_FLOOR_THICKNESS_M = 0.02  # as the physics drop builds the bin (sygrid.physics)


@dataclass
class MitsubaShapes:
    """The shapes and emitters of one scene, by name; part meshes are ``part_{k:04d}`` for instance k."""

    shapes: dict[str, object] = field(default_factory=dict)
    emitters: dict[str, dict] = field(default_factory=dict)
    part_names: list[str] = field(default_factory=list)


def sensor_dict(
    T_world_camera: np.ndarray,
    intrinsics: CameraIntrinsics,
    spp: int,
    rfilter: str = "box",
    pixel_format: str = "rgb",
) -> dict:
    """A Mitsuba perspective sensor matching an OpenCV pinhole camera with square pixels of focal length ``fy`` (the
    principal point becomes Mitsuba's principal point offset); with ``fx != fy`` the scene must be built with
    ``anamorphic_warp`` (see the module doc)."""
    import mitsuba as mi

    T = np.asarray(T_world_camera, dtype=float) @ _CV_TO_MITSUBA
    w, h = intrinsics.width, intrinsics.height
    return {
        "type": "perspective",
        "fov_axis": "y",
        "fov": math.degrees(2.0 * math.atan(0.5 * h / intrinsics.fy)),
        # Mitsuba's offsets move the image content the other way from an OpenCV principal point (measured).
        "principal_point_offset_x": (0.5 * w - intrinsics.cx - 0.5) / w,
        "principal_point_offset_y": (0.5 * h - intrinsics.cy - 0.5) / h,
        "near_clip": NEAR_CLIP_M,
        "far_clip": FAR_CLIP_M,
        "to_world": mi.ScalarTransform4f(T.tolist()),
        "film": {
            "type": "hdrfilm", "width": w, "height": h, "pixel_format": pixel_format,
            "rfilter": {"type": rfilter}, "sample_border": False,
        },
        "sampler": {"type": "independent", "sample_count": int(spp)},
    }  # fmt: skip


def anamorphic_warp(T_world_camera: np.ndarray, intrinsics: CameraIntrinsics) -> np.ndarray | None:
    """(4, 4) the world-to-world stretch by ``fx / fy`` along the camera's x axis about the camera centre that makes
    ``sensor_dict``'s square-pixel sensor render ``intrinsics``; None when the pixels are square."""
    fx, fy = float(intrinsics.fx), float(intrinsics.fy)
    if abs(fx - fy) <= 1e-9 * fy:
        return None
    T = np.asarray(T_world_camera, dtype=float)
    return T @ np.diag([fx / fy, 1.0, 1.0, 1.0]) @ np.linalg.inv(T)


def _warped(warp: np.ndarray | None, points_m: np.ndarray) -> np.ndarray:
    points_m = np.asarray(points_m, dtype=float)
    return points_m if warp is None else points_m @ warp[:3, :3].T + warp[:3, 3]


def make_mesh(
    name: str, vertices_m: np.ndarray, faces: np.ndarray, bsdf: object, uv: np.ndarray | None = None
) -> object:
    """A Mitsuba mesh from (n, 3) world-frame vertices and (m, 3) faces, with a loaded BSDF object and, optionally,
    (n, 2) texture coordinates."""
    import drjit as dr
    import mitsuba as mi

    V = np.ascontiguousarray(vertices_m, dtype=np.float32)
    F = np.ascontiguousarray(faces, dtype=np.uint32)
    props = mi.Properties()
    props["bsdf"] = bsdf
    mesh = mi.Mesh(name, len(V), len(F), props=props, has_vertex_texcoords=uv is not None)
    params = mi.traverse(mesh)
    arrays = {"vertex_positions": V, "faces": F}
    if uv is not None:
        arrays["vertex_texcoords"] = np.ascontiguousarray(uv, dtype=np.float32)
    for key, array in arrays.items():
        if dr.is_jit_v(mi.Float):
            params[key] = (mi.UInt32 if key == "faces" else mi.Float)(array.ravel())
        else:
            params[key] = array.ravel()
    params.update()
    return mesh


def _box_mesh(name: str, centre: np.ndarray, half: np.ndarray, bsdf: object, warp: np.ndarray | None) -> object:
    box = trimesh.creation.box(extents=2.0 * np.asarray(half))
    return make_mesh(name, _warped(warp, box.vertices + np.asarray(centre)), box.faces, bsdf)


def build_shapes(
    models: list[ObjectModel],
    instances: list[Instance],
    T_world_obj: np.ndarray,
    container: ContainerSpec,
    rng: np.random.Generator,
    warp: np.ndarray | None = None,
    draws: ItemDraws | None = None,
    clutter: Sequence[ClutterPiece] = (),
) -> MitsubaShapes:
    """Floor, the bin (5 boxes, frame = world origin at the inner floor centre), one mesh per part instance and one
    per distractor (``clutter``, named ``clutter_{k:04d}``); ``warp``: ``anamorphic_warp``'s stretch of every
    vertex, or None.

    Materials are drawn from ``rng`` once per model (all instances of a part share a finish) and once for the bin,
    whatever ``draws`` holds (so the renderer's later draws never depend on the randomisation); the randomisation's
    ``surfaces`` (textured floor and bin) and ``parts`` (one finish per instance) then replace them when drawn.
    """
    import mitsuba as mi

    if len(T_world_obj) != len(instances):
        raise ValueError(f"T_world_obj has {len(T_world_obj)} poses for {len(instances)} instances")
    out = MitsubaShapes()
    f = BIN_FLOOR_THICKNESS_M
    floor_dict, bin_dict = floor_bsdf(rng), material_bsdf(container.material, rng)
    model_dicts = [material_bsdf(m.material, rng) for m in models]
    surfaces = draws.surfaces if draws is not None else None
    finishes = draws.parts if draws is not None else None
    quad = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]]) * FLOOR_HALF_SIZE_M + [0, 0, -f]
    quad_faces = np.array([[0, 1, 2], [0, 2, 3]])
    if surfaces is None:
        out.shapes["floor"] = make_mesh("floor", _warped(warp, quad), quad_faces, mi.load_dict(floor_dict))
        bin_bsdf = mi.load_dict(bin_dict)
    else:
        V, F, uv = box_projected_uv(quad, quad_faces, surfaces["floor"].tile_m)
        out.shapes["floor"] = make_mesh("floor", _warped(warp, V), F, mi.load_dict(surface_bsdf(surfaces["floor"])), uv)
        bin_bsdf = mi.load_dict(surface_bsdf(surfaces["bin"]))
    for part, (centre, half) in open_box_parts(container.inner_size_m, container.wall_thickness_m, f).items():
        name = f"bin_{part}"
        if surfaces is None:
            out.shapes[name] = _box_mesh(name, np.array(centre), np.array(half), bin_bsdf, warp)
        else:
            box = trimesh.creation.box(extents=2.0 * np.asarray(half))
            V, F, uv = box_projected_uv(box.vertices + np.asarray(centre), box.faces, surfaces["bin"].tile_m)
            out.shapes[name] = make_mesh(name, _warped(warp, V), F, bin_bsdf, uv)
    bsdfs = [mi.load_dict(d) for d in model_dicts] if finishes is None else []
    for k, (inst, T) in enumerate(zip(instances, np.asarray(T_world_obj, dtype=float), strict=True)):
        model = models[inst.model_index]
        name = f"part_{k:04d}"
        if finishes is None:
            V = _warped(warp, model.mesh.vertices @ T[:3, :3].T + T[:3, 3])
            out.shapes[name] = make_mesh(name, V, model.mesh.faces, bsdfs[inst.model_index])
        else:
            out.shapes[name] = _finished_mesh(name, model, T, finishes[k], warp)
        out.part_names.append(name)
    for k, piece in enumerate(clutter):
        name = f"clutter_{k:04d}"
        out.shapes[name] = _finished_mesh(name, piece.model, piece.T_world_obj, piece.finish, warp)
    return out


def _finished_mesh(name: str, model: ObjectModel, T: np.ndarray, finish: FinishDraw, warp: np.ndarray | None) -> object:
    """A mesh of ``model`` at ``T`` with ``finish``; texture coordinates (box-projected in the object frame, one
    tile per model diameter) when the finish needs them."""
    import mitsuba as mi

    V, F, uv = model.mesh.vertices, model.mesh.faces, None
    if finish_needs_uv(finish):
        V, F, uv = box_projected_uv(V, F, max(model.diameter_m, 1e-3))
    V = _warped(warp, np.asarray(V) @ T[:3, :3].T + T[:3, 3])
    return make_mesh(name, V, F, mi.load_dict(finish_bsdf(finish)), uv)


def environment_emitters(
    env: EnvironmentSpec, rng: np.random.Generator, base_dir: Path | str = ".", warp: np.ndarray | None = None
) -> dict:
    """Lights: the environment map file when the scene names one, else a constant sky and 1-3 (``random_lights``)
    area lights above the bin, all drawn from ``rng``; ``warp``: ``anamorphic_warp``'s stretch of the lamps, or
    None (lights at infinity are not stretched)."""
    import mitsuba as mi

    s = env.strength
    if env.map_file is not None:
        path = Path(env.map_file)
        path = path if path.is_absolute() else Path(base_dir) / path
        if not path.is_file():
            raise FileNotFoundError(f"environment.map_file: no such file {path}")
        spin = float(rng.uniform(0.0, 360.0))
        # Mitsuba's envmap has y up; the scene has z up.
        to_world = mi.ScalarTransform4f().rotate([0, 0, 1], spin).rotate([1, 0, 0], 90.0)
        return {"env": {"type": "envmap", "filename": str(path), "scale": s, "to_world": to_world}}
    emitters: dict[str, dict] = {}
    if env.procedural:
        sky = float(rng.uniform(0.15, 0.6)) * s
        emitters["sky"] = {"type": "constant", "radiance": {"type": "rgb", "value": [sky, sky, sky * 1.05]}}
    lo, hi = env.random_lights
    for i in range(int(rng.integers(lo, hi + 1))):
        height = float(rng.uniform(0.7, 1.5))
        xy = rng.uniform(-0.6, 0.6, 2)
        side = float(rng.uniform(0.15, 0.4))
        pos = [float(xy[0]), float(xy[1]), height]
        radiance = float(rng.uniform(8.0, 30.0)) * s * (height / side) ** 2 / 16.0
        warm = rng.uniform(0.9, 1.1, 3)
        to_world = mi.ScalarTransform4f.look_at(origin=pos, target=[0, 0, 0], up=[0, 1, 0]).scale(
            [side / 2, side / 2, 1.0]
        )
        if warp is not None:
            to_world = mi.ScalarTransform4f(warp.tolist()) @ to_world
        emitters[f"lamp_{i}"] = {
            "type": "rectangle",
            "to_world": to_world,
            "emitter": {"type": "area", "radiance": {"type": "rgb", "value": (radiance * warm).tolist()}},
            "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.0, 0.0, 0.0]}},
        }
    return emitters


def shape_index_values(scene: object) -> dict[str, int]:
    """Shape id (``Shape.id()``, the dict key it was loaded under) -> the value the ``shape_index`` AOV writes."""
    import drjit as dr
    import mitsuba as mi

    shapes = scene.shapes()
    if dr.is_jit_v(mi.Float):
        values = np.asarray(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(shapes))).astype(np.int64).tolist()
    else:
        values = list(range(1, len(shapes) + 1))
    return {s.id(): int(v) for s, v in zip(shapes, values, strict=True)}
