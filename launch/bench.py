"""``sygrid bench NAME``: run one benchmark; it prints medians and writes bench/results/NAME.{json,png}."""

from __future__ import annotations

import argparse
import importlib
from pathlib import Path

# name -> module providing add_arguments(parser) and run(args, out_dir)
BENCHMARKS = {
    "physics": "sygrid.bench.physics",
    "sim": "sim.bench",
    "render": "sygrid.bench.render",
    "generation": "sygrid.bench.generation",
    "parts": "sygrid.bench.parts",
    "perception": "perception.bench",
    "cell": "launch.bench_cell",
    "cell-detector": "launch.bench_cell_detector",
    "nudge": "launch.bench_nudge",
    "detection": "perception.bench_detection",
    "training": "sygrid.bench.training",
    "transfer": "perception.bench_transfer",
    "stability": "launch.stability.bench",
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out-dir", type=Path, default=Path("bench/results"), help="where JSON and PNG go")
    sub = parser.add_subparsers(dest="benchmark", required=True, metavar="BENCHMARK")
    for name, module in BENCHMARKS.items():
        bench_parser = sub.add_parser(name, help=importlib.import_module(module).__doc__.split("\n")[0])
        importlib.import_module(module).add_arguments(bench_parser)


def run(args: argparse.Namespace) -> int:
    return importlib.import_module(BENCHMARKS[args.benchmark]).run(args, out_dir=args.out_dir)
