"""Per-image ground truth: what every dataset writer and reader exchanges.

A rendered item gives a visible-instance id map ``ids_visib`` (h, w) int32 (0 = background, ``k + 1`` = instance
``k``), full (amodal) masks ``masks_full`` (n, h, w) bool, and poses ``T_camera_obj`` (n, 4, 4) in metres.
``annotate`` turns these into ``InstanceAnnotation``s with the BOP ``scene_gt_info`` quantities (boxes, pixel
counts, visible fraction). Boxes are ``[x, y, w, h]`` in pixels, ``w = x_max - x_min + 1`` (BOP convention).

Polygons (YOLO, COCO, the published SyGRID labels) are (n, 2) float arrays of ``[x, y]`` pixel coordinates
(pixel centres are integers, as ``cv2.findContours`` returns them).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from sygrid.camera import CameraIntrinsics

log = logging.getLogger(__name__)

DEFAULT_DEPTH_SCALE_MM = 0.1  # millimetres per unit of a uint16 depth PNG: 0.1 mm steps, 6.55 m range


@dataclass(frozen=True, eq=False)
class InstanceAnnotation:
    """One object instance in one image.

    ``T_camera_obj``: (4, 4) float64 pose of the object in the camera frame, metres. ``mask_visib``: (h, w) bool,
    the pixels where this instance is seen. ``mask_full``: (h, w) bool amodal silhouette (within the image), or
    None where the source has none (then ``px_count_all`` comes from ``visib_fract``). ``bbox_*``: ``(x, y, w, h)``
    pixels, ``(-1, -1, -1, -1)`` for an empty mask (BOP's convention). ``px_count_valid``: full-mask pixels with
    a depth measurement.
    """

    obj_id: int
    inst_id: int
    T_camera_obj: np.ndarray
    mask_visib: np.ndarray
    mask_full: np.ndarray | None
    bbox_visib: tuple[int, int, int, int]
    bbox_obj: tuple[int, int, int, int]
    px_count_all: int
    px_count_visib: int
    visib_fract: float
    px_count_valid: int = 0


@dataclass(frozen=True, eq=False)
class ImageAnnotation:
    """All instances of one image, with the camera that took it.

    ``scene_id`` / ``image_id`` name the image (BOP ``scene_id/image_id``; other writers build file names from
    them). ``depth_scale_mm``: millimetres per unit of the depth PNG when the image is written in BOP format.
    ``T_camera_world``: (4, 4) float64 pose of the scene's world frame in the camera frame, metres (a generated
    scene's world frame is the bin's: origin at the centre of its inner floor, z up), or None where unknown.
    """

    image_id: int
    intrinsics: CameraIntrinsics
    instances: tuple[InstanceAnnotation, ...]
    scene_id: int = 0
    depth_scale_mm: float = DEFAULT_DEPTH_SCALE_MM
    T_camera_world: np.ndarray | None = None

    @property
    def name(self) -> str:
        """``SSSSSS_IIIIII``: a file stem unique within a dataset (``image_name``)."""
        return image_name(self.scene_id, self.image_id)


def image_name(scene_id: int, image_id: int) -> str:
    """``SSSSSS_IIIIII``: the file stem of image ``scene_id/image_id`` in the YOLO and COCO layouts."""
    return f"{scene_id:06d}_{image_id:06d}"


# ------------------------------------------------------------------------------------------------- pure functions
def check_item(ann: ImageAnnotation, rgb: np.ndarray, depth_m: np.ndarray | None) -> None:
    """Raises ValueError when the arrays do not match the annotation's camera."""
    shape = (ann.intrinsics.height, ann.intrinsics.width)
    rgb = np.asarray(rgb)
    if rgb.shape != (*shape, 3) or rgb.dtype != np.uint8:
        raise ValueError(f"rgb: expected uint8 array of shape {(*shape, 3)}, got {rgb.dtype} {rgb.shape}")
    if depth_m is not None and np.shape(depth_m) != shape:
        raise ValueError(f"depth_m: expected shape {shape}, got {np.shape(depth_m)}")
    for inst in ann.instances:
        if np.shape(inst.mask_visib) != shape:
            raise ValueError(f"instance {inst.inst_id}: mask_visib shape {np.shape(inst.mask_visib)} != {shape}")


def mask_bbox(mask: np.ndarray) -> tuple[int, int, int, int]:
    """(h, w) bool -> ``(x, y, w, h)`` of the tight pixel box, ``(-1, -1, -1, -1)`` if the mask is empty."""
    ys, xs = np.nonzero(mask)
    if xs.size == 0:
        return (-1, -1, -1, -1)
    x0, y0 = int(xs.min()), int(ys.min())
    return (x0, y0, int(xs.max()) - x0 + 1, int(ys.max()) - y0 + 1)


def annotate(
    ids_visib: np.ndarray,
    masks_full: np.ndarray | None,
    T_camera_obj: np.ndarray,
    obj_ids: Sequence[int],
    intrinsics: CameraIntrinsics,
    depth_m: np.ndarray | None = None,
) -> list[InstanceAnnotation]:
    """Annotations of ``n`` instances from a rendered item.

    Args:
        ids_visib: (h, w) int32 visible-instance map, 0 = background, ``k + 1`` = instance ``k``.
        masks_full: (n, h, w) bool amodal masks, or None (then ``px_count_all``/``bbox_obj`` use the visible mask).
        T_camera_obj: (n, 4, 4) poses in metres.
        obj_ids: (n,) BOP object id of each instance.
        intrinsics: the camera; its size must match the maps.
        depth_m: (h, w) float depth in metres (0 = no data) for ``px_count_valid``; None counts every pixel valid.

    Raises:
        ValueError: shapes disagree, or a visible pixel lies outside its instance's full mask.
    """
    ids_visib = np.asarray(ids_visib)
    T_camera_obj = np.asarray(T_camera_obj, dtype=np.float64)
    n = len(obj_ids)
    shape = (intrinsics.height, intrinsics.width)
    if ids_visib.shape != shape:
        raise ValueError(f"ids_visib: expected shape {shape} (intrinsics height, width), got {ids_visib.shape}")
    if T_camera_obj.shape != (n, 4, 4):
        raise ValueError(f"T_camera_obj: expected shape ({n}, 4, 4) for {n} obj_ids, got {T_camera_obj.shape}")
    if masks_full is not None:
        masks_full = np.asarray(masks_full, dtype=bool)
        if masks_full.shape != (n, *shape):
            raise ValueError(f"masks_full: expected shape {(n, *shape)}, got {masks_full.shape}")
    if depth_m is not None and np.shape(depth_m) != shape:
        raise ValueError(f"depth_m: expected shape {shape}, got {np.shape(depth_m)}")
    id_max = int(ids_visib.max(initial=0))
    if id_max > n or int(ids_visib.min(initial=0)) < 0:
        raise ValueError(f"ids_visib: values must lie in [0, {n}] for {n} instances, got up to {id_max}")
    valid = np.ones(shape, dtype=bool) if depth_m is None else np.asarray(depth_m) > 0

    out = []
    for k in range(n):
        visib = ids_visib == k + 1
        full = visib if masks_full is None else masks_full[k]
        outside = int(np.count_nonzero(visib & ~full))
        if outside:
            raise ValueError(
                f"instance {k} (obj_id {obj_ids[k]}): {outside} visible pixels lie outside its full mask; "
                "the visible id map and the full masks must come from the same rasterisation"
            )
        px_all, px_visib = int(np.count_nonzero(full)), int(np.count_nonzero(visib))
        out.append(
            InstanceAnnotation(
                obj_id=int(obj_ids[k]),
                inst_id=k,
                T_camera_obj=T_camera_obj[k].copy(),
                mask_visib=visib,
                mask_full=None if masks_full is None else full.copy(),
                bbox_visib=mask_bbox(visib),
                bbox_obj=mask_bbox(full),
                px_count_all=px_all,
                px_count_visib=px_visib,
                visib_fract=px_visib / px_all if px_all else 0.0,
                px_count_valid=int(np.count_nonzero(full & valid)),
            )
        )
    return out


def mask_to_polygons(mask: np.ndarray) -> list[np.ndarray]:
    """(h, w) bool -> one (n, 2) float polygon per connected part (outer contours; holes are not represented).

    Parts are sorted by area, largest first. Single-pixel parts give one-point polygons.
    """
    mask = np.asarray(mask)
    if mask.ndim != 2:
        raise ValueError(f"mask: expected a 2-D (h, w) array, got shape {mask.shape}")
    contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    contours = sorted(contours, key=lambda c: (-cv2.contourArea(c), -len(c)))
    return [c.reshape(-1, 2).astype(np.float64) for c in contours]


def merge_polygons(polygons: Sequence[np.ndarray]) -> np.ndarray:
    """Joins polygons into one by zero-width bridges, as the SyGRID labels (and ultralytics' JSON2YOLO) do.

    YOLO segmentation allows one polygon per instance, so a mask split by an occluder is written as a single
    outline: starting from the first (largest) part, each remaining part is attached where it comes closest to the
    outline built so far. The outline walks from its point ``a`` to the part's nearest point ``b``, around the
    whole part back to ``b``, and back to ``a``: the bridge ``a-b`` is traversed once each way, so it encloses no
    area and a scanline fill rasterises the union of the parts (plus the one-pixel bridge lines).

    Returns (m, 2) float; an empty (0, 2) array for no polygons.
    """
    parts = [np.asarray(p, dtype=np.float64).reshape(-1, 2) for p in polygons if len(p)]
    if not parts:
        return np.zeros((0, 2))
    merged = parts[0]
    rest = parts[1:]
    while rest:
        best = None  # (distance^2, part index, index in merged, index in part)
        for j, part in enumerate(rest):
            d2 = ((merged[:, None, :] - part[None, :, :]) ** 2).sum(-1)
            a, b = np.unravel_index(int(np.argmin(d2)), d2.shape)
            if best is None or d2[a, b] < best[0]:
                best = (float(d2[a, b]), j, int(a), int(b))
        _, j, a, b = best
        part = rest.pop(j)
        loop = np.concatenate([np.roll(part, -b, axis=0), part[b : b + 1]])
        merged = np.concatenate([merged[: a + 1], loop, merged[a:]])
    return merged


def mask_holes(mask: np.ndarray) -> list[np.ndarray]:
    """(h, w) bool -> one (n, 2) float polygon per hole of the mask (background enclosed by it: the inside of a
    washer or a nut, a strap's loop), as the contours of the mask pixels around each hole; largest first."""
    contours, hierarchy = cv2.findContours(np.asarray(mask).astype(np.uint8), cv2.RETR_CCOMP, cv2.CHAIN_APPROX_SIMPLE)
    if hierarchy is None:
        return []
    holes = [c for c, h in zip(contours, hierarchy[0], strict=True) if h[3] >= 0]  # a parent: an inner contour
    holes = sorted(holes, key=lambda c: (-cv2.contourArea(c), -len(c)))
    return [c.reshape(-1, 2).astype(np.float64) for c in holes]


def mask_to_polygon(mask: np.ndarray) -> np.ndarray:
    """(h, w) bool -> one (m, 2) polygon of the whole mask: ``merge_polygons`` of its parts' outlines (largest first)
    and then of its holes' (``mask_holes``). A hole's outline runs the other way round, so a scanline fill
    (``polygon_to_mask``; ``cv2.fillPoly``, as ultralytics rasterises labels) leaves the hole out: the fill gives the
    mask back, plus the one-pixel bridge lines."""
    return merge_polygons([*mask_to_polygons(mask), *mask_holes(mask)])


def polygon_to_mask(polygons: np.ndarray | Sequence[np.ndarray], height: int, width: int) -> np.ndarray:
    """One (n, 2) polygon or a list of them in pixel coordinates -> (height, width) bool mask (their union)."""
    if isinstance(polygons, np.ndarray) and polygons.ndim == 2:
        polygons = [polygons]
    mask = np.zeros((int(height), int(width)), dtype=np.uint8)
    for poly in polygons:
        pts = np.asarray(poly, dtype=np.float64).reshape(-1, 2)
        if len(pts) == 0:
            continue
        layer = np.zeros_like(mask)
        ipts = [np.round(pts).astype(np.int32)]
        cv2.fillPoly(layer, ipts, 1)
        cv2.polylines(layer, ipts, isClosed=True, color=1)  # degenerate (1-2 point) parts and bridges
        mask |= layer
    return mask.astype(bool)
