"""Ray-cast test scenes with known answers: built-in parts at known poses on a floor (the bin's), seen by a pinhole
camera; exact z-depth and each part's visible mask (open3d ``RaycastingScene``, no renderer)."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import open3d as o3d

from perception.results import Detection
from sygrid.camera import CameraIntrinsics
from sygrid.objects.model import ObjectModel
from sygrid.transforms import make_T, rotation_about

CAMERA = CameraIntrinsics.from_fov(320, 240, 40.0)
# The floor: the plane z = FLOOR_Z_M of a frame tilted 20 degrees about the camera's x axis (a camera looking down
# into a bin at an angle).
T_CAMERA_FLOOR = make_T(rotation_about(np.array([1.0, 0.0, 0.0]), np.radians(160.0)), [0.0, 0.0, 0.32])


@dataclass(frozen=True)
class Scene:
    depth: np.ndarray  # (h, w) float32 metres, 0 = no data
    masks: list[np.ndarray]  # per part, (h, w) bool: its visible pixels
    poses: list[np.ndarray]  # per part, T_camera_object


def on_floor(
    model: ObjectModel, x_m: float, y_m: float, turn_deg: float, R_lying: np.ndarray | None = None
) -> np.ndarray:
    """T_camera_object of ``model`` resting on the floor at (x, y) of the floor frame: its rotation ``R_lying``
    (object -> floor; identity: z up), turned ``turn_deg`` about the floor normal, lowest point on the floor."""
    R = rotation_about(np.array([0.0, 0.0, 1.0]), np.radians(turn_deg)) @ (np.eye(3) if R_lying is None else R_lying)
    lowest = (np.asarray(model.mesh.vertices) @ R.T)[:, 2].min()
    return T_CAMERA_FLOOR @ make_T(R, [x_m, y_m, -lowest])


def render(parts: list[tuple[ObjectModel, np.ndarray]], floor: bool = True, camera: CameraIntrinsics = CAMERA) -> Scene:
    """Depth and visible masks of the parts (and a 0.4 m square floor) seen by ``camera``."""
    scene = o3d.t.geometry.RaycastingScene()
    ids = []
    for model, T in parts:
        vertices = np.asarray(model.mesh.vertices) @ T[:3, :3].T + T[:3, 3]
        ids.append(
            scene.add_triangles(
                o3d.core.Tensor(vertices.astype(np.float32)),
                o3d.core.Tensor(np.asarray(model.mesh.faces, dtype=np.uint32)),
            )
        )
    if floor:
        corners = np.array([[-0.2, -0.2, 0], [0.2, -0.2, 0], [0.2, 0.2, 0], [-0.2, 0.2, 0]])
        corners = corners @ T_CAMERA_FLOOR[:3, :3].T + T_CAMERA_FLOOR[:3, 3]
        scene.add_triangles(
            o3d.core.Tensor(corners.astype(np.float32)), o3d.core.Tensor(np.array([[0, 1, 2], [0, 2, 3]], np.uint32))
        )
    K = camera.K.copy()
    K[:2, 2] += 0.5  # open3d casts through u + 0.5; our pixel centres are the integers
    rays = scene.create_rays_pinhole(o3d.core.Tensor(K), o3d.core.Tensor(np.eye(4)), camera.width, camera.height)
    hit = scene.cast_rays(rays)
    depth = hit["t_hit"].numpy()  # the ray directions have z = 1: t is the z-depth
    depth[~np.isfinite(depth)] = 0.0
    geometry = hit["geometry_ids"].numpy()
    return Scene(depth.astype(np.float32), [geometry == i for i in ids], [T for _, T in parts])


def detection(model: ObjectModel, mask: np.ndarray, obj_id: int | None = None) -> Detection:
    """A detection of ``mask`` (its box) as ``model``'s part (or ``obj_id``'s)."""
    ys, xs = np.nonzero(mask)
    box = np.array([xs.min(), ys.min(), xs.max() + 1, ys.max() + 1], dtype=float)
    return Detection(0, model.obj_id if obj_id is None else obj_id, 0.9, box, mask)


def blob(mask: np.ndarray, grow_px: int = 2) -> np.ndarray:
    """A detector-like mask: the part's silhouette filled (holes and all) and grown by ``grow_px``."""
    contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    filled = cv2.drawContours(np.zeros(mask.shape, np.uint8), contours, -1, 1, thickness=cv2.FILLED)
    return cv2.dilate(filled, np.ones((3, 3), np.uint8), iterations=grow_px).astype(bool)
