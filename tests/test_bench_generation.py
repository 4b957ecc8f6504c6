"""``sygrid bench generation`` on the tiny bin (160x120, rasterised): recipes taking turns item by item, the
summary and ratios it reports, the JSON and chart it writes, and bad arguments. No timing assertions."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from launch.bench import run
from launch.cli import build_parser
from sygrid.errors import ConfigError
from tests.conftest import tiny_recipe_json


def _bench(argv: list[str], out_dir: Path) -> int:
    return run(build_parser("bench").parse_args(["bench", "--out-dir", str(out_dir), "generation", *argv]))


@pytest.fixture(scope="module")
def recipes(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    folder = tmp_path_factory.mktemp("generation_recipes")
    plain = folder / "plain.json"
    plain.write_text(json.dumps(tiny_recipe_json(name="plain")))
    lit = folder / "lit.json"
    lit.write_text(json.dumps(tiny_recipe_json(name="lit", randomisation={"lighting": {"enabled": True}})))
    return [plain, lit]


def test_recipes_take_turns_and_are_compared_with_the_first(recipes, tmp_path, capsys):
    argv = [f"--recipe={p}" for p in recipes] + ["--items", "3", "--seed", "4"]
    assert _bench(argv, tmp_path) == 0
    results = json.loads((tmp_path / "generation.json").read_text())
    assert (tmp_path / "generation.png").stat().st_size > 0
    assert results["config"]["warmup_items"] == 1 and list(results["summary"]) == ["plain", "lit"]
    for name in ("plain", "lit"):
        rows = results["runs"][name]["rows"]
        assert [r["index"] for r in rows] == [0, 1, 2] and all(r["mode"] == "raster" for r in rows)
        s = results["summary"][name]
        assert s["items"] == 2 and s["failed"] == 0 and s["items_by_mode"] == {"raster": 2}
        assert s["median_item_s"] > 0 and {"drop_s", "write_s", "annotate_s"} <= set(s["median_stage_s"])
    assert results["summary"]["plain"]["ratio_to_first"] == 1.0
    lit = results["summary"]["lit"]
    assert lit["ratio_to_first"] == pytest.approx(lit["median_item_s"] / results["summary"]["plain"]["median_item_s"])
    # the same seed draws the same scene: the drops agree, only the lighting differs
    assert [r["instances"] for r in results["runs"]["plain"]["rows"]] == [
        r["instances"] for r in results["runs"]["lit"]["rows"]
    ]
    assert "x first" in capsys.readouterr().out
    assert _bench(["--replot"], tmp_path) == 0


@pytest.mark.parametrize(
    ("argv", "message"),
    [([], "at least one --recipe"), (["--recipe", "{a}", "--items", "1"], "at least 2"),
     (["--recipe", "{a}", "--recipe", "{a}"], "share a file name"),
     (["--recipe", "{missing}"], "missing.json")],
)  # fmt: skip
def test_bad_arguments_are_configuration_errors(argv, message, recipes, tmp_path):
    argv = [a.format(a=recipes[0], missing=tmp_path / "missing.json") for a in argv]
    with pytest.raises(ConfigError, match=message):
        _bench(argv, tmp_path)
