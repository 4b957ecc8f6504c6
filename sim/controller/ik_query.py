"""URScript ``get_inverse_kin`` semantics on top of the analytic UR IK: the solution nearest ``qnear`` whose TCP
error is within ``maxPositionError`` [m] and ``maxOrientationError`` [rad], or none.

The analytic solver is exact; when its nearest branch misses the tolerances (numerically, near a singularity)
or the pose is out of reach, a damped-least-squares search from ``qnear`` looks for a pose within the tolerances,
which is how a generous tolerance lets a slightly unreachable pose through, as on the real controller.
"""

from __future__ import annotations

import numpy as np

from sygrid.robots.kinematics import forward_kinematics, ik_nearest
from sygrid.transforms import pose_difference

DEFAULT_MAX_POSITION_ERROR_M = 1e-10  # URScript defaults (also ur_rtde's)
DEFAULT_MAX_ORIENTATION_ERROR_RAD = 1e-10
_DLS_ITERATIONS = 60
_DLS_DAMPING = 1e-4
_JACOBIAN_STEP_RAD = 1e-7
_TRACK_ITERATIONS = 6
_TRACK_TOLERANCE = 1e-12  # m and rad, per component
_TRACK_MAX_STEP_RAD = 0.2  # a bigger Newton step means the Jacobian is near singular: use the analytic solver
_TOLERANCE_FLOOR = 1e-9  # below this, float noise in FK decides; treat as met


def _rotation_error(R: np.ndarray) -> np.ndarray:
    """Rotation vector of R, accurate for small angles (atan2, not arccos of the trace)."""
    axis = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    s = float(np.linalg.norm(axis))
    angle = np.arctan2(s / 2.0, (np.trace(R) - 1.0) / 2.0)
    if s < 1e-15:
        return np.zeros(3)
    return axis / s * angle


def _within(T: np.ndarray, T_target: np.ndarray, max_pos: float, max_ori: float) -> bool:
    dp, dr = pose_difference(T, T_target)
    return dp <= max(max_pos, _TOLERANCE_FLOOR) and dr <= max(max_ori, _TOLERANCE_FLOOR)


def _twist_error(T: np.ndarray, T_target: np.ndarray) -> np.ndarray:
    return np.concatenate([T_target[:3, 3] - T[:3, 3], _rotation_error(T_target[:3, :3] @ T[:3, :3].T)])


def _pose_and_jacobian(q: np.ndarray, T_flange_tcp: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """``T_base_tcp(q)`` and the 6x6 geometric Jacobian (base frame), by forward differences in one batched FK."""
    Q = np.repeat(q[None, :], 7, axis=0)
    Q[1:] += _JACOBIAN_STEP_RAD * np.eye(6)
    Ts = forward_kinematics(Q, T_flange_tcp)
    T = Ts[0]
    J = np.empty((6, 6))
    J[:3] = (Ts[1:, :3, 3] - T[:3, 3]).T / _JACOBIAN_STEP_RAD
    dR = Ts[1:, :3, :3] @ T[:3, :3].T  # (6, 3, 3) small rotations
    J[3:] = (
        0.5
        * np.stack([dR[:, 2, 1] - dR[:, 1, 2], dR[:, 0, 2] - dR[:, 2, 0], dR[:, 1, 0] - dR[:, 0, 1]])
        / (_JACOBIAN_STEP_RAD)
    )
    return T, J


def _dls(T_target: np.ndarray, q0: np.ndarray, T_flange_tcp: np.ndarray | None) -> np.ndarray:
    """Damped least squares on the 6-D pose error; returns the best q found."""
    q = np.array(q0, dtype=float)
    for _ in range(_DLS_ITERATIONS):
        T, J = _pose_and_jacobian(q, T_flange_tcp)
        err = _twist_error(T, T_target)
        if np.linalg.norm(err) < 1e-13:
            break
        q = q + J.T @ np.linalg.solve(J @ J.T + _DLS_DAMPING * np.eye(6), err)
    return q


def track_ik(T_base_tcp: np.ndarray, q_prev: np.ndarray, T_flange_tcp: np.ndarray | None = None) -> np.ndarray | None:
    """IK for a pose a small step away from ``FK(q_prev)``: Newton from ``q_prev`` (stays on its branch, so it is the
    solution nearest ``q_prev``), about 10x cheaper than the full analytic solve; falls back to the analytic
    ``ik_nearest`` when Newton does not converge (near a singularity). For the 500 Hz Cartesian motions."""
    q = np.array(q_prev, dtype=float)
    T, J = _pose_and_jacobian(q, T_flange_tcp)  # kept for every iteration (chord method: the step is small)
    try:
        J_inv = np.linalg.inv(J)
    except np.linalg.LinAlgError:
        J_inv = None
    for _ in range(_TRACK_ITERATIONS if J_inv is not None else 0):
        err = _twist_error(T, T_base_tcp)
        if np.max(np.abs(err)) < _TRACK_TOLERANCE:
            return q
        step = J_inv @ err
        if np.max(np.abs(step)) > _TRACK_MAX_STEP_RAD:
            break
        q = q + step
        T = forward_kinematics(q, T_flange_tcp)
    return ik_nearest(T_base_tcp, q_prev, T_flange_tcp)


def solve_ik(
    T_base_tcp: np.ndarray,
    q_near: np.ndarray,
    T_flange_tcp: np.ndarray | None = None,
    max_position_error_m: float = DEFAULT_MAX_POSITION_ERROR_M,
    max_orientation_error_rad: float = DEFAULT_MAX_ORIENTATION_ERROR_RAD,
) -> np.ndarray | None:
    """Joint angles reaching ``T_base_tcp`` within the tolerances, nearest ``q_near``; None when there is none."""
    q = ik_nearest(T_base_tcp, q_near, T_flange_tcp)
    if q is not None and _within(
        forward_kinematics(q, T_flange_tcp), T_base_tcp, max_position_error_m, max_orientation_error_rad
    ):
        return q
    q = _dls(T_base_tcp, q_near if q is None else q, T_flange_tcp)
    if _within(forward_kinematics(q, T_flange_tcp), T_base_tcp, max_position_error_m, max_orientation_error_rad):
        return q
    return None
