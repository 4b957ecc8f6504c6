"""``sygrid train detector|pose --data DIR --out DIR``: train a model on a generated dataset and export it to ONNX.

Each model kind lives in its own module (``sygrid.train.<kind>.command``) providing ``add_arguments(parser)`` and
``run(args) -> int``; torch comes from the ``train`` extra and is imported only when training runs.
"""

from __future__ import annotations

import argparse
import importlib

KINDS = {
    "detector": ("sygrid.train.detector.command", "YOLO-style instance segmentation on the dataset's yolo/ folder"),
    "pose": ("sygrid.train.pose.command", "GDR-Net-style 6D pose on the dataset's bop/ folder"),
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="kind", required=True, metavar="KIND")
    for name, (module, help_text) in KINDS.items():
        kind_parser = sub.add_parser(name, help=help_text, description=help_text)
        importlib.import_module(module).add_arguments(kind_parser)


def run(args: argparse.Namespace) -> int:
    return int(importlib.import_module(KINDS[args.kind][0]).run(args) or 0)
