"""sygrid.metrics against hand-computed cases: COCO AP through pycocotools, AbsRel/delta1, ADD/ADD-S, re/te."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
import pytest
import trimesh

from sygrid import metrics
from sygrid.annotations import ImageAnnotation, annotate
from sygrid.camera import CameraIntrinsics
from sygrid.objects.model import ObjectModel
from sygrid.objects.parts import builtin_part
from sygrid.transforms import make_T, rotation_about

H, W = 40, 60
INTRINSICS = CameraIntrinsics(100.0, 100.0, W / 2, H / 2, W, H)


@dataclass
class Det:
    obj_id: int
    score: float
    bbox_xyxy: np.ndarray
    mask: np.ndarray | None


def _image(boxes: list[tuple[int, int, int, int]], obj_ids: list[int]) -> ImageAnnotation:
    """An image whose instances are the filled pixel rectangles ``(x0, y0, x1, y1)`` (x1, y1 exclusive)."""
    ids = np.zeros((H, W), np.int32)
    for k, (x0, y0, x1, y1) in enumerate(boxes):
        ids[y0:y1, x0:x1] = k + 1
    poses = np.stack([make_T(t=[0, 0, 0.5])] * len(boxes)) if boxes else np.zeros((0, 4, 4))
    return ImageAnnotation(0, INTRINSICS, tuple(annotate(ids, None, poses, obj_ids, INTRINSICS)))


def _rect_mask(x0: int, y0: int, x1: int, y1: int) -> np.ndarray:
    m = np.zeros((H, W), bool)
    m[y0:y1, x0:x1] = True
    return m


def _det(obj_id: int, score: float, x0: float, y0: float, x1: float, y1: float, mask: np.ndarray | None = None) -> Det:
    return Det(obj_id, score, np.array([x0, y0, x1, y1], float), mask)


# ------------------------------------------------------------------------------------------------- detection AP
def test_perfect_detections_give_ap_one():
    image = _image([(5, 5, 15, 15), (30, 10, 50, 30)], [1, 3])
    dets = [
        _det(1, 0.9, 5, 5, 15, 15, _rect_mask(5, 5, 15, 15)),
        _det(3, 0.8, 30, 10, 50, 30, _rect_mask(30, 10, 50, 30)),
    ]
    m = metrics.detection_metrics([image], [dets])
    assert (m.box_map50_95, m.box_map50, m.mask_map50_95, m.mask_map50) == pytest.approx((1.0, 1.0, 1.0, 1.0))
    assert m.per_class[1]["box_ap50_95"] == pytest.approx(1.0) and m.per_class[3]["mask_ap50"] == pytest.approx(1.0)
    assert (m.n_images, m.n_gt, m.n_detections) == (1, 2, 2)


def test_known_iou_counts_at_the_thresholds_it_passes():
    # Ground truth: a 10 x 10 pixel square. Detection: the same square cut to 6.2 rows (box) / 62 pixels (mask):
    # IoU 0.62 passes the thresholds 0.50, 0.55, 0.60 of ten -> AP50 = 1, AP50-95 = 3/10.
    image = _image([(0, 0, 10, 10)], [2])
    mask = _rect_mask(0, 0, 10, 6)
    mask[6, 0:2] = True
    m = metrics.detection_metrics([image], [[_det(2, 0.7, 0, 0, 10, 6.2, mask)]])
    assert m.box_map50 == pytest.approx(1.0)
    assert m.box_map50_95 == pytest.approx(0.3)
    assert m.mask_map50 == pytest.approx(1.0)
    assert m.mask_map50_95 == pytest.approx(0.3)


def test_a_higher_scored_false_positive_halves_precision():
    # One object; a false positive ranked above the true positive: the only recall level (1.0) is reached at
    # precision 1/2, and COCO's interpolated precision is 1/2 at every recall threshold -> AP 0.5.
    image = _image([(0, 0, 10, 10)], [1])
    fp, tp = _det(1, 0.9, 40, 20, 50, 30), _det(1, 0.6, 0, 0, 10, 10)
    assert metrics.detection_metrics([image], [[fp, tp]]).box_map50 == pytest.approx(0.5)
    fp_low = _det(1, 0.5, 40, 20, 50, 30)
    assert metrics.detection_metrics([image], [[fp_low, tp]]).box_map50 == pytest.approx(1.0)


def test_wrong_class_misses_and_nan_where_there_is_no_ground_truth():
    image = _image([(0, 0, 10, 10)], [1])
    m = metrics.detection_metrics([image], [[_det(2, 0.9, 0, 0, 10, 10)]])
    assert m.per_class[1]["box_ap50"] == 0.0  # the object was not found
    assert math.isnan(m.per_class[2]["box_ap50"])  # no ground truth of class 2: COCO leaves it out of the mean
    assert m.box_map50 == 0.0
    assert math.isnan(m.mask_map50)  # a detection without a mask: no mask AP


def test_no_detections_and_several_images():
    images = [_image([(0, 0, 10, 10)], [1]), _image([(20, 20, 30, 30)], [1]), _image([], [])]
    assert metrics.detection_metrics(images, [[], [], []]).box_map50_95 == 0.0
    # Two of two found across images, nothing in the empty image.
    dets = [[_det(1, 0.9, 0, 0, 10, 10)], [_det(1, 0.8, 20, 20, 30, 30)], []]
    assert metrics.detection_metrics(images, dets).box_map50_95 == pytest.approx(1.0)
    # One of two found: recall 0.5 at precision 1 -> AP 0.5 (51 of 101 recall thresholds, 0.5 and below, reached).
    half = metrics.detection_metrics(images, [dets[0], [], []])
    assert half.box_map50 == pytest.approx(51 / 101)


def test_empty_results_give_zero_ap_and_no_ground_truth_gives_nan():
    image = _image([(0, 0, 10, 10)], [1])
    m = metrics.detection_metrics([image], [[]], obj_ids=[1, 2])  # nothing detected: AP 0, not NaN, for boxes and masks
    assert (m.box_map50_95, m.box_map50, m.mask_map50_95, m.mask_map50) == (0.0, 0.0, 0.0, 0.0)
    assert m.per_class[1]["box_ap50_95"] == 0.0 and m.per_class[1]["mask_ap50"] == 0.0
    assert math.isnan(m.per_class[2]["box_ap50"]) and m.per_class[2]["n_gt"] == 0  # class 2 has no ground truth
    assert (m.n_gt, m.n_detections) == (1, 0)
    empty = _image([], [])  # no ground truth at all: nothing to measure, with or without detections
    for dets in ([], [_det(1, 0.9, 0, 0, 10, 10, _rect_mask(0, 0, 10, 10))]):
        m = metrics.detection_metrics([empty], [dets], obj_ids=[1])
        assert math.isnan(m.box_map50_95) and math.isnan(m.mask_map50) and math.isnan(m.per_class[1]["box_ap50"])
    # Crowd-only ground truth is no ground truth either.
    gt = metrics.coco_ground_truth([image], [1], min_visib_fract=2.0)
    assert gt["annotations"][0]["iscrowd"] == 1
    ap = metrics.coco_average_precision(gt, [], "bbox")
    assert math.isnan(ap.map50_95) and math.isnan(ap.per_class[1][0])


def test_low_visibility_instances_can_be_ignored():
    image = _image([(0, 0, 10, 10), (30, 10, 40, 20)], [1, 1])
    faint = dataclasses.replace(image.instances[1], visib_fract=0.05)
    image = dataclasses.replace(image, instances=(image.instances[0], faint))
    found = [_det(1, 0.9, 0, 0, 10, 10), _det(1, 0.8, 30, 10, 40, 20)]
    assert metrics.detection_metrics([image], [found[:1]]).box_map50 == pytest.approx(51 / 101)
    ignored = metrics.detection_metrics([image], [found[:1]], min_visib_fract=0.1)
    assert ignored.box_map50 == pytest.approx(1.0) and ignored.n_gt == 1
    # A detection of the ignored instance is not a false positive either.
    assert metrics.detection_metrics([image], [found], min_visib_fract=0.1).box_map50 == pytest.approx(1.0)


def test_detection_input_errors():
    image = _image([(0, 0, 10, 10)], [1])
    with pytest.raises(ValueError, match="one list per image"):
        metrics.detection_metrics([image], [])
    with pytest.raises(ValueError, match="mask shape"):
        metrics.detection_metrics([image], [[_det(1, 0.9, 0, 0, 10, 10, np.zeros((5, 5), bool))]])


# -------------------------------------------------------------------------------------------------------- depth
def test_absrel_and_delta1_on_small_arrays():
    ref = np.array([[1.0, 2.0], [4.0, 0.0]])
    depth = np.array([[1.1, 2.0], [2.0, 3.0]])  # the last pixel has no reference: not valid
    m = metrics.depth_metrics(depth, ref)
    assert m.n_valid == 3
    assert m.abs_rel == pytest.approx((0.1 + 0.0 + 0.5) / 3)
    assert m.delta1 == pytest.approx(2 / 3)  # ratios 1.1, 1.0, 2.0
    # delta1 is symmetric in over- and under-estimation: 1.2x both ways passes, 1.3x fails.
    assert metrics.depth_metrics(np.array([[1.2, 1 / 1.2, 1.3]]), np.ones((1, 3))).delta1 == pytest.approx(2 / 3)
    masked = metrics.depth_metrics(depth, ref, mask=np.array([[True, False], [False, False]]))
    assert (masked.n_valid, masked.abs_rel) == (1, pytest.approx(0.1))
    nothing = metrics.depth_metrics(np.zeros((2, 2)), ref)
    assert nothing.n_valid == 0 and math.isnan(nothing.abs_rel)
    mean = metrics.mean_depth_metrics([m, masked, nothing])
    assert mean.abs_rel == pytest.approx((0.2 + 0.1) / 2) and mean.n_valid == 4
    with pytest.raises(ValueError, match="two \\(h, w\\) arrays"):
        metrics.depth_metrics(np.zeros((2, 2)), np.zeros((2, 3)))


# --------------------------------------------------------------------------------------------------------- pose
def _box_model() -> ObjectModel:
    return ObjectModel(obj_id=42, name="box", mesh=trimesh.creation.box(extents=(0.03, 0.02, 0.01)))


def test_add_of_a_pure_translation_is_its_norm():
    points = metrics.model_points(_box_model())
    T_gt = make_T(rotation_about(np.array([1.0, 2.0, 3.0]), 0.7), [0.1, -0.05, 0.6])
    shift = np.array([0.003, -0.004, 0.0])  # 5 mm
    T_est = T_gt.copy()
    T_est[:3, 3] += shift
    assert metrics.add_m(T_est, T_gt, points) == pytest.approx(0.005)
    assert metrics.translation_error_m(T_est[:3, 3], T_gt[:3, 3]) == pytest.approx(0.005)


def test_adds_is_the_mean_distance_to_the_closest_moved_point():
    points = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [3.0, 0.0, 0.0]])
    T_est = make_T(t=[1.0, 0.0, 0.0])  # moved points 1, 2, 4: closest to 0, 1, 3 are at 1, 0, 1
    assert metrics.adds_m(T_est, np.eye(4), points) == pytest.approx(2 / 3)
    assert metrics.add_m(T_est, np.eye(4), points) == pytest.approx(1.0)


def test_adds_of_a_symmetric_rotation_is_near_zero_while_add_is_not():
    nut = builtin_part("hex_nut")  # 6-fold about z
    T_gt = make_T(rotation_about(np.array([0.3, 1.0, 0.2]), 1.1), [0.02, 0.01, 0.45])
    T_est = T_gt @ make_T(rotation_about(np.array([0.0, 0.0, 1.0]), np.pi / 3))
    errors = metrics.pose_errors(T_est, T_gt, nut)
    assert errors.metric == "ADD-S"
    assert errors.add_m < 0.015 * nut.diameter_m  # only the sampling bias (about 0.26 mm of 22.5 mm)
    assert errors.correct()
    assert metrics.add_m(T_est, T_gt, metrics.model_points(nut)) > 0.3 * nut.diameter_m
    assert errors.re_deg == pytest.approx(0.0, abs=1e-6)
    assert errors.te_m == pytest.approx(0.0, abs=1e-12)


def test_rotation_errors_plain_and_symmetry_aware():
    R = rotation_about(np.array([0.0, 0.0, 1.0]), np.pi / 2)
    assert metrics.rotation_error_deg(R, np.eye(3)) == pytest.approx(90.0)
    assert metrics.rotation_error_deg(rotation_about(np.array([1.0, 1.0, 0.0]), np.radians(170)), np.eye(3)) == (
        pytest.approx(170.0)
    )
    nut = builtin_part("hex_nut")
    re, te = metrics.symmetric_pose_errors(make_T(R), np.eye(4), nut.symmetry_transforms())
    assert re == pytest.approx(30.0)  # 90 deg about the 6-fold axis is 30 deg from the nearest equivalent
    assert te == 0.0
    box = _box_model()
    assert metrics.pose_errors(make_T(R), np.eye(4), box).re_deg == pytest.approx(90.0)  # no symmetry declared


def test_asymmetric_model_uses_add_and_the_threshold():
    box = _box_model()
    T_gt = make_T(t=[0.0, 0.0, 0.5])
    near, far = T_gt.copy(), T_gt.copy()
    near[0, 3] += 0.09 * box.diameter_m
    far[0, 3] += 0.11 * box.diameter_m
    assert metrics.pose_errors(near, T_gt, box).metric == "ADD"
    assert metrics.pose_errors(near, T_gt, box).correct() and not metrics.pose_errors(far, T_gt, box).correct()
    with pytest.raises(ValueError, match="T_est: expected a finite 4x4"):
        metrics.add_m(np.eye(3), T_gt, np.zeros((2, 3)))


def test_pose_metrics_table_per_object():
    d = 0.02
    records = [
        metrics.PoseErrors(1, "ADD-S", 0.001, 1.0, 0.001, d),  # correct
        metrics.PoseErrors(1, "ADD-S", 0.003, 3.0, 0.004, d),  # 3 mm > 2 mm: wrong
        metrics.PoseErrors(1, "ADD-S", 0.0015, 2.0, 0.002, d),  # correct
        metrics.pose_errors(None, np.eye(4), builtin_part("hex_nut")),  # missed
        metrics.PoseErrors(4, "ADD", 0.002, 5.0, 0.003, 0.06),
    ]
    table = metrics.pose_metrics_table(records)
    nut = table["per_object"][1]
    assert (nut["n"], nut["n_estimated"]) == (4, 3)
    assert nut["add_recall"] == pytest.approx(0.5)  # the miss counts as a failure
    assert nut["median_re_deg"] == pytest.approx(2.0)
    assert nut["median_te_mm"] == pytest.approx(2.0)
    assert nut["median_add_mm"] == pytest.approx(1.5)
    assert table["per_object"][4]["add_recall"] == 1.0
    assert table["all"]["metric"] == "ADD(-S)" and table["all"]["add_recall"] == pytest.approx(3 / 5)


def test_model_points_are_seeded_and_on_the_surface():
    nut = builtin_part("hex_nut")
    a, b = metrics.model_points(nut, 500, seed=3), metrics.model_points(nut, 500, seed=3)
    assert np.array_equal(a, b) and not np.array_equal(a, metrics.model_points(nut, 500, seed=4))
    assert np.all(np.abs(a) <= nut.extents_m / 2 + 1e-9)
