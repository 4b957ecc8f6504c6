"""Post-processing of a YOLO(v8)-seg network's outputs (numpy + OpenCV): one rule for training validation
(``sygrid.train.detector.evaluate``) and the runtime (``perception.detector``).

Output contract (the ultralytics YOLOv8-seg layout): ``output0`` ``[1, 4 + nc + nm, A]`` (or ``[4 + nc + nm, A]``),
per anchor the box ``cx, cy, w, h`` in network-input pixels, ``nc`` class scores (already sigmoided, no
objectness) and ``nm`` mask coefficients; the prototypes ``[nm, mh, mw]`` cover the network input (a detection-only
model has none and ``nm = 0``).

Steps: each anchor votes for its best class above a confidence threshold (ultralytics' single-label prediction),
class-aware NMS (OpenCV), boxes mapped back through the letterbox into image pixels, then per kept box the mask
``sigmoid(coefficients @ prototypes)`` resampled bilinearly straight into image pixels (upsampling and
un-letterboxing in one affine warp), cropped to the box, threshold ``MASK_THRESHOLD``. Masks are built only inside
each box, so their cost scales with the box area.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from sygrid.letterbox import Letterbox

MAX_NMS_CANDIDATES = 30000  # boxes entering NMS at most (highest scores first): bounds the cost of a noisy frame
MASK_THRESHOLD = 0.5


@dataclass(frozen=True)
class DecodedDetections:
    """The kept detections of one image, highest score first, in its original pixels.

    ``boxes_xyxy`` (n, 4) float64 clipped to the image; ``scores`` (n,) float64; ``class_index`` (n,) int64 (the
    network's class, not an obj_id); ``masks``: (h, w) bool per detection, or None for a detection-only model.
    """

    boxes_xyxy: np.ndarray
    scores: np.ndarray
    class_index: np.ndarray
    masks: list[np.ndarray] | None


def decode_predictions(
    output0: np.ndarray, num_classes: int, conf_threshold: float, max_candidates: int = MAX_NMS_CANDIDATES
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Candidates of one ``[1, 4 + nc + nm, A]`` (or ``[4 + nc + nm, A]``) prediction above ``conf_threshold``.

    Returns ``boxes_xyxy`` (n, 4) input pixels, ``scores`` (n,), ``class_index`` (n,) int, ``coefficients`` (n, nm)
    (nm = 0 for a detection-only model), at most ``max_candidates``, highest score first. Each anchor votes for
    its best class only.
    """
    pred = output0[0] if output0.ndim == 3 else output0
    class_scores = pred[4 : 4 + num_classes]
    best = class_scores.max(axis=0)  # the max over classes first: cheaper than an argmax over every anchor
    keep = np.flatnonzero(best > conf_threshold)
    keep = keep[np.argsort(-best[keep], kind="stable")][:max_candidates]
    class_index = np.argmax(class_scores[:, keep], axis=0)
    cx, cy, w, h = pred[0:4, keep].astype(np.float64)
    boxes = np.stack([cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2], axis=1)
    coefficients = pred[4 + num_classes :, keep].T.astype(np.float32)
    return boxes, best[keep].astype(np.float64), class_index.astype(np.int64), coefficients


def class_aware_nms(
    boxes_xyxy: np.ndarray, scores: np.ndarray, class_index: np.ndarray, iou_threshold: float, max_detections: int
) -> np.ndarray:
    """Indices of the boxes kept by per-class NMS (IoU > ``iou_threshold`` with a better box of the same class
    suppresses), highest score first, at most ``max_detections``. OpenCV's batched NMS does the work."""
    if len(boxes_xyxy) == 0:
        return np.zeros(0, dtype=np.int64)
    xywh = np.concatenate([boxes_xyxy[:, :2], boxes_xyxy[:, 2:] - boxes_xyxy[:, :2]], axis=1)
    kept = np.asarray(
        cv2.dnn.NMSBoxesBatched(
            xywh.astype(np.float64), scores.astype(np.float32), class_index.astype(np.int32), -math.inf, iou_threshold
        ),
        dtype=np.int64,
    ).reshape(-1)
    kept = kept[np.argsort(-scores[kept], kind="stable")]
    return kept[:max_detections]


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return 0.5 * (1.0 + np.tanh(0.5 * x))  # = 1 / (1 + exp(-x)), without overflow warnings


def assemble_mask(
    coefficients: np.ndarray, prototypes: np.ndarray, box_image_xyxy: np.ndarray, geometry: Letterbox
) -> np.ndarray:
    """The (h, w) bool instance mask, in original image pixels, of one detection.

    Args:
        coefficients: (nm,) mask coefficients of the detection.
        prototypes: (nm, mh, mw) mask prototypes covering the network input.
        box_image_xyxy: (4,) the detection's box in image pixels: the mask is cropped to it (pixel centres inside).
        geometry: the letterbox that made the network input.

    The mask probability ``sigmoid(coefficients @ prototypes)`` is resampled bilinearly (edge pixels replicated,
    like an ``align_corners=False`` upsampling) at each image pixel centre, mapped back through the letterbox to
    prototype coordinates; pixels above ``MASK_THRESHOLD`` are the mask. Only the prototype window under the box is
    computed.
    """
    h, w = geometry.image_hw
    mask = np.zeros((h, w), dtype=bool)
    x0, y0, x1, y1 = (float(v) for v in box_image_xyxy)
    # Pixels whose centre (j + 0.5) lies in [x0, x1).
    j0, j1 = max(0, math.ceil(x0 - 0.5)), min(w, math.ceil(x1 - 0.5))
    i0, i1 = max(0, math.ceil(y0 - 0.5)), min(h, math.ceil(y1 - 0.5))
    if j1 <= j0 or i1 <= i0:
        return mask
    nm, mh, mw = prototypes.shape
    in_h, in_w = geometry.input_hw
    # Image pixel (j, i) centre -> prototype index coordinates: x_p = ((j + 0.5) * s_x + pad_left) * mw / in_w - 0.5.
    ax, ay = geometry.scale_x * mw / in_w, geometry.scale_y * mh / in_h
    bx = (0.5 * geometry.scale_x + geometry.pad_left) * mw / in_w - 0.5
    by = (0.5 * geometry.scale_y + geometry.pad_top) * mh / in_h - 0.5
    # The prototype window the box needs (one cell of margin for the bilinear neighbours).
    px0 = min(max(math.floor(ax * j0 + bx), 0), mw - 1)
    px1 = min(max(math.floor(ax * (j1 - 1) + bx) + 2, px0 + 1), mw)
    py0 = min(max(math.floor(ay * i0 + by), 0), mh - 1)
    py1 = min(max(math.floor(ay * (i1 - 1) + by) + 2, py0 + 1), mh)
    window = prototypes[:, py0:py1, px0:px1].reshape(nm, -1)  # a small copy: the window under the box
    probability = _sigmoid(coefficients @ window).reshape(py1 - py0, px1 - px0).astype(np.float32)
    # Output pixel (u, v) = image pixel (j0 + u, i0 + v) samples the window at (ax*(j0+u) + bx - px0, ...). Bilinear
    # by hand, separable: cv2.warpAffine quantises sample positions to 1/32 pixel, which moves mask borders by a
    # pixel on small parts.
    patch = _bilinear_rows(_bilinear_rows(probability, ay * np.arange(i0, i1) + by - py0).T,
                           ax * np.arange(j0, j1) + bx - px0).T  # fmt: skip
    mask[i0:i1, j0:j1] = patch > MASK_THRESHOLD
    return mask


def _bilinear_rows(values: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """``values`` (n, m) linearly interpolated at the fractional row coordinates ``rows`` (k,), edge rows replicated:
    (k, m)."""
    n = values.shape[0]
    r = np.clip(rows, 0.0, n - 1.0)
    lo = np.minimum(np.floor(r).astype(np.int64), n - 1)
    hi = np.minimum(lo + 1, n - 1)
    t = (r - lo)[:, None]
    return values[lo] * (1.0 - t) + values[hi] * t


def postprocess(
    output0: np.ndarray,
    prototypes: np.ndarray | None,
    geometry: Letterbox,
    num_classes: int,
    conf_threshold: float,
    iou_threshold: float,
    max_detections: int,
    max_candidates: int = MAX_NMS_CANDIDATES,
) -> DecodedDetections:
    """One image's outputs -> its detections in image pixels: decode, class-aware NMS, masks.

    Args:
        output0: ``[1, 4 + nc + nm, A]`` or ``[4 + nc + nm, A]`` predictions.
        prototypes: ``[nm, mh, mw]`` (or ``[1, nm, mh, mw]``) mask prototypes; None for a detection-only model.
        geometry: the letterbox that made the network input from the image.
        num_classes: ``nc``.
        conf_threshold: least class score of a candidate; iou_threshold: NMS overlap above which the lower-scored
            box of a class is dropped; max_detections: most detections kept; max_candidates: most boxes entering NMS.
    """
    boxes, scores, classes, coefficients = decode_predictions(output0, num_classes, conf_threshold, max_candidates)
    kept = class_aware_nms(boxes, scores, classes, iou_threshold, max_detections)
    boxes_image = geometry.boxes_to_image(boxes[kept])
    masks = None
    if prototypes is not None:
        protos = prototypes[0] if prototypes.ndim == 4 else prototypes
        protos = protos.astype(np.float32, copy=False)
        masks = [assemble_mask(coefficients[idx], protos, boxes_image[k], geometry) for k, idx in enumerate(kept)]
    return DecodedDetections(boxes_image, scores[kept], classes[kept], masks)
