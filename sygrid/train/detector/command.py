"""``sygrid train detector --data DIR --out DIR``: train the YOLOv8-style segmenter and export it to ONNX.

Argument parsing only imports the standard library (the defaults come from ``config.TrainConfig``); torch is
imported when the command runs.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import fields
from pathlib import Path

from sygrid.train.detector.config import CACHE_MODES, MODEL_SIZES, PROTO_STRIDES, TrainConfig
from sygrid.train.device_choice import DEVICE_CHOICES

DEFAULTS = {f.name: f.default for f in fields(TrainConfig)}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--data", required=True, action="append",
        help="dataset folder (sygrid generate output, or a YOLO data.yaml); repeat it to train on several as one "
        "(the same classes), e.g. plain and randomised renders",
    )  # fmt: skip
    parser.add_argument("--out", required=True, help="output folder: last.pt, best.pt, detector.onnx, train_log.json")
    parser.add_argument("--epochs", type=int, default=DEFAULTS["epochs"], help="total epochs (%(default)s)")
    parser.add_argument(
        "--imgsz",
        type=int,
        default=DEFAULTS["imgsz"],
        help="model input side, multiple of 32: frames are letterboxed into it (%(default)s)",
    )
    parser.add_argument(
        "--train-size",
        type=int,
        default=DEFAULTS["train_size"],
        help="side of the square training crops, multiple of 32, at most imgsz (%(default)s); objects keep the "
        "imgsz scale",
    )
    parser.add_argument("--batch", type=int, default=DEFAULTS["batch"], help="images per iteration (%(default)s)")
    parser.add_argument(
        "--width",
        default=DEFAULTS["size"],
        choices=MODEL_SIZES,
        help="network size: f (femto, 0.43 M parameters), p (pico, 1.0 M), n (YOLOv8n's scale, 3.3 M), "
        "s (11.8 M) (%(default)s)",
    )
    parser.add_argument("--p2", action="store_true", help="add a stride-4 detection level (parts a few cells wide)")
    parser.add_argument(
        "--proto-stride", type=int, default=DEFAULTS["proto_stride"], choices=PROTO_STRIDES,
        help="mask prototypes' stride: 4, or 2 for finer masks (%(default)s)",
    )  # fmt: skip
    parser.add_argument(
        "--device", default=DEFAULTS["device"], choices=DEVICE_CHOICES,
        help="auto: CUDA (mixed precision) when torch sees it, else the CPU (%(default)s)",
    )  # fmt: skip
    parser.add_argument("--seed", type=int, default=DEFAULTS["seed"], help="initialisation, data order, augmentation")
    parser.add_argument("--resume", action="store_true", help="continue from OUT/last.pt")
    parser.add_argument(
        "--checkpoint-minutes", type=float, default=DEFAULTS["checkpoint_minutes"],
        help="write OUT/last.pt inside an epoch every this many minutes too, so that --resume loses at most that "
        "much (%(default)s)",
    )  # fmt: skip
    parser.add_argument(
        "--init", default=None, help="start from this checkpoint's weights (fine-tuning; same --width and classes)"
    )
    parser.add_argument(
        "--threads",
        type=int,
        default=DEFAULTS["threads"],
        help="torch threads (%(default)s: on a shared 2-core machine a second thread mostly waits)",
    )
    parser.add_argument("--max-iters", type=int, default=None, help="at most this many iterations per epoch")
    parser.add_argument("--lr", type=float, default=DEFAULTS["lr"], help="peak AdamW learning rate (%(default)s)")
    parser.add_argument(
        "--labels", default=DEFAULTS["labels"], choices=("auto", "coco", "yolo"), help="where masks come from"
    )
    ids = parser.add_mutually_exclusive_group()
    ids.add_argument(
        "--catalogue",
        default=None,
        help="parts catalogue (.toml/.json) the dataset was made from: the classes' ids by name, checked against "
        "the dataset's (default: the ids the dataset itself records)",
    )
    ids.add_argument(
        "--id-map",
        default=None,
        help="JSON file: class name or index -> obj_id, for classes that are not built-in "
        "parts when the dataset has no bop/ folder or COCO categories naming them",
    )
    parser.add_argument(
        "--val-every", type=int, default=DEFAULTS["val_every"], help="validate every N epochs (and after the last)"
    )
    parser.add_argument(
        "--augment", default=None, help='JSON object of augmentation overrides, e.g. \'{"mosaic": 0.0, "degrees": 0}\''
    )
    parser.add_argument(
        "--cache", default=DEFAULTS["cache"], choices=CACHE_MODES,
        help="keep decoded images in memory after the first epoch: ram, none, or auto (when they fit in half the "
        "available memory) (%(default)s)",
    )  # fmt: skip
    parser.add_argument(
        "--half-weights", action="store_true", help="store the ONNX weights as float16 (half the file size)"
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bars (one log line per epoch)")


def run(args: argparse.Namespace) -> int:
    from sygrid.id_map import load_id_map
    from sygrid.train.detector.trainer import TrainConfig, TrainError, train  # torch from here on

    try:
        augment = json.loads(args.augment) if args.augment else {}
        if not isinstance(augment, dict):
            raise ValueError(f"expected a JSON object, got {args.augment!r}")
    except (json.JSONDecodeError, ValueError) as err:
        raise TrainError(f"--augment: {err}") from err
    try:
        cfg = TrainConfig(
            data=args.data[0] if len(args.data) == 1 else tuple(args.data),
            out=args.out,
            epochs=args.epochs,
            imgsz=args.imgsz,
            train_size=args.train_size,
            batch=args.batch,
            size=args.width,
            p2=args.p2,
            proto_stride=args.proto_stride,
            device=args.device,
            seed=args.seed,
            threads=args.threads,
            max_iters=args.max_iters,
            labels=args.labels,
            id_map=load_id_map(args.id_map) if args.id_map else None,
            catalogue=str(Path(args.catalogue).resolve()) if args.catalogue else None,
            val_every=args.val_every,
            augment=augment,
            resume=args.resume,
            checkpoint_minutes=args.checkpoint_minutes,
            init=args.init,
            half_weights=args.half_weights,
            cache=args.cache,
            progress=not args.no_progress,
            lr=args.lr,
        )
    except (ValueError, TypeError) as err:
        raise TrainError(f"sygrid train detector: {err}") from err
    result = train(cfg)
    best = next((r for r in reversed(result.history) if "val" in r), None)
    print(
        f"wrote {result.last}, {result.best}, {result.export.path} ({result.export.size_bytes / 1e6:.1f} MB), "
        f"{result.log}"
    )
    if best is not None:
        v = best["val"]
        print(
            f"last validation (epoch {best['epoch']}): "
            f"box mAP50 {v['box_map50']:.3f} mAP50-95 {v['box_map50_95']:.3f}, "
            f"mask mAP50 {v['mask_map50']:.3f} mAP50-95 {v['mask_map50_95']:.3f}"
        )
    return 0
