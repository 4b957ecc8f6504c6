"""Learning curves of detector training runs: validation accuracy against epochs, training images seen and hours.

``sygrid bench training RUN [RUN ...]`` reads each run folder's ``train_log.json`` (written after every epoch by
``sygrid.train.detector.trainer``, so a run still in progress can be charted) and writes
``bench/results/<name>.{json,png}``: per run its configuration summary, per validated epoch the box mAP50 and mask
mAP50-95 on the run's own val split, the images seen so far (iterations x batch) and the cumulative training hours
(training and validation seconds), and per run the median training seconds per iteration over its epochs (after the
first, which fills the image cache where the run keeps one) with whether it cached, charted per epoch beside the
data thread's seconds per batch built and waited for. Nothing is trained here: the figures are the runs' own logs,
so the chart shows where more compute stops paying (a curve that is still rising when the run stops did not
converge). ``--earlier RESULT.json`` charts the runs of an earlier result of this benchmark beside them
(``earlier_curves``): a run whose folder is gone (another machine's, a session's) stays comparable, from the figures
it was charted with.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from sygrid.bench.common import DEFAULT_RESULTS_DIR, save_results
from sygrid.errors import ConfigError
from sygrid.fileio import read_json

#: The two accuracy figures charted (keys of a validation record), with their axis labels.
METRICS = {"box_map50": "val box mAP50", "mask_map50_95": "val mask mAP50-95"}


def run_curve(run_dir: Path) -> dict:
    """One run's learning curve from ``run_dir/train_log.json``: a summary of its recipe and one point per validated
    epoch (epoch, images seen, hours, and the ``METRICS``). Raises ``ConfigError`` naming the file when the log is
    missing or not a detector training log."""
    path = Path(run_dir) / "train_log.json"
    if not path.is_file():
        raise ConfigError(f"{path}: no training log (is {run_dir} a `sygrid train detector` output folder?)")
    log = read_json(path, "training log")
    try:
        cfg, epochs = log["config"], log["epochs"]
        batch = int(cfg["batch"])
    except (KeyError, TypeError, ValueError) as exc:
        raise ConfigError(f"{path}: not a detector training log (missing field {exc})") from None
    points, images, seconds = [], 0, 0.0
    speed = [_speed(record) for record in epochs if int(record.get("iterations", 0)) > 0]
    per_iter = [p["iteration"] for p in speed]
    for record in epochs:
        images += int(record["iterations"]) * batch
        seconds += float(record["train_seconds"]) + float(record.get("val_seconds", 0.0))
        val = record.get("val")
        if val is None:
            continue
        points.append(
            {"epoch": int(record["epoch"]), "images_seen": images, "hours": seconds / 3600.0}
            | {k: val.get(k) for k in METRICS}
        )
    dataset = log.get("dataset", {})
    return {
        "run": str(run_dir),
        "width": cfg.get("size"),
        "p2": cfg.get("p2"),
        "proto_stride": cfg.get("proto_stride"),
        "imgsz": cfg.get("imgsz"),
        "train_size": cfg.get("train_size"),
        "epochs_planned": cfg.get("epochs"),
        "train_images": dataset.get("train_images"),
        "val_images": dataset.get("val_images"),
        "augment": log.get("augment"),
        "best_epoch": log.get("best_epoch"),
        "cache": (log.get("cache") or {}).get("enabled"),
        "seconds_per_iter_median": float(np.median(per_iter[1:] or per_iter)) if per_iter else None,
        "points": points,
        "speed": speed,
    }


def _speed(record: dict) -> dict:
    """One epoch's seconds per iteration: the whole iteration, the data thread's building of a batch and the part of
    it the network waited for (None where the log predates those figures)."""
    n = int(record["iterations"])
    per = {k: (float(record[k]) / n if k in record else None) for k in ("data_build_seconds", "data_wait_seconds")}
    return {"epoch": int(record["epoch"]), "iteration": float(record["train_seconds"]) / n,
            "data_build": per["data_build_seconds"], "data_wait": per["data_wait_seconds"]}  # fmt: skip


def earlier_curves(path: Path) -> list[dict]:
    """The runs of an earlier result of this benchmark (``bench/results/NAME.json``), each marked with the file it
    came from (``earlier``). Raises ``ConfigError`` naming the file when it is not such a result."""
    data = read_json(path, "training benchmark result")
    runs = data.get("runs") if isinstance(data, dict) else None
    if not isinstance(runs, list) or not runs or not all(isinstance(r, dict) and {"run", "points"} <= r.keys()
                                                         for r in runs):  # fmt: skip
        raise ConfigError(f"{path}: not a `sygrid bench training` result (expected a list of runs with points)")
    return [{**r, "earlier": str(path)} for r in runs]


#: The speed figures charted per epoch (keys of ``_speed``), with their panel titles.
SPEEDS = {"iteration": "an iteration", "data_build": "building its batch (data thread)", "data_wait": "data waited for"}


def chart(curves: list[dict]):
    """Val accuracy against epochs, images seen and hours, one line per run; below, seconds per iteration by epoch."""
    fig, axes = plt.subplots(len(METRICS) + 1, 3, figsize=(14, 10), sharey="row", squeeze=False)
    for curve in curves:
        label, style = _label(curve), "--" if curve.get("earlier") else "-"
        for row, (key, name) in enumerate(METRICS.items()):
            for col, x_key in enumerate(("epoch", "images_seen", "hours")):
                xs = [p[x_key] for p in curve["points"] if p[key] is not None]
                ys = [p[key] for p in curve["points"] if p[key] is not None]
                axes[row, col].plot(xs, ys, style, marker=".", label=label)
                axes[row, 0].set_ylabel(name)
        for col, (key, title) in enumerate(SPEEDS.items()):
            speed = [p for p in curve.get("speed", []) if p[key] is not None]
            axes[-1, col].plot([p["epoch"] for p in speed], [p[key] for p in speed], style, marker=".", label=label)
            axes[-1, col].set_title(f"seconds per iteration: {title}", fontsize=9)
            axes[-1, col].set_xlabel("epoch")
    axes[-1, 0].set_ylabel("seconds (this machine)")
    for col, x_name in enumerate(("epoch", "training images seen", "training hours (this machine)")):
        axes[-2, col].set_xlabel(x_name)
    for ax in axes.flat:
        ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=8)
    fig.suptitle("Detector learning curves (validation split of each run's own dataset)")
    fig.tight_layout()
    return fig


def _label(curve: dict) -> str:
    extras = (" +P2" if curve["p2"] else "") + (f" proto/{curve['proto_stride']}" if curve["proto_stride"] != 4 else "")
    name = Path(curve["run"]).name + (" (earlier result)" if curve.get("earlier") else "")
    return f"{name}: {curve['width']}{extras} @{curve['imgsz']}, {curve['train_images']} images"


def format_results(curves: list[dict]) -> str:
    lines = []
    for c in curves:
        last = c["points"][-1] if c["points"] else None
        tail = (
            f"epoch {last['epoch']}/{c['epochs_planned']}, {last['hours']:.2f} h: box mAP50 {last['box_map50']:.3f}, "
            f"mask mAP50-95 {last['mask_map50_95']:.3f}"
            if last
            else "no validated epoch yet"
        )
        if c.get("seconds_per_iter_median") is not None:
            tail += f"; {c['seconds_per_iter_median']:.3f} s per iteration (median), image cache {c.get('cache')}"
        lines.append(f"{_label(c)}: {tail}")
    return "\n".join(lines)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("runs", nargs="+", type=Path, help="`sygrid train detector` output folders")
    parser.add_argument("--name", default="training", help="result name: bench/results/NAME.{json,png}")
    parser.add_argument("--earlier", type=Path, action="append", default=[],
                        help="an earlier result of this benchmark (JSON): its runs charted beside, dashed")  # fmt: skip


def run(args: argparse.Namespace, out_dir: Path = DEFAULT_RESULTS_DIR) -> int:
    curves = [run_curve(r) for r in args.runs] + [c for path in args.earlier for c in earlier_curves(path)]
    print(format_results(curves))
    json_path, png_path = save_results(args.name, {"runs": curves}, chart(curves), out_dir)
    print(f"wrote {json_path} and {png_path}")
    return 0
