"""UR5e forward and inverse kinematics in the controller's DH base frame, and UR pose <-> 4x4 conversions.

Pure numpy. Shapes: a joint vector ``q`` is (6,) in radians, or (n, 6) for the batched forward kinematics; poses
are 4x4 ``T_base_tcp`` (or (n, 4, 4)). ``T_flange_tcp`` is the tool offset (the ``setTcp`` of the controller);
``None`` means the TCP is the flange.

The inverse kinematics is the standard closed form for arms with the UR geometry (three parallel middle axes and a
spherical-ish wrist offset; Hawkins, "Analytic inverse kinematics for the Universal Robots UR-5/UR-10 arms", 2013):
two shoulder solutions x two wrist solutions x two elbow solutions, eight at most. At the wrist singularity
(``sin(q5) = 0``, joints 4 and 6 aligned) only the sum of ``q4`` and ``q6`` is determined: the solver fixes ``q6``
(to ``q6_singular``) and returns the solutions that remain, never NaN. Poses out of reach give no solutions.

Rotation vectors (``[x, y, z, rx, ry, rz]``, the controller's pose format) appear only here, at the ur_rtde
boundary. A rotation of exactly pi has two rotation vectors, ``r`` and ``-r``; ``T_to_pose`` returns the one whose
first non-zero component is positive, or the one nearest ``rotvec_near`` when given (for continuity along a path).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation

from sygrid.robots import ur5e
from sygrid.transforms import invert

_TWO_PI = 2.0 * math.pi
# |sin(q5)| below this is the wrist singularity (q6 is then free).
_WRIST_SINGULAR_EPS = 1e-10
# Arguments of asin/acos may overshoot +-1 by rounding at the workspace boundary; beyond this the pose is unreachable.
_BOUNDARY_EPS = 1e-9
# A candidate whose forward kinematics misses the target by more than this (m, or rotation-matrix entries) is dropped.
_SOLUTION_CHECK_TOL = 1e-7
# Solutions closer than this (rad, every joint) are one solution.
_DUPLICATE_TOL_RAD = 1e-9
# A rotation angle within this of pi uses the canonical sign of the rotation vector.
_ROTVEC_PI_TOL_RAD = 1e-9


# ---------------------------------------------------------------------------------------------- forward


def dh_transforms(q: np.ndarray) -> np.ndarray:
    """(..., 6) joint angles -> (..., 6, 4, 4) DH link transforms ``A_i = T_{i-1}_i``.

    ``A_i = Rz(q_i) Tz(d_i) Tx(a_i) Rx(alpha_i)``.
    """
    q = np.asarray(q, dtype=float)
    c, s = np.cos(q), np.sin(q)
    ca, sa = np.cos(ur5e.DH_ALPHA_RAD), np.sin(ur5e.DH_ALPHA_RAD)
    A = np.zeros((*q.shape, 4, 4))
    A[..., 0, 0], A[..., 0, 1], A[..., 0, 2], A[..., 0, 3] = c, -s * ca, s * sa, ur5e.DH_A_M * c
    A[..., 1, 0], A[..., 1, 1], A[..., 1, 2], A[..., 1, 3] = s, c * ca, -c * sa, ur5e.DH_A_M * s
    A[..., 2, 1], A[..., 2, 2], A[..., 2, 3] = sa, ca, ur5e.DH_D_M
    A[..., 3, 3] = 1.0
    return A


def link_transforms(q: np.ndarray) -> np.ndarray:
    """(..., 6) joint angles -> (..., 7, 4, 4) ``T_base_i`` for DH frames 0 (base, identity) to 6 (flange)."""
    A = dh_transforms(q)
    T = np.empty((*A.shape[:-3], 7, 4, 4))
    T[..., 0, :, :] = np.eye(4)
    for i in range(6):
        T[..., i + 1, :, :] = T[..., i, :, :] @ A[..., i, :, :]
    return T


def forward_kinematics(q: np.ndarray, T_flange_tcp: np.ndarray | None = None) -> np.ndarray:
    """``T_base_tcp`` for joint angles ``q``: (6,) -> (4, 4), or batched (n, 6) -> (n, 4, 4)."""
    q = _check_q(q, allow_batch=True)
    A = dh_transforms(q)
    T = A[..., 0, :, :]
    for i in range(1, 6):
        T = T @ A[..., i, :, :]
    if T_flange_tcp is not None:
        T = T @ _check_T(T_flange_tcp, "T_flange_tcp")
    return T


# ---------------------------------------------------------------------------------------------- inverse


def inverse_kinematics(
    T_base_tcp: np.ndarray,
    T_flange_tcp: np.ndarray | None = None,
    q6_singular: float = 0.0,
    limits: np.ndarray | None = None,
) -> np.ndarray:
    """Every joint solution that reaches ``T_base_tcp``: a (k, 6) array, k = 0..8.

    Each joint angle is the 2-pi equivalent nearest 0 that lies within ``limits`` ((6, 2) rad; default the UR5e
    limits); solutions with a joint that has no equivalent inside its limits are dropped. At the wrist
    singularity ``q6`` is set to ``q6_singular`` (wrapped) and fewer solutions come back.
    """
    T = _check_T(T_base_tcp, "T_base_tcp")
    if T_flange_tcp is not None:
        T = T @ invert(_check_T(T_flange_tcp, "T_flange_tcp"))
    limits = _check_limits(limits)
    candidates = _closed_form_candidates(T, float(q6_singular))
    if not len(candidates):
        return np.zeros((0, 6))
    # Keep the exact ones (rounding at the workspace boundary can leave a slightly wrong branch).
    T_fk = forward_kinematics(candidates)
    err = np.abs(T_fk[:, :3, :] - T[None, :3, :]).max(axis=(1, 2))
    candidates = candidates[err < _SOLUTION_CHECK_TOL]
    solutions = [w for w in (_wrap_into_limits(c, np.zeros(6), limits) for c in candidates) if w is not None]
    unique: list[np.ndarray] = []
    for s in solutions:
        if not any(np.abs(_angle_diff(s, u)).max() < _DUPLICATE_TOL_RAD for u in unique):
            unique.append(s)
    return np.array(unique).reshape(-1, 6)


def ik_solutions_near(
    T_base_tcp: np.ndarray,
    q_near: np.ndarray,
    T_flange_tcp: np.ndarray | None = None,
    limits: np.ndarray | None = None,
) -> np.ndarray:
    """Every IK solution of ``T_base_tcp`` (k, 6), k = 0..8, each joint the 2-pi equivalent nearest ``q_near`` within
    ``limits``, nearest ``q_near`` first (Euclidean in joint space; ties in ``inverse_kinematics``'s order). At the
    wrist singularity ``q6`` stays at ``q_near[5]``. For a caller whose first choice of arm configuration a check
    refuses (a wrist link against a bin wall) and who may take another branch."""
    q_near = _check_q(q_near)
    limits = _check_limits(limits)
    solutions = inverse_kinematics(T_base_tcp, T_flange_tcp, q6_singular=float(q_near[5]), limits=limits)
    wrapped = [w for w in (_wrap_into_limits(s, q_near, limits) for s in solutions) if w is not None]
    if not wrapped:
        return np.zeros((0, 6))
    wrapped = np.array(wrapped)
    return wrapped[np.argsort(np.linalg.norm(wrapped - q_near, axis=1), kind="stable")]


def ik_nearest(
    T_base_tcp: np.ndarray,
    q_near: np.ndarray,
    T_flange_tcp: np.ndarray | None = None,
    limits: np.ndarray | None = None,
) -> np.ndarray | None:
    """The IK solution nearest ``q_near`` (``ik_solutions_near``'s first), or None when the pose is out of reach."""
    solutions = ik_solutions_near(T_base_tcp, q_near, T_flange_tcp, limits)
    return solutions[0] if len(solutions) else None


def _closed_form_candidates(T_base_flange: np.ndarray, q6_singular: float) -> np.ndarray:
    """Up to 8 raw candidate solutions (unchecked, angles in (-pi, pi])."""
    d4, d6 = ur5e.DH_D_M[3], ur5e.DH_D_M[5]
    a2, a3 = ur5e.DH_A_M[1], ur5e.DH_A_M[2]
    R, p = T_base_flange[:3, :3], T_base_flange[:3, 3]
    p05 = p - d6 * R[:, 2]  # wrist centre (origin of frame 5)

    # q1: the wrist centre lies d4 off the plane of the arm, along z1 = (sin q1, -cos q1, 0).
    r = math.hypot(p05[0], p05[1])
    if r < abs(d4) * (1.0 - _BOUNDARY_EPS):
        return np.zeros((0, 6))  # inside the cylinder around the base axis that the wrist cannot enter
    psi = math.atan2(p05[1], p05[0])
    phi = math.asin(max(-1.0, min(1.0, d4 / r)))
    out = []
    for q1 in (psi + phi, psi + math.pi - phi):
        z1 = np.array([math.sin(q1), -math.cos(q1), 0.0])
        # z1 seen in the flange frame is (cos q6 sin q5, -sin q6 sin q5, cos q5): q5 from its angle to the flange
        # axis (atan2, exact near the singularity, where acos is not), q6 from its direction in the flange xy plane.
        w = R.T @ z1
        s5_abs = math.hypot(w[0], w[1])
        for sign5 in (1.0, -1.0):
            q5 = sign5 * math.atan2(s5_abs, w[2])
            singular = s5_abs < _WRIST_SINGULAR_EPS
            q6 = q6_singular if singular else math.atan2(-w[1] * sign5, w[0] * sign5)
            # The planar 3R chain (joints 2, 3, 4) from frame 1 to frame 4.
            T14 = invert(_dh(0, q1)) @ T_base_flange @ invert(_dh(4, q5) @ _dh(5, q6))
            px, py = T14[0, 3], T14[1, 3]
            c3 = (px * px + py * py - a2 * a2 - a3 * a3) / (2.0 * a2 * a3)
            if abs(c3) > 1.0 + _BOUNDARY_EPS:
                continue
            c3 = max(-1.0, min(1.0, c3))
            for sign3 in (1.0, -1.0):
                q3 = sign3 * math.acos(c3)
                q2 = math.atan2(py, px) - math.atan2(a3 * math.sin(q3), a2 + a3 * math.cos(q3))
                q234 = math.atan2(T14[1, 0], T14[0, 0])
                q4 = q234 - q2 - q3
                out.append([q1, q2, q3, q4, q5, q6])
    return _wrap_pi(np.array(out).reshape(-1, 6))


def _dh(i: int, theta: float) -> np.ndarray:
    q = np.zeros(6)
    q[i] = theta
    return dh_transforms(q)[i]


# ---------------------------------------------------------------------------------------------- joint wrapping


def _wrap_pi(q: np.ndarray) -> np.ndarray:
    """Angles wrapped into (-pi, pi]."""
    w = np.mod(np.asarray(q, dtype=float) + math.pi, _TWO_PI) - math.pi
    return np.where(w <= -math.pi, w + _TWO_PI, w)


def _angle_diff(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return _wrap_pi(np.asarray(a) - np.asarray(b))


def _wrap_into_limits(q: np.ndarray, q_ref: np.ndarray, limits: np.ndarray) -> np.ndarray | None:
    """Each joint's 2-pi equivalent nearest ``q_ref`` inside ``limits``; None if a joint has none."""
    k = np.arange(-3, 4)[:, None] * _TWO_PI  # (7, 1)
    options = np.asarray(q)[None, :] + k  # (7, 6)
    inside = (options >= limits[:, 0] - 1e-12) & (options <= limits[:, 1] + 1e-12)
    if not inside.any(axis=0).all():
        return None
    dist = np.where(inside, np.abs(options - q_ref[None, :]), np.inf)
    return options[dist.argmin(axis=0), np.arange(6)]


# ---------------------------------------------------------------------------------------------- UR poses


def pose_to_T(pose: np.ndarray) -> np.ndarray:
    """UR pose ``[x, y, z, rx, ry, rz]`` (m, rotation vector in rad) -> 4x4 transform."""
    pose = np.asarray(pose, dtype=float)
    if pose.shape != (6,) or not np.all(np.isfinite(pose)):
        raise ValueError(f"a UR pose must be 6 finite numbers [x, y, z, rx, ry, rz], got {pose.tolist()}")
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(pose[3:]).as_matrix()
    T[:3, 3] = pose[:3]
    return T


def T_to_pose(T: np.ndarray, rotvec_near: np.ndarray | None = None) -> np.ndarray:
    """4x4 transform -> UR pose ``[x, y, z, rx, ry, rz]``.

    Without ``rotvec_near`` the rotation vector has angle in [0, pi], and at exactly pi (within 1e-9 rad) its
    first non-zero component is positive. With ``rotvec_near`` it is the equivalent rotation vector
    (``axis * (angle + 2 pi k)``) nearest that one, for poses that must vary continuously.
    """
    T = _check_T(T, "T")
    rotvec = Rotation.from_matrix(T[:3, :3]).as_rotvec()
    angle = float(np.linalg.norm(rotvec))
    if angle > math.pi - _ROTVEC_PI_TOL_RAD:
        significant = np.flatnonzero(np.abs(rotvec) > 1e-9 * max(angle, 1.0))
        if len(significant) and rotvec[significant[0]] < 0:
            rotvec = -rotvec
    if rotvec_near is not None and angle > 0.0:
        rotvec_near = np.asarray(rotvec_near, dtype=float).reshape(3)
        axis = rotvec / angle
        options = [axis * (angle + _TWO_PI * k) for k in (-1, 0, 1)]
        rotvec = min(options, key=lambda r: float(np.linalg.norm(r - rotvec_near)))
    return np.concatenate([T[:3, 3], rotvec])


# ---------------------------------------------------------------------------------------------- checks


def _check_q(q: np.ndarray, allow_batch: bool = False) -> np.ndarray:
    q = np.asarray(q, dtype=float)
    ok_shape = q.shape == (6,) or (allow_batch and q.ndim == 2 and q.shape[1] == 6)
    if not ok_shape:
        expected = "(6,) or (n, 6)" if allow_batch else "(6,)"
        raise ValueError(f"joint angles must have shape {expected} (rad, {list(ur5e.JOINT_NAMES)}), got {q.shape}")
    if not np.all(np.isfinite(q)):
        raise ValueError(f"joint angles must be finite, got {q.tolist()}")
    return q


def _check_T(T: np.ndarray, name: str) -> np.ndarray:
    T = np.asarray(T, dtype=float)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"{name} must be a finite 4x4 transform, got shape {T.shape}")
    return T


def _check_limits(limits: np.ndarray | None) -> np.ndarray:
    if limits is None:
        return np.asarray(ur5e.JOINT_LIMITS_RAD)
    limits = np.asarray(limits, dtype=float)
    if limits.shape != (6, 2) or np.any(limits[:, 0] > limits[:, 1]):
        raise ValueError(f"joint limits must be (6, 2) [lower, upper] rad with lower <= upper, got {limits.tolist()}")
    return limits
