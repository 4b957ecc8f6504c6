"""``sygrid bench detection`` on the tiny bin: a detector trained for one iteration, packed as a model folder, seen
through the quick variants (the whole frame, the bin's box, tiles over the bin); the rows it writes and where."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from launch.cli import build_parser
from perception.bench_detection import QUICK_VARIANTS, run, select_variants
from sygrid.errors import ConfigError

pytestmark = pytest.mark.filterwarnings("ignore:__array__ implementation:DeprecationWarning")


@pytest.fixture(scope="module")
def model_folder(tiny_dataset: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    pytest.importorskip("torch")
    from sygrid.train.detector.config import TrainConfig
    from sygrid.train.detector.trainer import train

    out = tmp_path_factory.mktemp("detection_bench")
    train(TrainConfig(data=str(tiny_dataset), out=str(out / "run"), imgsz=128, batch=2, size="p", seed=0,
                      threads=1, epochs=1, max_iters=1, progress=False))  # fmt: skip
    folder = out / "models"
    folder.mkdir()
    shutil.copy(out / "run" / "detector.onnx", folder / "detector.onnx")
    (folder / "pose.onnx").write_bytes(b"")  # the manifest names one; the benchmark never opens it
    manifest = {"format": "sygrid-models/1", "objects": [{"builtin": "hex_nut"}, {"builtin": "washer"},
                {"builtin": "l_bracket"}], "pose": {"onnx": "pose.onnx"},
                "detector": {"onnx": "detector.onnx", "conf_threshold": 0.3}}  # fmt: skip
    (folder / "manifest.json").write_text(json.dumps(manifest))
    return folder


def _bench(argv: list[str], out_dir: Path) -> int:
    return run(build_parser("bench").parse_args(["bench", "detection", *argv]), out_dir=out_dir)


def test_every_quick_view_is_measured_and_a_named_run_keeps_the_default_result(model_folder, tiny_dataset, tmp_path):
    (tmp_path / "detection.json").write_text("{}")
    argv = ["--models", str(model_folder), "--data", str(tiny_dataset), "--quick", "--max-images", "2",
            "--timing-images", "1", "--threads", "1", "--name", "detection_n"]  # fmt: skip
    assert _bench(argv, tmp_path) == 0
    results = json.loads((tmp_path / "detection_n.json").read_text())
    assert (tmp_path / "detection_n.png").stat().st_size > 0
    assert (tmp_path / "detection.json").read_text() == "{}"  # the default result is left as it was
    assert results["n_images"] == 2 and results["operating_threshold"] == 0.3
    rows = results["variants"]
    assert [r["name"] for r in rows] == [v.name for v in QUICK_VARIANTS]
    assert [r["region"] for r in rows] == ["full", "bin", "bin"] and rows[2]["tile_px"] == 320
    for r in rows:
        assert r["ms_median"] > 0 and 0.0 <= r["box_map50"] <= 1.0
        assert set(r["recall_by_size"]) == {"<20", "20-50", ">50"}
    assert _bench(["--replot", "--name", "detection_n"], tmp_path) == 0


def test_named_variants_run_in_the_table_order_and_an_unknown_name_is_refused_with_the_choices():
    assert [v.name for v in select_variants(["bin @ 1.5", "full @ 480"])] == ["full @ 480", "bin @ 1.5"]
    with pytest.raises(ConfigError, match=r"--variant: unknown 'bin @ 2'; expected one of 'full @ 480'"):
        select_variants(["bin @ 1.0", "bin @ 2"])
