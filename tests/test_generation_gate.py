"""The generator's quality gate (sygrid.dataset_item): unsettled, penetrating, non-finite and empty items are drawn
again and, when no attempt passes, recorded as failed and never written; redraws are deterministic; each written
item's record keeps its stability figures; a resumed run notices a deleted file; `sygrid drop`'s exit codes."""

from __future__ import annotations

import dataclasses
import json
import logging
import re
from pathlib import Path

import numpy as np
import pytest

from launch.cli import main
from sygrid import dataset_item
from sygrid.dataset import generate, load_records
from sygrid.dataset_item import GateError, make_attempt, make_item
from sygrid.errors import ConfigError
from sygrid.recipe import Recipe, parse_recipe
from tests.conftest import TINY_SCENE, tiny_recipe_json

pytestmark = pytest.mark.filterwarnings("ignore:__array__ implementation:DeprecationWarning")  # pycocotools

UP = (1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0.6, 0, 0, 0, 1)  # above the bin, looking up: sees nothing of it


def _recipe(tmp_path: Path, scene: dict | None = None, **overrides: object) -> Recipe:
    data = tiny_recipe_json(**overrides)
    if scene is not None:
        data["scene"] = scene
    return parse_recipe(data, "tiny recipe", tmp_path)


def _with_camera_pose(recipe: Recipe, T: tuple[float, ...]) -> Recipe:
    """The recipe with a fixed camera pose that validation would refuse: what reaches the generator when a scene is
    built in code past the checks."""
    camera = recipe.scene.camera.model_copy(update={"T_world_camera": T})
    return Recipe(recipe.spec, recipe.scene.model_copy(update={"camera": camera}), recipe.base_dir)


def _tree(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def _files(root: Path) -> list[str]:
    return [k for k in _tree(root) if k != "dataset.json" and not k.startswith("bop/models/")]


# ------------------------------------------------------------------------------------------------- the recipe
def test_the_gate_settings_are_validated(tmp_path):
    recipe = _recipe(tmp_path)
    assert (recipe.spec.max_redraws, recipe.spec.min_visible_instances) == (5, 1)
    for field, value, message in [
        ("max_redraws", True, r"max_redraws: must be an integer, got true"),
        ("max_redraws", -1, r"max_redraws: must be >= 0, got -1"),
        ("min_visible_instances", 1.5, r"min_visible_instances: must be an integer, got 1\.5"),
        ("val_fraction", float("nan"), r"val_fraction: must be a finite number, got NaN"),
        ("full_masks", 1, r"full_masks: must be true or false, got 1"),
    ]:
        with pytest.raises(ConfigError, match=r"^r\.json: " + message):
            parse_recipe(tiny_recipe_json(**{field: value}), "r.json", tmp_path)


# ------------------------------------------------------------------------------------------------ the refusals
@pytest.mark.parametrize(
    ("physics", "reason"),
    [
        ({"max_time_s": 0.05}, r"the pile did not settle within 0\.05 s of simulated time"),
        ({"max_penetration_m": 1e-9}, r"penetration at rest \d+\.\d\d mm is above the bound 0\.00 mm"),
    ],
)
def test_a_pile_outside_its_bounds_is_redrawn_then_failed_never_written(tmp_path, caplog, physics, reason):
    scene = {**TINY_SCENE, "physics": physics}
    recipe = _recipe(tmp_path, scene, max_redraws=1)
    with caplog.at_level(logging.INFO, logger="sygrid.dataset_item"):
        summary = generate(recipe, tmp_path / "d", count=1, seed=4, progress=False)
    assert summary.written == 0
    assert list(summary.failed) == [0]
    assert summary.failed[0].startswith("GateError: item 0: none of 2 attempts passed the quality gate")
    assert len(re.findall(reason, summary.failed[0])) == 2  # both attempts, each with its reason
    assert re.search(r"item 0: attempt 0 failed the quality gate \(" + reason, caplog.text)
    ledger = json.loads((tmp_path / "d" / "dataset.json").read_text())
    assert ledger["done"] == [] and ledger["failed"]["0"] == summary.failed[0]
    assert [f for f in _files(tmp_path / "d") if not f.endswith("data.yaml")] == []  # nothing of the item written
    assert load_records(tmp_path / "d") == {}


def test_a_non_finite_camera_pose_never_reaches_the_files(tmp_path):
    """The issue's camera with NaN in its pose wrote NaN tokens into scene_gt.json: refused at load now, and the gate
    refuses it if one gets past the checks."""
    nan_pose = (float("nan"), *UP[1:])
    with pytest.raises(ConfigError, match=r"camera\.T_world_camera\[0\]: must be a finite number"):
        parse_recipe({**tiny_recipe_json(), "scene": {**TINY_SCENE, "camera": {"T_world_camera": nan_pose}}}, "r",
                     tmp_path)  # fmt: skip
    recipe = _with_camera_pose(_recipe(tmp_path, max_redraws=0), nan_pose)
    with pytest.raises(GateError, match=r"item 3: none of 1 attempts .*attempt 0: the camera pose is not finite"):
        make_item(recipe, seed=1, index=3)
    summary = generate(recipe, tmp_path / "d", count=1, seed=1, progress=False)
    assert "the camera pose is not finite" in summary.failed[0]
    assert [f for f in _files(tmp_path / "d") if not f.endswith("data.yaml")] == []  # no scene_gt.json, no labels


def test_an_item_without_a_visible_instance_is_refused_unless_allowed(tmp_path):
    recipe = _with_camera_pose(_recipe(tmp_path, max_redraws=1), UP)  # looks away; validation would refuse it
    with pytest.raises(GateError, match=r"attempt 1: 0 of \d+ instances visible, fewer than min_visible_instances 1"):
        make_item(recipe, seed=2, index=0)
    allowed = _with_camera_pose(_recipe(tmp_path, min_visible_instances=0), UP)
    item = make_item(allowed, seed=2, index=0)
    assert item.record["visible_instances"] == 0 and item.record["redraws"] == []
    crowded = _recipe(tmp_path, min_visible_instances=7, max_redraws=0)  # the tiny bin holds 6 parts
    with pytest.raises(GateError, match=r"of 6 instances visible, fewer than min_visible_instances 7"):
        make_item(crowded, seed=2, index=0)


# ------------------------------------------------------------------------------------ deterministic redraws
def test_redraws_are_deterministic_and_recorded(tmp_path, monkeypatch, caplog):
    """The first attempts of items 0 and 2 are made to fail (their drops reported unsettled): those items are written
    from attempt 1, exactly as ``make_attempt(.., 1)`` makes it, the same on every run; the records keep the
    redraws and the stability figures; the run's summary counts them."""
    seed = 9
    recipe = _recipe(tmp_path)
    first_seeds = {
        int(np.random.default_rng(dataset_item._attempt_streams(seed, i, 0)[0]).integers(0, 2**31 - 1)) for i in (0, 2)
    }
    real_drop = dataset_item.drop_scene

    def drop(scene, drop_seed, base_dir, clutter=()):
        result = real_drop(scene, drop_seed, base_dir, clutter)
        if drop_seed in first_seeds:
            result.report = dataclasses.replace(result.report, settled=False)
        return result

    monkeypatch.setattr(dataset_item, "drop_scene", drop)
    with caplog.at_level(logging.INFO, logger="sygrid.dataset_item"):
        one = generate(recipe, tmp_path / "one", count=3, seed=seed, progress=False)
    generate(recipe, tmp_path / "two", count=3, seed=seed, progress=False)
    assert one.failed == {} and one.written == 3
    assert set(one.redrawn) == {0, 2} and "did not settle" in one.redrawn[0][0]
    assert "item 2: attempt 0 failed the quality gate (the pile did not settle" in caplog.text
    tree_one, tree_two = _tree(tmp_path / "one"), _tree(tmp_path / "two")
    assert [k for k in tree_one if k != "dataset.json" and tree_one[k] != tree_two.get(k)] == []

    records = load_records(tmp_path / "one")
    assert [records[i]["attempt"] for i in range(3)] == [1, 0, 1]
    assert records[0]["redraws"] == [{"attempt": 0, "reason": one.redrawn[0][0]}] and records[1]["redraws"] == []
    for record in records.values():
        st = record["stability"]
        assert st["settled"] and 0 < st["sim_time_s"] <= st["max_time_s"]
        assert 0 <= st["max_penetration_m"] <= st["penetration_bound_m"] == recipe.scene.physics.max_penetration_m
        assert record["visible_instances"] >= 1 and record["instances"] == 6

    monkeypatch.setattr(dataset_item, "drop_scene", real_drop)
    written = make_item(recipe, seed, 0)  # the gate now passes attempt 0: a different item
    redrawn, reason = make_attempt(recipe, seed, 0, 1)
    assert reason == "" and written.record["attempt"] == 0
    rgb_file = next(k for k in tree_one if k.startswith("bop/") and k.endswith("rgb/000000.png"))
    from sygrid.writers.bop import encode_png

    assert encode_png(redrawn.rgb[..., ::-1], "rgb") == tree_one[rgb_file]  # the file holds attempt 1
    assert encode_png(written.rgb[..., ::-1], "rgb") != tree_one[rgb_file]


# ---------------------------------------------------------------------------------------------------- resume
def test_resume_notices_deleted_files_and_makes_those_items_again(tmp_path, caplog, capsys):
    recipe = _recipe(tmp_path)
    out = tmp_path / "d"
    generate(recipe, out, count=3, seed=5, progress=False)
    complete = _tree(out)
    mask = next(out.glob("bop/*/000000/mask_visib/000001_000000.png"))
    mask.unlink()
    next(out.glob("coco/annotations/items_*/000000_000002.json")).unlink()
    with caplog.at_level(logging.WARNING, logger="sygrid.dataset"):
        again = generate(recipe, out, count=3, seed=5, progress=False)
    assert again.redone == [1, 2] and again.written == 2 and again.skipped == 1
    assert f"item 1: recorded as done, but {mask} is missing; making the item again" in caplog.text
    assert "item 2: recorded as done, but" in caplog.text and "000000_000002.json is missing" in caplog.text
    assert {k: v for k, v in _tree(out).items() if k != "dataset.json"} == {
        k: v for k, v in complete.items() if k != "dataset.json"
    }
    # `sygrid show` prints the shown items' records
    split = mask.parents[2].name
    assert main(["show", str(out), "--split", split, "--items", "1", "--out", str(tmp_path / "s.png")]) == 0
    assert "settled in" in capsys.readouterr().out


# --------------------------------------------------------------------------------------------- sygrid drop
@pytest.mark.parametrize(
    ("physics", "code", "reason"),
    [
        ({}, 0, None),
        ({"max_time_s": 0.05}, 1, "the pile did not settle within 0.05 s"),
        ({"max_penetration_m": 1e-9}, 1, "mm is above the bound 0.00 mm"),
    ],
)
def test_drop_exits_non_zero_with_one_line_when_the_pile_fails_its_bounds(tmp_path, capsys, physics, code, reason):
    scene = tmp_path / "scene.json"
    scene.write_text(json.dumps({"objects": [{"builtin": "hex_nut", "count": 3}], "physics": physics}))
    assert main(["drop", str(scene), "--seed", "1", "--out", str(tmp_path / "p.json")]) == code
    captured = capsys.readouterr()
    assert (tmp_path / "p.json").is_file()
    if reason is None:
        assert captured.err == ""
    else:
        lines = captured.err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("sygrid drop: the pile is outside its stability bounds")
        assert reason in lines[0]


def test_drop_and_generate_document_their_exit_codes(capsys):
    for command in ("drop", "generate"):
        with pytest.raises(SystemExit):
            main([command, "--help"])
        text = " ".join(capsys.readouterr().out.split())
        assert "exit codes: 0" in text and "; 1 " in text and "; 2 bad input" in text
