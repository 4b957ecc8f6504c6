"""The Luxonis OAK camera through depthai v3: RGB plus stereo depth aligned to RGB, as ``Frame``s.

Pipeline (``OakCamera`` builds it from ``plan_pipeline``): a ``Camera`` node on the colour socket (CAM_A) gives
undistorted BGR frames of ``rgb_size``; two ``Camera`` nodes on the stereo sockets (CAM_B, CAM_C) feed a
``StereoDepth`` node (left-right check on, which depth alignment needs); the depth is aligned to the colour camera
on the device: by ``StereoDepth.setDepthAlign(CAM_A)`` with ``setOutputSize(rgb_size)`` on RVC2 devices (OAK-D,
OAK-D Pro, ...), by an ``ImageAlign`` node on RVC4 (OAK4), as Luxonis' depth-align examples do. A ``Sync`` node
pairs colour and depth frames taken within half a frame period.

Frames: RGB uint8 (H, W, 3); depth float32 metres along the colour camera's z axis (the device gives uint16
millimetres; 0 stays "no data"); intrinsics from the device's calibration (``readCalibration()``, the colour socket
at ``rgb_size``, centre-cropped to its aspect ratio as the ``Camera`` node's default resize mode does), without
distortion because the colour output is undistorted on the device. ``timestamp_s`` is the frame's capture time in
seconds: by default on depthai's host clock (device time converted by depthai's clock sync to ``dai.Clock``, a
steady clock: ``time.monotonic()`` on Linux), or the raw device clock with ``timestamp_clock="device"``.
``capture`` returns a frame whose timestamp is not older than the call, so a picture taken after the robot stopped
shows it stopped.

Without a device: ``OakCamera`` raises ``OakNotFoundError`` naming what it looked for and what depthai sees.
``OakFrameSource`` (the host side of ``capture``) reads any queue of synced groups, so with ``sync_queue`` it runs in
a host-only pipeline fed by host nodes (the tests do); the device nodes (``_device_streams``) need a device.
depthai is imported on first use (importing it searches for USB support and logs about it).
"""

from __future__ import annotations

import importlib
import logging
import time
from dataclasses import dataclass
from datetime import timedelta
from types import ModuleType
from typing import Any, Literal

import numpy as np

from perception.camera import Camera, Frame
from sygrid.camera import CameraIntrinsics
from sygrid.errors import ConfigError, SygridError

log = logging.getLogger(__name__)

RGB_SOCKET = "CAM_A"
LEFT_SOCKET, RIGHT_SOCKET = "CAM_B", "CAM_C"
#: Platforms whose depth alignment this module knows: RVC2 (StereoDepth aligns), RVC4 (ImageAlign node).
SUPPORTED_PLATFORMS = ("RVC2", "RVC4")
STEREO_PRESETS = ("DEFAULT", "ROBOTICS", "HIGH_DETAIL", "ACCURACY", "DENSITY", "FAST_ACCURACY", "FAST_DENSITY")


class OakError(SygridError, RuntimeError):
    """The OAK camera failed: connection, pipeline or frame trouble. The message says which."""


class OakNotFoundError(OakError):
    """No OAK device answered. The message names what was looked for and the devices depthai sees."""


@dataclass(frozen=True)
class OakConfig:
    """What the OAK camera delivers. ``device``: a device id (MxId), an IP address (PoE) or a USB port name; None
    takes the first device found. ``rgb_size``: width, height of the frames (RGB and aligned depth);
    ``stereo_size``: resolution of the stereo pair fed to the depth engine; ``stereo_preset``: a
    ``StereoDepth.PresetMode`` name. Timeouts in seconds."""

    device: str | None = None
    rgb_size: tuple[int, int] = (1280, 720)
    stereo_size: tuple[int, int] = (640, 400)
    fps: float = 15.0
    stereo_preset: str = "ROBOTICS"
    search_timeout_s: float = 3.0
    frame_timeout_s: float = 2.0
    timestamp_clock: Literal["host", "device"] = "host"

    def __post_init__(self) -> None:
        for name in ("rgb_size", "stereo_size"):
            size = getattr(self, name)
            if len(size) != 2 or not all(isinstance(v, int) and 16 <= v <= 8192 for v in size):
                raise ConfigError(f"OakConfig.{name} must be (width, height) integers in [16, 8192], got {size}")
        if self.rgb_size[0] % 16:
            # RVC2's aligned depth output needs a width that is a multiple of 16.
            raise ConfigError(f"OakConfig.rgb_size width must be a multiple of 16, got {self.rgb_size[0]}")
        if not 1.0 <= self.fps <= 60.0:
            raise ConfigError(f"OakConfig.fps must be in [1, 60], got {self.fps}")
        if self.stereo_preset not in STEREO_PRESETS:
            raise ConfigError(f"OakConfig.stereo_preset {self.stereo_preset!r} is not one of {list(STEREO_PRESETS)}")
        for name in ("search_timeout_s", "frame_timeout_s"):
            if not 0.0 < getattr(self, name) <= 60.0:
                raise ConfigError(f"OakConfig.{name} must be in (0, 60] s, got {getattr(self, name)}")
        if self.timestamp_clock not in ("host", "device"):
            raise ConfigError(f"OakConfig.timestamp_clock must be 'host' or 'device', got {self.timestamp_clock!r}")


@dataclass(frozen=True)
class OakPipelinePlan:
    """The pipeline ``OakCamera`` builds for a platform, resolved from an ``OakConfig`` before touching a device."""

    platform: str
    rgb_size: tuple[int, int]
    stereo_size: tuple[int, int]
    fps: float
    stereo_preset: str
    #: "stereo_depth": StereoDepth aligns to CAM_A itself (RVC2); "image_align": an ImageAlign node does (RVC4).
    depth_alignment: Literal["stereo_depth", "image_align"]
    sync_threshold_s: float


def plan_pipeline(config: OakConfig, platform: str) -> OakPipelinePlan:
    """The pipeline for ``platform`` ("RVC2", "RVC4"); OakError for a platform whose alignment is unknown here."""
    if platform not in SUPPORTED_PLATFORMS:
        raise OakError(
            f"OAK platform {platform!r} is not supported (depth alignment is known for {list(SUPPORTED_PLATFORMS)})"
        )
    return OakPipelinePlan(
        platform=platform,
        rgb_size=config.rgb_size,
        stereo_size=config.stereo_size,
        fps=config.fps,
        stereo_preset=config.stereo_preset,
        depth_alignment="stereo_depth" if platform == "RVC2" else "image_align",
        sync_threshold_s=0.5 / config.fps,
    )


# ---------------------------------------------------------------------------------------------- pure conversions


def oak_intrinsics(calibration: Any, socket: str, width: int, height: int) -> CameraIntrinsics:
    """``CameraIntrinsics`` of ``socket``'s frames at ``width`` x ``height`` from a ``dai.CalibrationHandler``:
    depthai scales the calibrated matrix to the output width or height and centre-crops the other side
    (``keepAspectRatio``), which is what the ``Camera`` node's default CROP resize does. OakError when the
    calibration has no data for the socket."""
    dai = _dai()
    try:
        K = np.array(calibration.getCameraIntrinsics(getattr(dai.CameraBoardSocket, socket), width, height), float)
    except RuntimeError as err:
        raise OakError(f"the OAK calibration has no intrinsics for socket {socket}: {err}") from None
    if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise OakError(f"the OAK calibration gave an invalid intrinsic matrix for socket {socket}: {K.tolist()}")
    return CameraIntrinsics.from_K(K, width, height)


def depth_mm_to_m(depth_mm: np.ndarray) -> np.ndarray:
    """The device's uint16 depth in millimetres -> float32 metres (0 = no data stays 0)."""
    depth_mm = np.asarray(depth_mm)
    if depth_mm.dtype != np.uint16 or depth_mm.ndim != 2:
        raise ValueError(f"depth must be a (H, W) uint16 image in millimetres, got {depth_mm.dtype} {depth_mm.shape}")
    return depth_mm.astype(np.float32) * np.float32(0.001)


# ---------------------------------------------------------------------------------------------- the camera


class OakCamera(Camera):
    """An OAK device as a ``Camera``. Connects and starts the pipeline in the constructor."""

    def __init__(self, config: OakConfig | None = None) -> None:
        self.config = config if config is not None else OakConfig()
        dai = _dai()
        self._closed = False
        self._device = _open_device(dai, self.config)
        try:
            platform = self._device.getPlatformAsString()
            self.plan = plan_pipeline(self.config, platform)
            calibration = self._device.readCalibration()
            self._intrinsics = oak_intrinsics(calibration, RGB_SOCKET, *self.config.rgb_size)
            self._pipeline = dai.Pipeline(self._device)
            queue = _build_pipeline(dai, self._pipeline, self.plan)
            self._pipeline.start()
        except Exception:
            self._device.close()
            raise
        self._source = OakFrameSource(queue, self._intrinsics, self.config, dai.Clock, f"OAK {self.device_id}")
        log.info(
            "OAK %s (%s) started: %dx%d RGB-D at %.0f fps, depth aligned by %s",
            self.device_id,
            platform,
            *self.config.rgb_size,
            self.config.fps,
            self.plan.depth_alignment,
        )

    @property
    def intrinsics(self) -> CameraIntrinsics:
        return self._intrinsics

    @property
    def device_id(self) -> str:
        return str(self._device.getDeviceId())

    def capture(self) -> Frame:
        if self._closed:
            raise OakError("the OAK camera is closed")
        return self._source.next_frame()

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        try:
            self._pipeline.stop()
        finally:
            self._device.close()


class OakFrameSource:
    """The host end of the pipeline: synced colour + depth ``dai.MessageGroup``s (members "rgb": BGR888i of the
    intrinsics' size, "depth": uint16 millimetres of the same size) from a depthai output ``queue`` as ``Frame``s.
    ``clock``: depthai's host clock (``dai.Clock``), the clock of the messages' host timestamps; ``name`` names the
    camera in errors. ``next_frame`` drops the groups queued before the call and returns the first whose colour frame
    was taken at or after the call, within ``config.frame_timeout_s``."""

    def __init__(self, queue: Any, intrinsics: CameraIntrinsics, config: OakConfig, clock: Any, name: str) -> None:
        self._queue, self._intrinsics, self.config, self._clock, self.name = queue, intrinsics, config, clock, name
        self._checked_transformation = False

    def next_frame(self) -> Frame:
        t_call_s = self._clock.now().total_seconds()
        deadline = time.monotonic() + self.config.frame_timeout_s
        self._queue.tryGetAll()  # frames queued before the call are stale
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise OakError(
                    f"no RGB-D frame from {self.name} within {self.config.frame_timeout_s} s "
                    "(device disconnected, or the pipeline stalled)"
                )
            group = self._queue.get(timedelta(seconds=remaining))
            if group is None:
                continue
            rgb_msg, depth_msg = group["rgb"], group["depth"]
            if rgb_msg.getTimestamp().total_seconds() >= t_call_s:
                break
        return self._to_frame(rgb_msg, depth_msg)

    def _to_frame(self, rgb_msg: Any, depth_msg: Any) -> Frame:
        w, h = self._intrinsics.width, self._intrinsics.height
        bgr = rgb_msg.getCvFrame()
        depth_mm = depth_msg.getFrame()
        if bgr.shape != (h, w, 3) or depth_mm.shape != (h, w):
            raise OakError(
                f"{self.name} frames do not match the requested {w}x{h}: RGB {bgr.shape}, depth {depth_mm.shape} "
                "(depth alignment to the colour camera failed?)"
            )
        if not self._checked_transformation:
            self._check_transformation(rgb_msg)
        stamp = rgb_msg.getTimestamp() if self.config.timestamp_clock == "host" else rgb_msg.getTimestampDevice()
        return Frame(
            rgb=np.ascontiguousarray(bgr[:, :, ::-1]),
            depth_m=depth_mm_to_m(depth_mm),
            intrinsics=self._intrinsics,
            timestamp_s=stamp.total_seconds(),
        )

    def _check_transformation(self, rgb_msg: Any) -> None:
        """Compares the calibration's intrinsics with those the frame itself carries (its ``ImgTransformation``,
        which knows every crop and scale on the device) once, and warns when they disagree."""
        self._checked_transformation = True
        try:
            K_frame = np.array(rgb_msg.getTransformation().getIntrinsicMatrix(), dtype=float)
        except (AttributeError, RuntimeError):
            return
        if K_frame.shape == (3, 3) and np.abs(K_frame - self._intrinsics.K).max() > 1.0:
            log.warning(
                "%s colour intrinsics from the calibration %s differ by more than 1 px from the frame's own %s",
                self.name,
                np.round(self._intrinsics.K, 2).tolist(),
                np.round(K_frame, 2).tolist(),
            )


def _dai() -> ModuleType:
    return importlib.import_module("depthai")


def _open_device(dai: ModuleType, config: OakConfig) -> Any:
    """Finds and opens the device, or raises OakNotFoundError naming what was looked for."""
    wanted = config.device
    looked_for = f"OAK device {wanted!r} (device id, IP address or USB name)" if wanted else "any OAK device"
    infos = _search(dai, config.search_timeout_s)
    seen = [f"{i.getDeviceId()} ({i.name}, {i.state.name})" for i in infos]
    if wanted is None:
        chosen = infos[0] if infos else None
    else:
        chosen = next((i for i in infos if wanted in (i.getDeviceId(), i.name)), None)
        if chosen is None and _is_ipv4(wanted):
            chosen = dai.DeviceInfo(wanted)  # PoE devices on another subnet answer to a direct connection only
    if chosen is None:
        raise OakNotFoundError(
            f"no OAK camera found: looked for {looked_for} over USB and TCP/IP for {config.search_timeout_s} s "
            f"with depthai {dai.__version__}; devices seen: {', '.join(seen) if seen else 'none'}. Check the cable "
            "or power, the USB udev rules, or the network for a PoE camera"
        )
    try:
        return dai.Device(chosen)
    except RuntimeError as err:
        raise OakNotFoundError(f"could not open {looked_for} at {chosen.getDeviceId() or wanted}: {err}") from None


def _search(dai: ModuleType, timeout_s: float) -> list[Any]:
    """Every device depthai sees, waiting up to ``timeout_s`` for the first one (a PoE camera may take a moment)."""
    deadline = time.monotonic() + timeout_s
    while True:
        infos = list(dai.Device.getAllAvailableDevices())
        if infos or time.monotonic() >= deadline:
            return infos
        time.sleep(0.2)


def _is_ipv4(name: str) -> bool:
    parts = name.split(".")
    return len(parts) == 4 and all(p.isdigit() and 0 <= int(p) <= 255 for p in parts)


def _build_pipeline(dai: ModuleType, pipeline: Any, plan: OakPipelinePlan) -> Any:
    """Creates the nodes of ``plan`` in ``pipeline`` (which needs its device) and returns the synced output queue."""
    rgb_out, depth_out = _device_streams(dai, pipeline, plan)
    return sync_queue(dai, pipeline, rgb_out, depth_out, plan)


def _device_streams(dai: ModuleType, pipeline: Any, plan: OakPipelinePlan) -> tuple[Any, Any]:
    """The device nodes: the colour output and the depth aligned to it (``Node.Output``s). depthai creates these
    nodes only in a pipeline that has a device."""
    rgb_socket = getattr(dai.CameraBoardSocket, RGB_SOCKET)
    camera = pipeline.create(dai.node.Camera).build(rgb_socket)
    rgb_out = camera.requestOutput(plan.rgb_size, type=dai.ImgFrame.Type.BGR888i, fps=plan.fps, enableUndistortion=True)
    left = pipeline.create(dai.node.Camera).build(getattr(dai.CameraBoardSocket, LEFT_SOCKET))
    right = pipeline.create(dai.node.Camera).build(getattr(dai.CameraBoardSocket, RIGHT_SOCKET))
    stereo = pipeline.create(dai.node.StereoDepth).build(
        left.requestOutput(plan.stereo_size, fps=plan.fps),
        right.requestOutput(plan.stereo_size, fps=plan.fps),
        presetMode=getattr(dai.node.StereoDepth.PresetMode, plan.stereo_preset),
    )
    stereo.setLeftRightCheck(True)  # depth alignment needs it, and it removes occlusion artefacts
    # Depth is aligned to the colour camera on the device in both branches (StereoDepth re-projects into CAM_A at
    # rgb_size; ImageAlign warps depth onto rgb_out's frames), so the host gets depth pixel-for-pixel with RGB and
    # does no registration of its own (``OakFrameSource`` checks the sizes match).
    if plan.depth_alignment == "stereo_depth":
        stereo.setDepthAlign(rgb_socket)
        stereo.setOutputSize(*plan.rgb_size)
        return rgb_out, stereo.depth
    align = pipeline.create(dai.node.ImageAlign)
    stereo.depth.link(align.input)
    rgb_out.link(align.inputAlignTo)
    return rgb_out, align.outputAligned


def sync_queue(dai: ModuleType, pipeline: Any, rgb_out: Any, depth_out: Any, plan: OakPipelinePlan) -> Any:
    """A ``Sync`` node pairing ``rgb_out`` and ``depth_out`` messages taken within ``plan.sync_threshold_s`` (group
    members "rgb" and "depth"; on the pipeline's device, or on the host in a pipeline without one), and its
    non-blocking host queue of the 4 newest groups (``OakFrameSource`` reads it)."""
    sync = pipeline.create(dai.node.Sync)
    sync.setRunOnHost(pipeline.getDefaultDevice() is None)  # on the device when there is one
    sync.setSyncThreshold(timedelta(seconds=plan.sync_threshold_s))
    rgb_out.link(sync.inputs["rgb"])
    depth_out.link(sync.inputs["depth"])
    return sync.out.createOutputQueue(maxSize=4, blocking=False)
