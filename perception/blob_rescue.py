"""Poses for the parts the detector's classes miss: every model tried on the depth that no accepted pose explains.

A bin's last parts are often ones the detector misses in a resting pose rare in its training renders (a gear
standing on its rim, a bracket resting on both sheet edges like a tent), or names with a wrong class whose pose the
verification refuses. The depth still shows each of them as a connected region of pixels above the bin's floor
(``pile_blobs``). A stereo camera's noisy depth draws a region's outline a few pixels off, which the verification's
outline check refuses, so the outline is taken from the colour image: OpenCV's GrabCut started from the region
(``outline_from_image``). Each region becomes a mask without a class, fitted with every model's own pose strategy;
the verification (``perception.verify``: the model at the fitted pose against the depth and that mask) keeps the
model that agrees best, or none. Nothing is accepted that the verification would not accept from a detection.

Every model per region costs what a frame's worth of detections does, so a caller asks for it only when a look
would otherwise leave parts in the bin (the picker: nothing posed, or nothing safe to pick among the poses).
Regions are found with OpenCV's connected components on a height-above-floor mask; the camera's floor plane and
the bin's floor polygon are the pipeline's (``PerceptionPipeline``'s ``floor_plane_camera``, floor bounds).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from perception.depth_tare import floor_polygon
from perception.mask_cleanup import floor_height_m
from perception.results import ObjectPose
from sygrid.camera import CameraIntrinsics


@dataclass(frozen=True)
class RescueConfig:
    """Attributes:
    min_height_m: depth pixels more than this above the floor plane can be the pile [m] (less than the thinnest
        part lying flat: a 2 mm sheet); the pipeline passes its floor margin.
    noise_sigmas: a region is seeded only by pixels more than this many of the depth's noise sigmas above
        ``min_height_m`` (a stereo camera's floor shows patches a few disparity steps high; exact depth has none).
    grow_px: a seeded region takes in the pixels above ``min_height_m`` this close to it (its part's low rim).
    speckle_px: the seed mask is opened (eroded, then grown back) by this many pixels: single noisy pixels go.
    wall_margin_px: the floor polygon is shrunk by this many pixels, so that the walls' foot is not a region.
    explained_margin_px: pixels this close to an accepted pose's mask are that part's (its mask's ragged edge).
    min_region_px: smaller seeds are noise or a sliver no model can be fitted to (pixels).
    outline_ring_px: GrabCut's start: the region eroded by half of it is the part, the region probably the part, a ring
        this wide around it probably not, the rest of its box not (pixels; 0: the depth's outline as it is).
    max_regions: at most this many regions are fitted per call, the largest first (each costs every model's fit).
    """

    min_height_m: float = 0.0015
    noise_sigmas: float = 4.0
    grow_px: int = 4
    speckle_px: int = 1
    wall_margin_px: int = 4
    explained_margin_px: int = 3
    min_region_px: int = 60
    outline_ring_px: int = 8
    max_regions: int = 3

    def __post_init__(self) -> None:
        if not (self.min_height_m > 0 and self.noise_sigmas >= 0):
            raise ValueError(
                f"RescueConfig: need min_height_m > 0, noise_sigmas >= 0; got {self.min_height_m}, {self.noise_sigmas}"
            )
        for name in ("grow_px", "speckle_px", "wall_margin_px", "explained_margin_px", "outline_ring_px"):
            if getattr(self, name) < 0:
                raise ValueError(f"RescueConfig.{name} must be >= 0, got {getattr(self, name)}")
        for name in ("min_region_px", "max_regions"):
            if getattr(self, name) < 1:
                raise ValueError(f"RescueConfig.{name} must be >= 1, got {getattr(self, name)}")


def pile_blobs(
    depth_m: np.ndarray,
    intrinsics: CameraIntrinsics,
    floor_plane_camera: np.ndarray,
    floor_bounds_camera_m: np.ndarray,
    explained: np.ndarray | None = None,
    config: RescueConfig | None = None,
    sigma_inv_m: float = 0.0,
) -> list[np.ndarray]:
    """The pile's connected regions that nothing explains, largest first, as ``(H, W)`` bool masks.

    The pile: the depth pixels (``depth_m`` metres, 0 = none) more than ``min_height_m`` above the floor plane
    ``(a, b, c, d)`` (camera frame), inside the floor's image polygon (``floor_bounds_camera_m`` ``(n, 3)``, e.g. the
    bin's inner corners, projected onto the plane) shrunk by ``wall_margin_px``, and off ``explained`` (``(H, W)``
    bool: the accepted poses' masks) grown by ``explained_margin_px``. A region is seeded by the pile's pixels also
    ``noise_sigmas`` depth sigmas higher (``sigma_inv_m``: the depth's noise in inverse depth, 1/m, so that the
    sigma at depth z is ``z^2 sigma_inv_m``; 0 for exact depth), opened by ``speckle_px``; seeds grown by ``grow_px``
    that touch are one region, which is the pile's pixels inside them. At most ``max_regions`` regions of at least
    ``min_region_px`` pixels; none when the floor is out of view."""
    cfg = config or RescueConfig()
    depth = np.asarray(depth_m, dtype=float)
    polygon = floor_polygon(floor_plane_camera, floor_bounds_camera_m, intrinsics)
    if polygon is None:
        return []
    inside = np.zeros(depth.shape, dtype=np.uint8)
    cv2.fillConvexPoly(inside, np.round(polygon).astype(np.int32), 1)
    inside = cv2.erode(inside, _disc(cfg.wall_margin_px)).astype(bool)
    if explained is not None and explained.any():
        inside &= ~cv2.dilate(explained.astype(np.uint8), _disc(cfg.explained_margin_px)).astype(bool)
    with np.errstate(invalid="ignore"):
        above = floor_height_m(depth, intrinsics, floor_plane_camera) - cfg.min_height_m
        pile = (above > 0) & inside
        seeds = pile & (above > cfg.noise_sigmas * sigma_inv_m * depth**2)
    seeds = cv2.morphologyEx(seeds.astype(np.uint8), cv2.MORPH_OPEN, _disc(cfg.speckle_px))
    # grown before they are told apart: the seeds of one part split by a stereo dropout or a thin edge join up
    _, labels, stats, _ = cv2.connectedComponentsWithStats(cv2.dilate(seeds, _disc(cfg.grow_px)), connectivity=8)
    regions = [(labels == k) & pile for k in range(1, len(stats))]
    regions = sorted((r for r in regions if r.sum() >= cfg.min_region_px), key=lambda r: -int(r.sum()))
    return regions[: cfg.max_regions]


def outline_from_image(rgb: np.ndarray, region: np.ndarray, ring_px: int) -> np.ndarray:
    """``(H, W)`` bool: the part in ``region`` (``(H, W)`` bool, from the depth) outlined in the colour image
    ``rgb`` (``(H, W, 3)`` uint8) by GrabCut (5 iterations) on the region's box grown by ``3 ring_px``: the region
    eroded by ``ring_px // 2`` is the part, the rest of the region probably the part, a ring of ``ring_px`` around it
    probably not, the rest not. Never outside region + ring; the region itself where GrabCut finds no part or
    cannot run (``ring_px`` 0, a region at the image's edge with no background)."""
    if ring_px <= 0:
        return region
    ys, xs = np.nonzero(region)
    h, w = region.shape
    x0, y0 = max(int(xs.min()) - 3 * ring_px, 0), max(int(ys.min()) - 3 * ring_px, 0)
    x1, y1 = min(int(xs.max()) + 3 * ring_px + 1, w), min(int(ys.max()) + 3 * ring_px + 1, h)
    inside = region[y0:y1, x0:x1].astype(np.uint8)
    labels = np.full(inside.shape, cv2.GC_BGD, np.uint8)
    labels[cv2.dilate(inside, _disc(ring_px)) > 0] = cv2.GC_PR_BGD
    labels[inside > 0] = cv2.GC_PR_FGD
    labels[cv2.erode(inside, _disc(ring_px // 2)) > 0] = cv2.GC_FGD
    try:
        cv2.grabCut(
            np.ascontiguousarray(rgb[y0:y1, x0:x1]), labels, None, np.zeros((1, 65)), np.zeros((1, 65)), 5,
            cv2.GC_INIT_WITH_MASK,
        )  # fmt: skip
    except cv2.error:  # a colour model needs pixels of both kinds
        return region
    part = (labels == cv2.GC_FGD) | (labels == cv2.GC_PR_FGD)
    if not part.any():
        return region
    out = np.zeros_like(region)
    out[y0:y1, x0:x1] = part
    return out


def best_verified(poses: list[ObjectPose | None]) -> ObjectPose | None:
    """The accepted pose (``verified`` True) the verification is most confident in; None when it accepted none."""
    accepted = [p for p in poses if p is not None and p.verified]
    return max(accepted, key=lambda p: p.score) if accepted else None


def explained_mask(poses: list[ObjectPose], shape: tuple[int, int]) -> np.ndarray:
    """``(H, W)`` bool: the union of the poses' detection masks (the depth they explain)."""
    out = np.zeros(shape, dtype=bool)
    for p in poses:
        m = p.detection.mask
        if m is not None and m.shape == shape:
            out |= m
    return out


def _disc(radius_px: int) -> np.ndarray:
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius_px + 1, 2 * radius_px + 1))
