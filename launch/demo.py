"""``sygrid demo``: the main job on built-in defaults.

Until the picking cell lands, the most complete thing the stack does is the first half of the SyGRID method: drop
a bin of built-in parts, write their poses, and show the pile in the simulated cell's bin through its overhead
camera. The picking issue switches this command to the picking demo.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

from launch.drop import print_drop_summary
from sim.camera import SimCamera
from sim.cell import Q_CLEAR_OF_CAMERA, add_pile
from sim.world import CellWorld
from sygrid.camera import project_points
from sygrid.drop import drop_scene, save_poses
from sygrid.fileio import write_bytes_atomic
from sygrid.physics import DropResult
from sygrid.scene import load_scene
from sygrid.transforms import invert, transform_points

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
    if result.report.ok:
        print(f"wrote {save_pile_picture(result, args.out_dir / f'{scene.name}.png')}")
    return 0 if result.report.ok else 1


def save_pile_picture(result: DropResult, path: Path) -> Path:
    """The pile in the sim cell's bin, seen by its overhead camera (MuJoCo, RGB and depth side by side)."""
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


def _bin_window(world: CellWorld, K: np.ndarray, margin_px: int = 8) -> tuple[slice, slice]:
    """Image rows and columns around the bin's rim, from the camera pose and intrinsics."""
    sx, sy, sz = (v / 2 for v in world.config.bin_inner_size_m)
    rim_bin = np.array([[x, y, 2 * sz] for x in (-sx, sx) for y in (-sy, sy)])
    T_camera_bin = invert(world.config.T_world_camera) @ world.T_world_bin
    uv = project_points(K, transform_points(T_camera_bin, rim_bin))
    (u0, v0), (u1, v1) = uv.min(0) - margin_px, uv.max(0) + margin_px
    h, w = world.config.camera_intrinsics.height, world.config.camera_intrinsics.width
    return slice(max(int(v0), 0), min(int(v1) + 1, h)), slice(max(int(u0), 0), min(int(u1) + 1, w))
