"""The `sygrid` command: drop writes a poses file and a picture of the pile; bad input exits 2."""

import json

import cv2
import pytest

from launch.cli import main
from sygrid.drop import load_poses


@pytest.fixture()
def small_scene(tmp_path, monkeypatch):
    monkeypatch.setenv("SYGRID_CACHE_DIR", str(tmp_path / "cache"))
    path = tmp_path / "small.json"
    path.write_text(json.dumps({"name": "small", "objects": [{"builtin": "hex_nut", "count": 4}]}))
    return path


def test_drop_writes_poses_and_a_picture_of_the_pile(small_scene, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["drop", str(small_scene), "--seed", "1", "--out", str(out / "small.poses.json"),
                 "--picture", str(out / "small.png")]) == 0  # fmt: skip
    poses = load_poses(tmp_path / "out" / "small.poses.json")
    assert len(poses.instances) == 4 and poses.seed == 1
    picture = cv2.imread(str(tmp_path / "out" / "small.png"))
    assert picture is not None and picture.shape[1] > picture.shape[0]  # RGB and depth side by side
    assert "wrote" in capsys.readouterr().out


def test_drop_command_and_its_errors(small_scene, tmp_path, capsys):
    out = tmp_path / "poses.json"
    assert main(["drop", str(small_scene), "--seed", "2", "--out", str(out)]) == 0
    assert load_poses(out).seed == 2
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"objects": [{"builtin": "hex_nutt"}]}))
    assert main(["drop", str(bad)]) == 2
    assert "unknown built-in part 'hex_nutt'" in capsys.readouterr().err
