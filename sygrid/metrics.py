"""The metrics of the SyGRID paper: detection/segmentation AP, depth accuracy and 6D pose errors.

Definitions: the standard ones that the paper names (its supplementary material was not at hand when this was
written; check it against them), spelled out so that every figure can be traced:

- **mAP50-95 / mAP50** for boxes and instance masks: COCO average precision, computed by ``pycocotools``'
  ``COCOeval`` (101-point interpolated precision, IoU thresholds 0.50:0.05:0.95, area range "all", at most 100
  detections per image). Ground truth is each visible instance (``mask_visib``, ``bbox_visib``) of our
  ``ImageAnnotation``; categories are BOP obj_ids, as in the COCO writer.
- **AbsRel** = mean over valid pixels of ``|d - d*| / d*`` and **delta1** = fraction of valid pixels with
  ``max(d / d*, d* / d) < 1.25`` (Eigen et al. 2014), ``d`` the evaluated depth, ``d*`` the reference; a pixel is
  valid where both are finite and > 0 (and inside an optional mask).
- **ADD** (Hinterstoisser et al. 2012) = mean over model points ``x`` of ``|| T_est x - T_gt x ||``; **ADD-S** =
  mean over model points ``x`` of ``min_y || T_gt x - T_est y ||`` (the closest transformed model point), used for
  parts with a declared symmetry. A pose is correct when ADD(-S) < 0.1 x the model diameter.
- **re** = angle of ``R_est R_gt^T`` in degrees, **te** = ``|| t_est - t_gt ||`` (metres inside, millimetres in
  tables), as in the BOP toolkit; the symmetry-aware re is the minimum over the model's symmetry transforms.

Model points are sampled uniformly from the mesh surface with a seed (CAD meshes have too few, unevenly spread
vertices to stand for the surface). ADD-S then carries a small positive bias even for an exact symmetric pose (the
distance between neighbouring samples, about ``0.5 / sqrt(n / area)``), which shrinks as ``n`` grows.

Empty cases of the AP: with no detections every AP is 0 where there is ground truth (not NaN, no error); a class,
or a whole evaluation, with no ground truth has NaN AP (COCO's -1: nothing to measure), detections or not.
"""

from __future__ import annotations

import contextlib
import io
import math
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass
from functools import lru_cache
from typing import NamedTuple, Protocol

import numpy as np
from pycocotools import mask as mask_utils
from pycocotools.coco import COCO
from pycocotools.cocoeval import COCOeval
from scipy.spatial import cKDTree

from sygrid.annotations import ImageAnnotation
from sygrid.objects.model import ObjectModel
from sygrid.objects.symmetry import sample_surface

ADD_THRESHOLD_FRACTION = 0.1  # a pose is correct when ADD(-S) < this fraction of the model diameter
DELTA1_RATIO = 1.25
DEFAULT_MODEL_POINTS = 5000


# ------------------------------------------------------------------------------------------ detection (COCO AP)
class DetectionLike(Protocol):
    """What the detection metrics read from a detection (``perception.results.Detection`` has these fields).

    ``bbox_xyxy``: (4,) ``[x0, y0, x1, y1]`` pixels; ``mask``: (h, w) bool in image pixels, or None.
    """

    obj_id: int
    score: float
    bbox_xyxy: np.ndarray
    mask: np.ndarray | None


@dataclass(frozen=True)
class DetectionMetrics:
    """COCO AP of a detector on a set of images. Values in [0, 1]; NaN where there is nothing to measure.

    ``mask_*`` are NaN when any detection has no mask (a detection-only model). ``per_class``: obj_id ->
    ``{"box_ap50_95", "box_ap50", "mask_ap50_95", "mask_ap50", "n_gt"}`` (NaN AP for a class with no ground truth).
    """

    box_map50_95: float
    box_map50: float
    mask_map50_95: float
    mask_map50: float
    per_class: dict[int, dict[str, float]]
    n_images: int
    n_gt: int
    n_detections: int

    def as_dict(self) -> dict:
        return asdict(self)


def coco_ground_truth(
    images: Sequence[ImageAnnotation], obj_ids: Sequence[int] | None = None, min_visib_fract: float = 0.0
) -> dict:
    """A COCO instances dataset (a new dict) for ``images``; image ``k`` gets COCO id ``k + 1``.

    Each instance with visible pixels becomes one annotation (RLE of ``mask_visib``, ``bbox_visib``). Instances
    seen less than ``min_visib_fract`` are marked ``iscrowd`` so that COCOeval neither requires nor penalises
    their detection. ``obj_ids``: the categories; None takes every obj_id in the ground truth.
    """
    annotations = []
    seen_ids: set[int] = set()
    for k, image in enumerate(images):
        for inst in image.instances:
            if inst.px_count_visib == 0:
                continue
            seen_ids.add(int(inst.obj_id))
            rle = mask_utils.encode(np.asfortranarray(np.asarray(inst.mask_visib, dtype=np.uint8)))
            x, y, w, h = inst.bbox_visib
            annotations.append(
                {
                    "id": len(annotations) + 1,
                    "image_id": k + 1,
                    "category_id": int(inst.obj_id),
                    "segmentation": rle,
                    "area": float(mask_utils.area(rle)),
                    "bbox": [float(x), float(y), float(w), float(h)],
                    "iscrowd": int(inst.visib_fract < min_visib_fract),
                }
            )
    categories = sorted(seen_ids) if obj_ids is None else sorted({int(i) for i in obj_ids})
    return {
        "images": [
            {"id": k + 1, "width": int(im.intrinsics.width), "height": int(im.intrinsics.height)}
            for k, im in enumerate(images)
        ],
        "annotations": annotations,
        "categories": [{"id": i, "name": str(i)} for i in categories],
    }


def coco_result(
    image_index: int, obj_id: int, score: float, bbox_xyxy: np.ndarray, segmentation: dict | None = None
) -> dict:
    """One COCO result record: image ``image_index`` -> COCO id ``image_index + 1``, the box from ``[x0, y0, x1, y1]``
    pixels to COCO ``[x, y, w, h]``; ``segmentation`` a COCO RLE of the mask (for a ``segm`` evaluation)."""
    x0, y0, x1, y1 = (float(v) for v in np.asarray(bbox_xyxy, dtype=float))
    record = {
        "image_id": int(image_index) + 1,
        "category_id": int(obj_id),
        "bbox": [x0, y0, x1 - x0, y1 - y0],
        "score": float(score),
    }
    if segmentation is not None:
        record["segmentation"] = segmentation
    return record


def coco_results(detections: Sequence[Sequence[DetectionLike]], with_masks: bool) -> list[dict]:
    """COCO result records (``coco_result``) for per-image detection lists; masks RLE-encoded when ``with_masks``."""
    results = []
    for k, dets in enumerate(detections):
        for det in dets:
            rle = None
            if with_masks:
                if det.mask is None:
                    raise ValueError(f"image {k}: a detection of obj_id {det.obj_id} has no mask")
                rle = mask_utils.encode(np.asfortranarray(np.asarray(det.mask, dtype=np.uint8)))
            results.append(coco_result(k, det.obj_id, det.score, det.bbox_xyxy, rle))
    return results


class CocoAP(NamedTuple):
    """COCO AP of one evaluation (boxes or masks), each in [0, 1] or NaN: ``per_class`` obj_id -> (AP50-95, AP50)."""

    map50_95: float
    map50: float
    per_class: dict[int, tuple[float, float]]


def coco_average_precision(gt_dataset: dict, results: list[dict], iou_type: str) -> CocoAP:
    """COCOeval of ``results`` (COCO result records) against ``gt_dataset`` (a COCO instances dict), for
    ``iou_type`` "bbox" or "segm", over the dataset's categories.

    Every category of ``gt_dataset["categories"]`` is in ``per_class``. No results: AP 0 for each category with
    (non-crowd) ground truth, NaN for the others; the means 0, or NaN when there is no ground truth at all. With
    results, a category without ground truth is NaN (COCO's -1) and left out of the means.
    """
    category_ids = [int(c["id"]) for c in gt_dataset["categories"]]
    if not results:  # COCO.loadRes cannot take an empty list; with no detections every AP is 0
        has_gt = {a["category_id"] for a in gt_dataset["annotations"] if not a.get("iscrowd", 0)}
        per_class_empty = {i: (0.0, 0.0) if i in has_gt else (math.nan, math.nan) for i in category_ids}
        value = 0.0 if has_gt & set(category_ids) else math.nan
        return CocoAP(value, value, per_class_empty)
    quiet = io.StringIO()
    with contextlib.redirect_stdout(quiet):  # pycocotools prints its progress and summary table
        coco_gt = COCO()
        coco_gt.dataset = gt_dataset
        coco_gt.createIndex()
        coco_dt = coco_gt.loadRes(results)
        evaluator = COCOeval(coco_gt, coco_dt, iouType=iou_type)
        evaluator.params.catIds = category_ids
        evaluator.evaluate()
        evaluator.accumulate()
        evaluator.summarize()
    map50_95, map50 = (float(v) if v > -1 else math.nan for v in evaluator.stats[:2])
    # Per-class AP: the same reduction summarize() applies, per category column of COCOeval's precision table
    # [iou threshold, recall, category, area range, max detections]: area "all", the largest max detections.
    precision = evaluator.eval["precision"][:, :, :, 0, -1]
    iou50 = int(np.argmin(np.abs(evaluator.params.iouThrs - 0.5)))
    per_class = {}
    for k, cat in enumerate(evaluator.params.catIds):
        p_all, p_50 = precision[:, :, k], precision[iou50, :, k]
        per_class[int(cat)] = (
            float(np.mean(p_all[p_all > -1])) if np.any(p_all > -1) else math.nan,
            float(np.mean(p_50[p_50 > -1])) if np.any(p_50 > -1) else math.nan,
        )
    return CocoAP(map50_95, map50, per_class)


def coco_detection_metrics(
    gt_dataset: dict, box_results: list[dict], mask_results: list[dict] | None
) -> DetectionMetrics:
    """Box and mask AP of COCO result records against a COCO instances dict (see ``coco_average_precision`` for
    the empty cases). ``mask_results`` None: a detection-only evaluation, mask AP NaN. ``n_gt`` counts the non-crowd
    annotations of the dataset's categories; ``n_detections`` the box results."""
    box = coco_average_precision(gt_dataset, box_results, "bbox")
    if mask_results is not None:
        mask = coco_average_precision(gt_dataset, mask_results, "segm")
    else:
        mask = CocoAP(math.nan, math.nan, {i: (math.nan, math.nan) for i in box.per_class})
    n_gt = {i: 0 for i in box.per_class}
    for a in gt_dataset["annotations"]:
        if not a.get("iscrowd", 0) and a["category_id"] in n_gt:
            n_gt[a["category_id"]] += 1
    per_class = {
        i: {
            "box_ap50_95": box.per_class[i][0],
            "box_ap50": box.per_class[i][1],
            "mask_ap50_95": mask.per_class[i][0],
            "mask_ap50": mask.per_class[i][1],
            "n_gt": n_gt[i],
        }
        for i in box.per_class
    }
    return DetectionMetrics(
        box_map50_95=box.map50_95,
        box_map50=box.map50,
        mask_map50_95=mask.map50_95,
        mask_map50=mask.map50,
        per_class=per_class,
        n_images=len(gt_dataset["images"]),
        n_gt=sum(n_gt.values()),
        n_detections=len(box_results),
    )


def detection_metrics(
    images: Sequence[ImageAnnotation],
    detections: Sequence[Sequence[DetectionLike]],
    obj_ids: Sequence[int] | None = None,
    min_visib_fract: float = 0.0,
) -> DetectionMetrics:
    """Box and mask mAP50-95 / mAP50 of ``detections[k]`` (the detections in image ``k``) against ``images[k]``.

    Args:
        images: ground truth per image (visible masks and boxes are used).
        detections: per image, the detections (obj_id, score, bbox_xyxy, mask in that image's pixels).
        obj_ids: categories to evaluate; None takes those in the ground truth and the detections.
        min_visib_fract: instances seen less than this are ignored (COCO crowd), neither needed nor penalised.

    Mask AP is NaN when any detection has no mask. No detections give AP 0 (NaN where there is no ground truth).

    Raises:
        ValueError: the number of detection lists differs from the number of images, or a mask's shape differs
            from its image.
    """
    if len(images) != len(detections):
        raise ValueError(f"detections: expected one list per image ({len(images)}), got {len(detections)}")
    for k, (image, dets) in enumerate(zip(images, detections, strict=True)):
        shape = (image.intrinsics.height, image.intrinsics.width)
        for det in dets:
            if det.mask is not None and np.shape(det.mask) != shape:
                raise ValueError(f"image {k}: detection mask shape {np.shape(det.mask)} != image shape {shape}")
    if obj_ids is None:
        gt_ids = {inst.obj_id for image in images for inst in image.instances if inst.px_count_visib}
        obj_ids = sorted(gt_ids | {int(d.obj_id) for dets in detections for d in dets})
    gt = coco_ground_truth(images, obj_ids, min_visib_fract)
    with_masks = all(d.mask is not None for dets in detections for d in dets)
    mask_results = coco_results(detections, with_masks=True) if with_masks else None
    return coco_detection_metrics(gt, coco_results(detections, with_masks=False), mask_results)


# -------------------------------------------------------------------------------------------------------- depth
@dataclass(frozen=True)
class DepthMetrics:
    """AbsRel (a fraction, lower is better) and delta1 (a fraction in [0, 1], higher is better) over ``n_valid``
    pixels; NaN when no pixel is valid. ``fill_rate``: the fraction of the reference's pixels with data (inside the
    mask) where the evaluated depth has data too (a sensor's dropouts); NaN when the reference has none."""

    abs_rel: float
    delta1: float
    n_valid: int
    fill_rate: float = math.nan


def depth_metrics(depth_m: np.ndarray, depth_ref_m: np.ndarray, mask: np.ndarray | None = None) -> DepthMetrics:
    """AbsRel and delta1 of ``depth_m`` against the reference ``depth_ref_m`` (both (h, w) metres, 0 = no data).

    Valid pixels: both depths finite and > 0, and ``mask`` (h, w) bool where given.
    """
    depth = np.asarray(depth_m, dtype=np.float64)
    ref = np.asarray(depth_ref_m, dtype=np.float64)
    if depth.ndim != 2 or depth.shape != ref.shape:
        raise ValueError(f"depth_m and depth_ref_m: expected two (h, w) arrays, got {depth.shape} and {ref.shape}")
    with np.errstate(invalid="ignore"):
        ref_valid = np.isfinite(ref) & (ref > 0)
        valid = np.isfinite(depth) & (depth > 0) & ref_valid
    if mask is not None:
        if np.shape(mask) != ref.shape:
            raise ValueError(f"mask: expected shape {ref.shape}, got {np.shape(mask)}")
        ref_valid &= np.asarray(mask, dtype=bool)
        valid &= ref_valid
    n, n_ref = int(np.count_nonzero(valid)), int(np.count_nonzero(ref_valid))
    fill_rate = n / n_ref if n_ref else math.nan
    if n == 0:
        return DepthMetrics(math.nan, math.nan, 0, fill_rate)
    d, d_ref = depth[valid], ref[valid]
    abs_rel = float(np.mean(np.abs(d - d_ref) / d_ref))
    delta1 = float(np.mean(np.maximum(d / d_ref, d_ref / d) < DELTA1_RATIO))
    return DepthMetrics(abs_rel, delta1, n, fill_rate)


def mean_depth_metrics(per_image: Iterable[DepthMetrics]) -> DepthMetrics:
    """Dataset-level AbsRel and delta1: the mean of the per-image values (images with no valid pixel skipped);
    ``fill_rate``: the mean over the images whose reference has data."""
    per_image = list(per_image)
    fills = [m.fill_rate for m in per_image if not math.isnan(m.fill_rate)]
    fill_rate = float(np.mean(fills)) if fills else math.nan
    items = [m for m in per_image if m.n_valid > 0]
    if not items:
        return DepthMetrics(math.nan, math.nan, 0, fill_rate)
    return DepthMetrics(
        float(np.mean([m.abs_rel for m in items])),
        float(np.mean([m.delta1 for m in items])),
        int(sum(m.n_valid for m in items)),
        fill_rate,
    )


# --------------------------------------------------------------------------------------------------------- pose
def _check_T(T: np.ndarray, name: str) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"{name}: expected a finite 4x4 transform, got shape {T.shape}")
    return T


def model_points(model: ObjectModel, n_points: int = DEFAULT_MODEL_POINTS, seed: int = 0) -> np.ndarray:
    """(n_points, 3) points [m] sampled uniformly from the model surface; the same seed gives the same points.

    Cached per (model, n_points, seed); the returned array is read-only.
    """
    return _model_points_cached(model, int(n_points), int(seed))


@lru_cache(maxsize=64)
def _model_points_cached(model: ObjectModel, n_points: int, seed: int) -> np.ndarray:
    if n_points < 1:
        raise ValueError(f"n_points must be >= 1, got {n_points}")
    points = sample_surface(model.mesh, n_points, np.random.default_rng(seed))
    points.setflags(write=False)
    return points


def add_m(T_est: np.ndarray, T_gt: np.ndarray, points: np.ndarray) -> float:
    """ADD [m]: mean distance between the (n, 3) model ``points`` moved by ``T_est`` and by ``T_gt`` (4x4)."""
    T_est, T_gt = _check_T(T_est, "T_est"), _check_T(T_gt, "T_gt")
    p = np.asarray(points, dtype=np.float64)
    diff = p @ (T_est[:3, :3] - T_gt[:3, :3]).T + (T_est[:3, 3] - T_gt[:3, 3])
    return float(np.mean(np.linalg.norm(diff, axis=1)))


def adds_m(T_est: np.ndarray, T_gt: np.ndarray, points: np.ndarray) -> float:
    """ADD-S [m]: mean over the (n, 3) model ``points`` moved by ``T_gt`` of the distance to the closest point
    of the model moved by ``T_est`` (a k-d tree query)."""
    T_est, T_gt = _check_T(T_est, "T_est"), _check_T(T_gt, "T_gt")
    p = np.asarray(points, dtype=np.float64)
    p_est = p @ T_est[:3, :3].T + T_est[:3, 3]
    p_gt = p @ T_gt[:3, :3].T + T_gt[:3, 3]
    distance, _ = cKDTree(p_est).query(p_gt, k=1)
    return float(np.mean(distance))


def rotation_error_deg(R_est: np.ndarray, R_gt: np.ndarray) -> float:
    """re [deg]: the angle of the rotation ``R_est R_gt^T`` between two 3x3 rotations, in [0, 180]."""
    R_est, R_gt = np.asarray(R_est, dtype=np.float64), np.asarray(R_gt, dtype=np.float64)
    if R_est.shape != (3, 3) or R_gt.shape != (3, 3):
        raise ValueError(f"R_est and R_gt: expected 3x3 rotations, got {R_est.shape} and {R_gt.shape}")
    cos = (np.trace(R_est @ R_gt.T) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def translation_error_m(t_est: np.ndarray, t_gt: np.ndarray) -> float:
    """te [m]: Euclidean distance between two translations (3-vectors, metres)."""
    t_est, t_gt = np.asarray(t_est, dtype=np.float64).reshape(-1), np.asarray(t_gt, dtype=np.float64).reshape(-1)
    if t_est.shape != (3,) or t_gt.shape != (3,):
        raise ValueError(f"t_est and t_gt: expected 3-vectors, got {t_est.shape} and {t_gt.shape}")
    return float(np.linalg.norm(t_est - t_gt))


def symmetric_pose_errors(T_est: np.ndarray, T_gt: np.ndarray, symmetry_transforms: np.ndarray) -> tuple[float, float]:
    """(re [deg], te [m]) against the closest symmetric equivalent of ``T_gt``.

    ``symmetry_transforms``: (n, 4, 4) ``T_obj_obj`` mapping the model onto itself, identity included
    (``ObjectModel.symmetry_transforms()``). The equivalent pose ``T_gt @ S`` with the smallest rotation error is
    chosen; te is measured to that same pose (equal to the plain te when the symmetry axes pass through the origin).
    """
    T_est, T_gt = _check_T(T_est, "T_est"), _check_T(T_gt, "T_gt")
    S = np.asarray(symmetry_transforms, dtype=np.float64)
    if S.ndim != 3 or S.shape[1:] != (4, 4) or len(S) == 0:
        raise ValueError(f"symmetry_transforms: expected (n, 4, 4) with n >= 1, got shape {S.shape}")
    T_gt_sym = T_gt @ S  # (n, 4, 4)
    traces = np.einsum("ij,nij->n", T_est[:3, :3], T_gt_sym[:, :3, :3])  # trace(R_est R^T) for each candidate
    cos = np.clip((traces - 1.0) / 2.0, -1.0, 1.0)
    best = int(np.argmax(cos))
    re = float(np.degrees(np.arccos(cos[best])))
    return re, translation_error_m(T_est[:3, 3], T_gt_sym[best, :3, 3])


@dataclass(frozen=True)
class PoseErrors:
    """The errors of one pose estimate of an object instance (or of a missed instance).

    ``add_m``: ADD for an asymmetric model, ADD-S for a symmetric one (``metric`` says which); ``inf`` for a miss.
    ``re_deg``: symmetry-aware rotation error; ``te_m``: translation error (NaN for a miss).
    """

    obj_id: int
    metric: str
    add_m: float
    re_deg: float
    te_m: float
    diameter_m: float

    @property
    def estimated(self) -> bool:
        return math.isfinite(self.add_m)

    def correct(self, threshold_fraction: float = ADD_THRESHOLD_FRACTION) -> bool:
        """ADD(-S) below ``threshold_fraction`` x diameter."""
        return self.add_m < threshold_fraction * self.diameter_m


def pose_errors(
    T_est: np.ndarray | None,
    T_gt: np.ndarray,
    model: ObjectModel,
    points: np.ndarray | None = None,
    continuous_steps: int = 360,
) -> PoseErrors:
    """ADD or ADD-S (by ``model.is_symmetric``), symmetry-aware re and te of ``T_est`` against ``T_gt`` (4x4, m).

    ``T_est`` None records a missed instance. ``points``: (n, 3) model points, default ``model_points(model)``.
    ``continuous_steps``: samples per turn of a continuous symmetry for re (360: 1 degree; the residual is at most
    half a step).
    """
    metric = "ADD-S" if model.is_symmetric else "ADD"
    if T_est is None:
        return PoseErrors(int(model.obj_id), metric, math.inf, math.nan, math.nan, float(model.diameter_m))
    pts = model_points(model) if points is None else points
    add = adds_m(T_est, T_gt, pts) if model.is_symmetric else add_m(T_est, T_gt, pts)
    re, te = symmetric_pose_errors(T_est, T_gt, _symmetry_transforms(model, int(continuous_steps)))
    return PoseErrors(int(model.obj_id), metric, add, re, te, float(model.diameter_m))


@lru_cache(maxsize=64)
def _symmetry_transforms(model: ObjectModel, continuous_steps: int) -> np.ndarray:
    return model.symmetry_transforms(continuous_steps)


def _summary(records: Sequence[PoseErrors], threshold_fraction: float) -> dict:
    found = [r for r in records if r.estimated]
    metrics = sorted({r.metric for r in records})
    return {
        "metric": metrics[0] if len(metrics) == 1 else "ADD(-S)",
        "n": len(records),
        "n_estimated": len(found),
        "add_recall": float(np.mean([r.correct(threshold_fraction) for r in records])) if records else math.nan,
        "median_add_mm": float(np.median([r.add_m for r in found]) * 1e3) if found else math.nan,
        "median_re_deg": float(np.median([r.re_deg for r in found])) if found else math.nan,
        "median_te_mm": float(np.median([r.te_m for r in found]) * 1e3) if found else math.nan,
    }


def pose_metrics_table(
    records: Iterable[PoseErrors], threshold_fraction: float = ADD_THRESHOLD_FRACTION
) -> dict[str, dict]:
    """Per-object and overall pose accuracy.

    Returns ``{"per_object": {obj_id: row}, "all": row}`` with each row ``{"metric", "n", "n_estimated",
    "add_recall" (fraction of instances with ADD(-S) < threshold x diameter; misses count as failures),
    "median_add_mm", "median_re_deg", "median_te_mm"}`` (medians over the estimated instances; NaN if none).
    """
    records = list(records)
    by_obj: dict[int, list[PoseErrors]] = {}
    for r in records:
        by_obj.setdefault(r.obj_id, []).append(r)
    return {
        "per_object": {obj_id: _summary(rs, threshold_fraction) for obj_id, rs in sorted(by_obj.items())},
        "all": _summary(records, threshold_fraction),
    }
