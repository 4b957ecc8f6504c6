"""The detector's training configuration (standard library only, so that the command line can read its defaults
without importing torch)."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields

from sygrid.train.device_choice import DEVICE_CHOICES

MODEL_SIZES = ("f", "p", "n", "s")  # the keys of model.SIZES (checked equal in the tests)
PROTO_STRIDES = (2, 4)  # model.PROTO_STRIDES
CACHE_MODES = ("auto", "ram", "none")  # cache.plan_cache


@dataclass(frozen=True)
class AugmentConfig:
    """Training augmentation. Colour: ``hsv_*`` gains (fractions, as ultralytics), ``brightness`` (fraction of 255)
    and ``contrast`` (fraction) ranges, Gaussian ``blur_p`` / ``noise_p`` probabilities with sigma up to
    ``blur_sigma_px`` / ``noise_sigma`` (grey levels). Geometry: ``scale`` (zoom in [1 - scale, 1 + scale] of the
    letterboxed size), ``translate`` (fraction of the input side), ``degrees`` (uniform rotation jitter),
    ``rot90_p`` (probability of a random quarter turn), ``flip_lr`` / ``flip_ud`` probabilities, ``mosaic``
    (probability of a 2x2 mosaic of four images), ``focus`` (probability of centring a crop on the labelled parts
    instead of the image centre)."""

    hsv_h: float = 0.015
    hsv_s: float = 0.7
    hsv_v: float = 0.4
    brightness: float = 0.1
    contrast: float = 0.2
    blur_p: float = 0.1
    blur_sigma_px: float = 1.2
    noise_p: float = 0.25
    noise_sigma: float = 6.0
    scale: float = 0.5
    translate: float = 0.1
    degrees: float = 10.0
    rot90_p: float = 0.5
    flip_lr: float = 0.5
    flip_ud: float = 0.5
    mosaic: float = 1.0
    focus: float = 0.8

    def __post_init__(self) -> None:
        for name in ("blur_p", "noise_p", "rot90_p", "flip_lr", "flip_ud", "mosaic", "focus"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"AugmentConfig.{name} must be a probability in [0, 1], got {getattr(self, name)}")
        if not 0.0 <= self.scale < 1.0:
            raise ValueError(f"AugmentConfig.scale must be in [0, 1), got {self.scale}")
        for name in ("hsv_h", "hsv_s", "hsv_v", "brightness", "contrast", "blur_sigma_px", "noise_sigma"):
            if getattr(self, name) < 0.0:
                raise ValueError(f"AugmentConfig.{name} must be >= 0, got {getattr(self, name)}")

    @classmethod
    def none(cls) -> AugmentConfig:
        """No augmentation at all (a plain letterbox)."""
        return cls(**{f.name: 0.0 for f in fields(cls)})


@dataclass(frozen=True)
class TrainConfig:
    """One training run. The defaults are the shipped recipe (docs/perception.md gives its measurements): the nano
    (YOLOv8n-scale) network trained on 320 px crops at the frame's own scale (``imgsz`` 640 for 640 px frames, so
    that the runtime's crop and tile views, which run at scale 1, see parts at the trained size), with ultralytics'
    default colour, zoom (+-50 %) and mosaic augmentation and EMA time constant, and mask prototypes at stride 2 (at
    stride 4 even a perfect prediction's masks cannot reach the mask mAP the built-in parts need: docs/perception.md).

    Args:
        data: dataset folder (``sygrid generate`` output, or a YOLO folder / ``data.yaml``), or several, trained
            on as one (``data.combine_datasets``: same classes; e.g. plain and randomised renders mixed).
        out: output folder.
        epochs: total epochs (a resumed run goes on up to this many).
        imgsz: the model's input side in pixels (a multiple of 32): the runtime letterboxes a frame into it, and
            training scales images the same way.
        train_size: side of the square training crops (a multiple of 32; None, or more than ``imgsz``: ``imgsz``).
            Smaller than ``imgsz``, training sees crops at the runtime's object scale, centred on the parts (see
            ``augment``).
        batch: images per iteration.
        size: network size, a key of ``model.SIZES`` (``"f"``, ``"p"``, ``"n"``, ``"s"``).
        p2: a stride-4 detection level (``model.ModelConfig.p2``); proto_stride: the mask prototypes' stride, 4 or 2.
        device: ``"auto"`` (CUDA when torch sees it), ``"cpu"`` or ``"cuda"`` (``sygrid.train.device``).
        seed: weights initialisation, data order and augmentation.
        threads: torch intra-op threads (on a shared 2-core machine a second thread mostly waits for a core).
        max_iters: at most this many iterations per epoch (smoke runs, quick looks); None for whole epochs.
        lr: peak AdamW learning rate; ``lr_final``: the cosine's end as a fraction of it.
        weight_decay: AdamW decoupled weight decay on convolution weights (not on BatchNorm or biases).
        warmup_epochs: linear warmup length (at least ``warmup_min_iters`` iterations).
        ema_decay, ema_tau: EMA of the weights, decay ``ema_decay * (1 - exp(-updates / ema_tau))``.
        close_mosaic: no mosaic in the last this many epochs (None: 15% of the epochs).
        labels: ``"auto"``, ``"coco"`` or ``"yolo"`` (see ``data.open_dataset``).
        obj_ids: BOP obj_id per class (None: from the dataset).
        id_map: class name or index -> obj_id, for a dataset whose classes nothing else maps (``sygrid.id_map``).
        catalogue: a parts catalogue file (``sygrid.catalogue``): the classes' ids by name, checked against the
            dataset's (``data.catalogue_class_ids``); recorded in the log for ``sygrid models pack``.
        val_every: validate every this many epochs (and always after the last).
        channels_last: NHWC tensors (oneDNN's preferred CPU layout).
        cache: keep the decoded images in memory after their first read: ``"ram"``, ``"none"``, or ``"auto"`` (when
            they fit in half the available memory; ``cache.plan_cache``). The data are the same either way.
        augment: overrides of ``AugmentConfig`` fields.
        resume: continue from ``out/last.pt``.
        init: a checkpoint of this trainer (``best.pt`` or ``last.pt``) whose EMA weights start the run instead of
            the seed's initialisation: fine-tuning, e.g. on views of one cell. Same network size and classes;
            optimiser, schedule and EMA start afresh. A resumed run continues from its own ``last.pt`` instead.
        export: write ``detector.onnx`` from ``best.pt`` at the end.
        half_weights: store the ONNX weights as float16 (half the file; computed in float32, see ``export``).
        checkpoint_minutes: also write ``last.pt`` inside an epoch once this many minutes of training have passed
            since the last write, so that an interruption loses at most that much (None: at epoch ends only).
        progress: tqdm progress bars.
    """

    data: str | tuple[str, ...]
    out: str
    epochs: int = 40
    imgsz: int = 640
    train_size: int | None = 320
    batch: int = 8
    size: str = "n"
    p2: bool = False
    proto_stride: int = 2
    device: str = "auto"
    seed: int = 0
    threads: int = 1
    max_iters: int | None = None
    lr: float = 5e-3
    lr_final: float = 0.02
    weight_decay: float = 5e-4
    warmup_epochs: float = 1.0
    warmup_min_iters: int = 20
    ema_decay: float = 0.999
    ema_tau: float = 2000.0
    close_mosaic: int | None = None
    labels: str = "auto"
    obj_ids: tuple[int, ...] | None = None
    id_map: dict[str, int] | None = None
    catalogue: str | None = None
    val_every: int = 1
    channels_last: bool = True
    cache: str = "auto"
    augment: dict = field(default_factory=dict)
    resume: bool = False
    init: str | None = None
    export: bool = True
    half_weights: bool = False
    checkpoint_minutes: float | None = 10.0
    progress: bool = True

    def __post_init__(self) -> None:
        if not self.data_dirs:
            raise ValueError("data: expected at least one dataset folder")
        if self.epochs < 1 or self.batch < 1 or self.threads < 1 or self.val_every < 1:
            raise ValueError("epochs, batch, threads and val_every must be >= 1")
        if self.imgsz < 32 or self.imgsz % 32:
            raise ValueError(f"imgsz must be a positive multiple of 32, got {self.imgsz}")
        if self.train_size is not None and (self.train_size < 32 or self.train_size % 32):
            raise ValueError(f"train_size must be a positive multiple of 32, got {self.train_size}")
        if self.size not in MODEL_SIZES:
            raise ValueError(f"size: expected one of {MODEL_SIZES}, got {self.size!r}")
        if self.max_iters is not None and self.max_iters < 1:
            raise ValueError(f"max_iters must be >= 1 or None, got {self.max_iters}")
        if self.proto_stride not in PROTO_STRIDES:
            raise ValueError(f"proto_stride: expected one of {PROTO_STRIDES}, got {self.proto_stride}")
        if self.device not in DEVICE_CHOICES:
            raise ValueError(f"device: expected one of {DEVICE_CHOICES}, got {self.device!r}")
        if self.checkpoint_minutes is not None and not self.checkpoint_minutes > 0:
            raise ValueError(f"checkpoint_minutes must be > 0 or None, got {self.checkpoint_minutes}")
        if self.cache not in CACHE_MODES:
            raise ValueError(f"cache: expected one of {CACHE_MODES}, got {self.cache!r}")
        unknown = set(self.augment) - {f.name for f in fields(AugmentConfig)}
        if unknown:
            raise ValueError(
                f"augment: unknown fields {sorted(unknown)}; valid: {[f.name for f in fields(AugmentConfig)]}"
            )

    @property
    def data_dirs(self) -> tuple[str, ...]:
        """The dataset folders, one or several."""
        return (self.data,) if isinstance(self.data, str) else tuple(self.data)

    @property
    def crop_size(self) -> int:
        """The side of the training canvas: ``train_size``, at most ``imgsz``."""
        return min(self.train_size or self.imgsz, self.imgsz)

    @property
    def augment_config(self) -> AugmentConfig:
        return AugmentConfig(**self.augment)

    def as_dict(self) -> dict:
        d = asdict(self)
        d["data"] = self.data if isinstance(self.data, str) else list(self.data)
        d["obj_ids"] = list(self.obj_ids) if self.obj_ids is not None else None
        return d
