"""The pixels-per-part warnings where a camera meets a model folder's detector (launch.part_check): a recipe's camera
(sygrid generate, sygrid eval) and a cell's calibrated camera and bin (sygrid pick)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np

from launch.part_check import cell_warnings, folder_detector, scene_warnings
from sygrid.camera import CameraIntrinsics
from sygrid.drop import resolve_objects
from sygrid.scene import load_scene

ROOT = Path(__file__).resolve().parents[1]


def _models(tmp_path: Path, min_part_px: float | None) -> Path:
    """The shipped folder with the detector at scale 1 and the given ``min_part_px`` (None: none)."""
    folder = tmp_path / "models"
    shutil.copytree(ROOT / "models" / "builtin", folder)
    manifest = json.loads((folder / "manifest.json").read_text())
    manifest["detector"].pop("min_part_px", None)
    manifest["detector"].pop("tile_px", None)
    manifest["detector"]["scale"] = 1.0
    if min_part_px is not None:
        manifest["detector"]["min_part_px"] = min_part_px
    (folder / "manifest.json").write_text(json.dumps(manifest))
    return folder


def test_recipe_and_cell_warnings_name_the_small_parts(tmp_path):
    scene_path = ROOT / "launch" / "scenes" / "builtin_bin.json"
    scene = load_scene(scene_path)
    folder = _models(tmp_path, 20.0)
    warnings = scene_warnings(scene, scene_path.parent, folder)
    # at 0.95 m, fx 579 px and scale 1.0: the nut (22.5 mm) spans 13.7 px, the flange (96 mm) 58.5 px
    assert any(w.startswith("hex_nut spans 13.7 network px") for w in warnings)
    assert not any(w.startswith("flange") for w in warnings)
    assert all("bring the camera within" in w and "scale >=" in w and "fx >=" in w for w in warnings)
    assert scene_warnings(scene, scene_path.parent, _models(tmp_path / "none", None)) == []
    assert scene_warnings(scene, scene_path.parent, tmp_path / "no_models") == []

    detector, min_px = folder_detector(folder)
    assert min_px == 20.0
    intrinsics = CameraIntrinsics.from_fov(640, 480, 45.0)
    floor = np.array([[-0.15, -0.1, 0.5], [0.15, -0.1, 0.5], [-0.15, 0.1, 0.5], [0.15, 0.1, 0.55]])
    models = resolve_objects(scene, scene_path.parent)
    near = cell_warnings(detector, folder, models, intrinsics, floor)
    far = cell_warnings(detector, folder, models, intrinsics, floor + np.array([0.0, 0.0, 0.5]))
    assert len(near) < len(far) and any("hex_nut" in w for w in far)
