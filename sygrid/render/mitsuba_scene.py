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
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sygrid.camera import CameraIntrinsics
from sygrid.mjspec import open_box_parts
from sygrid.objects.model import ObjectModel
from sygrid.physics import Instance
from sygrid.render.materials import floor_bsdf, material_bsdf
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


def make_mesh(name: str, vertices_m: np.ndarray, faces: np.ndarray, bsdf: object) -> object:
    """A Mitsuba mesh from (n, 3) world-frame vertices and (m, 3) faces, with a loaded BSDF object."""
    import drjit as dr
    import mitsuba as mi

    V = np.ascontiguousarray(vertices_m, dtype=np.float32)
    F = np.ascontiguousarray(faces, dtype=np.uint32)
    props = mi.Properties()
    props["bsdf"] = bsdf
    mesh = mi.Mesh(name, len(V), len(F), props=props)
    params = mi.traverse(mesh)
    if dr.is_jit_v(mi.Float):
        params["vertex_positions"] = mi.Float(V.ravel())
        params["faces"] = mi.UInt32(F.ravel())
    else:
        params["vertex_positions"] = V.ravel()
        params["faces"] = F.ravel()
    params.update()
    return mesh


def _box_mesh(name: str, centre: np.ndarray, half: np.ndarray, bsdf: object, warp: np.ndarray | None) -> object:
    import trimesh

    box = trimesh.creation.box(extents=2.0 * np.asarray(half))
    return make_mesh(name, _warped(warp, box.vertices + np.asarray(centre)), box.faces, bsdf)


def build_shapes(
    models: list[ObjectModel],
    instances: list[Instance],
    T_world_obj: np.ndarray,
    container: ContainerSpec,
    rng: np.random.Generator,
    warp: np.ndarray | None = None,
) -> MitsubaShapes:
    """Floor, the bin (5 boxes, frame = world origin at the inner floor centre) and one mesh per part instance;
    ``warp``: ``anamorphic_warp``'s stretch of every vertex, or None.

    Materials are drawn from ``rng`` once per model (all instances of a part share a finish) and once for the bin.
    """
    import mitsuba as mi

    if len(T_world_obj) != len(instances):
        raise ValueError(f"T_world_obj has {len(T_world_obj)} poses for {len(instances)} instances")
    out = MitsubaShapes()
    f = BIN_FLOOR_THICKNESS_M
    floor = mi.load_dict(floor_bsdf(rng))
    out.shapes["floor"] = make_mesh(
        "floor",
        _warped(warp, np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]]) * FLOOR_HALF_SIZE_M + [0, 0, -f]),
        np.array([[0, 1, 2], [0, 2, 3]]),
        floor,
    )
    bin_bsdf = mi.load_dict(material_bsdf(container.material, rng))
    for part, (centre, half) in open_box_parts(container.inner_size_m, container.wall_thickness_m, f).items():
        out.shapes[f"bin_{part}"] = _box_mesh(f"bin_{part}", np.array(centre), np.array(half), bin_bsdf, warp)
    bsdfs = [mi.load_dict(material_bsdf(m.material, rng)) for m in models]
    for k, (inst, T) in enumerate(zip(instances, np.asarray(T_world_obj, dtype=float), strict=True)):
        model = models[inst.model_index]
        V = _warped(warp, model.mesh.vertices @ T[:3, :3].T + T[:3, 3])
        name = f"part_{k:04d}"
        out.shapes[name] = make_mesh(name, V, model.mesh.faces, bsdfs[inst.model_index])
        out.part_names.append(name)
    return out


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
