"""``sygrid demo``: the main job on built-in defaults.

Until the picking cell lands, the most complete thing the stack does is the first half of the SyGRID method: drop
a bin of built-in parts and write their poses. The picking issue switches this command to the picking demo.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from launch.drop import print_drop_summary
from sygrid.drop import drop_scene, save_poses
from sygrid.scene import load_scene

DEFAULT_SCENE = Path(__file__).parent / "scenes" / "builtin_bin.json"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scene", type=Path, default=DEFAULT_SCENE, help="scene description (JSON)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out-dir", type=Path, default=Path("out/demo"))


def run(args: argparse.Namespace) -> int:
    scene = load_scene(args.scene)
    print(f"dropping the parts of {args.scene} (seed {args.seed}) ...")
    result = drop_scene(scene, args.seed, base_dir=args.scene.parent)
    print_drop_summary(result)
    out = save_poses(args.out_dir / f"{scene.name}.poses.json", result, scene, args.seed)
    print(f"wrote {out}")
    return 0 if result.report.ok else 1
