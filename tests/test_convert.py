"""``sygrid convert`` (SyGRID pickle and YOLO-seg sources), the id map, training data without a BOP folder, and the
evaluation's and ``sygrid show``'s checks on a converted dataset.

The SyGRID fixture: two 64 x 48 images in the published layout, made here; image 0 holds obj 1 with a box 20 px
off its polygon (recomputed) and obj 3 with a box 1 px off (kept, within the 2 px tolerance); image 1 holds obj 3.
The YOLO-seg fixture: two classes that are not built-in parts, one image per split.
"""

from __future__ import annotations

import json
import pickle
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import trimesh

from launch.cli import main
from sygrid.convert import ConvertOptions, box_disagreement_px, convert_sygrid_pickle, convert_yolo_seg
from sygrid.errors import ConfigError, SygridError
from sygrid.id_map import class_obj_ids, load_id_map
from sygrid.objects.model import ObjectModel
from sygrid.train.detector.data import DetectorDataError, open_dataset
from sygrid.writers import BopWriter, load_bop_item

ROOT = Path(__file__).resolve().parents[1]
W, H = 64, 48
K = [80.0, 0.0, 31.5, 0.0, 80.0, 23.5, 0.0, 0.0, 1.0]


def _corners_mm(centre_mm, half_mm):
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=float)
    return (np.asarray(centre_mm) + signs * np.asarray(half_mm)).tolist()


def _obj(obj_id: int, square: tuple[int, int, int], bbox: list[int]) -> dict:
    x, y, side = square
    polygon = [[x, y], [x + side - 1, y], [x + side - 1, y + side - 1], [x, y + side - 1]]
    return {
        "obj_id": obj_id, "inst_id": 0, "R": np.eye(3).reshape(-1), "t": [0.0, 0.0, 600.0], "bbox": bbox,
        "3d-bbox": _corners_mm([0.0, 0.0, 600.0], [15.0, 15.0, 15.0]), "segmentation": [polygon], "mask_visib": 100,
    }  # fmt: skip


def _sygrid_source(root: Path, depth: str = "8bit", obj_ids: tuple[int, int] = (1, 3)) -> Path:
    """``root/gt.pickle`` + ``root/rgb/*.png`` (+ ``root/depth/*.png``: ``8bit``, ``16bit`` or ``none``)."""
    labels = {
        "000000.png": {
            "cam_K": K,
            "objects": [
                _obj(obj_ids[0], (10, 10, 10), [0, 0, 40, 30]),  # 20 px off its polygon's box (10, 10, 10, 10)
                _obj(obj_ids[1], (30, 20, 20), [31, 20, 20, 20]),  # 1 px off
            ],
        },
        "000001.png": {"cam_K": K, "objects": [_obj(obj_ids[1], (5, 5, 12), [5, 5, 12, 12])]},
    }
    (root / "rgb").mkdir(parents=True)
    rng = np.random.default_rng(0)
    for name in labels:
        cv2.imwrite(str(root / "rgb" / name), rng.integers(0, 256, (H, W, 3), dtype=np.uint8))
        if depth != "none":
            (root / "depth").mkdir(exist_ok=True)
            values = np.full((H, W), 6000, np.uint16) if depth == "16bit" else np.full((H, W), 128, np.uint8)
            cv2.imwrite(str(root / "depth" / name), values)
    path = root / "gt.pickle"
    path.write_bytes(pickle.dumps(labels, protocol=2))
    return path


def _bop_models(root: Path, obj_ids: tuple[int, ...]) -> Path:
    """A BOP models folder (cubes of 30 mm) for ``obj_ids``, written by the BOP writer."""
    models = [ObjectModel(obj_id=i, name=f"part{i}", mesh=trimesh.creation.box((0.03, 0.03, 0.03))) for i in obj_ids]
    BopWriter(root, models, split="test")
    return root / "models"


def _yolo_source(root: Path) -> Path:
    """A YOLO-seg folder: data.yaml naming 'clamp' and 'nozzle', one image in train and one in val."""
    rng = np.random.default_rng(1)
    for split, lines in (("train", ["0 0.1 0.1 0.5 0.1 0.5 0.5 0.1 0.5", "1 0.6 0.6 0.9 0.6 0.9 0.9"]),
                         ("val", ["1 0.2 0.2 0.7 0.2 0.7 0.8 0.2 0.8"])):  # fmt: skip
        (root / "images" / split).mkdir(parents=True)
        (root / "labels" / split).mkdir(parents=True)
        cv2.imwrite(str(root / "images" / split / "photo.jpg"), rng.integers(0, 256, (H, W, 3), dtype=np.uint8))
        (root / "labels" / split / "photo.txt").write_text("\n".join(lines) + "\n")
    (root / "data.yaml").write_text("train: images/train\nval: images/val\nnames: ['clamp', 'nozzle']\n")
    return root


@pytest.fixture(scope="module")
def converted(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The SyGRID fixture converted to BOP, COCO and YOLO (obj 1 and 3, 8-bit depth dropped); read-only."""
    tmp = tmp_path_factory.mktemp("converted")
    source = _sygrid_source(tmp / "src")
    options = ConvertOptions(bop_models=_bop_models(tmp / "models_src", (1, 3)))
    convert_sygrid_pickle(source, tmp / "out", options)
    return tmp / "out"


# ------------------------------------------------------------------------------------------------- the id map
def test_id_map_file_and_class_resolution(tmp_path):
    path = tmp_path / "ids.json"
    path.write_text(json.dumps({"clamp": 11, "1": 12}))
    id_map = load_id_map(path)
    assert class_obj_ids(["clamp", "nozzle"], "labels", id_map) == [11, 12]  # by name, then by index
    assert class_obj_ids(["hex_nut", "washer"], "labels") == [1, 3]  # built-in part names
    assert class_obj_ids(["clamp"], "labels", known={"clamp": 7}) == [7]
    assert class_obj_ids([None, None], "gt.pickle", {"3": 15}, own_ids=[1, 3]) == [1, 15]  # a pickle's own ids
    with pytest.raises(ConfigError, match=r"labels: no obj_id for classes 1 'nozzle' \(index and name\).*--id-map"):
        class_obj_ids(["hex_nut", "nozzle"], "labels")
    with pytest.raises(ConfigError, match="classes 0 and 1 both map to obj_id 11"):
        class_obj_ids(["clamp", "nozzle"], "labels", {"clamp": 11, "nozzle": 11})
    path.write_text(json.dumps({"clamp": "11"}))
    with pytest.raises(ConfigError, match=r"ids\.json\['clamp'\]: expected an integer obj_id >= 1"):
        load_id_map(path)


# ---------------------------------------------------------------------------------------------- SyGRID pickles
def test_pickle_converts_with_boxes_recomputed_and_8bit_depth_dropped(tmp_path, capsys):
    source = _sygrid_source(tmp_path / "src")
    models = _bop_models(tmp_path / "models_src", (1, 3))
    out = tmp_path / "out"
    assert main(["convert", str(source), "--out", str(out), "--bop-models", str(models)]) == 0
    printed = capsys.readouterr().out
    assert "boxes: 1 of 3 recomputed from their masks; worst disagreement 20 px" in printed
    assert "objects[0].bbox [0, 0, 40, 30], mask box [10, 10, 10, 10]" in printed
    assert "depth: 0 kept, 2 dropped (not metric)" in printed and "8-bit" in printed
    report = json.loads((out / "convert.json").read_text())
    assert report["boxes_recomputed"] == 1 and report["box_worst_px"] == 20.0
    assert [i["name"] for i in report["items"]] == ["000000_000000", "000000_000001"]
    assert sorted(p.name for p in out.iterdir()) == ["bop", "coco", "convert.json", "yolo"]
    assert not list(tmp_path.glob(".out.*"))  # the temporary folder was renamed into place

    ann, rgb, depth = load_bop_item(out / "bop", 0, 0, split="test")
    assert depth is None and rgb.shape == (H, W, 3)
    assert [i.obj_id for i in ann.instances] == [1, 3]
    assert ann.instances[0].bbox_visib == (10, 10, 10, 10)  # recomputed from the polygon
    assert ann.instances[1].bbox_visib == (31, 20, 20, 20)  # 1 px off: kept as stored
    np.testing.assert_allclose(ann.instances[0].T_camera_obj[:3, 3], [0.0, 0.0, 0.6])
    coco = json.loads((out / "coco" / "annotations" / "instances_test.json").read_text())
    assert [a["bbox"] for a in coco["annotations"][:2]] == [[10, 10, 10, 10], [31, 20, 20, 20]]
    assert (out / "yolo" / "labels" / "test" / "000000_000000.txt").read_text().count("\n") == 2


def test_metric_depth_is_kept_and_16bit_needs_a_scale(tmp_path):
    source = _sygrid_source(tmp_path / "src", depth="16bit")
    models = _bop_models(tmp_path / "models_src", (1, 3))
    with pytest.raises(ConfigError, match=r"depth/000000\.png: 16-bit depth needs its scale: pass --depth-scale-mm"):
        convert_sygrid_pickle(source, tmp_path / "out", ConvertOptions(bop_models=models))
    assert not (tmp_path / "out").exists() and not list(tmp_path.glob(".out.*"))  # nothing left behind
    report = convert_sygrid_pickle(source, tmp_path / "out", ConvertOptions(bop_models=models, depth_scale_mm=0.1))
    assert report.depth == {"kept": 2, "dropped_non_metric": 0, "missing": 0}
    ann, _, depth = load_bop_item(tmp_path / "out" / "bop", 0, 1, split="test")
    assert ann.depth_scale_mm == 0.1 and depth is not None and np.allclose(depth, 0.6)


def test_existing_output_is_refused_without_force(converted, tmp_path):
    source = _sygrid_source(tmp_path / "src", depth="none")
    out = tmp_path / "out"
    (out / "keep").mkdir(parents=True)
    options = ConvertOptions(formats=("coco", "yolo"))
    with pytest.raises(ConfigError, match=r"out: exists and is not empty; pass --force"):
        convert_sygrid_pickle(source, out, options)
    assert (out / "keep").is_dir()
    convert_sygrid_pickle(source, out, ConvertOptions(formats=("coco", "yolo"), force=True))
    assert sorted(p.name for p in out.iterdir()) == ["coco", "convert.json", "yolo"]
    with pytest.raises(ConfigError, match=r"bop format: the parts' meshes are needed.*--bop-models"):
        convert_sygrid_pickle(source, tmp_path / "other", ConvertOptions())
    bad = tmp_path / "bad"
    shutil.copytree(tmp_path / "src", bad)
    (bad / "rgb" / "000001.png").unlink()
    with pytest.raises(ConfigError, match=r"gt\.pickle\['000001\.png'\]: no image for this entry in .*rgb"):
        convert_sygrid_pickle(bad / "gt.pickle", tmp_path / "bad_out", options)
    assert not (tmp_path / "bad_out").exists()


def test_box_disagreement_is_the_largest_edge_difference():
    assert box_disagreement_px((10, 10, 10, 10), (10, 10, 10, 10)) == 0.0
    assert box_disagreement_px((0, 0, 40, 30), (10, 10, 10, 10)) == 20.0  # right edge 40 vs 20


# ------------------------------------------------------------------------------------------------ YOLO-seg folders
def test_yolo_seg_folder_needs_an_id_map_for_unknown_names(tmp_path):
    source = _yolo_source(tmp_path / "photos")
    with pytest.raises(ConfigError, match=r"data\.yaml: no obj_id for classes 0 'clamp', 1 'nozzle' "):
        convert_yolo_seg(source, tmp_path / "out", ConvertOptions(formats=("coco", "yolo")))
    with pytest.raises(ConfigError, match="no camera and no poses"):
        convert_yolo_seg(source, tmp_path / "out", ConvertOptions())
    id_map = {"clamp": 11, "1": 12}
    report = convert_yolo_seg(source, tmp_path / "out", ConvertOptions(formats=("coco", "yolo"), id_map=id_map))
    assert report.images == {"train": 1, "val": 1} and report.instances == 3 and report.boxes_checked == 0
    coco = json.loads((tmp_path / "out" / "coco" / "annotations" / "instances_train.json").read_text())
    assert coco["categories"] == [{"id": 11, "name": "clamp"}, {"id": 12, "name": "nozzle"}]
    assert [a["category_id"] for a in coco["annotations"]] == [11, 12]
    x, y, w, h = coco["annotations"][0]["bbox"]  # the polygon 0.1..0.5 of 64 x 48 px
    assert (x, y, x + w - 1, y + h - 1) == (6, 5, 32, 24)
    assert 'names:\n  0: "clamp"\n  1: "nozzle"' in (tmp_path / "out" / "yolo" / "data.yaml").read_text()

    flat = tmp_path / "flat"
    shutil.copytree(source / "images" / "train", flat / "images")
    shutil.copytree(source / "labels" / "train", flat / "labels")
    (flat / "labels" / "photo.txt").write_text("0 0.1 0.1 0.5 0.5\n")  # a box, not a polygon
    with pytest.raises(ConfigError, match=r"flat: no class names .*--names"):
        convert_yolo_seg(flat, tmp_path / "flat_out", ConvertOptions(formats=("coco",)))
    with pytest.raises(ConfigError, match=r"labels/photo\.txt:1: .*segmentation polygons expected, not boxes"):
        convert_yolo_seg(flat, tmp_path / "flat_out", ConvertOptions(formats=("coco",)), names=["hex_nut"])


# ----------------------------------------------------------------------------------- training without bop/
def test_training_data_takes_ids_from_coco_categories_or_the_id_map(tmp_path, tiny_dataset):
    source = _yolo_source(tmp_path / "photos")
    out = tmp_path / "out"
    convert_yolo_seg(source, out, ConvertOptions(formats=("coco", "yolo"), id_map={"clamp": 11, "nozzle": 12}))
    ds = open_dataset(out)  # no bop/: ids from the COCO categories, by name
    assert ds.names == ["clamp", "nozzle"] and ds.obj_ids == [11, 12] and ds.label_source == "coco"
    assert [a["category_id"] for a in ds.coco_gt["val"]["annotations"]] == [12]
    shutil.rmtree(out / "coco")
    with pytest.raises(DetectorDataError, match=r"no obj_id for classes .*--id-map"):
        open_dataset(out)
    ds = open_dataset(out, id_map={"clamp": 21, "1": 22})
    assert ds.obj_ids == [21, 22] and ds.label_source == "yolo"

    copy = tmp_path / "generated"  # a generated dataset written with only the yolo and coco formats
    shutil.copytree(tiny_dataset / "yolo", copy / "yolo")
    shutil.copytree(tiny_dataset / "coco", copy / "coco")
    ds = open_dataset(copy)
    assert ds.obj_ids == [1, 3, 4] and ds.label_source == "coco"


# ---------------------------------------------------------------------------------- eval and show on the result
def test_eval_refuses_models_without_the_datasets_parts(converted, tmp_path, capsys):
    from perception.evaluation import check_model_classes

    check_model_classes(converted, {1: "hex_nut", 2: "hex_bolt", 3: "washer"})  # more parts than the data: fine
    expected = r"parts \[3\]\. Dataset: \[1 obj_000001, 3 obj_000003\]; models: \[1 hex_nut, 2 hex_bolt\]"
    with pytest.raises(ConfigError, match=expected):
        check_model_classes(converted, {1: "hex_nut", 2: "hex_bolt"})
    mismatched = tmp_path / "mismatched"
    source = _sygrid_source(tmp_path / "src", depth="none", obj_ids=(1, 15))
    convert_sygrid_pickle(source, mismatched, ConvertOptions(bop_models=_bop_models(tmp_path / "m", (1, 15))))
    assert main(["eval", "--data", str(mismatched), "--models", str(ROOT / "models" / "builtin")]) == 2
    captured = capsys.readouterr()
    assert "do not know the dataset's parts [15]" in captured.err and "7 flange" in captured.err
    assert "warning" not in captured.out  # refused before anything else is said


@pytest.mark.filterwarnings("ignore:__array__ implementation:DeprecationWarning")
def test_eval_without_depth_reports_detection_only(converted):
    from perception.evaluation import EvalSettings, evaluate, format_table
    from perception.pipeline import PerceptionPipeline, PipelineOverrides

    pipeline = PerceptionPipeline.from_folder(ROOT / "models" / "builtin", PipelineOverrides(num_threads=1))
    report = evaluate(pipeline, converted, EvalSettings(), progress=False)
    assert report["split"] == "test" and report["n_images"] == 2
    assert report["pose"] is None and "no depth maps" in report["pose_skipped"] and report["depth"] is None
    assert set(report["timings_ms_median"]) == {"detect"} and "box_map50" in report["detection"]
    table = format_table(report)
    assert "pose skipped: the dataset has no depth maps" in table and "ADD(-S)" not in table
    with pytest.raises(ConfigError, match="no depth maps, so the sensor 'oak-d' cannot be simulated"):
        evaluate(pipeline, converted, EvalSettings(sensor="oak-d"), progress=False)


def test_show_picks_the_only_split(converted, tmp_path, capsys):
    out = tmp_path / "show.png"
    assert main(["show", str(converted), "--out", str(out)]) == 0
    assert "2 of 2 items of test" in capsys.readouterr().out and cv2.imread(str(out)) is not None
    two = tmp_path / "two"
    shutil.copytree(converted / "bop", two / "bop")
    shutil.copytree(converted / "bop" / "test", two / "bop" / "val_pbr")
    with pytest.raises(SygridError, match=r"splits \['test', 'val_pbr'\]; choose one with --split"):
        from launch.show import choose_split

        choose_split(two / "bop", None)
