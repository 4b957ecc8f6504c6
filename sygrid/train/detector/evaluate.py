"""Validation of the detector during training: the runtime's post-processing, then COCO mAP.

Post-processing is ``sygrid.detection_decode`` (the runtime's code) with a low confidence threshold
(``VAL_CONF_THRESHOLD``) and up to ``VAL_MAX_DETECTIONS`` detections per image, as COCO evaluation expects; masks
are kept as COCO RLEs. mAP50-95 / mAP50 for boxes and masks come from ``sygrid.metrics.coco_detection_metrics``
against the dataset's validation ground truth in original image pixels (the COCO annotations of the visible masks,
or the rasterised YOLO polygons): a YOLO folder has no ``ImageAnnotation`` ground truth, so the COCO dataset is
passed as it is.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pycocotools import mask as mask_utils

from sygrid.detection_decode import postprocess
from sygrid.letterbox import Letterbox
from sygrid.metrics import DetectionMetrics, coco_detection_metrics, coco_result

VAL_CONF_THRESHOLD = 0.001
VAL_IOU_THRESHOLD = 0.7
VAL_MAX_DETECTIONS = 100
VAL_MAX_NMS_CANDIDATES = 3000


@dataclass(frozen=True)
class ImageDetections:
    """Detections in one image, in its original pixels: ``boxes_xyxy`` (n, 4), ``scores`` (n,), ``classes`` (n,)
    int (class indices), ``rles`` COCO RLEs of the masks (empty for a detection-only evaluation)."""

    boxes_xyxy: np.ndarray
    scores: np.ndarray
    classes: np.ndarray
    rles: list


def val_detections(
    output0: np.ndarray,
    protos: np.ndarray | None,
    geometry: Letterbox,
    num_classes: int,
    conf_threshold: float = VAL_CONF_THRESHOLD,
    iou_threshold: float = VAL_IOU_THRESHOLD,
    max_detections: int = VAL_MAX_DETECTIONS,
) -> ImageDetections:
    """One image's ``output0`` (4 + nc + nm, A) and ``protos`` (nm, H/4, W/4) -> its detections in image pixels."""
    decoded = postprocess(
        output0,
        protos,
        geometry,
        num_classes,
        conf_threshold,
        iou_threshold,
        max_detections,
        max_candidates=VAL_MAX_NMS_CANDIDATES,
    )
    masks = decoded.masks or []
    rles = [mask_utils.encode(np.asfortranarray(m.astype(np.uint8))) for m in masks]
    return ImageDetections(decoded.boxes_xyxy, decoded.scores, decoded.class_index, rles)


def coco_evaluate(gt: dict, detections: list[ImageDetections], obj_ids: list[int]) -> DetectionMetrics:
    """COCO AP of ``detections[k]`` (image id ``k + 1`` of the COCO dataset ``gt``; class ``c`` is category
    ``obj_ids[c]``) for boxes and, where every image with detections has masks, masks (else the mask AP is NaN)."""
    if len(detections) != len(gt["images"]):
        raise ValueError(
            f"detections: expected one entry per ground-truth image ({len(gt['images'])}), got {len(detections)}"
        )
    box_results, mask_results = [], []
    for k, det in enumerate(detections):
        for j in range(len(det.scores)):
            obj_id = obj_ids[int(det.classes[j])]
            box_results.append(coco_result(k, obj_id, det.scores[j], det.boxes_xyxy[j]))
            if det.rles:
                mask_results.append(coco_result(k, obj_id, det.scores[j], det.boxes_xyxy[j], det.rles[j]))
    with_masks = all(bool(d.rles) or len(d.scores) == 0 for d in detections)
    return coco_detection_metrics(gt, box_results, mask_results if with_masks else None)
