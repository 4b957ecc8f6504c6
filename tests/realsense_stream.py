"""Test support for the RealSense camera without hardware: a synthetic scene seen by a D435-like pair of cameras
(depth and colour with their own intrinsics and a depth-to-colour transform), fed through the SDK's own
``rs.software_device`` and written by its ``rs.recorder``, so that ``perception.realsense.RealSenseCamera`` plays it
back through the real SDK (playback, alignment, depth units).

The scene, in the depth camera's frame (z forward, metres): a floor plane at ``FLOOR_Z_M`` and a box standing on it
whose top is at ``BOX_TOP_Z_M``; depth is ray-cast exactly (a ray hits the box, top or walls, before the floor).
"""

from __future__ import annotations

import gc
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sygrid.camera import CameraIntrinsics
from sygrid.transforms import invert, make_T

FLOOR_Z_M = 0.70
BOX_TOP_Z_M = 0.55
BOX_LO_M = np.array([-0.05, -0.04, BOX_TOP_Z_M])
BOX_HI_M = np.array([0.06, 0.05, FLOOR_Z_M])
SERIAL = "817612340001"
DEPTH_K = CameraIntrinsics(213.0, 213.0, 212.4, 119.6, 424, 240)  # wider than the colour camera, like a D435's
COLOR_K = CameraIntrinsics(462.0, 461.0, 318.7, 181.3, 640, 360)


def _rotation_y(deg: float) -> np.ndarray:
    a = np.radians(deg)
    return np.array([[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]])


@dataclass(frozen=True)
class StereoRig:
    """A D435-like rig at 15 fps: the depth camera (the scene's frame), the colour camera at ``T_depth_color``,
    ``depth_scale_m`` metres per Z16 unit."""

    depth: CameraIntrinsics = DEPTH_K
    color: CameraIntrinsics = COLOR_K
    T_depth_color: np.ndarray = field(default_factory=lambda: make_T(_rotation_y(0.5), (-0.0148, 0.0002, 0.0003)))
    depth_scale_m: float = 0.0001
    fps: int = 15


def raycast_depth(K: CameraIntrinsics, T_scene_camera: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(z along the camera's axis in metres, label: 0 floor, 1 box top, 2 box wall) per pixel of a camera."""
    v, u = np.mgrid[0 : K.height, 0 : K.width].astype(float)
    d_cam = np.stack([(u - K.cx) / K.fx, (v - K.cy) / K.fy, np.ones_like(u)], axis=-1)  # z = 1: t is the depth
    R, origin = T_scene_camera[:3, :3], T_scene_camera[:3, 3]
    d = d_cam @ R.T
    with np.errstate(divide="ignore", invalid="ignore"):
        t0 = (BOX_LO_M - origin) / d
        t1 = (BOX_HI_M - origin) / d
    t_near = np.nanmax(np.minimum(t0, t1), axis=-1)
    t_far = np.nanmin(np.maximum(t0, t1), axis=-1)
    hits_box = (t_near <= t_far) & (t_far > 0)
    t_floor = (FLOOR_Z_M - origin[2]) / d[..., 2]
    t = np.where(hits_box, t_near, t_floor)
    entry_axis = np.argmax(np.minimum(t0, t1), axis=-1)
    label = np.where(hits_box, np.where(entry_axis == 2, 1, 2), 0)
    return t, label


def colour_image(K: CameraIntrinsics, T_scene_camera: np.ndarray, marker: int = 0) -> np.ndarray:
    """The colour camera's RGB view: a grey checker floor (2 cm squares), a red box; pixel (0, 0) holds ``marker``."""
    t, label = raycast_depth(K, T_scene_camera)
    v, u = np.mgrid[0 : K.height, 0 : K.width].astype(float)
    d = np.stack([(u - K.cx) / K.fx, (v - K.cy) / K.fy, np.ones_like(u)], axis=-1) @ T_scene_camera[:3, :3].T
    p = T_scene_camera[:3, 3] + t[..., None] * d
    checker = ((np.floor(p[..., 0] / 0.02) + np.floor(p[..., 1] / 0.02)) % 2).astype(np.uint8)
    rgb = np.empty((K.height, K.width, 3), np.uint8)
    rgb[...] = (80 + 80 * checker)[..., None]
    rgb[label == 1] = (200, 30, 30)
    rgb[label == 2] = (120, 20, 20)
    rgb[0, 0] = (marker, 0, 0)
    return rgb


def _rs_intrinsics(rs, K: CameraIntrinsics):
    i = rs.intrinsics()
    i.width, i.height, i.fx, i.fy, i.ppx, i.ppy = K.width, K.height, K.fx, K.fy, K.cx, K.cy
    i.model, i.coeffs = rs.distortion.none, [0.0] * 5
    return i


class SoftwareD435:
    """An ``rs.software_device`` shaped like a D435 (``rs.option_range`` takes min, max, default, step): a "Stereo
    Module" (Z16 depth, depth units, visual preset,
    emitter, laser power options) and an "RGB Camera" (RGB8 colour), depth-to-colour extrinsics registered."""

    def __init__(self, rig: StereoRig = StereoRig(), serial: str = SERIAL) -> None:
        import pyrealsense2 as rs

        self.rs, self.rig = rs, rig
        self.device = dev = rs.software_device()
        dev.register_info(rs.camera_info.name, "Intel RealSense D435 (software device)")
        dev.register_info(rs.camera_info.serial_number, serial)
        dev.register_info(rs.camera_info.product_line, "D400")
        self.depth_sensor = dev.add_sensor("Stereo Module")
        self.color_sensor = dev.add_sensor("RGB Camera")
        self.depth_profile = self._add_stream(self.depth_sensor, rs.stream.depth, rs.format.z16, 2, rig.depth, 0)
        self.color_profile = self._add_stream(self.color_sensor, rs.stream.color, rs.format.rgb8, 3, rig.color, 1)
        self.depth_sensor.add_read_only_option(rs.option.depth_units, rig.depth_scale_m)
        self.depth_sensor.add_option(rs.option.visual_preset, rs.option_range(0, 6, 1, 1), True)
        self.depth_sensor.add_option(rs.option.emitter_enabled, rs.option_range(0, 1, 1, 1), True)
        self.depth_sensor.add_option(rs.option.laser_power, rs.option_range(0, 360, 150, 30), True)
        T_color_depth = invert(rig.T_depth_color)
        extrinsics = rs.extrinsics()
        extrinsics.rotation = T_color_depth[:3, :3].T.flatten().tolist()  # column-major, as librealsense keeps it
        extrinsics.translation = T_color_depth[:3, 3].tolist()
        self.depth_profile.register_extrinsics_to(self.color_profile, extrinsics)

    def _add_stream(self, sensor, kind, fmt, bpp: int, K: CameraIntrinsics, uid: int):
        stream = self.rs.video_stream()
        stream.type, stream.index, stream.uid, stream.fmt, stream.bpp = kind, 0, uid, fmt, bpp
        stream.width, stream.height, stream.fps = K.width, K.height, self.rig.fps
        stream.intrinsics = _rs_intrinsics(self.rs, K)
        return sensor.add_video_stream(stream)

    def record(self, path: Path, n_frames: int = 3, t0_ms: float = 1000.0) -> Path:
        """Records ``n_frames`` frame sets of the scene to ``path`` (the SDK's recording format: ``.db3`` for
        pyrealsense2 2.56+); colour frame k carries marker k at pixel (0, 0) and time stamp ``t0_ms + k / fps``."""
        rs, rig = self.rs, self.rig
        depth_units = np.round(raycast_depth(rig.depth, np.eye(4))[0] / rig.depth_scale_m).astype(np.uint16)
        recorder = rs.recorder(str(path), self.device)
        self.depth_sensor.open(self.depth_profile)
        self.color_sensor.open(self.color_profile)
        self.depth_sensor.start(lambda frame: None)
        self.color_sensor.start(lambda frame: None)
        for k in range(n_frames):
            rgb = colour_image(rig.color, rig.T_depth_color, marker=k)
            stamp = t0_ms + 1000.0 * k / rig.fps
            for sensor, profile, pixels in ((self.depth_sensor, self.depth_profile, depth_units),
                                            (self.color_sensor, self.color_profile, rgb)):  # fmt: skip
                frame = rs.software_video_frame()
                frame.pixels = pixels
                frame.bpp = pixels.itemsize * (pixels.shape[2] if pixels.ndim == 3 else 1)
                frame.stride = frame.bpp * pixels.shape[1]
                frame.timestamp, frame.domain, frame.frame_number = stamp, rs.timestamp_domain.hardware_clock, k
                frame.profile = profile.as_video_stream_profile()
                sensor.on_video_frame(frame)
        for sensor in (self.depth_sensor, self.color_sensor):
            sensor.stop()
            sensor.close()
        del recorder  # the recorder writes the file out when it is destroyed
        gc.collect()
        return path
