"""``sygrid drop SCENE.json --seed S --out poses.json [--picture PNG]``: steps 1-2 of the SyGRID method from the
command line; ``--picture`` also shows the pile in the simulated cell's bin through its overhead camera. Exit codes:
``EXIT_CODES``."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

from sygrid.camera import project_points
from sygrid.drop import drop_scene, save_poses
from sygrid.fileio import write_bytes_atomic
from sygrid.physics import DropResult
from sygrid.scene import load_scene
from sygrid.transforms import invert, transform_points

#: ``sygrid drop``'s exit codes (its ``--help`` epilog says the same).
EXIT_CODES = (
    "exit codes: 0 the pile is within the scene's stability bounds (every part in the bin with a finite pose, settled "
    "within physics.max_time_s, penetration at rest at most physics.max_penetration_m); 1 it is not (the poses file "
    "is written all the same, and one line on stderr says which bounds failed); 2 bad input (the scene file, its "
    "parts) or a drop that could not be made."
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.epilog = EXIT_CODES
    parser.add_argument("scene", type=Path, help="scene description (JSON)")
    parser.add_argument("--seed", type=int, default=0, help="seed: the same seed gives the same poses")
    parser.add_argument("--out", type=Path, default=None, help="poses file (default: SCENE.poses.json beside it)")
    parser.add_argument("--picture", type=Path, default=None, help="PNG of the pile in the sim cell (RGB + depth)")


def run(args: argparse.Namespace) -> int:
    scene = load_scene(args.scene)
    result = drop_scene(scene, args.seed, base_dir=args.scene.parent)
    out = args.out or args.scene.with_suffix(".poses.json")
    save_poses(out, result, scene, args.seed)
    print_drop_summary(result)
    print(f"wrote {len(result.instances)} poses to {out}")
    if args.picture and result.report.ok:
        print(f"wrote {save_pile_picture(result, args.picture)}")
    if not result.report.within_bounds:
        print(f"sygrid drop: the pile is outside its stability bounds: {'; '.join(result.report.failures)}",
              file=sys.stderr)  # fmt: skip
        return 1
    return 0


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


def save_pile_picture(result: DropResult, path: Path) -> Path:
    """The pile in the sim cell's bin, seen by its overhead camera (MuJoCo, RGB and depth side by side)."""
    from sim.camera import SimCamera  # the simulated cell, only when a picture is asked for
    from sim.cell import Q_CLEAR_OF_CAMERA, add_pile
    from sim.world import CellWorld

    world = CellWorld()
    add_pile(world, result)
    world.reset_arm(np.array(Q_CLEAR_OF_CAMERA))
    with SimCamera(world) as camera:
        frame = camera.capture()
    rows, cols = _bin_window(world, frame.intrinsics.K)
    rgb, depth = frame.rgb[rows, cols], frame.depth_m[rows, cols]
    valid = depth > 0
    near, far = np.percentile(depth[valid], [1, 99]) if valid.any() else (0.0, 1.0)
    scaled = np.clip((depth - near) / max(far - near, 1e-6), 0, 1)
    depth_bgr = cv2.applyColorMap((255 * (1 - scaled)).astype(np.uint8), cv2.COLORMAP_VIRIDIS)
    picture = np.hstack([rgb[:, :, ::-1], depth_bgr])
    picture = cv2.resize(picture, None, fx=2, fy=2, interpolation=cv2.INTER_NEAREST)
    path.parent.mkdir(parents=True, exist_ok=True)
    ok, png = cv2.imencode(".png", picture)
    if not ok:
        raise OSError(f"{path}: PNG encoding failed")
    return write_bytes_atomic(path, png.tobytes())


def _bin_window(world, K: np.ndarray, margin_px: int = 8) -> tuple[slice, slice]:
    """Image rows and columns around the bin's rim, from the camera pose and intrinsics."""
    sx, sy, sz = (v / 2 for v in world.config.bin_inner_size_m)
    rim_bin = np.array([[x, y, 2 * sz] for x in (-sx, sx) for y in (-sy, sy)])
    T_camera_bin = invert(world.config.T_world_camera) @ world.T_world_bin
    uv = project_points(K, transform_points(T_camera_bin, rim_bin))
    (u0, v0), (u1, v1) = uv.min(0) - margin_px, uv.max(0) + margin_px
    h, w = world.config.camera_intrinsics.height, world.config.camera_intrinsics.width
    return slice(max(int(v0), 0), min(int(v1) + 1, h)), slice(max(int(u0), 0), min(int(u1) + 1, w))
