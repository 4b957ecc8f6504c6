"""The pick cycle as an explicit state machine: ``Picker.cycle`` runs one handler per ``CycleState``, each returning
the next state, and checks every step against ``TRANSITIONS``::

    CAPTURE -> PERCEIVE -> PLAN -> DECIDE -> NEXT_GRASP -> APPROACH -> GRASP -> VERIFY -> PLACE -> ATTEMPT_END
    PERCEIVE -> CAPTURE                        parts seen, every pose refused: look again (``relooks``)
    PLAN -> REFINE -> PLAN | DECIDE            nothing safe: have more parts refined (else the missed ones rescued,
                                               ``_rescue``), plan again
    DECIDE -> NUDGE -> RETREAT | DONE          nothing safe: nudge a part clear of a wall or a neighbour, or stop
    NUDGE -> CAPTURE                           nothing safe or to nudge, poses refused: look again (``relooks``)
    PERCEIVE | DECIDE -> CHECK_EMPTY -> DONE   no part estimated in the bin (none rescued either): "bin_empty" or
                                               "parts_unseen"
    PERCEIVE | REFINE -> GIVE_UP -> DONE       every part seen is where attempts failed too often
    APPROACH | GRASP | VERIFY -> ATTEMPT_END   the attempt failed
    ATTEMPT_END -> DONE | NEXT_GRASP | RETREAT picked | motion refused: the next candidate | look again
    RETREAT -> DONE                            back at the observe pose

A look ahead (``PickerConfig.look_while_placing``): at the place pose, with the part still held, the next cycle's
first frame is taken (the place pose is the observe pose: the camera's view of the bin is clear) and perceived in a
worker thread while the arm lets go; the next CAPTURE takes that frame and PERCEIVE waits for what is left of its
perception. Only a successful place takes one; a failed attempt drops it, and the run waits for it before returning.

Every part is injected (``Picker(robot, gripper, camera, perception, planner, ...)``) through the protocols of
``robot.pick_protocols``, so the same cycle drives the simulated cell (the emulator through ur_rtde) and the real one
(a UR5e, an OAK camera), and unit tests can swap any part for a fake. Records and outcomes are ``robot.pick_report``,
the settings ``robot.pick_config``, the gripper checks ``robot.pick_fingers``, the moves between attempts and the
recovery ``robot.pick_arm``, what is remembered of failures and nudges per part location ``robot.pick_memory``.

A refused motion (``MotionRefusedError``: checked, nothing sent) moves on to the next candidate; any other failed
attempt, a protective stop or a dropped connection (recovered) ends the cycle, and the next cycle looks again (the
pile has changed). The run (``Picker.run``) stops on a cycle that ends it (``STOP_OF_END``), after ``max_cycles``,
after ``max_failed_cycles`` cycles in a row without a pick, or when a stop cannot be released by the cell itself
("needs_operator": nothing more is sent, the cycles so far are kept in the report).

Stopping from outside (``Picker.request_stop``, e.g. from a signal handler; ``robot.pick_stop``): the motion in
flight is decelerated to rest (``robot.stop()``), nothing more is sent to the arm or the gripper (which keeps its
state: a part held stays held), and the run returns "interrupted", its detail saying where it stopped. Whatever ends
a run, every cycle begun is in its report (``Picker.last_report``, also kept when the run raises): one cut short
ends "interrupted", with the step it was in and its attempt in progress.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from perception.camera import Frame
from perception.depth_tare import apply_tare
from robot.pick_arm import Arm, approach_legs, motion_cause
from robot.pick_config import PickerConfig
from robot.pick_fingers import Fingers
from robot.pick_look_ahead import LookAhead
from robot.pick_memory import PartMemory
from robot.pick_protocols import (
    CameraLike,
    GraspLike,
    GripperLike,
    NudgerLike,
    PerceptionLike,
    PerceptionResultLike,
    PlanLike,
    PlannerLike,
    RobotLike,
)
from robot.pick_report import (
    STOP_OF_END,
    Attempt,
    CycleEnd,
    CycleRecord,
    NudgeOutcome,
    Outcome,
    RunReport,
    Stage,
    StageTimer,
    StopReason,
    attempts_text,
    nothing_posed_reason,
)
from robot.pick_states import ATTEMPT_STAGES, TRANSITIONS, CycleState
from robot.pick_stop import GRIPPER_COMMANDS, ROBOT_COMMANDS, ArmStopper, Guarded, StopRequestedError, StopSwitch
from robot.ur_errors import MotionFailedError, MotionRefusedError, RecoveryError
from sygrid.errors import ConfigError

log = logging.getLogger(__name__)


_S = CycleState


@dataclass
class _Cycle:
    """What the steps of one cycle hand on to each other."""

    record: CycleRecord
    timer: StageTimer
    frame: Frame | None = None
    result: PerceptionResultLike | None = None
    seen_poses: list[Any] = field(default_factory=list)  # for ``on_cycle``: the poses the plan was made from
    poses: list[Any] = field(default_factory=list)  # planned from
    excluded: list[Any] = field(default_factory=list)  # given up
    plan: PlanLike | None = None
    empty_reason: str = ""  # what the camera saw, for CHECK_EMPTY
    pending: Future | None = None  # the perception of ``frame`` running in the look-ahead worker
    looks: int = 0  # frames taken again after every pose was refused
    refused_only: bool = False  # for CHECK_EMPTY: the camera saw parts, the verification refused every pose
    rescued: bool = False  # every model was tried on the depth no pose explains (once a cycle)
    candidates: list[GraspLike] = field(default_factory=list)  # grasps still to try, best first
    grasp: GraspLike | None = None
    attempt: Attempt | None = None
    opening: float | None = None  # the opening the grasp's approach was checked with (None: fully open)


class Picker:
    """The pick cycle; see the module docstring.

    Args:
        robot, gripper, camera, perception, planner: the injected parts (see ``robot.pick_protocols``).
        T_base_camera: the camera pose in the robot base frame (hand-eye calibration), 4x4.
        q_observe: joint angles (rad) where the arm waits while the camera looks (clear of its view); the arm
            goes there first and after every failed cycle.
        config: the cycle's settings.
        on_cycle: called with each finished ``CycleRecord``, its frame, the perception result and the poses the
            plan was made from (the result's, or after ``refine_more`` the further refined ones), for pictures.
        nudger: plans nudges when nothing is safe to pick (None: the run stops there).

    ``robot`` and ``gripper`` are the given ones behind ``robot.pick_stop.Guarded`` views (``.target`` is the object
    given): their commands refuse to run once a stop was requested.
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
        self.stop_switch = StopSwitch()
        self.robot = Guarded(robot, self.stop_switch, ROBOT_COMMANDS)
        self.gripper = Guarded(gripper, self.stop_switch, GRIPPER_COMMANDS)
        self.camera = camera
        self.perception, self.planner = perception, planner
        self.T_base_camera = np.asarray(T_base_camera, dtype=float)
        if self.T_base_camera.shape != (4, 4):
            raise ConfigError(f"Picker: T_base_camera must be 4x4, got shape {self.T_base_camera.shape}")
        self.q_observe = np.asarray(q_observe, dtype=float)
        self.config = config or PickerConfig()
        self.on_cycle = on_cycle
        self.nudger = nudger
        self.fingers = Fingers(self.gripper, self.config)
        self.arm = Arm(self.robot, self.fingers, self.config, self.q_observe)
        self.memory = PartMemory(self.config, self.T_base_camera)
        self.n_placed = 0  # parts let go in the tray by this picker: the next one goes to the next place slot
        self.look_ahead = LookAhead()  # the next cycle's first look, taken at the place pose
        self.last_report: RunReport | None = None  # the last run's, also when it raised
        self._steps: dict[CycleState, Callable[[_Cycle], CycleState]] = {
            _S.CAPTURE: self._capture, _S.PERCEIVE: self._perceive, _S.PLAN: self._plan, _S.REFINE: self._refine,
            _S.DECIDE: self._decide, _S.CHECK_EMPTY: self._check_empty, _S.GIVE_UP: self._give_up,
            _S.NUDGE: self._nudge, _S.NEXT_GRASP: self._next_grasp, _S.APPROACH: self._approach,
            _S.GRASP: self._grasp, _S.VERIFY: self._verify, _S.PLACE: self._place,
            _S.ATTEMPT_END: self._attempt_end, _S.RETREAT: self._retreat,
        }  # fmt: skip

    # --- the run ---------------------------------------------------------------------------------------------
    def run(self, max_cycles: int | None = None) -> RunReport:
        """Picks until a cycle ends the run, ``max_cycles`` (default ``config.max_cycles``), too many failed cycles
        in a row, a stop the cell cannot release, or a stop request (``request_stop``). An unexpected error is
        raised on, after ``last_report`` got the cycles so far (``StopReason.ERROR``)."""
        limit = max_cycles or self.config.max_cycles
        cycles: list[CycleRecord] = []
        self.last_report = None
        with ArmStopper(self.stop_switch, lambda: self.robot.target.stop()) as stopper, self.look_ahead.running():
            try:
                return self._run_cycles(cycles, limit)
            except StopRequestedError as exc:
                stopper.acknowledge()
                return self._finish(cycles, StopReason.INTERRUPTED, self._where_stopped(cycles, str(exc)))
            except (RecoveryError, MotionFailedError) as exc:  # a recoverable MotionFailedError never gets here
                log.error("the cell needs an operator: %s", exc)
                return self._finish(cycles, StopReason.NEEDS_OPERATOR, f"{type(exc).__name__}: {exc}")
            except BaseException as exc:  # a forced interrupt (KeyboardInterrupt) or an unexpected error
                reason = StopReason.INTERRUPTED if isinstance(exc, KeyboardInterrupt) else StopReason.ERROR
                self._finish(cycles, reason, f"{type(exc).__name__}: {exc}")
                raise

    def request_stop(self, reason: str) -> None:
        """Asks the run to stop (``reason``: who asked, e.g. "SIGTERM"); safe from any thread and from a signal
        handler. The run's stopper thread decelerates the motion in flight (``robot.stop()``); the cycle raises at
        its next command or step, nothing more is sent, and ``run`` returns "interrupted". A request made before
        ``run`` ends that run before it moves; ``clear_stop`` forgets it."""
        self.stop_switch.request(reason)

    def clear_stop(self) -> None:
        self.stop_switch.clear()

    def _run_cycles(self, cycles: list[CycleRecord], limit: int) -> RunReport:
        """The run's loop; every cycle's record is in ``cycles`` from its start, so one cut short is kept."""
        failed_in_row = 0
        self.stop_switch.check()
        self.arm.to_observe()
        while True:
            if len(cycles) >= limit:
                return self._finish(cycles, StopReason.MAX_CYCLES, f"stopped after {limit} cycle(s)")
            self.stop_switch.check()
            record = CycleRecord(index=len(cycles), sim_time_s=float("nan"))
            cycles.append(record)
            self._run_cycle(record)
            if len(cycles) > 1 and cycles[-2].sim_cycle_s is None:
                cycles[-2].sim_cycle_s = record.sim_time_s - cycles[-2].sim_time_s
            if record.end in STOP_OF_END:
                return self._finish(cycles, STOP_OF_END[record.end], record.plan_summary)
            if record.end != CycleEnd.NUDGED:  # a nudge is neither a pick nor a failure
                failed_in_row = 0 if record.picked else failed_in_row + 1
            if failed_in_row >= self.config.max_failed_cycles:
                why = f"{failed_in_row} cycles in a row without a pick; last: {record.end}"
                return self._finish(cycles, StopReason.TOO_MANY_FAILURES, why)

    def _finish(self, cycles: list[CycleRecord], reason: StopReason, detail: str) -> RunReport:
        report = self.last_report = RunReport(cycles, reason, detail)
        log.log(
            logging.WARNING if reason in (StopReason.INTERRUPTED, StopReason.ERROR) else logging.INFO,
            "pick run stopped (%s): %d picked in %d attempts; %s", reason, report.n_picked, len(report.attempts),
            detail,
        )  # fmt: skip
        return report

    def _where_stopped(self, cycles: list[CycleRecord], reason: str) -> str:
        """Where a stopped run stopped: the cycle and its step (or between cycles), the TCP position, the fingers."""
        last = cycles[-1] if cycles else None
        if last is not None and last.end == CycleEnd.INTERRUPTED:
            where = f"in cycle {last.index} during {last.interrupted_in}"
            attempt = last.attempts[-1] if last.attempts else None
            if attempt is not None and attempt.outcome == Outcome.INTERRUPTED:
                where += f" (attempt on part {attempt.part_index}, obj {attempt.obj_id})"
        else:
            where = f"after cycle {last.index}" if last is not None else "before the first cycle"
        try:
            p = np.asarray(self.robot.T_base_tcp())[:3, 3]
            where += f"; the arm at rest at TCP ({p[0]:.3f}, {p[1]:.3f}, {p[2]:.3f}) m (base frame)"
        except Exception as exc:  # the link may be gone: say so, the report is written all the same
            where += f"; the arm's position is unknown ({type(exc).__name__}: {exc})"
        try:
            where += f"; the gripper left as it was, at {self.fingers.width_text()}"
        except Exception as exc:
            where += f"; the gripper's state is unknown ({type(exc).__name__})"
        return f"stop requested ({reason}): stopped {where}"

    # --- one cycle: the state machine -------------------------------------------------------------------------
    def cycle(self, index: int = 0) -> CycleRecord:
        """Runs the steps from ``CAPTURE`` to ``DONE``; returns the record (``end``: see ``CycleEnd``). Raises
        ``StopRequestedError`` after a stop request, and what the cell cannot recover from."""
        record = CycleRecord(index=index, sim_time_s=float("nan"))
        self._run_cycle(record)
        return record

    def _run_cycle(self, record: CycleRecord) -> None:
        """Fills ``record``; on any exception it is marked interrupted (``CycleRecord.mark_interrupted``) first."""
        c = _Cycle(record, StageTimer(record.stage_wall_s))
        state = _S.CAPTURE
        try:
            while state is not _S.DONE:
                after = self._step(state, c)
                if after not in TRANSITIONS[state]:
                    raise RuntimeError(f"Picker: no transition from {state.name} to {after.name}")
                if after is not _S.DONE:
                    self.stop_switch.check()  # a request during a step without commands (perception, planning)
                state = after
        except BaseException as exc:
            why = f"stop requested ({exc})" if isinstance(exc, StopRequestedError) else f"{type(exc).__name__}: {exc}"
            record.mark_interrupted(state.value, c.attempt, why)
            raise
        finally:
            if c.result is not None:
                log.info(
                    "cycle %d: %s (%s) in %.2f s wall", record.index, record.end, attempts_text(record.attempts),
                    sum(record.stage_wall_s.values()),
                )  # fmt: skip
                if self.on_cycle is not None:
                    self.on_cycle(record, c.frame, c.result, c.seen_poses)

    def _step(self, state: CycleState, c: _Cycle) -> CycleState:
        """One step. In an attempt's steps the attempt's stage is the step's, and a refused motion or a recoverable
        motion failure ends the attempt (after recovering and backing out to the lift)."""
        if state not in ATTEMPT_STAGES:
            return self._steps[state](c)
        c.attempt.stage = ATTEMPT_STAGES[state]
        try:
            return self._steps[state](c)
        except MotionRefusedError as exc:
            return _fail(c.attempt, Outcome.MOTION_REFUSED, str(exc))
        except MotionFailedError as exc:
            if not exc.recoverable:
                raise
            cause = motion_cause(exc)
            log.warning(
                "attempt on part %d: %s during %s (%s); recovering", c.grasp.part_index, cause, state.value, exc
            )
            after = _fail(c.attempt, cause, str(exc))  # recorded first: the recovery may end the run
            self.arm.recover_and_back_out(float(c.grasp.T_base_lift[2, 3]))
            return after

    def _capture(self, c: _Cycle) -> CycleState:
        """A frame; the cycle's first look is the one taken at the last place pose where there is one."""
        ahead = self.look_ahead.take()  # only a pick takes one, and the cycle after it starts here
        if ahead is not None:
            (c.frame, c.pending), c.record.looked_ahead = ahead, True
        else:
            with c.timer(Stage.CAPTURE):
                c.frame = self.camera.capture()
        c.record.sim_time_s = float(c.frame.timestamp_s)
        return _S.PERCEIVE

    def _perceive(self, c: _Cycle) -> CycleState:
        record = c.record
        with c.timer(Stage.PERCEIVE):
            pending, c.pending = c.pending, None
            c.result = pending.result() if pending is not None else self.perception.run(c.frame)
        tare = getattr(c.result, "depth_tare", None)
        if tare is not None and tare.applied:
            # Plan on the depth the poses were fitted in: with a stereo offset left in, a part's own points lie
            # millimetres off its estimated surface and read as something lying on it (or a gap under it).
            c.frame = replace(c.frame, depth_m=apply_tare(c.frame.depth_m, tare))
        record.n_detections, record.n_poses = len(c.result.detections), len(c.result.poses)
        record.perception_ms = {k: float(v) for k, v in c.result.timings_ms.items()}
        self.memory.look_after_last_pick(c.result.poses)
        c.seen_poses = c.result.poses
        if not c.result.poses:
            c.refused_only = bool(getattr(c.result, "refused", None))
            if c.refused_only and c.looks < self.config.relooks:  # stereo noise and masks change between frames
                c.looks += 1
                log.info("cycle %d: every pose refused; looking again (%d of %d)", record.index, c.looks,
                         self.config.relooks)  # fmt: skip
                return _S.CAPTURE
            more = self._rescue(c)
            if more is None:
                c.empty_reason = nothing_posed_reason(c.result)
                return _S.CHECK_EMPTY
            c.seen_poses = more
        c.poses, c.excluded = self.memory.split_given_up(c.seen_poses)
        return _S.PLAN if c.poses else _S.GIVE_UP

    def _rescue(self, c: _Cycle) -> list[Any] | None:
        """Once a cycle, when the look would leave parts in the bin: the seen poses with the parts the perception
        finds by trying every model on the depth they do not explain (``PerceptionLike.rescue``); None when it
        finds none."""
        if c.rescued:
            return None
        c.rescued = True
        with c.timer(Stage.PERCEIVE):
            more = self.perception.rescue(list(c.seen_poses), c.frame)
        if more is not None:
            c.record.n_rescued = len(more) - len(c.seen_poses)
            log.info("cycle %d: %d part(s) posed on depth no detection explained", c.record.index, c.record.n_rescued)
        return more

    def _plan(self, c: _Cycle) -> CycleState:
        frame = c.frame
        with c.timer(Stage.PLAN):
            c.plan = self.planner.plan(
                c.poses, self.T_base_camera, frame.depth_m, frame.intrinsics, self.robot.q(), self.n_placed,
                touches=self.memory.touches,
            )  # fmt: skip
        return _S.REFINE if c.plan.nothing_safe else _S.DECIDE

    def _refine(self, c: _Cycle) -> CycleState:
        """Nothing safe among the refined parts: refine the next ones the perception skipped, else look for parts the
        detector's classes missed (``_rescue``), and plan again."""
        with c.timer(Stage.PERCEIVE):
            more = self.perception.refine_more(c.poses, c.frame)
        if more is None:
            more = self._rescue(c)
            if more is None:
                return _S.DECIDE
            more = [p for p in more if not any(p is e for e in c.excluded)]
        c.seen_poses = [*more, *c.excluded]
        # a skipped part's RGB estimate can lie centimetres from where its refined pose puts it: where attempts
        # failed is checked again on the refined poses
        c.poses, given_up = self.memory.split_given_up(more)
        c.excluded += given_up
        return _S.PLAN if c.poses else _S.GIVE_UP

    def _decide(self, c: _Cycle) -> CycleState:
        record, plan = c.record, c.plan
        record.n_excluded = len(c.excluded)
        record.n_planned, record.plan_summary = len(plan.grasps), plan.summary()
        if record.n_excluded:
            record.plan_summary += f" ({record.n_excluded} part(s) given up after repeated failures)"
        if plan.nothing_safe:
            if plan.n_in_bin == 0:  # the camera sees parts, but none in the bin
                c.empty_reason = f"no part estimated in the bin ({len(c.poses)} seen outside it); {record.plan_summary}"
                return _S.CHECK_EMPTY
            return _S.NUDGE
        record.end = CycleEnd.FAILED  # until an attempt picks
        c.candidates = list(plan.grasps[: self.config.max_attempts_per_cycle])
        return _S.NEXT_GRASP

    def _check_empty(self, c: _Cycle) -> CycleState:
        """No part estimated in the bin (``empty_reason`` says what the camera saw): "bin_empty" when the depth
        agrees, "parts_unseen" when it shows ``min_unseen_area_m2`` of the bin covered (parts the detector does not
        find, or whose estimates land outside the bin) or when the camera saw parts whose every pose the
        verification refused (a small part's depth may show less than that)."""
        record = c.record
        if c.refused_only:
            record.end, record.plan_summary = CycleEnd.PARTS_UNSEEN, c.empty_reason
            return _S.DONE
        covered = self.planner.pile_area_m2(c.frame.depth_m, c.frame.intrinsics, self.T_base_camera)
        if covered >= self.config.min_unseen_area_m2:
            record.end = CycleEnd.PARTS_UNSEEN
            record.plan_summary = f"{c.empty_reason}, but the depth shows {1e4 * covered:.1f} cm2 of the bin covered"
        else:
            record.end, record.plan_summary = CycleEnd.BIN_EMPTY, c.empty_reason
        return _S.DONE

    def _give_up(self, c: _Cycle) -> CycleState:
        record = c.record
        record.end, record.n_excluded = CycleEnd.GAVE_UP, len(c.excluded)
        record.plan_summary = (
            f"every part seen ({record.n_excluded}) is where {self.config.max_failures_per_part} attempts failed "
            "already"
        )
        return _S.DONE

    def _nudge(self, c: _Cycle) -> CycleState:
        """Nothing is safe to pick: nudge a part the planner left for a wall or a neighbour, if the nudger finds a safe
        nudge and the limits allow one (``end`` "nudged", then back to the observe pose); else "nothing_safe"."""
        record, poses = c.record, c.poses
        if self.nudger is None or not self.memory.may_nudge():
            return self._nothing_safe(c)

        def nudged_enough(index: int) -> bool:
            return self.memory.nudged_enough(poses[index])

        with c.timer(Stage.PLAN):
            nudge = self.nudger.plan(poses, self.T_base_camera, c.plan, self.robot.q(), self.q_observe, nudged_enough)
        if nudge is None:
            return self._nothing_safe(c)
        record.end = CycleEnd.NUDGED
        record.nudge = {
            "part_index": nudge.part_index, "obj_id": nudge.obj_id, "cause": nudge.cause,
            "tilt_deg": nudge.tilt_deg, "distance_m": nudge.distance_m, "outcome": NudgeOutcome.DONE, "detail": "",
        }  # fmt: skip
        self.memory.add_nudge(nudge.obj_id, nudge.T_base_obj)
        outcome, detail = self.arm.nudge(nudge, c.timer)
        record.nudge.update(outcome=outcome, detail=detail)
        record.plan_summary = (
            f"nudged part {nudge.part_index} (obj {nudge.obj_id}, {nudge.cause}) {1e3 * nudge.distance_m:.0f} mm "
            f"({record.nudge['outcome']}); {record.plan_summary}"
        )
        return _S.RETREAT

    def _nothing_safe(self, c: _Cycle) -> CycleState:
        """Nothing safe to pick, nothing to nudge: where this look refused poses, look again (``relooks``: a new
        frame's stereo noise and masks may confirm them, and one of them be safe), else "nothing_safe"."""
        refused = len(getattr(c.result, "refused", None) or ())
        if refused and c.looks < self.config.relooks:
            c.looks += 1
            log.info("cycle %d: nothing safe, %d pose(s) refused; looking again (%d of %d)", c.record.index, refused,
                     c.looks, self.config.relooks)  # fmt: skip
            return _S.CAPTURE
        c.record.end = CycleEnd.NOTHING_SAFE
        return _S.DONE

    def _next_grasp(self, c: _Cycle) -> CycleState:
        grasp = c.grasp = c.candidates.pop(0)
        # "picked" unless a step records a failure
        c.attempt = Attempt(
            grasp.part_index, grasp.obj_id, Outcome.PICKED, Stage.APPROACH, T_base_obj=grasp.T_base_obj.tolist()
        )
        return _S.APPROACH

    def _approach(self, c: _Cycle) -> CycleState:
        """Open to the grasp's opening and check that the fingers got there (else ``gripper_blocked``), joint move to
        the lift pose, straight lines to the pre-grasp and, guarded, to the grasp (its last stretch slower); a guard
        that trips ends the attempt ``contact``, backed out to the lift."""
        cfg, grasp = self.config, c.grasp
        with c.timer(Stage.APPROACH):
            c.opening = self.fingers.grasp_opening(grasp)
            if not self.fingers.open_to(c.opening):
                target = "fully" if c.opening is None else f"to {1e3 * c.opening:.1f} mm"
                return _fail(
                    c.attempt, Outcome.GRIPPER_BLOCKED,
                    f"the fingers did not open {target} (at {self.fingers.width_text()}): something is stuck between "
                    "them",
                )  # fmt: skip
            # Joint move to the lift pose (back out along the approach, above the pile and the bin's rim), then
            # straight lines down the checked approach: a joint move straight to the pre-grasp could sweep the arm
            # through the bin wall.
            self.robot.move_j(grasp.q_lift, cfg.transit_speed_rad_s, cfg.transit_accel_rad_s2)
            self.robot.move_l(grasp.T_base_pregrasp, cfg.transit_linear_speed_m_s, cfg.approach_accel_m_s2)
            legs = approach_legs(grasp, cfg)
            for k, (T_target, speed) in enumerate(legs):
                detect = cfg.final_approach_contact_detection and k == len(legs) - 1
                down = self.robot.move_l(
                    T_target, speed, cfg.approach_accel_m_s2, cfg.approach_max_force_n, stop_on_contact=detect
                )
                if down.contact_force_n is not None:
                    break
            else:
                return _S.GRASP
            # a finger met something the plan did not expect: remember where (the next plans keep clear of it), and
            # back out along the approach, fingers still open
            self.memory.add_touch(down.T_base_tcp, c.opening)
            self.robot.move_l(grasp.T_base_lift, cfg.approach_speed_m_s, cfg.approach_accel_m_s2)
        short = float(np.linalg.norm(down.T_base_tcp[:3, 3] - grasp.T_base_grasp[:3, 3]))
        guard = cfg.approach_max_force_n
        how = (
            f"TCP force {down.contact_force_n:.0f} N, above the approach's {guard:g} N guard"
            if guard is not None and down.contact_force_n > guard
            else "the controller's contact detection"
        )
        return _fail(
            c.attempt, Outcome.CONTACT,
            f"the fingers met something {1e3 * short:.0f} mm short of the grasp ({how}): stopped and backed out",
        )  # fmt: skip

    def _grasp(self, c: _Cycle) -> CycleState:
        """Close: held when the gripper detects the object or the fingers stopped at least ``min_held_width_m``
        apart; else ``gripper_empty``, and the fingers open and the arm backs out along the approach to the lift."""
        cfg, grasp = self.config, c.grasp
        with c.timer(Stage.GRASP):
            held = self.gripper.close(force_n=cfg.grip_force_n)
        if held is not False or self.fingers.apart():
            return _S.VERIFY
        # closed on air: open to the opening the approach was checked with (fully open, a finger may reach a wall)
        # and go back out along the approach to the lift (above the rim, where the planner checked the joint move
        # that follows)
        with c.timer(Stage.GRASP):
            self.fingers.open_to(self.fingers.grasp_opening(grasp))
            self.robot.move_l(grasp.T_base_lift, cfg.approach_speed_m_s, cfg.approach_accel_m_s2)
        return _fail(c.attempt, Outcome.GRIPPER_EMPTY, "the fingers closed without meeting the part")

    def _verify(self, c: _Cycle) -> CycleState:
        """Straight line back out to the lift; ``Fingers.slip_reason`` says whether the part is still held (else
        ``slipped``). A part held at another of its widths than the planned one is placed, with a note."""
        cfg, grasp = self.config, c.grasp
        with c.timer(Stage.VERIFY):
            self.robot.move_l(grasp.T_base_lift, cfg.approach_speed_m_s, cfg.approach_accel_m_s2)
            why, width = self.fingers.slip_reason(grasp)
        if why:
            self.fingers.open_to(None)
            return _fail(c.attempt, Outcome.SLIPPED, why)
        if width is not None and width < grasp.grasp_width_m - cfg.slip_width_tolerance_m:
            c.attempt.detail = (
                f"held at {1e3 * width:.1f} mm, not at the planned {1e3 * grasp.grasp_width_m:.1f} mm: the part "
                "turned in the fingers or its estimate was off"
            )
        return _S.PLACE

    def _place(self, c: _Cycle) -> CycleState:
        """Joint move to the place pose; a part no longer in the fingers there (``Fingers.slip_reason``) was lost on
        the way (``dropped``: it lies somewhere between the bin and the tray). Else let go, lowered first
        (``Arm.let_go``; fingers that do not open: ``not_released``, the run stops "gripper_blocked"). Whether the
        part left the bin is the next look's (``PartMemory.look_after_last_pick``)."""
        cfg = self.config
        with c.timer(Stage.PLACE):
            self.robot.move_j(c.grasp.q_place, cfg.transit_speed_rad_s, cfg.transit_accel_rad_s2)
            lost, _ = self.fingers.slip_reason(c.grasp)
            if not lost and cfg.look_while_placing:  # the observe pose: the camera's view of the bin is clear
                self.look_ahead.start(self.camera.capture, self.perception.run)
            released = self.fingers.release(c.opening) if lost else self.arm.let_go(c.grasp.T_base_place, c.opening)
        if released and lost:
            return _fail(c.attempt, Outcome.DROPPED, f"the part was lost on the way to the place pose: {lost}")
        if released:
            self.n_placed += 1
            return _S.ATTEMPT_END
        return _fail(
            c.attempt, Outcome.NOT_RELEASED,
            f"the fingers did not open at the place pose after {cfg.release_tries} tries (at "
            f"{self.fingers.width_text()}): the part is stuck in the gripper",
        )  # fmt: skip

    def _attempt_end(self, c: _Cycle) -> CycleState:
        """Records the attempt: a pick ends the cycle; a blocked gripper ends the run; a refused motion moves on to
        the next candidate; anything else (something moved or failed) looks again."""
        record, attempt = c.record, c.attempt
        record.attempts.append(attempt)
        if attempt.outcome == Outcome.PICKED:
            record.end = CycleEnd.PICKED
            self.memory.remember_pick(attempt)
            return _S.DONE
        self.memory.count_failure(attempt)
        self.look_ahead.drop()  # a part not let go may hang in the next look's way; the cycle looks again
        if attempt.outcome in (Outcome.GRIPPER_BLOCKED, Outcome.NOT_RELEASED):
            record.end, record.plan_summary = CycleEnd.GRIPPER_BLOCKED, attempt.detail
            return _S.RETREAT
        if attempt.outcome == Outcome.MOTION_REFUSED and c.candidates:
            return _S.NEXT_GRASP
        return _S.RETREAT

    def _retreat(self, c: _Cycle) -> CycleState:
        self.arm.to_observe()
        return _S.DONE


def _fail(attempt: Attempt, cause: Outcome, detail: str) -> CycleState:
    """Records a failed attempt (its stage is the step's); the attempt ends."""
    attempt.outcome, attempt.detail = cause, detail
    return _S.ATTEMPT_END
