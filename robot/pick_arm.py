"""``Arm``: the pick cycle's moves outside an attempt's steps: the joint move to the observe pose (where the arm waits
while the camera looks), letting go over the tray, a nudge's strokes, and the recovery after a protective stop or a
dropped link (hold the fingers, recover, go straight up, let go). ``approach_legs``: how an attempt's guarded
approach is split by speed. Joint angles in radians, heights as base z in metres; the settings are
``PickerConfig``'s."""

from __future__ import annotations

import logging
import time

import numpy as np

from robot.gripper import GripperError
from robot.pick_config import PickerConfig
from robot.pick_fingers import Fingers
from robot.pick_protocols import ForceLimitedRobotLike, GraspLike, NudgeLike, RobotLike
from robot.pick_report import NudgeOutcome, Outcome, Stage, StageTimer
from robot.ur_errors import (
    ConnectionLostError,
    MotionFailedError,
    MotionRefusedError,
    NoContactError,
    ProtectiveStopError,
    RecoveryError,
    RobotConnectionError,
)
from sygrid.transforms import make_T

log = logging.getLogger(__name__)


class Arm:
    """``robot`` and the gripper's ``fingers`` as the pick cycle moves them between attempts; ``q_observe`` (6,)."""

    def __init__(self, robot: RobotLike, fingers: Fingers, config: PickerConfig, q_observe: np.ndarray) -> None:
        self.robot, self.fingers, self.config = robot, fingers, config
        self.q_observe = np.asarray(q_observe, dtype=float)
        self._observe_height_m: float | None = None  # base z of the TCP at the observe pose, once it was there

    def to_observe(self) -> None:
        """The joint move to the observe pose. A protective stop on the way (the arm met a wall or a part leaving the
        bin) is recovered once (``recover_and_back_out`` to the observe pose's height) and the joint move is made
        again; a second one (or one before the arm was ever at the observe pose) is raised."""
        cfg = self.config
        try:
            if np.max(np.abs(np.asarray(self.robot.q()) - self.q_observe)) > 1e-3:
                self.robot.move_j(self.q_observe, cfg.transit_speed_rad_s, cfg.transit_accel_rad_s2)
        except MotionFailedError as exc:
            if not exc.recoverable or self._observe_height_m is None:
                raise
            log.warning("%s on the way to the observe pose (%s); recovering", motion_cause(exc), exc)
            self.recover_and_back_out(self._observe_height_m)
            self.robot.move_j(self.q_observe, cfg.transit_speed_rad_s, cfg.transit_accel_rad_s2)
        if self._observe_height_m is None:
            self._observe_height_m = float(np.asarray(self.robot.T_base_tcp())[2, 3])

    def let_go(self, T_base_place: np.ndarray, opening: float | None) -> bool:
        """Lets go of the held part at the place pose ``T_base_place`` (where the arm is): straight down
        ``release_drop_m`` along the tool's approach, guarded (it stops where the part meets what lies in the tray),
        open (``Fingers.release``) and straight back up, so that the next cycle's moves start from the place pose.
        (Left low, a nudge's joint move out of the tray folded the wrist: the forearm met the gripper's housing, a
        self-collision the planner does not check.) A lowering the robot refuses (outside its workspace) lets go at
        the place pose. Returns whether the fingers opened."""
        cfg = self.config
        if cfg.release_drop_m <= 0:
            return self.fingers.release(opening)
        T_low = T_base_place @ make_T(t=(0.0, 0.0, cfg.release_drop_m))
        try:
            self.robot.move_l(T_low, cfg.approach_speed_m_s, cfg.approach_accel_m_s2, cfg.approach_max_force_n)
        except MotionRefusedError as exc:
            log.warning("lowering the part to let it go was refused (%s): letting go at the place pose", exc)
            return self.fingers.release(opening)
        released = self.fingers.release(opening)
        self.robot.move_l(T_base_place, cfg.transit_linear_speed_m_s, cfg.approach_accel_m_s2)
        return released

    def nudge(self, nudge: NudgeLike, timer: StageTimer) -> tuple[NudgeOutcome, str]:
        """A nudge's strokes (timed as ``Stage.NUDGE``): close the fingers (the pads together are the paddle), joint
        move above the press, the press and the drag (``PickerConfig.nudge_contact``: force-limited, or straight
        lines to the planned press and the end of the drag), the straight line up to the retreat. Returns how it
        ended and the error message; a recoverable motion failure is recovered (``recover_and_back_out`` to the
        retreat's height). A force-limited nudge on a robot without force-limited motion is refused (nothing moves)."""
        cfg = self.config
        force_limited = cfg.nudge_contact == "force_limited"
        if force_limited and not isinstance(self.robot, ForceLimitedRobotLike):
            detail = (
                f"nudge_contact = 'force_limited' but {type(self.robot).__name__} has no force-limited motion "
                "(move_until_contact, move_l_pressing): nudges are refused"
            )
            log.error("nudge of part %d refused: %s", nudge.part_index, detail)
            return NudgeOutcome.MOTION_REFUSED, detail
        try:
            with timer(Stage.NUDGE):
                self.fingers.gripper.close(force_n=cfg.grip_force_n)
                self.robot.move_j(nudge.q_above, cfg.transit_speed_rad_s, cfg.transit_accel_rad_s2)
                if force_limited:
                    self._press_and_drag(nudge)
                else:
                    self.robot.move_l(nudge.T_base_press, nudge.speed_m_s, cfg.approach_accel_m_s2)
                    self.robot.move_l(nudge.T_base_end, nudge.speed_m_s, cfg.approach_accel_m_s2)
                self.robot.move_l(nudge.T_base_retreat, cfg.approach_speed_m_s, cfg.approach_accel_m_s2)
        except MotionRefusedError as exc:
            return NudgeOutcome.MOTION_REFUSED, str(exc)
        except MotionFailedError as exc:
            if not exc.recoverable:
                raise
            cause = NudgeOutcome(motion_cause(exc).value)
            outcome = NudgeOutcome.NO_CONTACT if isinstance(exc, NoContactError) else cause
            log.warning("nudge of part %d: %s (%s); recovering", nudge.part_index, outcome, exc)
            # The arm stopped where the press or drag was, not where the retreat was planned from: up to the observe
            # pose's height (above the rim), fingers kept closed as the paddle the nudge's paths were checked with
            # (opened there, a pad reached the bin wall on the joint move that follows)
            height = float(nudge.T_base_retreat[2, 3])
            if self._observe_height_m is not None:
                height = max(height, self._observe_height_m)
            self.recover_and_back_out(height, open_fingers=False)
            return outcome, str(exc)
        return NudgeOutcome.DONE, ""

    def _press_and_drag(self, nudge: NudgeLike) -> None:
        """The force-limited press and drag: down (the way the retreat goes up) from ``nudge_approach_m`` above the
        planned press until the contact, then the drag at the contact's height in force mode, pressing with
        ``nudge_press_force_n``."""
        cfg = self.config
        robot: ForceLimitedRobotLike = self.robot  # type: ignore[assignment]
        up = np.asarray(nudge.T_base_retreat, dtype=float)[:3, 3] - np.asarray(nudge.T_base_end, dtype=float)[:3, 3]
        up /= np.linalg.norm(up)
        T_start = np.array(nudge.T_base_press, dtype=float)
        T_start[:3, 3] += cfg.nudge_approach_m * up
        self.robot.move_l(T_start, cfg.approach_speed_m_s, cfg.approach_accel_m_s2)
        travel = cfg.nudge_approach_m + cfg.nudge_overtravel_m
        robot.move_until_contact(-up, cfg.nudge_contact_speed_m_s, travel)
        T_touch = np.asarray(self.robot.T_base_tcp(), dtype=float)
        T_end = np.array(nudge.T_base_end, dtype=float)
        T_end[:3, 3] += ((T_touch[:3, 3] - np.asarray(nudge.T_base_press)[:3, 3]) @ up) * up  # at the contact's height
        robot.move_l_pressing(T_end, -up, cfg.nudge_press_force_n, nudge.speed_m_s, cfg.approach_accel_m_s2)

    def recover_and_back_out(self, safe_height_m: float, open_fingers: bool = True) -> None:
        """After a protective stop or a dropped link the arm is at rest somewhere on the way, perhaps with a finger
        pressed on a wall: hold the fingers where they are, recover, go straight up to ``safe_height_m`` (base z of
        a pose above the bin's rim), and only then let go (``open_fingers``), before the joint move to the observe
        pose. Fingers that go on pushing would stop the arm again as soon as it is unlocked."""
        self.fingers.hold()
        self.recover()
        T = np.array(self.robot.T_base_tcp())
        T[2, 3] = max(T[2, 3], safe_height_m)
        try:
            self.robot.move_l(T, self.config.approach_speed_m_s, self.config.approach_accel_m_s2)
        except MotionRefusedError as exc:
            log.warning("cannot back out straight up after recovery (%s); going to the observe pose directly", exc)
        except MotionFailedError as exc:
            if not exc.recoverable:
                raise
            log.warning("backing out after recovery failed too (%s); recovering again", exc)
            self.recover()
        if not open_fingers:
            return
        try:
            self.fingers.gripper.open()
        except GripperError as exc:
            log.warning("the gripper did not open after recovery (%s)", exc)

    def recover(self) -> None:
        """``robot.recover()``, tried again every half second while the controller cannot be reached at all (the
        link is down), for up to ``reconnect_timeout_s``; any other failure to recover is raised at once."""
        deadline = time.monotonic() + self.config.reconnect_timeout_s
        while True:
            try:
                self.robot.recover()
                return
            except RecoveryError as exc:
                if not isinstance(exc.__cause__, RobotConnectionError) or time.monotonic() > deadline:
                    raise
                log.warning("cannot reach the robot yet (%s); trying again", exc)
                time.sleep(0.5)


def motion_cause(exc: MotionFailedError) -> Outcome:
    """The outcome a recoverable motion failure gives an attempt."""
    if isinstance(exc, ProtectiveStopError):
        return Outcome.PROTECTIVE_STOP
    if isinstance(exc, ConnectionLostError):
        return Outcome.CONNECTION_LOST
    return Outcome.MOTION_FAILED


def approach_legs(grasp: GraspLike, cfg: PickerConfig) -> list[tuple[np.ndarray, float | None]]:
    """The guarded line pre-grasp -> grasp as (target, speed) legs: at the approach speed to ``final_approach_m``
    short of the grasp, then at the final approach speed (never faster than the approach speed)."""
    p_pre, p_grasp = grasp.T_base_pregrasp[:3, 3], grasp.T_base_grasp[:3, 3]
    length = float(np.linalg.norm(p_grasp - p_pre))
    final_speed = cfg.final_approach_speed_m_s
    if cfg.approach_speed_m_s is not None:
        final_speed = min(final_speed, cfg.approach_speed_m_s)
    if length <= cfg.final_approach_m:
        return [(grasp.T_base_grasp, final_speed)]
    T_slow = grasp.T_base_grasp.copy()
    T_slow[:3, 3] = p_grasp + (p_pre - p_grasp) * (cfg.final_approach_m / length)
    return [(T_slow, cfg.approach_speed_m_s), (grasp.T_base_grasp, final_speed)]
