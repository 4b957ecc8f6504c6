"""What a pick run records: the outcomes (string-valued enums), one record per attempt and per cycle, the run's
report with its JSON form, and the texts the cycle's log and summary are written with.

The enums are ``str`` subclasses whose members print, format and compare as their values (``Outcome.PICKED ==
"picked"``), so logs, the JSON report (``RunReport.to_json``) and the benchmark's readers see the plain strings.

Times: ``stage_wall_s`` holds wall seconds per ``Stage``; ``sim_time_s`` is the camera's timestamp at capture
(simulated seconds in the simulated cell, the device clock on hardware), so a cycle's robot time is the difference
between two captures (``CycleRecord.sim_cycle_s``).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from enum import Enum, StrEnum
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from robot.pick_protocols import PerceptionResultLike


class Stage(StrEnum):
    """The stages a cycle's wall time is split into (``CycleRecord.stage_wall_s``); an attempt ends in one of
    ``APPROACH``, ``GRASP``, ``VERIFY``, ``PLACE``."""

    CAPTURE = "capture"
    PERCEIVE = "perceive"
    PLAN = "plan"
    APPROACH = "approach"
    GRASP = "grasp"
    VERIFY = "verify"
    PLACE = "place"
    NUDGE = "nudge"


class Outcome(StrEnum):
    """How one attempt (one planned grasp tried) ended: ``PICKED`` or a failure cause."""

    PICKED = "picked"
    MOTION_REFUSED = "motion_refused"  # checked and refused, nothing sent: next candidate
    GRIPPER_EMPTY = "gripper_empty"  # closed on air (no object detected, the fingers closed)
    SLIPPED = "slipped"  # lost the part while lifting
    DROPPED = "dropped"  # held after lifting, gone at the place pose: lost on the way there
    CONTACT = "contact"  # the guarded approach met something before the grasp: stopped and backed out
    PROTECTIVE_STOP = "protective_stop"
    CONNECTION_LOST = "connection_lost"
    MOTION_FAILED = "motion_failed"  # another recoverable motion failure (program stopped, timeout)
    PART_STILL_IN_BIN = "part_still_in_bin"  # placed "something", but the next look shows the part where it was
    GRIPPER_BLOCKED = "gripper_blocked"  # the fingers did not open to the grasp's opening: nothing sent down
    NOT_RELEASED = "not_released"  # the fingers did not open at the place pose: something is stuck in them
    INTERRUPTED = "interrupted"  # the run was stopped during the attempt (the gripper kept its state)


class NudgeOutcome(StrEnum):
    """How a nudge ended (``CycleRecord.nudge["outcome"]``)."""

    DONE = "done"
    MOTION_REFUSED = "motion_refused"
    PROTECTIVE_STOP = "protective_stop"
    CONNECTION_LOST = "connection_lost"
    MOTION_FAILED = "motion_failed"
    NO_CONTACT = "no_contact"  # the force-limited press met nothing within its travel: the part is not there


class StopReason(StrEnum):
    """Why a run stopped (``RunReport.stop_reason``)."""

    BIN_EMPTY = "bin_empty"
    PARTS_UNSEEN = "parts_unseen"  # no part estimated in the bin, but the depth or the detector shows something there
    NOTHING_SAFE = "nothing_safe"  # no safe grasp and no nudge left (the planner's reasons in the detail)
    GAVE_UP = "gave_up"  # every part left is where too many attempts failed
    GRIPPER_BLOCKED = "gripper_blocked"  # the fingers cannot be freed
    MAX_CYCLES = "max_cycles"
    TOO_MANY_FAILURES = "too_many_failures"  # too many cycles in a row without a pick
    NEEDS_OPERATOR = "needs_operator"  # a stop the cell cannot release itself (emergency stop, arm pinned)
    INTERRUPTED = "interrupted"  # a stop was requested (a signal, the cell's process died): the detail says where
    ERROR = "error"  # an unexpected error ended the run (raised on to the caller; its type and message in the detail)


class CycleEnd(StrEnum):
    """How one cycle ended (``CycleRecord.end``): a pick, a failed or a nudge cycle (the run goes on), one that
    ends the run (the same string as its ``StopReason``, see ``STOP_OF_END``), or one the run's end cut short
    (``INTERRUPTED``: a stop request, an error, or a stop the cell cannot release; ``CycleRecord.interrupted_in``
    names its step)."""

    PICKED = "picked"
    FAILED = "failed"
    NUDGED = "nudged"
    INTERRUPTED = "interrupted"
    BIN_EMPTY = "bin_empty"
    PARTS_UNSEEN = "parts_unseen"
    NOTHING_SAFE = "nothing_safe"
    GAVE_UP = "gave_up"
    GRIPPER_BLOCKED = "gripper_blocked"


#: The cycle ends that stop the run, and the run's stop reason for each.
STOP_OF_END: dict[CycleEnd, StopReason] = {
    CycleEnd.BIN_EMPTY: StopReason.BIN_EMPTY,
    CycleEnd.PARTS_UNSEEN: StopReason.PARTS_UNSEEN,
    CycleEnd.NOTHING_SAFE: StopReason.NOTHING_SAFE,
    CycleEnd.GAVE_UP: StopReason.GAVE_UP,
    CycleEnd.GRIPPER_BLOCKED: StopReason.GRIPPER_BLOCKED,
}


@dataclass
class Attempt:
    """One planned grasp tried: which part, how it ended, in which stage, and the error message or the note (a
    part held at another width than planned) where there was one."""

    part_index: int
    obj_id: int
    outcome: Outcome
    stage: Stage
    detail: str = ""
    T_base_obj: list | None = None  # where the part was estimated (for the next look and the report)


@dataclass
class CycleRecord:
    """One cycle: wall seconds per stage, the camera's time at capture, what was seen and planned, the attempts.

    ``end`` is None until the cycle has ended; a string given for it is read as a ``CycleEnd``."""

    index: int
    sim_time_s: float
    stage_wall_s: dict[Stage, float] = field(default_factory=lambda: dict.fromkeys(Stage, 0.0))
    n_detections: int = 0
    n_poses: int = 0
    n_planned: int = 0
    n_excluded: int = 0  # parts left out of planning after repeated failures at their location
    n_rescued: int = 0  # parts posed on depth that no detection explained (``PerceptionLike.rescue``)
    perception_ms: dict[str, float] = field(default_factory=dict)
    # the first look was taken at the previous cycle's place pose and perceived while the arm let go
    # (``PickerConfig.look_while_placing``): ``stage_wall_s`` "perceive" is then only the wait for it
    looked_ahead: bool = False
    plan_summary: str = ""
    attempts: list[Attempt] = field(default_factory=list)
    nudge: dict | None = None  # the nudge of a "nudged" cycle: part, cause, tilt, distance, outcome, detail
    end: CycleEnd | None = None
    sim_cycle_s: float | None = None  # filled when the next capture's time is known
    interrupted_in: str = ""  # an interrupted cycle's step, running or just finished (a ``CycleState`` value)

    def __post_init__(self) -> None:
        if self.end is not None:
            self.end = CycleEnd(self.end)

    @property
    def picked(self) -> bool:
        return any(a.outcome == Outcome.PICKED for a in self.attempts)

    def mark_interrupted(self, step: str, attempt: Attempt | None, why: str) -> None:
        """Cut short in ``step`` (a ``CycleState`` value) for ``why``: ``end`` "interrupted"; the attempt in progress
        joins the record, as "interrupted" unless a failure was recorded for it already (e.g. the connection lost
        before a recovery that failed)."""
        self.end, self.interrupted_in = CycleEnd.INTERRUPTED, step
        if attempt is None or any(a is attempt for a in self.attempts):
            return
        if attempt.outcome == Outcome.PICKED:  # the placeholder: nothing recorded yet
            attempt.outcome, attempt.detail = Outcome.INTERRUPTED, f"{why} during {step}"
        else:
            attempt.detail = f"{attempt.detail}; then {why}"
        self.attempts.append(attempt)


@dataclass
class RunReport:
    """A whole run: the cycles, why it stopped and the details (e.g. the planner's reasons)."""

    cycles: list[CycleRecord]
    stop_reason: StopReason
    stop_detail: str = ""

    @property
    def attempts(self) -> list[Attempt]:
        return [a for c in self.cycles for a in c.attempts]

    @property
    def n_picked(self) -> int:
        return sum(a.outcome == Outcome.PICKED for a in self.attempts)

    @property
    def success_rate(self) -> float:
        """Picks over attempts that sent motion and ended (refused candidates moved nothing, an interrupted attempt
        did not end: neither counts)."""
        tried = [a for a in self.attempts if a.outcome not in (Outcome.MOTION_REFUSED, Outcome.INTERRUPTED)]
        return self.n_picked / len(tried) if tried else float("nan")

    @property
    def n_nudges(self) -> int:
        return sum(c.nudge is not None for c in self.cycles)

    def failures_by_cause(self) -> dict[str, int]:
        """Failed attempts per ``Outcome`` value (an interrupted attempt is not a failure)."""
        counts: dict[str, int] = {}
        for a in self.attempts:
            if a.outcome not in (Outcome.PICKED, Outcome.INTERRUPTED):
                counts[a.outcome.value] = counts.get(a.outcome.value, 0) + 1
        return counts

    def sim_cycle_times_s(self) -> list[float]:
        """Robot time of the cycles that picked a part (camera time from their capture to the next one)."""
        return [c.sim_cycle_s for c in self.cycles if c.picked and c.sim_cycle_s is not None]

    def to_json(self) -> dict:
        """The report as plain JSON data (the enums as their strings)."""
        return _plain(
            {
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
        )


class StageTimer:
    """Adds the wall time of ``with timer(stage):`` blocks to ``totals[stage]``."""

    def __init__(self, totals: dict[Stage, float]) -> None:
        self.totals = totals
        self._stage = Stage.CAPTURE
        self._t0 = 0.0

    def __call__(self, stage: Stage) -> StageTimer:
        self._stage = stage
        return self

    def __enter__(self) -> None:
        self._t0 = time.perf_counter()

    def __exit__(self, *exc: object) -> None:
        self.totals[self._stage] = self.totals.get(self._stage, 0.0) + time.perf_counter() - self._t0


def _plain(value: Any) -> Any:
    """``value`` with every enum member replaced by its value, in dicts (keys too) and lists."""
    if isinstance(value, Enum):
        return value.value
    if isinstance(value, dict):
        return {_plain(k): _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    return value


def nothing_posed_reason(result: PerceptionResultLike) -> str:
    """What the camera saw when perception gave no pose to pick, for the cycle's summary: no detections, detections
    whose every pose the verification refused (``result.refused``, where the perception verifies), or detections it
    could not pose (masks too small, outside the bin's region, an unknown class)."""
    n_detections = len(result.detections)
    if n_detections == 0:
        return "the camera sees no parts (no detections)"
    refused = list(getattr(result, "refused", None) or [])
    if refused:
        best = max(p.score for p in refused)
        return (
            f"the camera sees {n_detections} part(s) but the verification refused every pose "
            f"({len(refused)} refused, best confidence {best:.2f})"
        )
    return f"the camera sees {n_detections} part(s) but none could be posed"


def attempts_text(attempts: list[Attempt]) -> str:
    """A cycle's attempts for its log line: "part 2: picked, part 0: slipped" ("no attempt" for none)."""
    return ", ".join(f"part {a.part_index}: {a.outcome}" for a in attempts) or "no attempt"
