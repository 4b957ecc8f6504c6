"""``sygrid train pose --data DIR --out DIR``: train the GDR-Net-style pose network on DIR/bop, export OUT/pose.onnx.

Writes OUT/last.pt (resume with ``--resume``), OUT/best.pt, OUT/pose.onnx and OUT/train_log.json. Argument parsing
only imports the standard library (the defaults come from ``config.TrainConfig``); torch is imported when the command
runs.
"""

from __future__ import annotations

import argparse
from dataclasses import fields
from pathlib import Path

from sygrid.errors import ConfigError
from sygrid.train.device_choice import DEVICE_CHOICES
from sygrid.train.pose.config import TrainConfig

DEFAULTS = {f.name: f.default for f in fields(TrainConfig)}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", type=Path, required=True, help="dataset folder written by 'sygrid generate'")
    parser.add_argument("--out", type=Path, required=True, help="output folder (checkpoints, ONNX, log)")
    parser.add_argument(
        "--epochs", type=int, default=DEFAULTS["epochs"], help="passes over the training instances (%(default)s)"
    )
    parser.add_argument(
        "--input-size", type=int, default=DEFAULTS["input_size"], help="RoI side in pixels (%(default)s)"
    )
    parser.add_argument(
        "--output-stride",
        type=int,
        default=DEFAULTS["output_stride"],
        choices=(2, 4, 8),
        help="input / dense output size (%(default)s)",
    )
    parser.add_argument(
        "--width", type=int, default=DEFAULTS["width"], help="backbone width, channels of the first stage (%(default)s)"
    )
    parser.add_argument("--batch", type=int, default=DEFAULTS["batch_size"], help="batch size (%(default)s)")
    parser.add_argument("--lr", type=float, default=DEFAULTS["lr"], help="AdamW base learning rate (%(default)s)")
    parser.add_argument("--seed", type=int, default=DEFAULTS["seed"])
    parser.add_argument("--resume", action="store_true", help="continue from OUT/last.pt")
    parser.add_argument(
        "--threads", type=int, default=DEFAULTS["threads"], help="torch CPU threads (default: torch's choice)"
    )
    parser.add_argument(
        "--device", default=DEFAULTS["device"], choices=DEVICE_CHOICES,
        help="auto: CUDA (mixed precision) when torch sees it, else the CPU (%(default)s)",
    )  # fmt: skip
    parser.add_argument("--max-iters", type=int, default=None, help="stop after this many iterations in all")
    parser.add_argument("--val-max", type=int, default=DEFAULTS["val_max"], help="validation instances (%(default)s)")
    parser.add_argument(
        "--min-visib",
        type=float,
        default=DEFAULTS["min_visib_fract"],
        help="least visible fraction of a trained instance (%(default)s)",
    )
    parser.add_argument(
        "--catalogue",
        type=Path,
        default=None,
        help="parts catalogue (.toml/.json) the dataset was made from: the parts' names and symmetries come from it, "
        "checked against the dataset's models (default: the dataset's bop/models)",
    )
    parser.add_argument(
        "--objects", nargs="+", default=None,
        help="obj_ids, built-in part names or the catalogue's part names to train for (default: all)",
    )  # fmt: skip
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def _obj_ids(values: list[str] | None, catalogue: Path | None) -> tuple[int, ...] | None:
    if values is None:
        return None
    from sygrid.catalogue import load_catalogue

    names = {p.name: p.id for p in load_catalogue(catalogue).parts} if catalogue is not None else {}
    ids = []
    for value in values:
        if value.isdigit():
            ids.append(int(value))
            continue
        if value in names:
            ids.append(names[value])
            continue
        from sygrid.objects.parts import BUILTIN_PARTS, builtin_part

        if value not in BUILTIN_PARTS:
            raise ConfigError(
                f"--objects: {value!r} is neither an obj_id, a part of the catalogue nor a built-in part "
                f"({', '.join([*names, *BUILTIN_PARTS])})"
            )
        ids.append(builtin_part(value).obj_id)
    return tuple(sorted(set(ids)))


def run(args: argparse.Namespace) -> int:
    from sygrid.train.pose.train import train  # torch is imported only when training runs

    config = TrainConfig(
        data_dir=args.data,
        out_dir=args.out,
        epochs=args.epochs,
        batch_size=args.batch,
        input_size=args.input_size,
        output_stride=args.output_stride,
        width=args.width,
        lr=args.lr,
        seed=args.seed,
        threads=args.threads,
        device=args.device,
        max_iters=args.max_iters,
        objects=_obj_ids(args.objects, args.catalogue),
        catalogue=args.catalogue.resolve() if args.catalogue is not None else None,
        min_visib_fract=args.min_visib,
        val_max=args.val_max,
        progress=not args.no_progress,
    )
    result = train(config, resume=args.resume)
    print(
        f"trained {result.iterations} iterations in {result.seconds:.0f} s ({result.seconds_per_iter:.3f} s/iter); "
        f"ONNX matches torch within {result.export_max_diff:.1e}"
    )
    if result.best_val:
        for method, table in result.best_val.items():
            row = table["all"]
            print(
                f"val {method}: ADD(-S) recall {row['add_recall']:.3f}, median re {row['median_re_deg']:.2f} deg, "
                f"median te {row['median_te_mm']:.2f} mm ({row['n']} instances)"
            )
    for path in result.files:
        print(f"wrote {path}")
    return 0
