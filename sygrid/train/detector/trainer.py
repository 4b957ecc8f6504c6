"""The detector's training loop: AdamW with warmup and cosine decay, an EMA of the weights, per-epoch validation
(COCO mAP on the val split), checkpoints to resume from, and the ONNX export of the best weights.

Files under ``OUT``: ``last.pt`` (everything needed to resume: model, EMA, optimiser, epoch, history, torch RNG;
written atomically after every epoch, and inside an epoch every ``TrainConfig.checkpoint_minutes`` with how far the
epoch got), ``best.pt`` (the EMA weights with the best validation mask mAP50-95, for
export and evaluation), ``detector.onnx`` and ``train_log.json`` (configuration, per-epoch losses, metrics and
seconds, the export check).

Determinism: the weights are initialised from ``seed``; the order of an epoch and every augmentation come from
``(seed, epoch, index)`` (``sygrid.train.detector.augment``), so a run resumed from ``last.pt`` sees the data an
uninterrupted run would (no numpy generator state needs saving); one resumed inside an epoch skips the batches it
had trained on and goes on with the same weights, optimiser state and loss sums.
"""

from __future__ import annotations

import copy
import io
import logging
import math
import time
from collections.abc import Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
from tqdm import tqdm

from sygrid.catalogue import load_catalogue
from sygrid.errors import SygridError
from sygrid.fileio import write_bytes_atomic, write_json_atomic
from sygrid.metrics import DetectionMetrics
from sygrid.train.detector.augment import (
    Example,
    epoch_order,
    example_rng,
    train_example,
    val_example,
)
from sygrid.train.detector.cache import InstanceCache, plan_cache
from sygrid.train.detector.config import TrainConfig
from sygrid.train.detector.data import DetectionDataset, open_datasets
from sygrid.train.detector.evaluate import coco_evaluate, val_detections
from sygrid.train.detector.export import ExportReport, export_onnx
from sygrid.train.detector.loss import LOSS_NAMES, SegmentationLoss, Targets
from sygrid.train.detector.model import ModelConfig, YoloSeg, build_model, count_parameters
from sygrid.train.device import autocast, grad_scaler, resolve_device, to_float32

log = logging.getLogger(__name__)

CHECKPOINT_FORMAT = "sygrid-detector-checkpoint/1"
LOG_FORMAT = "sygrid-detector-train-log/1"
GRAD_CLIP_NORM = 10.0  # as YOLOv8: guards the first iterations against a bad batch


class TrainError(SygridError, RuntimeError):
    """Training cannot start or go on (bad configuration, a checkpoint that does not fit the run)."""


@dataclass(frozen=True)
class TrainResult:
    """What a run wrote. ``export`` is None when the run did not export (``TrainConfig.export`` False)."""

    out: Path
    last: Path
    best: Path
    log: Path
    history: list[dict]
    export: ExportReport | None


class ModelEMA:
    """Exponential moving average of a model's parameters and buffers (decay ramps up over ``tau`` updates so that
    the first, fast-changing weights do not linger)."""

    def __init__(self, model: YoloSeg, decay: float, tau: float, updates: int = 0) -> None:
        self.model = copy.deepcopy(model).eval()
        for p in self.model.parameters():
            p.requires_grad_(False)
        self.decay, self.tau, self.updates = decay, tau, updates

    @torch.no_grad()
    def update(self, model: YoloSeg) -> None:
        self.updates += 1
        d = self.decay * (1.0 - math.exp(-self.updates / self.tau))
        current = model.state_dict()
        for name, value in self.model.state_dict().items():
            if value.dtype.is_floating_point:
                value.mul_(d).add_(current[name].detach(), alpha=1.0 - d)
            else:
                value.copy_(current[name])


def collate(examples: Sequence[Example], channels_last: bool) -> tuple[torch.Tensor, Targets]:
    """Examples of one input size -> images (B, 3, H, W) float in [0, 1] and padded targets."""
    images = torch.from_numpy(np.stack([e.image for e in examples])).permute(0, 3, 1, 2).float().div_(255.0)
    images = images.contiguous(memory_format=torch.channels_last if channels_last else torch.contiguous_format)
    b, m = len(examples), max([len(e.classes) for e in examples] + [0])
    mh, mw = (
        examples[0].masks.shape[1:] if examples[0].masks.ndim == 3 else (images.shape[2] // 4, images.shape[3] // 4)
    )
    labels = torch.zeros((b, m), dtype=torch.long)
    boxes = torch.zeros((b, m, 4), dtype=torch.float32)
    valid = torch.zeros((b, m), dtype=torch.bool)
    masks = torch.zeros((b, m, mh, mw), dtype=torch.float32)
    for i, e in enumerate(examples):
        n = len(e.classes)
        labels[i, :n] = torch.from_numpy(e.classes)
        boxes[i, :n] = torch.from_numpy(e.boxes_xyxy)
        valid[i, :n] = True
        masks[i, :n] = torch.from_numpy(e.masks)
    return images, Targets(labels, boxes, valid, masks)


def _param_groups(model: YoloSeg, weight_decay: float) -> list[dict]:
    decay, no_decay = [], []
    for module in model.modules():
        for name, p in module.named_parameters(recurse=False):
            (decay if name == "weight" and p.ndim > 1 else no_decay).append(p)
    return [{"params": decay, "weight_decay": weight_decay}, {"params": no_decay, "weight_decay": 0.0}]


def learning_rate(cfg: TrainConfig, iteration: int, iters_per_epoch: int) -> float:
    """Linear warmup from 0, then cosine from ``lr`` down to ``lr * lr_final`` at the last iteration."""
    total = cfg.epochs * iters_per_epoch
    warmup = min(max(round(cfg.warmup_epochs * iters_per_epoch), cfg.warmup_min_iters), max(total - 1, 1))
    if iteration < warmup:
        return cfg.lr * (iteration + 1) / warmup
    progress = (iteration - warmup) / max(total - warmup, 1)
    return cfg.lr * (cfg.lr_final + (1.0 - cfg.lr_final) * 0.5 * (1.0 + math.cos(math.pi * min(progress, 1.0))))


def _save(obj: dict, path: Path) -> Path:
    buffer = io.BytesIO()
    torch.save(obj, buffer)
    return write_bytes_atomic(path, buffer.getvalue())


def load_checkpoint(path: str | Path) -> dict:
    """A ``last.pt`` or ``best.pt`` of this trainer (tensors and plain data only: loaded with ``weights_only``)."""
    path = Path(path)
    if not path.is_file():
        raise TrainError(f"{path}: checkpoint not found")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except (RuntimeError, OSError, ValueError, EOFError) as err:
        raise TrainError(f"{path}: not a readable checkpoint ({err})") from err
    if not isinstance(ckpt, dict) or ckpt.get("format") != CHECKPOINT_FORMAT:
        raise TrainError(f"{path}: not a detector checkpoint (expected format {CHECKPOINT_FORMAT!r})")
    return ckpt


def model_from_checkpoint(path: str | Path, weights: str = "ema") -> tuple[YoloSeg, dict]:
    """The network of a checkpoint (``weights`` ``"ema"`` or ``"model"``) in eval mode, and the checkpoint."""
    ckpt = load_checkpoint(path)
    model = build_model(ModelConfig(**ckpt["model_config"]))
    model.load_state_dict(ckpt[weights])
    return model.eval(), ckpt


class _Trainer:
    def __init__(self, cfg: TrainConfig) -> None:
        self.cfg = cfg
        self.out = Path(cfg.out)
        self.out.mkdir(parents=True, exist_ok=True)
        try:
            self.device = resolve_device(cfg.device)
        except ValueError as err:
            raise TrainError(f"--device: {err}") from err
        self.dataset: DetectionDataset = open_datasets(
            cfg.data_dirs, labels=cfg.labels, obj_ids=cfg.obj_ids, id_map=cfg.id_map,
            catalogue=load_catalogue(cfg.catalogue) if cfg.catalogue else None,
        )  # fmt: skip
        self.cache_plan = plan_cache(self.dataset, cfg.cache)
        self.instances = InstanceCache(self.dataset, self.cache_plan.enabled)
        self.model_cfg = ModelConfig(self.dataset.num_classes, cfg.size, prior_image_size=cfg.imgsz,
                                     p2=cfg.p2, proto_stride=cfg.proto_stride)  # fmt: skip
        torch.manual_seed(cfg.seed)
        self.model = build_model(self.model_cfg)
        self.memory_format = torch.channels_last if cfg.channels_last else torch.contiguous_format
        self.model.to(self.device, memory_format=self.memory_format)
        self.ema = ModelEMA(self.model, cfg.ema_decay, cfg.ema_tau)
        self.optimizer = torch.optim.AdamW(_param_groups(self.model, cfg.weight_decay), lr=cfg.lr, betas=(0.9, 0.999))
        self.scaler = grad_scaler(self.device)
        self.loss = SegmentationLoss(self.dataset.num_classes, self.model_cfg.reg_max, self.model.strides)
        n = len(self.dataset.images["train"])
        self.iters_per_epoch = math.ceil(n / cfg.batch)
        if cfg.max_iters is not None:
            self.iters_per_epoch = min(self.iters_per_epoch, cfg.max_iters)
        self.close_mosaic = cfg.close_mosaic if cfg.close_mosaic is not None else round(0.15 * cfg.epochs)
        self.epoch = 0
        self.iteration = 0
        self.history: list[dict] = []
        self.best_fitness = -math.inf
        self.best_epoch = None
        self.partial_epoch: dict | None = None  # how far an interrupted epoch got (a mid-epoch last.pt)
        if cfg.resume:
            self._resume()
        elif cfg.init:
            self._init_from(Path(cfg.init))

    # ------------------------------------------------------------------------------------------ checkpoints
    def _resume(self) -> None:
        path = self.out / "last.pt"
        ckpt = load_checkpoint(path)
        self._check_same_network(path, ckpt, "--resume", "--width, --imgsz and dataset classes")
        self.model.load_state_dict(ckpt["model"])
        self.ema.model.load_state_dict(ckpt["ema"])
        self.ema.updates = int(ckpt["ema_updates"])
        self.optimizer.load_state_dict(ckpt["optimizer"])
        torch.set_rng_state(ckpt["torch_rng"])
        self.epoch = int(ckpt["epoch"])
        self.iteration = int(ckpt["iteration"])
        self.history = list(ckpt["history"])
        self.best_fitness = float(ckpt["best_fitness"])
        self.best_epoch = ckpt["best_epoch"]
        self.partial_epoch = ckpt.get("partial_epoch")
        if self.partial_epoch is None:
            log.info("resumed from %s after epoch %d (%d iterations)", path, self.epoch, self.iteration)
            return
        done, batch, per_epoch = (self.partial_epoch[k] for k in ("iterations", "batch", "iters_per_epoch"))
        if (batch, per_epoch) != (self.cfg.batch, self.iters_per_epoch):
            raise TrainError(
                f"{path} (--resume): the checkpoint stopped inside epoch {self.epoch + 1} of batches of {batch}, "
                f"{per_epoch} per epoch; this run has batches of {self.cfg.batch}, {self.iters_per_epoch} per epoch "
                "(keep the same --batch and --max-iters to finish that epoch)"
            )
        log.info(
            "resumed from %s inside epoch %d, after %d of its %d iterations", path, self.epoch + 1, done, per_epoch
        )

    def _init_from(self, path: Path) -> None:
        ckpt = load_checkpoint(path)
        # the class-bias prior (prior_image_size) only initialises weights that the checkpoint replaces
        self._check_same_network(path, ckpt, "--init", "--width and dataset classes", ignore=("prior_image_size",))
        self.model.load_state_dict(ckpt["ema"])
        self.ema.model.load_state_dict(ckpt["ema"])
        log.info("weights from %s (epoch %d of its run)", path, int(ckpt["epoch"]))

    def _check_same_network(self, path: Path, ckpt: dict, how: str, same: str, ignore: tuple[str, ...] = ()) -> None:
        """``TrainError`` naming ``path`` and ``how`` when the checkpoint's network (less ``ignore``) or classes
        are not this run's; ``same``: what the user must keep."""
        mine = {k: v for k, v in self.model_cfg.as_dict().items() if k not in ignore}
        theirs = {k: v for k, v in ckpt["model_config"].items() if k not in ignore}
        if mine != theirs:
            raise TrainError(
                f"{path} ({how}): the checkpoint's network {theirs} differs from this run's {mine} (keep the same "
                f"{same})"
            )
        if ckpt["names"] != self.dataset.names:
            raise TrainError(f"{path} ({how}): classes {ckpt['names']}, the dataset has {self.dataset.names}")

    def _common(self) -> dict:
        return {
            "format": CHECKPOINT_FORMAT,
            "model_config": self.model_cfg.as_dict(),
            "names": list(self.dataset.names),
            "obj_ids": list(self.dataset.obj_ids),
            "imgsz": self.cfg.imgsz,
            "epoch": self.epoch,
        }

    def _save_last(self, partial_epoch: dict | None = None) -> Path:
        """``last.pt``; ``partial_epoch``: how far the epoch after ``self.epoch`` got, when written inside it."""
        return _save(
            {
                **self._common(),
                "train_config": self.cfg.as_dict(),
                "model": self.model.state_dict(),
                "ema": self.ema.model.state_dict(),
                "ema_updates": self.ema.updates,
                "optimizer": self.optimizer.state_dict(),
                "iteration": self.iteration,
                "history": self.history,
                "best_fitness": self.best_fitness,
                "best_epoch": self.best_epoch,
                "torch_rng": torch.get_rng_state(),
                "partial_epoch": partial_epoch,
            },
            self.out / "last.pt",
        )

    def _save_best(self, metrics: dict | None) -> Path:
        return _save({**self._common(), "ema": self.ema.model.state_dict(), "metrics": metrics}, self.out / "best.pt")

    # ------------------------------------------------------------------------------------------------ data
    def _train_batches(
        self, epoch: int, seconds: dict[str, float], first: int = 0
    ) -> Iterator[tuple[torch.Tensor, Targets]]:
        """The epoch's batches from its ``first``; adds the data thread's time building them to ``seconds["build"]``
        and the time spent waiting for them to ``seconds["wait"]``."""
        cfg, aug = self.cfg, self.cfg.augment_config
        order = epoch_order(len(self.dataset.images["train"]), cfg.seed, epoch)
        mosaic = epoch < cfg.epochs - self.close_mosaic
        chunks = [order[k * cfg.batch : (k + 1) * cfg.batch] for k in range(first, self.iters_per_epoch)]

        def build(indices: np.ndarray) -> tuple[torch.Tensor, Targets]:
            start = time.perf_counter()
            examples = [
                train_example(
                    self.dataset,
                    int(i),
                    cfg.crop_size,
                    aug,
                    example_rng(cfg.seed, epoch, int(i)),
                    mosaic,
                    imgsz=cfg.imgsz,
                    mask_stride=self.model_cfg.proto_stride,
                    load=self.instances.load,
                )
                for i in indices
            ]
            batch = collate(examples, cfg.channels_last)
            seconds["build"] += time.perf_counter() - start
            return batch

        # One batch is prepared in a thread while the network trains on the previous one (OpenCV and numpy
        # release the GIL for the heavy parts).
        with ThreadPoolExecutor(max_workers=1) as pool:
            pending = pool.submit(build, chunks[0]) if chunks else None
            for k in range(len(chunks)):
                start = time.perf_counter()
                batch = pending.result()
                seconds["wait"] += time.perf_counter() - start
                pending = pool.submit(build, chunks[k + 1]) if k + 1 < len(chunks) else None
                yield batch

    # ------------------------------------------------------------------------------------------- training
    def _train_epoch(self, epoch: int) -> dict:
        self.model.train()
        # An epoch an interrupted run had begun goes on from its checkpoint's sums; a fresh one starts at zero.
        partial = self.partial_epoch or {
            "iterations": 0, "loss_sums": dict.fromkeys(LOSS_NAMES, 0.0), "train_seconds": 0.0,
            "data_seconds": {"build": 0.0, "wait": 0.0},
        }  # fmt: skip
        self.partial_epoch = None
        n = int(partial["iterations"])
        sums = dict(partial["loss_sums"])
        data = dict(partial["data_seconds"])  # the data thread's seconds this epoch
        bar = tqdm(
            self._train_batches(epoch, data, first=n),
            total=self.iters_per_epoch,
            initial=n,
            desc=f"epoch {epoch + 1}/{self.cfg.epochs}",
            disable=not self.cfg.progress,
            leave=True,
            dynamic_ncols=True,
        )
        start = last_write = time.perf_counter()
        lr = self.cfg.lr
        for images, targets in bar:
            lr = learning_rate(self.cfg, self.iteration, self.iters_per_epoch)
            for group in self.optimizer.param_groups:
                group["lr"] = lr
            images = images.to(self.device, non_blocking=True)
            with autocast(self.device):
                outputs = self.model(images)
            total, terms = self.loss(to_float32(outputs), targets.to(self.device))
            if not math.isfinite(float(total.detach())):
                raise TrainError(
                    f"epoch {epoch + 1}, iteration {self.iteration}: the loss is {float(total.detach())} ({terms})"
                )
            self.optimizer.zero_grad(set_to_none=True)
            self.scaler.scale(total).backward()
            self.scaler.unscale_(self.optimizer)
            torch.nn.utils.clip_grad_norm_(self.model.parameters(), GRAD_CLIP_NORM)
            self.scaler.step(self.optimizer)
            self.scaler.update()
            self.ema.update(self.model)
            self.iteration += 1
            n += 1
            for k in LOSS_NAMES:
                sums[k] += terms[k]
            bar.set_postfix({k: f"{sums[k] / n:.3f}" for k in LOSS_NAMES} | {"lr": f"{lr:.2e}"}, refresh=False)
            if n < self.iters_per_epoch and self._checkpoint_due(last_write):
                self._save_last({
                    "iterations": n, "loss_sums": sums, "data_seconds": data,
                    "train_seconds": partial["train_seconds"] + time.perf_counter() - start,
                    "batch": self.cfg.batch, "iters_per_epoch": self.iters_per_epoch,
                })  # fmt: skip
                last_write = time.perf_counter()
        seconds = partial["train_seconds"] + time.perf_counter() - start
        losses = {k: sums[k] / max(n, 1) for k in LOSS_NAMES}
        losses["total"] = sum(losses.values())
        return {
            "iterations": n,
            "train_seconds": seconds,
            "seconds_per_iter": seconds / max(n, 1),
            # the data thread's time building the batches, and the part of it the network waited for
            "data_build_seconds": data["build"],
            "data_wait_seconds": data["wait"],
            "lr": lr,
            "loss": losses,
        }

    def _checkpoint_due(self, last_write: float) -> bool:
        minutes = self.cfg.checkpoint_minutes
        return minutes is not None and time.perf_counter() - last_write >= 60.0 * minutes

    @torch.no_grad()
    def validate(self, model: YoloSeg) -> DetectionMetrics:
        """COCO mAP of ``model`` on the val split, images letterboxed as the runtime does."""
        model.eval()
        stride = max(model.strides)
        n = len(self.dataset.images["val"])
        detections = []
        for start in range(0, n, self.cfg.batch):
            items = [
                val_example(self.dataset, i, self.cfg.imgsz, stride, self.model_cfg.proto_stride, self.instances.load)
                for i in range(start, min(start + self.cfg.batch, n))
            ]
            by_shape: dict[tuple, list[int]] = {}
            for j, (example, _) in enumerate(items):
                by_shape.setdefault(example.image.shape, []).append(j)
            results: dict[int, object] = {}
            for idx in by_shape.values():
                images, _ = collate([items[j][0] for j in idx], self.cfg.channels_last)
                with autocast(self.device):
                    output0, protos = model(images.to(self.device))
                output0, protos = output0.float().cpu(), protos.float().cpu()
                for row, j in enumerate(idx):
                    results[j] = val_detections(
                        output0[row].numpy(), protos[row].numpy(), items[j][1], self.dataset.num_classes
                    )
            detections += [results[j] for j in range(len(items))]
        return coco_evaluate(self.dataset.coco_gt["val"], detections, self.dataset.obj_ids)

    def run(self) -> TrainResult:
        torch_threads, cv2_threads = torch.get_num_threads(), cv2.getNumThreads()
        torch.set_num_threads(self.cfg.threads)
        cv2.setNumThreads(1)  # the data thread must not compete with torch's threads
        try:
            return self._run()
        finally:
            torch.set_num_threads(torch_threads)
            cv2.setNumThreads(cv2_threads)

    def _run(self) -> TrainResult:
        cfg = self.cfg
        run_start = time.perf_counter()
        if self.epoch >= cfg.epochs:
            log.info("%s: already trained %d of %d epochs; exporting only", self.out, self.epoch, cfg.epochs)
        for epoch in range(self.epoch, cfg.epochs):
            record = {"epoch": epoch + 1, **self._train_epoch(epoch)}
            self.epoch = epoch + 1
            metrics = None
            if self.epoch % cfg.val_every == 0 or self.epoch == cfg.epochs:
                t0 = time.perf_counter()
                metrics = self.validate(self.ema.model).as_dict()
                record["val"] = metrics
                record["val_seconds"] = time.perf_counter() - t0
                fitness = _fitness(metrics)
                if fitness > self.best_fitness or not (self.out / "best.pt").is_file():
                    self.best_fitness, self.best_epoch = fitness, self.epoch
                    self._save_best(metrics)
            self.history.append(record)
            self._save_last()
            self._write_log(None, time.perf_counter() - run_start)
            log.info("%s", _epoch_line(record))
            if cfg.progress:
                tqdm.write(_epoch_line(record))
        best_path = self.out / "best.pt"
        if not best_path.is_file():  # a resumed run that had finished, with best.pt deleted since
            self._save_best(None)
        report = None
        if cfg.export:
            model, _ = model_from_checkpoint(best_path)
            report = export_onnx(
                model,
                self.out / "detector.onnx",
                self.dataset.names,
                self.dataset.obj_ids,
                cfg.imgsz,
                half_weights=cfg.half_weights,
            )
        self._write_log(report, time.perf_counter() - run_start)
        return TrainResult(self.out, self.out / "last.pt", best_path, self.out / "train_log.json", self.history, report)

    def _write_log(self, report: ExportReport | None, seconds: float) -> None:
        write_json_atomic(
            self.out / "train_log.json",
            {
                "format": LOG_FORMAT,
                "config": self.cfg.as_dict(),
                "augment": asdict(self.cfg.augment_config),
                "dataset": {
                    "root": str(self.dataset.yolo_root),
                    "roots": [str(r) for r in self.dataset.roots],
                    "names": self.dataset.names,
                    "obj_ids": self.dataset.obj_ids,
                    "label_source": self.dataset.label_source,
                    "train_images": len(self.dataset.images["train"]),
                    "val_images": len(self.dataset.images["val"]),
                },
                "cache": self.cache_plan.as_dict(),
                "model": {**self.model_cfg.as_dict(), "parameters": count_parameters(self.model)},
                "iters_per_epoch": self.iters_per_epoch,
                "epochs": _json_safe(self.history),
                "best_epoch": self.best_epoch,
                "best_fitness": None if not math.isfinite(self.best_fitness) else self.best_fitness,
                "seconds_this_run": seconds,
                "export": report.as_dict() if report else None,
            },
        )


def _fitness(metrics: dict) -> float:
    """Mask mAP50-95 (box mAP50-95 breaks ties); NaN (nothing to measure) counts as -1."""
    mask, box = metrics["mask_map50_95"], metrics["box_map50_95"]
    mask = mask if math.isfinite(mask) else -1.0
    box = box if math.isfinite(box) else -1.0
    return mask + 1e-3 * box


def _epoch_line(record: dict) -> str:
    loss = record["loss"]
    text = (
        f"epoch {record['epoch']}: {record['iterations']} it, {record['seconds_per_iter']:.2f} s/it, loss "
        + " ".join(f"{k} {loss[k]:.3f}" for k in (*LOSS_NAMES, "total"))
    )
    if "val" in record:
        v = record["val"]
        text += (
            f" | val box mAP50 {v['box_map50']:.3f} mAP50-95 {v['box_map50_95']:.3f}, "
            f"mask mAP50 {v['mask_map50']:.3f} mAP50-95 {v['mask_map50_95']:.3f}"
        )
    return text


def _json_safe(value: object) -> object:
    """NaN -> None, recursively (JSON has no NaN)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    return value


def train(cfg: TrainConfig) -> TrainResult:
    """Runs (or resumes) a training run and exports the best weights; see the module docstring for the files."""
    return _Trainer(cfg).run()
