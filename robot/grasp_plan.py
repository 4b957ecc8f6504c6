"""What the grasp planner answers: the parts it plans for (``PartEstimate``), the picks (``PlannedGrasp``), a report
per part (``PartReport``) and the whole ``GraspPlan``; and the causes a part or candidate is refused for
(``REJECTION_CAUSES``)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from sygrid.transforms import is_rigid

#: Why a part or a grasp candidate was not planned, in the order the checks run.
REJECTION_CAUSES = (
    "no_model",
    "outside_bin",
    "low_confidence",
    "unrefined",
    "no_candidates",
    "covered",
    "approach_angle",
    "collision_floor",
    "collision_bin",
    "collision_parts",
    "unreachable",
    "singular",
    "collision_transit",
)


def main_cause(rejections: dict[str, int]) -> str:
    """The cause that stopped the candidates that got furthest (the last check any candidate failed): for a part
    whose candidates mostly miss the approach cone, that says why the ones inside the cone were not planned."""
    seen = [c for c in REJECTION_CAUSES if rejections.get(c, 0)]
    return seen[-1] if seen else "no_candidates"


@dataclass(frozen=True, eq=False)
class PartEstimate:
    """A part to plan for: its object id, pose in the robot base frame, pose confidence in [0, 1], and whether
    depth refinement confirmed the pose (None: no refinement was run, e.g. ground truth or an RGB-only cell)."""

    obj_id: int
    T_base_obj: np.ndarray
    score: float = 1.0
    refined: bool | None = None

    def __post_init__(self) -> None:
        if not is_rigid(self.T_base_obj, atol=1e-4):
            raise ValueError(
                f"PartEstimate.T_base_obj must be a 4x4 rigid transform, got {np.asarray(self.T_base_obj).tolist()}"
            )


@dataclass(frozen=True, eq=False)
class PlannedGrasp:
    """One safe pick. Poses are TCP poses ``T_base_tcp`` (4x4, metres), joint solutions ``q_*`` (6,) radians.

    part_index: index of the part in the planner's input. opening_width_m: open the gripper to this before it
    reaches the pre-grasp (the approach was checked with the fingers at this opening: fully open they may hit the
    bin or a neighbour). grasp_width_m: the part's width between the pads (the gripper should stop about there when it
    closes on the part). min_hold_width_m: the narrowest of the part's candidate widths: a part that turns in the
    closing fingers, or whose estimate was off, is held at another of its widths, not lost. backoff_m: how far the
    grasp was moved back along the approach from the candidate to clear the floor or neighbours. engagement_m: the
    length of pad that holds the part. clearance_m: distance from the open fingers (at the grasp) to the nearest
    obstacle (capped at the saturation). score_terms: the score's terms.
    """

    part_index: int
    obj_id: int
    score: float
    T_base_obj: np.ndarray
    T_base_pregrasp: np.ndarray
    T_base_grasp: np.ndarray
    T_base_lift: np.ndarray
    T_base_place: np.ndarray
    q_pregrasp: np.ndarray
    q_grasp: np.ndarray
    q_lift: np.ndarray
    q_place: np.ndarray
    opening_width_m: float
    grasp_width_m: float
    min_hold_width_m: float
    approach_angle_deg: float
    backoff_m: float
    engagement_m: float
    clearance_m: float
    pose_score: float
    score_terms: dict[str, float]

    @property
    def waypoints(self) -> tuple[tuple[str, np.ndarray], ...]:
        """``(name, T_base_tcp)`` in the order the robot visits them: pre_grasp, grasp, lift, place."""
        return (
            ("pre_grasp", self.T_base_pregrasp),
            ("grasp", self.T_base_grasp),
            ("lift", self.T_base_lift),
            ("place", self.T_base_place),
        )

    @property
    def joint_waypoints(self) -> tuple[tuple[str, np.ndarray], ...]:
        """``(name, q)`` for the same waypoints."""
        return (
            ("pre_grasp", self.q_pregrasp),
            ("grasp", self.q_grasp),
            ("lift", self.q_lift),
            ("place", self.q_place),
        )


@dataclass(frozen=True, eq=False)
class PartReport:
    """What the planner made of one part: ``status`` is ``"planned"``, ``"not_planned"`` (``max_planned_parts``
    was reached first) or the cause that ended it (the part-level cause, or the last check its candidates failed).
    ``rejections``: candidates per cause (a part-level cause counts every candidate). ``top_height_m``: its highest
    point (base z); ``covered_fraction``: share of its upward surface with something above it."""

    part_index: int
    obj_id: int
    status: str
    n_candidates: int
    n_planned: int
    rejections: dict[str, int]
    top_height_m: float
    covered_fraction: float


@dataclass(frozen=True, eq=False)
class GraspPlan:
    """The planner's answer: ``grasps`` best first (empty: nothing is safe to pick), a report per part, the
    rejection counts over all parts per cause, and the time each stage took (seconds).

    Order: grasps of parts with nothing lying on them (``covered_fraction`` at most 2 %) come first, then the
    others (a part under another comes after it); within each group, by score."""

    grasps: tuple[PlannedGrasp, ...]
    parts: tuple[PartReport, ...]
    rejections: dict[str, int]
    timings_s: dict[str, float]
    #: ``(n, 3)`` the depth camera's pile points (base frame, the bin's own points dropped) the plan was checked
    #: against; empty without a depth frame. What else lies in the bin, seen or not (the nudge planner's obstacles).
    cloud_base: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))

    @property
    def nothing_safe(self) -> bool:
        return not self.grasps

    @property
    def best(self) -> PlannedGrasp | None:
        return self.grasps[0] if self.grasps else None

    @property
    def n_in_bin(self) -> int:
        """Parts that are in the bin (all of them without a bin): 0 means the bin is empty whatever else the camera
        saw."""
        return sum(p.status != "outside_bin" for p in self.parts)

    def summary(self) -> str:
        """One line for logs: what was planned, or that nothing is safe, with the rejection counts."""
        causes = ", ".join(f"{c} {n}" for c, n in self.rejections.items() if n) or "none"
        statuses = ", ".join(f"part {p.part_index} (obj {p.obj_id}): {p.status}" for p in self.parts)
        if self.nothing_safe:
            return f"nothing safe to pick among {len(self.parts)} part(s): {statuses}; rejected candidates: {causes}"
        planned = len({g.part_index for g in self.grasps})
        return (
            f"{len(self.grasps)} grasp(s) for {planned} of {len(self.parts)} part(s), best on part "
            f"{self.grasps[0].part_index} (score {self.grasps[0].score:.2f}); rejected candidates: {causes}"
        )
