"""Procedural skies: equirectangular environment maps of the ``sky`` families, in numpy, from a seed.

A map is (H, 2H, 3) float32 linear radiance in Mitsuba's ``envmap`` layout: row 0 looks straight up (the map's +y),
the middle row along the horizon, columns sweep the azimuth. Its mean radiance over the sphere is about 1 (so the
lighting knob's ``environment_strength`` sets the light level); the renderer rotates it about the world's up axis.
"""

from __future__ import annotations

import numpy as np


def _angles(rows: int) -> tuple[np.ndarray, np.ndarray]:
    """(H, 2H) elevation (rad, +pi/2 at the top row) and azimuth (rad, 0 .. 2 pi) of each pixel centre."""
    elevation = np.pi / 2 - (np.arange(rows) + 0.5) / rows * np.pi
    azimuth = (np.arange(2 * rows) + 0.5) / (2 * rows) * 2 * np.pi
    return np.meshgrid(elevation, azimuth, indexing="ij")


def _normalised(radiance: np.ndarray, elevation: np.ndarray) -> np.ndarray:
    """The map scaled to a mean radiance of 1 over the sphere (pixels weighted by their solid angle)."""
    weights = np.cos(elevation)[..., None]
    mean = float((radiance * weights).sum() / (weights.sum() * 3))
    return (radiance / max(mean, 1e-9)).astype(np.float32)


def _gradient(elevation: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Zenith blue-white, a bright horizon, a dim brown-grey ground."""
    zenith = np.array([0.55, 0.7, 1.0]) * rng.uniform(0.8, 1.2)
    horizon = np.array([1.0, 0.97, 0.9]) * rng.uniform(0.9, 1.3)
    ground = np.array([0.16, 0.14, 0.12]) * rng.uniform(0.5, 1.5)
    up = np.clip(elevation / (np.pi / 2), 0.0, 1.0)[..., None]
    sky = horizon + (zenith - horizon) * np.sqrt(up)
    return np.where(elevation[..., None] >= 0, sky, ground)


def sky_map(family: str, rows: int, seed: int, sun_elevation_deg: float = 45.0) -> np.ndarray | None:
    """(rows, 2 rows, 3) float32 map of ``family``, or None for ``uniform_sky`` (a constant emitter: no map)."""
    rng = np.random.default_rng(seed)
    elevation, azimuth = _angles(int(rows))
    if family == "uniform_sky":
        return None
    if family == "gradient_sky":
        return _normalised(_gradient(elevation, rng), elevation)
    if family == "sun_sky":
        # A sun of 4 degrees (a couple of pixels at the default size, so it stays sampled) bringing about as much
        # light as the rest of the sky: hard shadows.
        sky = _gradient(elevation, rng)
        sun_el, sun_az = np.radians(sun_elevation_deg), rng.uniform(0, 2 * np.pi)
        cos_gap = np.sin(elevation) * np.sin(sun_el) + np.cos(elevation) * np.cos(sun_el) * np.cos(azimuth - sun_az)
        disc = cos_gap >= np.cos(np.radians(max(2.0, 180.0 / rows)))
        weights = np.cos(elevation)
        share = float(weights[disc].sum() / weights.sum())
        sky[disc] += np.array([1.0, 0.95, 0.85]) * rng.uniform(0.5, 1.5) / max(share, 1e-6)
        return _normalised(sky, elevation)
    if family == "window_sky":
        # A dim hall with bright windows near the horizon and strip lights above.
        hall = np.full((*elevation.shape, 3), 0.05) * rng.uniform(0.5, 1.5)
        for _ in range(int(rng.integers(2, 6))):
            az0, width = rng.uniform(0, 2 * np.pi), rng.uniform(0.15, 0.6)
            lo = rng.uniform(-0.05, 0.35)
            hi = lo + rng.uniform(0.1, 0.4)
            gap = np.abs((azimuth - az0 + np.pi) % (2 * np.pi) - np.pi)
            hall[(gap < width / 2) & (elevation > lo) & (elevation < hi)] = rng.uniform(2.0, 6.0)
        for _ in range(int(rng.integers(0, 4))):
            az0 = rng.uniform(0, 2 * np.pi)
            gap = np.abs((azimuth - az0 + np.pi) % (2 * np.pi) - np.pi)
            hall[(gap < 0.08) & (elevation > 0.9)] = rng.uniform(4.0, 10.0)
        return _normalised(hall, elevation)
    raise ValueError(f"unknown sky family {family!r}")
