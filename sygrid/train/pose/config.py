"""Configuration of pose training, standard library only (the command line reads its defaults without torch): the
network architecture, the loss weights and a training run. The architecture defaults are those of the shipped
``models/builtin/pose.onnx``; a training run and ``sygrid train pose`` take theirs from ``PoseNetConfig``.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path

from sygrid.errors import ConfigError
from sygrid.train.device_choice import DEVICE_CHOICES


@dataclass(frozen=True)
class PoseNetConfig:
    """Architecture. ``input_size``: RoI side in pixels; ``output_size``: side of the dense outputs (the input size
    divided by 2, 4 or 8); ``width``: channels of the first stage (stages have 1, 2, 4, 8 x width);
    ``num_regions``: surface regions; ``pnp_channels``: convolution width of the Patch-PnP head; ``pnp_hidden``:
    width of its fully connected layers; ``decoder_convs``: 3x3 convolutions per upsampling step of the geometry
    head."""

    num_classes: int
    input_size: int = 64
    output_size: int = 16
    width: int = 16
    num_regions: int = 32
    pnp_channels: int = 96
    pnp_hidden: int = 256
    decoder_convs: int = 1

    def __post_init__(self) -> None:
        ratio = self.input_size // max(self.output_size, 1)
        if self.input_size % 16 or ratio not in (2, 4, 8) or self.input_size != ratio * self.output_size:
            raise ValueError(
                f"input_size {self.input_size} must be a multiple of 16 and output_size {self.output_size} the input "
                "size divided by 2, 4 or 8"
            )
        if self.output_size < 8:
            raise ValueError(f"output_size must be >= 8 for the Patch-PnP head, got {self.output_size}")
        if self.num_classes < 1 or self.num_regions < 1:
            raise ValueError(f"num_classes and num_regions must be >= 1, got {self.num_classes}, {self.num_regions}")

    def as_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class LossWeights:
    """Weight of each loss term in the total (``sygrid.train.pose.losses``)."""

    xyz: float = 1.0
    mask: float = 1.0
    region: float = 1.0
    rotation: float = 1.0
    centre: float = 1.0
    depth: float = 1.0

    def as_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class TrainConfig:
    """Everything a training run depends on. Sizes in pixels; ``objects`` None trains every part of the dataset.

    ``epochs`` passes over the training instances (``max_iters`` caps the iterations); ``output_stride``: input
    size / dense output size; ``width``: backbone width; ``val_max``: validation instances used (spread evenly);
    ``checkpoint_every``: iterations between checkpoints; ``device``: ``"auto"``, ``"cpu"`` or ``"cuda"``
    (``sygrid.train.device``). Architecture defaults come from ``PoseNetConfig``.
    """

    data_dir: Path
    out_dir: Path
    epochs: int = 30
    batch_size: int = 32
    input_size: int = PoseNetConfig.input_size
    output_stride: int = PoseNetConfig.input_size // PoseNetConfig.output_size
    width: int = PoseNetConfig.width
    num_regions: int = PoseNetConfig.num_regions
    lr: float = 1e-3
    weight_decay: float = 1e-2
    warmup_iters: int = 300
    seed: int = 0
    threads: int | None = None
    device: str = "auto"
    max_iters: int | None = None
    objects: tuple[int, ...] | None = None
    catalogue: Path | None = None  # the parts catalogue the dataset was made from: the parts' names and symmetries
    min_visib_fract: float = 0.2
    val_max: int = 500
    checkpoint_every: int = 200
    sym_steps: int = 36
    progress: bool = True
    loss_weights: LossWeights = field(default_factory=LossWeights)

    def __post_init__(self) -> None:
        for name in ("epochs", "batch_size", "checkpoint_every", "sym_steps"):
            if getattr(self, name) < 1:
                raise ConfigError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.max_iters is not None and self.max_iters < 1:
            raise ConfigError(f"max_iters must be >= 1, got {self.max_iters}")
        if self.device not in DEVICE_CHOICES:
            raise ConfigError(f"device: expected one of {DEVICE_CHOICES}, got {self.device!r}")
        if self.output_stride not in (2, 4, 8) or self.input_size % (4 * self.output_stride):
            raise ConfigError(
                f"input_size {self.input_size} / output_stride {self.output_stride}: the stride must be 2, 4 or 8 "
                "and the input size a multiple of 16 and of 4 x stride"
            )

    @property
    def output_size(self) -> int:
        """Side of the network's dense outputs in pixels."""
        return self.input_size // self.output_stride

    def net_config(self, num_classes: int) -> PoseNetConfig:
        """The architecture this run trains, for ``num_classes`` parts."""
        return PoseNetConfig(
            num_classes=num_classes,
            input_size=self.input_size,
            output_size=self.output_size,
            width=self.width,
            num_regions=self.num_regions,
        )

    def as_json(self) -> dict:
        d = asdict(self)
        d["data_dir"], d["out_dir"] = str(self.data_dir), str(self.out_dir)
        d["catalogue"] = None if self.catalogue is None else str(self.catalogue)
        d["objects"] = None if self.objects is None else list(self.objects)
        return d
