"""Letterboxing, augmentation and training targets for the detector (numpy + OpenCV).

Augmentation warps an image and its instance-id map (``sygrid.train.detector.data.load_instances``) with the same
affine (nearest neighbour for the ids), so masks and boxes stay consistent through scaling, rotation, flips,
translation and mosaic without clipping polygons; boxes and stride-4 mask targets are then read off the warped id
map. Mask targets are the fraction of each stride-4 cell the instance covers (soft targets: small parts are only a
few cells wide), except where the instance is thinner than a cell (``thin_cells``): there the target is 1, so that
the decoded mask (coverage resampled bilinearly, threshold 0.5) keeps a strap, a wire or a sheet seen edge on instead
of losing it.

Scale: images are scaled as the runtime letterbox into the model's input side (``imgsz``) scales them, times a
random zoom; the training canvas may be smaller than ``imgsz``, which makes it a crop at the runtime's object
scale, centred on the labelled parts (a bin of parts fills a small part of a frame, the rest is floor).

Randomness: each example draws from ``np.random.default_rng([seed, epoch, index])``, so an epoch is the same
whatever order or process it is built in, and a resumed run sees the same data as an uninterrupted one.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial

import cv2
import numpy as np
from scipy import ndimage

from sygrid.letterbox import PAD_VALUE, Letterbox, letterbox
from sygrid.letterbox import letterbox_geometry as _letterbox_geometry
from sygrid.train.detector.config import AugmentConfig
from sygrid.train.detector.data import DetectionDataset, load_instances

MASK_STRIDE = 4  # default prototype resolution: 1/4 of the network input (ModelConfig.proto_stride)

# (split, index) -> image, instance-id map, classes, as ``load_instances`` returns them (``cache.InstanceCache.load``)
Loader = Callable[[str, int], tuple[np.ndarray, np.ndarray, np.ndarray]]


# --------------------------------------------------------------------------------------------------- geometry
def letterbox_geometry(image_hw: tuple[int, int], size: int, stride: int | None) -> Letterbox:
    """Where an image goes in a square network input of at most ``size`` x ``size`` (the runtime's rule)."""
    return _letterbox_geometry(image_hw, (size, size), stride)


def _cv_affine(A: np.ndarray) -> np.ndarray:
    """3x3 affine in continuous pixel coordinates (pixel i spans [i, i+1)) -> OpenCV's 2x3 (pixel i at i), so that
    a pure scaling matches ``cv2.resize``'s sampling grid."""
    half = np.array([[1.0, 0.0, 0.5], [0.0, 1.0, 0.5], [0.0, 0.0, 1.0]])
    return (np.linalg.inv(half) @ A @ half)[:2]


def _translation(tx: float, ty: float) -> np.ndarray:
    return np.array([[1.0, 0.0, tx], [0.0, 1.0, ty], [0.0, 0.0, 1.0]])


# ------------------------------------------------------------------------------------------------ augmentation
def _random_geometry(
    rng: np.random.Generator, cfg: AugmentConfig, size: int, center: tuple[float, float]
) -> np.ndarray:
    """3x3 map (continuous pixels) that puts ``center`` (of an already scaled source) at the middle of a ``size``
    output, with flips, a rotation and a zoom about it, and a random shift."""
    cx, cy = center
    angle = math.radians(rng.uniform(-cfg.degrees, cfg.degrees))
    if rng.random() < cfg.rot90_p:
        angle += math.pi / 2 * int(rng.integers(1, 4))
    zoom = rng.uniform(1.0 - cfg.scale, 1.0 + cfg.scale)
    fx = -1.0 if rng.random() < cfg.flip_lr else 1.0
    fy = -1.0 if rng.random() < cfg.flip_ud else 1.0
    c, s = math.cos(angle) * zoom, math.sin(angle) * zoom
    linear = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ np.diag([fx, fy, 1.0])
    shift = rng.uniform(-cfg.translate, cfg.translate, size=2) * size
    return _translation(size / 2 + shift[0], size / 2 + shift[1]) @ linear @ _translation(-cx, -cy)


def _focus_point(ids: np.ndarray, cfg: AugmentConfig, rng: np.random.Generator) -> tuple[float, float]:
    """Source pixel to centre a training crop on: with probability ``cfg.focus`` a random point of the box around
    all labelled instances (the parts sit in a bin that fills a small part of the frame), else the image centre."""
    h, w = ids.shape
    if cfg.focus > 0 and rng.random() < cfg.focus:
        ys, xs = np.nonzero(ids[::4, ::4])  # a coarse look is enough to find the pile
        if len(xs):
            x0, x1 = xs.min() * 4.0, xs.max() * 4.0 + 4.0
            y0, y1 = ys.min() * 4.0, ys.max() * 4.0 + 4.0
            return float(rng.uniform(x0, x1)), float(rng.uniform(y0, y1))
    return w / 2.0, h / 2.0


def _warp(image: np.ndarray, ids: np.ndarray, A: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    M = _cv_affine(A)
    out = cv2.warpAffine(image, M, (size, size), flags=cv2.INTER_LINEAR, borderValue=(PAD_VALUE,) * 3)
    out_ids = cv2.warpAffine(ids, M, (size, size), flags=cv2.INTER_NEAREST, borderValue=0)
    return out, out_ids


def _colour(image: np.ndarray, cfg: AugmentConfig, rng: np.random.Generator) -> np.ndarray:
    """HSV gains (lookup tables on OpenCV's 8-bit HSV), brightness/contrast, blur and sensor noise."""
    gains = rng.uniform(-1.0, 1.0, 3) * np.array([cfg.hsv_h, cfg.hsv_s, cfg.hsv_v]) + 1.0
    if np.any(gains != 1.0):
        hue, sat, val = cv2.split(cv2.cvtColor(image, cv2.COLOR_RGB2HSV))
        x = np.arange(256, dtype=np.float32)
        lut_h = ((x * gains[0]) % 180).astype(np.uint8)
        lut_s = np.clip(x * gains[1], 0, 255).astype(np.uint8)
        lut_v = np.clip(x * gains[2], 0, 255).astype(np.uint8)
        hsv = cv2.merge((cv2.LUT(hue, lut_h), cv2.LUT(sat, lut_s), cv2.LUT(val, lut_v)))
        image = cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)
    alpha = rng.uniform(1.0 - cfg.contrast, 1.0 + cfg.contrast)
    beta = rng.uniform(-cfg.brightness, cfg.brightness) * 255.0
    if alpha != 1.0 or beta != 0.0:
        mean = float(image.mean())  # contrast about the mean grey: brightness stays put
        image = cv2.convertScaleAbs(image, alpha=alpha, beta=beta + (1.0 - alpha) * mean)
    if rng.random() < cfg.blur_p:
        image = cv2.GaussianBlur(image, (0, 0), sigmaX=rng.uniform(0.3, max(cfg.blur_sigma_px, 0.3)))
    if rng.random() < cfg.noise_p:
        sigma = rng.uniform(0.0, cfg.noise_sigma)
        noise = rng.normal(0.0, sigma, image.shape).astype(np.float32)
        image = np.clip(image.astype(np.float32) + noise, 0, 255).astype(np.uint8)
    return image


@dataclass(frozen=True)
class Example:
    """One network input with its targets. ``image``: (S, S, 3) uint8 RGB (or the letterboxed shape in
    validation); ``classes`` (n,) int64; ``boxes_xyxy`` (n, 4) float32 input pixels; ``masks`` (n, H/4, W/4)
    float32 coverage in [0, 1]."""

    image: np.ndarray
    classes: np.ndarray
    boxes_xyxy: np.ndarray
    masks: np.ndarray


def targets_from_ids(
    ids: np.ndarray,
    classes: np.ndarray,
    min_area_px: int = 4,
    min_side_px: float = 2.0,
    mask_stride: int = MASK_STRIDE,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Boxes and mask coverage at ``mask_stride`` (the prototypes' stride) of every instance left in an id map
    (dropping slivers below ``min_area_px`` pixels or ``min_side_px`` box side). Returns ``(classes, boxes_xyxy,
    masks)`` as in ``Example``."""
    h, w = ids.shape
    if h % mask_stride or w % mask_stride:
        raise ValueError(f"id map {h}x{w}: both sides must be multiples of {mask_stride}")
    mh, mw = h // mask_stride, w // mask_stride
    areas = np.bincount(ids.ravel(), minlength=len(classes) + 1)
    slices = ndimage.find_objects(ids, max_label=len(classes))
    keep_cls, boxes, masks = [], [], []
    for k, sl in enumerate(slices):
        if sl is None or areas[k + 1] < min_area_px:
            continue
        y0, y1, x0, x1 = sl[0].start, sl[0].stop, sl[1].start, sl[1].stop
        if min(x1 - x0, y1 - y0) < min_side_px:
            continue
        # Coverage of each mask cell, computed on the box expanded to whole cells.
        cy0, cx0 = y0 // mask_stride, x0 // mask_stride
        cy1, cx1 = -(-y1 // mask_stride), -(-x1 // mask_stride)
        region = ids[cy0 * mask_stride : cy1 * mask_stride, cx0 * mask_stride : cx1 * mask_stride] == k + 1
        cover = region.reshape(cy1 - cy0, mask_stride, cx1 - cx0, mask_stride).mean(axis=(1, 3), dtype=np.float32)
        cover[thin_cells(cover)] = 1.0
        mask = np.zeros((mh, mw), dtype=np.float32)
        mask[cy0:cy1, cx0:cx1] = cover
        keep_cls.append(int(classes[k]))
        boxes.append((x0, y0, x1, y1))
        masks.append(mask)
    if not keep_cls:
        return np.zeros(0, np.int64), np.zeros((0, 4), np.float32), np.zeros((0, mh, mw), np.float32)
    return np.asarray(keep_cls, np.int64), np.asarray(boxes, np.float32), np.stack(masks)


def thin_cells(cover: np.ndarray) -> np.ndarray:
    """The cells where an instance is thinner than a cell: covered less than half, but no less than by any of its
    eight neighbours (a ridge of the coverage ``cover``, (h, w) in [0, 1], zero outside the instance's box). A part's
    edge is never one (the cell inside it is covered more); a strap or a wire one pixel wide, or a part inside one
    cell, always is. Where the coverage is the target, such a part has no cell above 0.5 and its decoded mask would
    be empty. Returns (h, w) bool."""
    neighbours = ndimage.maximum_filter(cover, size=3, mode="constant", cval=0.0)
    return (cover > 0) & (cover < 0.5) & (cover >= neighbours)


def train_example(
    dataset: DetectionDataset,
    index: int,
    size: int,
    cfg: AugmentConfig,
    rng: np.random.Generator,
    mosaic: bool = True,
    imgsz: int | None = None,
    mask_stride: int = MASK_STRIDE,
    load: Loader | None = None,
) -> Example:
    """Training example ``index`` of the train split on a ``size`` x ``size`` canvas (a multiple of 32), augmented by
    ``cfg`` with ``rng``; a mosaic of four images with probability ``cfg.mosaic`` (when ``mosaic``).

    ``imgsz``: the input side the model will run at (default ``size``). Images are scaled as the runtime letterbox
    into ``imgsz`` scales them (times the random zoom), so a canvas smaller than ``imgsz`` is a crop at the
    runtime's object scale: with ``cfg.focus``, centred on the labelled parts rather than the empty floor.
    ``mask_stride``: the mask targets' stride (the model's ``proto_stride``). ``load``: where images come from
    (default: ``load_instances`` from the files).
    """
    imgsz = imgsz or size
    load = load or partial(load_instances, dataset)
    n = len(dataset.images["train"])
    if mosaic and cfg.mosaic > 0 and rng.random() < cfg.mosaic:
        picks = [index, *(int(i) for i in rng.integers(0, n, size=3))]
        image, ids, classes = _mosaic(load, picks, size, imgsz, cfg, rng)
    else:
        src, src_ids, classes = load("train", index)
        r = imgsz / max(src.shape[:2])
        fx, fy = _focus_point(src_ids, cfg, rng)
        A = _random_geometry(rng, cfg, size, (fx * r, fy * r)) @ np.diag([r, r, 1.0])
        image, ids = _warp(src, src_ids, A, size)
    image = _colour(image, cfg, rng)
    classes, boxes, masks = targets_from_ids(ids, classes, mask_stride=mask_stride)
    return Example(np.ascontiguousarray(image), classes, boxes, masks)


def _mosaic(
    load: Loader, picks: list[int], size: int, imgsz: int, cfg: AugmentConfig, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Four images around a random junction of a 2S x 2S canvas, each cropped to its quadrant with its focus point
    in the middle of the quadrant's part of the central S x S window; then the random geometry from the canvas to
    the S x S output. Each image is warped straight to the output (one interpolation); an output pixel takes the
    image of the quadrant its canvas pre-image lies in."""
    xc, yc = rng.uniform(0.5 * size, 1.5 * size, size=2)
    A_out = _random_geometry(rng, cfg, size, (size, size))
    inv = np.linalg.inv(A_out)
    grid = np.arange(size, dtype=np.float64) + 0.5
    canvas_x = inv[0, 0] * grid[None, :] + inv[0, 1] * grid[:, None] + inv[0, 2]
    canvas_y = inv[1, 0] * grid[None, :] + inv[1, 1] * grid[:, None] + inv[1, 2]
    quadrant = (canvas_x >= xc).astype(np.int8) + 2 * (canvas_y >= yc).astype(np.int8)
    inside = (canvas_x >= 0) & (canvas_x < 2 * size) & (canvas_y >= 0) & (canvas_y < 2 * size)
    image = np.full((size, size, 3), PAD_VALUE, dtype=np.uint8)
    ids = np.zeros((size, size), dtype=np.int32)
    all_classes = []
    lo, hi = 0.5 * size, 1.5 * size  # the central window of the canvas
    for q, idx in enumerate(picks):
        src, src_ids, classes = load("train", idx)
        r = imgsz / max(src.shape[:2])
        fx, fy = _focus_point(src_ids, cfg, rng)
        tx = (lo + xc) / 2 if q in (0, 2) else (xc + hi) / 2
        ty = (lo + yc) / 2 if q in (0, 1) else (yc + hi) / 2
        A_tile = A_out @ _translation(tx - fx * r, ty - fy * r) @ np.diag([r, r, 1.0])
        tile_image, tile_ids = _warp(src, src_ids, A_tile, size)
        sel = (quadrant == q) & inside
        image[sel] = tile_image[sel]
        offset = sum(len(c) for c in all_classes)
        ids[sel] = np.where(tile_ids[sel] > 0, tile_ids[sel] + offset, 0)
        all_classes.append(classes)
    return image, ids, np.concatenate(all_classes)


def val_example(
    dataset: DetectionDataset,
    index: int,
    size: int,
    stride: int,
    mask_stride: int = MASK_STRIDE,
    load: Loader | None = None,
) -> tuple[Example, Letterbox]:
    """Validation example ``index``: letterboxed as the runtime does for a dynamic-input model (no augmentation);
    ``load`` as in ``train_example``."""
    src, src_ids, classes = (load or partial(load_instances, dataset))("val", index)
    geometry = letterbox_geometry(src.shape[:2], size, stride)
    image = letterbox(src, geometry)
    ids = letterbox(src_ids, geometry, cv2.INTER_NEAREST)
    classes, boxes, masks = targets_from_ids(ids, classes, mask_stride=mask_stride)
    return Example(image, classes, boxes, masks), geometry


def epoch_order(n: int, seed: int, epoch: int) -> np.ndarray:
    """The shuffled order of ``n`` training images in ``epoch`` (depends only on seed and epoch)."""
    return np.random.default_rng([seed, epoch, 0x5EED]).permutation(n)


def example_rng(seed: int, epoch: int, index: int) -> np.random.Generator:
    """The random stream of one training example."""
    return np.random.default_rng([seed, epoch, index])
