"""``sygrid eval --data DIR --models DIR``: the perception pipeline's accuracy and speed on a generated dataset.

Prints box/mask mAP and per-part ADD(-S) recall, median rotation and translation errors, and writes them as JSON.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from perception.evaluation import EvalSettings, evaluate, format_table
from perception.pipeline import PerceptionPipeline, PipelineOverrides
from sygrid.fileio import write_json_atomic


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
    parser.add_argument("--out", type=Path, default=None, help="JSON report (default: DATA/eval_<models>.json)")


def run(args: argparse.Namespace) -> int:
    overrides = PipelineOverrides(pose_method=args.pose_method, refine=args.refine, num_threads=args.threads)
    pipeline = PerceptionPipeline.from_folder(args.models, overrides)
    report = evaluate(pipeline, args.data, EvalSettings(split=args.split, max_images=args.max_images))
    print(format_table(report))
    out = args.out or args.data / f"eval_{args.models.name}.json"
    print(f"wrote {write_json_atomic(out, report)}")
    return 0
