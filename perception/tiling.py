"""Where the detector looks in a frame and at what scale: one region (the frame, or the bin's box) in one piece or
cut into overlapping tiles (SAHI-style slicing), and the merge of the detections made in the tiles.

Pure geometry and numpy. ``ViewSettings`` says how a region is seen; ``tile_layout`` cuts a region into square tiles
that overlap and together cover it exactly; ``merge_tiles`` merges detections (already mapped to frame pixels) that
several tiles made of one part: a part on a seam is seen whole or cut in two tiles, and its pieces overlap.

Merge rule: detections are taken best score first; one joins an already kept detection of the same class that came
from other tiles when their overlap, intersection over the smaller of the two (masks where both have one, else
boxes), reaches ``merge_overlap``. A joined group keeps the best score, the union of the masks and the union of the
boxes. Two detections from the same tile are never merged (the detector's own NMS already separated them), so two
touching parts found in one tile stay two.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from perception.results import Detection

DEFAULT_TILE_OVERLAP = 0.25  # of a tile's side
DEFAULT_MERGE_OVERLAP = 0.5


@dataclass(frozen=True)
class ViewSettings:
    """How the detector looks at its region (the whole frame, or the box the caller gives, e.g. the bin's).

    Args:
        scale: network input pixels per image pixel; None: the scale at which the whole frame fills the model's
            input size (``YoloSegDetector.input_hw``). Above that scale a region costs more than the frame would.
        tile_px: None: the region in one piece; else square tiles of ``tile_px`` network pixels (``tile_px / scale``
            image pixels), overlapping by ``tile_overlap`` of their side, merged (``merge_tiles``).
        tile_overlap: in [0, 0.9]; a part narrower than the overlap lies whole in at least one tile.
        merge_overlap: in (0, 1]; see ``merge_tiles``.
    """

    scale: float | None = None
    tile_px: int | None = None
    tile_overlap: float = DEFAULT_TILE_OVERLAP
    merge_overlap: float = DEFAULT_MERGE_OVERLAP

    def __post_init__(self) -> None:
        if self.scale is not None and not 0.05 <= self.scale <= 8.0:
            raise ValueError(f"ViewSettings.scale: expected network px per image px in [0.05, 8], got {self.scale}")
        if self.tile_px is not None and not 32 <= self.tile_px <= 4096:
            raise ValueError(f"ViewSettings.tile_px: expected 32..4096 network pixels, got {self.tile_px}")
        if not 0.0 <= self.tile_overlap <= 0.9:
            raise ValueError(f"ViewSettings.tile_overlap: expected a fraction in [0, 0.9], got {self.tile_overlap}")
        if not 0.0 < self.merge_overlap <= 1.0:
            raise ValueError(f"ViewSettings.merge_overlap: expected a fraction in (0, 1], got {self.merge_overlap}")

    @property
    def default(self) -> bool:
        """The detector's plain behaviour: one piece at the frame's scale."""
        return self.scale is None and self.tile_px is None


@dataclass(frozen=True)
class Tile:
    """A tile's integer pixel box ``[x0, y0, x1, y1)`` in the frame."""

    x0: int
    y0: int
    x1: int
    y1: int

    @property
    def xyxy(self) -> tuple[int, int, int, int]:
        return self.x0, self.y0, self.x1, self.y1


def _starts(lo: int, hi: int, side: int, overlap: int) -> list[tuple[int, int]]:
    """``[a, b)`` spans of length ``side`` (at most ``hi - lo``) covering ``[lo, hi)``, neighbours overlapping by at
    least ``overlap``, spread evenly with the first at ``lo`` and the last ending at ``hi``."""
    length = hi - lo
    if length <= side:
        return [(lo, hi)]
    n = math.ceil((length - overlap) / (side - overlap))
    return [(lo + round(k * (length - side) / (n - 1)), lo + round(k * (length - side) / (n - 1)) + side)
            for k in range(n)]  # fmt: skip


def tile_layout(region_xyxy: Sequence[int], side_px: int, overlap: float = DEFAULT_TILE_OVERLAP) -> list[Tile]:
    """Square tiles of ``side_px`` image pixels (narrower where the region is) covering the integer region
    ``[x0, y0, x1, y1)`` exactly, row by row; neighbours overlap by at least ``overlap`` of the side.

    Raises:
        ValueError: an empty region, ``side_px < 1`` or ``overlap`` outside [0, 0.9].
    """
    x0, y0, x1, y1 = (int(v) for v in region_xyxy)
    if x1 <= x0 or y1 <= y0:
        raise ValueError(f"region_xyxy: expected a non-empty box [x0, y0, x1, y1], got {list(region_xyxy)}")
    if int(side_px) < 1:
        raise ValueError(f"side_px: expected >= 1, got {side_px}")
    if not 0.0 <= overlap <= 0.9:
        raise ValueError(f"overlap: expected a fraction in [0, 0.9], got {overlap}")
    side = int(side_px)
    step_overlap = min(math.ceil(overlap * side), side - 1)
    rows, columns = _starts(y0, y1, side, step_overlap), _starts(x0, x1, side, step_overlap)
    return [Tile(a, b, c, d) for b, d in rows for a, c in columns]


def _box_intersection(a: np.ndarray, b: np.ndarray) -> float:
    w = min(a[2], b[2]) - max(a[0], b[0])
    h = min(a[3], b[3]) - max(a[1], b[1])
    return max(w, 0.0) * max(h, 0.0)


def _box_area(b: np.ndarray) -> float:
    return max(b[2] - b[0], 0.0) * max(b[3] - b[1], 0.0)


class _Group:
    """Detections of one part merged so far: best score, union box, union mask, the tiles they came from."""

    def __init__(self, det: Detection, tile: int) -> None:
        self.best = det
        self.box = np.asarray(det.bbox_xyxy, dtype=np.float64).copy()
        self.mask = None if det.mask is None else np.asarray(det.mask, dtype=bool).copy()
        self.mask_px = 0 if self.mask is None else int(np.count_nonzero(self.mask))
        self.tiles = {tile}

    def overlap(self, det: Detection, det_mask_px: int) -> float:
        """Intersection over the smaller of the two: masks when both have one, else boxes."""
        box = np.asarray(det.bbox_xyxy, dtype=np.float64)
        if _box_intersection(self.box, box) <= 0.0:
            return 0.0
        if self.mask is not None and det.mask is not None:
            smaller = min(self.mask_px, det_mask_px)
            if smaller == 0:
                return 0.0
            # Only the boxes' common window can hold common pixels.
            x0, y0 = int(max(self.box[0], box[0])), int(max(self.box[1], box[1]))
            x1, y1 = math.ceil(min(self.box[2], box[2])), math.ceil(min(self.box[3], box[3]))
            common = np.count_nonzero(self.mask[y0:y1, x0:x1] & det.mask[y0:y1, x0:x1])
            return common / smaller
        smaller = min(_box_area(self.box), _box_area(box))
        return _box_intersection(self.box, box) / smaller if smaller > 0 else 0.0

    def add(self, det: Detection, tile: int) -> None:
        box = np.asarray(det.bbox_xyxy, dtype=np.float64)
        self.box = np.concatenate([np.minimum(self.box[:2], box[:2]), np.maximum(self.box[2:], box[2:])])
        if self.mask is not None and det.mask is not None:
            self.mask |= det.mask
            self.mask_px = int(np.count_nonzero(self.mask))
        self.tiles.add(tile)

    def detection(self) -> Detection:
        if len(self.tiles) == 1:
            return self.best
        return Detection(self.best.class_index, self.best.obj_id, self.best.score, self.box, self.mask)


def merge_tiles(
    detections: Sequence[Detection], tile_index: Sequence[int], merge_overlap: float = DEFAULT_MERGE_OVERLAP
) -> list[Detection]:
    """Detections of several tiles (in frame pixels, ``tile_index[k]`` the tile of ``detections[k]``) with the
    duplicates on seams merged (see the module docstring), highest score first.

    Raises:
        ValueError: ``tile_index`` does not give one tile per detection, or ``merge_overlap`` is not in (0, 1].
    """
    if len(tile_index) != len(detections):
        raise ValueError(f"tile_index: expected one tile per detection ({len(detections)}), got {len(tile_index)}")
    if not 0.0 < merge_overlap <= 1.0:
        raise ValueError(f"merge_overlap: expected a fraction in (0, 1], got {merge_overlap}")
    order = sorted(range(len(detections)), key=lambda k: -detections[k].score)
    groups: list[_Group] = []
    for k in order:
        det, tile = detections[k], int(tile_index[k])
        mask_px = 0 if det.mask is None else int(np.count_nonzero(det.mask))
        best, best_overlap = None, merge_overlap
        for group in groups:
            if group.best.class_index != det.class_index or tile in group.tiles:
                continue
            overlap = group.overlap(det, mask_px)
            if overlap >= best_overlap:
                best, best_overlap = group, overlap
        if best is None:
            groups.append(_Group(det, tile))
        else:
            best.add(det, tile)
    return [g.detection() for g in groups]
