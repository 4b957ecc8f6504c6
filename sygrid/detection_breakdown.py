"""Where a detector fails: AP and recall per part, per size bin and per visibility bin, at two confidence thresholds.

Sizes are the longer side of an instance's visible box (``bbox_visib``) in image pixels (``SIZE_BINS``); visibility is
its visible fraction (``VISIB_BINS``). Instances seen less than ``min_visib_fract`` are left out (as in
``sygrid.metrics.detection_metrics``). A part's *nominal size* is what the pixels-per-part check predicts
(``sygrid.part_pixels``): ``fx * diameter / z`` image pixels times the detector's scale (network input pixels per
image pixel), ``z`` the part's distance from the camera.

- Recall: instances matched by a detection of the same part with mask IoU >= ``match_iou`` (box IoU for a
  detection-only model), each detection used once, instances in annotation order taking their best-overlapping
  free detection (``match_instances``, which ``perception.evaluation.match_poses`` uses too), among the detections
  at or above a threshold.
- AP: pycocotools' COCOeval over the same ground truth. Size bins are COCO area ranges with an instance's (and a
  detection's) "area" set to the square of its box's longer side, so an unmatched detection counts against the bin
  its own size falls in, as COCO does; a visibility bin marks the instances outside it ``iscrowd`` (neither needed
  nor penalised; detections outside every bin count as false positives in each).

Views of a run for other questions, fed to the same metrics: ``only_parts`` keeps the ground truth and detections of
some parts (a class-aware evaluation on the parts two label sets share); ``class_agnostic`` puts every instance and
detection under one category (``AGNOSTIC_ID``), so a right box under the wrong part name counts as found.
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import io
import itertools
import math
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from pycocotools.coco import COCO
from pycocotools.cocoeval import COCOeval

from sygrid.annotations import ImageAnnotation, InstanceAnnotation
from sygrid.metrics import DetectionLike, coco_ground_truth, coco_results

SIZE_BINS: tuple[tuple[str, float, float], ...] = (("<20", 0.0, 20.0), ("20-50", 20.0, 50.0), (">50", 50.0, math.inf))
VISIB_BINS: tuple[tuple[str, float, float], ...] = (("10-40%", 0.1, 0.4), ("40-70%", 0.4, 0.7), ("70-100%", 0.7, 1.01))
NOMINAL_BINS_PX = (0.0, 8.0, 10.0, 12.0, 14.0, 16.0, 18.0, 20.0, 24.0, 28.0, 32.0, 40.0, 48.0, 64.0, math.inf)
# "Resolved reliably": recall at a size at least this fraction of what the detector recalls of the same parts at any
# size (the parts' own recall, so that a part hard at every size does not read as a size limit).
RELIABLE_RELATIVE = 0.8
WELL_SEEN = 0.5  # the nominal-size curve counts instances at least this visible (occlusion is not a size effect)
MIN_CURVE_COUNT = 20  # a bin of the nominal-size curve with fewer instances is not trusted
AGNOSTIC_ID = 0  # the one category of a class-agnostic evaluation (no BOP obj_id is 0)


@dataclass(frozen=True)
class InstanceRecord:
    """One evaluated ground-truth instance: its part, size, visibility and whether it was found at each threshold
    (``found[t]`` for the threshold ``t``)."""

    image: int
    obj_id: int
    box_px: float
    visib_fract: float
    nominal_px: float  # NaN without a diameter
    found: dict[float, bool]
    input_box_px: float = math.nan  # box_px at the detector's scale; NaN without a scale


def box_side_px(inst: InstanceAnnotation) -> float:
    """The longer side of the visible box, image pixels (0 for an unseen instance)."""
    _, _, w, h = inst.bbox_visib
    return float(max(w, h, 0))


def _window(a: np.ndarray, b: np.ndarray, shape: tuple[int, int]) -> tuple[slice, slice] | None:
    """The pixel window shared by two ``[x0, y0, x1, y1]`` boxes, or None when they do not meet."""
    x0, y0 = max(int(a[0]), int(b[0]), 0), max(int(a[1]), int(b[1]), 0)
    x1, y1 = min(math.ceil(a[2]), math.ceil(b[2]), shape[1]), min(math.ceil(a[3]), math.ceil(b[3]), shape[0])
    return (slice(y0, y1), slice(x0, x1)) if x1 > x0 and y1 > y0 else None


def _iou(
    inst: InstanceAnnotation,
    inst_box: np.ndarray,
    inst_px: int,
    det: DetectionLike,
    mask: np.ndarray | None,
    det_px: int,
) -> float:
    box = np.asarray(det.bbox_xyxy, dtype=float)
    if mask is None:  # box IoU against the visible box
        w = max(0.0, min(inst_box[2], box[2]) - max(inst_box[0], box[0]))
        h = max(0.0, min(inst_box[3], box[3]) - max(inst_box[1], box[1]))
        inter = w * h
        union = (inst_box[2] - inst_box[0]) * (inst_box[3] - inst_box[1]) + (box[2] - box[0]) * (box[3] - box[1])
        return inter / (union - inter) if union - inter > 0 else 0.0
    window = _window(inst_box, box, inst.mask_visib.shape)
    if window is None:
        return 0.0
    inter = int(np.count_nonzero(inst.mask_visib[window] & mask[window]))
    union = inst_px + det_px - inter
    return inter / union if union else 0.0


def match_instances(
    ann: ImageAnnotation, detections: Sequence[DetectionLike], min_visib_fract: float, match_iou: float
) -> list[tuple[InstanceAnnotation, DetectionLike | None]]:
    """Per instance seen at least ``min_visib_fract``: (instance, the detection matched to it or None); see the
    module docstring for the rule."""
    free = sorted(detections, key=lambda d: -d.score)
    masks = {id(d): d.mask for d in free}  # read once: a detection may build its mask on each access
    det_px = {k: int(np.count_nonzero(m)) if m is not None else 0 for k, m in masks.items()}
    out = []
    for inst in ann.instances:
        if inst.visib_fract < min_visib_fract:
            continue
        x, y, w, h = inst.bbox_visib
        inst_box = np.array([x, y, x + w, y + h], dtype=float)
        inst_px = int(inst.px_count_visib)
        best, best_iou = None, match_iou
        for d in free:
            if d.obj_id != inst.obj_id:
                continue
            iou = _iou(inst, inst_box, inst_px, d, masks[id(d)], det_px[id(d)])
            if iou >= best_iou:
                best, best_iou = d, iou
        if best is not None:
            free.remove(best)
        out.append((inst, best))
    return out


def instance_records(
    images: Sequence[ImageAnnotation],
    detections: Sequence[Sequence[DetectionLike]],
    thresholds: Sequence[float],
    min_visib_fract: float = 0.1,
    match_iou: float = 0.5,
    diameters_m: Mapping[int, float] | None = None,
    scale: float | None = None,
) -> list[InstanceRecord]:
    """One record per instance seen at least ``min_visib_fract``, found or not at each of ``thresholds`` (the
    detections at or above it are matched). ``diameters_m`` (obj_id -> model diameter) and ``scale`` (network input
    pixels per image pixel) give the nominal size; without them it is NaN."""
    if len(images) != len(detections):
        raise ValueError(f"detections: expected one list per image ({len(images)}), got {len(detections)}")
    records: dict[tuple[int, int], dict] = {}
    for t in thresholds:
        for k, (ann, dets) in enumerate(zip(images, detections, strict=True)):
            kept = [d for d in dets if d.score >= t]
            for inst, det in match_instances(ann, kept, min_visib_fract, match_iou):
                key = (k, inst.inst_id)
                if key not in records:
                    nominal = math.nan
                    if diameters_m is not None and scale is not None and inst.obj_id in diameters_m:
                        z = float(inst.T_camera_obj[2, 3])
                        nominal = ann.intrinsics.fx * diameters_m[inst.obj_id] / z * scale if z > 0 else math.nan
                    records[key] = {"image": k, "obj_id": int(inst.obj_id), "box_px": box_side_px(inst),
                                    "visib_fract": float(inst.visib_fract), "nominal_px": nominal, "found": {},
                                    "input_box_px": box_side_px(inst) * scale if scale else math.nan}  # fmt: skip
                records[key]["found"][float(t)] = det is not None
    return [InstanceRecord(**r) for r in records.values()]


@dataclass(frozen=True, eq=False)
class _Relabelled:
    """A detection under another obj_id; score, box and mask read through from the original (whose mask may be
    built on each access)."""

    original: DetectionLike
    obj_id: int

    @property
    def score(self) -> float:
        return self.original.score

    @property
    def bbox_xyxy(self) -> np.ndarray:
        return self.original.bbox_xyxy

    @property
    def mask(self) -> np.ndarray | None:
        return self.original.mask


def only_parts(
    images: Sequence[ImageAnnotation], detections: Sequence[Sequence[DetectionLike]], obj_ids: Collection[int]
) -> tuple[list[ImageAnnotation], list[list[DetectionLike]]]:
    """The ground truth and detections of the parts ``obj_ids`` alone (new annotation objects; the detections are
    the same objects)."""
    keep = {int(i) for i in obj_ids}
    kept_images = [dataclasses.replace(im, instances=tuple(i for i in im.instances if i.obj_id in keep))
                   for im in images]  # fmt: skip
    return kept_images, [[d for d in dets if int(d.obj_id) in keep] for dets in detections]


def class_agnostic(
    images: Sequence[ImageAnnotation], detections: Sequence[Sequence[DetectionLike]]
) -> tuple[list[ImageAnnotation], list[list[DetectionLike]]]:
    """The ground truth and detections with every obj_id replaced by ``AGNOSTIC_ID``: matched and scored as one
    category, a detection counts for any part whatever part it names (COCO's 100 detections per image then apply
    to all parts together)."""
    relabelled = [
        dataclasses.replace(im, instances=tuple(dataclasses.replace(i, obj_id=AGNOSTIC_ID) for i in im.instances))
        for im in images
    ]
    return relabelled, [[_Relabelled(d, AGNOSTIC_ID) for d in dets] for dets in detections]


def _recall(records: Sequence[InstanceRecord], t: float) -> float:
    return float(np.mean([r.found[t] for r in records])) if records else math.nan


def recall_table(
    records: Sequence[InstanceRecord], thresholds: Sequence[float], names: Mapping[int, str] | None = None
) -> dict:
    """Recall at each threshold per part and overall, each split by size and visibility bin:
    ``{part: {"all" | size label | visibility label: {"n", "recall@t"...}}}``, part ``"all"`` for every part."""
    names = names or {}
    parts: dict[str, list[InstanceRecord]] = {"all": list(records)}
    for r in sorted(records, key=lambda r: r.obj_id):
        parts.setdefault(f"{r.obj_id} {names.get(r.obj_id, '?')}", []).append(r)
    table = {}
    for part, rs in parts.items():
        row = {"all": rs}
        row |= {label: [r for r in rs if lo <= r.box_px < hi] for label, lo, hi in SIZE_BINS}
        row |= {label: [r for r in rs if lo <= r.visib_fract < hi] for label, lo, hi in VISIB_BINS}
        table[part] = {k: {"n": len(v), **{f"recall@{t:g}": _recall(v, t) for t in thresholds}} for k, v in row.items()}
    return table


def size_curve(records: Sequence[InstanceRecord], threshold: float, size: str = "nominal_px") -> list[dict]:
    """Recall at ``threshold`` of the instances seen at least ``WELL_SEEN``, per bin (``NOMINAL_BINS_PX``) of their
    ``size`` (``"nominal_px"`` or ``"input_box_px"``, network input pixels): ``[{"lo_px", "hi_px", "n", "recall",
    "relative"}]`` (bins without instances left out). ``relative``: the bin's recall over the recall its instances'
    parts have over all sizes (1: as well as the detector does on those parts anywhere)."""
    seen = [r for r in records if r.visib_fract >= WELL_SEEN and math.isfinite(getattr(r, size))]
    part_recall = {}
    for obj_id in {r.obj_id for r in seen}:
        part_recall[obj_id] = _recall([r for r in seen if r.obj_id == obj_id], threshold)
    rows = []
    for lo, hi in itertools.pairwise(NOMINAL_BINS_PX):
        rs = [r for r in seen if lo <= getattr(r, size) < hi]
        if rs:
            expected = sum(part_recall[r.obj_id] for r in rs)
            relative = sum(r.found[threshold] for r in rs) / expected if expected > 0 else math.nan
            rows.append(
                {"lo_px": lo, "hi_px": hi, "n": len(rs), "recall": _recall(rs, threshold), "relative": relative}
            )
    return rows


def min_reliable_px(curve: Sequence[Mapping]) -> float:
    """The smallest nominal size (network input pixels) from which every trusted bin of ``curve`` (at least
    ``MIN_CURVE_COUNT`` instances) reaches ``RELIABLE_RELATIVE`` of its parts' recall; NaN when the largest trusted
    bin does not."""
    trusted = [row for row in curve if row["n"] >= MIN_CURVE_COUNT]
    edge = math.nan
    for row in reversed(trusted):
        if not row["relative"] >= RELIABLE_RELATIVE:
            break
        edge = row["lo_px"]
    return edge


def _coco_eval(gt: dict, results: list[dict], iou_type: str, area_of: dict[int, float], area_ranges: list) -> COCOeval:
    """COCOeval of ``results`` against ``gt`` over ``area_ranges`` with each result's area replaced by ``area_of``
    (by result id, 1-based); evaluated, not yet accumulated."""
    quiet = io.StringIO()
    with contextlib.redirect_stdout(quiet):
        coco_gt = COCO()
        coco_gt.dataset = gt
        coco_gt.createIndex()
        coco_dt = coco_gt.loadRes(results)
        for ann_id, ann in coco_dt.anns.items():
            ann["area"] = area_of[ann_id]
        evaluator = COCOeval(coco_gt, coco_dt, iouType=iou_type)
        evaluator.params.catIds = [int(c["id"]) for c in gt["categories"]]
        evaluator.params.areaRng = area_ranges
        evaluator.params.areaRngLbl = [str(i) for i in range(len(area_ranges))]
        evaluator.evaluate()
    return evaluator


def _reevaluate(evaluator: COCOeval, ignored: set[int], area_ranges: list) -> None:
    """Matches ``evaluator``'s detections again (its IoUs kept) with the ground truth of ids ``ignored`` neither
    needed nor penalised, over ``area_ranges``; then accumulates."""
    for gts in evaluator._gts.values():
        for g in gts:
            g["ignore"] = bool(g["iscrowd"]) or g["id"] in ignored
    p = evaluator.params
    p.areaRng, p.areaRngLbl = area_ranges, [str(i) for i in range(len(area_ranges))]
    evaluator.evalImgs = [evaluator.evaluateImg(image, cat, area, p.maxDets[-1])
                          for cat in p.catIds for area in p.areaRng for image in p.imgIds]  # fmt: skip
    evaluator._paramsEval = copy.deepcopy(p)  # what accumulate() reads the layout of evalImgs from
    with contextlib.redirect_stdout(io.StringIO()):
        evaluator.accumulate()


def _ap(precision: np.ndarray) -> float:
    valid = precision[precision > -1]
    return float(np.mean(valid)) if valid.size else math.nan


def _ap_rows(evaluator: COCOeval, labels: Sequence[str], area_index: Sequence[int]) -> dict[str, dict]:
    """``{"all" | obj_id: {label: (AP50-95, AP50)}}`` from an accumulated evaluation."""
    precision = evaluator.eval["precision"]  # [iou, recall, category, area, max dets]
    iou50 = int(np.argmin(np.abs(evaluator.params.iouThrs - 0.5)))
    out: dict[str, dict] = {"all": {}}
    for label, a in zip(labels, area_index, strict=True):
        p = precision[:, :, :, a, -1]
        out["all"][label] = (_ap(p), _ap(p[iou50]))
        for k, cat in enumerate(evaluator.params.catIds):
            out.setdefault(str(cat), {})[label] = (_ap(p[:, :, k]), _ap(p[iou50, :, k]))
    return out


def ap_table(
    images: Sequence[ImageAnnotation], detections: Sequence[Sequence[DetectionLike]], min_visib_fract: float = 0.1
) -> dict:
    """Box AP50 / AP50-95 and mask AP50-95 per part (obj_id as a string, and ``"all"``: the mean over parts) and
    per bin: ``{part: {bin label: {"box_ap50", "box_ap50_95", "mask_ap50_95"}}}`` (NaN where nothing to measure;
    mask AP NaN for a detection-only model). No detections: AP 0 where there is ground truth.

    One IoU computation per box/mask evaluation: the visibility bins re-match with other ground truth ignored."""
    obj_ids = sorted({i.obj_id for im in images for i in im.instances if i.px_count_visib}
                     | {int(d.obj_id) for dets in detections for d in dets})  # fmt: skip
    gt = coco_ground_truth(images, obj_ids, min_visib_fract)
    sides = [box_side_px(i) for im in images for i in im.instances if i.px_count_visib]
    visib = [i.visib_fract for im in images for i in im.instances if i.px_count_visib]
    for ann, side in zip(gt["annotations"], sides, strict=True):
        ann["area"] = side * side
    with_masks = all(d.mask is not None for dets in detections for d in dets)
    types = {"box": coco_results(detections, with_masks=False)}
    if with_masks:
        types["mask"] = coco_results(detections, with_masks=True)
    size_labels = [label for label, _, _ in SIZE_BINS]
    all_range = [[0.0, 1e10]]
    size_ranges = all_range + [[lo * lo, min(hi, 1e5) ** 2] for _, lo, hi in SIZE_BINS]
    rows: dict[str, dict] = {}
    for kind, results in types.items():
        per: dict[str, dict] = {}
        if results:
            area_of = {k + 1: float(np.max(r["bbox"][2:])) ** 2 for k, r in enumerate(results)}
            evaluator = _coco_eval(gt, results, "bbox" if kind == "box" else "segm", area_of, size_ranges)
            _reevaluate(evaluator, set(), size_ranges)
            per = _ap_rows(evaluator, ["all", *size_labels], range(len(size_ranges)))
            for label, lo, hi in VISIB_BINS:
                outside = {a["id"] for a, v in zip(gt["annotations"], visib, strict=True) if not lo <= v < hi}
                _reevaluate(evaluator, outside, all_range)
                for part, cells in _ap_rows(evaluator, [label], [0]).items():
                    per.setdefault(part, {}).update(cells)
        rows[kind] = per
    labels = ["all", *size_labels, *(label for label, _, _ in VISIB_BINS)]
    table = {}
    for part in ["all", *[str(i) for i in obj_ids]]:
        table[part] = {}
        for label in labels:
            cell = {}
            for kind, key, idx in (("box", "box_ap50", 1), ("box", "box_ap50_95", 0), ("mask", "mask_ap50_95", 0)):
                value = rows.get(kind, {}).get(part, {}).get(label)
                if value is None:
                    value = (0.0, 0.0) if kind in rows and not rows[kind] and _has_gt(gt, part) else (math.nan,) * 2
                cell[key] = value[idx]
            table[part][label] = cell
    return table


def _has_gt(gt: dict, part: str) -> bool:
    return any(not a["iscrowd"] and (part == "all" or str(a["category_id"]) == part) for a in gt["annotations"])


def breakdown(
    images: Sequence[ImageAnnotation],
    detections: Sequence[Sequence[DetectionLike]],
    thresholds: Sequence[float],
    min_visib_fract: float = 0.1,
    match_iou: float = 0.5,
    names: Mapping[int, str] | None = None,
    diameters_m: Mapping[int, float] | None = None,
    scale: float | None = None,
) -> dict:
    """The whole breakdown of one detector run (``detections`` made at the lowest of ``thresholds``):
    ``{"thresholds", "recall": recall_table, "ap": {threshold: ap_table}, "nominal_curve": {threshold: curve},
    "min_reliable_px": {threshold: px}}``; thresholds as strings in the keys (JSON)."""
    thresholds = sorted({float(t) for t in thresholds})
    records = instance_records(images, detections, thresholds, min_visib_fract, match_iou, diameters_m, scale)
    out = {
        "thresholds": thresholds,
        "size_bins_px": [[label, lo, hi if math.isfinite(hi) else None] for label, lo, hi in SIZE_BINS],
        "visibility_bins": [[label, lo, min(hi, 1.0)] for label, lo, hi in VISIB_BINS],
        "recall": recall_table(records, thresholds, names),
        "ap": {},
        "nominal_curve": {},
        "box_curve": {},
        "min_reliable_px": {},
    }
    for t in thresholds:
        kept = [[d for d in dets if d.score >= t] for dets in detections]
        out["ap"][f"{t:g}"] = ap_table(images, kept, min_visib_fract)
        curve = size_curve(records, t)
        out["nominal_curve"][f"{t:g}"] = curve
        out["box_curve"][f"{t:g}"] = size_curve(records, t, "input_box_px")
        out["min_reliable_px"][f"{t:g}"] = min_reliable_px(curve)
    return out
