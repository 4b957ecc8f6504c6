"""A compact anchor-free YOLOv8-style instance segmentation network (torch).

Layout (the YOLOv8-seg structure, at widths for a few part classes on a CPU):

- backbone: Conv-BN-SiLU stem and stride-2 convs down to stride 32, C2f blocks (a split, a chain of bottlenecks,
  every intermediate concatenated), SPPF (three chained 5x5 max pools) at the end;
- neck: PAN-FPN over strides 8, 16, 32 (top-down upsample + concat + C2f, then bottom-up stride-2 conv + concat +
  C2f); with ``p2`` also over stride 4 (the stem's output), as ultralytics' yolov8-p2: a fourth detection level
  whose cells are a quarter of the stride-8 ones, for parts a few cells wide;
- head, per level, three decoupled branches of two 3x3 convs and a 1x1: box (4 sides x ``reg_max`` DFL bins), class
  (``nc`` logits) and mask coefficients (``nm``); a prototype branch on the finest level (3x3 conv, 2x transposed
  convs, 3x3 conv, 1x1 conv) gives ``nm`` prototypes at ``proto_stride`` (4, or 2 for finer masks).

``SIZES`` scales channels (``width``, of the YOLOv8 base 64-128-256-512-1024) and C2f repeats (``depth``, of
3-6-6-3): ``"n"`` is YOLOv8n's scale, ``"p"`` (pico) half its width, ``"f"`` (femto) a quarter (for the speed/accuracy
chart's narrow end), ``"s"`` twice it.

In training mode ``forward`` returns the raw head outputs for the loss; in eval mode it returns the decoded
``(output0, output1)`` of the ultralytics YOLOv8-seg ONNX layout: ``[B, 4 + nc + nm, A]`` (box centre x, y, width,
height in input pixels, per-class sigmoid scores, mask coefficients; the anchors of every level, finest first) and
the prototypes ``[B, nm, H/s, W/s]``, ``s = proto_stride``. The options change the anchor count and the prototype
size, not the layout.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import torch
from torch import nn

from sygrid.train.detector.boxes import make_anchors

STRIDES = (8, 16, 32)
P2_STRIDES = (4, 8, 16, 32)
PROTO_STRIDES = (2, 4)
BASE_CHANNELS = (64, 128, 256, 512, 1024)
BASE_REPEATS = (3, 6, 6, 3)
# BatchNorm: YOLOv8's eps; torch's default momentum (0.1), not YOLOv8's 0.03. Short CPU runs have a few hundred to
# a few thousand iterations, and the huge activation variances of the first ones linger in the running statistics
# at 0.03 (0.97^120 = 0.03 of them after 120 iterations; measured: eval-mode variances 10-1000x the true ones and
# no detection above 0.003 after 120 iterations, where train-mode scores reached 0.8).
BN_EPS, BN_MOMENTUM = 1e-3, 0.1


@dataclass(frozen=True)
class ModelSize:
    """Width and depth multipliers of the YOLOv8 base network."""

    name: str
    width: float
    depth: float
    max_channels: int = 1024


SIZES = {
    "f": ModelSize("f", width=0.0625, depth=0.33),
    "p": ModelSize("p", width=0.125, depth=0.33),
    "n": ModelSize("n", width=0.25, depth=0.33),
    "s": ModelSize("s", width=0.5, depth=0.33),
}


@dataclass(frozen=True)
class ModelConfig:
    """What fixes the network: ``num_classes``, ``size`` (a key of ``SIZES``), ``reg_max`` DFL bins per box side,
    ``num_masks`` prototypes, ``prior_image_size`` (px), used only to initialise the class bias, ``p2`` a stride-4
    detection level, ``proto_stride`` the prototypes' stride (4 or 2)."""

    num_classes: int
    size: str = "n"
    reg_max: int = 16
    num_masks: int = 32
    prior_image_size: int = 640
    p2: bool = False
    proto_stride: int = 4

    def __post_init__(self) -> None:
        if self.num_classes < 1:
            raise ValueError(f"num_classes must be >= 1, got {self.num_classes}")
        if self.size not in SIZES:
            raise ValueError(f"size: expected one of {sorted(SIZES)}, got {self.size!r}")
        if self.reg_max < 2 or self.num_masks < 1:
            raise ValueError(f"reg_max must be >= 2 and num_masks >= 1, got {self.reg_max}, {self.num_masks}")
        if self.proto_stride not in PROTO_STRIDES:
            raise ValueError(f"proto_stride: expected one of {PROTO_STRIDES}, got {self.proto_stride}")

    @property
    def strides(self) -> tuple[int, ...]:
        return P2_STRIDES if self.p2 else STRIDES

    def as_dict(self) -> dict:
        return asdict(self)


def _channels(c: int, size: ModelSize) -> int:
    """Scaled channel count, rounded up to a multiple of 8 (SIMD-friendly, as YOLOv8's make_divisible)."""
    return int(math.ceil(min(c, size.max_channels) * size.width / 8) * 8)


def _repeats(n: int, size: ModelSize) -> int:
    return max(round(n * size.depth), 1)


class ConvBNAct(nn.Module):
    """Conv (no bias, 'same' padding) -> BatchNorm -> SiLU."""

    def __init__(self, c_in: int, c_out: int, k: int = 1, s: int = 1) -> None:
        super().__init__()
        self.conv = nn.Conv2d(c_in, c_out, k, s, k // 2, bias=False)
        self.bn = nn.BatchNorm2d(c_out, eps=BN_EPS, momentum=BN_MOMENTUM)
        self.act = nn.SiLU(inplace=True)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.act(self.bn(self.conv(x)))


class Bottleneck(nn.Module):
    """Two 3x3 ConvBNAct with an optional residual."""

    def __init__(self, c: int, shortcut: bool) -> None:
        super().__init__()
        self.cv1 = ConvBNAct(c, c, 3)
        self.cv2 = ConvBNAct(c, c, 3)
        self.add = shortcut

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.cv2(self.cv1(x))
        return x + y if self.add else y


class C2f(nn.Module):
    """1x1 conv to two halves; ``n`` bottlenecks chained on the second; all ``2 + n`` pieces concatenated and fused
    by a 1x1 conv (cheap gradient paths of several depths)."""

    def __init__(self, c_in: int, c_out: int, n: int, shortcut: bool) -> None:
        super().__init__()
        self.hidden = c_out // 2
        self.cv1 = ConvBNAct(c_in, 2 * self.hidden, 1)
        self.blocks = nn.ModuleList(Bottleneck(self.hidden, shortcut) for _ in range(n))
        self.cv2 = ConvBNAct((2 + n) * self.hidden, c_out, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        pieces = list(self.cv1(x).split(self.hidden, 1))
        for block in self.blocks:
            pieces.append(block(pieces[-1]))
        return self.cv2(torch.cat(pieces, 1))


class SPPF(nn.Module):
    """Spatial pyramid pooling, fast: three chained k x k max pools (receptive fields k, 2k-1, 3k-2) concatenated."""

    def __init__(self, c_in: int, c_out: int, k: int = 5) -> None:
        super().__init__()
        hidden = c_in // 2
        self.cv1 = ConvBNAct(c_in, hidden, 1)
        self.pool = nn.MaxPool2d(k, 1, k // 2)
        self.cv2 = ConvBNAct(4 * hidden, c_out, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = [self.cv1(x)]
        for _ in range(3):
            y.append(self.pool(y[-1]))
        return self.cv2(torch.cat(y, 1))


class Backbone(nn.Module):
    """Stem to stride 32; returns the stride-4, -8, -16 and -32 features."""

    def __init__(self, size: ModelSize) -> None:
        super().__init__()
        c1, c2, c3, c4, c5 = (_channels(c, size) for c in BASE_CHANNELS)
        n2, n3, n4, n5 = (_repeats(n, size) for n in BASE_REPEATS)
        self.stem = nn.Sequential(ConvBNAct(3, c1, 3, 2), ConvBNAct(c1, c2, 3, 2), C2f(c2, c2, n2, True))
        self.stage3 = nn.Sequential(ConvBNAct(c2, c3, 3, 2), C2f(c3, c3, n3, True))
        self.stage4 = nn.Sequential(ConvBNAct(c3, c4, 3, 2), C2f(c4, c4, n4, True))
        self.stage5 = nn.Sequential(ConvBNAct(c4, c5, 3, 2), C2f(c5, c5, n5, True), SPPF(c5, c5))
        self.out_channels = (c2, c3, c4, c5)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, ...]:
        p2 = self.stem(x)
        p3 = self.stage3(p2)
        p4 = self.stage4(p3)
        return p2, p3, p4, self.stage5(p4)


class PanNeck(nn.Module):
    """PAN-FPN: top-down (upsample, concat, C2f) then bottom-up (stride-2 conv, concat, C2f), from stride 32 down to
    stride 8, or to stride 4 with ``p2``. Returns the features of the detection levels, finest first."""

    def __init__(self, channels: tuple[int, int, int, int], n: int, p2: bool = False) -> None:
        super().__init__()
        c2, c3, c4, c5 = channels
        self.p2 = p2
        self.up = nn.Upsample(scale_factor=2.0, mode="nearest")
        self.td4 = C2f(c5 + c4, c4, n, False)
        self.td3 = C2f(c4 + c3, c3, n, False)
        if p2:
            self.td2 = C2f(c3 + c2, c2, n, False)
            self.down2 = ConvBNAct(c2, c2, 3, 2)
            self.bu3 = C2f(c2 + c3, c3, n, False)
        self.down3 = ConvBNAct(c3, c3, 3, 2)
        self.bu4 = C2f(c3 + c4, c4, n, False)
        self.down4 = ConvBNAct(c4, c4, 3, 2)
        self.bu5 = C2f(c4 + c5, c5, n, False)

    def forward(self, feats: tuple[torch.Tensor, ...]) -> list[torch.Tensor]:
        p2, p3, p4, p5 = feats
        t4 = self.td4(torch.cat((self.up(p5), p4), 1))
        n3 = self.td3(torch.cat((self.up(t4), p3), 1))
        finer = []
        if self.p2:
            n2 = self.td2(torch.cat((self.up(n3), p2), 1))
            n3 = self.bu3(torch.cat((self.down2(n2), n3), 1))
            finer = [n2]
        n4 = self.bu4(torch.cat((self.down3(n3), t4), 1))
        n5 = self.bu5(torch.cat((self.down4(n4), p5), 1))
        return [*finer, n3, n4, n5]


def _branch(c_in: int, c_mid: int, c_out: int) -> nn.Sequential:
    return nn.Sequential(ConvBNAct(c_in, c_mid, 3), ConvBNAct(c_mid, c_mid, 3), nn.Conv2d(c_mid, c_out, 1))


class Prototypes(nn.Module):
    """Mask prototypes from the finest level's feature, upsampled ``2 ** steps`` times by transposed convolutions
    (one step: stride 8 to 4, as YOLOv8-seg)."""

    def __init__(self, c_in: int, c_mid: int, num_masks: int, steps: int = 1) -> None:
        super().__init__()
        self.cv1 = ConvBNAct(c_in, c_mid, 3)
        up = [nn.ConvTranspose2d(c_mid, c_mid, 2, 2, 0, bias=True) for _ in range(steps)]
        # one step keeps YOLOv8-seg's parameter names
        self.upsample = up[0] if steps == 1 else nn.Sequential(*up) if up else nn.Identity()
        self.cv2 = ConvBNAct(c_mid, c_mid, 3)
        self.cv3 = ConvBNAct(c_mid, num_masks, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.cv3(self.cv2(self.upsample(self.cv1(x))))


class SegmentHead(nn.Module):
    """Decoupled box / class / mask-coefficient branches per level, and the prototype branch."""

    def __init__(self, channels: tuple[int, ...], cfg: ModelConfig) -> None:
        super().__init__()
        nc, reg_max, nm = cfg.num_classes, cfg.reg_max, cfg.num_masks
        strides = cfg.strides
        c8 = channels[strides.index(8)]  # branch widths from the stride-8 level, with or without a P2 level
        c_box = max(16, c8 // 4, 4 * reg_max)
        c_cls = max(c8, min(nc, 100))
        c_coef = max(c8 // 4, nm)
        self.box = nn.ModuleList(_branch(c, c_box, 4 * reg_max) for c in channels)
        self.cls = nn.ModuleList(_branch(c, c_cls, nc) for c in channels)
        self.coef = nn.ModuleList(_branch(c, c_coef, nm) for c in channels)
        steps = int(math.log2(strides[0] // cfg.proto_stride))
        self.proto = Prototypes(channels[0], _channels(256, SIZES[cfg.size]), nm, steps)
        # Priors: every box side starts at the same distance; class scores start near the rate of a few objects
        # per image spread over the cells of a level (as YOLOv8 initialises them).
        for box, cls, s in zip(self.box, self.cls, strides, strict=True):
            nn.init.constant_(box[-1].bias, 1.0)
            nn.init.constant_(cls[-1].bias, math.log(5 / nc / (cfg.prior_image_size / s) ** 2))

    def forward(self, feats: list[torch.Tensor]) -> tuple[list[torch.Tensor], torch.Tensor, torch.Tensor]:
        raw = [torch.cat((b(x), c(x)), 1) for x, b, c in zip(feats, self.box, self.cls, strict=True)]
        coef = torch.cat([m(x).flatten(2) for x, m in zip(feats, self.coef, strict=True)], 2)
        return raw, coef, self.proto(feats[0])


class YoloSeg(nn.Module):
    """The instance segmentation network; see the module docstring for its outputs."""

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        self.cfg = cfg
        size = SIZES[cfg.size]
        self.backbone = Backbone(size)
        self.neck = PanNeck(self.backbone.out_channels, _repeats(3, size), cfg.p2)
        self.head = SegmentHead(self.backbone.out_channels[0 if cfg.p2 else 1 :], cfg)
        self.strides = cfg.strides

    def forward(self, images: torch.Tensor) -> tuple:
        raw, coef, proto = self.head(self.neck(self.backbone(images)))
        if self.training:
            return raw, coef, proto
        return decode(raw, coef, self.cfg.reg_max, self.strides), proto


def flatten_levels(raw: list[torch.Tensor]) -> torch.Tensor:
    """Per-level ``[B, C, h, w]`` -> ``[B, C, A]`` (levels concatenated, row-major within a level)."""
    return torch.cat([r.flatten(2) for r in raw], 2)


def decode(raw: list[torch.Tensor], coef: torch.Tensor, reg_max: int, strides: tuple[int, ...]) -> torch.Tensor:
    """Raw head outputs -> ``[B, 4 + nc + nm, A]``: box ``cx, cy, w, h`` in input pixels (DFL expectation of each
    side around the anchor), per-class sigmoid scores, mask coefficients."""
    anchors, stride = make_anchors([r.shape[2:] for r in raw], strides, raw[0].dtype, raw[0].device)
    pred = flatten_levels(raw)
    b, a = pred.shape[0], pred.shape[2]
    probs = pred[:, : 4 * reg_max].reshape(b, 4, reg_max, a).softmax(2)
    bins = torch.arange(reg_max, dtype=pred.dtype, device=pred.device).reshape(1, 1, reg_max, 1)
    dist = (probs * bins).sum(2)  # [B, 4, A] ltrb in cells
    anchors, stride = anchors.T.unsqueeze(0), stride.T.unsqueeze(0)  # [1, 2, A], [1, 1, A]
    xy0, xy1 = anchors - dist[:, :2], anchors + dist[:, 2:]
    boxes = torch.cat(((xy0 + xy1) / 2, xy1 - xy0), 1) * stride
    return torch.cat((boxes, pred[:, 4 * reg_max :].sigmoid(), coef), 1)


def build_model(cfg: ModelConfig) -> YoloSeg:
    return YoloSeg(cfg)


def count_parameters(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())
