"""The overhead camera of an emulated cell, seen from outside the emulator's process.

``EmulatorCamera`` asks a ``ControllerProcess`` (MuJoCo backend) for a frame: the emulator's render process
(``sim.render_process``) renders the world's current state with ``SimCamera`` and sends the arrays over a pipe, so
rendering never runs in the emulator's process. So the picking runtime sees frames exactly as from an OAK: RGB,
metric depth registered to it, intrinsics and a timestamp (the world's simulated time). ``T_base_camera`` is
withheld unless ``report_T_base_camera``: the runtime takes the camera pose from its calibration, as on hardware.
A ``sensor`` (``sygrid.sensor.SensorModel``) is applied here to the exact frames the emulator renders, with this
camera's ``rng``.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from perception.camera import Camera, Frame
from sygrid.camera import CameraIntrinsics
from sygrid.sensor import IDEAL, SensorModel


class EmulatorCamera(Camera):
    """A ``perception.camera.Camera`` over ``process.capture()`` (``sim.controller.ControllerProcess``)."""

    def __init__(
        self,
        process: Any,
        report_T_base_camera: bool = False,
        timeout_s: float = 10.0,
        sensor: SensorModel = IDEAL,
        rng: np.random.Generator | None = None,
    ) -> None:
        if not sensor.is_ideal and rng is None:
            raise ValueError(
                f"sensor {sensor.name!r} needs an rng (np.random.Generator) so that frames are reproducible"
            )
        self._sensor, self._rng = sensor, rng
        self._process = process
        self._report = report_T_base_camera
        self._timeout_s = timeout_s
        self._intrinsics: CameraIntrinsics | None = None
        self.last_T_base_camera: np.ndarray | None = None  # the true pose of the last frame (for checks)

    @property
    def intrinsics(self) -> CameraIntrinsics:
        if self._intrinsics is None:
            self.capture()
        assert self._intrinsics is not None
        return self._intrinsics

    def capture(self) -> Frame:
        fields = self._process.capture(timeout_s=self._timeout_s)
        self._intrinsics = fields["intrinsics"]
        self.last_T_base_camera = fields["T_base_camera"]
        rgb, depth = fields["rgb"], fields["depth_m"]
        if not self._sensor.is_ideal:
            rgb, depth = self._sensor.sense(rgb, depth, fields["intrinsics"], self._rng)
        return Frame(
            rgb=rgb,
            depth_m=depth,
            intrinsics=fields["intrinsics"],
            timestamp_s=float(fields["timestamp_s"]),
            T_base_camera=fields["T_base_camera"] if self._report else None,
        )

    def close(self) -> None:
        """Nothing to release here: the renderer belongs to the emulator's process."""
