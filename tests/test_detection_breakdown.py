"""sygrid.detection_breakdown on a small hand-made fixture (recall and AP per part, size and visibility bin, at two
thresholds; the nominal-size curve), and sygrid.part_pixels (the pixels-per-part check and its advice)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pytest

from sygrid.annotations import ImageAnnotation, annotate
from sygrid.camera import CameraIntrinsics
from sygrid.detection_breakdown import (
    MIN_CURVE_COUNT,
    RELIABLE_RELATIVE,
    ap_table,
    breakdown,
    instance_records,
    min_reliable_px,
)
from sygrid.part_pixels import advice, check_parts, nominal_px, part_warnings
from sygrid.transforms import make_T

H, W = 120, 160
INTRINSICS = CameraIntrinsics(200.0, 200.0, W / 2, H / 2, W, H)


@dataclass
class Det:
    obj_id: int
    score: float
    bbox_xyxy: np.ndarray
    mask: np.ndarray | None


def _rect(x0: int, y0: int, x1: int, y1: int) -> np.ndarray:
    m = np.zeros((H, W), bool)
    m[y0:y1, x0:x1] = True
    return m


# (obj_id, full rectangle, visible rectangle): A small, B medium, C large, D half hidden, E barely seen.
INSTANCES = [
    (1, (5, 5, 15, 15), (5, 5, 15, 15)),
    (1, (20, 5, 50, 35), (20, 5, 50, 35)),
    (3, (60, 5, 120, 65), (60, 5, 120, 65)),
    (3, (20, 60, 60, 100), (20, 60, 38, 100)),
    (1, (130, 80, 150, 100), (130, 80, 132, 82)),
]


@pytest.fixture
def image() -> ImageAnnotation:
    ids = np.zeros((H, W), np.int32)
    for k, (_, _, visible) in enumerate(INSTANCES):
        ids[_rect(*visible)] = k + 1
    full = np.stack([_rect(*r) for _, r, _ in INSTANCES])
    poses = np.stack([make_T(t=[0, 0, 0.5])] * len(INSTANCES))
    instances = annotate(ids, full, poses, [o for o, _, _ in INSTANCES], INTRINSICS)
    return ImageAnnotation(0, INTRINSICS, tuple(instances))


def _det(obj_id: int, score: float, rect: tuple[int, int, int, int]) -> Det:
    return Det(obj_id, score, np.array(rect, float), _rect(*rect))


@pytest.fixture
def detections() -> list[Det]:
    # A found only at a low score, B and C at a high one, D missed; a false positive of obj 3 somewhere empty
    return [_det(1, 0.3, (5, 5, 15, 15)), _det(1, 0.9, (20, 5, 50, 35)), _det(3, 0.9, (60, 5, 120, 65)),
            _det(3, 0.2, (130, 20, 150, 40))]  # fmt: skip


def test_recall_per_size_and_visibility_at_both_thresholds(image, detections):
    b = breakdown([image], [detections], [0.4, 0.001], names={1: "hex_nut", 3: "washer"},
                  diameters_m={1: 0.05, 3: 0.1}, scale=0.5)  # fmt: skip
    assert b["thresholds"] == [0.001, 0.4]
    r = b["recall"]
    assert r["all"]["all"]["n"] == 4  # E is seen less than 10 %
    assert r["all"]["all"]["recall@0.4"] == 0.5 and r["all"]["all"]["recall@0.001"] == 0.75
    assert (r["all"]["<20"]["n"], r["all"]["<20"]["recall@0.4"], r["all"]["<20"]["recall@0.001"]) == (1, 0.0, 1.0)
    assert (r["all"]["20-50"]["n"], r["all"]["20-50"]["recall@0.4"]) == (2, 0.5)
    assert (r["all"][">50"]["n"], r["all"][">50"]["recall@0.4"]) == (1, 1.0)
    assert (r["all"]["40-70%"]["n"], r["all"]["40-70%"]["recall@0.001"]) == (1, 0.0)
    assert (r["all"]["70-100%"]["n"], r["all"]["70-100%"]["recall@0.4"]) == (3, pytest.approx(2 / 3))
    assert r["1 hex_nut"]["all"]["recall@0.001"] == 1.0 and r["3 washer"]["all"]["recall@0.4"] == 0.5
    assert math.isnan(r["3 washer"]["<20"]["recall@0.4"])  # no instance there
    # AP: the small part's only detection is right (AP 1 at 0.001, 0 at 0.4 where it is filtered out)
    assert b["ap"]["0.001"]["1"]["<20"]["box_ap50"] == pytest.approx(1.0)
    assert b["ap"]["0.4"]["1"]["<20"]["box_ap50"] == pytest.approx(0.0)
    assert b["ap"]["0.001"]["1"]["20-50"]["mask_ap50_95"] == pytest.approx(1.0)
    assert b["ap"]["0.001"]["3"]["40-70%"]["box_ap50"] == pytest.approx(0.0)  # D missed
    # nominal size: fx * diameter / z * scale = 200 * 0.05 / 0.5 * 0.5 = 10 px (obj 1), 20 px (obj 3)
    records = instance_records([image], [detections], [0.4], diameters_m={1: 0.05, 3: 0.1}, scale=0.5)
    assert sorted(round(x.nominal_px, 6) for x in records) == [10.0, 10.0, 20.0, 20.0]
    assert sum(row["n"] for row in b["nominal_curve"]["0.4"]) == 3  # D is less than half visible
    assert math.isnan(b["min_reliable_px"]["0.4"])  # too few instances to trust


def test_ap_with_no_detections_is_zero_where_there_is_ground_truth(image):
    table = ap_table([image], [[]])
    assert table["all"]["all"]["box_ap50"] == 0.0 and table["1"]["<20"]["mask_ap50_95"] == 0.0


def test_min_reliable_px_reads_the_curve_from_the_large_end():
    n = MIN_CURVE_COUNT
    curve = [{"lo_px": 8.0, "hi_px": 12.0, "n": n, "relative": 0.5},
             {"lo_px": 12.0, "hi_px": 16.0, "n": n, "relative": 0.9},
             {"lo_px": 16.0, "hi_px": 20.0, "n": 2, "relative": 0.0},  # too few to trust: skipped
             {"lo_px": 20.0, "hi_px": 24.0, "n": n, "relative": RELIABLE_RELATIVE}]  # fmt: skip
    assert min_reliable_px(curve) == 12.0
    assert math.isnan(min_reliable_px([{**curve[0], "lo_px": 40.0}]))


def test_the_curve_compares_each_size_with_the_same_parts_at_any_size():
    """A part recalled half the time everywhere is not a size limit; one missed only when small is."""
    from sygrid.detection_breakdown import InstanceRecord, size_curve

    def rec(obj_id: int, px: float, found: bool) -> InstanceRecord:
        return InstanceRecord(0, obj_id, px, 1.0, px, {0.4: found})

    hard = [rec(1, px, k % 2 == 0) for px in (9.0, 30.0) for k in range(40)]  # 50 % at both sizes
    small_limited = [rec(2, 9.0, k < 10) for k in range(40)] + [rec(2, 30.0, True) for _ in range(40)]
    curve = {row["lo_px"]: row for row in size_curve(hard + small_limited, 0.4)}
    # part 2 recalls 50/80 overall; its small instances 10/40: 0.25 / 0.625 = 0.4 of its usual; part 1 at 1.0
    assert curve[8.0]["relative"] == pytest.approx((20 + 10) / (40 * 0.5 + 40 * 50 / 80))
    assert curve[28.0]["relative"] > 1.0 and min_reliable_px(list(curve.values())) == 28.0


# ------------------------------------------------------------------------------------------------ part pixels
def test_nominal_size_and_the_warning_say_what_to_change():
    assert nominal_px(0.0225, 579.4, 0.95) == pytest.approx(13.72, abs=0.01)
    assert nominal_px(0.0225, 579.4, 0.95, 0.75) == pytest.approx(10.29, abs=0.01)
    with pytest.raises(ValueError, match="distance_m"):
        nominal_px(0.02, 500.0, 0.0)
    parts = {"hex_nut": 0.0225, "flange": 0.096}
    checks = check_parts(parts, 579.4, 0.95, 0.75, 14.0)
    assert [c.name for c in checks] == ["hex_nut", "flange"] and not checks[0].ok and checks[1].ok
    warnings = part_warnings(parts, 579.4, 0.95, 0.75, 14.0)
    assert len(warnings) == 1 and warnings[0].startswith("hex_nut spans 10.3 network px")
    text = advice(checks[0], 579.4, 0.75)
    # each remedy, applied alone, brings the part to the threshold
    closer = float(text.split("within ")[1].split(" m")[0])
    assert nominal_px(0.0225, 579.4, closer, 0.75) == pytest.approx(14.0, abs=0.1)
    scale = float(text.split("scale >= ")[1].split(" ")[0])
    assert nominal_px(0.0225, 579.4, 0.95, scale) >= 14.0
    fx = float(text.split("fx >= ")[1].split(" px")[0])
    assert nominal_px(0.0225, fx, 0.95, 0.75) == pytest.approx(14.0, abs=0.05)
    assert part_warnings(parts, 579.4, 0.95, 0.75, None) == []  # the model states no threshold
