"""Parts at rest on a known support: a fit put back on the surface it lies on, in the nearest stable pose.

A part lying on the bin's floor has three free parameters, not six: where it lies on the floor (two) and its turn
about the floor's normal (one), in one of the few stable poses its shape allows. The floor's plane comes from the
cell's calibration and thousands of depth pixels (``perception.depth_tare``); the part's own cloud is a few hundred
pixels whose stereo noise is of the order of a small part's thickness (a 2.5 mm washer under about 2 mm of noise at
the bin). So a free 6-DoF fit of a small part tilts and floats with that noise, while the same part put back on the
floor in its nearest stable pose takes its height and tilt from the floor and only its position and heading from
its own pixels, which the mask's outline fixes well.

Where the depth shows too little of a part to fit it at all (a washer's top quantised to the floor's depth by the
stereo camera's disparity step, so that the mask's clean-up takes it for floor), ``mask_hypotheses`` places it from
its mask alone: each likely stable pose standing on the plane under the mask's centre, headed along the mask's
principal axis.

``rest_on_support`` levels a fit: the stable pose (``stable_poses``: trimesh's quasi-static analysis of the convex
hull) whose up direction is nearest the fit's, turned by the smallest rotation that makes it level, lowered or
raised onto the plane. ``planar_search`` then slides and turns it in the plane while the verification improves.
The pose strategies (``perception.pose_strategies``) offer the result beside the free fit and keep it where the
verification agrees (a part leaning on a neighbour or lying on another part is no stable pose on the floor, and
keeps its free fit).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import trimesh

from perception.observation import Observation
from perception.verify import PoseVerifier, Verification
from sygrid.objects.model import ObjectModel
from sygrid.transforms import rotation_about

SAME_UP_DEG = 1.0  # stable poses whose up directions and heights agree this closely are one


@dataclass(frozen=True)
class StablePoses:
    """A model's stable resting poses on a horizontal plane: ``up`` (k, 3) the object-frame direction that points
    away from the plane (unit), ``height_m`` (k,) the object origin's height above the plane, ``probability`` (k,)
    trimesh's estimate of how often a dropped part comes to rest so (most likely first)."""

    up: np.ndarray
    height_m: np.ndarray
    probability: np.ndarray


@lru_cache(maxsize=64)
def stable_poses(model: ObjectModel) -> StablePoses:
    """The stable poses of ``model`` (cached per model). Every pose trimesh finds is kept, however unlikely: a
    washer on its rim or a pipe on its side is a rare outcome of a drop but a pose a part can be found in."""
    transforms, probability = trimesh.poses.compute_stable_poses(model.mesh, n_samples=1, threshold=0.0)
    up = np.array([T[:3, :3].T @ (0.0, 0.0, 1.0) for T in transforms])  # T maps the object into the plane's frame
    height = np.array([T[2, 3] for T in transforms])
    keep: list[int] = []
    for i in np.argsort(-probability, kind="stable"):
        same = [
            k
            for k in keep
            if up[k] @ up[i] > np.cos(np.radians(SAME_UP_DEG)) and abs(height[k] - height[i]) < 1e-4 * model.diameter_m
        ]
        if not same:
            keep.append(int(i))
    return StablePoses(up[keep], height[keep], probability[keep])


def _perpendicular(v: np.ndarray) -> np.ndarray:
    """A unit vector perpendicular to the unit vector ``v``."""
    p = np.cross(v, (1.0, 0.0, 0.0) if abs(v[0]) < 0.9 else (0.0, 1.0, 0.0))
    return p / np.linalg.norm(p)


def _rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation taking unit vector ``a`` onto unit vector ``b``."""
    axis = np.cross(a, b)
    s, c = float(np.linalg.norm(axis)), float(np.clip(a @ b, -1.0, 1.0))
    if s < 1e-12:
        return np.eye(3) if c > 0 else rotation_about(_perpendicular(a), np.pi)
    return rotation_about(axis, np.arctan2(s, c))


def rest_on_support(T_camera_object: np.ndarray, model: ObjectModel, plane: np.ndarray) -> tuple[np.ndarray, float]:
    """``(T, tilt_deg)``: the pose in the stable pose nearest the fit's, levelled by the smallest rotation about
    the object's origin and moved along the plane's normal onto the plane; ``tilt_deg`` is that rotation's angle.

    ``plane``: ``(a, b, c, d)`` in the camera frame, unit normal pointing away from the support (towards the
    camera), a point p lying ``n . p + d`` above it.
    """
    n, d = np.asarray(plane[:3], dtype=float), float(plane[3])
    R, t = T_camera_object[:3, :3], T_camera_object[:3, 3]
    poses = stable_poses(model)
    up_fit = R.T @ n  # the plane's normal in the object frame
    k = int(np.argmax(poses.up @ up_fit))
    turn = _rotation_between(R @ poses.up[k], n)
    out = np.eye(4)
    out[:3, :3] = turn @ R
    out[:3, 3] = t - (n @ t + d - poses.height_m[k]) * n
    tilt = float(np.degrees(np.arccos(np.clip(poses.up[k] @ up_fit, -1.0, 1.0))))
    return out, tilt


def mask_hypotheses(
    model: ObjectModel, obs: Observation, plane: np.ndarray, max_poses: int = 4, min_probability: float = 0.02
) -> list[np.ndarray]:
    """Poses of the part from its mask alone, at rest on ``plane``: for each of the ``max_poses`` most likely stable
    poses (at least ``min_probability``), the object's origin on the ray through the mask's centroid at that pose's
    height, turned about the normal so that the model's longest horizontal axis lies along the mask's principal
    axis on the plane (both ways round). Empty when the mask is empty or the rays miss the plane."""
    n, d = np.asarray(plane[:3], dtype=float), float(plane[3])
    ys, xs = np.nonzero(obs.mask)
    if len(xs) == 0:
        return []
    K = obs.intrinsics.K
    rays = np.column_stack([(xs + obs.x0 - K[0, 2]) / K[0, 0], (ys + obs.y0 - K[1, 2]) / K[1, 1], np.ones(len(xs))])
    denominator = rays @ n
    if (np.abs(denominator) < 1e-9).any():
        return []
    poses = stable_poses(model)
    hull = np.asarray(model.mesh.convex_hull.vertices)
    out = []
    for k in np.flatnonzero(poses.probability >= min_probability)[:max_poses]:
        height = float(poses.height_m[k])
        on_plane = rays * ((height - d) / denominator)[:, None]  # where each ray meets the plane raised by height
        if (on_plane[:, 2] <= 0).any():
            return []
        R0 = _rotation_between(poses.up[k], n)  # object -> camera, the stable pose's up along the normal
        centre = on_plane.mean(axis=0)
        mask_axis = _horizontal_axis(on_plane - centre, n)
        model_axis = _horizontal_axis(hull @ R0.T, n)
        for sign in (1.0, -1.0):
            angle = np.arctan2(np.cross(model_axis, sign * mask_axis) @ n, model_axis @ (sign * mask_axis))
            T = np.eye(4)
            T[:3, :3] = rotation_about(n, angle) @ R0
            T[:3, 3] = centre
            out.append(T)
    return out


def _horizontal_axis(points: np.ndarray, n: np.ndarray) -> np.ndarray:
    """The principal direction of ``points`` projected onto the plane with normal ``n`` (unit, in the plane); some
    in-plane direction where the points give none (one point, e.g. a one-pixel mask, or no spread in the plane)."""
    flat = points - np.outer(points @ n, n)
    spread = flat - flat.mean(axis=0)
    if len(points) >= 2 and np.isfinite(spread).all():
        _, vectors = np.linalg.eigh(spread.T @ spread)
        axis = vectors[:, -1] - (vectors[:, -1] @ n) * n
        norm = float(np.linalg.norm(axis))
        if norm > 1e-9:
            return axis / norm
    return _perpendicular(n)


def planar_search(
    T_camera_object: np.ndarray,
    model: ObjectModel,
    obs: Observation,
    plane: np.ndarray,
    verifier: PoseVerifier,
    steps: tuple[tuple[float, float], ...],
    start: Verification | None = None,
) -> tuple[np.ndarray, Verification]:
    """The pose slid along the plane and turned about its normal (through the object's origin) while the
    verification improves: steps of (fraction of the diameter, degrees) from ``steps``, coarse to fine. A compass
    search: the six moves (two slides each way, a turn each way) are tried in turn, the last one that paid first,
    and the first that improves the confidence is taken; a step size ends when none does. It evaluates fewer
    poses than taking the best of all six each time (a walk in one direction costs one evaluation a step), and
    every search ends where no move of the finest step improves. The height and tilt stay as given. ``start``: the
    given pose's verification where the caller has it already."""
    n = np.asarray(plane[:3], dtype=float)
    e1 = _perpendicular(n)
    e2 = np.cross(n, e1)
    T = np.array(T_camera_object, dtype=float)
    v = start if start is not None else verifier.verify(T, model, obs)
    for fraction, degrees in steps:
        moves = _planar_moves(n, (e1, e2), fraction * float(model.diameter_m), np.radians(degrees))
        first, undo = 0, None
        improved = True
        while improved:
            improved = False
            for k in range(len(moves)):
                i = (first + k) % len(moves)
                if i == undo:  # back to where the last move came from: known to be worse
                    continue
                T_try = _moved(T, moves[i])
                v_try = verifier.verify(T_try, model, obs)
                if v_try.confidence > v.confidence + 1e-3:
                    T, v, first, undo, improved = T_try, v_try, i, i ^ 1, True
                    break
    return T, v


def _planar_moves(
    n: np.ndarray, axes: tuple[np.ndarray, np.ndarray], shift_m: float, turn_rad: float
) -> list[tuple[np.ndarray, np.ndarray]]:
    """The six moves of the planar search as (shift [m], rotation) pairs: slides by ``shift_m`` along each in-plane
    axis both ways, turns by ``turn_rad`` about the normal ``n`` both ways (``_moved`` applies one); move ``i ^ 1``
    undoes move ``i``."""
    slides = [(sign * shift_m * e, np.eye(3)) for e in axes for sign in (1.0, -1.0)]
    return slides + [(np.zeros(3), rotation_about(n, sign * turn_rad)) for sign in (1.0, -1.0)]


def _moved(T: np.ndarray, move: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """``T`` shifted by the move's shift and turned by its rotation about the object's origin."""
    shift, R = move
    out = T.copy()
    out[:3, :3] = R @ T[:3, :3]
    out[:3, 3] += shift
    return out
