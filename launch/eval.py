"""``sygrid eval --data DIR --models DIR``: the perception pipeline's accuracy and speed on a generated dataset.

Prints box/mask mAP and per-part ADD(-S) recall, median rotation and translation errors, and writes them as JSON.
``--sensor ideal,oak-d`` runs the same images through each named sensor model (``sygrid.sensor`` presets, seeded
per image from ``--sensor-seed``): one report per sensor, with the sensed depth's AbsRel and delta1 against the
exact depth, and a table of the sensors side by side. Models that do not know the dataset's parts are refused
before anything runs; a dataset without depth gets detection metrics only. ``--rescue`` also poses, in every frame,
the parts the detections missed (``PerceptionPipeline.rescue``, as the picker asks for it) and reports how many of
those were right.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from launch.eval_detector import (
    add_detector_arguments,
    detector_breakdown,
    detector_overrides,
    warn_part_pixels,
)
from perception.detector_eval import dataset_region
from perception.evaluation import EvalSettings, check_model_classes, evaluate, format_comparison, format_table
from perception.pipeline import PerceptionPipeline, PipelineOverrides
from sygrid.errors import ConfigError
from sygrid.fileio import write_json_atomic
from sygrid.sensor import SENSOR_PRESETS, sensor_preset


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", type=Path, required=True, help="dataset folder made by 'sygrid generate'")
    parser.add_argument("--models", type=Path, required=True, help="model folder with manifest.json")
    parser.add_argument("--split", default=None, help="BOP split (default: test, else val_pbr)")
    parser.add_argument("--max-images", type=int, default=None)
    parser.add_argument("--pose-method", choices=["direct", "pnp"], default=None, help="override the manifest's")
    refine = parser.add_mutually_exclusive_group()
    refine.add_argument("--refine", dest="refine", action="store_true", default=None, help="ICP on depth")
    refine.add_argument("--no-refine", dest="refine", action="store_false")
    parser.add_argument("--threads", type=int, default=2, help="onnxruntime threads")
    parser.add_argument(
        "--sensor",
        default="ideal",
        help=f"sensor model(s) the frames go through, comma-separated (default ideal: the stored frames); "
        f"{', '.join(SENSOR_PRESETS)}",
    )
    parser.add_argument("--sensor-seed", type=int, default=0, help="seeds the sensor models, with each image's ids")
    parser.add_argument(
        "--rescue", action="store_true",
        help="also pose the parts the detections missed on the depth (PerceptionPipeline.rescue), as the picker does",
    )  # fmt: skip
    parser.add_argument(
        "--out", type=Path, default=None, help="JSON report (default: DATA/eval_<models>[_<sensor>].json)"
    )
    add_detector_arguments(parser)


def run(args: argparse.Namespace) -> int:
    sensors = [name.strip() for name in args.sensor.split(",") if name.strip()]
    if not sensors or len(set(sensors)) != len(sensors):
        raise ConfigError(f"--sensor: expected distinct sensor names, got {args.sensor!r}")
    for name in sensors:
        sensor_preset(name, "--sensor")
    overrides = PipelineOverrides(pose_method=args.pose_method, refine=args.refine, num_threads=args.threads,
                                  **detector_overrides(args))  # fmt: skip
    pipeline = PerceptionPipeline.from_folder(args.models, overrides)
    check_model_classes(args.data, {obj_id: m.name for obj_id, m in pipeline.models.items()}, args.split)
    warn_part_pixels(args)
    region = dataset_region(args.data, args.region)
    reports = []
    for name in sensors:
        settings = EvalSettings(split=args.split, max_images=args.max_images, sensor=name, sensor_seed=args.sensor_seed,
                                region=region, rescue=args.rescue)  # fmt: skip
        report = evaluate(pipeline, args.data, settings)
        print(format_table(report))
        if name == "ideal":  # the detector alone on the stored frames: AP and recall per part, size and visibility
            report["detector"] = detector_breakdown(args, pipeline, settings)
        print(f"wrote {write_json_atomic(_out_path(args, name, len(sensors)), report)}")
        reports.append(report)
    if len(reports) > 1:
        print(format_comparison(reports))
    return 0


def _out_path(args: argparse.Namespace, sensor: str, n_sensors: int) -> Path:
    """``--out`` (or DATA/eval_<models>.json) for a lone ideal sensor; otherwise the sensor's name is appended."""
    out = args.out or args.data / f"eval_{args.models.name}.json"
    if n_sensors == 1 and (sensor == "ideal" or args.out is not None):
        return out
    return out.with_name(f"{out.stem}_{sensor}{out.suffix}")
