"""The pick cycle as an explicit state machine: capture -> perceive -> plan -> approach -> grasp -> verify ->
place -> next, or plan -> nudge -> next when nothing is safe to pick but a part can be dragged clear.

Every part is injected (``Picker(robot, gripper, camera, perception, planner, ...)``), each through a small
protocol below, so the same cycle drives the simulated cell (the emulator through ur_rtde, a rendered camera) and
the real one (a UR5e, an OAK camera), and unit tests can swap any part for a fake.

One cycle (``Picker.cycle``) takes one frame, estimates the parts, plans, and tries the planned grasps best first:

- ``approach``: open the gripper to the grasp's opening and check that the fingers got there (something stuck
  between them: ``gripper_blocked``), joint move to the lift pose (above the bin's rim on the approach line),
  straight lines to the pre-grasp and the grasp;
- ``grasp``: close; the gripper's object detection must say "held", or the fingers must have stopped at least
  ``min_held_width_m`` apart (False and closed: on air, or the part slid away; the gripper opens and backs out along
  the approach to the lift);
- ``verify``: straight line back out to the lift; the fingers must not have closed below the narrowest width the
  part can be held at less ``slip_width_tolerance_m`` (the part slipped out), and the gripper must report the object
  again, or its fingers rest where they are, within ``slip_settle_s``. A part held at another of its widths than the
  planned one (it turned in the closing fingers, or its estimate was off: a nut across its faces, not its flats) is
  in the gripper and is placed; the attempt's detail says so;
- ``place``: joint move to the place pose, open, and check that the fingers opened: a part that keeps them from
  opening is still in the gripper (``not_released``; the run stops with "gripper_blocked" if re-opening does not
  free it). The look after lifting is the next cycle's frame (the arm is then clear of the camera): if a part of
  the same model is still where the picked one was (``still_there_distance_m``), the pick is marked failed
  (``part_still_in_bin``).

Retries: a refused motion (``MotionRefusedError``: checked, nothing sent) moves on to the next candidate; a grasp
that fails verification, a protective stop or a dropped connection (after ``robot.recover()``) end the cycle, and
the next cycle looks again (the pile has changed); one on the joint move back to the observe pose is recovered once
(straight up to the observe pose's height, then the move again). When nothing is safe to pick but a part lies too
close to a wall or a neighbour for the fingers, the picker nudges it (``robot.nudge``: drags it away from them with
the closed fingers) and looks again: at most ``max_nudges`` per run and ``max_nudges_per_part`` at one location. A
part whose location has seen ``max_failures_per_part`` failed attempts (within ``exclusion_distance_m``: a part that
moved is a new chance) is left out of planning, so one stubborn part cannot make the run loop. The run stops cleanly
when no part is estimated in the bin ("bin_empty"; "parts_unseen" when the depth shows it is not empty), when no safe
grasp is left ("nothing_safe", with the planner's reasons), when every part left has been given up ("gave_up"), when
the fingers cannot be freed ("gripper_blocked"), after ``max_cycles``, after ``max_failed_cycles`` cycles in a row
without a pick, or when a stop cannot be released by the cell itself (an emergency stop, a protective stop that does
not release: "needs_operator", nothing more is sent, the cycles so far are kept in the report).

Times: stage timings are wall seconds; ``sim_time_s`` is the camera's timestamp (simulated seconds in the
simulated cell, the device clock on hardware), so a cycle's robot time is the difference between two captures.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any, Protocol

import numpy as np

from perception.camera import Frame
from robot.gripper import GripperError
from robot.ur_errors import (
    ConnectionLostError,
    MotionFailedError,
    MotionRefusedError,
    ProtectiveStopError,
    RecoveryError,
    RobotConnectionError,
)
from sygrid.errors import ConfigError

log = logging.getLogger(__name__)

STAGES = ("capture", "perceive", "plan", "approach", "grasp", "verify", "place", "nudge")
#: Why a run stopped.
STOP_REASONS = (
    "bin_empty",
    "parts_unseen",  # no part estimated in the bin, but the depth shows something in it
    "nothing_safe",
    "gave_up",
    "gripper_blocked",
    "max_cycles",
    "too_many_failures",
    "needs_operator",  # a stop the cell cannot release itself (emergency stop, arm pinned in a protective stop)
)
#: The outcome of one attempt (one planned grasp tried): "picked" or a failure cause.
FAILURE_CAUSES = (
    "motion_refused",  # checked and refused, nothing sent: next candidate
    "gripper_empty",  # closed on air (no object detected)
    "slipped",  # lost the part while lifting
    "protective_stop",
    "connection_lost",
    "motion_failed",  # another recoverable motion failure (program stopped, timeout)
    "part_still_in_bin",  # placed "something", but the next look shows the part where it was
    "gripper_blocked",  # the fingers did not open to the grasp's opening before the approach: nothing sent down
    "not_released",  # the fingers did not open at the place pose: the part (or something) is stuck in them
)
_WIDTH_STEADY_M = 0.0005  # fingers that move less than this ...
_WIDTH_STEADY_S = 0.15  # ... for this long rest on what they hold
#: Outcomes that count against a part's location (``PickerConfig.max_failures_per_part``): a dropped connection
#: or a blocked gripper says nothing about the part.
_PART_FAILURES = frozenset(FAILURE_CAUSES) - {"connection_lost", "gripper_blocked", "not_released"}


# ---------------------------------------------------------------------------------------------- protocols


class RobotLike(Protocol):
    """What the cycle needs of ``robot.ur.URRobot``."""

    def q(self) -> np.ndarray: ...
    def T_base_tcp(self) -> np.ndarray: ...
    def move_l(
        self, T_base_tcp: np.ndarray, speed_m_s: float | None = None, accel_m_s2: float | None = None
    ) -> Any: ...
    def move_j(self, q: np.ndarray, speed_rad_s: float | None = None, accel_rad_s2: float | None = None) -> Any: ...
    def recover(self, timeout_s: float | None = None) -> None: ...


class GripperLike(Protocol):
    """What the cycle needs of ``robot.gripper.Gripper``."""

    can_set_width: bool

    def open(self, width_m: float | None = None, speed_m_s: float | None = None) -> None: ...
    def close(self, force_n: float | None = None, speed_m_s: float | None = None) -> bool | None: ...
    def width_m(self) -> float | None: ...
    def object_detected(self) -> bool | None: ...


class CameraLike(Protocol):
    def capture(self) -> Frame: ...


class PerceptionLike(Protocol):
    """``perception.pipeline.PerceptionPipeline`` (or the simulated cell's oracle): ``run(frame)`` returns an object
    with ``poses`` (``ObjectPose`` list), ``detections`` and ``timings_ms``. Optional: ``refine_more(poses, frame)``,
    the poses with more of them depth-refined (None when there is nothing left to refine); the picker calls it when
    nothing is safe among the refined ones."""

    def run(self, frame: Frame) -> Any: ...


class NudgerLike(Protocol):
    """``robot.nudge.NudgePlanner``."""

    def plan(
        self, poses: Sequence[Any], T_base_camera: np.ndarray, plan: Any, q_from: np.ndarray, q_after: np.ndarray,
        skip: Callable[[int], bool] | None = None,
    ) -> Any: ...  # fmt: skip


class PlannerLike(Protocol):
    """``robot.grasp.GraspPlanner``."""

    def plan(
        self,
        poses: Sequence[Any],
        T_base_camera: np.ndarray,
        depth_m: np.ndarray | None = None,
        intrinsics: Any = None,
        q_seed: np.ndarray | None = None,
    ) -> Any: ...

    def pile_area_m2(self, depth_m: np.ndarray, intrinsics: Any, T_base_camera: np.ndarray) -> float: ...


# ---------------------------------------------------------------------------------------------- config & records


@dataclass(frozen=True)
class PickerConfig:
    """Settings of the cycle. Speeds in m/s (straight lines) and rad/s (joint moves); None: the robot's default.

    approach_speed_m_s: pre-grasp -> grasp and grasp -> lift; transit_linear_speed_m_s: lift -> pre-grasp.
    transit_speed_rad_s: joint moves (to the lift,
    to the place pose). grip_force_n: closing force (None: the gripper's default). max_attempts_per_cycle: planned
    grasps tried in one cycle before looking again. slip_width_tolerance_m: after lifting, an opening smaller than
    the narrowest width the part can be held at (``hold_any_width``; else the planned grasp width) less this means
    the part slipped out; hold_any_width: a part held at another of its widths than the planned one is held (False:
    only near the planned width; the fingers closing on a nut's faces instead of its flats then drop it back into
    the bin as "slipped"); slip_settle_s: how long the gripper may report no object (its fingers settling) before
    the part counts as lost. still_there_distance_m: a part of the same model this close to a picked one in the next
    frame means the pick failed. max_failures_per_part /
    exclusion_distance_m: after this many failed attempts on parts of one model within this distance of each other,
    parts there are no longer planned (checked on the poses planned from, refined ones included).
    open_tolerance_m / open_timeout_s: the fingers must reach a commanded opening less this within this time (a
    gripper may report "stopped" while its fingers still move); release_tries: how often the gripper is opened at
    the place pose before the part counts as stuck. reconnect_timeout_s: how long recovery keeps trying to reach a
    controller that does not answer (a network link that is down). max_nudges / max_nudges_per_part: nudges per
    run (0: never nudge) and per location (within ``exclusion_distance_m``); a nudge is not a failed cycle.
    min_unseen_area_m2: with no part estimated in the bin, a bin whose depth shows at least this much of it covered
    (something above the floor, ``PlannerLike.pile_area_m2``) holds parts the detector does not find or whose
    estimates land outside it: the run stops with "parts_unseen", not "bin_empty". 1 cm2 is a third of a nut's top
    seen from above.
    min_held_width_m: fingers that stopped at least this far apart hold something, even when the gripper reports no
    object, and fingers closer than this after lifting hold nothing. A gripper detects an object when its fingers
    stop short of the commanded position by more than a tolerance (1.5 mm on the emulated 2F-85): a 2 mm sheet,
    which the pads squeeze to 1.3 mm, reads "no object", although the fingers, closed on air, read 0 mm. 1 mm is
    three of the 2F-85's position counts; on hardware, calibrate ``pos_closed`` so that closed on air reads 0.
    """

    max_cycles: int = 50
    max_attempts_per_cycle: int = 3
    max_failed_cycles: int = 3
    approach_speed_m_s: float | None = 0.25
    transit_linear_speed_m_s: float | None = 0.5
    approach_accel_m_s2: float | None = 1.2
    transit_speed_rad_s: float | None = 2.0
    transit_accel_rad_s2: float | None = 3.0
    grip_force_n: float | None = None
    slip_width_tolerance_m: float = 0.004
    hold_any_width: bool = True
    slip_settle_s: float = 0.5
    still_there_distance_m: float = 0.01
    max_failures_per_part: int = 2
    exclusion_distance_m: float = 0.015
    open_tolerance_m: float = 0.003
    open_timeout_s: float = 2.0
    release_tries: int = 2
    reconnect_timeout_s: float = 30.0
    max_nudges: int = 8
    max_nudges_per_part: int = 2
    min_unseen_area_m2: float = 1e-4
    min_held_width_m: float = 0.001

    def __post_init__(self) -> None:
        for name in (
            "max_cycles",
            "max_attempts_per_cycle",
            "max_failed_cycles",
            "max_failures_per_part",
            "release_tries",
            "max_nudges_per_part",
        ):
            if not (isinstance(getattr(self, name), int) and getattr(self, name) >= 1):
                raise ConfigError(f"PickerConfig.{name} must be an integer >= 1, got {getattr(self, name)!r}")
        if not isinstance(self.hold_any_width, bool):
            raise ConfigError(f"PickerConfig.hold_any_width must be true or false, got {self.hold_any_width!r}")
        if not (isinstance(self.max_nudges, int) and self.max_nudges >= 0):
            raise ConfigError(f"PickerConfig.max_nudges must be an integer >= 0, got {self.max_nudges!r}")
        for name in (
            "slip_width_tolerance_m", "still_there_distance_m", "exclusion_distance_m", "open_tolerance_m",
            "open_timeout_s", "slip_settle_s", "reconnect_timeout_s", "min_unseen_area_m2", "min_held_width_m",
        ):  # fmt: skip
            if not getattr(self, name) >= 0:
                raise ConfigError(f"PickerConfig.{name} must be >= 0, got {getattr(self, name)!r}")


@dataclass
class Attempt:
    """One planned grasp tried: which part, how it ended (``outcome`` "picked" or a ``FAILURE_CAUSES`` entry),
    in which stage, and the error message where there was one."""

    part_index: int
    obj_id: int
    outcome: str
    stage: str
    detail: str = ""
    T_base_obj: list | None = None  # where the part was estimated (for the next look and the report)


@dataclass
class CycleRecord:
    """One cycle: wall seconds per stage, the camera's time at capture, what was seen and planned, the attempts."""

    index: int
    sim_time_s: float
    stage_wall_s: dict[str, float] = field(default_factory=lambda: dict.fromkeys(STAGES, 0.0))
    n_detections: int = 0
    n_poses: int = 0
    n_planned: int = 0
    n_excluded: int = 0  # parts left out of planning after repeated failures at their location
    perception_ms: dict[str, float] = field(default_factory=dict)
    plan_summary: str = ""
    attempts: list[Attempt] = field(default_factory=list)
    nudge: dict | None = None  # the nudge of a "nudged" cycle: part, cause, tilt, distance, outcome, detail
    end: str = ""  # "picked", "failed", "nudged", or a stop reason
    sim_cycle_s: float | None = None  # filled when the next capture's time is known

    @property
    def picked(self) -> bool:
        return any(a.outcome == "picked" for a in self.attempts)


@dataclass
class RunReport:
    """A whole run: the cycles, why it stopped (``STOP_REASONS``) and the details (e.g. the planner's reasons)."""

    cycles: list[CycleRecord]
    stop_reason: str
    stop_detail: str = ""

    @property
    def attempts(self) -> list[Attempt]:
        return [a for c in self.cycles for a in c.attempts]

    @property
    def n_picked(self) -> int:
        return sum(a.outcome == "picked" for a in self.attempts)

    @property
    def success_rate(self) -> float:
        """Picks over attempts that sent motion (refused candidates moved nothing and do not count)."""
        tried = [a for a in self.attempts if a.outcome != "motion_refused"]
        return self.n_picked / len(tried) if tried else float("nan")

    @property
    def n_nudges(self) -> int:
        return sum(c.nudge is not None for c in self.cycles)

    def failures_by_cause(self) -> dict[str, int]:
        counts: dict[str, int] = {}
        for a in self.attempts:
            if a.outcome != "picked":
                counts[a.outcome] = counts.get(a.outcome, 0) + 1
        return counts

    def sim_cycle_times_s(self) -> list[float]:
        """Robot time of the cycles that picked a part (camera time from their capture to the next one)."""
        return [c.sim_cycle_s for c in self.cycles if c.picked and c.sim_cycle_s is not None]

    def to_json(self) -> dict:
        return {
            "stop_reason": self.stop_reason,
            "stop_detail": self.stop_detail,
            "n_picked": self.n_picked,
            "n_attempts": len(self.attempts),
            "n_nudges": self.n_nudges,
            "success_rate": self.success_rate,
            "failures_by_cause": self.failures_by_cause(),
            "sim_cycle_times_s": self.sim_cycle_times_s(),
            "cycles": [{**asdict(c), "picked": c.picked} for c in self.cycles],
        }


# ---------------------------------------------------------------------------------------------- the picker


class Picker:
    """The pick cycle; see the module docstring.

    Args:
        robot, gripper, camera, perception, planner: the injected parts (see the protocols).
        T_base_camera: the camera pose in the robot base frame (hand-eye calibration), 4x4.
        q_observe: joint angles (rad) where the arm waits while the camera looks (clear of its view); the arm
            goes there first and after every failed cycle.
        config: the cycle's settings.
        on_cycle: called with each finished ``CycleRecord``, its frame, the perception result and the poses the
            plan was made from (the result's, or after ``refine_more`` the further refined ones), for pictures.
        nudger: plans nudges when nothing is safe to pick (None: the run stops there).
    """

    def __init__(
        self,
        robot: RobotLike,
        gripper: GripperLike,
        camera: CameraLike,
        perception: PerceptionLike,
        planner: PlannerLike,
        T_base_camera: np.ndarray,
        q_observe: np.ndarray,
        config: PickerConfig | None = None,
        on_cycle: Callable[[CycleRecord, Frame, Any, list[Any]], None] | None = None,
        nudger: NudgerLike | None = None,
    ) -> None:
        self.robot, self.gripper, self.camera = robot, gripper, camera
        self.perception, self.planner = perception, planner
        self.T_base_camera = np.asarray(T_base_camera, dtype=float)
        if self.T_base_camera.shape != (4, 4):
            raise ConfigError(f"Picker: T_base_camera must be 4x4, got shape {self.T_base_camera.shape}")
        self.q_observe = np.asarray(q_observe, dtype=float)
        self.config = config or PickerConfig()
        self.on_cycle = on_cycle
        self.nudger = nudger
        self._last_picked: Attempt | None = None
        self._failed_at = _LocationCounts(self.config.exclusion_distance_m)  # failed attempts per location
        self._nudged_at = _LocationCounts(self.config.exclusion_distance_m)
        self._observe_height_m: float | None = None  # base z of the TCP at the observe pose, once it was there

    # --- the run ---------------------------------------------------------------------------------------------
    def run(self, max_cycles: int | None = None) -> RunReport:
        """Picks until the bin is empty, nothing is safe, ``max_cycles`` (default ``config.max_cycles``) or too
        many failed cycles in a row."""
        limit = max_cycles or self.config.max_cycles
        cycles: list[CycleRecord] = []
        failed_in_row = 0
        self._to_observe()
        while True:
            if len(cycles) >= limit:
                return self._finish(cycles, "max_cycles", f"stopped after {limit} cycle(s)")
            try:
                record = self.cycle(len(cycles))
            except (RecoveryError, MotionFailedError) as exc:  # a recoverable MotionFailedError never gets here
                log.error("the cell needs an operator: %s", exc)
                return self._finish(cycles, "needs_operator", f"{type(exc).__name__}: {exc}")
            if cycles and cycles[-1].sim_cycle_s is None:
                cycles[-1].sim_cycle_s = record.sim_time_s - cycles[-1].sim_time_s
            cycles.append(record)
            if record.end in ("bin_empty", "parts_unseen", "nothing_safe", "gave_up", "gripper_blocked"):
                return self._finish(cycles, record.end, record.plan_summary)
            if record.end != "nudged":  # a nudge is neither a pick nor a failure
                failed_in_row = 0 if record.picked else failed_in_row + 1
            if failed_in_row >= self.config.max_failed_cycles:
                return self._finish(
                    cycles, "too_many_failures", f"{failed_in_row} cycles in a row without a pick; last: {record.end}"
                )

    def _finish(self, cycles: list[CycleRecord], reason: str, detail: str) -> RunReport:
        report = RunReport(cycles, reason, detail)
        log.info(
            "pick run stopped (%s): %d picked in %d attempts; %s", reason, report.n_picked, len(report.attempts), detail
        )
        return report

    # --- one cycle -------------------------------------------------------------------------------------------
    def cycle(self, index: int = 0) -> CycleRecord:
        """capture -> perceive -> plan -> (approach -> grasp -> verify -> place) per planned grasp until one
        picks; returns the record (``end``: "picked", "failed", "nudged", or a stop reason: "bin_empty",
        "parts_unseen", "nothing_safe", "gave_up", "gripper_blocked")."""
        t = time.perf_counter()
        frame = self.camera.capture()
        record = CycleRecord(index=index, sim_time_s=float(frame.timestamp_s))
        record.stage_wall_s["capture"] = time.perf_counter() - t

        t = time.perf_counter()
        result = self.perception.run(frame)
        record.stage_wall_s["perceive"] = time.perf_counter() - t
        record.n_detections, record.n_poses = len(result.detections), len(result.poses)
        record.perception_ms = {k: float(v) for k, v in getattr(result, "timings_ms", {}).items()}
        self._look_after_last_pick(result.poses)
        seen_poses = result.poses  # for the callback: after refine_more, the poses the plan was made from

        try:
            if not result.poses:
                return self._empty_or_unseen(record, frame, "the camera sees no parts (no detections)")
            poses, excluded = self._split_given_up(result.poses)
            if not poses:
                return self._all_given_up(record, len(excluded))
            plan = self._plan(poses, frame, record)
            refine_more = getattr(self.perception, "refine_more", None)
            while plan.nothing_safe and refine_more is not None:
                # nothing safe among the refined parts: refine the next ones the pipeline skipped, and plan again
                t = time.perf_counter()
                more = refine_more(poses, frame)
                record.stage_wall_s["perceive"] += time.perf_counter() - t
                if more is None:
                    break
                seen_poses = [*more, *excluded]
                # a skipped part's RGB estimate can lie centimetres from where its refined pose puts it: where
                # attempts failed is checked again on the refined poses
                poses, given_up = self._split_given_up(more)
                excluded += given_up
                if not poses:
                    return self._all_given_up(record, len(excluded))
                plan = self._plan(poses, frame, record)
            record.n_excluded = len(excluded)
            record.n_planned, record.plan_summary = len(plan.grasps), plan.summary()
            if record.n_excluded:
                record.plan_summary += f" ({record.n_excluded} part(s) given up after repeated failures)"
            if plan.nothing_safe:
                if getattr(plan, "n_in_bin", None) == 0:  # the camera sees parts, but none in the bin
                    seen = f"no part estimated in the bin ({len(poses)} seen outside it); {record.plan_summary}"
                    return self._empty_or_unseen(record, frame, seen)
                if not self._nudge(poses, plan, record):
                    record.end = "nothing_safe"
                return record
            record.end = "failed"
            for grasp in plan.grasps[: self.config.max_attempts_per_cycle]:
                attempt = self._attempt(grasp, record)
                record.attempts.append(attempt)
                if attempt.outcome == "picked":
                    record.end = "picked"
                    self._last_picked = attempt
                    break
                self._count_failure(attempt)
                if attempt.outcome in ("gripper_blocked", "not_released"):
                    record.end, record.plan_summary = "gripper_blocked", attempt.detail
                    break
                if attempt.outcome != "motion_refused":
                    break  # something moved or failed: look again
            if record.end != "picked":
                self._to_observe()
            return record
        finally:
            log.info(
                "cycle %d: %s (%s) in %.2f s wall", index, record.end, _attempts_text(record.attempts),
                sum(record.stage_wall_s.values()),
            )  # fmt: skip
            if self.on_cycle is not None:
                self.on_cycle(record, frame, result, seen_poses)

    def _empty_or_unseen(self, record: CycleRecord, frame: Frame, seen: str) -> CycleRecord:
        """No part estimated in the bin (``seen`` says what the camera saw): "bin_empty" when the depth agrees,
        "parts_unseen" when it shows ``min_unseen_area_m2`` of the bin covered (parts the detector does not find, or
        whose estimates land outside the bin)."""
        covered = self.planner.pile_area_m2(frame.depth_m, frame.intrinsics, self.T_base_camera)
        if covered >= self.config.min_unseen_area_m2:
            record.end = "parts_unseen"
            record.plan_summary = f"{seen}, but the depth shows {1e4 * covered:.1f} cm2 of the bin covered"
        else:
            record.end, record.plan_summary = "bin_empty", seen
        return record

    def _all_given_up(self, record: CycleRecord, n_excluded: int) -> CycleRecord:
        record.end, record.n_excluded = "gave_up", n_excluded
        record.plan_summary = (
            f"every part seen ({n_excluded}) is where {self.config.max_failures_per_part} attempts failed already"
        )
        return record

    def _plan(self, poses: Sequence[Any], frame: Frame, record: CycleRecord) -> Any:
        t = time.perf_counter()
        plan = self.planner.plan(poses, self.T_base_camera, frame.depth_m, frame.intrinsics, q_seed=self.robot.q())
        record.stage_wall_s["plan"] = record.stage_wall_s.get("plan", 0.0) + time.perf_counter() - t
        return plan

    def _attempt(self, grasp: Any, record: CycleRecord) -> Attempt:
        attempt = Attempt(grasp.part_index, grasp.obj_id, "picked", "approach", T_base_obj=grasp.T_base_obj.tolist())
        cfg, stage = self.config, "approach"
        timer = _StageTimer(record.stage_wall_s)
        try:
            with timer("approach"):
                opening = self._grasp_opening(grasp)
                if not self._open_to(opening):
                    target = "fully" if opening is None else f"to {1e3 * opening:.1f} mm"
                    return _fail(
                        attempt, "gripper_blocked", stage,
                        f"the fingers did not open {target} (at {self._width_text()}): something "
                        "is stuck between them",
                    )  # fmt: skip
                # Joint move to the lift pose (back out along the approach, above the pile and the bin's rim),
                # then straight lines down the checked approach: a joint move straight to the pre-grasp could
                # sweep the arm through the bin wall.
                self.robot.move_j(grasp.q_lift, cfg.transit_speed_rad_s, cfg.transit_accel_rad_s2)
                self.robot.move_l(grasp.T_base_pregrasp, cfg.transit_linear_speed_m_s, cfg.approach_accel_m_s2)
                self.robot.move_l(grasp.T_base_grasp, cfg.approach_speed_m_s, cfg.approach_accel_m_s2)
            stage = "grasp"
            with timer("grasp"):
                held = self.gripper.close(force_n=cfg.grip_force_n)
            if held is False and not self._fingers_apart():
                self._back_out(grasp, timer)
                return _fail(attempt, "gripper_empty", stage, "the fingers closed without meeting the part")
            stage = "verify"
            with timer("verify"):
                self.robot.move_l(grasp.T_base_lift, cfg.approach_speed_m_s, cfg.approach_accel_m_s2)
                why, width = self._slip_reason(grasp)
            if why:
                self._open_to(None)
                return _fail(attempt, "slipped", stage, why)
            if width is not None and width < grasp.grasp_width_m - cfg.slip_width_tolerance_m:
                attempt.detail = (
                    f"held at {1e3 * width:.1f} mm, not at the planned {1e3 * grasp.grasp_width_m:.1f} mm: the part "
                    "turned in the fingers or its estimate was off"
                )
            stage = "place"
            with timer("place"):
                self.robot.move_j(grasp.q_place, cfg.transit_speed_rad_s, cfg.transit_accel_rad_s2)
                released = self._release(opening)
            attempt.stage = "place"
            if not released:
                return _fail(
                    attempt, "not_released", stage,
                    f"the fingers did not open at the place pose after {cfg.release_tries} tries (at "
                    f"{self._width_text()}): the part is stuck in the gripper",
                )  # fmt: skip
            return attempt
        except MotionRefusedError as exc:
            return _fail(attempt, "motion_refused", stage, str(exc))
        except MotionFailedError as exc:
            if not exc.recoverable:
                raise
            cause = _motion_cause(exc)
            log.warning("attempt on part %d: %s during %s (%s); recovering", grasp.part_index, cause, stage, exc)
            self._recover_and_back_out(float(grasp.T_base_lift[2, 3]))
            return _fail(attempt, cause, stage, str(exc))

    def _nudge(self, poses: Sequence[Any], plan: Any, record: CycleRecord) -> bool:
        """Nothing is safe to pick: nudge a part the planner left for a wall or a neighbour, if the nudger finds a safe
        nudge and the limits allow one. True when the arm moved (``record.end`` "nudged")."""
        cfg = self.config
        if self.nudger is None or self._nudged_at.total >= cfg.max_nudges:
            return False

        def nudged_enough(index: int) -> bool:
            pose = poses[index]
            return self._nudged_at.count(pose.obj_id, self._position_base(pose)) >= cfg.max_nudges_per_part

        timer = _StageTimer(record.stage_wall_s)
        with timer("plan"):
            nudge = self.nudger.plan(poses, self.T_base_camera, plan, self.robot.q(), self.q_observe, nudged_enough)
        if nudge is None:
            return False
        record.end = "nudged"
        record.nudge = {
            "part_index": nudge.part_index, "obj_id": nudge.obj_id, "cause": nudge.cause,
            "tilt_deg": nudge.tilt_deg, "distance_m": nudge.distance_m, "outcome": "done", "detail": "",
        }  # fmt: skip
        self._nudged_at.add(nudge.obj_id, nudge.T_base_obj[:3, 3])
        try:
            with timer("nudge"):
                self.gripper.close(force_n=cfg.grip_force_n)  # the pads together are the paddle
                self.robot.move_j(nudge.q_above, cfg.transit_speed_rad_s, cfg.transit_accel_rad_s2)
                self.robot.move_l(nudge.T_base_press, nudge.speed_m_s, cfg.approach_accel_m_s2)
                self.robot.move_l(nudge.T_base_end, nudge.speed_m_s, cfg.approach_accel_m_s2)
                self.robot.move_l(nudge.T_base_retreat, cfg.approach_speed_m_s, cfg.approach_accel_m_s2)
        except MotionRefusedError as exc:
            record.nudge.update(outcome="motion_refused", detail=str(exc))
        except MotionFailedError as exc:
            if not exc.recoverable:
                raise
            record.nudge.update(outcome=_motion_cause(exc), detail=str(exc))
            log.warning("nudge of part %d: %s (%s); recovering", nudge.part_index, record.nudge["outcome"], exc)
            self._recover_and_back_out(float(nudge.T_base_retreat[2, 3]))
        record.plan_summary = (
            f"nudged part {nudge.part_index} (obj {nudge.obj_id}, {nudge.cause}) {1e3 * nudge.distance_m:.0f} mm "
            f"({record.nudge['outcome']}); {record.plan_summary}"
        )
        self._to_observe()
        return True

    # --- helpers ---------------------------------------------------------------------------------------------
    def _slip_reason(self, grasp: Any) -> tuple[str, float | None]:
        """Why the part is not in the gripper after lifting ("" when it is), and the fingers' last width.

        Fingers closed below the narrowest width the part can be held at (``PickerConfig.hold_any_width``), less
        ``slip_width_tolerance_m`` and never below ``min_held_width_m``, say so at once. Otherwise the part is held
        when the gripper reports an object, or when the fingers rest where they are (no change over
        ``_WIDTH_STEADY_S``): the emulated 2F-85 reads "moving" (no object) much of the time while its stiff pads
        hold a part, from the jitter of the finger speed. Neither within ``slip_settle_s``: the object is lost."""
        cfg = self.config
        narrowest = min(grasp.min_hold_width_m, grasp.grasp_width_m) if cfg.hold_any_width else grasp.grasp_width_m
        lowest = max(narrowest - cfg.slip_width_tolerance_m, cfg.min_held_width_m)
        deadline = time.monotonic() + cfg.slip_settle_s
        steady_since, last_width = time.monotonic(), None
        while True:
            detected = self.gripper.object_detected()
            width = self.gripper.width_m()
            now = time.monotonic()
            if width is not None and width < lowest:
                why = f"the fingers closed to {1e3 * width:.1f} mm, the part is {1e3 * grasp.grasp_width_m:.1f} mm wide"
                if narrowest < grasp.grasp_width_m:
                    why += f" ({1e3 * narrowest:.1f} mm at its narrowest hold)"
                return why, width
            if detected is not False:
                return "", width
            if width is not None and last_width is not None and abs(width - last_width) > _WIDTH_STEADY_M:
                steady_since = now
            last_width = width
            if width is not None and now - steady_since >= _WIDTH_STEADY_S:
                return "", width
            if now > deadline:
                return "the gripper no longer reports an object after lifting", width
            time.sleep(0.02)

    def _back_out(self, grasp: Any, timer: _StageTimer) -> None:
        """Open to the grasp's opening (what the approach was checked with: fully open, a finger may reach a wall)
        and go back out along the approach to the lift (above the rim: the joint move that follows starts where the
        planner checked it)."""
        with timer("grasp"):
            self._open_to(self._grasp_opening(grasp))
            self.robot.move_l(grasp.T_base_lift, self.config.approach_speed_m_s, self.config.approach_accel_m_s2)

    def _recover_and_back_out(self, safe_height_m: float) -> None:
        """After a protective stop or a dropped link the arm is at rest somewhere on the way, perhaps with a finger
        pressed on a wall: hold the fingers where they are, recover, go straight up to ``safe_height_m`` (base z of
        a pose above the bin's rim), and only then let go, before the joint move to the observe pose. Fingers that
        go on pushing stop the arm again as soon as it is unlocked (in the cell bench a finger opening into a wall
        did, twice, and the run needed an operator)."""
        self._hold_fingers()
        self._recover()
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
            self._recover()
        try:
            self.gripper.open()
        except GripperError as exc:
            log.warning("the gripper did not open after recovery (%s)", exc)

    def _hold_fingers(self) -> None:
        """Stop the fingers where they are (commanded to their own width), so they no longer push on anything."""
        try:
            width = self.gripper.width_m() if self.gripper.can_set_width else None
            if width is not None:
                self.gripper.open(width_m=width)
        except GripperError as exc:
            log.warning("could not hold the fingers before recovering (%s)", exc)

    def _recover(self) -> None:
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

    def _open_to(self, width_m: float | None) -> bool:
        """Opens to ``width_m`` (None: fully) and waits until the fingers are there (within ``open_tolerance_m``,
        for up to ``open_timeout_s``): a gripper can report "stopped on something" while a squeezed part still
        holds its fingers. False if they did not get there; True also for a gripper that cannot tell its width."""
        cfg = self.config
        if width_m is None:
            self.gripper.open()
        else:
            self.gripper.open(width_m=width_m)
        target = self._stroke() if width_m is None else width_m
        deadline = time.monotonic() + cfg.open_timeout_s
        while True:
            width = self.gripper.width_m()
            if width is None or not np.isfinite(target) or width >= target - cfg.open_tolerance_m:
                return True
            if time.monotonic() > deadline:
                return False
            time.sleep(0.02)

    def _release(self, width_m: float | None) -> bool:
        """Lets go at the place pose: opens (up to ``release_tries`` times) until the fingers are open."""
        for k in range(self.config.release_tries):
            if self._open_to(width_m):
                return True
            log.warning("the fingers did not open at the place pose (at %s, try %d)", self._width_text(), k + 1)
        return False

    def _width_text(self) -> str:
        width = self.gripper.width_m()
        return "an unknown width" if width is None else f"{1e3 * width:.1f} mm"

    def _count_failure(self, attempt: Attempt) -> None:
        """Adds a failed attempt to its location's count (see ``max_failures_per_part``)."""
        if attempt.outcome in _PART_FAILURES and attempt.T_base_obj is not None:
            self._failed_at.add(attempt.obj_id, np.asarray(attempt.T_base_obj)[:3, 3])

    def _split_given_up(self, poses: Sequence[Any]) -> tuple[list[Any], list[Any]]:
        """``(kept, given_up)``: ``poses`` split by ``_given_up``."""
        kept, given_up = [], []
        for pose in poses:
            (given_up if self._given_up(pose) else kept).append(pose)
        return kept, given_up

    def _given_up(self, pose: Any) -> bool:
        """A part where ``max_failures_per_part`` attempts failed already (same model, within the distance)."""
        return self._failed_at.count(pose.obj_id, self._position_base(pose)) >= self.config.max_failures_per_part

    def _position_base(self, pose: Any) -> np.ndarray:
        """(3,) where a pose (camera frame) puts its part's origin in the base frame."""
        return (self.T_base_camera @ np.asarray(pose.T_camera_object))[:3, 3]

    def _to_observe(self) -> None:
        """The joint move to the observe pose. A protective stop on the way (the arm met a wall or a part leaving the
        bin) is recovered once (``_recover_and_back_out`` to the observe pose's height) and the joint move is made
        again; a second one needs an operator."""
        cfg = self.config
        try:
            if np.max(np.abs(np.asarray(self.robot.q()) - self.q_observe)) > 1e-3:
                self.robot.move_j(self.q_observe, cfg.transit_speed_rad_s, cfg.transit_accel_rad_s2)
        except MotionFailedError as exc:
            if not exc.recoverable or self._observe_height_m is None:
                raise
            log.warning("%s on the way to the observe pose (%s); recovering", _motion_cause(exc), exc)
            self._recover_and_back_out(self._observe_height_m)
            self.robot.move_j(self.q_observe, cfg.transit_speed_rad_s, cfg.transit_accel_rad_s2)
        if self._observe_height_m is None:
            self._observe_height_m = float(np.asarray(self.robot.T_base_tcp())[2, 3])

    def _fingers_apart(self) -> bool:
        """The fingers stopped at least ``min_held_width_m`` apart: something thin is between them."""
        width = self.gripper.width_m()
        return width is not None and width >= self.config.min_held_width_m

    def _grasp_opening(self, grasp: Any) -> float | None:
        """The opening a grasp's approach was checked with, as the gripper is commanded to it (None: a gripper that
        can only open fully)."""
        return min(grasp.opening_width_m, self._stroke()) if self.gripper.can_set_width else None

    def _stroke(self) -> float:
        config = getattr(self.gripper, "config", None)
        return float(getattr(config, "stroke_m", np.inf))

    def _look_after_last_pick(self, poses: Sequence[Any]) -> None:
        """The look after lifting: a part of the picked model still where the picked one was means it is not
        gone (the gripper reported something, but not that part)."""
        last, self._last_picked = self._last_picked, None
        if last is None or last.T_base_obj is None:
            return
        p_was = np.asarray(last.T_base_obj)[:3, 3]
        for pose in poses:
            if pose.obj_id != last.obj_id:
                continue
            p_now = (self.T_base_camera @ np.asarray(pose.T_camera_object))[:3, 3]
            if np.linalg.norm(p_now - p_was) < self.config.still_there_distance_m:
                last.outcome, last.detail = "part_still_in_bin", "the next frame shows the part where it was"
                log.warning("part %d (obj %d) is still in the bin after its pick", last.part_index, last.obj_id)
                self._count_failure(last)
                return


class _LocationCounts:
    """Events per part location: same model, within ``distance_m`` of where the last one at that location was."""

    def __init__(self, distance_m: float) -> None:
        self.distance_m = distance_m
        self._entries: list[list] = []  # [obj_id, position (3,), count]
        self.total = 0

    def add(self, obj_id: int, position: np.ndarray) -> None:
        self.total += 1
        for entry in self._entries:
            if entry[0] == obj_id and np.linalg.norm(entry[1] - position) < self.distance_m:
                entry[1], entry[2] = position, entry[2] + 1
                return
        self._entries.append([obj_id, position, 1])

    def clear(self) -> None:
        self._entries.clear()
        self.total = 0

    def count(self, obj_id: int, position: np.ndarray) -> int:
        """The count of the location ``position`` lies at (the largest, where it lies within two)."""
        return max(
            (n for o, where, n in self._entries if o == obj_id and np.linalg.norm(where - position) < self.distance_m),
            default=0,
        )


class _StageTimer:
    """Adds the wall time of ``with timer(stage):`` blocks to ``totals[stage]``."""

    def __init__(self, totals: dict[str, float]) -> None:
        self.totals = totals
        self._stage = ""
        self._t0 = 0.0

    def __call__(self, stage: str) -> _StageTimer:
        self._stage = stage
        return self

    def __enter__(self) -> None:
        self._t0 = time.perf_counter()

    def __exit__(self, *exc: object) -> None:
        self.totals[self._stage] = self.totals.get(self._stage, 0.0) + time.perf_counter() - self._t0


def _fail(attempt: Attempt, cause: str, stage: str, detail: str) -> Attempt:
    attempt.outcome, attempt.stage, attempt.detail = cause, stage, detail
    return attempt


def _motion_cause(exc: MotionFailedError) -> str:
    if isinstance(exc, ProtectiveStopError):
        return "protective_stop"
    if isinstance(exc, ConnectionLostError):
        return "connection_lost"
    return "motion_failed"


def _attempts_text(attempts: list[Attempt]) -> str:
    return ", ".join(f"part {a.part_index}: {a.outcome}" for a in attempts) or "no attempt"
