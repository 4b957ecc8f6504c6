"""The ``sygrid`` command. Each subcommand lives in its own module and is imported only when it runs, so
``sygrid --help`` stays fast and a missing optional dependency only breaks the command that needs it."""

from __future__ import annotations

import argparse
import importlib
import logging
import signal
import sys

from sygrid.errors import SygridError

# name -> (module, one-line help). The module provides add_arguments(parser) and run(args) -> int.
SUBCOMMANDS: dict[str, tuple[str, str]] = {
    "demo": ("launch.demo", "the main job: the picking demo in the simulated cell (sygrid pick on its defaults)"),
    "drop": ("launch.drop", "drop the parts of a scene into its bin and write their poses"),
    "parts": ("launch.parts", "inspect the built-in parts or your own CAD files / catalogue; export a part as a mesh"),
    "bench": ("launch.bench", "run a benchmark and write its JSON and chart"),
    "sim": ("sim.server", "serve a simulated UR5e cell that ur_rtde clients can drive"),
    "generate": ("launch.generate", "generate (or resume) a dataset from a recipe: BOP, YOLO and COCO labels"),
    "train": ("launch.train", "train the detector or the pose model on a generated dataset, export ONNX"),
    "models": ("launch.models", "pack trained runs into a model folder; choose its pose strategy per part"),
    "eval": ("launch.eval", "evaluate the perception models on a generated dataset (mAP, ADD(-S), errors)"),
    "pick": ("launch.pick", "run the pick cycle on a cell file (simulated or hardware) and write its report"),
    "calibrate": (
        "launch.calibrate",
        "calibrate a cell's gripper (empty open/close) or its camera's pose (hand-eye, ChArUco on the flange)",
    ),
    "show": ("launch.show", "draw the labels of a few dataset items over their images (PNG)"),
    "convert": ("launch.convert", "convert SyGRID label pickles or YOLO-seg folders to BOP, COCO and YOLO"),
}


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The full parser; only ``command``'s module is imported, to add its own arguments."""
    parser = argparse.ArgumentParser(
        prog="sygrid", description="SyGRID picking stack: synthetic data from CAD, perception, and the UR5e cell."
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, (module_name, help_text) in SUBCOMMANDS.items():
        sub_parser = sub.add_parser(name, help=help_text, description=help_text)
        if name == command:
            module = importlib.import_module(module_name)
            module.add_arguments(sub_parser)
            sub_parser.set_defaults(_run=module.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    command = next((a for a in argv if a in SUBCOMMANDS), None)
    args = build_parser(command).parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO, format="%(levelname)s %(name)s: %(message)s"
    )
    try:
        return int(args._run(args) or 0)
    except SygridError as exc:
        print(f"sygrid {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:  # 130 for SIGINT, 143 for SIGTERM (launch.pick_stops.Interrupted)
        print(f"sygrid {args.command}: interrupted", file=sys.stderr)
        return 128 + getattr(exc, "signum", signal.SIGINT)


if __name__ == "__main__":
    sys.exit(main())
