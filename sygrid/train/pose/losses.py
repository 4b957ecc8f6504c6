"""Losses of the pose network, symmetry-aware where the part has symmetries (GDR-Net's set).

For a part with symmetry transforms ``S_k`` (``T_obj_obj``, identity first), the poses ``T @ S_k`` all give the same
image, so the targets are ambiguous and each loss takes the minimum over the equivalents:

- **XYZ**: the object coordinates seen under ``T @ S_k`` are ``S_k^-1 p``; L1 over the visible cells against the
  closest equivalent.
- **Regions**: cross-entropy against the region labels (nearest surface-region centre) of that same equivalent.
- **Rotation**: point matching, mean L1 distance between the model points (in units of the diameter) turned by the
  predicted and by the ground-truth allocentric rotation ``R S_k``, minimum over ``k`` (rotation parts only: the
  symmetry axes of our parts pass through the origin; an offset axis would also shift the translation).
- **Mask**: binary cross-entropy on the visible mask; **SITE**: L1 on the centre offset and on the depth ratio.
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F  # noqa: N812 (the torch convention)

from sygrid.train.pose.config import LossWeights
from sygrid.train.pose.model import rot6d_to_matrix
from sygrid.train.pose.objects import ObjectTables


class PoseLoss(nn.Module):
    """forward(outputs of ``PoseNet``, batch of torch tensors) -> (total loss, {name: detached value})."""

    def __init__(self, tables: ObjectTables, weights: LossWeights | None = None) -> None:
        super().__init__()
        self.weights = weights or LossWeights()
        f32 = torch.float32
        sym = torch.as_tensor(tables.sym_T, dtype=f32)
        self.register_buffer("sym_R", sym[:, :, :3, :3].contiguous())  # (C, S, 3, 3)
        self.register_buffer("sym_t", sym[:, :, :3, 3].contiguous())  # (C, S, 3)
        self.register_buffer("sym_valid", torch.as_tensor(tables.sym_valid))  # (C, S)
        bounds = torch.as_tensor(tables.bounds_m, dtype=f32)
        self.register_buffer("lo", bounds[:, 0])  # (C, 3)
        self.register_buffer("extent", bounds[:, 1] - bounds[:, 0])
        self.register_buffer("regions", torch.as_tensor(tables.regions_m, dtype=f32))  # (C, R, 3)
        diam = torch.as_tensor(tables.diameters_m, dtype=f32)
        self.register_buffer("points", torch.as_tensor(tables.points_m, dtype=f32) / diam[:, None, None])

    def symmetric_xyz(
        self, xyz_pred: torch.Tensor, xyz_m: torch.Tensor, visible: torch.Tensor, cls: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Per-sample L1 against the closest symmetric equivalent, and that equivalent's coordinates [m].

        xyz_pred (B, 3, H, W) normalised; xyz_m (B, 3, H, W) ground truth [m]; visible (B, H, W); cls (B,).
        Returns (B,) loss and (B, HW, 3) metres.
        """
        B = xyz_pred.shape[0]
        p = xyz_m.flatten(2).transpose(1, 2)  # (B, N, 3)
        vis = visible.flatten(1)  # (B, N)
        R, t, valid = self.sym_R[cls], self.sym_t[cls], self.sym_valid[cls]  # (B, S, 3, 3), (B, S, 3), (B, S)
        # S^-1 p = R^T (p - t); as row vectors (p - t) @ R.
        p_sym = torch.einsum("bnj,bsjk->bsnk", p, R) - torch.einsum("bsj,bsjk->bsk", t, R)[:, :, None]
        target = (p_sym - self.lo[cls][:, None, None]) / self.extent[cls][:, None, None]  # (B, S, N, 3)
        pred = xyz_pred.flatten(2).transpose(1, 2)[:, None]  # (B, 1, N, 3)
        n_vis = vis.sum(1).clamp(min=1.0)
        err = ((pred - target).abs().sum(-1) * vis[:, None]).sum(-1) / (3.0 * n_vis[:, None])  # (B, S)
        err = torch.where(valid, err, torch.full_like(err, float("inf")))
        best_err, best = err.min(dim=1)
        p_best = p_sym[torch.arange(B, device=p.device), best]  # (B, N, 3)
        return best_err, p_best

    def region_labels(self, p_m: torch.Tensor, visible: torch.Tensor, cls: torch.Tensor) -> torch.Tensor:
        """(B, N) index of the nearest region centre of each visible point, -100 (ignored) elsewhere."""
        labels = torch.cdist(p_m, self.regions[cls]).argmin(dim=-1)
        return torch.where(visible.flatten(1) > 0.5, labels, torch.full_like(labels, -100))

    def rotation_pm(self, rot6d: torch.Tensor, R_gt: torch.Tensor, cls: torch.Tensor) -> torch.Tensor:
        """(B,) symmetric point-matching loss of the allocentric rotation, in units of the diameter."""
        R_pred = rot6d_to_matrix(rot6d)
        pts = self.points[cls]  # (B, P, 3)
        pred = pts @ R_pred.transpose(1, 2)  # (B, P, 3)
        R_eq = R_gt[:, None] @ self.sym_R[cls]  # (B, S, 3, 3)
        gt = torch.einsum("bpj,bskj->bspk", pts, R_eq)  # (B, S, P, 3)
        err = (pred[:, None] - gt).abs().sum(-1).mean(-1)  # (B, S)
        err = torch.where(self.sym_valid[cls], err, torch.full_like(err, float("inf")))
        return err.min(dim=1).values

    def forward(
        self, outputs: tuple[torch.Tensor, ...], batch: dict[str, torch.Tensor]
    ) -> tuple[torch.Tensor, dict[str, float]]:
        xyz, mask_logit, region_logit, rot6d, site = outputs
        cls, visible = batch["class_index"], batch["visible"]
        w = self.weights
        l_xyz, p_best = self.symmetric_xyz(xyz, batch["xyz_m"], visible, cls)
        labels = self.region_labels(p_best.detach(), visible, cls)
        logits = region_logit.flatten(2)  # (B, R, N)
        if bool((labels >= 0).any()):
            l_region = F.cross_entropy(logits, labels, ignore_index=-100)
        else:
            l_region = logits.sum() * 0.0
        l_mask = F.binary_cross_entropy_with_logits(mask_logit[:, 0], visible)
        l_rot = self.rotation_pm(rot6d, batch["R_allo"], cls)
        l_centre = (site[:, :2] - batch["site"][:, :2]).abs().sum(1)
        l_depth = (site[:, 2] - batch["site"][:, 2]).abs()
        parts = {
            "xyz": l_xyz.mean(),
            "mask": l_mask,
            "region": l_region,
            "rotation": l_rot.mean(),
            "centre": l_centre.mean(),
            "depth": l_depth.mean(),
        }
        total = sum(getattr(w, k) * v for k, v in parts.items())
        return total, {k: float(v.detach()) for k, v in parts.items()}
