"""``PartMemory``: what the pick cycle remembers of earlier cycles, per part location (a model, and a position in the
robot base frame within ``exclusion_distance_m``: a part that moved is a new chance): the failed attempts (after
``max_failures_per_part`` parts there are given up), the nudges (at most ``max_nudges`` per run and
``max_nudges_per_part`` per location), the last pick, checked in the next look (``still_there_distance_m``), and
where the gripper met something on an approach (``touches``, which the next plans keep clear of)."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import Any

import numpy as np

from robot.pick_config import PickerConfig
from robot.pick_protocols import PoseLike
from robot.pick_report import Attempt, Outcome

log = logging.getLogger(__name__)

#: A touch is forgotten once a part is picked this close to where the gripper stopped (m, horizontally): the part
#: picked may have been what it met. About a part's size; ``clear`` forgets every touch.
TOUCH_FORGET_M = 0.05

#: Outcomes that count against a part's location: a dropped connection or a blocked gripper says nothing about the
#: part, and a part dropped on the way to the tray has left that location.
PART_FAILURES = frozenset(Outcome) - {
    Outcome.PICKED, Outcome.CONNECTION_LOST, Outcome.GRIPPER_BLOCKED, Outcome.NOT_RELEASED, Outcome.DROPPED,
}  # fmt: skip


class PartMemory:
    """Failed attempts and nudges per part location, and the last pick. Poses are camera-frame estimates
    (``PoseLike``), mapped to the base frame with ``T_base_camera`` (4x4)."""

    def __init__(self, config: PickerConfig, T_base_camera: np.ndarray) -> None:
        self.config = config
        self.T_base_camera = np.asarray(T_base_camera, dtype=float)
        self._failed_at = _LocationCounts(config.exclusion_distance_m)
        self._nudged_at = _LocationCounts(config.exclusion_distance_m)
        self._last_picked: Attempt | None = None
        self.touches: list[tuple[np.ndarray, float | None]] = []

    def clear(self) -> None:
        """Forgets earlier runs."""
        self._failed_at.clear()
        self._nudged_at.clear()
        self._last_picked = None
        self.touches.clear()

    # --- touches -----------------------------------------------------------------------------------------------
    def add_touch(self, T_base_tcp: np.ndarray, opening_m: float | None) -> None:
        """Where an approach stopped on contact: the TCP pose (4x4, base frame) and the pads' opening (m; None:
        fully open)."""
        self.touches.append((np.array(T_base_tcp, dtype=float), opening_m))

    # --- failures ----------------------------------------------------------------------------------------------
    def count_failure(self, attempt: Attempt) -> None:
        """Adds a failed attempt to its location's count (``PART_FAILURES`` only)."""
        if attempt.outcome in PART_FAILURES and attempt.T_base_obj is not None:
            self._failed_at.add(attempt.obj_id, np.asarray(attempt.T_base_obj)[:3, 3])

    def split_given_up(self, poses: Sequence[PoseLike]) -> tuple[list[Any], list[Any]]:
        """``(kept, given_up)``: ``poses`` split by ``given_up``."""
        kept, given_up = [], []
        for pose in poses:
            (given_up if self.given_up(pose) else kept).append(pose)
        return kept, given_up

    def given_up(self, pose: PoseLike) -> bool:
        """A part where ``max_failures_per_part`` attempts failed already (same model, within the distance)."""
        return self._failed_at.count(pose.obj_id, self.position_base(pose)) >= self.config.max_failures_per_part

    # --- nudges ------------------------------------------------------------------------------------------------
    def may_nudge(self) -> bool:
        """Fewer than ``max_nudges`` nudges so far."""
        return self._nudged_at.total < self.config.max_nudges

    def nudged_enough(self, pose: PoseLike) -> bool:
        """A part whose location was nudged ``max_nudges_per_part`` times already."""
        return self._nudged_at.count(pose.obj_id, self.position_base(pose)) >= self.config.max_nudges_per_part

    def add_nudge(self, obj_id: int, T_base_obj: np.ndarray) -> None:
        self._nudged_at.add(obj_id, np.asarray(T_base_obj)[:3, 3])

    # --- the last pick -----------------------------------------------------------------------------------------
    def remember_pick(self, attempt: Attempt) -> None:
        """The last pick (checked in the next look); the touches near its part are forgotten."""
        self._last_picked = attempt
        if attempt.T_base_obj is not None:
            picked = np.asarray(attempt.T_base_obj)[:2, 3]
            self.touches = [t for t in self.touches if np.linalg.norm(t[0][:2, 3] - picked) >= TOUCH_FORGET_M]

    def look_after_last_pick(self, poses: Sequence[PoseLike]) -> None:
        """The look after lifting: a part of the picked model still where the picked one was means it is not gone
        (the gripper reported something, but not that part): the pick becomes ``PART_STILL_IN_BIN``."""
        last, self._last_picked = self._last_picked, None
        if last is None or last.T_base_obj is None:
            return
        p_was = np.asarray(last.T_base_obj)[:3, 3]
        for pose in poses:
            if pose.obj_id != last.obj_id:
                continue
            if np.linalg.norm(self.position_base(pose) - p_was) < self.config.still_there_distance_m:
                last.outcome, last.detail = Outcome.PART_STILL_IN_BIN, "the next frame shows the part where it was"
                log.warning("part %d (obj %d) is still in the bin after its pick", last.part_index, last.obj_id)
                self.count_failure(last)
                return

    def position_base(self, pose: PoseLike) -> np.ndarray:
        """(3,) where a pose (camera frame) puts its part's origin in the base frame."""
        return (self.T_base_camera @ np.asarray(pose.T_camera_object))[:3, 3]


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
