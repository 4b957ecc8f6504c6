"""Why a pick attempt in the simulated cell failed: the error of the pose it was planned on, against the simulator.

``sygrid bench cell`` snapshots the parts' true poses each time the picker plans (``TruthAtPlan``); after the bin,
each attempt's estimate (``Attempt.T_base_obj``, the planned grasp's part pose) is compared with the true pose of
the nearest part of its kind in the snapshot of the plan it came from. The errors are the evaluation's own
(``sygrid.metrics.pose_errors``: ADD or ADD-S by the part's symmetry, symmetry-aware rotation and translation
error), plus the height error in the world (the fingers close at a height). An attempt whose estimate is right
(ADD(-S) < 0.1 d) and failed is the grasp's or the physics' failure; one whose estimate is wrong is perception's.

Computed after the bin, off the picker's timed path; only the snapshot (one call to the emulator) is taken while
the cell runs.
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from sygrid.bench.common import median
from sygrid.metrics import ADD_THRESHOLD_FRACTION, pose_errors
from sygrid.objects import ObjectModel


def _key(T_base_obj: Any) -> bytes:
    """A planned part pose as a lookup key (the attempt keeps the grasp's pose as a list of the same floats)."""
    return np.round(np.asarray(T_base_obj, dtype=float), 9).tobytes()


@dataclass
class TruthAtPlan:
    """The true part poses (``T_world_obj``, in the order of ``obj_ids``) at each plan, with the part poses that
    plan's grasps were planned on."""

    obj_ids: list[int]
    snapshots: list[tuple[np.ndarray, set[bytes]]] = field(default_factory=list)

    def add(self, T_world_obj: np.ndarray, planned_T_base_obj: list[Any]) -> None:
        self.snapshots.append((np.asarray(T_world_obj, dtype=float), {_key(T) for T in planned_T_base_obj}))

    def truth_for(self, T_base_obj: Any) -> np.ndarray | None:
        """The snapshot of the latest plan that planned a grasp on ``T_base_obj`` (None: no plan did)."""
        key = _key(T_base_obj)
        return next((T for T, keys in reversed(self.snapshots) if key in keys), None)


def attempt_pose_error(
    T_world_base: np.ndarray, T_base_obj: Any, obj_id: int, truth: TruthAtPlan, model: ObjectModel
) -> dict[str, float] | None:
    """The errors of one attempt's estimate against the nearest true part of its kind at its plan: ``add_d``
    (ADD(-S) / diameter), ``re_deg``, ``te_mm``, ``dz_mm`` (estimated minus true height of the part's origin in the
    world). None where no plan or no part of the kind is found (a false detection)."""
    T_true_all = truth.truth_for(T_base_obj)
    if T_true_all is None:
        return None
    same_kind = [T for T, i in zip(T_true_all, truth.obj_ids, strict=True) if i == obj_id]
    if not same_kind:
        return None
    T_est = np.asarray(T_world_base, dtype=float) @ np.asarray(T_base_obj, dtype=float)
    T_true = min(same_kind, key=lambda T: float(np.linalg.norm(T[:3, 3] - T_est[:3, 3])))
    e = pose_errors(T_est, T_true, model)
    return {
        "add_d": round(e.add_m / e.diameter_m, 4),
        "re_deg": round(e.re_deg, 2),
        "te_mm": round(1e3 * e.te_m, 2),
        "dz_mm": round(1e3 * float(T_est[2, 3] - T_true[2, 3]), 2),
    }


def summarize_attempt_errors(attempts: list[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """Per attempt outcome: how many attempts, how many had an estimate (a part of the kind was found), how many of
    those were wrong (ADD(-S) >= 0.1 d), and the medians of te, |dz| and re. ``attempts``: records with
    ``outcome`` and ``pose_error`` (a dict from ``attempt_pose_error``, or None)."""
    by_outcome: dict[str, list[dict[str, float] | None]] = defaultdict(list)
    for a in attempts:
        by_outcome[a["outcome"]].append(a.get("pose_error"))
    out = {}
    for outcome, errors in sorted(by_outcome.items()):
        known = [e for e in errors if e is not None]
        out[outcome] = {
            "n": len(errors),
            "n_with_truth": len(known),
            "n_wrong_estimate": sum(e["add_d"] >= ADD_THRESHOLD_FRACTION for e in known),
            "te_median_mm": median([e["te_mm"] for e in known]),
            "abs_dz_median_mm": median([abs(e["dz_mm"]) for e in known]),
            "re_median_deg": median([e["re_deg"] for e in known]),
        }
    return out


def format_attempt_errors(name: str, summary: dict[str, dict[str, Any]]) -> str:
    parts = [
        f"{outcome} {s['n_wrong_estimate']}/{s['n_with_truth']} wrong (te {s['te_median_mm']:.1f} mm, "
        f"|dz| {s['abs_dz_median_mm']:.1f} mm, re {s['re_median_deg']:.1f} deg)"
        for outcome, s in summary.items()
    ]
    return f"{name}: attempts' estimates (ADD(-S) >= 0.1 d: wrong; medians): " + ("; ".join(parts) or "none")
