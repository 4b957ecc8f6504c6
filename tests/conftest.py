"""Shared fixtures: a tiny generated dataset (raster mode, so it takes a couple of seconds) for the tests of the
dataset command, the training smoke runs and the perception runtime."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

os.environ.setdefault("MUJOCO_GL", "egl")

TINY_SCENE = {
    "name": "tiny_bin",
    "objects": [
        {"builtin": "hex_nut", "count": 2},
        {"builtin": "washer", "count": 2},
        {"builtin": "l_bracket", "count": 2},
    ],
    "camera": {
        "width_px": 160,
        "height_px": 120,
        "fov_y_deg": 45.0,
        "pose_sampling": {"distance_m": [0.35, 0.45], "max_tilt_deg": 15.0},
    },
}


def tiny_recipe_json(**overrides: object) -> dict:
    """A recipe of the tiny bin, rendered with the rasteriser unless overridden."""
    return {
        "name": "tiny",
        "scene": TINY_SCENE,
        "split": "train",
        "val_fraction": 0.25,
        "raster_fraction": 1.0,
        **overrides,
    }


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """DIR of an 8-item dataset of the tiny bin (160x120, raster) in BOP, YOLO and COCO; read-only for tests."""
    from sygrid.dataset import generate
    from sygrid.recipe import parse_recipe

    out = tmp_path_factory.mktemp("tiny_dataset")
    recipe = parse_recipe(tiny_recipe_json(), "tiny recipe", out)
    summary = generate(recipe, out, count=8, seed=7, progress=False)
    assert not summary.failed, summary.failed
    return out
