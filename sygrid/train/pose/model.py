"""The pose network (GDR-Net family, sized for a CPU): a small residual backbone, a geometry head predicting dense
normalised object coordinates, the visible mask and surface-region logits, and a Patch-PnP head that regresses the
allocentric 6D rotation and SITE from the geometry.

One network serves every trained part. It is told the part's class (a one-hot vector, from the detector) in two
places: a learned bias on the bottleneck features, so the geometry head predicts that part's coordinates, and an
input of the Patch-PnP head's fully connected layers. The dense outputs are class-agnostic channels (3 + 1 + R),
so the last layer does not grow with the number of parts (class-specific channels were not tried).

Shapes: image (B, 3, S, S) RGB in [0, 1]; coord2d (B, 2, s, s) normalised camera coordinates of the output cells
(``sygrid.pose_geometry.roi_ray_map``); class_onehot (B, C). ``s = S / 2**k`` for ``k`` in 1..3.
"""

from __future__ import annotations

import math

import torch
from torch import nn
from torch.nn import functional as F  # noqa: N812 (the torch convention)

from sygrid.train.pose.config import PoseNetConfig

_MEAN = (0.485, 0.456, 0.406)  # ImageNet statistics: a conventional, harmless input scaling
_STD = (0.229, 0.224, 0.225)


def _conv_bn(c_in: int, c_out: int, stride: int = 1, kernel: int = 3) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(c_in, c_out, kernel, stride, kernel // 2, bias=False), nn.BatchNorm2d(c_out), nn.ReLU(inplace=True)
    )


class _Block(nn.Module):
    """ResNet basic block."""

    def __init__(self, c_in: int, c_out: int, stride: int = 1) -> None:
        super().__init__()
        self.conv1 = _conv_bn(c_in, c_out, stride)
        self.conv2 = nn.Sequential(nn.Conv2d(c_out, c_out, 3, 1, 1, bias=False), nn.BatchNorm2d(c_out))
        self.skip = (
            nn.Identity()
            if stride == 1 and c_in == c_out
            else nn.Sequential(nn.Conv2d(c_in, c_out, 1, stride, bias=False), nn.BatchNorm2d(c_out))
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.relu(self.conv2(self.conv1(x)) + self.skip(x))


class PoseNet(nn.Module):
    """forward(image, coord2d, class_onehot) -> (xyz (B, 3, s, s), mask logits (B, 1, s, s), region logits
    (B, R, s, s), rot6d (B, 6) allocentric, site (B, 3))."""

    def __init__(self, config: PoseNetConfig) -> None:
        super().__init__()
        self.config = config
        w = config.width
        self.register_buffer("mean", torch.tensor(_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(_STD).view(1, 3, 1, 1), persistent=False)
        self.stem = _conv_bn(3, w, stride=2)  # S/2
        self.stages = nn.ModuleList(
            [
                nn.Sequential(_Block(w, w)),  # S/2
                nn.Sequential(_Block(w, 2 * w, 2), _Block(2 * w, 2 * w)),  # S/4
                nn.Sequential(_Block(2 * w, 4 * w, 2), _Block(4 * w, 4 * w)),  # S/8
                nn.Sequential(_Block(4 * w, 8 * w, 2), _Block(8 * w, 8 * w)),  # S/16
            ]
        )
        self.class_bias = nn.Linear(config.num_classes, 8 * w)
        # Decoder: up from S/16 to the output stride, each step fusing the backbone feature of that stride.
        n_up = int(math.log2(config.input_size // config.output_size))
        self.n_up = 4 - n_up  # upsampling steps: output at S/2 -> 3 steps, S/4 -> 2, S/8 -> 1
        chans = [8 * w, 4 * w, 2 * w, w]
        self.up = nn.ModuleList(
            [
                nn.Sequential(
                    _conv_bn(chans[i] + chans[i + 1], chans[i + 1]),
                    *[_conv_bn(chans[i + 1], chans[i + 1]) for _ in range(config.decoder_convs - 1)],
                )
                for i in range(self.n_up)
            ]
        )
        c_dec = chans[self.n_up]
        R = config.num_regions
        self.geometry_out = nn.Conv2d(c_dec, 3 + 1 + R, 1)
        p = config.pnp_channels
        groups = 8 if p % 8 == 0 else 1
        self.pnp_convs = nn.Sequential(
            *[
                layer
                for c_in in (3 + R + 2, p, p)
                for layer in (nn.Conv2d(c_in, p, 3, 2, 1, bias=False), nn.GroupNorm(groups, p), nn.ReLU(inplace=True))
            ]
        )
        flat = p * (config.output_size // 8) ** 2
        self.pnp_fc = nn.Sequential(
            nn.Linear(flat + config.num_classes, config.pnp_hidden),
            nn.ReLU(inplace=True),
            nn.Linear(config.pnp_hidden, config.pnp_hidden),
            nn.ReLU(inplace=True),
        )
        self.rot_out = nn.Linear(config.pnp_hidden, 6)
        self.site_out = nn.Linear(config.pnp_hidden, 3)
        with torch.no_grad():  # start at the identity rotation and a plausible depth ratio
            self.rot_out.weight.mul_(0.01)
            self.rot_out.bias.copy_(torch.tensor([1.0, 0.0, 0.0, 0.0, 1.0, 0.0]))
            self.site_out.weight.mul_(0.01)
            self.site_out.bias.copy_(torch.tensor([0.0, 0.0, 1.3]))

    def forward(
        self, image: torch.Tensor, coord2d: torch.Tensor, class_onehot: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        x = self.stem((image - self.mean) / self.std)
        feats = []
        for stage in self.stages:
            x = stage(x)
            feats.append(x)
        x = F.relu(x + self.class_bias(class_onehot)[:, :, None, None])
        for i, up in enumerate(self.up):
            skip = feats[2 - i]
            x = up(torch.cat([F.interpolate(x, scale_factor=2.0, mode="nearest"), skip], dim=1))
        geo = self.geometry_out(x)
        xyz, mask, region = geo[:, :3], geo[:, 3:4], geo[:, 4:]
        pnp_in = torch.cat([xyz, torch.softmax(region, dim=1), coord2d], dim=1)
        h = self.pnp_convs(pnp_in).flatten(1)
        h = self.pnp_fc(torch.cat([h, class_onehot], dim=1))
        return xyz, mask, region, self.rot_out(h), self.site_out(h)


class PoseNetForExport(nn.Module):
    """The ONNX graph: probabilities instead of logits (mask sigmoid, region softmax); the rest unchanged."""

    def __init__(self, net: PoseNet) -> None:
        super().__init__()
        self.net = net

    def forward(
        self, image: torch.Tensor, coord2d: torch.Tensor, class_onehot: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        xyz, mask, region, rot6d, site = self.net(image, coord2d, class_onehot)
        return xyz, torch.sigmoid(mask), torch.softmax(region, dim=1), rot6d, site


def rot6d_to_matrix(x: torch.Tensor) -> torch.Tensor:
    """(B, 6) -> (B, 3, 3): Gram-Schmidt of the two columns (as ``sygrid.pose_geometry.rot6d_to_matrix``)."""
    b1 = F.normalize(x[:, 0:3], dim=1)
    a2 = x[:, 3:6]
    b2 = F.normalize(a2 - (b1 * a2).sum(1, keepdim=True) * b1, dim=1)
    b3 = torch.cross(b1, b2, dim=1)
    return torch.stack([b1, b2, b3], dim=2)
