"""Rigid transforms as 4x4 float64 arrays, named ``T_a_b`` (pose of frame b in frame a: ``p_a = T_a_b @ p_b``).

Rotation maths comes from scipy; these are the few helpers every package needs on top of it.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def make_T(R: np.ndarray | None = None, t: np.ndarray | None = None) -> np.ndarray:
    """Builds a 4x4 transform from a 3x3 rotation and a 3-vector translation (identity where omitted)."""
    T = np.eye(4)
    if R is not None:
        T[:3, :3] = R
    if t is not None:
        T[:3, 3] = t
    return T


def invert(T_a_b: np.ndarray) -> np.ndarray:
    """Returns ``T_b_a`` for a rigid ``T_a_b``, without a general matrix inverse."""
    R = T_a_b[:3, :3]
    T_b_a = np.eye(4)
    T_b_a[:3, :3] = R.T
    T_b_a[:3, 3] = -R.T @ T_a_b[:3, 3]
    return T_b_a


def transform_points(T_a_b: np.ndarray, p_b: np.ndarray) -> np.ndarray:
    """Maps (n, 3) points from frame b to frame a."""
    return p_b @ T_a_b[:3, :3].T + T_a_b[:3, 3]


def rotation_about(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    """3x3 rotation of ``angle_rad`` about a (not necessarily unit) axis."""
    axis = np.asarray(axis, dtype=float)
    return Rotation.from_rotvec(axis / np.linalg.norm(axis) * angle_rad).as_matrix()


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A uniformly distributed 3x3 rotation drawn from ``rng``."""
    return Rotation.random(random_state=rng).as_matrix()


def rotation_angle_rad(R_a: np.ndarray, R_b: np.ndarray) -> float:
    """Angle of the relative rotation between two 3x3 rotations, radians in [0, pi]: from both the trace and the
    antisymmetric part (atan2), so that it stays exact for small angles, where the trace's arccos loses half its
    digits (a controller's convergence test compares angles of 1e-9 rad)."""
    R = R_a.T @ R_b
    s = np.linalg.norm([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    return float(np.arctan2(s / 2.0, (np.trace(R) - 1.0) / 2.0))


def rotation_angle_deg(R_a: np.ndarray, R_b: np.ndarray) -> float:
    """Angle of the relative rotation between two 3x3 rotations, in degrees."""
    return float(np.degrees(rotation_angle_rad(R_a, R_b)))


def pose_difference(T_a: np.ndarray, T_b: np.ndarray) -> tuple[float, float]:
    """(distance between the origins [m], angle of the relative rotation [rad]) of two 4x4 poses."""
    return float(np.linalg.norm(T_a[:3, 3] - T_b[:3, 3])), rotation_angle_rad(T_a[:3, :3], T_b[:3, :3])


def is_rigid(T: np.ndarray, atol: float = 1e-6) -> bool:
    """True when T is a finite 4x4 rigid transform (orthonormal rotation with det +1, last row 0 0 0 1)."""
    T = np.asarray(T)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        return False
    R = T[:3, :3]
    return (
        np.allclose(R.T @ R, np.eye(3), atol=atol)
        and abs(np.linalg.det(R) - 1.0) < atol
        and np.allclose(T[3], [0, 0, 0, 1], atol=atol)
    )
