"""The OAK camera without a device: configuration, the pipeline plan per platform, intrinsics from a depthai
calibration (a real ``dai.CalibrationHandler`` filled on the host), depth units, and the error when no device is
connected."""

from __future__ import annotations

import numpy as np
import pytest

from perception.camera import Camera
from perception.oak import (
    LEFT_SOCKET,
    RGB_SOCKET,
    RIGHT_SOCKET,
    STEREO_PRESETS,
    OakCamera,
    OakConfig,
    OakError,
    OakNotFoundError,
    depth_mm_to_m,
    oak_intrinsics,
    plan_pipeline,
)
from sygrid.errors import ConfigError, SygridError

dai = pytest.importorskip("depthai")


def test_config_is_validated() -> None:
    assert OakConfig().rgb_size == (1280, 720)
    with pytest.raises(ConfigError, match=r"rgb_size width must be a multiple of 16, got 1000"):
        OakConfig(rgb_size=(1000, 750))
    with pytest.raises(ConfigError, match=r"stereo_size must be \(width, height\)"):
        OakConfig(stereo_size=(640,))
    with pytest.raises(ConfigError, match="stereo_preset 'SHARP' is not one of"):
        OakConfig(stereo_preset="SHARP")
    with pytest.raises(ConfigError, match="fps must be in"):
        OakConfig(fps=0.0)
    with pytest.raises(ConfigError, match="timestamp_clock"):
        OakConfig(timestamp_clock="wall")  # type: ignore[arg-type]


def test_pipeline_plan_per_platform_and_the_depthai_names_it_uses() -> None:
    config = OakConfig(rgb_size=(1280, 720), fps=20.0)
    rvc2, rvc4 = plan_pipeline(config, "RVC2"), plan_pipeline(config, "RVC4")
    assert rvc2.depth_alignment == "stereo_depth" and rvc4.depth_alignment == "image_align"
    assert rvc2.rgb_size == (1280, 720) and rvc2.sync_threshold_s == pytest.approx(0.025)
    with pytest.raises(OakError, match="platform 'RVC3' is not supported"):
        plan_pipeline(config, "RVC3")
    # Every depthai name the pipeline builder resolves exists in the installed depthai (guards against API drift).
    for socket in (RGB_SOCKET, LEFT_SOCKET, RIGHT_SOCKET):
        assert hasattr(dai.CameraBoardSocket, socket)
    for preset in STEREO_PRESETS:
        assert hasattr(dai.node.StereoDepth.PresetMode, preset)
    assert hasattr(dai.ImgFrame.Type, "BGR888i")
    for node, attributes in (
        (dai.node.StereoDepth, ("setDepthAlign", "setOutputSize", "setLeftRightCheck", "depth", "build")),
        (dai.node.ImageAlign, ("input", "inputAlignTo", "outputAligned")),
        (dai.node.Sync, ("setSyncThreshold", "inputs", "out")),
        (dai.node.Camera, ("build", "requestOutput")),
    ):
        for attribute in attributes:
            assert hasattr(node, attribute), f"depthai {dai.__version__}: {node.__name__}.{attribute} is missing"


def test_intrinsics_from_a_depthai_calibration_scale_and_centre_crop() -> None:
    calibration = dai.CalibrationHandler()
    K_full = [[3000.0, 0.0, 2020.0], [0.0, 3010.0, 1510.0], [0.0, 0.0, 1.0]]
    calibration.setCameraIntrinsics(dai.CameraBoardSocket.CAM_A, K_full, 4056, 3040)  # IMX378, 4:3
    same = oak_intrinsics(calibration, "CAM_A", 4056, 3040)
    np.testing.assert_allclose(same.K, K_full)
    half = oak_intrinsics(calibration, "CAM_A", 2028, 1520)
    assert (half.fx, half.fy, half.cx, half.cy) == pytest.approx((1500.0, 1505.0, 1010.0, 755.0))
    # 16:9 from 4:3: scaled to the width, the height centre-cropped.
    K = oak_intrinsics(calibration, "CAM_A", 1280, 720)
    s = 1280 / 4056
    crop_rows = (3040 * s - 720) / 2
    assert (K.width, K.height) == (1280, 720)
    assert K.fx == pytest.approx(3000.0 * s) and K.fy == pytest.approx(3010.0 * s)
    assert K.cx == pytest.approx(2020.0 * s) and K.cy == pytest.approx(1510.0 * s - crop_rows)
    with pytest.raises(OakError, match="no intrinsics for socket CAM_B"):
        oak_intrinsics(calibration, "CAM_B", 640, 400)


def test_depth_millimetres_to_metres() -> None:
    depth = depth_mm_to_m(np.array([[0, 1, 650], [1234, 65535, 0]], dtype=np.uint16))
    assert depth.dtype == np.float32
    np.testing.assert_allclose(depth, [[0.0, 0.001, 0.65], [1.234, 65.535, 0.0]], rtol=1e-6)
    assert np.count_nonzero(depth == 0) == 2
    with pytest.raises(ValueError, match="uint16"):
        depth_mm_to_m(np.zeros((4, 4), dtype=np.float32))


def test_no_device_gives_a_clear_error() -> None:
    if dai.Device.getAllAvailableDevices():
        pytest.skip("an OAK device is connected to this machine")
    with pytest.raises(OakNotFoundError, match=r"looked for any OAK device.*devices seen: none") as info:
        OakCamera(OakConfig(search_timeout_s=0.3))
    assert isinstance(info.value, SygridError)
    with pytest.raises(OakNotFoundError, match="OAK device '14442C10D13EABCE00'"):
        OakCamera(OakConfig(device="14442C10D13EABCE00", search_timeout_s=0.3))
    assert issubclass(OakCamera, Camera)
