"""Every pose strategy measured per part on a generated test set, with ground-truth masks (the pose stage alone),
and the choice of a strategy per part.

For every ground-truth instance seen at least ``min_visib_fract``, a detection is made from its visible mask and
box; each strategy (``perception.pose_strategies``) estimates the pose; the record keeps its pose errors
(``sygrid.metrics.pose_errors``), its time (a share of the network's batch time for the strategies that use the
network) and the verification's verdict. A wrong-class trial per instance fits the model of another part (the next
obj_id) with each strategy: its verification must refuse it. As in the pipeline end to end
(``perception.evaluation.evaluate``), each image's bin floor is given (``bin_floor_camera``, ``EvalSettings.floor``):
the depth is corrected by the stereo offset measured on it (``tare``, ``perception.depth_tare``) and the strategies
take it as the parts' support. The verifier's noise allowance is the caller's (``VerifyConfig.for_sensor`` of the
frames' sensor, ``perception.evaluation.frames_sensor``).

The choice per part is the cheapest strategy (median CPU milliseconds per object: steadier than wall time on a
shared machine) whose ADD(-S) recall reaches the bar, else the
most accurate one.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from perception.depth_tare import TareConfig, tared_depth
from perception.evaluation import EvalSettings, bin_floor_camera, eval_items, floor_bin
from perception.pose import PoseEstimator
from perception.pose_strategies import NETWORK_STRATEGIES, STRATEGIES, StrategyRunner
from perception.results import Detection, ObjectPose
from sygrid.annotations import ImageAnnotation, InstanceAnnotation
from sygrid.errors import ConfigError
from sygrid.metrics import ADD_THRESHOLD_FRACTION, pose_errors
from sygrid.objects.model import ObjectModel
from sygrid.writers import load_bop_item

SenseFn = Callable[[ImageAnnotation, np.ndarray, np.ndarray | None], tuple[np.ndarray, np.ndarray | None]]
Thresholds = float | Mapping[int, float]  # the verification threshold: one for every part, or one per obj_id
THRESHOLDS = tuple(round(0.5 + 0.01 * k, 2) for k in range(50))  # the verification thresholds the choice tries


@dataclass(frozen=True)
class StrategyRecord:
    """One strategy's result on one instance: ``correct`` (ADD(-S) < 0.1 d; False when no pose), ``re_deg`` and
    ``te_m`` (NaN when no pose), wall and CPU milliseconds, the verification's ``confidence`` (0 when no pose)
    and that of the wrong-class trial (NaN where not run); ``image`` names the instance (``scene_image/inst``)."""

    obj_id: int
    strategy: str
    correct: bool
    re_deg: float
    te_m: float
    ms: float
    cpu_ms: float
    confidence: float
    wrong_class_confidence: float = math.nan
    visib_fract: float = math.nan
    image: str = ""


def threshold_of(min_confidence: Thresholds, obj_id: int) -> float:
    """The verification threshold of part ``obj_id``: the one threshold, or the part's (KeyError when the
    mapping lacks it)."""
    return float(min_confidence) if isinstance(min_confidence, int | float) else float(min_confidence[obj_id])


def accepted_by(records: list[StrategyRecord], min_confidence: Thresholds) -> np.ndarray:
    """(n,) bool: which records' confidence reaches their part's threshold."""
    return np.array([x.confidence >= threshold_of(min_confidence, x.obj_id) for x in records], dtype=bool)


def summarize(records: list[StrategyRecord], min_confidence: Thresholds) -> dict:
    """The records' figures with poses accepted at ``min_confidence`` (one threshold, or one per obj_id): ADD(-S)
    recall over all estimates and over the accepted ones (of all instances), median re/te/ms, false accepts (wrong
    among the accepted), false refusals (refused among the correct) and the wrong-class trials accepted (fractions;
    NaN where undefined; a wrong-class trial is held to the threshold of the instance's own part)."""
    n = len(records)
    correct = np.array([x.correct for x in records], dtype=bool)
    accepted = accepted_by(records, min_confidence)
    trials = [x for x in records if math.isfinite(x.wrong_class_confidence)]
    wrong = np.array([x.wrong_class_confidence >= threshold_of(min_confidence, x.obj_id) for x in trials], dtype=bool)
    return {
        "n": n,
        "add_recall": _ratio(correct.sum(), n),
        "accepted_recall": _ratio((accepted & correct).sum(), n),
        "median_re_deg": _median([x.re_deg for x in records]),
        "median_te_mm": 1e3 * _median([x.te_m for x in records]),
        "median_ms": _median([x.ms for x in records]),
        "median_cpu_ms": _median([x.cpu_ms for x in records]),
        "false_accept": _ratio((accepted & ~correct).sum(), accepted.sum()),
        "false_refuse": _ratio((~accepted & correct).sum(), correct.sum()),
        "wrong_class_accept": _ratio(wrong.sum(), len(wrong)),
    }


def visibility_gates(records: list[StrategyRecord], min_confidence: Thresholds, gates: tuple[float, ...]) -> list[dict]:
    """What refusing every instance less visible than a gate would trade (the ground truth's visible fraction, an
    oracle a runtime does not have): per gate, the false accepts among the accepted instances at least that visible
    and the accepted recall over all instances (a refused instance counts as a failure)."""
    n = len(records)
    rows = []
    for gate in gates:
        kept = [x for x, ok in zip(records, accepted_by(records, min_confidence), strict=True)
                if ok and x.visib_fract >= gate]  # fmt: skip
        right = sum(x.correct for x in kept)
        rows.append({"min_visible": gate, "accepted": len(kept), "false_accept": _ratio(len(kept) - right, len(kept)),
                     "accepted_recall": _ratio(right, n)})  # fmt: skip
    return rows


def _ratio(a: int, b: int) -> float:
    return float(a) / float(b) if b else math.nan


def _median(values: list[float]) -> float:
    v = [x for x in values if math.isfinite(x)]
    return float(np.median(v)) if v else math.nan


def gt_detection(inst: InstanceAnnotation, obj_id: int | None = None) -> Detection:
    """A detection from a ground-truth instance: its visible mask and that mask's box (``obj_id`` overrides the
    class, for the wrong-class trials)."""
    return Detection.from_mask(inst.mask_visib, inst.obj_id if obj_id is None else obj_id, 1.0)


def evaluate_strategies(
    runner: StrategyRunner,
    network: PoseEstimator,
    models: dict[int, ObjectModel],
    data_dir: str | Path,
    strategies: tuple[str, ...] = STRATEGIES,
    settings: EvalSettings | None = None,
    wrong_class: bool = True,
    sense: SenseFn | None = None,  # (annotation, rgb, depth) -> (rgb, depth) as a sensor sees them; None: as stored
    progress: bool = True,
    tare: TareConfig | None = None,
    per_part: dict[int, str] | None = None,
) -> dict[tuple[int, str], list[StrategyRecord]]:
    """Runs every strategy on every evaluated instance; (obj_id, strategy) -> records. ``tare``: the depth tare's
    settings (the pipeline's, ``PerceptionPipeline.depth_tare``); None: the depth as stored. ``per_part``: obj_id ->
    the one strategy to run on that part's instances (``strategies`` is then not used)."""
    s = settings or EvalSettings()
    root, split, items = eval_items(data_dir, s)
    if not items:
        raise ConfigError(f"{root / split}: no images")
    stats: dict[tuple[int, str], list[StrategyRecord]] = {}
    ids = sorted(models)
    floor_of = floor_bin(data_dir, s)
    for scene_id, image_id in tqdm(items, unit="image", disable=not progress):
        ann, rgb, depth = load_bop_item(root, scene_id, image_id, split=split)
        if sense is not None:
            rgb, depth = sense(ann, rgb, depth)
        if depth is None:
            raise ConfigError(f"{root / split / f'{scene_id:06d}'}: image {image_id} has no depth map")
        floor = bounds = None
        if floor_of is not None:
            floor, bounds = bin_floor_camera(floor_of, ann)
            depth, _ = tared_depth(depth, ann.intrinsics, floor, bounds, tare)
        instances = [i for i in ann.instances if i.visib_fract >= s.min_visib_fract and i.obj_id in models]
        instances = [i for i in instances if i.mask_visib.any()]
        if not instances:
            continue
        detections = [gt_detection(i) for i in instances]
        wrong = [gt_detection(i, ids[(ids.index(i.obj_id) + 1) % len(ids)]) for i in instances]
        t, c = time.perf_counter(), time.process_time()
        net = network.estimate(rgb, detections + wrong, ann.intrinsics)
        net_ms = 1e3 * (time.perf_counter() - t) / max(len(net), 1)
        net_cpu_ms = 1e3 * (time.process_time() - c) / max(len(net), 1)
        by_det = {id(p.detection): p for p in net}
        for inst, det, bad in zip(instances, detections, wrong, strict=True):
            model = models[inst.obj_id]
            for strategy in strategies if per_part is None else (per_part[inst.obj_id],):
                uses_net = strategy in NETWORK_STRATEGIES
                pose = _run(runner, strategy, det, depth, ann.intrinsics, model, by_det.get(id(det)), uses_net, floor)
                ms = pose.details.get("time_ms", 0.0) + (net_ms if uses_net else 0.0) if pose else math.nan
                cpu_ms = pose.details.get("cpu_ms", 0.0) + (net_cpu_ms if uses_net else 0.0) if pose else math.nan
                wrong_confidence = math.nan
                if wrong_class and len(ids) > 1:
                    bad_pose = _run(runner, strategy, bad, depth, ann.intrinsics, models[bad.obj_id],
                                    by_det.get(id(bad)), uses_net, floor)  # fmt: skip
                    wrong_confidence = bad_pose.score if bad_pose is not None else 0.0
                stats.setdefault((inst.obj_id, strategy), []).append(
                    _record(inst, model, strategy, pose, ms, cpu_ms, wrong_confidence, f"{ann.name}/{inst.inst_id}")
                )
    return stats


def _run(
    runner: StrategyRunner,
    strategy: str,
    det: Detection,
    depth: np.ndarray,
    intrinsics,
    model: ObjectModel,
    net: ObjectPose | None,
    uses_net: bool,
    floor_plane_camera: np.ndarray | None = None,
) -> ObjectPose | None:
    if uses_net and net is None:
        return None
    return runner.estimate(strategy, det, depth, intrinsics, model, net if uses_net else None, floor_plane_camera)


def _record(
    inst: InstanceAnnotation,
    model: ObjectModel,
    strategy: str,
    pose: ObjectPose | None,
    ms: float,
    cpu_ms: float,
    wrong_confidence: float,
    image: str,
) -> StrategyRecord:
    err = pose_errors(None if pose is None else pose.T_camera_object, inst.T_camera_obj, model)
    return StrategyRecord(
        obj_id=inst.obj_id,
        strategy=strategy,
        correct=err.correct(ADD_THRESHOLD_FRACTION),
        re_deg=err.re_deg if pose is not None else math.nan,
        te_m=err.te_m if pose is not None else math.nan,
        ms=ms,
        cpu_ms=cpu_ms,
        confidence=pose.score if pose is not None else 0.0,
        wrong_class_confidence=wrong_confidence,
        visib_fract=inst.visib_fract,
        image=image,
    )


def choose(
    records: dict[tuple[int, str], list[StrategyRecord]], bar: float, min_confidence: Thresholds
) -> dict[int, str]:
    """Per obj_id: the cheapest strategy (median CPU ms) whose recall of accepted estimates (at
    ``min_confidence``: what the pipeline delivers, refused poses being dropped) reaches ``bar``, else the most
    accurate (ties: the cheaper)."""
    options: dict[int, list[tuple[str, dict]]] = {}
    for (obj_id, strategy), recs in records.items():
        options.setdefault(obj_id, []).append((strategy, summarize(recs, min_confidence)))
    out = {}
    for obj_id, rows in sorted(options.items()):
        good = [(row["median_cpu_ms"], name) for name, row in rows if row["accepted_recall"] >= bar]
        if good:
            out[obj_id] = min(good)[1]
        else:
            out[obj_id] = max(rows, key=lambda o: (o[1]["accepted_recall"], -o[1]["median_cpu_ms"]))[0]
    return out


def choose_all(
    records: dict[tuple[int, str], list[StrategyRecord]], bar: float, max_false_accept: float, per_part: bool = False
) -> tuple[dict[int, str], Thresholds]:
    """The strategy per obj_id (``choose``) and the verification thresholds that keep the chosen strategies' false
    accepts within ``max_false_accept``: one for all (``choose_threshold``), or with ``per_part`` one per part
    (``choose_part_thresholds``); each chosen given the other until they agree (a few rounds; the thresholds start
    from all records together)."""
    pick = choose_part_thresholds if per_part else choose_threshold
    threshold = pick([r for recs in records.values() for r in recs], max_false_accept)
    choice = choose(records, bar, threshold)
    for _ in range(4):
        chosen = [r for (obj_id, s), recs in records.items() if choice[obj_id] == s for r in recs]
        threshold = pick(chosen, max_false_accept)
        again = choose(records, bar, threshold)
        if again == choice:
            break
        choice = again
    return choice, threshold


def choose_threshold(
    records: list[StrategyRecord], max_false_accept: float, grid: tuple[float, ...] = THRESHOLDS
) -> float:
    """The lowest verification threshold on ``grid`` at which the false accepts of ``records`` stay within
    ``max_false_accept`` (the grid's last value when none does)."""
    for threshold in grid:
        fa = summarize(records, threshold)["false_accept"]
        if not fa > max_false_accept:  # NaN (nothing accepted) passes
            return threshold
    return grid[-1]


# The trade-off prices choose_part_thresholds tries: wrong poses accepted, in right poses given up for each.
_PRICES = (0.0, *np.geomspace(0.01, 1e4, 300))


def choose_part_thresholds(
    records: list[StrategyRecord], max_false_accept: float, grid: tuple[float, ...] = THRESHOLDS
) -> dict[int, float]:
    """A threshold on ``grid`` per obj_id of ``records`` such that the right estimates accepted, over all parts, are
    as many as the false accepts over all parts (wrong among accepted) within ``max_false_accept`` allow.

    One threshold for every part spends the false-accept budget where it buys least: a part whose confidence
    separates right from wrong poses well loses right poses to a threshold set by a part where it does not. For
    each price ``p`` (wrong poses accepted, in right ones), each part takes the threshold that maximises its
    ``right - p x wrong`` accepted (ties: the higher threshold, the margin for views not in ``records``); the
    richest choice within the budget wins. These are the optimal choices on the convex hull of the parts'
    trade-offs; a part with no wrong estimate takes the highest threshold that keeps all its right ones. The grid's
    last value for every part when no price meets the budget."""
    by_part: dict[int, list[StrategyRecord]] = {}
    for r in records:
        by_part.setdefault(r.obj_id, []).append(r)
    t = np.asarray(grid)[:, None]
    counts = {}  # obj_id -> (right accepted, wrong accepted) per threshold of the grid
    for obj_id, recs in by_part.items():
        conf = np.array([r.confidence for r in recs])[None, :]
        right = np.array([r.correct for r in recs])[None, :]
        counts[obj_id] = (((conf >= t) & right).sum(axis=1), ((conf >= t) & ~right).sum(axis=1))
    best, best_right = {obj_id: len(grid) - 1 for obj_id in by_part}, -1
    for price in _PRICES:
        pick = {}
        for obj_id, (right, wrong) in counts.items():
            gain = right - price * wrong
            pick[obj_id] = int(np.flatnonzero(gain == gain.max())[-1])  # ties: the higher threshold
        n_right = sum(int(counts[o][0][k]) for o, k in pick.items())
        n_wrong = sum(int(counts[o][1][k]) for o, k in pick.items())
        if n_wrong <= max_false_accept * (n_right + n_wrong) and n_right > best_right:
            best, best_right = pick, n_right
    return {obj_id: float(grid[k]) for obj_id, k in sorted(best.items())}
