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

from collections import Counter, defaultdict
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
    T_true, e = _nearest_error(T_est, same_kind, model)
    return {
        "add_d": round(e.add_m / e.diameter_m, 4),
        "re_deg": round(e.re_deg, 2),
        "te_mm": round(1e3 * e.te_m, 2),
        "dz_mm": round(1e3 * float(T_est[2, 3] - T_true[2, 3]), 2),
    }


def _nearest_error(T_world_est: np.ndarray, same_kind: list[np.ndarray], model: ObjectModel) -> tuple[np.ndarray, Any]:
    """The true pose nearest the estimate (by position) among ``same_kind`` (non-empty), and the estimate's errors
    against it (``sygrid.metrics.pose_errors``)."""
    T_true = min(same_kind, key=lambda T: float(np.linalg.norm(T[:3, 3] - T_world_est[:3, 3])))
    return T_true, pose_errors(T_world_est, T_true, model)


def refused_pose_figures(
    T_world_camera: np.ndarray,
    refused: list[Any],
    T_world_obj: np.ndarray,
    obj_ids: list[int],
    models: dict[int, ObjectModel],
) -> list[dict[str, Any]]:
    """The poses the verification refused in a frame, each with the verification's figures and whether the estimate
    was right (ADD(-S) < 0.1 d against the nearest true part of its kind in ``T_world_obj``, in the order of
    ``obj_ids``): a right estimate refused is the verification's loss, and ``weakest`` names its lowest term (the
    depth's ``fit``, its ``coverage`` of the mask, or the outline's ``iou``, ``perception.verify``). ``refused``:
    poses with ``obj_id``, ``T_camera_object`` and the verification's figures in ``details["verify"]``; a pose of a
    kind not in ``models`` or not among the parts (a false detection), or without figures, is left out."""
    out = []
    for pose in refused:
        figures = pose.details.get("verify")
        same_kind = [T for T, i in zip(T_world_obj, obj_ids, strict=True) if i == pose.obj_id]
        if pose.obj_id not in models or not same_kind or not figures:
            continue
        T_est = np.asarray(T_world_camera, dtype=float) @ np.asarray(pose.T_camera_object, dtype=float)
        _, e = _nearest_error(T_est, same_kind, models[pose.obj_id])
        terms = {k: float(figures[k]) for k in ("fit", "coverage", "iou")}
        out.append({
            "part": models[pose.obj_id].name,
            "right": e.correct(),
            "te_mm": round(1e3 * e.te_m, 2),
            "confidence": round(float(figures["confidence"]), 3),
            **{k: round(v, 3) for k, v in terms.items()},
            "weakest": min(terms, key=terms.__getitem__),
        })  # fmt: skip
    return out


def summarize_refused(refused: list[dict[str, Any]]) -> dict[str, Any]:
    """Over ``refused_pose_figures`` records: how many, how many right, the weakest term's counts among the right
    ones, their median terms, and right / refused per part."""
    right = [r for r in refused if r["right"]]
    by_part: dict[str, list[int]] = defaultdict(lambda: [0, 0])
    for r in refused:
        by_part[r["part"]][0] += r["right"]
        by_part[r["part"]][1] += 1
    return {
        "n": len(refused),
        "n_right": len(right),
        "right_weakest": dict(Counter(r["weakest"] for r in right).most_common()),
        **{f"right_median_{k}": median([r[k] for r in right]) for k in ("fit", "coverage", "iou")},
        "right_by_part": {part: f"{n_right}/{n}" for part, (n_right, n) in sorted(by_part.items())},
    }


def format_refused(name: str, s: dict[str, Any]) -> str:
    return (
        f"{name}: poses refused in the bins' last frames: {s['n']}, right {s['n_right']} "
        f"(by part {s['right_by_part']}); "
        f"the right ones' weakest term {s['right_weakest'] or '-'}, medians fit {s['right_median_fit']:.2f}, "
        f"coverage {s['right_median_coverage']:.2f}, iou {s['right_median_iou']:.2f}"
    )


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
