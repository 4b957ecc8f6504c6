"""The RealSense camera without hardware: a D435-like software device (``tests/realsense_stream.py``) records a
synthetic scene with the SDK's recorder, and ``RealSenseCamera`` plays it back through the SDK, as a recording and
as a device found by serial in a context; plus configuration, option setting, frame assembly and the error when no
device is connected."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from perception.camera import Camera
from perception.realsense import (
    RealSenseCamera,
    RealSenseConfig,
    RealSenseError,
    RealSenseNotFoundError,
    apply_depth_options,
    colour_camera_depth,
    depth_units_to_m,
    realsense_frame,
)
from sygrid.camera import CameraIntrinsics
from sygrid.errors import ConfigError, SygridError
from tests.realsense_stream import SERIAL, SoftwareD435, StereoRig, colour_image, raycast_depth

rs = pytest.importorskip("pyrealsense2")

RIG = StereoRig()
N_FRAMES = 4


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return SoftwareD435(RIG).record(tmp_path_factory.mktemp("realsense") / "d435.db3", n_frames=N_FRAMES)


def _edges(depth: np.ndarray, margin_px: int) -> np.ndarray:
    """Pixels within ``margin_px`` of a depth step of more than 5 mm."""
    step = np.zeros(depth.shape, bool)
    step[:, 1:] |= np.abs(np.diff(depth, axis=1)) > 0.005
    step[1:, :] |= np.abs(np.diff(depth, axis=0)) > 0.005
    out = step.copy()
    for dy in range(-margin_px, margin_px + 1):
        for dx in range(-margin_px, margin_px + 1):
            out |= np.roll(np.roll(step, dy, axis=0), dx, axis=1)
    return out


def test_a_recorded_frame_plays_back_in_metres_aligned_to_colour(recording: Path) -> None:
    with RealSenseCamera(RealSenseConfig(recording=str(recording), frame_timeout_s=0.5)) as camera:
        assert isinstance(camera, Camera) and camera.playing_back
        assert camera.depth_scale_m == pytest.approx(RIG.depth_scale_m, rel=1e-6)  # the device's, not 1 mm
        frames = []
        with pytest.raises(RealSenseError, match="has no more frames"):  # the recording's end, within the timeout
            while True:
                frames.append(camera.capture())
    # In recorded order, each colour frame once; the SDK's syncer may leave the first colour frame unpaired
    # (its depth frame not yet read), which capture skips.
    markers = [int(f.rgb[0, 0, 0]) for f in frames]
    assert len(frames) >= N_FRAMES - 1 and markers == sorted(set(markers)) and markers[-1] == N_FRAMES - 1, markers
    K = RIG.color
    for k, frame in zip(markers, frames, strict=True):
        # The colour stream's intrinsics (float32 in the SDK), shared by the aligned depth.
        got = frame.intrinsics
        assert (got.width, got.height) == (K.width, K.height)
        np.testing.assert_allclose([got.fx, got.fy, got.cx, got.cy], [K.fx, K.fy, K.cx, K.cy], atol=1e-4)
        assert frame.rgb.dtype == np.uint8 and frame.depth_m.dtype == np.float32
        assert frame.timestamp_s == pytest.approx(1.0 + k / RIG.fps, abs=1e-6)
    frame = frames[-1]
    np.testing.assert_array_equal(frame.rgb, colour_image(K, RIG.T_depth_color, marker=N_FRAMES - 1))  # RGB order
    truth_z, label = raycast_depth(K, RIG.T_depth_color)  # what the colour camera would measure, exactly
    # Away from depth steps (3 px: the coarser depth camera's footprint), aligned depth is the colour camera's depth
    # within 1 mm (the Z16 unit is 0.1 mm) on at least 99 % of pixels; at the steps the SDK leaves holes (0).
    interior = ~_edges(truth_z, 3)
    close = np.abs(frame.depth_m - truth_z) <= 0.001
    assert close[interior].mean() >= 0.99, close[interior].mean()
    # The box top sits where the colour camera sees it: unaligned depth (the depth image resized to the colour size)
    # would put it about 12 px off and at another scale.
    top_truth = label == 1
    top_aligned = np.abs(frame.depth_m - 0.55) < 0.001
    iou = (top_truth & top_aligned).sum() / (top_truth | top_aligned).sum()
    assert iou > 0.97, iou
    raw = np.round(raycast_depth(RIG.depth, np.eye(4))[0] / RIG.depth_scale_m).astype(np.uint16)
    v = np.arange(K.height) * RIG.depth.height // K.height
    u = np.arange(K.width) * RIG.depth.width // K.width
    top_unaligned = np.abs(depth_units_to_m(raw, RIG.depth_scale_m)[np.ix_(v, u)] - 0.55) < 0.001
    assert (top_truth & top_unaligned).sum() / (top_truth | top_unaligned).sum() < 0.8


def test_a_device_is_found_by_serial_and_streams_as_configured(recording: Path) -> None:
    context = rs.context()
    playback = context.load_device(str(recording))  # a device in the context (while referenced), as if plugged in
    config = RealSenseConfig(
        serial=SERIAL, rgb_size=(RIG.color.width, RIG.color.height),
        depth_size=(RIG.depth.width, RIG.depth.height), fps=RIG.fps, frame_timeout_s=1.0,
    )  # fmt: skip
    with RealSenseCamera(config, context=context) as camera:
        assert camera.source == f"RealSense {SERIAL}" and camera.playing_back  # options stay as recorded
        frame = camera.capture()
        assert frame.depth_m.shape == (RIG.color.height, RIG.color.width) and frame.valid_depth.mean() > 0.95
    with pytest.raises(RealSenseNotFoundError, match=rf"serial '000000000000'.*devices seen: {SERIAL}"):
        RealSenseCamera(RealSenseConfig(serial="000000000000"), context=context)
    with pytest.raises(RealSenseError, match=r"would not stream depth \(848, 480\) Z16"):
        RealSenseCamera(RealSenseConfig(serial=SERIAL, fps=RIG.fps), context=context)  # the default sizes
    assert playback.is_playback()


def test_visual_preset_emitter_and_laser_power_are_set_on_the_depth_sensor() -> None:
    sensor = SoftwareD435(RIG).depth_sensor
    read = apply_depth_options(sensor, RealSenseConfig(visual_preset="high_accuracy", emitter_enabled=False))
    assert read == {"visual_preset": float(rs.rs400_visual_preset.high_accuracy), "emitter_enabled": 0.0}
    read = apply_depth_options(sensor, RealSenseConfig(visual_preset="default", laser_power_mw=240))
    assert read == {"visual_preset": 1.0, "emitter_enabled": 1.0, "laser_power": 240.0}
    assert sensor.get_option(rs.option.laser_power) == 240.0
    with pytest.raises(RealSenseError, match=r"laser_power 390 is outside the sensor's range \[0, 360\]"):
        apply_depth_options(sensor, RealSenseConfig(laser_power_mw=390))
    bare = rs.software_device().add_sensor("Stereo Module")
    with pytest.raises(RealSenseError, match="no visual_preset option"):
        apply_depth_options(bare, RealSenseConfig())


def test_config_is_validated() -> None:
    assert RealSenseConfig().rgb_size == (1280, 720) and RealSenseConfig().depth_size == (848, 480)
    for kwargs, match in (
        ({"fps": 25}, r"fps must be one of \[6, 15, 30, 60, 90\]"),
        ({"visual_preset": "sharp"}, "visual_preset 'sharp' is not one of"),
        ({"rgb_size": (1280,)}, r"rgb_size must be \(width, height\)"),
        ({"laser_power_mw": -1.0}, "laser_power_mw"),
        ({"emitter_enabled": "on"}, "emitter_enabled"),
        ({"serial": ""}, "serial"),
    ):
        with pytest.raises(ConfigError, match=match):
            RealSenseConfig(**kwargs)


def test_frame_assembly_units_and_channel_order() -> None:
    K = CameraIntrinsics.from_fov(4, 3, 60.0)
    bgr = np.zeros((3, 4, 3), np.uint8)
    bgr[..., 0] = 255  # blue in BGR
    depth = np.array([[0, 1, 5500, 65535]] * 3, np.uint16)
    frame = realsense_frame(bgr, "bgr8", depth, 0.0001, K, 12.5)
    assert frame.rgb[0, 0].tolist() == [0, 0, 255] and frame.timestamp_s == 12.5
    np.testing.assert_allclose(frame.depth_m[0], [0.0, 0.0001, 0.55, 6.5535], rtol=1e-6)
    assert np.count_nonzero(frame.depth_m == 0) == 3
    with pytest.raises(RealSenseError, match="colour format 'yuyv'"):
        realsense_frame(bgr, "yuyv", depth, 0.001, K, 0.0)
    with pytest.raises(RealSenseError, match="do not match the colour stream's 4x3"):
        realsense_frame(bgr, "rgb8", depth[:, :3], 0.001, K, 0.0)
    with pytest.raises(ValueError, match="uint16"):
        depth_units_to_m(depth.astype(np.float32), 0.001)


def test_depth_frame_z_is_re_expressed_along_the_colour_axis() -> None:
    """``rs.align`` keeps each point's depth-camera z; ``colour_camera_depth`` returns its colour-camera z."""
    K = RIG.color
    T_color_depth = np.linalg.inv(RIG.T_depth_color)
    rng = np.random.default_rng(3)
    u, v = rng.integers(0, K.width, 50), rng.integers(0, K.height, 50)
    z_color = rng.uniform(0.3, 1.5, 50)
    p_color = np.stack([(u - K.cx) / K.fx * z_color, (v - K.cy) / K.fy * z_color, z_color], axis=1)
    p_depth = (p_color - T_color_depth[:3, 3]) @ T_color_depth[:3, :3]  # R^T (p - t), row-wise
    aligned = np.zeros((K.height, K.width), np.float32)
    aligned[v, u] = p_depth[:, 2]
    out = colour_camera_depth(aligned, K, T_color_depth)
    np.testing.assert_allclose(out[v, u], z_color, atol=2e-6)  # float32 depth
    assert np.abs(p_depth[:, 2] - z_color).max() > 0.001  # the correction is not negligible for this rig
    assert np.count_nonzero(out) == np.count_nonzero(aligned)


def test_no_device_gives_a_clear_error(tmp_path: Path) -> None:
    empty = rs.context()
    if len(empty.query_devices()):
        pytest.skip("a RealSense device is connected to this machine")
    with pytest.raises(RealSenseNotFoundError, match=r"looked for serial '817612345678'.*devices seen: none") as info:
        RealSenseCamera(RealSenseConfig(serial="817612345678"))
    assert isinstance(info.value, SygridError)
    with pytest.raises(RealSenseNotFoundError, match="looked for any device"):
        RealSenseCamera()
    with pytest.raises(RealSenseError, match=r"recording .*missing\.db3 does not exist"):
        RealSenseCamera(RealSenseConfig(recording=str(tmp_path / "missing.db3")))
