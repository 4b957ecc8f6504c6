"""Trajectory generators the emulated controller runs once per 2 ms tick.

- ``PathMotion``: a geometric path ``q(u)``, ``u`` in [0, 1], driven by a trapezoidal profile on its length.
  ``JointPath`` is movej's straight line in joint space (synchronised joints: the leading joint follows the
  trapezoid, the others scale with it); ``CartesianPath`` is movel's straight TCP line with slerped rotation,
  solved each tick by IK nearest to the previous target (``track_ik``: Newton from it, analytic fallback).
- Stopping a path motion keeps it on its path and decelerates the path speed (so stopl after movel stays on the
  line); other motions stop with ``DecelerationMotion`` (all joints reach zero speed together).
- ``JointSpeedMotion`` (speedj), ``TcpSpeedMotion`` (speedl) and ``ServoMotion`` (servoj) follow a target that the
  program updates every tick.

Every ``step`` returns the new target joint positions, or ``None`` when the motion cannot continue (IK failed).
"""

from __future__ import annotations

import math
from typing import Protocol

import numpy as np
from scipy.spatial.transform import Rotation

from sim.controller.ik_query import track_ik
from sygrid.robots import ur5e
from sygrid.robots.kinematics import forward_kinematics

MAX_JOINT_SPEED_RAD_S = ur5e.MAX_JOINT_SPEED_RAD_S
IK_JUMP_LIMIT_RAD = 0.5  # a per-tick joint change above this means the nearest IK branch flipped (singularity)


class Trapezoid:
    """Scalar trapezoidal (or triangular) profile from 0 to ``length`` with speed ``v`` and acceleration ``a``."""

    def __init__(self, length: float, v: float, a: float) -> None:
        if v <= 0 or a <= 0:
            raise ValueError(f"speed and acceleration must be positive, got v={v}, a={a}")
        self.length, self.a = length, a
        if length * a >= v * v:  # reaches cruise speed
            self.v_peak, self.t_acc = v, v / a
            self.duration = length / v + v / a
        else:
            self.t_acc = math.sqrt(length / a)
            self.v_peak, self.duration = a * self.t_acc, 2.0 * self.t_acc

    def at(self, t: float) -> tuple[float, float]:
        """``(s, ds/dt)`` at time ``t``."""
        if t <= 0.0:
            return 0.0, 0.0
        if t >= self.duration:
            return self.length, 0.0
        if t < self.t_acc:
            return 0.5 * self.a * t * t, self.a * t
        t_dec = self.duration - self.t_acc
        if t <= t_dec:
            return 0.5 * self.a * self.t_acc**2 + self.v_peak * (t - self.t_acc), self.v_peak
        rest = self.duration - t
        return self.length - 0.5 * self.a * rest * rest, self.a * rest


class Path(Protocol):
    length: float

    def point(self, u: float, q_prev: np.ndarray) -> np.ndarray | None: ...


class JointPath:
    """Straight line in joint space; length is the leading joint's travel in [rad]."""

    def __init__(self, q_start: np.ndarray, q_end: np.ndarray) -> None:
        self.q_start, self.delta = np.array(q_start, dtype=float), np.asarray(q_end, dtype=float) - q_start
        self.length = float(np.max(np.abs(self.delta)))

    def point(self, u: float, q_prev: np.ndarray) -> np.ndarray | None:
        return self.q_start + u * self.delta


class CartesianPath:
    """Straight TCP line with slerped orientation; length is max(translation [m], rotation [rad]), as movel
    treats a pure rotation's speed in rad/s."""

    def __init__(self, T_base_tcp_start: np.ndarray, T_base_tcp_end: np.ndarray, T_flange_tcp: np.ndarray) -> None:
        self.p0, self.p1 = T_base_tcp_start[:3, 3].copy(), T_base_tcp_end[:3, 3].copy()
        self.R0 = T_base_tcp_start[:3, :3].copy()
        # slerp as R0 @ exp(u * w): w is the rotation from start to end in the start TCP frame
        w = Rotation.from_matrix(self.R0.T @ T_base_tcp_end[:3, :3]).as_rotvec()
        self._angle = float(np.linalg.norm(w))
        self._axis = w / self._angle if self._angle > 0 else np.zeros(3)
        self.length = float(max(np.linalg.norm(self.p1 - self.p0), self._angle))
        self.T_flange_tcp = T_flange_tcp

    def pose(self, u: float) -> np.ndarray:
        u = min(max(u, 0.0), 1.0)
        T = np.eye(4)
        T[:3, :3] = self.R0 @ _axis_angle_matrix(self._axis, u * self._angle)
        T[:3, 3] = self.p0 + u * (self.p1 - self.p0)
        return T

    def point(self, u: float, q_prev: np.ndarray) -> np.ndarray | None:
        q = track_ik(self.pose(u), q_prev, self.T_flange_tcp)
        if q is None or np.max(np.abs(q - q_prev)) > IK_JUMP_LIMIT_RAD:
            return None
        return q


def _axis_angle_matrix(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rodrigues: the 3x3 rotation of ``angle`` about the unit ``axis``."""
    K = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    return np.eye(3) + math.sin(angle) * K + (1.0 - math.cos(angle)) * (K @ K)


class PathMotion:
    """Follows a ``Path`` with a trapezoid on its length; ``begin_stop`` decelerates along the same path."""

    def __init__(self, path: Path, v: float, a: float, q_start: np.ndarray) -> None:
        self.path = path
        self.q = np.array(q_start, dtype=float)
        self.profile = Trapezoid(path.length, v, a) if path.length > 0 else None
        self.t = 0.0
        self.s, self.sd = 0.0, 0.0
        self._stop: tuple[float, float, float] | None = None  # (s0, sd0, decel) once stopping
        self._stop_t = 0.0
        self.finished = self.profile is None

    @property
    def duration_s(self) -> float:
        return 0.0 if self.profile is None else self.profile.duration

    def step(self, dt_s: float) -> np.ndarray | None:
        if self.finished:
            return self.q
        if self._stop is None:
            assert self.profile is not None
            self.t += dt_s
            self.s, self.sd = self.profile.at(self.t)
            self.finished = self.t >= self.profile.duration
        else:
            s0, sd0, decel = self._stop
            t_end = sd0 / decel
            self._stop_t = min(self._stop_t + dt_s, t_end)
            self.s = min(s0 + sd0 * self._stop_t - 0.5 * decel * self._stop_t**2, self.path.length)
            self.sd = max(sd0 - decel * self._stop_t, 0.0)
            self.finished = self._stop_t >= t_end or self.s >= self.path.length
        q = self.path.point(self.s / self.path.length, self.q)
        if q is None:
            return None
        self.q = q
        return q

    def begin_stop(self, decel_path: float) -> None:
        """Decelerates at ``decel_path`` (path units / s^2) from the current path speed, staying on the path."""
        if self.finished or self._stop is not None:
            return
        self._stop = (self.s, self.sd, max(decel_path, 1e-9))
        self._stop_t = 0.0
        self.finished = self.sd <= 0.0


class DecelerationMotion:
    """From ``q0`` at ``qd0``, every joint slows linearly to rest in ``duration_s`` (a synchronised stop)."""

    def __init__(self, q0: np.ndarray, qd0: np.ndarray, duration_s: float) -> None:
        self.q0, self.qd0, self.duration_s = np.array(q0, dtype=float), np.array(qd0, dtype=float), duration_s
        self.t = 0.0
        self.finished = duration_s <= 0.0
        self.q = self.q0.copy()

    def step(self, dt_s: float) -> np.ndarray | None:
        if not self.finished:
            self.t = min(self.t + dt_s, self.duration_s)
            self.q = self.q0 + self.qd0 * (self.t - self.t * self.t / (2.0 * self.duration_s))
            self.finished = self.t >= self.duration_s
        return self.q


def _toward(current: np.ndarray, target: np.ndarray, max_change: float) -> np.ndarray:
    """Moves ``current`` toward ``target`` by at most ``max_change`` in the max-norm, keeping the direction."""
    delta = target - current
    largest = float(np.max(np.abs(delta))) if delta.size else 0.0
    return target.copy() if largest <= max_change else current + delta * (max_change / largest)


class JointSpeedMotion:
    """speedj: joint velocities ramp toward the target at the leading joint's acceleration."""

    finished = False

    def __init__(self, q0: np.ndarray, qd0: np.ndarray) -> None:
        self.q, self.qd = np.array(q0, dtype=float), np.array(qd0, dtype=float)
        self.qd_target, self.a = np.zeros(6), 1.0

    def set_target(self, qd: np.ndarray, a: float) -> None:
        self.qd_target = np.clip(np.asarray(qd, dtype=float), -MAX_JOINT_SPEED_RAD_S, MAX_JOINT_SPEED_RAD_S)
        self.a = max(a, 1e-6)

    def step(self, dt_s: float) -> np.ndarray | None:
        self.qd = _toward(self.qd, self.qd_target, self.a * dt_s)
        self.q = self.q + self.qd * dt_s
        return self.q


class TcpSpeedMotion:
    """speedl: the TCP twist ``[vx, vy, vz, wx, wy, wz]`` (base frame) ramps toward the target; the integrated TCP
    pose is solved by IK each tick nearest to the previous target."""

    finished = False

    def __init__(self, q0: np.ndarray, T_flange_tcp: np.ndarray) -> None:
        self.q = np.array(q0, dtype=float)
        self.T_flange_tcp = T_flange_tcp
        self.T = forward_kinematics(self.q, T_flange_tcp)
        self.twist, self.twist_target, self.a = np.zeros(6), np.zeros(6), 1.0

    def set_target(self, xd: np.ndarray, a: float) -> None:
        self.twist_target, self.a = np.asarray(xd, dtype=float), max(a, 1e-6)

    def step(self, dt_s: float) -> np.ndarray | None:
        lin = _toward(self.twist[:3], self.twist_target[:3], self.a * dt_s)
        rot = _toward(self.twist[3:], self.twist_target[3:], self.a * dt_s)
        self.twist = np.concatenate([lin, rot])
        T = self.T.copy()
        T[:3, 3] += lin * dt_s
        T[:3, :3] = Rotation.from_rotvec(rot * dt_s).as_matrix() @ T[:3, :3]
        q = track_ik(T, self.q, self.T_flange_tcp)
        if q is None or np.max(np.abs(q - self.q)) > IK_JUMP_LIMIT_RAD:
            return None
        self.T, self.q = T, q
        return q


class ServoMotion:
    """servoj: a first-order follower of the latest target with time constant ``lookahead_time`` (the UR
    parameter's smoothing role), speed-limited to the joint limits. The ``gain`` argument is accepted, not used."""

    finished = False

    def __init__(self, q0: np.ndarray) -> None:
        self.q = np.array(q0, dtype=float)
        self.q_target = self.q.copy()
        self.lookahead_s = 0.1

    def set_target(self, q: np.ndarray, lookahead_s: float) -> None:
        self.q_target = np.asarray(q, dtype=float)
        self.lookahead_s = min(max(lookahead_s, 0.03), 0.2)  # UR's documented range

    def step(self, dt_s: float) -> np.ndarray | None:
        qd = np.clip((self.q_target - self.q) / self.lookahead_s, -MAX_JOINT_SPEED_RAD_S, MAX_JOINT_SPEED_RAD_S)
        self.q = self.q + qd * dt_s
        return self.q
