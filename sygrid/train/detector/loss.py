"""The training loss of the segmentation network (YOLOv8's recipe, own implementation).

After task-aligned assignment (``sygrid.train.detector.assigner``), with ``S`` the sum of the soft class targets:

- **class**: binary cross-entropy of every anchor's class logits against the soft targets, summed, over ``S``;
- **box**: ``1 - CIoU`` of each positive's predicted box with its ground truth, weighted by the positive's target
  score, over ``S``;
- **DFL**: cross-entropy of each side's bin distribution against the two bins bracketing the true distance
  (weights by linear interpolation), weighted and normalised as the box term;
- **mask**: per positive, the BCE of ``coefficients @ prototypes`` against the ground-truth mask coverage at
  stride 4, averaged over the prototype pixels inside the ground-truth box and divided by the box's area as a
  fraction of the image (so small parts weigh as much as large ones), summed and divided by the positive count.

Gains as YOLOv8's defaults: box 7.5, class 0.5, DFL 1.5, mask 7.5. The total is the sum of the weighted terms (a
mean over the batch, not multiplied by the batch size as ultralytics does; AdamW does not care about the scale).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch.nn import functional as nnf

from sygrid.train.detector.assigner import TaskAlignedAssigner
from sygrid.train.detector.boxes import box_ciou, box_to_dist, dfl_expectation, dist_to_box, make_anchors
from sygrid.train.detector.model import flatten_levels

LOSS_NAMES = ("box", "mask", "cls", "dfl")


@dataclass(frozen=True)
class LossGains:
    box: float = 7.5
    mask: float = 7.5
    cls: float = 0.5
    dfl: float = 1.5


@dataclass
class Targets:
    """A batch's ground truth, padded to ``M`` instances per image. ``labels`` (B, M) long, ``boxes`` (B, M, 4)
    ``x0, y0, x1, y1`` input pixels, ``valid`` (B, M) bool, ``masks`` (B, M, H/4, W/4) float coverage."""

    labels: torch.Tensor
    boxes: torch.Tensor
    valid: torch.Tensor
    masks: torch.Tensor

    def to(self, device: torch.device) -> Targets:
        return Targets(*(t.to(device, non_blocking=True) for t in (self.labels, self.boxes, self.valid, self.masks)))


def dfl_loss(logits: torch.Tensor, target: torch.Tensor, reg_max: int) -> torch.Tensor:
    """(n, 4 * reg_max) logits, (n, 4) target distances in ``[0, reg_max - 1)`` -> (n,) mean over the 4 sides of
    the interpolated cross-entropy against the two neighbouring bins."""
    logits = logits.reshape(-1, reg_max)
    target = target.reshape(-1)
    left = target.long()
    w_right = target - left
    loss = (
        nnf.cross_entropy(logits, left, reduction="none") * (1 - w_right)
        + nnf.cross_entropy(logits, (left + 1).clamp(max=reg_max - 1), reduction="none") * w_right
    )
    return loss.reshape(-1, 4).mean(-1)


def crop_to_boxes(values: torch.Tensor, boxes: torch.Tensor) -> torch.Tensor:
    """Zeroes (n, h, w) ``values`` outside each (n, 4) ``x0, y0, x1, y1`` box (in the values' pixel units; a pixel
    counts as inside when its index lies in ``[x0, x1)``)."""
    _, h, w = values.shape
    x0, y0, x1, y1 = boxes[:, :, None, None].unbind(1)
    cols = torch.arange(w, dtype=values.dtype, device=values.device)[None, None, :]
    rows = torch.arange(h, dtype=values.dtype, device=values.device)[None, :, None]
    return values * ((cols >= x0) & (cols < x1) & (rows >= y0) & (rows < y1))


class SegmentationLoss:
    """Computes the loss terms from the network's training outputs and the batch targets."""

    def __init__(
        self,
        num_classes: int,
        reg_max: int = 16,
        strides: tuple[int, ...] = (8, 16, 32),
        gains: LossGains | None = None,
        topk: int = 10,
        alpha: float = 0.5,
        beta: float = 6.0,
    ) -> None:
        self.num_classes = num_classes
        self.reg_max = reg_max
        self.strides = strides
        self.gains = gains or LossGains()
        self.assigner = TaskAlignedAssigner(num_classes, topk=topk, alpha=alpha, beta=beta)

    def __call__(
        self, outputs: tuple[list[torch.Tensor], torch.Tensor, torch.Tensor], targets: Targets
    ) -> tuple[torch.Tensor, dict[str, float]]:
        """Returns the total loss (a scalar to backpropagate) and the weighted terms by name (floats, for logs)."""
        raw, coef, proto = outputs
        reg_max = self.reg_max
        pred = flatten_levels(raw).transpose(1, 2)  # (B, A, 4 * reg_max + nc)
        coef = coef.transpose(1, 2)  # (B, A, nm)
        pred_dist, pred_logits = pred[..., : 4 * reg_max], pred[..., 4 * reg_max :]
        batch = pred.shape[0]
        input_h, input_w = raw[0].shape[2] * self.strides[0], raw[0].shape[3] * self.strides[0]
        anchors, stride = make_anchors([r.shape[2:] for r in raw], self.strides, pred.dtype, pred.device)

        pred_boxes = dist_to_box(dfl_expectation(pred_dist, reg_max), anchors)  # cells of each anchor's level
        assigned = self.assigner(
            pred_logits.detach().sigmoid(),
            pred_boxes.detach() * stride,
            anchors * stride,
            targets.labels,
            targets.boxes,
            targets.valid,
        )
        score_sum = assigned.scores.sum().clamp(min=1.0)
        loss_cls = nnf.binary_cross_entropy_with_logits(pred_logits, assigned.scores, reduction="sum") / score_sum

        fg = assigned.fg
        zero = pred.sum() * 0.0  # keeps the graph connected when a batch has no positives
        loss_box = loss_dfl = loss_mask = zero
        if bool(fg.any()):
            weight = assigned.scores.sum(-1)[fg]
            target_cells = assigned.boxes / stride  # (B, A, 4) in cells of each anchor's level
            ciou = box_ciou(pred_boxes[fg], target_cells[fg])
            loss_box = ((1.0 - ciou) * weight).sum() / score_sum
            target_dist = box_to_dist(anchors[None].expand(batch, -1, -1)[fg], target_cells[fg], reg_max - 1 - 0.01)
            loss_dfl = (dfl_loss(pred_dist[fg], target_dist, reg_max) * weight).sum() / score_sum
            loss_mask = self._mask_loss(
                fg, assigned.gt_index, assigned.boxes, coef, proto, targets.masks, input_h, input_w
            )
        terms = {
            "box": loss_box * self.gains.box,
            "mask": loss_mask * self.gains.mask,
            "cls": loss_cls * self.gains.cls,
            "dfl": loss_dfl * self.gains.dfl,
        }
        total = terms["box"] + terms["mask"] + terms["cls"] + terms["dfl"]
        return total, {k: float(v.detach()) for k, v in terms.items()}

    @staticmethod
    def _mask_loss(
        fg: torch.Tensor,
        gt_index: torch.Tensor,
        boxes: torch.Tensor,
        coef: torch.Tensor,
        proto: torch.Tensor,
        gt_masks: torch.Tensor,
        input_h: int,
        input_w: int,
    ) -> torch.Tensor:
        _, nm, mh, mw = proto.shape
        total = proto.sum() * 0.0
        scale = torch.tensor(
            [mw / input_w, mh / input_h, mw / input_w, mh / input_h], dtype=proto.dtype, device=proto.device
        )
        for i in range(fg.shape[0]):
            fg_i = fg[i]
            if not bool(fg_i.any()):
                continue
            target = gt_masks[i][gt_index[i][fg_i]]  # (n, mh, mw)
            logits = (coef[i][fg_i] @ proto[i].reshape(nm, -1)).reshape(-1, mh, mw)
            box = boxes[i][fg_i]
            area = ((box[:, 2] - box[:, 0]) * (box[:, 3] - box[:, 1]) / (input_w * input_h)).clamp(min=1e-6)
            bce = nnf.binary_cross_entropy_with_logits(logits, target, reduction="none")
            total = total + (crop_to_boxes(bce, box * scale).mean(dim=(1, 2)) / area).sum()
        return total / fg.sum().clamp(min=1)
