"""Pinhole camera intrinsics, shared by the generator, the sim camera and the runtime cameras."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole intrinsics in pixels for an image of ``width`` x ``height``; no lens distortion."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    @classmethod
    def from_fov(cls, width: int, height: int, fov_y_deg: float) -> CameraIntrinsics:
        """Square pixels, principal point at the image centre, vertical field of view ``fov_y_deg``."""
        f = 0.5 * height / math.tan(math.radians(fov_y_deg) / 2.0)
        return cls(f, f, (width - 1) / 2.0, (height - 1) / 2.0, width, height)

    @classmethod
    def from_K(cls, K: np.ndarray, width: int, height: int) -> CameraIntrinsics:
        K = np.asarray(K, dtype=float).reshape(3, 3)
        return cls(K[0, 0], K[1, 1], K[0, 2], K[1, 2], int(width), int(height))

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def fov_y_deg(self) -> float:
        return math.degrees(2.0 * math.atan(0.5 * self.height / self.fy))

    def scaled(self, width: int, height: int) -> CameraIntrinsics:
        """The same camera at another resolution (pixel-centre convention kept)."""
        sx, sy = width / self.width, height / self.height
        return CameraIntrinsics(
            self.fx * sx, self.fy * sy, (self.cx + 0.5) * sx - 0.5, (self.cy + 0.5) * sy - 0.5, width, height
        )


def project_points(K: np.ndarray, p_cam: np.ndarray) -> np.ndarray:
    """(n, 3) points in the camera frame (z forward, metres) -> (n, 2) pixel coordinates."""
    uvw = p_cam @ np.asarray(K).T
    return uvw[:, :2] / uvw[:, 2:3]


def unproject_depth(K: np.ndarray, depth_m: np.ndarray) -> np.ndarray:
    """(h, w) depth in metres (0 = no data) -> (h, w, 3) camera-frame points (NaN where there is no data)."""
    h, w = depth_m.shape
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    z = np.where(depth_m > 0, depth_m, np.nan)
    x = (u - K[0, 2]) * z / K[0, 0]
    y = (v - K[1, 2]) * z / K[1, 1]
    return np.stack([x, y, z], axis=-1)
