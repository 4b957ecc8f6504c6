"""Training of the pose network on a BOP dataset: AdamW with a warm-up and a cosine schedule, checkpoints that
resume exactly, validation on ``val_pbr`` with the paper's metrics, and the ONNX export of the best model.

Determinism and resuming: the samples of iteration ``i`` are drawn from ``SeedSequence([seed, i])`` (the epoch's
order from ``[seed, epoch]``) and nothing else in a step is random, so a run resumed from ``last.pt`` continues
with the same batches it would have seen.

Files under ``out_dir``: ``last.pt`` (every ``checkpoint_every`` iterations and at each validation), ``best.pt``
(highest direct ADD(-S) recall on validation; the last model when there is no validation split), ``pose.onnx``
(exported from ``best.pt``), ``train_log.json`` (configuration, loss means, validation tables, timings).
"""

from __future__ import annotations

import io
import logging
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from sygrid.catalogue import load_catalogue
from sygrid.errors import ConfigError
from sygrid.fileio import write_bytes_atomic, write_json_atomic
from sygrid.metrics import pose_errors, pose_metrics_table
from sygrid.objects.model import ObjectModel
from sygrid.pose_geometry import decode_direct, decode_pnp
from sygrid.train.device import autocast, grad_scaler, resolve_device, to_float32
from sygrid.train.pose.config import TrainConfig
from sygrid.train.pose.data import CoordinateRenderer, InstanceCrop, SampleConfig, collate, index_split, make_sample
from sygrid.train.pose.export import export_onnx
from sygrid.train.pose.losses import PoseLoss
from sygrid.train.pose.model import PoseNet, PoseNetForExport
from sygrid.train.pose.objects import ObjectTables, build_tables, catalogue_models, load_bop_models

log = logging.getLogger(__name__)

CHECKPOINT_FORMAT = "sygrid-pose-checkpoint/1"
_ARCH_KEYS = ("input_size", "output_stride", "width", "num_regions")


@dataclass
class TrainResult:
    out_dir: Path
    iterations: int
    seconds: float
    seconds_per_iter: float
    best_val: dict | None
    onnx_path: Path
    export_max_diff: float
    files: list[Path]


# ------------------------------------------------------------------------------------------------ validation
def evaluate(
    net: PoseNet,
    crops: list[InstanceCrop],
    tables: ObjectTables,
    models: dict[int, ObjectModel],
    renderer: CoordinateRenderer,
    sample_config: SampleConfig,
    batch_size: int = 64,
    methods: tuple[str, ...] = ("direct", "pnp"),
) -> dict:
    """ADD(-S) recall, median re and te per method on ``crops`` (ground-truth visible boxes, no augmentation).

    Returns ``{method: {"all": row, "per_object": {obj_id: row}}}`` with the rows of
    ``sygrid.metrics.pose_metrics_table``; a failed PnP counts as a miss.
    """
    wrapper = PoseNetForExport(net).eval()
    device = next(net.parameters()).device
    records: dict[str, list] = {m: [] for m in methods}
    with torch.no_grad():
        for start in range(0, len(crops), batch_size):
            chunk = crops[start : start + batch_size]
            batch = collate([make_sample(c, tables, renderer, sample_config, None) for c in chunk])
            onehot = np.eye(tables.num_classes, dtype=np.float32)[batch["class_index"]]
            inputs = (torch.from_numpy(a).to(device) for a in (batch["image"], batch["coord2d"], onehot))
            with autocast(device):
                outputs = wrapper(*inputs)
            xyz, mask, _, rot6d, site = (t.float().cpu().numpy() for t in outputs)
            for j, crop in enumerate(chunk):
                c = crop.class_index
                centre, size = batch["roi"][j, :2], float(batch["roi"][j, 2])
                model = models[crop.obj_id]
                for method in methods:
                    if method == "direct":
                        try:
                            T = decode_direct(rot6d[j], site[j], centre, size, crop.K, tables.diameters_m[c])
                        except ValueError:  # a depth behind the camera (an untrained network): a miss
                            T = None
                    else:
                        sol = decode_pnp(xyz[j], mask[j, 0], centre, size, crop.K, tables.bounds_m[c])
                        T = None if sol is None else sol.T_camera_object
                    records[method].append(pose_errors(T, crop.T_camera_obj, model))
    return {m: _json_table(pose_metrics_table(r)) for m, r in records.items()}


def _json_table(table: dict) -> dict:
    return {"all": table["all"], "per_object": {str(k): v for k, v in table["per_object"].items()}}


def _spread(items: list, n: int) -> list:
    """At most ``n`` items spread evenly over the list (validation on every image, not only the first)."""
    if len(items) <= n:
        return items
    return [items[i] for i in np.linspace(0, len(items) - 1, n).round().astype(int)]


# ------------------------------------------------------------------------------------------------ checkpoints
def _save(path: Path, state: dict) -> None:
    buf = io.BytesIO()
    torch.save(state, buf)
    write_bytes_atomic(path, buf.getvalue())


def _load(path: Path) -> dict:
    try:
        state = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as exc:  # torch raises many types for a truncated or foreign file
        raise ConfigError(f"{path}: not a readable checkpoint ({type(exc).__name__}: {exc})") from exc
    if not isinstance(state, dict) or state.get("format") != CHECKPOINT_FORMAT:
        raise ConfigError(f"{path}: not a pose checkpoint (expected format {CHECKPOINT_FORMAT!r})")
    return state


def _lr_factor(it: int, total: int, warmup: int) -> float:
    """Linear warm-up, then cosine decay to 1 % of the base rate."""
    if it < warmup:
        return (it + 1) / warmup
    progress = (it - warmup) / max(total - warmup, 1)
    return 0.01 + 0.99 * 0.5 * (1.0 + math.cos(math.pi * min(progress, 1.0)))


# ------------------------------------------------------------------------------------------------ the run
def train(config: TrainConfig, resume: bool = False) -> TrainResult:
    """Trains, validates and exports; see the module docstring for the files written."""
    out = Path(config.out_dir)
    last_path, best_path = out / "last.pt", out / "best.pt"
    if resume and not last_path.is_file():
        raise ConfigError(f"{last_path}: nothing to resume (no checkpoint); run without --resume to start")
    if not resume and last_path.exists():
        raise ConfigError(f"{last_path} exists: pass --resume to continue that run, or choose another --out")
    if config.threads is not None:
        torch.set_num_threads(int(config.threads))
    try:
        device = resolve_device(config.device)
    except ValueError as err:
        raise ConfigError(f"--device: {err}") from err
    torch.manual_seed(config.seed)
    bop = Path(config.data_dir) / "bop"
    if not bop.is_dir():
        raise ConfigError(f"{config.data_dir}: no bop/ folder; expected a dataset written by 'sygrid generate'")

    if config.catalogue is not None:
        models = catalogue_models(load_catalogue(config.catalogue), bop / "models", config.objects)
    else:
        models = load_bop_models(bop / "models", config.objects)
    tables = build_tables(models, config.num_regions, sym_steps=config.sym_steps, seed=config.seed)
    sample_cfg = SampleConfig(input_size=config.input_size, output_size=config.output_size)
    train_crops = index_split(
        bop, "train_pbr", tables.obj_ids, sample_cfg, config.min_visib_fract, progress=config.progress
    )
    if not train_crops:
        raise ConfigError(
            f"{bop / 'train_pbr'}: no training instances of obj_ids {list(tables.obj_ids)} with visib_fract >= "
            f"{config.min_visib_fract}"
        )
    val_crops = _spread(
        index_split(bop, "val_pbr", tables.obj_ids, sample_cfg, config.min_visib_fract, progress=config.progress),
        config.val_max,
    )
    renderer = CoordinateRenderer(models)
    log.info("pose training: %d train instances, %d validation instances, obj_ids %s", len(train_crops),
             len(val_crops), list(tables.obj_ids))  # fmt: skip

    net_cfg = config.net_config(tables.num_classes)
    net = PoseNet(net_cfg).to(device)
    criterion = PoseLoss(tables, config.loss_weights).to(device)
    optimizer = torch.optim.AdamW(net.parameters(), lr=config.lr, weight_decay=config.weight_decay)
    scaler = grad_scaler(device)
    n = len(train_crops)
    iters_per_epoch = max(1, n // config.batch_size)
    total = config.epochs * iters_per_epoch
    if config.max_iters is not None:
        total = min(total, config.max_iters)
    scheduler = torch.optim.lr_scheduler.LambdaLR(
        optimizer, lambda it: _lr_factor(it, total, min(config.warmup_iters, max(total // 10, 1)))
    )
    train_log: dict = {"config": config.as_json(), "architecture": net_cfg.as_dict(), "obj_ids": list(tables.obj_ids),
                       "train_instances": n, "val_instances": len(val_crops), "entries": [],
                       "runs": [{"start_iteration": 0, "epochs": config.epochs}]}  # fmt: skip
    start, best, seconds_before = 0, None, 0.0
    if resume:
        state = _load(last_path)
        if state["architecture"] != net_cfg.as_dict() or state["obj_ids"] != list(tables.obj_ids):
            raise ConfigError(
                f"{last_path}: the checkpoint's architecture/objects {state['architecture']}, {state['obj_ids']} "
                f"differ from this run's {net_cfg.as_dict()}, {list(tables.obj_ids)}"
            )
        net.load_state_dict(state["model"])
        optimizer.load_state_dict(state["optimizer"])
        scheduler.load_state_dict(state["scheduler"])
        start, best, seconds_before = state["iteration"], state["best"], state["seconds"]
        train_log["entries"] = state["log_entries"]
        # Every invocation of a resumed run (a longer --epochs on resume restarts the cosine schedule from where
        # the new length puts it), so the model card can tell how the model was trained.
        first = [{"start_iteration": 0, "epochs": state["train_config"]["epochs"]}]
        train_log["runs"] = [*state.get("runs", first), {"start_iteration": start, "epochs": config.epochs}]
        log.info("resuming %s at iteration %d of %d", last_path, start, total)

    def checkpoint(it: int, seconds: float) -> None:
        state = {
            "format": CHECKPOINT_FORMAT,
            "iteration": it,
            "seconds": seconds,
            "architecture": net_cfg.as_dict(),
            "obj_ids": list(tables.obj_ids),
            "pad_scale": sample_cfg.pad_scale,
            "train_config": config.as_json(),
            "model": net.state_dict(),
            "optimizer": optimizer.state_dict(),
            "scheduler": scheduler.state_dict(),
            "best": best,
            "log_entries": train_log["entries"],
            "runs": train_log["runs"],
        }
        _save(last_path, state)
        write_json_atomic(out / "train_log.json", train_log)

    t_start = time.perf_counter()
    sums: dict[str, float] = {}
    count, step_seconds, data_seconds, cpu0 = 0, 0.0, 0.0, time.process_time()
    perm_epoch, perm = -1, None
    bar = tqdm(total=total, initial=start, desc="train pose", disable=not config.progress, unit="it")
    net.train()
    for it in range(start, total):
        epoch = it // iters_per_epoch
        if epoch != perm_epoch:
            perm_epoch, perm = epoch, np.random.default_rng([config.seed, epoch]).permutation(n)
        t0 = time.perf_counter()
        pos = (it % iters_per_epoch) * config.batch_size
        idx = perm.take(range(pos, pos + config.batch_size), mode="wrap")
        rngs = np.random.SeedSequence([config.seed, it]).spawn(len(idx))
        samples = [make_sample(train_crops[i], tables, renderer, sample_cfg, np.random.default_rng(r))
                   for i, r in zip(idx, rngs, strict=True)]  # fmt: skip
        batch = {k: torch.from_numpy(v).to(device) for k, v in collate(samples).items() if k != "roi"}
        onehot = torch.nn.functional.one_hot(batch["class_index"], tables.num_classes).float()
        t1 = time.perf_counter()
        with autocast(device):
            outputs = net(batch["image"], batch["coord2d"], onehot)
        loss, parts = criterion(to_float32(outputs), batch)
        optimizer.zero_grad(set_to_none=True)
        scaler.scale(loss).backward()
        scaler.unscale_(optimizer)
        torch.nn.utils.clip_grad_norm_(net.parameters(), 10.0)
        scaler.step(optimizer)
        scaler.update()
        scheduler.step()
        t2 = time.perf_counter()
        data_seconds += t1 - t0
        step_seconds += t2 - t1
        count += 1
        for k, v in {"loss": float(loss.detach()), **parts}.items():
            sums[k] = sums.get(k, 0.0) + v
        bar.update(1)
        bar.set_postfix(loss=f"{float(loss.detach()):.3f}", lr=f"{scheduler.get_last_lr()[0]:.1e}")

        done = it + 1
        end_of_epoch = done % iters_per_epoch == 0 or done == total
        if end_of_epoch or done % config.checkpoint_every == 0:
            seconds = seconds_before + time.perf_counter() - t_start
            entry = {
                "iteration": done,
                "epoch": done / iters_per_epoch,
                "lr": scheduler.get_last_lr()[0],
                "loss": {k: v / count for k, v in sums.items()},
                "seconds_per_iter": (data_seconds + step_seconds) / count,
                "data_seconds_per_iter": data_seconds / count,
                # process CPU time (all threads): on a shared machine, wall time also counts other jobs' load
                "cpu_seconds_per_iter": (time.process_time() - cpu0) / count,
                "seconds": seconds,
            }
            sums, count, step_seconds, data_seconds = {}, 0, 0.0, 0.0
            if end_of_epoch and val_crops:
                entry["val"] = evaluate(net, val_crops, tables, models, renderer, sample_cfg)
                net.train()
                recall = entry["val"]["direct"]["all"]["add_recall"]
                log.info("iteration %d: val ADD(-S) recall direct %.3f, pnp %.3f", done, recall,
                         entry["val"]["pnp"]["all"]["add_recall"])  # fmt: skip
                if best is None or recall > best["add_recall"]:
                    best = {"iteration": done, "add_recall": recall}
                    _save(best_path, {"format": CHECKPOINT_FORMAT, "iteration": done, "architecture": net_cfg.as_dict(),
                                      "obj_ids": list(tables.obj_ids), "pad_scale": sample_cfg.pad_scale,
                                      "model": net.state_dict(), "val": entry["val"]})  # fmt: skip
            train_log["entries"].append(entry)
            checkpoint(done, seconds)
            cpu0 = time.process_time()
    bar.close()
    seconds = seconds_before + time.perf_counter() - t_start
    if start >= total:
        log.info("%s: already trained for %d iterations", last_path, total)
    if not val_crops or not best_path.exists():
        _save(best_path, {"format": CHECKPOINT_FORMAT, "iteration": total, "architecture": net_cfg.as_dict(),
                          "obj_ids": list(tables.obj_ids), "pad_scale": sample_cfg.pad_scale,
                          "model": net.state_dict(), "val": None})  # fmt: skip
    best_state = _load(best_path)
    net.load_state_dict(best_state["model"])
    net.cpu()  # the export and its check against onnxruntime run on the CPU
    check_crops = (val_crops or train_crops)[: min(8, len(val_crops or train_crops))]
    check = collate([make_sample(c, tables, renderer, sample_cfg, None) for c in check_crops])
    check["class_onehot"] = np.eye(tables.num_classes, dtype=np.float32)[check["class_index"]]
    onnx_path = out / "pose.onnx"
    diff = export_onnx(net, tables, sample_cfg.pad_scale, onnx_path, check)
    train_log["export"] = {"onnx": str(onnx_path), "from": str(best_path), "iteration": best_state["iteration"],
                           "max_abs_diff_vs_torch": diff, "bytes": onnx_path.stat().st_size}  # fmt: skip
    train_log["best"] = best
    train_log["seconds"] = seconds
    write_json_atomic(out / "train_log.json", train_log)
    timed = [e["seconds_per_iter"] for e in train_log["entries"]]
    return TrainResult(
        out_dir=out,
        iterations=total,
        seconds=seconds,
        seconds_per_iter=float(np.mean(timed)) if timed else float("nan"),
        best_val=best_state.get("val"),
        onnx_path=onnx_path,
        export_max_diff=diff,
        files=[last_path, best_path, onnx_path, out / "train_log.json"],
    )
