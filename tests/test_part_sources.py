"""One source of part ids and names: the catalogue, as a model folder's manifest, training, evaluation, conversion
and a cell file read it, and the foreign example (launch/examples/foreign) that the walkthrough uses."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import pytest
import trimesh

from launch.part_check import check_scene_parts
from perception.evaluation import check_model_classes
from perception.manifest import check_detector_parts, load_manifest, manifest_models
from sygrid.catalogue import copy_catalogue, load_catalogue, parse_catalogue
from sygrid.errors import ConfigError
from sygrid.objects.model import ObjectModel
from sygrid.train.detector.data import DetectorDataError, catalogue_class_ids

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "launch" / "examples" / "foreign"
FOREIGN = ROOT / "tests" / "fixtures" / "foreign_parts"
CATALOGUE = {"part": [{"id": 21, "name": "nut", "builtin": "hex_nut"}, {"id": 22, "name": "ring", "builtin": "washer"}]}


def _part(obj_id: int, name: str) -> ObjectModel:
    return ObjectModel(obj_id=obj_id, name=name, mesh=trimesh.creation.box((0.01, 0.01, 0.01)))


def _model_folder(folder: Path, manifest: dict) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    for name in ("detector.onnx", "pose.onnx"):
        (folder / name).write_bytes(b"")
    (folder / "manifest.json").write_text(json.dumps(manifest))
    return folder


def _manifest(**extra: object) -> dict:
    return {"format": "sygrid-models/1", "detector": {"onnx": "detector.onnx"}, "pose": {"onnx": "pose.onnx"}, **extra}


def test_a_manifest_names_its_catalogues_parts(tmp_path: Path) -> None:
    (tmp_path / "models" / "parts").mkdir(parents=True)
    (tmp_path / "models" / "parts" / "parts.json").write_text(json.dumps(CATALOGUE))
    objects = [{"catalogue_part": "ring"}, {"builtin": "l_bracket"}]
    folder = _model_folder(tmp_path / "models", _manifest(catalogue="parts/parts.json", objects=objects))
    models = manifest_models(folder, load_manifest(folder))  # the catalogue relative to the folder
    assert {i: m.name for i, m in models.items()} == {22: "ring", 4: "l_bracket"}

    _model_folder(folder, _manifest(objects=objects))
    with pytest.raises(ConfigError, match=r"manifest.json: .*objects\[0\] name\(s\) a 'catalogue_part': give the"):
        load_manifest(folder)
    _model_folder(folder, _manifest(catalogue="parts/parts.json", objects=[{"catalogue_part": "bolt"}]))
    with pytest.raises(ConfigError, match=r"manifest.json: objects\[0\]: .*no part named 'bolt'; its parts: nut, ring"):
        manifest_models(folder, load_manifest(folder))
    _model_folder(folder, _manifest(catalogue="nowhere.toml", objects=objects))
    with pytest.raises(ConfigError, match=r"manifest.json: catalogue: .*nowhere.toml"):
        manifest_models(folder, load_manifest(folder))


def test_the_detector_and_the_manifest_agree_on_each_id() -> None:
    models = {21: _part(21, "nut"), 22: _part(22, "ring")}
    check_detector_parts(SimpleNamespace(class_obj_ids=[21, 7], class_names=["nut", "other"]), models, "d.onnx")
    detector = SimpleNamespace(class_obj_ids=[21, 22], class_names=["nut", "washer"])
    with pytest.raises(ConfigError, match=r"d.onnx: .*class 1 'washer' is obj_id 22, which the manifest's objects"):
        check_detector_parts(detector, models, "d.onnx")


def test_eval_compares_the_parts_by_id_and_name(tmp_path: Path) -> None:
    (tmp_path / "bop" / "models").mkdir(parents=True)
    (tmp_path / "bop" / "test").mkdir()
    (tmp_path / "bop" / "models" / "models_info.json").write_text(json.dumps({"21": {}, "22": {}}))
    (tmp_path / "yolo").mkdir()
    (tmp_path / "yolo" / "data.yaml").write_text('train: images/train\nnames:\n  0: "nut"\n  1: "ring"\n')
    check_model_classes(tmp_path, {21: "nut", 22: "ring", 4: "l_bracket"})
    with pytest.raises(ConfigError, match=r"name the dataset's parts \[22\] differently\. Dataset: \[21 nut, 22 ring"):
        check_model_classes(tmp_path, {21: "nut", 22: "washer"})


def test_training_takes_the_catalogues_ids_and_checks_the_datasets(tmp_path: Path) -> None:
    catalogue = parse_catalogue(CATALOGUE, "parts.json", tmp_path)
    yaml_path = tmp_path / "yolo" / "data.yaml"
    assert catalogue_class_ids(["nut", "ring"], catalogue, yaml_path) == [21, 22]
    with pytest.raises(DetectorDataError, match=r"classes \['bolt'\] are not parts of the catalogue parts.json"):
        catalogue_class_ids(["nut", "bolt"], catalogue, yaml_path)
    (tmp_path / "bop" / "models").mkdir(parents=True)
    (tmp_path / "bop" / "models" / "models_info.json").write_text(json.dumps({"1": {}, "3": {}}))
    with pytest.raises(DetectorDataError, match=r"obj_ids \[1, 3\] .* catalogue parts.json's ids .* \[21, 22\]"):
        catalogue_class_ids(["nut", "ring"], catalogue, yaml_path, tmp_path)


def test_pose_training_takes_the_catalogues_parts_of_the_datasets_ids(tmp_path: Path) -> None:
    from sygrid.train.pose.objects import catalogue_models

    catalogue = load_catalogue(EXAMPLE / "parts.toml")
    clamp = catalogue.model("strap_clamp")
    info = {"16": {"diameter": clamp.diameter_m * 1000.0}, "15": {"diameter": 1.0}}
    (tmp_path / "models_info.json").write_text(json.dumps(info))
    models = catalogue_models(catalogue, tmp_path, [16])
    assert models[16].name == "strap_clamp"
    with pytest.raises(ConfigError, match=r"models_info.json\[15\]: diameter 1.00 mm, .*'spacer_block'"):
        catalogue_models(catalogue, tmp_path)
    with pytest.raises(ConfigError, match=r"obj_ids \[3\] are not in both the dataset"):
        catalogue_models(catalogue, tmp_path, [3])


def test_a_copied_catalogue_moves_with_its_folder(tmp_path: Path) -> None:
    catalogue = load_catalogue(EXAMPLE / "parts.toml")
    path = copy_catalogue(catalogue, ["strap_clamp", "spacer_block"], tmp_path / "models" / "catalogue", header="h")
    moved = tmp_path / "elsewhere"
    (tmp_path / "models").rename(moved)
    copy = load_catalogue(moved / "catalogue" / path.name)
    assert [(p.id, p.name, p.file) for p in copy.parts] == [(16, "strap_clamp", "strap_clamp.stl"),
                                                           (15, "spacer_block", "spacer_block.stl")]  # fmt: skip
    assert copy.part("strap_clamp").mass_kg == 0.012
    assert copy.model("spacer_block").extents_m == pytest.approx(catalogue.model("spacer_block").extents_m)


def test_a_cells_scene_must_hold_its_models_parts() -> None:
    models = {21: _part(21, "nut"), 22: _part(22, "ring")}
    check_scene_parts([_part(22, "ring")], models, "cell.toml")
    with pytest.raises(ConfigError, match=r"cell.toml: the scene's parts \[3, 22\] .*Scene: 3 washer, 22 washer;"):
        check_scene_parts([_part(22, "washer"), _part(3, "washer")], models, "cell.toml")


def test_convert_takes_ids_names_and_meshes_from_the_catalogue(tmp_path: Path) -> None:
    import cv2
    import numpy as np

    from sygrid.convert import ConvertOptions, convert_yolo_seg

    source = tmp_path / "photos"
    (source / "images" / "val").mkdir(parents=True)
    (source / "labels" / "val").mkdir(parents=True)
    cv2.imwrite(str(source / "images" / "val" / "a.png"), np.zeros((48, 64, 3), np.uint8))
    (source / "labels" / "val" / "a.txt").write_text("0 0.1 0.1 0.5 0.1 0.5 0.5\n1 0.6 0.6 0.9 0.6 0.9 0.9\n")
    (source / "data.yaml").write_text("val: images/val\nnames: ['strap_clamp', 'nozzle']\n")
    options = ConvertOptions(formats=("coco",), catalogue=load_catalogue(EXAMPLE / "parts.toml"))
    convert_yolo_seg(source, tmp_path / "out", options)
    coco = json.loads((tmp_path / "out" / "coco" / "annotations" / "instances_val.json").read_text())
    assert coco["categories"] == [{"id": 13, "name": "nozzle"}, {"id": 16, "name": "strap_clamp"}]


def test_the_foreign_example_files_share_one_catalogue() -> None:
    from launch.pick import scene_models
    from robot.cell_setup import load_cell_setup
    from sygrid.drop import resolve_objects
    from sygrid.recipe import load_recipe

    catalogue = load_catalogue(EXAMPLE / "parts.toml")
    assert {p.id: p.name for p in catalogue.parts} == {
        11: "bolt_nut_pair", 12: "duct_cover", 13: "nozzle", 14: "plate_bracket", 15: "spacer_block", 16: "strap_clamp"
    }  # fmt: skip
    assert sorted(f.name for f in FOREIGN.glob("*.stl")) == sorted(Path(p.file).name for p in catalogue.parts)
    for name in ("train.json", "test.json"):
        recipe = load_recipe(EXAMPLE / name)
        models = resolve_objects(recipe.scene, recipe.base_dir)
        assert [(m.obj_id, m.name) for m in models] == [(p.id, p.name) for p in catalogue.parts]
    setup = load_cell_setup(EXAMPLE / "cell.toml")
    assert setup.resolve(setup.data.sim.scene) == EXAMPLE / "scene.json"
    assert setup.resolve(setup.data.perception.models_dir).resolve() == ROOT / "models" / "foreign"
    assert [(m.obj_id, m.name) for m in scene_models(setup)] == [(p.id, p.name) for p in catalogue.parts]
