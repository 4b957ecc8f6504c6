"""Box maths of the anchor-free head (torch): anchor points, distance (ltrb) <-> box, the DFL expectation and CIoU.

Anchors are the centres of the feature-map cells, ``(j + 0.5, i + 0.5)`` in cells of their level; a box is
predicted as its distances to the four sides (left, top, right, bottom) in cells of the anchor's stride, each as a
discrete distribution over ``0 .. reg_max - 1`` whose expectation is the distance (distribution focal loss, Li et
al. 2020, as in YOLOv8).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch


def make_anchors(
    shapes: Sequence[tuple[int, int]],
    strides: Sequence[int],
    dtype: torch.dtype = torch.float32,
    device: torch.device | str | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Anchor points (A, 2) ``(x, y)`` in cells of their level, and each anchor's stride (A, 1) in input pixels,
    level by level, row-major within a level (the order of the flattened head outputs)."""
    points, stride_list = [], []
    for (h, w), s in zip(shapes, strides, strict=True):
        ys = torch.arange(h, dtype=dtype, device=device) + 0.5
        xs = torch.arange(w, dtype=dtype, device=device) + 0.5
        gy, gx = torch.meshgrid(ys, xs, indexing="ij")
        points.append(torch.stack((gx, gy), -1).reshape(-1, 2))
        stride_list.append(torch.full((h * w, 1), float(s), dtype=dtype, device=device))
    return torch.cat(points), torch.cat(stride_list)


def dist_to_box(ltrb: torch.Tensor, anchors: torch.Tensor) -> torch.Tensor:
    """(..., 4) distances left, top, right, bottom from (..., 2) anchor points -> (..., 4) ``x0, y0, x1, y1``."""
    lt, rb = ltrb[..., :2], ltrb[..., 2:]
    return torch.cat((anchors - lt, anchors + rb), -1)


def box_to_dist(anchors: torch.Tensor, boxes_xyxy: torch.Tensor, max_dist: float) -> torch.Tensor:
    """Inverse of ``dist_to_box``, clamped to ``[0, max_dist]`` (the DFL support ends at ``reg_max - 1``; a
    little below it so that the upper of the two target bins exists)."""
    return torch.cat((anchors - boxes_xyxy[..., :2], boxes_xyxy[..., 2:] - anchors), -1).clamp(0.0, max_dist)


def dfl_expectation(logits: torch.Tensor, reg_max: int) -> torch.Tensor:
    """(..., 4 * reg_max) bin logits -> (..., 4) expected distances (softmax over each side's bins)."""
    probs = logits.reshape(*logits.shape[:-1], 4, reg_max).softmax(-1)
    bins = torch.arange(reg_max, dtype=logits.dtype, device=logits.device)
    return (probs * bins).sum(-1)


def box_ciou(box1: torch.Tensor, box2: torch.Tensor, eps: float = 1e-7) -> torch.Tensor:
    """Complete IoU (Zheng et al. 2020) of matching ``x0, y0, x1, y1`` boxes (..., 4) -> (...): the IoU minus the
    normalised centre distance and the aspect-ratio consistency term."""
    b1x0, b1y0, b1x1, b1y1 = box1.unbind(-1)
    b2x0, b2y0, b2x1, b2y1 = box2.unbind(-1)
    w1, h1 = b1x1 - b1x0, (b1y1 - b1y0).clamp(min=eps)
    w2, h2 = b2x1 - b2x0, (b2y1 - b2y0).clamp(min=eps)
    inter = (torch.minimum(b1x1, b2x1) - torch.maximum(b1x0, b2x0)).clamp(min=0) * (
        torch.minimum(b1y1, b2y1) - torch.maximum(b1y0, b2y0)
    ).clamp(min=0)
    union = w1 * h1 + w2 * h2 - inter + eps
    iou = inter / union
    cw = torch.maximum(b1x1, b2x1) - torch.minimum(b1x0, b2x0)
    ch = torch.maximum(b1y1, b2y1) - torch.minimum(b1y0, b2y0)
    c2 = cw**2 + ch**2 + eps  # squared diagonal of the enclosing box
    rho2 = ((b2x0 + b2x1 - b1x0 - b1x1) ** 2 + (b2y0 + b2y1 - b1y0 - b1y1) ** 2) / 4  # squared centre distance
    v = (4 / math.pi**2) * (torch.atan(w2 / h2) - torch.atan(w1 / h1)).pow(2)
    with torch.no_grad():
        alpha = v / (v - iou + (1 + eps))
    return iou - (rho2 / c2 + v * alpha)
