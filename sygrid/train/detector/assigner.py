"""Task-aligned assignment of anchors to ground-truth boxes (TOOD, Feng et al. 2021; as YOLOv8 trains with it).

For every ground truth, the candidates are the anchors whose centre lies inside its box. Each candidate gets the
alignment metric ``t = s^alpha * u^beta`` (``s`` the predicted score of the ground truth's class, ``u`` the CIoU
of the predicted box with the ground truth, clamped at 0); the ``topk`` candidates with the highest ``t`` become
positives. An anchor positive for several ground truths keeps the one it overlaps most. The class target of a
positive is its metric normalised per ground truth so that the best anchor of each ground truth gets that anchor's
IoU: ``t * max_u / max_t``, which ties the classification score to the localisation quality.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from sygrid.train.detector.boxes import box_ciou


@dataclass(frozen=True)
class Assignment:
    """Targets per anchor. ``fg`` (B, A) bool: positive anchors. ``gt_index`` (B, A) long: the assigned ground truth
    (0 for negatives). ``labels`` (B, A) long, ``boxes`` (B, A, 4) ``x0, y0, x1, y1`` pixels: of that ground truth.
    ``scores`` (B, A, C): the soft class targets (zero for negatives)."""

    fg: torch.Tensor
    gt_index: torch.Tensor
    labels: torch.Tensor
    boxes: torch.Tensor
    scores: torch.Tensor


class TaskAlignedAssigner:
    """``topk`` positives per ground truth by the metric ``score^alpha * iou^beta``."""

    def __init__(self, num_classes: int, topk: int = 10, alpha: float = 0.5, beta: float = 6.0, eps: float = 1e-9):
        if topk < 1:
            raise ValueError(f"topk must be >= 1, got {topk}")
        self.num_classes = num_classes
        self.topk = topk
        self.alpha = alpha
        self.beta = beta
        self.eps = eps

    @torch.no_grad()
    def __call__(
        self,
        pred_scores: torch.Tensor,
        pred_boxes: torch.Tensor,
        anchors: torch.Tensor,
        gt_labels: torch.Tensor,
        gt_boxes: torch.Tensor,
        gt_valid: torch.Tensor,
    ) -> Assignment:
        """Assign anchors to ground truths.

        Args:
            pred_scores: (B, A, C) predicted class probabilities (after the sigmoid).
            pred_boxes: (B, A, 4) predicted boxes ``x0, y0, x1, y1`` in pixels.
            anchors: (A, 2) anchor centres in pixels.
            gt_labels: (B, M) long class indices (padded).
            gt_boxes: (B, M, 4) ground-truth boxes in pixels (padded).
            gt_valid: (B, M) bool, False for padding.
        """
        b, a, c = pred_scores.shape
        m = gt_boxes.shape[1]
        device = pred_scores.device
        if m == 0 or not bool(gt_valid.any()):
            return Assignment(
                torch.zeros((b, a), dtype=torch.bool, device=device),
                torch.zeros((b, a), dtype=torch.long, device=device),
                torch.zeros((b, a), dtype=torch.long, device=device),
                torch.zeros((b, a, 4), dtype=pred_boxes.dtype, device=device),
                torch.zeros_like(pred_scores),
            )
        # Candidates: anchor centres strictly inside the (valid) ground-truth box.
        lt = anchors[None, None] - gt_boxes[:, :, None, :2]  # (B, M, A, 2)
        rb = gt_boxes[:, :, None, 2:] - anchors[None, None]
        candidate = (torch.cat((lt, rb), -1).amin(-1) > self.eps) & gt_valid[:, :, None]  # (B, M, A)

        labels = gt_labels.clamp(0, c - 1)
        score = pred_scores.gather(2, labels[:, None, :].expand(b, a, m)).transpose(1, 2)  # (B, M, A)
        iou = torch.zeros((b, m, a), dtype=pred_boxes.dtype, device=device)
        bi, gi, ai = candidate.nonzero(as_tuple=True)
        iou[bi, gi, ai] = box_ciou(gt_boxes[bi, gi], pred_boxes[bi, ai]).clamp(min=0).to(iou.dtype)
        metric = score.pow(self.alpha) * iou.pow(self.beta) * candidate

        k = min(self.topk, a)
        top = metric.topk(k, dim=-1).indices  # (B, M, k)
        positive = torch.zeros_like(candidate).scatter_(-1, top, True) & candidate

        # An anchor claimed by several ground truths keeps the one with the highest IoU among them.
        claims = positive.sum(1)  # (B, A)
        if bool((claims > 1).any()):
            best = (iou * positive).argmax(1)  # (B, A)
            only_best = torch.zeros_like(positive).scatter_(1, best[:, None, :], True)
            positive = torch.where((claims > 1)[:, None, :], only_best & positive, positive)
        fg = positive.any(1)
        gt_index = positive.to(torch.uint8).argmax(1)  # (B, A)

        target_labels = labels.gather(1, gt_index)
        target_boxes = gt_boxes.gather(1, gt_index[..., None].expand(b, a, 4))
        metric = metric * positive
        norm = metric * (iou * positive).amax(-1, keepdim=True) / (metric.amax(-1, keepdim=True) + self.eps)
        quality = norm.amax(1)  # (B, A)
        scores = torch.zeros_like(pred_scores)
        scores.scatter_(2, target_labels[..., None], (quality * fg)[..., None].to(scores.dtype))
        return Assignment(fg, gt_index, target_labels, target_boxes, scores)
