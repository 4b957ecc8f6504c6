"""The walkthrough, by commands alone, on the foreign CAD set (tests/fixtures/foreign_parts: mm, open and
multi-component meshes) at tiny sizes: a folder of CAD -> ``sygrid parts --write-catalogue`` -> the catalogue edited
-> a scene and recipes naming its parts -> ``sygrid generate`` -> ``sygrid train detector`` / ``pose`` with the
catalogue -> ``sygrid models pack`` (the catalogue copied into the model folder) -> ``sygrid eval`` -> a cell file
(launch/examples/foreign/cell.toml, pointed at this model folder and scene) -> ``sygrid pick --dry-run``."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from launch.cli import main
from sygrid.catalogue import load_catalogue

ROOT = Path(__file__).resolve().parents[1]
FOREIGN = ROOT / "tests" / "fixtures" / "foreign_parts"
EXAMPLE = ROOT / "launch" / "examples" / "foreign"

pytestmark = [pytest.mark.slow, pytest.mark.filterwarnings("ignore:__array__ implementation:DeprecationWarning")]

SCENE = {
    "name": "foreign_tiny",
    "catalogue": "parts.toml",
    "objects": [
        {"catalogue_part": "strap_clamp", "count": 2},
        {"catalogue_part": "spacer_block", "count": 1},
        {"catalogue_part": "bolt_nut_pair", "count": 1},
    ],
    "camera": {"width_px": 160, "height_px": 120, "fov_y_deg": 45.0,
               "pose_sampling": {"distance_m": [0.35, 0.45], "max_tilt_deg": 15.0}},
}  # fmt: skip


def _run(*argv: str) -> None:
    assert main(list(argv)) == 0, argv


def test_own_parts_from_a_cad_folder_to_a_cell_by_commands(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    pytest.importorskip("torch")
    parts = tmp_path / "parts.toml"
    _run("parts", str(FOREIGN), "--unit", "mm", "--write-catalogue", str(parts))
    written = load_catalogue(parts)
    assert [(p.id, p.name) for p in written.parts][-1] == (6, "strap_clamp")
    assert written.part("nozzle").symmetries_continuous  # proposed from the mesh
    # the user's edit: ids from 11 (the walkthrough's example catalogue, launch/examples/foreign/parts.toml)
    parts.write_text(re.sub(r"(?m)^id = (\d+)$", lambda m: f"id = {int(m.group(1)) + 10}", parts.read_text()))

    (tmp_path / "scene.json").write_text(json.dumps(SCENE))
    for name, split in (("train", {"split": "train", "val_fraction": 0.5}), ("test", {"split": "test"})):
        recipe = {"name": f"foreign_{name}", "scene": "scene.json", "raster_fraction": 1.0, **split}
        (tmp_path / f"{name}.json").write_text(json.dumps(recipe))
    data = tmp_path / "datasets"
    _run("generate", str(tmp_path / "train.json"), "--out", str(data / "train"), "--count", "4", "--no-progress")
    _run("generate", str(tmp_path / "test.json"), "--out", str(data / "test"), "--count", "2", "--seed", "1",
         "--no-progress")  # fmt: skip
    assert '2: "strap_clamp"' in (data / "train" / "yolo" / "data.yaml").read_text()

    runs = tmp_path / "runs"
    _run("train", "detector", "--data", str(data / "train"), "--out", str(runs / "detector"), "--catalogue",
         str(parts), "--imgsz", "160", "--train-size", "160", "--batch", "2", "--epochs", "1", "--max-iters", "2",
         "--width", "f", "--threads", "1", "--no-progress")  # fmt: skip
    log = json.loads((runs / "detector" / "train_log.json").read_text())
    assert log["dataset"]["obj_ids"] == [11, 15, 16] and log["config"]["catalogue"] == str(parts.resolve())
    _run("train", "pose", "--data", str(data / "train"), "--out", str(runs / "pose"), "--catalogue", str(parts),
         "--epochs", "1", "--max-iters", "2", "--batch", "4", "--input-size", "32", "--output-stride", "4",
         "--width", "8", "--val-max", "4", "--threads", "1", "--no-progress")  # fmt: skip

    models = tmp_path / "models" / "foreign"
    _run("models", "pack", "--detector", str(runs / "detector"), "--pose", str(runs / "pose"), "--out", str(models),
         "--conf-threshold", "0.01", "--test-data", str(data / "test"), "--max-images", "2")  # fmt: skip
    manifest = json.loads((models / "manifest.json").read_text())
    assert manifest["catalogue"] == "catalogue/parts.toml"
    assert manifest["objects"] == [{"catalogue_part": n} for n in ("bolt_nut_pair", "spacer_block", "strap_clamp")]
    assert sorted(p.name for p in (models / "catalogue").iterdir()) == [
        "bolt_nut_pair.stl", "parts.toml", "spacer_block.stl", "strap_clamp.stl"
    ]  # fmt: skip

    _run("eval", "--data", str(data / "test"), "--models", str(models), "--max-images", "2", "--out",
         str(tmp_path / "eval.json"))  # fmt: skip
    report = json.loads((tmp_path / "eval.json").read_text())
    assert report["n_images"] == 2 and set(report["pose"]["per_object"]) == {
        "11 bolt_nut_pair", "15 spacer_block", "16 strap_clamp"
    }  # fmt: skip

    cell = (EXAMPLE / "cell.toml").read_text()
    cell = re.sub(r'(?m)^models_dir = ".*"', f'models_dir = "{models}"', cell)
    (tmp_path / "cell.toml").write_text(re.sub(r'(?m)^scene = ".*"', 'scene = "scene.json"', cell))
    capsys.readouterr()
    _run("pick", "--config", str(tmp_path / "cell.toml"), "--dry-run")
    out = capsys.readouterr().out
    assert "parts 11 bolt_nut_pair, 15 spacer_block, 16 strap_clamp" in out and "nothing was started" in out
    (tmp_path / "cell_all.toml").write_text(re.sub(r'(?m)^scene = ".*"', f'scene = "{EXAMPLE / "scene.json"}"', cell))
    assert main(["pick", "--config", str(tmp_path / "cell_all.toml"), "--dry-run"]) == 2  # parts 12-14 unknown
    assert "the scene's parts [12, 13, 14] are not the model folder's" in capsys.readouterr().err
