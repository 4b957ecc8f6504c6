"""The runtime camera interface: a ``Frame`` of RGB + metric depth, and the ``Camera`` every backend implements.

Backends: the rendered camera of the simulated cell (``sim.camera.SimCamera``) and, for hardware, the OAK camera
(``perception.oak``) and the RealSense D435 (``perception.realsense``).
Images follow the project conventions: RGB uint8 (H, W, 3); depth float32 metres along the camera z axis
(0 = no data), registered to the RGB image, so that ``intrinsics`` describes both.
"""

from __future__ import annotations

import abc
from dataclasses import dataclass
from types import TracebackType

import numpy as np

from sygrid.camera import CameraIntrinsics


@dataclass(frozen=True, eq=False)
class Frame:
    """One capture. ``T_base_camera`` is the camera pose in the robot base frame when the backend knows it (the
    simulator does; a real camera does not until hand-eye calibration)."""

    rgb: np.ndarray
    depth_m: np.ndarray
    intrinsics: CameraIntrinsics
    timestamp_s: float
    T_base_camera: np.ndarray | None = None

    def __post_init__(self) -> None:
        h, w = self.intrinsics.height, self.intrinsics.width
        if self.rgb.shape != (h, w, 3) or self.rgb.dtype != np.uint8:
            raise ValueError(
                f"Frame.rgb must be uint8 ({h}, {w}, 3) to match the intrinsics, got {self.rgb.dtype} {self.rgb.shape}"
            )
        if self.depth_m.shape != (h, w) or self.depth_m.dtype != np.float32:
            raise ValueError(
                f"Frame.depth_m must be float32 ({h}, {w}) metres (0 = no data), "
                f"got {self.depth_m.dtype} {self.depth_m.shape}"
            )
        if self.T_base_camera is not None and np.asarray(self.T_base_camera).shape != (4, 4):
            raise ValueError(f"Frame.T_base_camera must be 4x4 or None, got shape {np.shape(self.T_base_camera)}")

    @property
    def valid_depth(self) -> np.ndarray:
        """(H, W) bool: pixels with a depth measurement."""
        return self.depth_m > 0


class Camera(abc.ABC):
    """A source of ``Frame``s. Use it as a context manager, or call ``close`` when done."""

    @property
    @abc.abstractmethod
    def intrinsics(self) -> CameraIntrinsics:
        """Intrinsics of the frames this camera returns."""

    @abc.abstractmethod
    def capture(self) -> Frame:
        """Takes one frame, blocking until it is available."""

    @abc.abstractmethod
    def close(self) -> None:
        """Releases the device or renderer; safe to call twice."""

    def __enter__(self) -> Camera:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()
