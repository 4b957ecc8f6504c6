"""Annotations and the BOP / YOLO / COCO writers on a tiny synthetic item built in code.

The item: 64 x 48 image, instance 0 (obj 1) a wide rectangle behind, instance 1 (obj 2) a vertical bar in front
that cuts instance 0's visible mask in two.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh
from pycocotools.coco import COCO

from sygrid.annotations import (
    ImageAnnotation,
    annotate,
    mask_to_polygon,
    mask_to_polygons,
    merge_polygons,
    polygon_to_mask,
)
from sygrid.camera import CameraIntrinsics
from sygrid.errors import ConfigError
from sygrid.objects.model import ObjectModel
from sygrid.writers import WRITERS, BopWriter, CocoWriter, YoloWriter, create_writer, load_bop_item
from sygrid.writers.coco import rle_to_mask
from sygrid.writers.yolo import parse_label_line

W, H = 64, 48


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.count_nonzero(a & b) / np.count_nonzero(a | b))


def _models() -> list[ObjectModel]:
    return [
        ObjectModel(obj_id=2, name="bar", mesh=trimesh.creation.box((0.01, 0.04, 0.01))),
        ObjectModel(obj_id=1, name="plate", mesh=trimesh.creation.box((0.05, 0.02, 0.005))),
    ]


def _item(image_id: int = 0, scene_id: int = 0) -> tuple[ImageAnnotation, np.ndarray, np.ndarray]:
    full = np.zeros((2, H, W), dtype=bool)
    full[0, 10:30, 5:55] = True  # plate, behind
    full[1, 2:44, 25:33] = True  # bar, in front, crosses the plate
    ids = np.zeros((H, W), dtype=np.int32)
    ids[full[0]] = 1
    ids[full[1]] = 2
    depth = np.zeros((H, W), dtype=np.float32)
    depth[full[0]] = 0.61234
    depth[full[1]] = 0.5
    depth[0, 0] = 6.5  # near the uint16 range at 0.1 mm
    T = np.stack([np.eye(4), np.eye(4)])
    T[0, :3, 3] = [0.01, -0.02, 0.61234]
    T[1, :3, :3] = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    T[1, :3, 3] = [0.0, 0.0, 0.5]
    intr = CameraIntrinsics(80.0, 80.0, 31.5, 23.5, W, H)
    instances = annotate(ids, full, T, [1, 2], intr, depth_m=depth)
    rgb = np.random.default_rng(0).integers(0, 256, (H, W, 3), dtype=np.uint8)
    return ImageAnnotation(image_id, intr, tuple(instances), scene_id=scene_id), rgb, depth


def _no_tmp(root: Path) -> None:
    leftovers = [p for p in root.rglob("*") if p.name.endswith(".tmp")]
    assert leftovers == []


# ---------------------------------------------------------------------------------------------------- annotations
def test_annotate_counts_boxes_and_visibility():
    ann, _, _ = _item()
    plate, bar = ann.instances
    for inst in ann.instances:
        assert not np.any(inst.mask_visib & ~inst.mask_full)  # visible is a subset of full
    assert plate.px_count_all == 20 * 50 and plate.px_count_visib == 20 * 42
    assert plate.visib_fract == pytest.approx(42 / 50)
    assert plate.bbox_obj == (5, 10, 50, 20) and plate.bbox_visib == (5, 10, 50, 20)
    assert bar.px_count_all == bar.px_count_visib == 42 * 8 and bar.visib_fract == 1.0
    assert bar.bbox_visib == (25, 2, 8, 42)
    assert plate.px_count_valid == plate.px_count_all
    assert len(mask_to_polygons(plate.mask_visib)) == 2


def test_annotate_rejects_bad_input():
    ann, _, _ = _item()
    ids = np.zeros((H, W), dtype=np.int32)
    ids[0, 0] = 1
    with pytest.raises(ValueError, match="outside its full mask"):
        annotate(ids, np.zeros((1, H, W), bool), np.eye(4)[None], [1], ann.intrinsics)
    with pytest.raises(ValueError, match=r"T_camera_obj: expected shape \(2, 4, 4\)"):
        annotate(ids, None, np.eye(4)[None], [1, 2], ann.intrinsics)
    with pytest.raises(ValueError, match="ids_visib: expected shape"):
        annotate(ids[:10], None, np.eye(4)[None], [1], ann.intrinsics)


def test_split_mask_becomes_one_polygon():
    ann, _, _ = _item()
    mask = ann.instances[0].mask_visib
    pieces = mask_to_polygons(mask)
    merged = mask_to_polygon(mask)
    assert len(merged) == sum(len(p) for p in pieces) + 2  # each bridge adds its two ends once more
    assert _iou(polygon_to_mask(merged, H, W), mask) >= 0.9
    assert _iou(polygon_to_mask(pieces, H, W), mask) == 1.0
    assert merge_polygons([]).shape == (0, 2)


# ----------------------------------------------------------------------------------------------------------- BOP
def test_bop_round_trip(tmp_path):
    ann, rgb, depth = _item(image_id=3, scene_id=7)
    writer = BopWriter(tmp_path, _models())
    writer.write(ann, rgb, depth)
    writer.finish()
    sdir = tmp_path / "train_pbr" / "000007"
    for rel in ("rgb/000003.png", "depth/000003.png", "mask/000003_000001.png", "mask_visib/000003_000000.png"):
        assert (sdir / rel).is_file(), rel
    gt = json.loads((sdir / "scene_gt.json").read_text())["3"]
    assert gt[0]["cam_t_m2c"] == pytest.approx([10.0, -20.0, 612.34])  # millimetres in the file
    assert gt[1]["cam_R_m2c"] == pytest.approx([0, -1, 0, 1, 0, 0, 0, 0, 1])
    cam = json.loads((sdir / "scene_camera.json").read_text())["3"]
    assert cam["depth_scale"] == 0.1 and cam["cam_K"][0] == 80.0
    info = json.loads((sdir / "scene_gt_info.json").read_text())["3"]
    assert info[0]["bbox_obj"] == [5, 10, 50, 20] and info[0]["px_count_visib"] == 840
    models_info = json.loads((tmp_path / "models" / "models_info.json").read_text())
    assert models_info["1"]["size_x"] == pytest.approx(50.0)
    ply = trimesh.load(tmp_path / "models" / "obj_000002.ply")
    assert ply.extents == pytest.approx([10.0, 40.0, 10.0])

    back, rgb2, depth2 = load_bop_item(tmp_path, 7, 3)
    np.testing.assert_array_equal(rgb2, rgb)
    assert np.abs(depth2 - depth).max() <= 0.05e-3 + 1e-7  # half of depth_scale (0.1 mm)
    assert back.intrinsics == ann.intrinsics and back.depth_scale_mm == 0.1
    for a, b in zip(ann.instances, back.instances, strict=True):
        np.testing.assert_allclose(b.T_camera_obj, a.T_camera_obj, atol=1e-12)  # metres again
        np.testing.assert_array_equal(b.mask_visib, a.mask_visib)
        np.testing.assert_array_equal(b.mask_full, a.mask_full)
        assert (b.obj_id, b.bbox_visib, b.px_count_all, b.visib_fract) == (
            a.obj_id, a.bbox_visib, a.px_count_all, pytest.approx(a.visib_fract),
        )  # fmt: skip
    _no_tmp(tmp_path)


def test_bop_items_are_records_until_flushed_and_a_flush_merges_them(tmp_path):
    writer = BopWriter(tmp_path, _models())
    sdir = tmp_path / "train_pbr" / "000000"
    writer.write(*_item(image_id=0))
    writer.flush()
    first = (sdir / "scene_gt.json").read_bytes()
    for image_id in (1, 2, 1):  # image 1 written twice: the second replaces the first
        writer.write(*_item(image_id=image_id))
    # an item costs its own files only: the scene JSONs are not rewritten per item
    assert (sdir / "scene_gt.json").read_bytes() == first
    assert sorted(p.name for p in (sdir / "gt_items").iterdir()) == ["000001.json", "000002.json"]
    assert writer.instance_counts(0) == {0: 2, 1: 2, 2: 2}  # a resume sees records and scene entries alike
    assert writer.finish() == [sdir / f for f in ("scene_gt_info.json", "scene_camera.json", "scene_gt.json")]
    assert not (sdir / "gt_items").exists()
    for name in ("scene_gt.json", "scene_gt_info.json", "scene_camera.json"):
        assert list(json.loads((sdir / name).read_text())) == ["0", "1", "2"], name
    assert load_bop_item(tmp_path, 0, 2)[0].instances[1].obj_id == 2
    # a record left by a killed run that cannot be read is named, with what was expected
    (sdir / "gt_items").mkdir()
    (sdir / "gt_items" / "000005.json").write_text('{"scene_gt": []}')
    with pytest.raises(ConfigError, match=r"gt_items/000005.json: expected a BOP item record .*scene_camera"):
        writer.flush()
    assert list(json.loads((sdir / "scene_gt.json").read_text())) == ["0", "1", "2"]  # nothing merged, nothing lost


def test_bop_updates_scene_json_and_bad_item_leaves_it_intact(tmp_path):
    writer = BopWriter(tmp_path, _models())
    for image_id in (0, 1):
        writer.write(*_item(image_id=image_id))
    writer.flush()
    sdir = tmp_path / "train_pbr" / "000000"
    before = {f: (sdir / f).read_bytes() for f in ("scene_gt.json", "scene_camera.json", "scene_gt_info.json")}
    assert set(json.loads(before["scene_gt.json"])) == {"0", "1"}
    ann, rgb, depth = _item(image_id=2)
    with pytest.raises(ValueError, match=r"depth_m: values must be finite and in \[0, 6.553\] m"):
        writer.write(ann, rgb, depth * 2.0)
    with pytest.raises(ValueError, match=r"rgb: expected uint8 array of shape \(48, 64, 3\)"):
        writer.write(ann, rgb[:, :10], depth)
    assert {f: (sdir / f).read_bytes() for f in before} == before
    assert not (sdir / "rgb" / "000002.png").exists() and not (sdir / "gt_items").exists()
    _no_tmp(tmp_path)


# ---------------------------------------------------------------------------------------------------------- YOLO
def test_yolo_labels_rasterise_back_to_the_masks(tmp_path):
    ann, rgb, _ = _item()
    writer = YoloWriter(tmp_path, _models())
    writer.write(ann, rgb)
    writer.write(_item(image_id=1)[0], rgb, split="val")
    writer.finish()
    assert (tmp_path / "images" / "train" / "000000_000000.png").is_file()
    lines = (tmp_path / "labels" / "train" / "000000_000000.txt").read_text().splitlines()
    assert len(lines) == 2
    for line, inst in zip(lines, ann.instances, strict=True):
        cls, poly = parse_label_line(line, W, H)
        assert cls == sorted([1, 2]).index(inst.obj_id)
        assert _iou(polygon_to_mask(poly, H, W), inst.mask_visib) >= 0.9  # instance 0 is split in two
    yaml = (tmp_path / "data.yaml").read_text()
    assert "train: images/train\nval: images/val\nnames:\n" in yaml
    assert '  0: "plate"\n  1: "bar"\n' in yaml
    assert yaml.startswith("train: images/train\n") and "path:" not in yaml
    _no_tmp(tmp_path)


@pytest.mark.parametrize(("splits", "val"), [(("train",), "train"), (("train", "test"), "train"), (("test",), "test")])
def test_yolo_data_yaml_names_a_val_split_that_exists_and_never_trains_on_another(tmp_path, splits, val):
    """ultralytics needs train and val: val is the val split, else the train split, else (a test set alone) the
    test split, so that `yolo val` evaluates it; train always names images/train, which a test set does not have."""
    _, rgb, _ = _item()
    writer = YoloWriter(tmp_path, _models(), split=splits[0])
    for k, split in enumerate(splits):
        writer.write(_item(image_id=k)[0], rgb, split=split)
    writer.finish()
    yaml = (tmp_path / "data.yaml").read_text()
    assert yaml.startswith(f"train: images/train\nval: images/{val}\n")
    assert ("test: images/test\n" in yaml) == ("test" in splits)


# ---------------------------------------------------------------------------------------------------------- COCO
@pytest.mark.filterwarnings("ignore:__array__ implementation:DeprecationWarning")  # inside pycocotools, numpy 2
def test_coco_loads_in_pycocotools_and_decodes_exactly(tmp_path):
    writer = CocoWriter(tmp_path, _models())
    items = [_item(image_id=i) for i in range(2)]
    for ann, rgb, depth in items:
        writer.write(ann, rgb, depth)
    written = writer.finish()
    assert tmp_path / "annotations" / "instances_train.json" in written
    coco = COCO(str(tmp_path / "annotations" / "instances_train.json"))
    assert sorted(coco.getCatIds()) == [1, 2]
    assert len(coco.getImgIds()) == 2
    for img_id, (ann, _, _) in zip(sorted(coco.getImgIds()), items, strict=True):
        anns = coco.loadAnns(coco.getAnnIds(imgIds=[img_id]))
        assert len(anns) == 2
        for a, inst in zip(anns, ann.instances, strict=True):
            np.testing.assert_array_equal(coco.annToMask(a).astype(bool), inst.mask_visib)
            np.testing.assert_array_equal(rle_to_mask(a["segmentation"]), inst.mask_visib)
            assert a["area"] == inst.px_count_visib and a["bbox"] == list(inst.bbox_visib) and a["iscrowd"] == 0
    # a new writer on the same folder extends the set; writing an image again replaces it; ids are stable
    before = json.loads((tmp_path / "annotations" / "instances_train.json").read_text())
    again = CocoWriter(tmp_path, _models())
    again.write(*_item(image_id=5))
    again.write(*items[0])
    again.finish()
    after = json.loads((tmp_path / "annotations" / "instances_train.json").read_text())
    assert [im["id"] for im in after["images"]] == [1, 2, 6]
    assert after["images"][:2] == before["images"] and after["annotations"][:4] == before["annotations"]
    assert [a["id"] for a in after["annotations"]] == list(range(1, len(after["annotations"]) + 1))
    _no_tmp(tmp_path)


# ------------------------------------------------------------------------------------------------------ registry
def test_registry_and_errors(tmp_path):
    assert set(WRITERS) == {"bop", "yolo", "coco"}
    assert isinstance(create_writer("coco", tmp_path, _models()), CocoWriter)
    with pytest.raises(ValueError, match=r"unknown format, expected one of \['bop', 'coco', 'yolo'\]"):
        create_writer("voc", tmp_path, _models())
    with pytest.raises(ValueError, match="split: expected 'train', 'val' or 'test'"):
        YoloWriter(tmp_path, _models(), split="training")
    ann, rgb, depth = _item()
    with pytest.raises(ValueError, match=r"obj_id \[2\] not among the writer's models \[1\]"):
        BopWriter(tmp_path / "bop", _models()[1:]).write(ann, rgb, depth)
