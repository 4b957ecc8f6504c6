"""The shipped models (models/builtin, and the simulated cell's models/sim_cell) on small test sets generated here,
with seeds no model has seen.

The recipes are the ones the model cards were measured on (launch/recipes/*_test.json, path-traced and rasterised
items alike); the bars sit well below the cards' figures because six images are a noisy sample.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from perception.detector_eval import dataset_region
from perception.evaluation import EvalSettings, evaluate, format_table
from perception.pipeline import PerceptionPipeline, PipelineOverrides
from sygrid.dataset import generate
from sygrid.recipe import load_recipe

pytestmark = [pytest.mark.slow, pytest.mark.filterwarnings("ignore:__array__ implementation:DeprecationWarning")]

ROOT = Path(__file__).resolve().parents[1]
FRESH_SEED = 424242  # neither the training sets (0) nor the cards' test sets (1000)
# Per model folder: the recipe its cards were measured on, and conservative bars (box mAP50, mask mAP50-95, ADD(-S)
# recall with refinement; the cards' figures over 100-200 images are higher, see models/*/*.card.md)
FOLDERS = {
    "builtin": ("builtin_test.json", 0.35, 0.15, 0.2),  # cards: 0.58, 0.29, 0.39 at the operating threshold
    "sim_cell": ("sim_cell_test.json", 0.5, 0.25, 0.3),  # cards: 0.80, 0.48, 0.62
}


@pytest.fixture(scope="module")
def fresh_test_sets(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    sets = {}
    for name, (recipe, *_) in FOLDERS.items():
        out = tmp_path_factory.mktemp(f"fresh_{name}")
        summary = generate(load_recipe(ROOT / "launch" / "recipes" / recipe), out, count=6, seed=FRESH_SEED,
                           progress=False)  # fmt: skip
        assert not summary.failed, summary.failed
        sets[name] = out
    return sets


@pytest.mark.parametrize("folder", FOLDERS)
def test_the_model_folder_matches_its_cards(folder: str):
    models = ROOT / "models" / folder
    manifest = json.loads((models / "manifest.json").read_text())
    for name in ("detector.onnx", "pose.onnx"):
        size_mb = (models / name).stat().st_size / 1e6
        assert size_mb < 10, f"{name} is {size_mb:.1f} MB: shipped models must stay small"
    assert manifest["detector"]["onnx"] == "detector.onnx" and manifest["pose"]["onnx"] == "pose.onnx"
    for card in ("detector.card.md", "pose.card.md"):
        text = (models / card).read_text()
        assert "command: `sygrid train" in text and "Held-out test set" in text


@pytest.mark.parametrize("folder", FOLDERS)
def test_shipped_models_on_a_fresh_test_set(folder: str, fresh_test_sets: dict[str, Path]):
    _, min_box_map50, min_mask_map50_95, min_add_recall = FOLDERS[folder]
    pipeline = PerceptionPipeline.from_folder(ROOT / "models" / folder, PipelineOverrides(refine=True))
    settings = EvalSettings(region=dataset_region(fresh_test_sets[folder]))  # where the cell looks: the bin's box
    report = evaluate(pipeline, fresh_test_sets[folder], settings, progress=False)
    print(format_table(report))
    det, pose = report["detection"], report["pose"]["all"]
    assert det["box_map50"] >= min_box_map50
    assert det["mask_map50_95"] >= min_mask_map50_95
    assert pose["add_recall"] >= min_add_recall
