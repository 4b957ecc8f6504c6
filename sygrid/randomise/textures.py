"""Procedural surface textures in numpy: tileable bitmaps of the ``surface`` families and the wear mask of worn
paint, each a pure function of its parameters and an ``np.random.Generator`` (an item's record keeps the seed).

Every bitmap tiles (its left edge continues its right, its top its bottom), so a renderer can repeat it over a
surface of any size. Colours are linear reflectances in [0, 1]; ``base`` is the family's colour at the tile's mean.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy import ndimage

_METAL_GREY = np.array([0.55, 0.56, 0.58])


def tileable_noise(rng: np.random.Generator, size: int, cells: int, octaves: int = 4) -> np.ndarray:
    """(size, size) float32 fractal value noise in [0, 1] that tiles: ``octaves`` layers of random values on a
    ``cells``-wide periodic grid (doubling each layer, half the amplitude), interpolated with periodic cubics."""
    out = np.zeros((size, size), np.float64)
    amplitude, total = 1.0, 0.0
    for _ in range(octaves):
        cells = max(1, min(int(cells), size))
        grid = rng.random((cells, cells))
        out += amplitude * ndimage.zoom(grid, size / cells, order=3, mode="grid-wrap", grid_mode=True)[:size, :size]
        total += amplitude
        amplitude *= 0.5
        cells *= 2
    out /= total
    lo, hi = out.min(), out.max()
    return ((out - lo) / (hi - lo if hi > lo else 1.0)).astype(np.float32)


def _coords(size: int) -> tuple[np.ndarray, np.ndarray]:
    """(size, size) x and y in [0, 1) over the tile."""
    t = np.arange(size, dtype=np.float32) / size
    return np.meshgrid(t, t, indexing="xy")


def _streaks(rng: np.random.Generator, size: int, length_px: int) -> np.ndarray:
    """(size, size) white noise smeared along x over ``length_px`` pixels (tiling)."""
    white = rng.random((size, size)).astype(np.float32)
    return ndimage.uniform_filter1d(white, length_px, axis=1, mode="wrap")


def _shade(base: np.ndarray, factor: np.ndarray) -> np.ndarray:
    return np.clip(factor[..., None] * np.asarray(base, np.float32)[None, None, :], 0.0, 1.0).astype(np.float32)


def _plain(base: np.ndarray, size: int, rng: np.random.Generator) -> np.ndarray:
    return _shade(base, np.ones((size, size), np.float32))


def _wood(base: np.ndarray, size: int, rng: np.random.Generator) -> np.ndarray:
    """Planks along x: growth rings warped by noise, fine grain streaks, a darker seam between planks."""
    _, y = _coords(size)
    planks = int(rng.integers(2, 6))
    warp = tileable_noise(rng, size, 4, 3)
    rings = 0.5 + 0.5 * np.sin(2 * np.pi * (int(rng.integers(6, 18)) * y + 1.5 * warp + np.floor(y * planks) * 0.37))
    grain = _streaks(rng, size, max(3, size // 8))
    seam = np.abs((y * planks) % 1.0 - 0.5) > 0.48
    factor = 0.75 + 0.35 * rings + 0.4 * (grain - grain.mean())
    return _shade(base, np.where(seam, 0.45, factor))


def _concrete(base: np.ndarray, size: int, rng: np.random.Generator) -> np.ndarray:
    """Blotchy fractal noise, fine speckle and a few dark pores."""
    blotch = tileable_noise(rng, size, 4, 5)
    speckle = rng.random((size, size)).astype(np.float32)
    pores = rng.random((size, size)) < 0.004
    factor = 0.75 + 0.45 * blotch + 0.15 * (speckle - 0.5)
    return _shade(base, np.where(pores, 0.35, factor))


def _cardboard(base: np.ndarray, size: int, rng: np.random.Generator) -> np.ndarray:
    """Low-frequency blotches over faint corrugation ridges along y."""
    x, _ = _coords(size)
    ridges = 0.5 + 0.5 * np.sin(2 * np.pi * int(rng.integers(12, 40)) * x)
    blotch = tileable_noise(rng, size, 3, 3)
    return _shade(base, 0.85 + 0.25 * blotch - 0.08 * ridges)


def _brushed_metal(base: np.ndarray, size: int, rng: np.random.Generator) -> np.ndarray:
    """Streaks along x: white noise smeared over a quarter of the tile."""
    streaks = _streaks(rng, size, max(3, size // 4))
    streaks = (streaks - streaks.mean()) / (streaks.std() + 1e-6)
    return _shade(base, 1.0 + 0.06 * streaks)


def _painted_metal(base: np.ndarray, size: int, rng: np.random.Generator) -> np.ndarray:
    """Paint with slight mottling and bright scratches down to the metal."""
    out = _shade(base, 0.92 + 0.16 * tileable_noise(rng, size, 4, 3))
    for _ in range(int(rng.integers(3, 12))):
        start = rng.uniform(0, size, 2)
        angle = rng.uniform(0, np.pi)
        steps = np.arange(int(rng.uniform(0.1, 0.5) * size))
        cols = np.round(start[0] + steps * np.cos(angle)).astype(int) % size
        rows = np.round(start[1] + steps * np.sin(angle)).astype(int) % size
        out[rows, cols] = _METAL_GREY
    return out


def _rubber_mat(base: np.ndarray, size: int, rng: np.random.Generator) -> np.ndarray:
    """A raised pattern (diamonds or ribs) on a dark, slightly dusty mat."""
    x, y = _coords(size)
    k = int(rng.integers(4, 12))
    if rng.random() < 0.5:
        raised = (np.abs(np.sin(np.pi * k * (x + y))) + np.abs(np.sin(np.pi * k * (x - y)))) > 1.4
    else:
        raised = np.abs(np.sin(np.pi * k * x)) > 0.8
    dust = tileable_noise(rng, size, 6, 3)
    return _shade(base, np.where(raised, 1.5, 1.0) * (0.9 + 0.25 * dust))


SURFACE_TEXTURES: dict[str, Callable[[np.ndarray, int, np.random.Generator], np.ndarray]] = {
    "plain": _plain,
    "wood": _wood,
    "concrete": _concrete,
    "cardboard": _cardboard,
    "brushed_metal": _brushed_metal,
    "painted_metal": _painted_metal,
    "rubber_mat": _rubber_mat,
}
#: Each family's base colour as (hue, saturation, value); painted metal and plain draw their hue (None).
SURFACE_HSV: dict[str, tuple[float | None, float, float]] = {
    "plain": (None, 0.2, 0.35),
    "wood": (0.07, 0.6, 0.45),
    "concrete": (0.1, 0.06, 0.45),
    "cardboard": (0.09, 0.5, 0.55),
    "brushed_metal": (0.6, 0.03, 0.75),
    "painted_metal": (None, 0.65, 0.5),
    "rubber_mat": (0.0, 0.0, 0.07),
}


def surface_texture(family: str, base_rgb: np.ndarray, size: int, seed: int) -> np.ndarray:
    """(size, size, 3) float32 tileable reflectance of ``family`` around ``base_rgb``, from ``seed``."""
    if family not in SURFACE_TEXTURES:
        raise ValueError(f"unknown surface family {family!r}; valid: {sorted(SURFACE_TEXTURES)}")
    return SURFACE_TEXTURES[family](np.asarray(base_rgb, np.float32), int(size), np.random.default_rng(seed))


def wear_mask(wear: float, size: int, seed: int) -> np.ndarray:
    """(size, size, 1) float32 in [0, 1]: 1 where the metal shows through worn paint, on about ``wear`` of the
    tile, in blotches with a soft edge; tileable."""
    noise = tileable_noise(np.random.default_rng(seed), size, 4, 4)
    if wear <= 0:
        return np.zeros((size, size, 1), np.float32)
    threshold = float(np.quantile(noise, 1.0 - wear))
    return np.clip((noise - threshold) / 0.05 + 0.5, 0.0, 1.0).astype(np.float32)[..., None]
