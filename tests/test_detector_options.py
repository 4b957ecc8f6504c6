"""Small-object options of the detector network (a stride-4 P2 level, stride-2 prototypes): the exported ONNX keeps
the ultralytics layout (more anchors, finer prototypes) and the runtime decodes it; a short training run works."""

from __future__ import annotations

import json

import numpy as np
import onnxruntime as ort
import pytest

torch = pytest.importorskip("torch")

from perception.detector import YoloSegDetector  # noqa: E402
from sygrid.train.detector.config import TrainConfig  # noqa: E402
from sygrid.train.detector.export import export_onnx  # noqa: E402
from sygrid.train.detector.model import ModelConfig, build_model, count_parameters  # noqa: E402
from sygrid.train.detector.trainer import train  # noqa: E402


@pytest.mark.parametrize(("p2", "proto_stride"), [(False, 4), (True, 4), (False, 2), (True, 2)])
def test_options_keep_the_onnx_layout_and_decode(tmp_path, p2, proto_stride):
    torch.manual_seed(0)
    cfg = ModelConfig(num_classes=2, size="f", p2=p2, proto_stride=proto_stride, prior_image_size=128)
    model = build_model(cfg).eval()
    report = export_onnx(model, tmp_path / "d.onnx", ["hex_nut", "washer"], [1, 3], 128, check_shapes=[(96, 128)])
    session = ort.InferenceSession(str(report.path), providers=["CPUExecutionProvider"])
    output0, output1 = session.run(["output0", "output1"], {"images": np.zeros((1, 3, 96, 128), np.float32)})
    anchors = sum((96 // s) * (128 // s) for s in cfg.strides)
    assert output0.shape == (1, 4 + 2 + 32, anchors)
    assert output1.shape == (1, 32, 96 // proto_stride, 128 // proto_stride)
    assert cfg.strides == ((4, 8, 16, 32) if p2 else (8, 16, 32))
    detector = YoloSegDetector(report.path, conf_threshold=0.001, max_detections=20)
    frame = np.random.default_rng(0).integers(0, 255, (120, 160, 3), dtype=np.uint8)
    for det in detector.detect(frame):
        assert det.obj_id in (1, 3) and det.mask.shape == (120, 160)


def test_the_default_network_is_unchanged():
    """Without the options, the parameter names and count are those of the shipped detector's network."""
    model = build_model(ModelConfig(num_classes=7, size="p", prior_image_size=480))
    names = set(model.state_dict())
    assert "head.proto.upsample.weight" in names and not any(".td2." in n or ".bu3." in n for n in names)
    assert count_parameters(model) == pytest.approx(1.03e6, rel=0.01)


@pytest.mark.slow  # a two-iteration training run and its export
def test_smoke_training_with_p2_and_fine_prototypes(tiny_dataset, tmp_path):
    result = train(TrainConfig(data=str(tiny_dataset), out=str(tmp_path / "run"), imgsz=128, batch=2, size="f",
                               p2=True, proto_stride=2, device="cpu", epochs=1, max_iters=2, threads=1,
                               progress=False))  # fmt: skip
    log = json.loads((tmp_path / "run" / "train_log.json").read_text())
    assert log["model"]["p2"] is True and log["model"]["proto_stride"] == 2 and log["config"]["device"] == "cpu"
    assert 0.0 <= log["epochs"][0]["val"]["mask_map50_95"] <= 1.0
    detector = YoloSegDetector(result.export.path, conf_threshold=0.001, max_detections=10)
    detector.detect(np.full((120, 160, 3), 90, np.uint8))
