"""Camera poses for rendering a scene (the intrinsics: ``sygrid.scene.intrinsics_from_spec``).

Camera frame: OpenCV convention, x right, y down, z forward (out of the lens). ``T_world_camera`` maps camera-frame
points to the world frame (origin at the centre of the bin's inner floor, z up).
"""

from __future__ import annotations

import math

import numpy as np

from sygrid.scene import CameraPoseSampling, CameraSpec


def look_at_T_world_camera(
    eye_world: np.ndarray, target_world: np.ndarray, up_world: np.ndarray = (0.0, 0.0, 1.0)
) -> np.ndarray:
    """4x4 ``T_world_camera`` of an OpenCV camera at ``eye_world`` looking at ``target_world``.

    The image's "up" (-y) leans towards ``up_world``; when the view is parallel to it, world +y is used instead
    (a camera straight above the bin, looking down, then has image x along world +x and image y along world -y).
    """
    eye, target = np.asarray(eye_world, dtype=float), np.asarray(target_world, dtype=float)
    z = target - eye
    norm = np.linalg.norm(z)
    if norm < 1e-12:
        raise ValueError(f"eye and target coincide at {eye.tolist()}: no viewing direction")
    z /= norm
    up = np.asarray(up_world, dtype=float)
    if np.linalg.norm(np.cross(z, up)) < 1e-6:
        up = np.array([0.0, 1.0, 0.0])
    x = np.cross(z, up)  # right = forward x up  (for z down and up=+y this gives x = +x world)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)  # down
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, y, z, eye
    return T


def sample_T_world_camera(sampling: CameraPoseSampling, rng: np.random.Generator) -> np.ndarray:
    """A random camera pose above the bin: a viewpoint drawn uniformly (by area) on the spherical cap of polar
    angle <= ``max_tilt_deg`` about world +z, at a distance drawn uniformly from ``distance_m``, looking at the
    bin centre plus a uniform jitter of up to ``look_at_jitter_m`` per axis in x and y.

    Returns:
        (4, 4) float64 ``T_world_camera`` (OpenCV camera frame).
    """
    d_min, d_max = sampling.distance_m
    distance = float(rng.uniform(d_min, d_max))
    cos_max = math.cos(math.radians(sampling.max_tilt_deg))
    cos_tilt = float(rng.uniform(cos_max, 1.0))
    azimuth = float(rng.uniform(0.0, 2.0 * math.pi))
    sin_tilt = math.sqrt(max(0.0, 1.0 - cos_tilt * cos_tilt))
    j = sampling.look_at_jitter_m
    target = np.array([rng.uniform(-j, j), rng.uniform(-j, j), 0.0])
    direction = np.array([sin_tilt * math.cos(azimuth), sin_tilt * math.sin(azimuth), cos_tilt])
    eye = target + distance * direction
    # A random roll about the viewing axis, so part orientations in the image are not tied to the bin's axes.
    T = look_at_T_world_camera(eye, target)
    roll = float(rng.uniform(-math.pi, math.pi))
    c, s = math.cos(roll), math.sin(roll)
    R_roll = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    T[:3, :3] = T[:3, :3] @ R_roll
    return T


def camera_T_world_camera(camera: CameraSpec, rng: np.random.Generator) -> np.ndarray:
    """The scene's fixed ``T_world_camera`` when it gives one, else a sampled pose."""
    if camera.T_world_camera is not None:
        return np.asarray(camera.T_world_camera, dtype=float).reshape(4, 4)
    return sample_T_world_camera(camera.pose_sampling, rng)
