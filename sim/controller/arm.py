"""The motion side of the emulated controller: the active motion, the target joint state it produces each tick,
the active TCP and payload, and force mode. The program (``program.py``) starts and stops motions here; the tick
steps it.

In force mode (``force.ForceMode``) the motion produces the nominal target (``nominal_q``, where every new motion
starts) and the compliant offset moves it; ``target_q`` is what the arm is sent. Ending force mode keeps the arm
where it is (the offset becomes part of the nominal target).
"""

from __future__ import annotations

import logging

import numpy as np

from sim.controller.errors import MotionError
from sim.controller.force import MAX_GAIN_SCALING, ForceMode
from sim.controller.motion import (
    IK_JUMP_LIMIT_RAD,
    CartesianPath,
    DecelerationMotion,
    JointPath,
    JointSpeedMotion,
    PathMotion,
    ServoMotion,
    TcpSpeedMotion,
)
from sygrid.robots import ur5e
from sygrid.robots.kinematics import T_to_pose, forward_kinematics, inverse_kinematics, pose_to_T

log = logging.getLogger(__name__)

Motion = PathMotion | DecelerationMotion | JointSpeedMotion | TcpSpeedMotion | ServoMotion
STEADY_SPEED_RAD_S = 1e-3  # isSteady: every joint slower than this ...
STEADY_TIME_S = 0.05  # ... for this long, with no motion active
FORCE_MODE_END_DECEL_RAD_S2 = 10.0  # a motion still running when force mode ends slows to rest at this rate


def within_joint_limits(q: np.ndarray) -> bool:
    """True when every joint angle is finite and inside the UR5e limits (elbow +-pi, others +-2 pi)."""
    q = np.asarray(q, dtype=float)
    limits = ur5e.JOINT_LIMITS_RAD
    return bool(np.all(np.isfinite(q)) and np.all(q >= limits[:, 0]) and np.all(q <= limits[:, 1]))


def _vector(values: np.ndarray, what: str, n: int = 6) -> np.ndarray:
    v = np.asarray(values, dtype=float)
    if v.shape != (n,) or not np.all(np.isfinite(v)):
        raise MotionError(f"{what} must be {n} finite numbers, got {values!r}")
    return v


class ArmController:
    """Owns the target trajectory. ``step`` advances it by one tick."""

    def __init__(self, q0: np.ndarray) -> None:
        self.target_q = np.array(q0, dtype=float)
        self.nominal_q = self.target_q.copy()  # the motion's own target, without the force-mode offset
        self.nominal_qd = np.zeros(6)
        self.target_qd = np.zeros(6)
        self.target_qdd = np.zeros(6)
        self.motion: Motion | None = None
        self.T_flange_tcp = np.eye(4)
        self.payload_mass_kg = 0.0
        self.payload_cog_m = np.zeros(3)
        self.payload_inertia = np.zeros(6)
        self._steady_s = 0.0
        self.force: ForceMode | None = None
        self.contact_watch = False  # a command acts on the measured wrench (moveUntilContact): see force_sensitive
        self.force_gain_scaling = 1.0
        self.force_damping = 0.005

    # --- configuration -------------------------------------------------------------------------------------
    @property
    def tcp_pose(self) -> np.ndarray:
        return T_to_pose(self.T_flange_tcp)

    def set_tcp(self, pose: np.ndarray) -> None:
        self.T_flange_tcp = pose_to_T(_vector(pose, "TCP offset"))

    def set_payload(self, mass_kg: float, cog_m: np.ndarray | None, inertia: np.ndarray | None = None) -> None:
        if not np.isfinite(mass_kg) or mass_kg < 0:
            raise MotionError(f"payload mass must be a finite number >= 0 kg, got {mass_kg}")
        self.payload_mass_kg = float(mass_kg)
        if cog_m is not None:
            self.payload_cog_m = _vector(cog_m, "payload centre of gravity", 3)
        if inertia is not None:
            self.payload_inertia = _vector(inertia, "payload inertia")

    # --- force mode ----------------------------------------------------------------------------------------
    def force_mode(
        self, task_frame: np.ndarray, selection: np.ndarray, wrench: np.ndarray, frame_type: int, limits: np.ndarray
    ) -> None:
        """Enters force mode, or updates its parameters (see ``force.ForceMode``)."""
        if self.force is None:
            self.force = ForceMode()
        self.force.set(task_frame, selection, wrench, frame_type, limits)

    def end_force_mode(self) -> None:
        """Leaves force mode where the arm is: the compliant offset becomes part of the nominal target."""
        if self.force is not None:
            self.force = None
            self.nominal_q = self.target_q.copy()
            self.nominal_qd = self.target_qd.copy()
            if self.motion is not None:  # generated without the offset: slow to rest from where the arm is
                speed = float(np.max(np.abs(self.nominal_qd)))
                self.motion = DecelerationMotion(self.nominal_q, self.nominal_qd, speed / FORCE_MODE_END_DECEL_RAD_S2)

    @property
    def force_sensitive(self) -> bool:
        """The motion depends on the measured wrench (force mode, a move until contact): the controller then lets
        it advance only while the backend's measurements are current (a lagging simulation must not run on)."""
        return self.force is not None or self.contact_watch

    def set_force_gain_scaling(self, scaling: float) -> None:
        if not (np.isfinite(scaling) and 0.0 <= scaling <= MAX_GAIN_SCALING):
            raise MotionError(f"force_mode_set_gain_scaling: scaling must be in [0, {MAX_GAIN_SCALING}], got {scaling}")
        self.force_gain_scaling = float(scaling)

    def set_force_damping(self, damping: float) -> None:
        if not (np.isfinite(damping) and 0.0 <= damping <= 1.0):
            raise MotionError(f"force_mode_set_damping: damping must be in [0, 1], got {damping}")
        self.force_damping = float(damping)

    # --- motions -------------------------------------------------------------------------------------------
    def movej(self, q: np.ndarray, v: float, a: float) -> PathMotion:
        q = _vector(q, "movej target q")
        if not within_joint_limits(q):
            raise MotionError(
                f"movej target {np.round(q, 4).tolist()} is outside the UR5e joint limits "
                f"{ur5e.JOINT_LIMITS_RAD.round(4).tolist()} rad"
            )
        self.motion = PathMotion(JointPath(self.nominal_q, q), v, a, self.nominal_q)
        return self.motion

    def movel(self, pose: np.ndarray, v: float, a: float) -> PathMotion:
        T_end = pose_to_T(_vector(pose, "movel target pose"))
        if len(inverse_kinematics(T_end, self.T_flange_tcp)) == 0:
            raise MotionError(f"movel target pose {np.round(pose, 4).tolist()} is out of reach (no IK solution)")
        T_start = forward_kinematics(self.nominal_q, self.T_flange_tcp)
        self.motion = PathMotion(CartesianPath(T_start, T_end, self.T_flange_tcp), v, a, self.nominal_q)
        return self.motion

    def servo(self, q: np.ndarray, lookahead_s: float) -> None:
        if not isinstance(self.motion, ServoMotion):
            self.motion = ServoMotion(self.nominal_q)
        self.motion.set_target(_vector(q, "servoj target q"), lookahead_s)

    def speedj(self, qd: np.ndarray, a: float) -> None:
        if not isinstance(self.motion, JointSpeedMotion):
            self.motion = JointSpeedMotion(self.nominal_q, self.nominal_qd)
        self.motion.set_target(_vector(qd, "speedj joint speeds"), a)

    def speedl(self, xd: np.ndarray, a: float) -> None:
        if not isinstance(self.motion, TcpSpeedMotion):
            self.motion = TcpSpeedMotion(self.nominal_q, self.T_flange_tcp)
        self.motion.set_target(_vector(xd, "speedl tool speed"), a)

    def stop(self, decel: float, linear: bool) -> Motion | None:
        """stopj (``linear=False``, decel in rad/s^2 of the leading joint) or stopl (decel in m/s^2 of the TCP).
        Path motions decelerate along their path; others slow every joint to rest together."""
        if self.motion is None:
            return None
        decel = float(decel) if np.isfinite(decel) and decel > 0 else 1.0
        joint_speed = float(np.max(np.abs(self.nominal_qd)))
        scale = self._tcp_speed() if linear else joint_speed
        if isinstance(self.motion, PathMotion):
            ratio = scale / self.motion.sd if self.motion.sd > 1e-9 and scale > 1e-9 else 1.0
            self.motion.begin_stop(decel / ratio)
        elif joint_speed > 1e-9:
            self.motion = DecelerationMotion(self.nominal_q, self.nominal_qd, max(scale, 1e-9) / decel)
        else:
            self.motion = None
        return self.motion

    def halt(self) -> None:
        """Stops dead at the current target (protective stop); force mode ends."""
        self.motion = None
        self.force = None
        self.contact_watch = False
        self.nominal_q = self.target_q.copy()
        self.target_qd = np.zeros(6)
        self.nominal_qd = np.zeros(6)
        self.target_qdd = np.zeros(6)

    def hold_at(self, q: np.ndarray) -> None:
        self.halt()
        self.target_q = np.array(q, dtype=float)
        self.nominal_q = self.target_q.copy()

    # --- tick ----------------------------------------------------------------------------------------------
    def step(self, dt_s: float, speed_fraction: float, tcp_wrench: np.ndarray | None = None) -> str | None:
        """Advances the active motion (and, in force mode, the admittance on ``tcp_wrench``, the measured external
        wrench in the base frame about the TCP; None: hold the compliant offset); returns why it failed (and halts),
        or None."""
        qd_prev, q_prev = self.target_qd, self.target_q
        finished = False
        q_nominal = self.nominal_q
        if self.motion is not None:
            q = self.motion.step(dt_s * speed_fraction)
            if q is None:
                self.halt()
                return "the TCP path crossed a singularity or left the workspace (no continuous IK solution)"
            q_nominal, finished = q, self.motion.finished
        self.nominal_qd = (q_nominal - self.nominal_q) / dt_s
        self.nominal_q = q_nominal
        q = q_nominal
        if self.force is not None:
            if tcp_wrench is not None:
                self.force.update(tcp_wrench, dt_s, self.force_gain_scaling)
            q = self.force.apply(q_nominal, q_prev, self.T_flange_tcp)
            if q is None or np.max(np.abs(q - q_prev)) > IK_JUMP_LIMIT_RAD:
                self.halt()
                return "force mode moved the TCP out of reach (no continuous IK solution)"
        if not within_joint_limits(q):
            self.halt()
            return f"joint limit: target {np.round(q, 4).tolist()} leaves {ur5e.JOINT_LIMITS_RAD.round(4).tolist()}"
        self.target_qd = (q - q_prev) / dt_s
        self.target_q = q
        if finished:  # every profile ends at rest; the last tick's mean speed is not the end speed
            self.motion = None
            self.nominal_qd = np.zeros(6)
            if self.force is None:
                self.target_qd = np.zeros(6)
        self.target_qdd = (self.target_qd - qd_prev) / dt_s
        return None

    def update_steady(self, actual_qd: np.ndarray, dt_s: float) -> None:
        moving = self.motion is not None or float(np.max(np.abs(actual_qd))) > STEADY_SPEED_RAD_S
        self._steady_s = 0.0 if moving else self._steady_s + dt_s

    @property
    def is_steady(self) -> bool:
        return self._steady_s >= STEADY_TIME_S

    def _tcp_speed(self) -> float:
        """Linear TCP speed of the target motion in [m/s] (finite difference over one tick)."""
        dt_s = 1e-3
        p0 = forward_kinematics(self.target_q, self.T_flange_tcp)[:3, 3]
        p1 = forward_kinematics(self.target_q + self.target_qd * dt_s, self.T_flange_tcp)[:3, 3]
        return float(np.linalg.norm(p1 - p0) / dt_s)
