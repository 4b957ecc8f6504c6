"""Validation of the detector during training: post-processing of the decoded outputs and COCO mAP.

Post-processing follows the runtime (``perception.detector``, which ``sygrid`` may not import): the best class
per anchor above a low confidence, class-aware NMS (OpenCV), masks as ``sigmoid(coefficients @ prototypes)``
resampled bilinearly straight into image pixels inside each box, threshold 0.5. A low confidence threshold (0.001)
and up to 100 detections per image, as COCO evaluation expects.

mAP50-95 / mAP50 for boxes and masks come from ``pycocotools``' COCOeval against the dataset's validation ground
truth in original image pixels (the COCO annotations of the visible masks, or the rasterised YOLO polygons).
``sygrid.metrics.detection_metrics`` computes the same figures but from ``ImageAnnotation`` ground truth (the BOP
side of a dataset), which a YOLO folder does not have; so COCOeval is called directly here.
"""

from __future__ import annotations

import contextlib
import io
import math
from dataclasses import dataclass

import cv2
import numpy as np
from pycocotools import mask as mask_utils
from pycocotools.coco import COCO
from pycocotools.cocoeval import COCOeval

from sygrid.train.detector.augment import MASK_STRIDE, LetterboxGeometry

VAL_CONF_THRESHOLD = 0.001
VAL_IOU_THRESHOLD = 0.7
VAL_MAX_DETECTIONS = 100
MAX_NMS_CANDIDATES = 3000


@dataclass(frozen=True)
class ImageDetections:
    """Detections in one image, in its original pixels: ``boxes_xyxy`` (n, 4), ``scores`` (n,), ``classes`` (n,)
    int, ``rles`` COCO RLEs of the masks (empty for a detection-only evaluation)."""

    boxes_xyxy: np.ndarray
    scores: np.ndarray
    classes: np.ndarray
    rles: list


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-x))


def postprocess(
    output0: np.ndarray,
    protos: np.ndarray | None,
    geometry: LetterboxGeometry,
    num_classes: int,
    conf_threshold: float = VAL_CONF_THRESHOLD,
    iou_threshold: float = VAL_IOU_THRESHOLD,
    max_detections: int = VAL_MAX_DETECTIONS,
) -> ImageDetections:
    """One image's ``output0`` (4 + nc + nm, A) and ``protos`` (nm, H/4, W/4) -> its detections in image pixels."""
    scores_all = output0[4 : 4 + num_classes]
    best = scores_all.max(0)
    keep = np.flatnonzero(best > conf_threshold)
    keep = keep[np.argsort(-best[keep], kind="stable")][:MAX_NMS_CANDIDATES]
    classes = scores_all[:, keep].argmax(0)
    scores = best[keep]
    cx, cy, w, h = output0[:4, keep].astype(np.float64)
    boxes = np.stack([cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2], 1)
    if len(keep):
        xywh = np.stack([boxes[:, 0], boxes[:, 1], w, h], 1)
        kept = np.asarray(
            cv2.dnn.NMSBoxesBatched(xywh.tolist(), scores.tolist(), classes.tolist(), conf_threshold, iou_threshold),
            dtype=np.int64,
        ).reshape(-1)
        kept = kept[np.argsort(-scores[kept], kind="stable")][:max_detections]
    else:
        kept = np.zeros(0, np.int64)
    boxes_image = geometry.boxes_to_image(boxes[kept])
    rles = []
    if protos is not None:
        coefficients = output0[4 + num_classes :, keep[kept]].T  # (n, nm)
        for k in range(len(kept)):
            rles.append(_mask_rle(coefficients[k], protos, boxes_image[k], geometry))
    return ImageDetections(boxes_image, scores[kept].astype(np.float64), classes[kept].astype(np.int64), rles)


def _mask_rle(coefficients: np.ndarray, protos: np.ndarray, box: np.ndarray, g: LetterboxGeometry) -> dict:
    """The instance mask inside ``box`` (image pixels), resampled from the prototype grid in one affine warp."""
    nm, mh, mw = protos.shape
    h, w = g.image_hw
    prob = _sigmoid(coefficients @ protos.reshape(nm, -1)).reshape(mh, mw).astype(np.float32)
    x0, y0 = math.floor(box[0]), math.floor(box[1])
    x1, y1 = min(math.ceil(box[2]), w), min(math.ceil(box[3]), h)
    mask = np.zeros((h, w), dtype=np.uint8)
    if x1 > x0 and y1 > y0:
        sx, sy = g.resized_hw[1] / w, g.resized_hw[0] / h
        # Image pixel (u, v) of the box region, centre (x0 + u + 0.5) -> prototype index coordinate.
        ax, ay = sx / MASK_STRIDE, sy / MASK_STRIDE
        bx = ((x0 + 0.5) * sx + g.pad_left) / MASK_STRIDE - 0.5
        by = ((y0 + 0.5) * sy + g.pad_top) / MASK_STRIDE - 0.5
        M = np.array([[ax, 0.0, bx], [0.0, ay, by]])
        region = cv2.warpAffine(
            prob, M, (x1 - x0, y1 - y0), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REPLICATE
        )
        mask[y0:y1, x0:x1] = region > 0.5
    return mask_utils.encode(np.asfortranarray(mask))


@dataclass(frozen=True)
class ValMetrics:
    """COCO AP on the validation split, in [0, 1] (NaN with no ground truth). ``per_class``: obj_id ->
    {box_ap50_95, box_ap50, mask_ap50_95, mask_ap50}."""

    box_map50_95: float
    box_map50: float
    mask_map50_95: float
    mask_map50: float
    per_class: dict
    n_images: int
    n_detections: int

    def as_dict(self) -> dict:
        return {
            "box_map50_95": self.box_map50_95,
            "box_map50": self.box_map50,
            "mask_map50_95": self.mask_map50_95,
            "mask_map50": self.mask_map50,
            "per_class": {str(k): v for k, v in self.per_class.items()},
            "n_images": self.n_images,
            "n_detections": self.n_detections,
        }


def coco_evaluate(gt: dict, detections: list[ImageDetections], obj_ids: list[int]) -> ValMetrics:
    """COCOeval of ``detections[k]`` (image id ``k + 1`` of ``gt``) for boxes and, where masks exist, masks."""
    if len(detections) != len(gt["images"]):
        raise ValueError(
            f"detections: expected one entry per ground-truth image ({len(gt['images'])}), got {len(detections)}"
        )
    box_results, mask_results = [], []
    for k, det in enumerate(detections):
        for j in range(len(det.scores)):
            x0, y0, x1, y1 = (float(v) for v in det.boxes_xyxy[j])
            record = {
                "image_id": k + 1,
                "category_id": int(obj_ids[int(det.classes[j])]),
                "bbox": [x0, y0, x1 - x0, y1 - y0],
                "score": float(det.scores[j]),
            }
            box_results.append(record)
            if det.rles:
                mask_results.append({**record, "segmentation": det.rles[j]})
    box = _coco_ap(gt, box_results, "bbox")
    with_masks = all(bool(d.rles) or len(d.scores) == 0 for d in detections)
    mask = _coco_ap(gt, mask_results, "segm") if with_masks else (math.nan, math.nan, {})
    per_class = {
        i: {
            "box_ap50_95": box[2].get(i, (math.nan, math.nan))[0],
            "box_ap50": box[2].get(i, (math.nan, math.nan))[1],
            "mask_ap50_95": mask[2].get(i, (math.nan, math.nan))[0],
            "mask_ap50": mask[2].get(i, (math.nan, math.nan))[1],
        }
        for i in obj_ids
    }
    return ValMetrics(box[0], box[1], mask[0], mask[1], per_class, len(detections), len(box_results))


def _coco_ap(gt: dict, results: list[dict], iou_type: str) -> tuple[float, float, dict]:
    has_gt = {a["category_id"] for a in gt["annotations"] if not a.get("iscrowd", 0)}
    if not results:  # COCO.loadRes refuses an empty list; with nothing detected every AP is 0
        return (0.0, 0.0, {i: (0.0, 0.0) for i in has_gt}) if has_gt else (math.nan, math.nan, {})
    with contextlib.redirect_stdout(io.StringIO()):  # pycocotools prints progress and its summary table
        coco_gt = COCO()
        coco_gt.dataset = gt
        coco_gt.createIndex()
        coco_dt = coco_gt.loadRes(results)
        evaluator = COCOeval(coco_gt, coco_dt, iouType=iou_type)
        evaluator.params.catIds = [c["id"] for c in gt["categories"]]
        evaluator.evaluate()
        evaluator.accumulate()
        evaluator.summarize()
    map50_95, map50 = (float(v) if v > -1 else math.nan for v in evaluator.stats[:2])
    precision = evaluator.eval["precision"][:, :, :, 0, -1]  # [iou, recall, class, area "all", max dets 100]
    iou50 = int(np.argmin(np.abs(evaluator.params.iouThrs - 0.5)))
    per_class = {}
    for k, cat in enumerate(evaluator.params.catIds):
        p_all, p_50 = precision[:, :, k], precision[iou50, :, k]
        per_class[cat] = (
            float(p_all[p_all > -1].mean()) if np.any(p_all > -1) else math.nan,
            float(p_50[p_50 > -1].mean()) if np.any(p_50 > -1) else math.nan,
        )
    return map50_95, map50, per_class
