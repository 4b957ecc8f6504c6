"""A stereo depth-camera noise model (pure numpy, seeded): what an OAK-D-like sensor makes of clean depth.

Stereo measures disparity ``d = f * b / z``; a disparity error ``sigma_d`` (pixels) becomes a depth error
``sigma_z = z^2 * sigma_d / (f * b)``, growing with the square of the depth. On top: dropouts where depth jumps
(occlusion edges, where one of the two views does not see the point), dropouts on dark or saturated pixels when an
image is given (no texture to match), and random holes. Noise is spatially correlated over ``blob_px`` pixels,
as block matching makes it.
"""

from __future__ import annotations

import numpy as np

from sygrid.camera import CameraIntrinsics


def _box_blur(x: np.ndarray, r: int) -> np.ndarray:
    """Separable box mean of half-width ``r`` (edge-padded), for correlated noise."""
    if r <= 0:
        return x
    k = 2 * r + 1
    p = np.pad(x, r, mode="edge")
    c = np.cumsum(np.pad(p, ((1, 0), (0, 0))), axis=0)
    p = (c[k:] - c[:-k]) / k
    c = np.cumsum(np.pad(p, ((0, 0), (1, 0))), axis=1)
    return (c[:, k:] - c[:, :-k]) / k


def depth_edges(depth_m: np.ndarray, rel_jump: float = 0.03, dilate_px: int = 1) -> np.ndarray:
    """(H, W) bool: pixels next to a relative depth jump above ``rel_jump`` or a valid/invalid border."""
    z = np.asarray(depth_m, dtype=np.float64)
    valid = z > 0
    edge = np.zeros(z.shape, dtype=bool)
    for axis in (0, 1):
        a = np.take(z, range(z.shape[axis] - 1), axis=axis)
        b = np.take(z, range(1, z.shape[axis]), axis=axis)
        va = np.take(valid, range(z.shape[axis] - 1), axis=axis)
        vb = np.take(valid, range(1, z.shape[axis]), axis=axis)
        jump = (va != vb) | (va & vb & (np.abs(a - b) > rel_jump * np.minimum(a, b)))
        sl_a = [slice(None)] * 2
        sl_b = [slice(None)] * 2
        sl_a[axis], sl_b[axis] = slice(0, -1), slice(1, None)
        edge[tuple(sl_a)] |= jump
        edge[tuple(sl_b)] |= jump
    for _ in range(dilate_px):
        grown = edge.copy()
        grown[1:] |= edge[:-1]
        grown[:-1] |= edge[1:]
        grown[:, 1:] |= edge[:, :-1]
        grown[:, :-1] |= edge[:, 1:]
        edge = grown
    return edge & valid


def apply_stereo_noise(
    depth_m: np.ndarray,
    image: np.ndarray | None,
    intrinsics: CameraIntrinsics,
    rng: np.random.Generator,
    baseline_m: float = 0.075,
    sigma_disparity_px: float = 0.1,
    blob_px: int = 2,
    edge_dropout: float = 0.7,
    edge_rel_jump: float = 0.03,
    hole_fraction: float = 0.005,
    hole_radius_px: int = 3,
    dark_threshold: float = 0.03,
    min_depth_m: float = 0.2,
    max_depth_m: float = 10.0,
) -> np.ndarray:
    """Noisy (H, W) float32 depth in metres (0 = no data) from clean depth, as a stereo camera would report it.

    Args:
        depth_m: (H, W) clean camera-z depth in metres, 0 = no data.
        image: optional (H, W, 3) uint8 RGB: pixels darker than ``dark_threshold`` (fraction of 255) drop out.
        intrinsics: focal length ``fx`` (pixels) for the disparity model.
        rng: the only source of randomness.
        baseline_m: stereo baseline in metres (OAK-D: 0.075).
        sigma_disparity_px: disparity noise in pixels; ``sigma_z = z^2 * sigma_d / (fx * baseline_m)``.
        blob_px: half-width of the spatial correlation of the noise, pixels (0 = independent per pixel).
        edge_dropout: probability that a pixel at a depth edge reports no data.
        edge_rel_jump: relative depth change that makes an edge.
        hole_fraction: expected fraction of pixels that seed a random hole of radius ``hole_radius_px``.
        dark_threshold: image brightness below which matching fails.
        min_depth_m, max_depth_m: the sensor's working range; outside it there is no data.
    """
    z = np.asarray(depth_m, dtype=np.float64)
    if z.ndim != 2:
        raise ValueError(f"depth_m must be (H, W), got shape {z.shape}")
    if baseline_m <= 0 or sigma_disparity_px < 0:
        raise ValueError(f"baseline_m must be > 0 and sigma_disparity_px >= 0, got {baseline_m}, {sigma_disparity_px}")
    h, w = z.shape
    valid = z > 0
    white = rng.standard_normal((h, w))
    if blob_px > 0:
        white = _box_blur(white, blob_px) * (2 * blob_px + 1)  # keep unit variance after averaging k*k samples
    sigma_z = z * z * sigma_disparity_px / (intrinsics.fx * baseline_m)
    noisy = z + sigma_z * white
    drop = ~valid | (noisy < min_depth_m) | (noisy > max_depth_m)
    drop |= depth_edges(z, edge_rel_jump) & (rng.random((h, w)) < edge_dropout)
    if image is not None:
        img = np.asarray(image)
        if img.shape[:2] != (h, w):
            raise ValueError(f"image must be {h}x{w} like depth_m, got shape {img.shape}")
        lum = (img.reshape(h, w, -1)[..., :3].astype(np.float64).mean(-1)) / 255.0
        drop |= lum < dark_threshold
    seeds = rng.random((h, w)) < hole_fraction
    if seeds.any() and hole_radius_px > 0:
        drop |= _box_blur(seeds.astype(np.float64), hole_radius_px) > 0
    return np.where(drop, 0.0, noisy).astype(np.float32)
