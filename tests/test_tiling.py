"""perception.tiling and the detector's views: tile layouts, the merge of duplicates on seams, and detections made in
a crop or in tiles at another scale landing back on the full frame exactly.

The exactness checks run the real detector's pre- and post-processing around a stand-in network (``_run``) that
"detects" the white rectangles of its input: each connected white region of the letterboxed input becomes a box
(its tight pixel box, network pixels) and a prototype at the input's full resolution (+10 inside, -10 outside).
At scale 2 (and 1) a bilinear upsampling of a sharp edge keeps the 0.5 crossing on the edge, so the rectangles'
boxes and masks must come back in frame pixels to the pixel.
"""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest
from scipy import ndimage

from perception.detector import YoloSegDetector
from perception.results import Detection
from perception.tiling import ViewSettings, merge_tiles, tile_layout
from tests.test_detector_runtime import NM, anchors, save_model

FRAME_H, FRAME_W = 96, 160


def white_boxes_network(blob: np.ndarray) -> list[np.ndarray]:
    """The stand-in network: output0 [1, 4 + 2 + NM, A] and prototypes [1, NM, H, W] for the white regions."""
    bright = blob[0].mean(axis=0) > 0.5
    labels, n = ndimage.label(bright)
    h, w = bright.shape
    output0 = np.zeros((1, 4 + 2 + NM, max(n, 1)), np.float32)
    protos = np.full((1, NM, h, w), -10.0, np.float32)
    for k, sl in enumerate(ndimage.find_objects(labels)):
        y0, y1, x0, x1 = sl[0].start, sl[0].stop, sl[1].start, sl[1].stop
        output0[0, :4, k] = [(x0 + x1) / 2, (y0 + y1) / 2, x1 - x0, y1 - y0]
        output0[0, 4, k] = 0.9  # class 0 (hex_nut)
        output0[0, 6 + k, k] = 1.0
        protos[0, k][labels == k + 1] = 10.0
    return [output0, protos]


@pytest.fixture
def detector_factory(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    output0, output1 = anchors()
    path = save_model(tmp_path / "dyn.onnx", {"output0": output0, "output1": output1}, None, [1, 3, "h", "w"])

    def make(view: ViewSettings | None = None) -> tuple[YoloSegDetector, list]:
        detector = YoloSegDetector(path, input_size=64, view=view)
        shapes: list = []

        def run(blob: np.ndarray) -> list[np.ndarray]:
            shapes.append(blob.shape)
            return white_boxes_network(blob)

        monkeypatch.setattr(detector, "_run", run)
        return detector, shapes

    return make


# Rectangles [x0, y0, x1, y1) on a black frame: one inside a tile, one across a vertical seam, one across a
# horizontal seam and one at a corner of four tiles (all narrower than the tiles' overlap).
RECTS = [(4, 6, 14, 12), (74, 10, 86, 20), (20, 44, 30, 54), (72, 42, 88, 54), (140, 80, 150, 90)]


def frame_with(rects: list[tuple[int, int, int, int]]) -> np.ndarray:
    image = np.zeros((FRAME_H, FRAME_W, 3), np.uint8)
    for x0, y0, x1, y1 in rects:
        image[y0:y1, x0:x1] = 255
    return image


def assert_exact(dets: list[Detection], rects: list[tuple[int, int, int, int]]) -> None:
    assert len(dets) == len(rects)
    found = sorted(dets, key=lambda d: (d.bbox_xyxy[0], d.bbox_xyxy[1]))
    for det, (x0, y0, x1, y1) in zip(found, sorted(rects), strict=True):
        np.testing.assert_allclose(det.bbox_xyxy, [x0, y0, x1, y1], atol=1e-6)
        expected = np.zeros((FRAME_H, FRAME_W), bool)
        expected[y0:y1, x0:x1] = True
        assert det.mask.shape == (FRAME_H, FRAME_W)
        assert np.array_equal(det.mask, expected), (x0, y0, x1, y1)


# ------------------------------------------------------------------------------------------------ layouts
LAYOUTS = [
    ((0, 0, 160, 96), 48, 0.25),
    ((7, 3, 101, 90), 32, 0.5),
    ((10, 10, 30, 20), 64, 0.25),
    ((0, 0, 100, 40), 40, 0.0),
]


@pytest.mark.parametrize(("region", "side", "overlap"), LAYOUTS)
def test_tiles_cover_the_region_exactly_with_the_overlap(region, side, overlap):
    tiles = tile_layout(region, side, overlap)
    x0, y0, x1, y1 = region
    covered = np.zeros((y1, x1), int)
    for t in tiles:
        assert x0 <= t.x0 < t.x1 <= x1 and y0 <= t.y0 < t.y1 <= y1
        assert t.x1 - t.x0 == min(side, x1 - x0) and t.y1 - t.y0 == min(side, y1 - y0)
        covered[t.y0 : t.y1, t.x0 : t.x1] += 1
    assert (covered[y0:y1, x0:x1] >= 1).all() and covered.sum() == sum((t.x1 - t.x0) * (t.y1 - t.y0) for t in tiles)
    columns = sorted({(t.x0, t.x1) for t in tiles})
    for (_, a1), (b0, _) in itertools.pairwise(columns):
        assert a1 - b0 >= overlap * side - 1  # neighbours overlap by at least the requested fraction (rounded)


def test_tile_layout_rejects_bad_input():
    with pytest.raises(ValueError, match="non-empty box"):
        tile_layout((5, 5, 5, 10), 16)
    with pytest.raises(ValueError, match="overlap"):
        tile_layout((0, 0, 10, 10), 16, 0.95)
    with pytest.raises(ValueError, match="tile_px"):
        ViewSettings(tile_px=8)
    with pytest.raises(ValueError, match="scale"):
        ViewSettings(scale=0.0)


# ------------------------------------------------------------------------------------------------ merge
def _det(box: tuple, cls: int = 0, score: float = 0.9, shape: tuple[int, int] = (40, 40)) -> Detection:
    mask = np.zeros(shape, bool)
    x0, y0, x1, y1 = box
    mask[y0:y1, x0:x1] = True
    return Detection(cls, cls + 1, score, np.array(box, float), mask)


def test_merge_joins_a_cut_part_with_its_whole_view_once():
    whole = _det((10, 10, 20, 20), score=0.8)
    cut = _det((15, 10, 20, 20), score=0.9)  # the same part cut by a tile's edge, scored higher
    other_class = _det((10, 10, 20, 20), cls=1)
    neighbour = _det((20, 10, 30, 20))  # touching, same class, same tile as the whole view
    merged = merge_tiles([whole, cut, other_class, neighbour], [0, 1, 0, 0])
    assert len(merged) == 3
    joined = next(d for d in merged if d.class_index == 0 and d.bbox_xyxy[0] == 10)
    assert joined.score == 0.9 and np.array_equal(joined.mask, whole.mask)
    np.testing.assert_array_equal(joined.bbox_xyxy, [10, 10, 20, 20])
    # two parts in the same tile are never merged, however they overlap
    assert len(merge_tiles([whole, _det((12, 10, 20, 20))], [0, 0])) == 2
    with pytest.raises(ValueError, match="one tile per detection"):
        merge_tiles([whole], [])


# ------------------------------------------------------------------------------------------------ exactness
@pytest.mark.parametrize("scale", [1.0, 2.0])
def test_a_crop_at_another_scale_lands_on_the_frame_exactly(detector_factory, scale):
    detector, shapes = detector_factory(ViewSettings(scale=scale))
    rects = [r for r in RECTS if r[2] <= 120]
    dets = detector.detect(frame_with(RECTS), roi_xyxy=(0, 0, 120, 70))
    assert_exact(dets, [r for r in rects if r[3] <= 70])
    assert shapes == [(1, 3, int(np.ceil(70 * scale / 32) * 32), int(np.ceil(120 * scale / 32) * 32))]
    assert detector.frame_scale((FRAME_H, FRAME_W)) == scale


def test_tiles_land_on_the_frame_exactly_and_seams_merge_once(detector_factory):
    view = ViewSettings(scale=2.0, tile_px=96, tile_overlap=0.5)  # 48 px tiles overlapping by 24 px
    detector, shapes = detector_factory(view)
    dets = detector.detect(frame_with(RECTS))
    assert len(shapes) == len(tile_layout((0, 0, FRAME_W, FRAME_H), 48, 0.5)) > 4
    assert_exact(dets, RECTS)
    assert detector.last_timings_ms["tiles"] == len(shapes)
    # the same over a region: parts outside it are not seen, the rest are found once
    dets = detector.detect(frame_with(RECTS), roi_xyxy=(0, 0, 100, 60))
    assert_exact(dets, [r for r in RECTS if r[2] <= 100 and r[3] <= 60])


def test_the_plain_view_is_unchanged_and_a_fixed_input_refuses_a_scale(detector_factory, tmp_path: Path):
    detector, shapes = detector_factory()
    assert detector.view.default and detector.frame_scale((FRAME_H, FRAME_W)) == pytest.approx(0.4)
    detector.detect(frame_with(RECTS))
    assert shapes == [(1, 3, 64, 64)]  # 160 x 96 at 0.4 = 64 x 38, padded to 64
    output0, output1 = anchors()
    fixed = save_model(tmp_path / "fixed.onnx", {"output0": output0, "output1": output1})
    with pytest.raises(ValueError, match="need a model with a dynamic input"):
        YoloSegDetector(fixed, view=ViewSettings(scale=1.0))
