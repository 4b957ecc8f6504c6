"""The Intel RealSense D435 / D435i through pyrealsense2: colour plus depth aligned to colour, as ``Frame``s.

Streams: colour as RGB8 at ``rgb_size`` and depth as Z16 at ``depth_size``, both at ``fps``, from the device with
``serial`` (the first one found when None). The depth is re-projected into the colour camera on the host by the
SDK's ``rs.align(rs.stream.color)`` (depth pixel -> 3-D point with the depth intrinsics and depth units -> colour
camera with the device's depth-to-colour extrinsics -> colour pixel); pixels the depth camera does not see from its
own viewpoint stay 0. The SDK keeps each depth pixel's value, the z of the point in the *depth* camera's frame, so
``colour_camera_depth`` turns it into the z along the colour camera's axis with the same extrinsics (they differ by
the small rotation and the z offset between the two cameras: millimetres across the image).

Device settings, applied to the depth sensor at start in this order (a preset rewrites the others):
``visual_preset`` (an ``rs.rs400_visual_preset`` name), ``emitter_enabled`` (the IR projector), ``laser_power_mw``
(None: whatever the preset set). An option the sensor lacks, or a value outside its range, is an error.

Frames: RGB uint8 (H, W, 3); depth float32 metres along the colour camera's z axis: the Z16 units times the depth
sensor's own depth scale (``get_depth_scale()``, metres per unit; 0 stays "no data"); intrinsics from the colour
stream profile, which the aligned depth shares. Lens distortion is not modelled by ``CameraIntrinsics``: a colour
profile with non-zero distortion coefficients is logged as a warning. ``timestamp_s`` is the colour frame's
timestamp in seconds in the frame's own clock: the host's wall clock (``time.time()``) when the frame's domain is
``global_time`` or ``system_time`` (the D400 default), the device clock otherwise. With a host clock, ``capture``
returns a frame whose colour timestamp is not older than the call; it never returns the same colour frame twice.

Playback (``recording``: a file written by the SDK's recorder, ``.bag`` or ``.db3`` by SDK version): the streams
and options are the recorded ones (device options cannot be changed in a recording), frames come one set per
``capture`` in recorded order (not in real time; a colour frame the SDK's syncer delivers without its depth frame is
skipped), and the end of the recording raises ``RealSenseError``.

Without a device: ``RealSenseCamera`` raises ``RealSenseNotFoundError`` naming the serial looked for and the
devices the SDK sees. pyrealsense2 is imported on first use.
"""

from __future__ import annotations

import datetime
import functools
import importlib
import logging
import time
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

from perception.camera import Camera, Frame
from sygrid.camera import CameraIntrinsics
from sygrid.errors import ConfigError, SygridError

log = logging.getLogger(__name__)

#: ``rs.rs400_visual_preset`` names (the D400 depth presets).
VISUAL_PRESETS = (
    "custom", "default", "hand", "high_accuracy", "high_density", "medium_density", "remove_ir_pattern",
)  # fmt: skip
#: Frame rates the D435 streams at (its depth and colour modes list these).
FRAME_RATES = (6, 15, 30, 60, 90)
#: Timestamp domains on the host's wall clock (``time.time()``), where ``capture`` can tell a frame's age.
_HOST_CLOCK_DOMAINS = ("global_time", "system_time")


class RealSenseError(SygridError, RuntimeError):
    """The RealSense camera failed: connection, stream configuration, option or frame trouble. The message says
    which."""


class RealSenseNotFoundError(RealSenseError):
    """No RealSense device with the wanted serial. The message names it and the devices the SDK sees."""


@dataclass(frozen=True)
class RealSenseConfig:
    """What the RealSense camera delivers. ``serial``: the device's serial number (None: the first device found);
    ``rgb_size``/``depth_size``: width, height of the colour and depth streams (the frames are ``rgb_size``: depth
    is aligned to colour); ``fps``: one of ``FRAME_RATES``; ``visual_preset``: one of ``VISUAL_PRESETS``;
    ``emitter_enabled``: the IR projector on or off; ``laser_power_mw``: the projector's power (None: the preset's);
    ``frame_timeout_s``: the longest ``capture`` waits; ``recording``: a file recorded by the SDK to play instead of a
    device (the streams and options are then the recorded ones)."""

    serial: str | None = None
    rgb_size: tuple[int, int] = (1280, 720)
    depth_size: tuple[int, int] = (848, 480)
    fps: int = 15
    visual_preset: str = "default"
    emitter_enabled: bool = True
    laser_power_mw: float | None = None
    frame_timeout_s: float = 2.0
    recording: str | None = None

    def __post_init__(self) -> None:
        if self.serial is not None and (not isinstance(self.serial, str) or not self.serial):
            raise ConfigError(f"RealSenseConfig.serial must be a non-empty string or None, got {self.serial!r}")
        for name in ("rgb_size", "depth_size"):
            size = getattr(self, name)
            if len(size) != 2 or not all(isinstance(v, int) and 16 <= v <= 4096 for v in size):
                raise ConfigError(f"RealSenseConfig.{name} must be (width, height) integers in [16, 4096], got {size}")
        if self.fps not in FRAME_RATES:
            raise ConfigError(f"RealSenseConfig.fps must be one of {list(FRAME_RATES)}, got {self.fps!r}")
        if self.visual_preset not in VISUAL_PRESETS:
            raise ConfigError(
                f"RealSenseConfig.visual_preset {self.visual_preset!r} is not one of {list(VISUAL_PRESETS)}"
            )
        if not isinstance(self.emitter_enabled, bool):
            raise ConfigError(f"RealSenseConfig.emitter_enabled must be true or false, got {self.emitter_enabled!r}")
        if self.laser_power_mw is not None and not (
            isinstance(self.laser_power_mw, int | float) and 0 <= self.laser_power_mw <= 1000
        ):
            raise ConfigError(
                f"RealSenseConfig.laser_power_mw must be in [0, 1000] mW or None, got {self.laser_power_mw}"
            )
        if not 0.0 < self.frame_timeout_s <= 60.0:
            raise ConfigError(f"RealSenseConfig.frame_timeout_s must be in (0, 60] s, got {self.frame_timeout_s}")


# ---------------------------------------------------------------------------------------------- pure conversions


def realsense_intrinsics(video_profile: Any) -> CameraIntrinsics:
    """``CameraIntrinsics`` of an ``rs.video_stream_profile`` (fx, fy, ppx, ppy at its width x height). A profile
    with non-zero distortion coefficients is logged as a warning (``CameraIntrinsics`` models none)."""
    i = video_profile.get_intrinsics()
    if max((abs(c) for c in i.coeffs), default=0.0) > 0.0:
        log.warning(
            "RealSense %s stream has %s distortion %s, which the pipeline does not model (it assumes an "
            "undistorted image)",
            video_profile.stream_type(),
            i.model,
            [round(c, 5) for c in i.coeffs],
        )
    if not (i.fx > 0 and i.fy > 0 and i.width > 0 and i.height > 0):
        raise RealSenseError(f"the RealSense colour profile has invalid intrinsics: {i}")
    return CameraIntrinsics(float(i.fx), float(i.fy), float(i.ppx), float(i.ppy), int(i.width), int(i.height))


def depth_units_to_m(depth: np.ndarray, depth_scale_m: float) -> np.ndarray:
    """The device's Z16 depth (uint16 units of ``depth_scale_m`` metres) -> float32 metres (0 = no data stays 0)."""
    depth = np.asarray(depth)
    if depth.dtype != np.uint16 or depth.ndim != 2:
        raise ValueError(f"depth must be a (H, W) uint16 image of depth units, got {depth.dtype} {depth.shape}")
    if not (np.isfinite(depth_scale_m) and 0.0 < depth_scale_m < 1.0):
        raise ValueError(f"depth_scale_m must be in (0, 1) metres per unit, got {depth_scale_m}")
    return depth.astype(np.float32) * np.float32(depth_scale_m)


def colour_camera_depth(depth_z_m: np.ndarray, intrinsics: CameraIntrinsics, T_color_depth: np.ndarray) -> np.ndarray:
    """Depth aligned to the colour image but holding each point's z in the depth camera's frame (what ``rs.align``
    writes) -> float32 z along the colour camera's axis (0 stays 0). ``T_color_depth``: the depth camera's frame in
    the colour camera's (``p_color = R p_depth + t``). A point on the colour pixel's ray ``s * r`` has depth-frame z
    ``s * (R^T r)_z - (R^T t)_z``, so ``s = (z_depth + (R^T t)_z) / (R^T r)_z``."""
    R, t = np.asarray(T_color_depth)[:3, :3], np.asarray(T_color_depth)[:3, 3]
    inv_along = _inverse_ray_z(intrinsics, tuple(float(x) for x in R[:, 2]))
    z = (depth_z_m + np.float32(R[:, 2] @ t)) * inv_along
    return np.where(depth_z_m > 0, z, np.float32(0.0)).astype(np.float32, copy=False)


@functools.lru_cache(maxsize=4)
def _inverse_ray_z(K: CameraIntrinsics, r_col2: tuple[float, float, float]) -> np.ndarray:
    """1 / (R^T r)_z per pixel, with r = ((u - cx) / fx, (v - cy) / fy, 1) and ``r_col2`` = R's third column."""
    v, u = np.mgrid[0 : K.height, 0 : K.width]
    along = r_col2[0] * (u - K.cx) / K.fx + r_col2[1] * (v - K.cy) / K.fy + r_col2[2]
    out = (1.0 / along).astype(np.float32)
    out.flags.writeable = False
    return out


def realsense_frame(
    color: np.ndarray,
    color_format: str,
    depth: np.ndarray,
    depth_scale_m: float,
    intrinsics: CameraIntrinsics,
    timestamp_s: float,
    T_color_depth: np.ndarray | None = None,
) -> Frame:
    """A ``Frame`` from an aligned colour image (``color_format`` "rgb8" or "bgr8", (H, W, 3) uint8) and the depth
    aligned to it (Z16 units of ``depth_scale_m``, depth-frame z re-expressed along the colour axis by
    ``colour_camera_depth`` when ``T_color_depth`` is given); ``RealSenseError`` when their sizes disagree with
    ``intrinsics``."""
    w, h = intrinsics.width, intrinsics.height
    if color.shape != (h, w, 3) or depth.shape != (h, w):
        raise RealSenseError(
            f"RealSense frames do not match the colour stream's {w}x{h}: colour {color.shape}, aligned depth "
            f"{depth.shape}"
        )
    if color_format == "bgr8":
        color = color[:, :, ::-1]
    elif color_format != "rgb8":
        raise RealSenseError(f"RealSense colour format {color_format!r} is not supported (rgb8 or bgr8)")
    depth_m = depth_units_to_m(depth, depth_scale_m)
    if T_color_depth is not None:
        depth_m = colour_camera_depth(depth_m, intrinsics, T_color_depth)
    return Frame(
        rgb=np.ascontiguousarray(color, dtype=np.uint8),
        depth_m=depth_m,
        intrinsics=intrinsics,
        timestamp_s=float(timestamp_s),
    )


def apply_depth_options(sensor: Any, config: RealSenseConfig) -> dict[str, float]:
    """Sets the visual preset, the emitter and the laser power (when given) on a depth sensor, in that order, and
    returns the values read back by option name. ``RealSenseError`` naming the option when the sensor lacks it or
    the value is outside its range."""
    rs = _rs()
    preset = int(getattr(rs.rs400_visual_preset, config.visual_preset))
    settings: list[tuple[str, float]] = [
        ("visual_preset", float(preset)),
        ("emitter_enabled", float(config.emitter_enabled)),
    ]
    if config.laser_power_mw is not None:
        settings.append(("laser_power", float(config.laser_power_mw)))
    read_back: dict[str, float] = {}
    for name, value in settings:
        option = getattr(rs.option, name)
        if not sensor.supports(option):
            raise RealSenseError(f"the RealSense depth sensor has no {name} option (is it a D400 camera?)")
        bounds = sensor.get_option_range(option)
        if not bounds.min <= value <= bounds.max:
            raise RealSenseError(
                f"RealSense {name} {value:g} is outside the sensor's range [{bounds.min:g}, {bounds.max:g}]"
            )
        try:
            sensor.set_option(option, value)
        except RuntimeError as err:
            raise RealSenseError(f"could not set the RealSense {name} to {value:g}: {err}") from None
        read_back[name] = float(sensor.get_option(option))
    return read_back


# ---------------------------------------------------------------------------------------------- the camera


class RealSenseCamera(Camera):
    """A RealSense D400 device (or a recording of one) as a ``Camera``. Starts streaming in the constructor.
    ``context``: the ``rs.context`` to look for devices in (default: a new one)."""

    def __init__(self, config: RealSenseConfig | None = None, context: Any = None) -> None:
        self.config = cfg = config if config is not None else RealSenseConfig()
        rs = _rs()
        self._closed = False
        self._pipeline = rs.pipeline(context) if context is not None else rs.pipeline()
        rs_config = rs.config()
        if cfg.recording is not None:
            path = Path(cfg.recording)
            if not path.is_file():
                raise RealSenseError(f"RealSense recording {path} does not exist")
            rs_config.enable_device_from_file(str(path), repeat_playback=False)
            rs_config.enable_stream(rs.stream.depth)
            rs_config.enable_stream(rs.stream.color)
            self.source = f"recording {path}"
        else:
            serial = _find_serial(rs, context if context is not None else rs.context(), cfg.serial)
            rs_config.enable_device(serial)
            rs_config.enable_stream(rs.stream.depth, *cfg.depth_size, rs.format.z16, cfg.fps)
            rs_config.enable_stream(rs.stream.color, *cfg.rgb_size, rs.format.rgb8, cfg.fps)
            self.source = f"RealSense {serial}"
        try:
            profile = self._pipeline.start(rs_config)
        except RuntimeError as err:
            raise RealSenseError(
                f"{self.source} would not stream depth {cfg.depth_size} Z16 and colour {cfg.rgb_size} RGB8 at "
                f"{cfg.fps} fps: {err}"
            ) from None
        try:
            device = profile.get_device()
            self.playing_back = bool(device.is_playback())
            depth_sensor = device.first_depth_sensor()
            self.options: dict[str, float] = {}
            if self.playing_back:
                # Every recorded frame, in order, at the reader's pace; playback starts with the pipeline, in real
                # time, so frames played before this line may be gone: rewind to the start.
                playback = device.as_playback()
                playback.set_real_time(False)
                playback.seek(datetime.timedelta(0))
            else:
                self.options = apply_depth_options(depth_sensor, cfg)
            self.depth_scale_m = float(depth_sensor.get_depth_scale())
            color_profile = profile.get_stream(rs.stream.color).as_video_stream_profile()
            self._intrinsics = realsense_intrinsics(color_profile)
            extrinsics = profile.get_stream(rs.stream.depth).get_extrinsics_to(color_profile)
            self.T_color_depth = np.eye(4)
            self.T_color_depth[:3, :3] = np.reshape(extrinsics.rotation, (3, 3)).T  # the SDK's is column-major
            self.T_color_depth[:3, 3] = extrinsics.translation
            self._color_format = color_profile.format().name
            self._align = rs.align(rs.stream.color)
            self._last_color_number: int | None = None
        except Exception:
            self._pipeline.stop()
            raise
        log.info(
            "%s started: %dx%d RGB + aligned depth (scale %.6g m/unit) at %s fps%s",
            self.source,
            self._intrinsics.width,
            self._intrinsics.height,
            self.depth_scale_m,
            color_profile.fps(),
            "" if self.playing_back else f", options {self.options}",
        )

    @property
    def intrinsics(self) -> CameraIntrinsics:
        return self._intrinsics

    def capture(self) -> Frame:
        if self._closed:
            raise RealSenseError(f"the {self.source} camera is closed")
        t_call_ms = time.time() * 1000.0
        deadline = time.monotonic() + self.config.frame_timeout_s
        if not self.playing_back:
            self._pipeline.poll_for_frames()  # drops the frames queued before the call
        while True:
            remaining_ms = int(1000 * (deadline - time.monotonic()))
            ok, frames = self._pipeline.try_wait_for_frames(remaining_ms) if remaining_ms > 0 else (False, None)
            if not ok:
                if self.playing_back:
                    raise RealSenseError(f"{self.source} has no more frames")
                raise RealSenseError(
                    f"no colour + depth frame from {self.source} within {self.config.frame_timeout_s} s "
                    "(device disconnected, or a USB 2 port too slow for the streams?)"
                )
            aligned = self._align.process(frames)
            color, depth = aligned.get_color_frame(), aligned.get_depth_frame()
            if not color or not depth or color.get_frame_number() == self._last_color_number:
                continue  # a set without both, or one repeating the colour frame already returned
            stamp_ms = color.get_timestamp()
            on_host_clock = color.get_frame_timestamp_domain().name in _HOST_CLOCK_DOMAINS
            if self.playing_back or not on_host_clock or stamp_ms >= t_call_ms:
                break
        self._last_color_number = color.get_frame_number()
        return realsense_frame(
            np.asanyarray(color.get_data()),
            self._color_format,
            np.asanyarray(depth.get_data()),
            self.depth_scale_m,
            self._intrinsics,
            stamp_ms / 1000.0,
            self.T_color_depth,
        )

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self._pipeline.stop()


def _rs() -> ModuleType:
    try:
        return importlib.import_module("pyrealsense2")
    except ImportError as err:
        raise RealSenseError(f"the RealSense camera needs pyrealsense2 (pip install pyrealsense2): {err}") from None


def _find_serial(rs: ModuleType, context: Any, wanted: str | None) -> str:
    """The serial of the device to open, or ``RealSenseNotFoundError`` naming what was looked for."""
    seen = {}
    for device in context.query_devices():
        serial = device.get_info(rs.camera_info.serial_number)
        name = device.get_info(rs.camera_info.name) if device.supports(rs.camera_info.name) else "?"
        seen[serial] = name
    if wanted is None and seen:
        return next(iter(seen))
    if wanted in seen:
        return wanted
    looked_for = f"serial {wanted!r}" if wanted else "any device"
    found = ", ".join(f"{s} ({n})" for s, n in seen.items()) or "none"
    raise RealSenseNotFoundError(
        f"no RealSense camera found: looked for {looked_for} with pyrealsense2 {getattr(rs, '__version__', '?')}; "
        f"devices seen: {found}. Check the USB 3 cable and port, and librealsense's udev rules"
    )
