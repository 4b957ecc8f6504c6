"""Where training and inference run: ``--device auto|cpu|cuda`` (sygrid.train.device) and onnxruntime's providers
(perception.providers). The tests run on the CPU; CUDA is simulated where only the selection is under test."""

from __future__ import annotations

import pytest

from perception.providers import CPU, CUDA, session_providers
from sygrid.errors import ConfigError, ModelError

torch = pytest.importorskip("torch")

from sygrid.train.detector.config import TrainConfig  # noqa: E402
from sygrid.train.device import autocast, grad_scaler, resolve_device, to_float32  # noqa: E402
from sygrid.train.pose.config import TrainConfig as PoseTrainConfig  # noqa: E402


def test_device_selection(monkeypatch: pytest.MonkeyPatch):
    assert resolve_device("cpu").type == "cpu"
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert resolve_device("auto").type == "cpu"
    with pytest.raises(ValueError, match=r"device 'cuda': torch .* sees no CUDA device"):
        resolve_device("cuda")
    with pytest.raises(ValueError, match="expected one of"):
        resolve_device("gpu")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert resolve_device("auto").type == "cuda" and resolve_device("cuda").type == "cuda"
    assert resolve_device("cpu").type == "cpu"


def test_the_cpu_path_has_no_autocast_and_no_scaling():
    cpu = torch.device("cpu")
    scaler = grad_scaler(cpu)
    assert not scaler.is_enabled()
    loss = torch.tensor(2.0, requires_grad=True)
    assert scaler.scale(loss) is loss
    with autocast(cpu):
        y = torch.ones(2, 2) @ torch.ones(2, 2)
    assert y.dtype == torch.float32
    out = to_float32(
        (
            [torch.ones(1, dtype=torch.float16)],
            {"a": torch.ones(1, dtype=torch.bfloat16)},
            torch.ones(1, dtype=torch.long),
        )
    )
    assert out[0][0].dtype == torch.float32 and out[1]["a"].dtype == torch.float32 and out[2].dtype == torch.long


def test_trainer_configs_check_the_device():
    assert TrainConfig(data="d", out="o").device == "auto"
    with pytest.raises(ValueError, match="device"):
        TrainConfig(data="d", out="o", device="tpu")
    assert PoseTrainConfig(data_dir="d", out_dir="o", device="cpu").device == "cpu"
    with pytest.raises(ConfigError, match="device"):
        PoseTrainConfig(data_dir="d", out_dir="o", device="tpu")


def test_command_lines_take_device():
    import argparse

    from sygrid.train.detector.command import add_arguments as detector_args
    from sygrid.train.pose.command import add_arguments as pose_args

    for add in (detector_args, pose_args):
        parser = argparse.ArgumentParser()
        add(parser)
        assert parser.parse_args(["--data", "d", "--out", "o"]).device == "auto"
        assert parser.parse_args(["--data", "d", "--out", "o", "--device", "cpu"]).device == "cpu"
        with pytest.raises(SystemExit):
            parser.parse_args(["--data", "d", "--out", "o", "--device", "gpu"])


def test_onnxruntime_providers():
    assert session_providers("cpu", [CUDA, CPU]) == [CPU]
    assert session_providers("auto", [CPU]) == [CPU]
    assert session_providers("auto", [CUDA, CPU]) == [CUDA, CPU]
    assert session_providers("cuda", [CUDA, CPU]) == [CUDA, CPU]
    with pytest.raises(ModelError, match="no CUDAExecutionProvider"):
        session_providers("cuda", [CPU])
    with pytest.raises(ValueError, match="expected one of"):
        session_providers("gpu", [CPU])
