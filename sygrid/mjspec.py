"""MjSpec building blocks shared by the generator's drop and the simulated cell, so that a pile the generator
renders and a pile the robot picks from are made of the same bodies: the open box (bin, tray) and the part body
(free joint, true mass and inertia, collision geoms of its collision tier); and the camera both render through, any
pinhole intrinsics included (``add_camera``, ``model_camera_intrinsics``)."""

from __future__ import annotations

import mujoco
import numpy as np
from scipy.spatial.transform import Rotation

from sygrid.camera import CameraIntrinsics
from sygrid.objects.collision.geometry import CollisionModel
from sygrid.objects.model import ObjectModel

_GEOM_TYPES = {
    "box": mujoco.mjtGeom.mjGEOM_BOX,
    "cylinder": mujoco.mjtGeom.mjGEOM_CYLINDER,
    "mesh": mujoco.mjtGeom.mjGEOM_MESH,
}
COLLISION_GROUP = 3  # collision-only geoms: hidden in renders
VISUAL_GROUP = 1
# OpenCV camera axes (x right, y down, z forward) -> MuJoCo camera axes (x right, y up, looking along -z).
CV_TO_MUJOCO_CAMERA = np.diag([1.0, -1.0, -1.0])
# A camera given by its sensor renders in lengths on the sensor; only ratios matter, so the pixel pitch is arbitrary.
_SENSOR_PITCH_M = 1e-5


def quat_wxyz(R: np.ndarray) -> np.ndarray:
    """A 3x3 rotation as MuJoCo's (w, x, y, z) quaternion."""
    x, y, z, w = Rotation.from_matrix(R).as_quat()
    return np.array([w, x, y, z])


def part_inertial(model: ObjectModel) -> tuple[float, np.ndarray, np.ndarray]:
    """Mass (kg), centre of mass (m, object frame) and MuJoCo's full inertia [ixx, iyy, izz, ixy, ixz, iyz]
    (kg m^2, about the centre of mass), from the part's solid (``ObjectModel.solid``: the true mesh, or the repair
    of an open or multi-body one) and its density: a collision hull would fill the holes and overstate both."""
    solid = model.solid
    inertia = np.asarray(solid.moment_inertia) * model.density_kg_m3  # trimesh: unit density
    full = [inertia[0, 0], inertia[1, 1], inertia[2, 2], inertia[0, 1], inertia[0, 2], inertia[1, 2]]
    return model.mass_kg, np.asarray(solid.center_mass), np.array(full)


def open_box_parts(
    inner_size_m: tuple[float, float, float], wall_m: float, floor_m: float
) -> dict[str, tuple[list[float], list[float]]]:
    """The five boxes of an open box whose frame is the centre of its inner floor: name -> (centre, half-size),
    metres. Shared by the physics/cell bodies and the renderer's bin, so all three see the same bin."""
    sx, sy, sz = (v / 2 for v in inner_size_m)
    t = wall_m / 2
    return {
        "floor": ([0, 0, -floor_m / 2], [sx + 2 * t, sy + 2 * t, floor_m / 2]),
        "wall_xp": ([sx + t, 0, sz], [t, sy + 2 * t, sz]),
        "wall_xn": ([-sx - t, 0, sz], [t, sy + 2 * t, sz]),
        "wall_yp": ([0, sy + t, sz], [sx, t, sz]),
        "wall_yn": ([0, -sy - t, sz], [sx, t, sz]),
    }


def add_open_box(
    parent: mujoco.MjsBody,
    name: str,
    T_parent_box: np.ndarray,
    inner_size_m: tuple[float, float, float],
    wall_m: float,
    floor_m: float,
    solref: list[float],
    friction: list[float],
    rgba: tuple[float, ...] = (0.5, 0.5, 0.55, 1.0),
) -> mujoco.MjsBody:
    """A static open box (bin, tray) whose frame is the centre of its inner floor."""
    body = parent.add_body(name=name, pos=T_parent_box[:3, 3].tolist(), quat=quat_wxyz(T_parent_box[:3, :3]).tolist())
    for part, (pos, half) in open_box_parts(inner_size_m, wall_m, floor_m).items():
        body.add_geom(
            name=f"{name}_{part}", type=mujoco.mjtGeom.mjGEOM_BOX, pos=pos, size=half, rgba=rgba,
            friction=friction, solref=solref,
        )  # fmt: skip
    return body


def add_mesh_asset(spec: mujoco.MjSpec, name: str, vertices: np.ndarray, faces: np.ndarray | None = None) -> str:
    """Adds a mesh asset once per name (meshes are shared by all instances of a part)."""
    if spec.mesh(name) is None:
        mesh = spec.add_mesh(name=name, uservert=np.asarray(vertices, dtype=np.float64).ravel().tolist())
        if faces is not None:
            mesh.userface = np.asarray(faces, dtype=np.int32).ravel().tolist()
    return name


def add_part_body(
    spec: mujoco.MjSpec,
    name: str,
    model: ObjectModel,
    collision: CollisionModel | None,
    T_world_obj: np.ndarray,
    solref: list[float],
    friction: list[float],
    visual_rgba: tuple[float, ...] | None = None,
) -> mujoco.MjsBody:
    """A free body for one part instance: true mass and inertia, collision geoms from ``collision`` (its mesh,
    convexified by MuJoCo, when None) and, with ``visual_rgba``, the true mesh as a non-colliding visual geom."""
    body = spec.worldbody.add_body(
        name=name, pos=T_world_obj[:3, 3].tolist(), quat=quat_wxyz(T_world_obj[:3, :3]).tolist()
    )
    body.add_freejoint(name=f"{name}_free")
    body.explicitinertial = True
    mass, com, inertia = part_inertial(model)
    body.mass, body.ipos, body.fullinertia = mass, com.tolist(), inertia.tolist()
    contact = {"solref": solref, "friction": friction, "mass": 0}
    visible = {"rgba": list(visual_rgba)} if visual_rgba is not None else {}
    if collision is None:
        mesh = add_mesh_asset(spec, f"mesh_{model.content_hash[:16]}", model.mesh.vertices, model.mesh.faces)
        body.add_geom(type=_GEOM_TYPES["mesh"], meshname=mesh, group=VISUAL_GROUP, **contact, **visible)
        return body
    if visual_rgba is not None:
        mesh = add_mesh_asset(spec, f"mesh_{model.content_hash[:16]}", model.mesh.vertices, model.mesh.faces)
        body.add_geom(
            type=_GEOM_TYPES["mesh"], meshname=mesh, contype=0, conaffinity=0, group=VISUAL_GROUP, mass=0, **visible
        )
    for g, geom in enumerate(collision.to_mujoco_geoms()):
        mesh = ""
        if geom["type"] == "mesh":
            asset = f"hull_{collision.content_hash[:16]}_{collision.tier.value}_{g}"
            mesh = add_mesh_asset(spec, asset, geom["vertices"])
        body.add_geom(
            type=_GEOM_TYPES[geom["type"]], meshname=mesh, size=[*geom["size"], 0.0, 0.0, 0.0][:3],
            pos=geom["pos"].tolist(), quat=geom["quat"].tolist(), group=COLLISION_GROUP, **contact,
        )  # fmt: skip
    return body


def add_camera(body: mujoco.MjsBody, name: str, T_body_camera: np.ndarray, K: CameraIntrinsics) -> mujoco.MjsCamera:
    """A camera on ``body`` at the OpenCV pose ``T_body_camera`` that renders the pinhole ``K`` at ``K.width`` x
    ``K.height``. Square pixels with the principal point at the image centre (``CameraIntrinsics.from_fov``) give a
    plain ``fovy`` camera; any other intrinsics (``fx != fy``, an off-centre principal point) are given to MuJoCo as
    they are: resolution, sensor size, focal length and principal point in pixels (MuJoCo's principal point is the
    image centre's offset from the OpenCV one, both axes)."""
    camera = body.add_camera(
        name=name, pos=np.asarray(T_body_camera)[:3, 3].tolist(),
        quat=quat_wxyz(np.asarray(T_body_camera)[:3, :3] @ CV_TO_MUJOCO_CAMERA).tolist(), fovy=K.fov_y_deg,
    )  # fmt: skip
    square = abs(K.fx - K.fy) <= 1e-9 * K.fy
    centred = abs(K.cx - (K.width - 1) / 2) <= 1e-9 * K.width and abs(K.cy - (K.height - 1) / 2) <= 1e-9 * K.height
    if not (square and centred):
        camera.resolution = [K.width, K.height]
        camera.sensor_size = [K.width * _SENSOR_PITCH_M, K.height * _SENSOR_PITCH_M]
        camera.focal_pixel = [K.fx, K.fy]
        camera.principal_pixel = [K.width / 2 - (K.cx + 0.5), K.height / 2 - (K.cy + 0.5)]
    return camera


def model_camera_intrinsics(model: mujoco.MjModel, camera_id: int, width: int, height: int) -> CameraIntrinsics:
    """The pinhole a compiled model's camera renders into a ``width`` x ``height`` image: its own intrinsics
    (``add_camera``) scaled to that size, or, for a ``fovy`` camera, square pixels centred at that size."""
    sensor = np.asarray(model.cam_sensorsize[camera_id], dtype=float)
    if sensor[1] <= 0:
        return CameraIntrinsics.from_fov(width, height, float(model.cam_fovy[camera_id]))
    w, h = (int(v) for v in model.cam_resolution[camera_id])
    fx, fy, px, py = (float(v) for v in model.cam_intrinsic[camera_id])
    sx, sy = w / sensor[0], h / sensor[1]  # pixels per sensor length
    K = CameraIntrinsics(fx * sx, fy * sy, w / 2 - 0.5 - px * sx, h / 2 - 0.5 - py * sy, w, h)
    return K if (width, height) == (w, h) else K.scaled(width, height)
