"""A stereo RGB-D sensor model (pure numpy/scipy, seeded): what an OAK-D or a RealSense D435 makes of a clean frame.

Depth goes through the stereo pair's own geometry, not the RGB camera's: a point at depth ``z`` has disparity
``d = f * b / z`` pixels, with ``f`` the stereo pair's focal length in its own pixels and ``b`` the baseline. The
sensor reports ``z' = f * b / d'`` where ``d'`` is ``d`` plus a per-frame offset (``disparity_bias_px``:
calibration / rectification error), plus spatially correlated matching noise (``disparity_noise_px`` with a
correlation length of ``noise_corr_px``, as block matching makes it), rounded to the subpixel step
(``disparity_step_px``). A disparity error ``e`` becomes a depth error ``z^2 * e / (f * b)``: it grows with the
square of the depth (the relative error grows linearly). Disparities above the search range
(``max_disparity_px``: too close) or depths beyond ``max_depth_m`` give no data.

On top, where the matching fails: pixels next to a depth jump either drop out (``edge_dropout``) or take a value
between the foreground and the background depth (flying pixels, ``flying_pixel_fraction``); background pixels that
the second camera cannot see behind a foreground edge (the occlusion "shadow", as wide as the disparity difference,
on the side away from the second camera: ``second_camera_side``) drop out; dark pixels drop out in patches
(``dark_dropout``, the texture-less case, less often with an IR projector); saturated pixels always drop out, and
pixels of specular metal in patches (``specular_dropout``) when the caller gives a metal mask; and random holes.

RGB: a per-frame exposure gain and white balance (log-normal), then shot and read noise in linear light.

Every parameter of the presets is documented against the sensors' published figures in docs/sensors.md. A model is
applied with one ``np.random.Generator``, the only source of randomness: the same generator state gives the same
bytes. The ``ideal`` model returns its inputs unchanged and draws nothing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from statistics import NormalDist

import numpy as np
from scipy import ndimage

from sygrid.camera import CameraIntrinsics
from sygrid.errors import ConfigError


@dataclass(frozen=True)
class SensorModel:
    """A stereo RGB-D camera. Lengths in metres, disparities in the stereo pair's pixels, probabilities in [0, 1].

    A field of 0 turns its effect off. ``second_camera_side``: +1 when the second camera of the pair sits at +x of
    the camera the depth is registered to (occlusion shadows fall at -x of foreground edges), -1 mirrored, 0: none.
    Brightness thresholds are fractions of full scale of the RGB image's mean over channels.
    """

    name: str
    baseline_m: float = 0.0  # 0: the ideal sensor (exact depth, no dropouts)
    stereo_focal_px: float = 0.0
    stereo_size_px: tuple[int, int] = (0, 0)  # width, height of the stereo pair's images (documentation)
    max_disparity_px: float = 0.0  # disparity search range: sets the minimum depth
    max_depth_m: float = 0.0  # 0: no limit
    disparity_step_px: float = 0.0
    disparity_noise_px: float = 0.0
    disparity_bias_px: float = 0.0
    noise_corr_px: float = 0.0
    second_camera_side: int = 0
    edge_rel_jump: float = 0.02
    edge_dropout: float = 0.0
    flying_pixel_fraction: float = 0.0
    dark_threshold: float = 0.0
    dark_dropout: float = 0.0
    saturation_threshold: float = 1.0  # 1: nothing saturates
    specular_dropout: float = 0.0
    dropout_corr_px: float = 3.0  # correlation length of the patchy dropouts, image pixels
    hole_fraction: float = 0.0
    hole_radius_px: int = 0
    exposure_sigma: float = 0.0  # log of the per-frame exposure gain, standard deviation
    white_balance_sigma: float = 0.0  # log of the per-channel gains, standard deviation
    shot_noise_dn: float = 0.0  # variance per digital number of linear signal (0-255 scale)
    read_noise_dn: float = 0.0  # standard deviation, digital numbers of linear signal

    def __post_init__(self) -> None:
        where = f"SensorModel {self.name!r}"
        if not self.name:
            raise ConfigError("SensorModel.name: must not be empty")
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name == "second_camera_side" or not isinstance(value, float | int):
                continue
            if not (math.isfinite(value) and value >= 0):
                raise ConfigError(f"{where}: {f.name} must be finite and >= 0, got {value}")
        probabilities = ("edge_dropout", "flying_pixel_fraction", "dark_dropout", "specular_dropout", "hole_fraction")
        for name in (*probabilities, "dark_threshold", "saturation_threshold"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ConfigError(f"{where}: {name} must be in [0, 1], got {getattr(self, name)}")
        if self.edge_dropout + self.flying_pixel_fraction > 1.0:
            raise ConfigError(f"{where}: edge_dropout + flying_pixel_fraction must be <= 1")
        if self.second_camera_side not in (-1, 0, 1):
            raise ConfigError(f"{where}: second_camera_side must be -1, 0 or 1, got {self.second_camera_side}")
        if self.baseline_m > 0 and not (self.stereo_focal_px > 0 and self.max_disparity_px > 0):
            raise ConfigError(f"{where}: a stereo sensor needs stereo_focal_px > 0 and max_disparity_px > 0")

    # ------------------------------------------------------------------------------------------ the error model
    @property
    def is_ideal(self) -> bool:
        """True when the model changes nothing (no stereo and no photometric effect)."""
        photometric = (self.exposure_sigma, self.white_balance_sigma, self.shot_noise_dn, self.read_noise_dn)
        return self.baseline_m == 0 and not any(photometric)

    @property
    def focal_baseline_px_m(self) -> float:
        """``f * b``: disparity (stereo pixels) times depth (metres)."""
        return self.stereo_focal_px * self.baseline_m

    @property
    def min_depth_m(self) -> float:
        """The nearest depth the disparity search reaches (0 for the ideal sensor)."""
        return self.focal_baseline_px_m / self.max_disparity_px if self.baseline_m > 0 else 0.0

    def depth_noise_sigma_m(self, z_m: float | np.ndarray) -> float | np.ndarray:
        """Per-pixel standard deviation of the depth at ``z_m`` (matching noise and the subpixel step's rounding,
        to first order): ``z^2 * sqrt(noise^2 + step^2 / 12) / (f * b)``."""
        if self.baseline_m == 0:
            return 0.0 * np.asarray(z_m)
        sigma_d = math.hypot(self.disparity_noise_px, self.disparity_step_px / math.sqrt(12.0))
        return np.asarray(z_m) ** 2 * sigma_d / self.focal_baseline_px_m

    def depth_bias_sigma_m(self, z_m: float | np.ndarray) -> float | np.ndarray:
        """Standard deviation over frames of the per-frame depth offset at ``z_m``: ``z^2 * bias / (f * b)``."""
        if self.baseline_m == 0:
            return 0.0 * np.asarray(z_m)
        return np.asarray(z_m) ** 2 * self.disparity_bias_px / self.focal_baseline_px_m

    def scaled(self, factor: float) -> SensorModel:
        """The same sensor with the depth's random errors times ``factor`` (>= 0): the disparity noise and per-frame
        bias, and the dropout probabilities (edge, flying pixels, dark, specular, holes), each capped at 1, with
        ``edge_dropout + flying_pixel_fraction`` kept <= 1 by scaling both down alike. The stereo geometry (range,
        subpixel step, occlusion shadows, saturation) and the RGB noise are unchanged: ``scaled(0)`` is the pair's
        geometry without random depth errors. Named ``"<name> x<factor>"``."""
        if not (math.isfinite(factor) and factor >= 0):
            raise ConfigError(f"SensorModel.scaled: factor must be finite and >= 0, got {factor}")
        edge, flying = self.edge_dropout * factor, self.flying_pixel_fraction * factor
        if edge + flying > 1.0:
            edge, flying = edge / (edge + flying), flying / (edge + flying)
        return replace(
            self,
            name=f"{self.name} x{factor:g}",
            disparity_noise_px=self.disparity_noise_px * factor,
            disparity_bias_px=self.disparity_bias_px * factor,
            edge_dropout=edge,
            flying_pixel_fraction=flying,
            dark_dropout=min(1.0, self.dark_dropout * factor),
            specular_dropout=min(1.0, self.specular_dropout * factor),
            hole_fraction=min(1.0, self.hole_fraction * factor),
        )

    def at_stereo_size(self, width: int, height: int, name: str | None = None) -> SensorModel:
        """The same camera running its stereo pair at ``width`` x ``height`` (a binning or cropping mode of the same
        imagers, same field of view): the focal length in stereo pixels scales with the width, and so does the
        per-frame offset in pixels (an angular calibration error, the same relative depth error at every
        resolution). The matching noise, the subpixel step and the disparity search range stay in stereo pixels (the
        depth engine's), so the per-pixel depth noise and step scale with ``1 / f`` and the minimum depth with ``f``.
        ``name`` defaults to ``"<name>@<height>p"``."""
        if self.baseline_m == 0:
            raise ConfigError(f"SensorModel.at_stereo_size: {self.name!r} has no stereo pair")
        if not (int(width) > 0 and int(height) > 0) or self.stereo_size_px[0] <= 0:
            raise ConfigError(
                f"SensorModel.at_stereo_size: need a positive width and height and a model with a stereo size, got "
                f"{width} x {height} for {self.name!r} ({self.stereo_size_px})"
            )
        scale = int(width) / self.stereo_size_px[0]
        return replace(
            self,
            name=name or f"{self.name}@{int(height)}p",
            stereo_focal_px=self.stereo_focal_px * scale,
            stereo_size_px=(int(width), int(height)),
            disparity_bias_px=self.disparity_bias_px * scale,
        )

    # ------------------------------------------------------------------------------------------------- applying
    def sense(
        self,
        rgb: np.ndarray,
        depth_m: np.ndarray,
        intrinsics: CameraIntrinsics,
        rng: np.random.Generator,
        metal_mask: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """(rgb (H, W, 3) uint8, depth (H, W) float32 metres, 0 = no data) as the sensor reports a clean frame.

        ``depth_m``: clean camera-z depth, 0 = no data; ``intrinsics``: the frame's camera (its ``fx`` scales the
        stereo pixels to image pixels); ``metal_mask``: optional (H, W) bool, pixels of specular metal. The depth's
        dropouts look at the clean ``rgb``. The ideal model returns the inputs as they are.
        """
        if self.is_ideal:
            return rgb, depth_m
        rng_depth, rng_rgb = rng.spawn(2)
        depth = self.sense_depth(depth_m, intrinsics, rng_depth, image=rgb, metal_mask=metal_mask)
        return self.sense_rgb(rgb, rng_rgb), depth

    def sense_depth(
        self,
        depth_m: np.ndarray,
        intrinsics: CameraIntrinsics,
        rng: np.random.Generator,
        image: np.ndarray | None = None,
        metal_mask: np.ndarray | None = None,
    ) -> np.ndarray:
        """The sensed (H, W) float32 depth, metres, 0 = no data (see the module doc for the effects)."""
        z = np.asarray(depth_m, dtype=np.float32)
        if z.ndim != 2:
            raise ValueError(f"depth_m must be (H, W), got shape {z.shape}")
        if self.baseline_m == 0:
            return np.asarray(depth_m, dtype=np.float32)
        h, w = z.shape
        for what, arr in (("image", image), ("metal_mask", metal_mask)):
            if arr is not None and np.shape(arr)[:2] != (h, w):
                raise ValueError(f"{what} must be {h}x{w} like depth_m, got shape {np.shape(arr)}")
        valid = np.isfinite(z) & (z > 0)
        z = np.where(valid, z, np.float32(0.0))
        image_px_per_stereo_px = intrinsics.fx / self.stereo_focal_px
        fb = np.float32(self.focal_baseline_px_m)
        disparity = fb / np.where(valid, z, np.float32(np.inf))  # 0 where there is no data
        if self.disparity_bias_px:
            disparity += np.float32(rng.normal(0.0, self.disparity_bias_px))
        if self.disparity_noise_px:
            corr = self.noise_corr_px * image_px_per_stereo_px
            disparity += np.float32(self.disparity_noise_px) * correlated_normal(rng, (h, w), corr)
        if self.disparity_step_px:
            step = np.float32(self.disparity_step_px)
            disparity = np.round(disparity / step) * step
        keep = valid & (disparity > 0) & (disparity <= self.max_disparity_px)
        sensed = fb / np.where(keep, disparity, np.float32(np.inf))
        if self.max_depth_m:
            keep &= sensed <= self.max_depth_m

        edges = depth_edges(z, self.edge_rel_jump)
        u = rng.random((h, w), dtype=np.float32)
        keep &= ~(edges & (u < self.edge_dropout))
        flying = edges & (u >= self.edge_dropout) & (u < self.edge_dropout + self.flying_pixel_fraction)
        if flying.any():
            lo = ndimage.minimum_filter(np.where(valid, z, np.float32(np.inf)), size=3)
            hi = ndimage.maximum_filter(z, size=3)
            t = rng.random((h, w), dtype=np.float32)
            sensed = np.where(flying, lo + t * (hi - lo), sensed)
        if self.second_camera_side:
            keep &= ~occlusion_shadow(z, intrinsics.fx * self.baseline_m, self.second_camera_side)
        if image is not None:
            channels = np.asarray(image).reshape(h, w, -1)[..., :3]
            lum = channels.sum(-1, dtype=np.int32)  # 0 .. full
            full = 255 * channels.shape[-1]
            keep &= ~(lum >= self.saturation_threshold * full)
            if self.dark_dropout:
                patches = patchy_mask(rng, (h, w), self.dark_dropout, self.dropout_corr_px)
                keep &= ~((lum < self.dark_threshold * full) & patches)
        if metal_mask is not None and self.specular_dropout:
            patches = patchy_mask(rng, (h, w), self.specular_dropout, self.dropout_corr_px)
            keep &= ~(np.asarray(metal_mask, dtype=bool) & patches)
        if self.hole_fraction and self.hole_radius_px:
            seeds = rng.random((h, w), dtype=np.float32) < self.hole_fraction
            keep &= ~ndimage.binary_dilation(seeds, iterations=self.hole_radius_px)
        return np.where(keep, sensed, np.float32(0.0))

    def sense_rgb(self, rgb: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """The sensed (H, W, 3) uint8 image: exposure gain and white balance, then shot and read noise, in linear
        light (sRGB decoded and encoded again)."""
        img = np.asarray(rgb)
        if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
            raise ValueError(f"rgb must be (H, W, 3) uint8, got {img.shape} {img.dtype}")
        gain = math.exp(rng.normal(0.0, self.exposure_sigma)) if self.exposure_sigma else 1.0
        wb = np.exp(rng.normal(0.0, self.white_balance_sigma, 3)) if self.white_balance_sigma else np.ones(3)
        signal = _SRGB_TO_LINEAR_DN[img] * (gain * wb).astype(np.float32)
        if self.shot_noise_dn or self.read_noise_dn:
            sigma = np.sqrt(np.float32(self.shot_noise_dn) * signal + np.float32(self.read_noise_dn**2))
            signal += sigma * rng.standard_normal(img.shape, dtype=np.float32)
        signal *= _LUT_STEPS_PER_DN
        signal += 0.5  # rounds in the truncating cast below
        np.clip(signal, 0, len(_LINEAR_TO_SRGB_U8) - 1, out=signal)
        return _LINEAR_TO_SRGB_U8[signal.astype(np.int32)]


# ------------------------------------------------------------------------------------------------------ presets
# The figures and where they come from: docs/sensors.md.
_OAK_D = SensorModel(
    name="oak-d",
    baseline_m=0.075,
    stereo_focal_px=441.25,
    stereo_size_px=(640, 400),
    max_disparity_px=95.0,
    max_depth_m=10.0,
    disparity_step_px=1 / 8,
    disparity_noise_px=0.1,
    disparity_bias_px=0.21,
    noise_corr_px=2.0,
    second_camera_side=-1,
    edge_dropout=0.4,
    flying_pixel_fraction=0.2,
    dark_threshold=0.06,
    dark_dropout=0.9,
    saturation_threshold=0.98,
    specular_dropout=0.15,
    hole_fraction=0.002,
    hole_radius_px=2,
    exposure_sigma=0.1,
    white_balance_sigma=0.03,
    shot_noise_dn=0.1,
    read_noise_dn=1.0,
)
_D435 = SensorModel(
    name="d435",
    baseline_m=0.050,
    stereo_focal_px=446.8,
    stereo_size_px=(848, 480),
    max_disparity_px=126.0,
    max_depth_m=10.0,
    disparity_step_px=1 / 32,
    disparity_noise_px=0.1,
    disparity_bias_px=0.28,
    noise_corr_px=2.0,
    second_camera_side=1,
    edge_dropout=0.4,
    flying_pixel_fraction=0.2,
    dark_threshold=0.06,
    dark_dropout=0.3,
    saturation_threshold=0.98,
    specular_dropout=0.1,
    hole_fraction=0.002,
    hole_radius_px=2,
    exposure_sigma=0.1,
    white_balance_sigma=0.03,
    shot_noise_dn=0.15,
    read_noise_dn=1.5,
)
SENSOR_PRESETS: dict[str, SensorModel] = {
    "ideal": SensorModel(name="ideal"),
    "oak-d": _OAK_D,
    "oak-d-800p": _OAK_D.at_stereo_size(1280, 800, "oak-d-800p"),
    "oak-d-pro": replace(_OAK_D, name="oak-d-pro", dark_dropout=0.3, specular_dropout=0.1),
    "d435": _D435,
    "d435i": replace(_D435, name="d435i"),
}
IDEAL = SENSOR_PRESETS["ideal"]


def sensor_preset(name: str, where: str = "sensor") -> SensorModel:
    """The preset called ``name``; ``ConfigError`` naming ``where`` and the valid names otherwise."""
    try:
        return SENSOR_PRESETS[name]
    except KeyError:
        raise ConfigError(f"{where}: unknown sensor {name!r}; valid: {sorted(SENSOR_PRESETS)}") from None


def sensor_rng(seed: int, *ids: int) -> np.random.Generator:
    """The generator for one frame: a pure function of ``seed`` and the frame's ids (e.g. scene id, image id)."""
    return np.random.default_rng([int(seed), *(int(i) for i in ids)])


def metal_mask(masks: list[np.ndarray], materials: list[str], metals: frozenset[str]) -> np.ndarray | None:
    """(H, W) bool union of the instance ``masks`` whose material is in ``metals``; None when there is no mask."""
    if not masks:
        return None
    out = np.zeros(np.shape(masks[0]), dtype=bool)
    for mask, material in zip(masks, materials, strict=True):
        if material in metals:
            out |= np.asarray(mask, dtype=bool)
    return out


# ------------------------------------------------------------------------------------------------------ helpers
def correlated_normal(rng: np.random.Generator, shape: tuple[int, int], corr_px: float) -> np.ndarray:
    """Standard-normal field (unit variance per pixel) smoothed with a Gaussian of ``corr_px`` pixels."""
    white = rng.standard_normal(shape, dtype=np.float32)
    if corr_px <= 0:
        return white
    radius = int(4.0 * corr_px + 0.5)  # scipy's kernel (truncate=4)
    g = np.exp(-0.5 * (np.arange(-radius, radius + 1) / corr_px) ** 2)
    g /= g.sum()
    return ndimage.gaussian_filter(white, corr_px, mode="reflect") / float(np.sum(g**2))


def patchy_mask(rng: np.random.Generator, shape: tuple[int, int], fraction: float, corr_px: float) -> np.ndarray:
    """(H, W) bool, true on a ``fraction`` of the pixels in expectation, in blobs of about ``corr_px`` pixels."""
    if fraction <= 0:
        return np.zeros(shape, dtype=bool)
    if fraction >= 1:
        return np.ones(shape, dtype=bool)
    return correlated_normal(rng, shape, corr_px) < NormalDist().inv_cdf(fraction)


def depth_edges(depth_m: np.ndarray, rel_jump: float) -> np.ndarray:
    """(H, W) bool: valid pixels with a 4-neighbour whose depth differs by more than ``rel_jump`` of the nearer
    one, or that has no data."""
    z = np.asarray(depth_m)
    valid = z > 0
    edge = np.zeros(z.shape, dtype=bool)
    for axis in (0, 1):
        a, b = np.moveaxis(z, axis, 0)[:-1], np.moveaxis(z, axis, 0)[1:]
        va, vb = a > 0, b > 0
        jump = (va != vb) | (va & vb & (np.abs(a - b) > rel_jump * np.minimum(a, b)))
        e = np.moveaxis(edge, axis, 0)  # a view: writes go to edge
        e[:-1] |= jump
        e[1:] |= jump
    return edge & valid


def occlusion_shadow(depth_m: np.ndarray, focal_baseline_px_m: float, second_camera_side: int) -> np.ndarray:
    """(H, W) bool: pixels the second camera of the pair cannot see, hidden behind nearer pixels of their row.

    ``focal_baseline_px_m``: the image's focal length (pixels) times the baseline. With the second camera at +x
    (``second_camera_side`` +1), pixel ``u`` of disparity ``d`` appears at ``u - d`` in the second view and is
    hidden when some pixel to its right lands further left there.
    """
    z = np.asarray(depth_m, dtype=np.float64)
    if second_camera_side < 0:
        return occlusion_shadow(z[:, ::-1], focal_baseline_px_m, 1)[:, ::-1]
    with np.errstate(divide="ignore"):
        disparity = np.where(z > 0, focal_baseline_px_m / np.where(z > 0, z, 1.0), 0.0)
    key = np.arange(z.shape[1])[None, :] - disparity
    right_min = np.minimum.accumulate(key[:, ::-1], axis=1)[:, ::-1]  # min over u' >= u
    beyond = np.full_like(key, np.inf)
    beyond[:, :-1] = right_min[:, 1:]  # min over u' > u
    return (z > 0) & (beyond < key - 1e-9)


def _srgb_to_linear(x: np.ndarray) -> np.ndarray:
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


def _linear_to_srgb(x: np.ndarray) -> np.ndarray:
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


_SRGB_TO_LINEAR_DN = (255.0 * _srgb_to_linear(np.arange(256) / 255.0)).astype(np.float32)  # uint8 sRGB -> linear
_LUT_STEPS_PER_DN = 64  # linear signal (0-255 scale) -> uint8 sRGB through a table with 1/64 DN steps
_LINEAR_TO_SRGB_U8 = np.round(
    255.0 * _linear_to_srgb(np.arange(255 * _LUT_STEPS_PER_DN + 1) / (255.0 * _LUT_STEPS_PER_DN))
).astype(np.uint8)
