"""The camera knob's image effects on a rendered (H, W, 3) uint8 sRGB image: ``optics`` (defocus, motion blur,
vignetting, exposure, white balance, in linear light) before the recipe's sensor, ``compress`` (JPEG) after it.
Both are deterministic given the draw (``sygrid.randomise.draws.CameraDraw``); neither touches depth or labels."""

from __future__ import annotations

import math

import cv2
import numpy as np

from sygrid.randomise.draws import CameraDraw


def _srgb_to_linear(x: np.ndarray) -> np.ndarray:
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


def _linear_to_srgb_u8(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    s = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return np.round(s * 255.0).astype(np.uint8)


def motion_kernel(length_px: float, angle_deg: float) -> np.ndarray | None:
    """A normalised line kernel ``length_px`` long at ``angle_deg`` (image x towards y), or None when shorter
    than a pixel."""
    if length_px < 1.0:
        return None
    size = math.ceil(length_px) | 1
    kernel = np.zeros((size, size), np.float32)
    c = size // 2
    t = np.linspace(-length_px / 2, length_px / 2, 4 * size)
    a = math.radians(angle_deg)
    cols = np.clip(np.round(c + t * math.cos(a)).astype(int), 0, size - 1)
    rows = np.clip(np.round(c + t * math.sin(a)).astype(int), 0, size - 1)
    np.add.at(kernel, (rows, cols), 1.0)
    return kernel / kernel.sum()


def optics(rgb: np.ndarray, draw: CameraDraw) -> np.ndarray:
    """The image through the drawn lens and exposure: blurs, vignetting, then exposure and white balance gains."""
    img = _srgb_to_linear(np.asarray(rgb, np.float32) / 255.0).astype(np.float32)
    if draw.defocus_sigma_px > 0.05:
        img = cv2.GaussianBlur(img, (0, 0), draw.defocus_sigma_px, borderType=cv2.BORDER_REFLECT)
    kernel = motion_kernel(draw.motion_blur_px, draw.motion_angle_deg)
    if kernel is not None:
        img = cv2.filter2D(img, -1, kernel, borderType=cv2.BORDER_REFLECT)
    h, w = img.shape[:2]
    if draw.vignetting > 0:
        v, u = np.mgrid[0:h, 0:w].astype(np.float32)
        r2 = ((u - (w - 1) / 2) ** 2 + (v - (h - 1) / 2) ** 2) / (((w - 1) / 2) ** 2 + ((h - 1) / 2) ** 2)
        img = img * (1.0 - draw.vignetting * r2)[..., None]
    gains = 2.0**draw.exposure_ev * np.array([draw.white_balance[0], 1.0, draw.white_balance[1]], np.float32)
    return _linear_to_srgb_u8(img * gains)


def compress(rgb: np.ndarray, draw: CameraDraw) -> np.ndarray:
    """The image after a JPEG round trip at the drawn quality (unchanged when the draw has none)."""
    if draw.jpeg_quality is None:
        return rgb
    ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(rgb[..., ::-1]), [cv2.IMWRITE_JPEG_QUALITY, draw.jpeg_quality])
    if not ok:
        raise RuntimeError("JPEG encoding failed")
    return cv2.imdecode(buf, cv2.IMREAD_COLOR)[..., ::-1].copy()
