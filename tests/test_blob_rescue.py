"""Parts the detector's classes miss, found on the depth no pose explains (``perception.blob_rescue``)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from perception.blob_rescue import RescueConfig, outline_from_image, pile_blobs
from perception.camera import Frame
from perception.pipeline import PerceptionPipeline
from sygrid.metrics import pose_errors
from sygrid.objects.parts import builtin_part
from sygrid.transforms import rotation_about
from tests.raycast_scene import CAMERA, T_CAMERA_FLOOR, blob, detection, on_floor, render

NUT, WASHER, BRACKET = (builtin_part(n) for n in ("hex_nut", "washer", "l_bracket"))
R_SIDE = rotation_about(np.array([1.0, 0.0, 0.0]), np.pi / 2)
# the floor plane (a, b, c, d) in the camera frame and the bin's inner corners on it
FLOOR = np.array([*T_CAMERA_FLOOR[:3, 2], -T_CAMERA_FLOOR[:3, 2] @ T_CAMERA_FLOOR[:3, 3]])
CORNERS = np.array([[sx * 0.09, sy * 0.07, 0.0] for sx in (-1, 1) for sy in (-1, 1)])
BOUNDS = CORNERS @ T_CAMERA_FLOOR[:3, :3].T + T_CAMERA_FLOOR[:3, 3]


@pytest.fixture(scope="module")
def scene():
    return render(
        [
            (NUT, on_floor(NUT, 0.0, 0.0, 20.0)),
            (WASHER, on_floor(WASHER, 0.05, 0.0, 0.0)),
            (BRACKET, on_floor(BRACKET, -0.06, 0.01, 30.0, R_SIDE)),
        ]
    )


def _overlap(region: np.ndarray, mask: np.ndarray) -> float:
    return float((region & mask).sum() / mask.sum())


def test_each_part_is_a_region_and_explained_parts_are_not(scene):
    regions = pile_blobs(scene.depth, CAMERA, FLOOR, BOUNDS, config=RescueConfig(max_regions=5))
    assert len(regions) == 3
    for mask in scene.masks:  # every part's visible pixels fall in one region, which holds no other part
        owners = [k for k, r in enumerate(regions) if _overlap(r, mask) > 0.0]
        assert len(owners) == 1 and _overlap(regions[owners[0]], mask) > 0.9
    explained = blob(scene.masks[0]) | blob(scene.masks[2])
    left = pile_blobs(scene.depth, CAMERA, FLOOR, BOUNDS, explained)
    assert len(left) == 1 and _overlap(left[0], scene.masks[1]) > 0.9
    assert not (left[0] & explained).any()
    # the largest first, at most max_regions, none smaller than min_region_px
    sizes = [int(r.sum()) for r in regions]
    assert sizes == sorted(sizes, reverse=True)
    assert len(pile_blobs(scene.depth, CAMERA, FLOOR, BOUNDS, config=RescueConfig(max_regions=1))) == 1
    big = RescueConfig(min_region_px=max(sizes) + 1)
    assert pile_blobs(scene.depth, CAMERA, FLOOR, BOUNDS, config=big) == []
    # a floor out of view gives nothing
    assert pile_blobs(scene.depth, CAMERA, FLOOR, -BOUNDS) == []


def test_a_noisy_floor_is_no_region_but_the_parts_still_are():
    rng = np.random.default_rng(3)
    empty = render([]).depth
    parts = render([(NUT, on_floor(NUT, 0.0, 0.0, 20.0)), (BRACKET, on_floor(BRACKET, -0.06, 0.01, 30.0, R_SIDE))])
    sigma_inv = 0.01  # 1/z's sigma: 1 mm at 0.32 m
    for depth, n_parts in ((empty, 0), (parts.depth, 2)):
        # a stereo camera's noise is correlated over a few pixels (its matching window)
        noise = cv2.GaussianBlur(rng.normal(0.0, 1.0, depth.shape), (0, 0), 3.0)
        noisy = 1.0 / (1.0 / depth + sigma_inv * noise / noise.std())
        assert len(pile_blobs(noisy, CAMERA, FLOOR, BOUNDS, sigma_inv_m=sigma_inv)) == n_parts
        # without the noise allowance the floor's noise is pile everywhere
        assert len(pile_blobs(noisy, CAMERA, FLOOR, BOUNDS, config=RescueConfig(max_regions=50))) > n_parts


def _colours(masks: list[np.ndarray]) -> np.ndarray:
    """A colour image of a scene: grey parts on a blue floor, with a little sensor noise."""
    rgb = np.empty((*masks[0].shape, 3), np.uint8)
    rgb[:] = (70, 110, 200)
    for m in masks:
        rgb[m] = (150, 150, 150)
    noise = np.random.default_rng(0).integers(-6, 7, rgb.shape)
    return np.clip(rgb.astype(int) + noise, 0, 255).astype(np.uint8)


def test_the_outline_comes_from_the_colour_image_where_the_depth_draws_it_off():
    part = np.zeros((120, 160), bool)
    cv2.circle(part.view(np.uint8), (80, 60), 15, 1, -1)
    rgb = _colours([part])
    # a stereo outline: shifted by 3 pixels and 2 pixels too wide
    region = cv2.dilate(np.roll(part, 3, axis=1).astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    outline = outline_from_image(rgb, region, ring_px=8)

    def iou(a: np.ndarray) -> float:
        return float((a & part).sum() / (a | part).sum())

    assert iou(region) < 0.8 and iou(outline) > 0.95
    assert outline_from_image(rgb, region, ring_px=0) is region  # off: the depth's outline as it is
    everything = np.ones_like(part)  # no background to learn a colour model from: the region as it is
    assert outline_from_image(rgb, everything, ring_px=8).all()


class _FixedDetector:
    conf_threshold = 0.5
    class_obj_ids = (NUT.obj_id, WASHER.obj_id, BRACKET.obj_id)

    def __init__(self, detections) -> None:
        self.detections = detections

    def detect(self, rgb, roi=None):
        return list(self.detections)


def test_the_pipeline_rescues_the_parts_the_detector_missed_or_misnamed(scene):
    models = {m.obj_id: m for m in (NUT, WASHER, BRACKET)}
    strategies = {NUT.obj_id: "depth+icp", WASHER.obj_id: "depth+icp", BRACKET.obj_id: "depth+search"}
    frame = Frame(_colours(scene.masks), scene.depth, CAMERA, 0.0)
    # the nut found; the washer missed; the bracket called a nut (its pose refused)
    detections = [detection(NUT, blob(scene.masks[0])), detection(NUT, blob(scene.masks[2]), obj_id=NUT.obj_id)]
    pipeline = PerceptionPipeline(
        _FixedDetector(detections), None, models, strategies=strategies,  # type: ignore[arg-type]
        floor_plane_camera=FLOOR, floor_bounds_camera_m=BOUNDS, depth_tare=None,
    )  # fmt: skip
    result = pipeline.run(frame)
    assert [p.obj_id for p in result.poses] == [NUT.obj_id] and len(result.refused) == 1
    more = pipeline.rescue(result.poses, frame)
    assert more is not None and any(p is result.poses[0] for p in more)  # the detected nut kept as it was
    found = {p.obj_id: p for p in more if "rescued" in p.details}
    assert sorted(found) == [WASHER.obj_id, BRACKET.obj_id]
    for k, model in ((1, WASHER), (2, BRACKET)):
        pose = found[model.obj_id]
        assert pose.verified and pose.detection.score == 0.0
        assert pose_errors(pose.T_camera_object, scene.poses[k], model).correct()
    assert [p.score for p in more] == sorted((p.score for p in more), reverse=True)
    # everything explained: nothing new; no floor plane: no rescue at all
    assert pipeline.rescue(more, frame) is None
    no_floor = PerceptionPipeline(_FixedDetector(detections), None, models, strategies=strategies)  # type: ignore[arg-type]
    assert no_floor.rescue(result.poses, frame) is None
