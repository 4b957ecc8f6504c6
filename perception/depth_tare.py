"""Depth tare: a stereo camera's per-frame depth offset, measured on the bin's floor whose plane the cell knows.

A stereo camera's calibration and rectification error shifts every disparity of a frame by about the same amount
(``sygrid.sensor``'s ``disparity_bias_px``); RealSense corrects it with a "tare calibration" against a target at a
known distance. Disparity is proportional to inverse depth, so a disparity offset is an inverse-depth offset,
``1 / z_obs = 1 / z + c`` at every pixel of the frame: a pose fitted to that depth is off by about ``c z^2`` along
the ray, and a verification against the same depth cannot see it.

A cell knows the plane of its bin's floor in the camera frame (calibration) and where the floor is (the bin's inner
corners). Inside the image polygon of the floor, a pixel's ``q = 1 / z_obs - 1 / z_plane`` (``z_plane``: where the
pixel's ray meets the plane) is ``c`` plus noise where the floor is seen and larger where a part or an inner wall is
(nearer than the floor); nothing there lies beyond the floor. So the floor is the lowest dense cluster of ``q``:
the first peak of q's smoothed histogram from the low end that reaches a share of the highest one, refined by the
median of the pixels in a window around it (a few times; the window's width from the spread of the cluster's low
side, which no part reaches). A stereo camera's disparities are quantised (subpixel steps): the floor's ``q`` then
falls on a few levels one step apart, and a median (or the lowest level dense enough) sticks on one of them, up to
a step off (3 mm at 0.9 m for the OAK-D). With the sensor's step known (``quantum_inv_m``, ``TareConfig.for_sensor``)
the histogram is smoothed over at least a step and the offset is the mean over a window of at least a step and a
half each side, where the noise dithers the levels into an unbiased mean. Fewer floor pixels than ``min_floor_px``
(a full bin, the floor out of view): no correction, with the reason. Nor where the cluster spreads wider than a
plane seen by the sensor can (``max_spread_factor`` x the spread its noise and steps give, ``noise_inv_m`` and
``quantum_inv_m``; checked where the sensor is known, ``TareConfig.for_sensor``): in a bin so full that little
floor shows, the lowest dense cluster is the parts' tops at many heights, and taking it for the floor would push
every depth of the frame centimetres too deep. The correction ``z = 1 / (1 / z_obs - c)`` applies to the whole
image; no data stays no data. Optionally a disparity gain too (``1 / z_obs = g / z + c``, a
baseline or focal length error), fitted to the floor pixels where the floor spans enough inverse depth
(``fit_gain``; the sensor model has no gain error).

The floor's polygon comes from any camera-frame points that bound where the floor is seen (the bin's inner corners,
floor and rim): projected onto the plane along its normal, then into the image, their convex hull.

Hand-written, numpy only: depth libraries fit planes (RANSAC) or register clouds, but none estimates a stereo
offset in inverse depth against a known plane on a depth image; RealSense's own tare runs in the camera's firmware,
against its own target.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from sygrid.camera import CameraIntrinsics, project_points
from sygrid.sensor import SensorModel


@dataclass(frozen=True)
class TareConfig:
    """Settings of the tare; inverse depths in 1/m (1e-3 /m is a 1 mm depth error at 1 m).

    Attributes:
        min_floor_px: fewer floor pixels than this (full-resolution pixels): no correction.
        stride: every ``stride``-th pixel of the floor's polygon in each direction is used.
        smooth_inv_m: the Gaussian smoothing of q's histogram (one standard deviation).
        peak_fraction: a histogram peak is a dense cluster when it reaches this fraction of the highest.
        window_sigmas: the refinement's window, in standard deviations of the cluster's low side ...
        min_window_inv_m: ... and at least this wide (each side; exact depth has no spread).
        iterations: median refinements of the offset.
        max_offset_inv_m: a larger offset is no stereo offset (a wrong floor plane): no correction.
        fit_gain: also fit a disparity gain where the floor spans ``min_gain_span`` of its inverse depth.
        min_gain_span: the 5-95 % span of the floor pixels' plane inverse depth, as a fraction of its median.
        quantum_inv_m: the depth's quantisation in inverse depth (a disparity step over focal length x baseline);
            0: not quantised (exact depth), the medians as they are.
        noise_inv_m: the depth's noise in inverse depth (one standard deviation; a disparity's noise over focal
            length x baseline, the same at every depth); 0: exact depth; None: not known (the spread is not checked).
        max_spread_factor: the floor's cluster may spread (robust standard deviation of its low side) at most this
            x the spread of a plane under the noise and the steps (``sqrt(noise^2 + quantum^2 / 12)``, at least
            ``min_window_inv_m``); wider: no plane is seen, no correction.
    """

    min_floor_px: int = 1000
    stride: int = 2
    smooth_inv_m: float = 1e-3
    peak_fraction: float = 0.2
    window_sigmas: float = 2.5
    min_window_inv_m: float = 2e-4
    iterations: int = 3
    max_offset_inv_m: float = 0.05
    fit_gain: bool = False
    min_gain_span: float = 0.15
    quantum_inv_m: float = 0.0
    noise_inv_m: float | None = None
    max_spread_factor: float = 1.5

    def __post_init__(self) -> None:
        if self.min_floor_px < 1 or self.stride < 1 or self.iterations < 1:
            raise ValueError(
                f"TareConfig: need min_floor_px, stride and iterations >= 1, got {self.min_floor_px}, {self.stride}, "
                f"{self.iterations}"
            )
        positive = (self.smooth_inv_m, self.window_sigmas, self.min_window_inv_m, self.max_offset_inv_m)
        if min(positive) <= 0 or not 0 < self.peak_fraction <= 1 or self.min_gain_span <= 0:
            raise ValueError(
                "TareConfig: need smooth_inv_m, window_sigmas, min_window_inv_m, max_offset_inv_m, min_gain_span > 0 "
                f"and peak_fraction in (0, 1], got {positive}, {self.min_gain_span}, {self.peak_fraction}"
            )
        if not all(math.isfinite(x) and x >= 0 for x in (self.quantum_inv_m, self.noise_inv_m or 0.0)):
            raise ValueError(
                f"TareConfig: need quantum_inv_m and noise_inv_m >= 0, got {self.quantum_inv_m}, {self.noise_inv_m}"
            )
        if not self.max_spread_factor >= 1:
            raise ValueError(f"TareConfig: need max_spread_factor >= 1, got {self.max_spread_factor}")

    def for_sensor(self, sensor: SensorModel) -> TareConfig:
        """These settings for depth from ``sensor``: its disparity step as the quantisation and its disparity noise
        as the inverse-depth noise (none for exact depth)."""
        stereo = sensor.stereo_focal_px * sensor.baseline_m
        quantum = sensor.disparity_step_px / stereo if stereo > 0 else 0.0
        noise = float(sensor.depth_noise_sigma_m(1.0))  # sigma_z = z^2 sigma_d / (f b): at 1 m it is 1/z's sigma
        return replace(self, quantum_inv_m=float(quantum), noise_inv_m=noise)

    @property
    def max_spread_inv_m(self) -> float:
        """The widest spread (robust standard deviation, 1/m) the floor's cluster may have; inf where the sensor's
        noise is not known."""
        if self.noise_inv_m is None:
            return math.inf
        plane = math.sqrt(self.noise_inv_m**2 + self.quantum_inv_m**2 / 12.0)
        return self.max_spread_factor * max(plane, self.min_window_inv_m)


@dataclass(frozen=True)
class Tare:
    """A frame's measured stereo offset: ``1 / z_obs = gain / z + offset_inv_m`` on the floor.

    ``applied``: whether the correction is used (False: ``reason`` says why; offset 0 and gain 1 then).
    ``floor_px``: the floor pixels it was measured on (full-resolution pixels)."""

    offset_inv_m: float = 0.0
    gain: float = 1.0
    floor_px: int = 0
    applied: bool = False
    reason: str = ""

    @property
    def offset_mm_at_1m(self) -> float:
        """The depth error the offset makes at 1 m (observed minus true, first order), millimetres."""
        return -1e3 * self.offset_inv_m

    def as_dict(self) -> dict:
        return {"offset_inv_m": self.offset_inv_m, "offset_mm_at_1m": self.offset_mm_at_1m, "gain": self.gain,
                "floor_px": self.floor_px, "applied": self.applied, "reason": self.reason}  # fmt: skip


def floor_polygon(
    floor_plane_camera: np.ndarray, bounds_camera_m: np.ndarray, intrinsics: CameraIntrinsics
) -> np.ndarray | None:
    """(k, 2) the floor's image polygon, counter-clockwise in pixel coordinates: the convex hull of
    ``bounds_camera_m`` (n, 3) projected onto the plane ``(a, b, c, d)`` along its normal, then into the image.
    None when a projected point is not in front of the camera or the hull is degenerate."""
    normal, offset = np.asarray(floor_plane_camera[:3], dtype=float), float(floor_plane_camera[3])
    points = np.asarray(bounds_camera_m, dtype=float).reshape(-1, 3)
    on_plane = points - (points @ normal + offset)[:, None] * normal[None, :]
    if len(on_plane) < 3 or not (on_plane[:, 2] > 1e-6).all():
        return None
    hull = _convex_hull(project_points(intrinsics.K, on_plane))
    return hull if len(hull) >= 3 else None


def estimate_tare(
    depth_m: np.ndarray,
    intrinsics: CameraIntrinsics,
    floor_plane_camera: np.ndarray,
    bounds_camera_m: np.ndarray,
    config: TareConfig | None = None,
) -> Tare:
    """The stereo offset of ``depth_m`` (H, W metres, 0 = no data) measured on the floor: the plane ``(a, b, c, d)``
    (camera frame; a point p lies ``(a, b, c) . p + d`` above it) inside the polygon of ``bounds_camera_m``
    (``floor_polygon``). Not applied (with the reason) when the floor is out of view or too little of it is seen."""
    cfg = config or TareConfig()
    polygon = floor_polygon(floor_plane_camera, bounds_camera_m, intrinsics)
    if polygon is None:
        return Tare(reason="the floor's polygon is not in front of the camera")
    depth = np.asarray(depth_m)
    h, w = depth.shape
    x0, y0 = max(int(np.floor(polygon[:, 0].min())), 0), max(int(np.floor(polygon[:, 1].min())), 0)
    x1, y1 = min(int(np.ceil(polygon[:, 0].max())) + 1, w), min(int(np.ceil(polygon[:, 1].max())) + 1, h)
    if x1 <= x0 or y1 <= y0:
        return Tare(reason="the floor's polygon lies outside the image")
    u = np.arange(x0, x1, cfg.stride, dtype=float)
    v = np.arange(y0, y1, cfg.stride, dtype=float)
    inside = _inside_convex(polygon, u, v)
    z = depth[y0 : y1 : cfg.stride, x0 : x1 : cfg.stride].astype(np.float64)
    K = intrinsics.K
    normal, offset = np.asarray(floor_plane_camera[:3], dtype=float), float(floor_plane_camera[3])
    # the plane's inverse depth along each pixel's ray (z = 1): -(n . ray) / d, separable in u and v
    ray_dot = (normal[0] * (u - K[0, 2]) / K[0, 0])[None, :] + (normal[1] * (v - K[1, 2]) / K[1, 1])[:, None]
    inv_plane = -(ray_dot + normal[2]) / offset if offset != 0 else np.full(ray_dot.shape, -np.inf)
    use = inside & np.isfinite(z) & (z > 0) & (inv_plane > 0)
    per_sample = cfg.stride**2
    if use.sum() * per_sample < cfg.min_floor_px:
        return Tare(floor_px=int(use.sum()) * per_sample,
                    reason=f"{int(use.sum()) * per_sample} depth pixels inside the floor's polygon, fewer than "
                           f"{cfg.min_floor_px}")  # fmt: skip
    inv_obs, inv_p = 1.0 / z[use], inv_plane[use]
    q = inv_obs - inv_p
    c, window, spread = _lowest_cluster(q, cfg)
    floor = np.abs(q - c) <= window
    n_floor = int(floor.sum()) * per_sample
    if n_floor < cfg.min_floor_px:
        return Tare(floor_px=n_floor, reason=f"{n_floor} floor pixels, fewer than {cfg.min_floor_px}")
    if spread > cfg.max_spread_inv_m:
        return Tare(floor_px=n_floor,
                    reason=f"the floor's cluster spreads {spread:.4f} /m, more than the {cfg.max_spread_inv_m:.4f} /m "
                           "of a plane seen by this sensor: parts cover the floor")  # fmt: skip
    gain = 1.0
    if cfg.fit_gain:
        c, gain, floor = _fit_gain(inv_obs, inv_p, c, window, floor, cfg)
        n_floor = int(floor.sum()) * per_sample
    if abs(c) > cfg.max_offset_inv_m:
        return Tare(offset_inv_m=0.0, floor_px=n_floor,
                    reason=f"offset {c:.4f} /m beyond {cfg.max_offset_inv_m} /m: not a stereo offset (check the floor "
                           "plane)")  # fmt: skip
    return Tare(offset_inv_m=float(c), gain=float(gain), floor_px=n_floor, applied=True)


def apply_tare(depth_m: np.ndarray, tare: Tare) -> np.ndarray:
    """``depth_m`` (H, W metres, 0 = no data) corrected by ``tare``: ``z = gain / (1 / z_obs - offset)``, float32;
    no data stays no data, and a pixel the correction would put beyond infinity gets none. An unapplied tare
    returns ``depth_m`` itself."""
    if not tare.applied:
        return depth_m
    z = np.asarray(depth_m, dtype=np.float32)
    valid = np.isfinite(z) & (z > 0)
    inv = np.where(valid, np.float32(1.0) / np.where(valid, z, np.float32(1.0)), np.float32(0.0))
    inv = (inv - np.float32(tare.offset_inv_m)) / np.float32(tare.gain)
    keep = valid & (inv > 0)
    return np.where(keep, np.float32(1.0) / np.where(keep, inv, np.float32(1.0)), np.float32(0.0))


def tared_depth(
    depth_m: np.ndarray,
    intrinsics: CameraIntrinsics,
    floor_plane_camera: np.ndarray | None,
    bounds_camera_m: np.ndarray | None,
    config: TareConfig | None,
) -> tuple[np.ndarray, Tare | None]:
    """``(depth, tare)``: the depth corrected on the floor (``estimate_tare``, ``apply_tare``) where a config, the
    floor plane and its bounds are given; otherwise ``(depth_m, None)``."""
    if config is None or floor_plane_camera is None or bounds_camera_m is None:
        return depth_m, None
    tare = estimate_tare(depth_m, intrinsics, floor_plane_camera, bounds_camera_m, config)
    return apply_tare(depth_m, tare), tare


# ----------------------------------------------------------------------------------------------------- helpers
def _lowest_cluster(q: np.ndarray, cfg: TareConfig) -> tuple[float, float, float]:
    """(centre, half window, spread) of the lowest dense cluster of ``q``: the first peak of its smoothed histogram
    from the low end reaching ``peak_fraction`` of the highest, then medians within the window, its half width
    ``window_sigmas`` robust standard deviations of the cluster's low side (the spread). Quantised depth
    (``quantum_inv_m``): smoothed over at least a step, means within at least a step and a half each side (see the
    module docstring), the spread measured through the steps (``_low_side_spread``)."""
    sigma_inv = max(cfg.smooth_inv_m, cfg.quantum_inv_m)  # the histogram's smoothing
    min_window = max(cfg.min_window_inv_m, 1.5 * cfg.quantum_inv_m)
    centre_of = np.mean if cfg.quantum_inv_m > 0 else np.median
    lo, hi = np.percentile(q, (0.1, 99.9))
    bin_width = sigma_inv / 4
    hi = max(hi, lo + 8 * sigma_inv)
    n_bins = min(math.ceil((hi - lo) / bin_width), 20000)
    counts, edges = np.histogram(q, bins=n_bins, range=(lo, lo + n_bins * bin_width))
    radius = 12  # three smoothing sigmas in bins
    kernel = np.exp(-0.5 * (np.arange(-radius, radius + 1) / 4.0) ** 2)
    smooth = np.convolve(np.pad(counts.astype(float), radius), kernel, mode="valid")
    left = np.concatenate(([-np.inf], smooth[:-1]))
    right = np.concatenate((smooth[1:], [-np.inf]))
    peaks = np.flatnonzero((smooth >= left) & (smooth > right) & (smooth >= cfg.peak_fraction * smooth.max()))
    centre = float(0.5 * (edges[peaks[0]] + edges[peaks[0] + 1]))
    window, sigma = min_window, 0.0
    dithered = _dithered(q, cfg.quantum_inv_m)  # for the spread: the same values in every refinement
    for _ in range(cfg.iterations):
        sigma = _low_side_spread(dithered, centre, 8 * sigma_inv, cfg.quantum_inv_m)
        window = max(cfg.window_sigmas * sigma, min_window)
        near = q[np.abs(q - centre) <= window]
        if not len(near):
            break
        centre = float(centre_of(near))
    return centre, window, _low_side_spread(dithered, centre, 8 * sigma_inv, cfg.quantum_inv_m)


_GOLDEN = (math.sqrt(5.0) - 1.0) / 2.0


def _dithered(q: np.ndarray, quantum: float) -> np.ndarray:
    """``q`` with each value spread over its step of ``quantum`` by a fixed dither (a golden-ratio sequence:
    deterministic, evenly filled); ``q`` itself without steps (``quantum`` 0)."""
    return q + (np.modf(np.arange(len(q)) * _GOLDEN)[0] - 0.5) * quantum if quantum > 0 else q


def _low_side_spread(dithered: np.ndarray, centre: float, reach: float, quantum: float) -> float:
    """The robust standard deviation of the low side (within ``reach`` below ``centre``; parts lie above the floor,
    so only the low side is the floor's) of ``_dithered`` values: 1.4826 x the median distance below the centre.
    Quantised to steps of ``quantum`` (> 0), a floor facing the camera sits on a few levels one step apart and that
    median jumps by a step with where the levels fall (anything from 0 to 1.5 steps for one plane), which moved the
    window and failed the spread check on clear floors; the dither makes it continuous, and its own variance
    (``quantum^2 / 12``) is taken back out here."""
    below = centre - dithered[(dithered <= centre) & (dithered >= centre - reach)]
    if not len(below):
        return 0.0
    sigma = 1.4826 * float(np.median(below))
    return math.sqrt(max(sigma**2 - quantum**2 / 12.0, 0.0))


def _fit_gain(
    inv_obs: np.ndarray, inv_plane: np.ndarray, c: float, window: float, floor: np.ndarray, cfg: TareConfig
) -> tuple[float, float, np.ndarray]:
    """(offset, gain, floor pixels) from a straight line ``inv_obs = gain * inv_plane + offset`` through the floor
    pixels (refitted twice with the pixels within ``window`` of it), where they span ``min_gain_span``; the offset
    alone (gain 1) otherwise."""
    p5, p50, p95 = np.percentile(inv_plane[floor], (5, 50, 95))
    if (p95 - p5) < cfg.min_gain_span * p50:
        return c, 1.0, floor
    gain, offset = 1.0, c
    for _ in range(3):
        A = np.stack([inv_plane[floor], np.ones(int(floor.sum()))], axis=1)
        gain, offset = np.linalg.lstsq(A, inv_obs[floor], rcond=None)[0]
        floor = np.abs(inv_obs - gain * inv_plane - offset) <= window
        if floor.sum() < 3:
            return c, 1.0, np.abs(inv_obs - inv_plane - c) <= window
    return float(offset), float(gain), floor


def _convex_hull(points: np.ndarray) -> np.ndarray:
    """(k, 2) the convex hull of (n, 2) points, counter-clockwise in a y-up frame (Andrew's monotone chain)."""
    pts = sorted(map(tuple, np.unique(np.round(np.asarray(points, dtype=float), 6), axis=0)))
    if len(pts) < 3:
        return np.asarray(pts)

    def half(seq: list) -> list:
        out: list = []
        for p in seq:
            while len(out) >= 2 and _cross(out[-2], out[-1], p) <= 0:
                out.pop()
            out.append(p)
        return out[:-1]

    return np.asarray(half(pts) + half(pts[::-1]))


def _cross(o: tuple, a: tuple, b: tuple) -> float:
    return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])


def _inside_convex(polygon: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(len(v), len(u)) bool: pixel centres (u, v) inside the convex ``polygon`` (``_convex_hull``'s order)."""
    inside = np.ones((len(v), len(u)), dtype=bool)
    for (ax, ay), (bx, by) in zip(polygon, np.roll(polygon, -1, axis=0), strict=True):
        inside &= ((bx - ax) * (v[:, None] - ay) - (by - ay) * (u[None, :] - ax)) >= 0
    return inside
