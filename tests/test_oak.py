"""The OAK camera without a device: configuration, the pipeline plan per platform, intrinsics from a depthai
calibration (a real ``dai.CalibrationHandler`` filled on the host), depth units, the error when no device is
connected, and capture (``OakFrameSource`` behind the pipeline's own ``Sync`` node, ``sync_queue``) in a host-only
depthai pipeline fed by a host node that sends colour and depth ``ImgFrame``s as the device would.

What needs a device: the device nodes of ``_device_streams`` (Camera, StereoDepth, ImageAlign). depthai refuses to
create them in a pipeline without one ("Pipeline is host only, cannot create device node"), so their wiring is
checked by name against the installed depthai only."""

from __future__ import annotations

import contextlib
import gc
import logging
import time
from collections.abc import Iterator
from datetime import timedelta

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
    OakFrameSource,
    OakNotFoundError,
    _build_pipeline,
    depth_mm_to_m,
    oak_intrinsics,
    plan_pipeline,
    sync_queue,
)
from sygrid.camera import CameraIntrinsics
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


# ---------------------------------------------------------------------------------------------- capture


SIZE = (128, 72)
K_HOST = CameraIntrinsics.from_fov(*SIZE, 60.0)


class _HostRgbd(dai.node.ThreadedHostNode):
    """Sends what the device's colour camera and aligned depth would: BGR888i frames (B = k % 256, G = 100, R = 200)
    and uint16 depth (600 + k mm) of ``SIZE``, stamped on depthai's host clock (depth 5 ms after colour) and on a
    device clock 100 s behind, at ``fps``; ``depth_size`` and ``frame_K`` change what it sends, ``stop_after``
    frames ends the stream."""

    def __init__(self) -> None:
        super().__init__()
        self.rgb = self.createOutput()
        self.depth = self.createOutput()
        self.fps, self.depth_size, self.frame_K, self.stop_after = 15.0, SIZE, K_HOST.K, None

    def run(self) -> None:
        k = 0
        while self.isRunning() and (self.stop_after is None or k < self.stop_after):
            now = dai.Clock.now()
            bgr = np.empty((SIZE[1], SIZE[0], 3), np.uint8)
            bgr[...] = (k % 256, 100, 200)
            rgb = dai.ImgFrame()
            rgb.setCvFrame(bgr, dai.ImgFrame.Type.BGR888i)
            rgb.setTransformation(dai.ImgTransformation(*SIZE, np.asarray(self.frame_K).tolist()))
            depth = dai.ImgFrame()
            depth.setFrame(np.full((self.depth_size[1], self.depth_size[0]), 600 + k, np.uint16))
            depth.setType(dai.ImgFrame.Type.RAW16)
            depth.setWidth(self.depth_size[0])
            depth.setHeight(self.depth_size[1])
            for msg, offset_ms in ((rgb, 0.0), (depth, 5.0)):
                msg.setTimestamp(now + timedelta(milliseconds=offset_ms))
                msg.setTimestampDevice(now + timedelta(milliseconds=offset_ms) - timedelta(seconds=100))
                msg.setSequenceNum(k)
            self.rgb.send(rgb)
            self.depth.send(depth)
            k += 1
            time.sleep(1.0 / self.fps)


@contextlib.contextmanager
def host_pipeline(config: OakConfig, **source: object) -> Iterator[OakFrameSource]:
    """A host-only pipeline: ``_HostRgbd`` (attributes from ``source``) into ``sync_queue``, read by an
    ``OakFrameSource``; stopped and released on exit (a depthai pipeline left to interpreter exit can crash it)."""
    pipeline = dai.Pipeline(False)
    node = pipeline.create(_HostRgbd)
    for name, value in source.items():
        setattr(node, name, value)
    queue = sync_queue(dai, pipeline, node.rgb, node.depth, plan_pipeline(config, "RVC2"))
    pipeline.start()
    try:
        yield OakFrameSource(queue, K_HOST, config, dai.Clock, "OAK host")
    finally:
        pipeline.stop()
        pipeline.wait()
        del node, queue, pipeline
        gc.collect()


def test_capture_returns_fresh_synced_frames_in_metres_and_rgb(caplog: pytest.LogCaptureFixture) -> None:
    config = OakConfig(rgb_size=SIZE, fps=15.0, frame_timeout_s=2.0)
    with caplog.at_level(logging.WARNING, logger="perception.oak"), host_pipeline(config) as source:
        time.sleep(0.5)  # groups pile up in the queue: stale by the time of the call
        frames = []
        for _ in range(3):
            t_call = dai.Clock.now().total_seconds()
            frames.append(source.next_frame())
            assert frames[-1].timestamp_s >= t_call  # taken after the call (host clock)
    ks = [int(f.rgb[0, 0, 2]) for f in frames]
    assert ks == sorted(set(ks)) and ks[0] >= 5, ks  # the stale ones were dropped, none returned twice
    for k, frame in zip(ks, frames, strict=True):
        assert frame.rgb.shape == (SIZE[1], SIZE[0], 3) and frame.intrinsics == K_HOST
        assert frame.rgb[0, 0].tolist() == [200, 100, k]  # BGR -> RGB
        # Synced pairs: the depth sent with this colour frame (5 ms apart, within half a frame period).
        np.testing.assert_allclose(frame.depth_m, (600 + k) / 1000.0, rtol=1e-6)
    assert not caplog.records  # the frames' own intrinsics match the calibration's


def test_capture_on_the_device_clock() -> None:
    config = OakConfig(rgb_size=SIZE, fps=15.0, timestamp_clock="device")
    with host_pipeline(config) as source:
        t_call = dai.Clock.now().total_seconds()
        frame = source.next_frame()
    assert t_call - 101.0 < frame.timestamp_s < t_call - 99.0


def test_capture_errors_name_the_camera(caplog: pytest.LogCaptureFixture) -> None:
    config = OakConfig(rgb_size=SIZE, fps=15.0, frame_timeout_s=0.5)
    with host_pipeline(config, stop_after=2) as source:
        time.sleep(0.4)  # both frames sent: nothing newer will come
        with pytest.raises(OakError, match=r"no RGB-D frame from OAK host within 0\.5 s"):
            source.next_frame()
    mismatch = r"OAK host frames do not match the requested 128x72: .*depth \(36, 64\)"
    with host_pipeline(config, depth_size=(64, 36)) as source, pytest.raises(OakError, match=mismatch):
        source.next_frame()
    K_other = K_HOST.K.copy()
    K_other[0, 2] += 5.0
    with caplog.at_level(logging.WARNING, logger="perception.oak"), host_pipeline(config, frame_K=K_other) as source:
        source.next_frame()
        source.next_frame()
    warnings = [r for r in caplog.records if "differ by more than 1 px" in r.getMessage()]
    assert len(warnings) == 1  # checked once


def test_device_nodes_need_a_device() -> None:
    """The part of the pipeline this module cannot run: depthai creates no device node without a device."""
    pipeline = dai.Pipeline(False)
    with pytest.raises(RuntimeError, match="cannot create device node"):
        _build_pipeline(dai, pipeline, plan_pipeline(OakConfig(), "RVC2"))
    del pipeline
    gc.collect()
