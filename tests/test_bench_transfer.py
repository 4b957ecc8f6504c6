"""`sygrid bench transfer`: the class-agnostic view of the detection metrics on a hand-made image, and the matrix of
three detectors on two tiny generated sources: an oracle (a constant ONNX model answering the first home image's
ground-truth boxes), the same boxes under the wrong part names, and a detector trained for one iteration."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from launch.cli import build_parser
from perception.bench_transfer import run
from perception.evaluation import EvalSettings, dataset_classes, eval_items
from perception.manifest import DetectorEntry
from perception.transfer import DetectorSpec, evaluate_cell, shared_parts
from sygrid.annotations import ImageAnnotation, annotate
from sygrid.camera import CameraIntrinsics
from sygrid.detection_breakdown import AGNOSTIC_ID, class_agnostic, only_parts
from sygrid.errors import ConfigError
from sygrid.metrics import detection_metrics
from sygrid.transforms import make_T
from sygrid.writers import load_bop_item
from tests.conftest import tiny_recipe_json
from tests.test_detector_runtime import save_model

pytestmark = pytest.mark.filterwarnings("ignore:__array__ implementation:DeprecationWarning")


class Det:
    def __init__(self, obj_id: int, score: float, box: tuple[int, int, int, int], mask: np.ndarray | None) -> None:
        self.obj_id, self.score, self.bbox_xyxy, self.mask = obj_id, score, np.array(box, float), mask


def test_class_agnostic_counts_a_right_box_under_the_wrong_name():
    h, w = 60, 80
    ids = np.zeros((h, w), np.int32)
    ids[10:30, 10:40] = 1
    instances = annotate(
        ids, (ids == 1)[None], make_T(t=[0, 0, 0.5])[None], [3], CameraIntrinsics(100, 100, 40, 30, w, h)
    )
    image = ImageAnnotation(0, CameraIntrinsics(100, 100, 40, 30, w, h), tuple(instances))
    wrong = [[Det(1, 0.9, (10, 10, 40, 30), ids == 1)]]  # the right box, named another part
    assert detection_metrics([image], wrong).box_map50 == 0.0
    images, dets = class_agnostic([image], wrong)
    assert [i.obj_id for i in images[0].instances] == [AGNOSTIC_ID] and dets[0][0].obj_id == AGNOSTIC_ID
    assert dets[0][0].mask is wrong[0][0].mask and dets[0][0].score == 0.9
    agnostic = detection_metrics(images, dets)
    assert agnostic.box_map50 == pytest.approx(1.0) and agnostic.mask_map50 == pytest.approx(1.0)
    assert image.instances[0].obj_id == 3 and wrong[0][0].obj_id == 1  # the originals are untouched
    kept_images, kept = only_parts([image], wrong, [3])
    assert len(kept_images[0].instances) == 1 and kept == [[]]


@pytest.fixture(scope="module")
def other_source(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """DIR of 2 test images of the tiny bin, another seed."""
    from sygrid.dataset import generate
    from sygrid.recipe import parse_recipe

    out = tmp_path_factory.mktemp("tiny_other")
    assert not generate(parse_recipe(tiny_recipe_json(split="test"), "other", out), out, count=2, seed=11,
                        progress=False).failed  # fmt: skip
    return out


def _constant(path: Path, data_dir: Path, rotate: int = 0, names: dict[int, str] | None = None) -> Path:
    """A detection-only model answering the ground-truth boxes of ``data_dir``'s first image (visible at least
    10 %), at its size, score 0.9, each under the class ``rotate`` places further on (0: the right one)."""
    root, split, items = eval_items(data_dir, EvalSettings())
    ann, _, _ = load_bop_item(root, *items[0], split=split)
    names = names or dataset_classes(data_dir, split)
    ids = sorted(names)
    seen = [i for i in ann.instances if i.visib_fract >= 0.1 and i.px_count_visib]
    cxcywh = np.array([[x + bw / 2, y + bh / 2, bw, bh] for x, y, bw, bh in (i.bbox_visib for i in seen)], float)
    scores = np.zeros((len(seen), len(ids)))
    for k, inst in enumerate(seen):
        scores[k, (ids.index(inst.obj_id) + rotate) % len(ids) if inst.obj_id in ids else 0] = 0.9
    meta = {"names": str(dict(enumerate(names[i] for i in ids))), "obj_ids": str(ids), "stride": "32"}
    path.mkdir(parents=True, exist_ok=True)
    shape = [1, 3, ann.intrinsics.height, ann.intrinsics.width]
    save_model(path / "detector.onnx", {"output0": np.concatenate([cxcywh, scores], axis=1).T[None]}, meta, shape)
    return path


@pytest.fixture(scope="module")
def detectors(tiny_dataset: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """``tiny``: the oracle as a model folder (manifest, operating threshold 0.5); ``swapped``: its boxes under
    the wrong names, a training run folder; ``trained``: a detector trained for one iteration (a training run)."""
    pytest.importorskip("torch")
    from sygrid.train.detector.config import TrainConfig
    from sygrid.train.detector.trainer import train

    out = tmp_path_factory.mktemp("transfer_detectors")
    oracle = _constant(out / "oracle", tiny_dataset)
    (oracle / "pose.onnx").write_bytes(b"")  # the manifest names one; the benchmark never opens it
    manifest = {"format": "sygrid-models/1", "objects": [{"builtin": "hex_nut"}], "pose": {"onnx": "pose.onnx"},
                "detector": {"onnx": "detector.onnx", "conf_threshold": 0.5}}  # fmt: skip
    (oracle / "manifest.json").write_text(json.dumps(manifest))
    train(TrainConfig(data=str(tiny_dataset), out=str(out / "trained"), imgsz=128, batch=2, size="p", seed=0,
                      threads=1, epochs=1, max_iters=1, progress=False))  # fmt: skip
    return {"tiny": oracle, "swapped": _constant(out / "swapped", tiny_dataset, rotate=1), "trained": out / "trained"}


def _bench(argv: list[str], out_dir: Path) -> int:
    return run(build_parser("bench").parse_args(["bench", "transfer", *argv]), out_dir=out_dir)


def test_the_matrix_of_three_detectors_on_two_sources(detectors, tiny_dataset, other_source, tmp_path, capsys):
    argv = [f"--detector={k}={v}" for k, v in detectors.items()]
    argv += [f"--source=tiny={tiny_dataset}", f"--source=other={other_source}", "--home", "swapped=tiny",
             "--held-apart", "other", "--max-images", "1", "--timing-images", "1", "--threads", "1"]  # fmt: skip
    assert _bench(argv, tmp_path) == 0
    results = json.loads((tmp_path / "transfer.json").read_text())
    assert (tmp_path / "transfer.png").stat().st_size > 0
    m = results["matrix"]
    assert m["detectors"] == ["tiny", "swapped", "trained"] and m["sources"] == ["tiny", "other"]
    assert m["home"] == {"tiny": "tiny", "swapped": "tiny", "trained": None}
    for key in ("box_map50", "ratio", "agnostic_box_map50", "ms_median"):
        assert np.shape(m[key]) == (3, 2), key
    oracle = results["cells"]["tiny"]["tiny"]
    assert oracle["box_map50"] == pytest.approx(1.0) and m["ratio"][0][0] == 1.0
    assert oracle["agnostic_box_map50"] == pytest.approx(1.0) and oracle["mask_map50"] is None
    assert oracle["shared_obj_ids"] == [1, 3, 4] and oracle["classes_note"] is None
    assert set(oracle["ap50_by_part"]) == {"1 hex_nut", "3 washer", "4 l_bracket"}
    assert set(oracle["recall_by_size"]) == set(oracle["agnostic_recall_by_size"]) == {"<20", "20-50", ">50"}
    assert oracle["ms_median"] > 0 and oracle["timing_images"] == 1 and oracle["n_images"] == 1
    swapped = results["cells"]["swapped"]["tiny"]
    assert swapped["box_map50"] == 0.0 and swapped["agnostic_box_map50"] == pytest.approx(1.0)
    assert all(math.isnan(r) for r in m["ratio"][1] + m["ratio"][2])  # home figure 0, and no home
    assert isinstance(results["cells"]["trained"]["tiny"]["mask_map50"], float)  # a segmentation model
    checks = results["target_checks"]
    assert [c["detector"] for c in checks] == ["tiny", "tiny", "swapped", "swapped", "trained", "trained"]
    assert checks[0]["measured"] == pytest.approx(m["ratio"][0][1], nan_ok=True) and checks[0]["threshold"] == 0.85
    assert checks[4]["met"] is None  # no home
    out = capsys.readouterr().out
    assert "targets on the held-apart source other" in out and "(home: tiny)" in out
    assert _bench(["--replot"], tmp_path) == 0


def test_a_named_run_keeps_the_default_result(detectors, tiny_dataset, tmp_path):
    (tmp_path / "transfer.json").write_text("{}")
    argv = [f"--detector=tiny={detectors['tiny']}", f"--source=tiny={tiny_dataset}", "--name", "transfer_ablation",
            "--max-images", "1", "--timing-images", "1", "--threads", "1"]  # fmt: skip
    assert _bench(argv, tmp_path) == 0
    assert json.loads((tmp_path / "transfer_ablation.json").read_text())["matrix"]["detectors"] == ["tiny"]
    assert (tmp_path / "transfer.json").read_text() == "{}"
    assert _bench(["--replot", "--name", "transfer_ablation"], tmp_path) == 0


def test_a_detector_knowing_some_or_none_of_a_sources_parts(tiny_dataset, tmp_path):
    split = eval_items(tiny_dataset, EvalSettings())[1]
    assert shared_parts({1: "hex_nut", 3: "washer", 4: "l_bracket", 9: "x"}, tiny_dataset, split) == ([1, 3, 4], None)
    shared, note = shared_parts({1: "hex_nut", 3: "nut"}, tiny_dataset, split)
    assert shared == [1] and "[3, 4] left out" in note
    nut_only = _constant(tmp_path / "nut", tiny_dataset, names={1: "hex_nut"})
    cell = evaluate_cell(DetectorSpec("nut", nut_only, "training run", _entry()), tiny_dataset,
                         EvalSettings(max_images=1), threads=1, timing_images=1, progress=False)  # fmt: skip
    assert cell["shared_obj_ids"] == [1] and "on the shared obj_ids [1] alone" in cell["classes_note"]
    assert list(cell["ap50_by_part"]) == ["1 hex_nut"] and cell["box_map50"] == pytest.approx(1.0)
    foreign = _constant(tmp_path / "foreign", tiny_dataset, names={99: "gear"})
    cell = evaluate_cell(DetectorSpec("gear", foreign, "training run", _entry()), tiny_dataset,
                         EvalSettings(max_images=1), threads=1, timing_images=1, progress=False)  # fmt: skip
    assert cell["shared_obj_ids"] == [] and "class-agnostic only" in cell["classes_note"]
    assert math.isnan(cell["box_map50"]) and cell["ap50_by_part"] is None and cell["recall_by_size"] is None
    assert cell["agnostic_box_map50"] == pytest.approx(1.0)  # every box is right, under the one name it knows


def _entry() -> DetectorEntry:
    return DetectorEntry(onnx="detector.onnx", conf_threshold=0.5)


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--detector", "nameonly", "--source", "s=."], r"--detector 'nameonly': expected NAME=PATH"),
        (["--detector", "d=/no/such", "--source", "s=."], r"--detector 'd=/no/such': .*neither .*no such folder"),
        (["--detector", "d={run}", "--source", "s=/no/such"], r"--source 's=/no/such': .*\(no bop/ folder\)"),
        (["--source", "s={data}"], r"at least one --detector"),
        (["--detector", "d={run}", "--detector", "d={run}", "--source", "s={data}"], r"--detector: .* d given twice"),
        (["--detector", "d={run}", "--source", "s={data}", "--home", "x=s"], r"--home 'x=s': no detector named 'x'"),
        (["--detector", "d={run}", "--source", "s={data}", "--home", "d=y"], r"--home 'd=y': no source named 'y'"),
        (["--detector", "d={run}", "--source", "s={data}", "--held-apart", "z"], r"--held-apart 'z': no source"),
        (["--detector", "d={run}", "--source", "s={data}", "--max-images", "0"], r"--max-images: expected a posit"),
    ],
)
def test_bad_arguments_are_configuration_errors_naming_the_option(argv, message, tiny_dataset, tmp_path):
    run_dir = _constant(tmp_path / "run", tiny_dataset)
    argv = [a.format(run=run_dir, data=tiny_dataset) for a in argv]
    with pytest.raises(ConfigError, match=message):
        _bench(argv, tmp_path)


def test_cards_get_the_model_folders_row_once_and_keep_the_rest(detectors, tiny_dataset, other_source, tmp_path):
    folder = tmp_path / "oracle"
    shutil.copytree(detectors["tiny"], folder)
    (folder / "detector.card.md").write_text("# Model card: detector\n\n## Held-out test set: x\n\nkept\n")
    argv = [f"--detector=tiny={folder}", f"--detector=trained={detectors['trained']}", f"--source=tiny={tiny_dataset}",
            f"--source=other={other_source}", "--held-apart", "other", "--max-images", "1", "--timing-images", "1",
            "--threads", "1", "--cards"]  # fmt: skip
    for _ in range(2):  # a second run replaces the section
        assert _bench(argv, tmp_path) == 0
    card = (folder / "detector.card.md").read_text()
    assert card.startswith("# Model card: detector\n\n## Held-out test set: x\n\nkept\n\n## Transfer to other image")
    assert card.count("## Transfer to other image sources") == 1
    assert "| tiny (home) | 1.000 | 1.00 | 1.000 |" in card and "| other (held apart) | " in card
    assert "Targets on the held-apart source (other): " in card
    assert not (detectors["trained"] / "detector.card.md").exists()  # a training run has no card
