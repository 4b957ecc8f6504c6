"""The bin's pose in generated datasets: written with each image (BOP cam_R_w2c / cam_t_w2c), read back, re-derived
for datasets written before (sygrid.dataset.DatasetBin), and the bin's image box the detector is given in eval."""

from __future__ import annotations

import dataclasses
import json

import numpy as np

from perception.detector_eval import bin_region_camera, region_box
from sygrid.dataset import DatasetBin, ledger_recipe
from sygrid.dataset_item import item_T_world_camera
from sygrid.transforms import invert, transform_points
from sygrid.writers import load_bop_item


def test_the_bin_pose_is_written_read_back_and_re_derived(tiny_dataset):
    recipe, seed = ledger_recipe(tiny_dataset)
    dataset_bin = DatasetBin(tiny_dataset)
    assert dataset_bin.inner_size_m == tuple(recipe.scene.container.inner_size_m)
    scene = json.loads((tiny_dataset / "bop" / "train_pbr" / "000000" / "scene_camera.json").read_text())
    some = next(iter(scene.values()))
    assert len(some["cam_R_w2c"]) == 9 and len(some["cam_t_w2c"]) == 3
    for split in ("train_pbr", "val_pbr"):
        for key in json.loads((tiny_dataset / "bop" / split / "000000" / "scene_gt.json").read_text()):
            ann, _, _ = load_bop_item(tiny_dataset / "bop", 0, int(key), split=split)
            assert ann.T_camera_world is not None
            # the stored pose is the one the generator drew, drawn again without rendering
            np.testing.assert_allclose(invert(item_T_world_camera(recipe, seed, int(key))), ann.T_camera_world,
                                       atol=1e-6)  # fmt: skip
            older = dataclasses.replace(ann, T_camera_world=None)  # a dataset written before the pose was stored
            np.testing.assert_allclose(dataset_bin.T_camera_bin(older), ann.T_camera_world, atol=1e-6)
            # every part lies in the bin's inner volume (small tolerances: parts lean on the walls)
            hx, hy, hz = dataset_bin.inner_size_m
            for inst in ann.instances:
                p = transform_points(invert(ann.T_camera_world), inst.T_camera_obj[None, :3, 3])[0]
                assert abs(p[0]) < hx / 2 + 0.01 and abs(p[1]) < hy / 2 + 0.01 and -0.001 < p[2] < hz
            # the bin's image box holds every visible part
            x0, y0, x1, y1 = region_box("bin", dataset_bin, ann)
            for inst in ann.instances:
                if inst.px_count_visib:
                    bx, by, bw, bh = inst.bbox_visib
                    assert x0 <= bx and y0 <= by and bx + bw <= x1 and by + bh <= y1
            assert region_box("full", None, ann) is None
            assert bin_region_camera(dataset_bin, ann).shape == (8, 3)


def test_an_older_ledger_still_gives_the_recipe(tiny_dataset, tmp_path):
    ledger = json.loads((tiny_dataset / "dataset.json").read_text())
    ledger["recipe"]["depth_noise"] = False  # written before the sensor models
    ledger["recipe"]["scene"]["render"]["depth_noise"] = False
    (tmp_path / "dataset.json").write_text(json.dumps(ledger))
    recipe, seed = ledger_recipe(tmp_path)
    assert seed == ledger["seed"] and recipe.scene.camera == ledger_recipe(tiny_dataset)[0].scene.camera
