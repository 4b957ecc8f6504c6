"""Masks of thin and holed parts from the labels to the decoded detection: a part thinner than the prototypes' cell
(a strap seen edge on) keeps a mask, and a YOLO polygon keeps the holes of its mask."""

from __future__ import annotations

import numpy as np

from sygrid.annotations import mask_holes, mask_to_polygon, polygon_to_mask
from sygrid.detection_decode import assemble_mask
from sygrid.letterbox import letterbox_geometry
from sygrid.train.detector.augment import targets_from_ids, thin_cells

SIZE = 64
STRIDE = 4


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.count_nonzero(a & b) / max(np.count_nonzero(a | b), 1))


def _decode(target: np.ndarray, box_xyxy: np.ndarray) -> np.ndarray:
    """The mask the runtime decodes from a network that reproduces ``target`` (coverage at the prototypes' stride)
    exactly: one prototype, the target's logit, coefficient 1."""
    p = np.clip(target, 1e-4, 1 - 1e-4)
    prototypes = np.log(p / (1 - p)).astype(np.float32)[None]
    geometry = letterbox_geometry((SIZE, SIZE), (SIZE, SIZE), None)
    return assemble_mask(np.ones(1, np.float32), prototypes, box_xyxy, geometry)


def test_a_strap_thinner_than_a_cell_keeps_its_decoded_mask() -> None:
    ids = np.zeros((SIZE, SIZE), np.int32)
    ids[21, 6:58] = 1  # a strap one pixel wide (a sheet seen edge on)
    ids[22:40, 6] = 1
    ids[36:56, 30:54] = 2  # a block: its cells' coverage is its target, as before
    _, boxes, masks = targets_from_ids(ids, np.array([0, 1]), mask_stride=STRIDE)
    strap = _decode(masks[0], boxes[0])
    recall = np.count_nonzero(strap & (ids == 1)) / np.count_nonzero(ids == 1)
    assert recall >= 0.9  # the coverage alone (0.25 per cell) decodes to an empty mask
    assert np.count_nonzero(strap) <= STRIDE * np.count_nonzero(ids == 1)  # one cell wide at most
    block_cover = (ids == 2).reshape(SIZE // STRIDE, STRIDE, SIZE // STRIDE, STRIDE).mean(axis=(1, 3))
    assert np.allclose(masks[1], block_cover)  # a part's edge is no thin cell
    assert _iou(_decode(masks[1], boxes[1]), ids == 2) >= 0.9


def test_thin_cells_are_ridges_of_the_coverage() -> None:
    cover = np.zeros((5, 5))
    cover[1:4, 1:4] = 1.0
    cover[0, 1:4] = 0.3  # an edge beside the covered cells: not thin
    cover[4, 4] = 0.2  # a corner cell touching a covered one diagonally: not thin
    assert not thin_cells(cover).any()
    speck = np.zeros((3, 3))
    speck[1, 1] = 0.1  # a part inside one cell
    assert thin_cells(speck)[1, 1]


def test_a_yolo_polygon_keeps_the_holes_of_its_mask() -> None:
    ring = np.zeros((40, 60), bool)
    ring[5:35, 5:35] = True
    ring[12:28, 12:28] = False  # a washer's hole
    ring[10:30, 42:55] = True  # a second piece with a hole of its own
    ring[15:25, 46:51] = False
    assert len(mask_holes(ring)) == 2
    polygon = mask_to_polygon(ring)
    assert _iou(polygon_to_mask(polygon, *ring.shape), ring) >= 0.97  # the bridges' pixels only
    assert not polygon_to_mask(polygon, *ring.shape)[14:26, 14:26].any()
