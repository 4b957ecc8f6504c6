"""``sygrid drop SCENE.json --seed S --out poses.json``: steps 1-2 of the SyGRID method from the command line."""

from __future__ import annotations

import argparse
from pathlib import Path

from sygrid.drop import drop_scene, save_poses
from sygrid.physics import DropResult
from sygrid.scene import load_scene


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scene", type=Path, help="scene description (JSON)")
    parser.add_argument("--seed", type=int, default=0, help="seed: the same seed gives the same poses")
    parser.add_argument("--out", type=Path, default=None, help="poses file (default: SCENE.poses.json beside it)")


def run(args: argparse.Namespace) -> int:
    scene = load_scene(args.scene)
    result = drop_scene(scene, args.seed, base_dir=args.scene.parent)
    out = args.out or args.scene.with_suffix(".poses.json")
    save_poses(out, result, scene, args.seed)
    print_drop_summary(result)
    print(f"wrote {len(result.instances)} poses to {out}")
    return 0 if result.report.ok else 1


def print_drop_summary(result: DropResult) -> None:
    r = result.report
    names = [result.models[i.model_index].name for i in result.instances]
    for inst, name, T in zip(result.instances, names, result.T_world_obj, strict=True):
        x, y, z = T[:3, 3] * 1000
        print(f"  instance {inst.inst_id:3d}  {name:<10s}  x={x:7.1f} mm  y={y:7.1f} mm  z={z:6.1f} mm")
    print(
        f"{len(names)} instances, {'settled' if r.settled else 'NOT settled'} after {r.sim_time_s:.2f} s simulated "
        f"in {r.wall_time_s:.2f} s wall; penetration at rest {r.max_penetration_m * 1e3:.3f} mm; "
        f"escaped: {r.escaped or 'none'}"
    )
