"""Force-limited motion of the emulated controller: URScript's ``force_mode`` (an admittance on the compliant axes
of a task frame) and ``tool_contact`` (contact detection on the measured TCP wrench), both driven by the wrench the
backend measures (the MuJoCo cell: contact forces on the gripper bodies, ``CellWorld.tool_wrench``).

Wrenches are ``[Fx, Fy, Fz, Tx, Ty, Tz]`` in the robot base frame, torques about the active TCP: the external wrench
the environment exerts on the tool (``actual_TCP_force``: pressing the tool down onto a table reads +Fz).

``ForceMode`` semantics (force_mode(task_frame, selection_vector, wrench, type, limits)):
- ``wrench`` is what the robot applies to its environment, in the task frame; on each compliant axis (selection 1)
  the TCP moves at ``gain * (wrench_i + external_i)``, clipped to ``limits[i]`` (m/s or rad/s), so it advances
  until the external reaction balances the commanded force and backs off when pressed harder. Along compliant
  translation axes the TCP's position is where force mode began plus the integrated offset: the program's motion
  along them is ignored. Compliant rotations add their offset to the program's orientation. Non-compliant axes
  follow the program exactly (their deviation limits are met trivially).
- ``type`` 2 (the task frame as given) is modelled; types 1 and 3 (frames that follow the TCP) are treated as 2 and
  logged once. ``force_mode_set_gain_scaling`` scales the gain; ``force_mode_set_damping`` is stored, not modelled.

``tool_contact(direction)``: a contact is the external force opposing ``direction`` (any direction when it is zero)
above ``CONTACT_FORCE_N``; the result is the number of controller steps back to just before that force first rose
above ``CONTACT_ONSET_N`` (0: no contact), so ``get_actual_joint_positions_history(steps)`` is the contact's start.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from sim.controller.errors import MotionError
from sim.controller.ik_query import track_ik
from sygrid.robots.kinematics import forward_kinematics, pose_to_T

log = logging.getLogger(__name__)

#: Admittance gains at gain scaling 1: TCP speed per newton of force error [m/s/N] and per newton metre [rad/s/N m].
#: Chosen stable against the MuJoCo cell's contact (about 1e5 N/m behind the 100 rad/s arm loop and the filter below).
FORCE_GAIN_M_S_PER_N = 5e-4
TORQUE_GAIN_RAD_S_PER_NM = 2e-2
MAX_GAIN_SCALING = 2.0
#: Time constant of the low-pass filter on the measured wrench the admittance acts on [s] (a stiff contact
#: chatters from one physics step to the next; the controller follows its mean).
WRENCH_FILTER_S = 0.02
#: tool_contact: the external force against the direction that counts as a contact, and where a contact starts.
CONTACT_FORCE_N = 10.0
CONTACT_ONSET_N = 2.0


def wrench_about(wrench_base: np.ndarray, p_from: np.ndarray, p_to: np.ndarray) -> np.ndarray:
    """The same wrench (base frame) with its torque taken about ``p_to`` instead of ``p_from``."""
    w = np.array(wrench_base, dtype=float)
    w[3:] += np.cross(p_from - p_to, w[:3])
    return w


class ForceMode:
    """The admittance state of one force_mode session: the compliant offset integrated in the task frame."""

    def __init__(self) -> None:
        self.T_base_task = np.eye(4)
        self.selection = np.zeros(6, dtype=bool)
        self.wrench = np.zeros(6)
        self.limits = np.zeros(6)
        self.offset = np.zeros(6)  # translation [m] and rotation vector [rad] in the task frame
        self.speed = np.zeros(6)
        self.filtered = np.zeros(6)  # the measured external wrench, low-pass filtered (task frame)
        self.p_start: np.ndarray | None = None  # the nominal TCP position when force mode began (base frame)
        self._warned_type: int | None = None

    def set(
        self,
        task_frame: Sequence[float],
        selection: Sequence[int],
        wrench: Sequence[float],
        frame_type: int,
        limits: Sequence[float],
    ) -> None:
        """New parameters (the program re-sends them every cycle); the integrated offset is kept."""
        values = np.array([*task_frame, *wrench, *limits], dtype=float)
        if not np.all(np.isfinite(values)):
            raise MotionError(f"force_mode: task frame, wrench and limits must be finite, got {values.tolist()}")
        if frame_type not in (1, 2, 3):
            raise MotionError(f"force_mode: type must be 1, 2 or 3, got {frame_type}")
        if frame_type != 2 and self._warned_type != frame_type:
            self._warned_type = frame_type
            log.warning("force_mode type %d is emulated as type 2 (the task frame as given)", frame_type)
        self.T_base_task = pose_to_T(np.asarray(task_frame, dtype=float))
        self.selection = np.array([int(s) != 0 for s in selection], dtype=bool)
        self.wrench = np.asarray(wrench, dtype=float)
        self.limits = np.abs(np.asarray(limits, dtype=float))

    def update(self, external_base: np.ndarray, dt_s: float, gain_scaling: float) -> None:
        """One step of the admittance from the measured external wrench (base frame, about the TCP)."""
        R = self.T_base_task[:3, :3]
        external = np.concatenate([R.T @ external_base[:3], R.T @ external_base[3:]])
        gains = np.array([FORCE_GAIN_M_S_PER_N] * 3 + [TORQUE_GAIN_RAD_S_PER_NM] * 3) * gain_scaling
        self.filtered += dt_s / (WRENCH_FILTER_S + dt_s) * (external - self.filtered)
        speed = np.clip(gains * (self.wrench + self.filtered), -self.limits, self.limits)
        self.speed = np.where(self.selection, speed, 0.0)
        self.offset += self.speed * dt_s

    def apply(self, q_nominal: np.ndarray, q_prev: np.ndarray, T_flange_tcp: np.ndarray) -> np.ndarray | None:
        """The joint target: the nominal TCP pose with its position along the compliant translation axes taken
        from where force mode began plus the compliant offset, and turned by the compliant rotation offset; None
        when IK fails."""
        T = forward_kinematics(q_nominal, T_flange_tcp)
        if self.p_start is None:
            self.p_start = T[:3, 3].copy()
        R = self.T_base_task[:3, :3]
        along = R @ np.diag(self.selection[:3].astype(float)) @ R.T  # projector on the compliant directions
        p = T[:3, 3] + along @ (self.p_start - T[:3, 3]) + R @ self.offset[:3]
        if np.allclose(p, T[:3, 3], rtol=0.0, atol=1e-12) and not np.any(self.offset[3:]):
            return q_nominal
        T[:3, 3] = p
        T[:3, :3] = Rotation.from_rotvec(R @ self.offset[3:]).as_matrix() @ T[:3, :3]
        return track_ik(T, q_prev, T_flange_tcp)


def tool_contact_steps(history: Sequence[np.ndarray], direction: np.ndarray, max_steps: int | None = None) -> int:
    """URScript ``tool_contact``: steps back from the newest wrench in ``history`` (oldest first, one per 2 ms
    step, base frame) to just before the contact began, or 0 without a contact (see the module docstring); at most
    ``max_steps`` back (a contact that was there before a motion began counts from its start)."""
    if not history:
        return 0
    if max_steps is not None:
        history = list(history)[-max(int(max_steps), 1) - 1 :]
    d = np.asarray(direction, dtype=float)[:3]
    norm = float(np.linalg.norm(d))

    def resisting(w: np.ndarray) -> float:
        return float(np.linalg.norm(w[:3])) if norm == 0.0 else float(-(w[:3] @ d) / norm)

    if resisting(history[-1]) <= CONTACT_FORCE_N:
        return 0
    steps = 1
    while steps < len(history) and resisting(history[-1 - steps]) > CONTACT_ONSET_N:
        steps += 1
    return max(1, min(steps, len(history) - 1))
