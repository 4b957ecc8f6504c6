"""perception.verify on ray-cast scenes: the true pose agrees with the depth and mask, wrong poses and a wrong
part's model are refused; occluders in front of a part are no evidence against it."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from perception.observation import Observation
from perception.pose_strategies import StrategyRunner
from perception.verify import PoseVerifier, VerifyConfig, mask_holes, raycaster
from sygrid.objects.parts import builtin_part
from sygrid.transforms import make_T, rotation_about
from tests.raycast_scene import CAMERA, T_CAMERA_FLOOR, detection, on_floor, render

NUT, WASHER, BRACKET = builtin_part("hex_nut"), builtin_part("washer"), builtin_part("l_bracket")
R_SIDE = rotation_about(np.array([1.0, 0.0, 0.0]), np.pi / 2)


@pytest.fixture(scope="module")
def scene():
    return render(
        [
            (NUT, on_floor(NUT, 0.0, 0.0, 20.0)),
            (WASHER, on_floor(WASHER, 0.04, 0.0, 0.0)),
            (BRACKET, on_floor(BRACKET, -0.045, 0.01, 30.0, R_SIDE)),
        ]
    )


def _obs(scene, k: int, model) -> Observation:
    return Observation.of_detection(scene.depth, detection(model, scene.masks[k]), CAMERA)


@pytest.mark.parametrize(("k", "model"), [(0, NUT), (1, WASHER), (2, BRACKET)])
def test_the_true_pose_is_accepted_and_wrong_poses_refused(scene, k, model):
    verifier = PoseVerifier()
    obs = _obs(scene, k, model)
    T = scene.poses[k]
    true = verifier.verify(T, model, obs)
    assert true.accepted and true.confidence > 0.97 and true.fit > 0.97 and true.coverage > 0.97
    assert true.violations <= 0.02 * true.rendered and true.rmse_m < 1e-4
    shifted = T.copy()
    shifted[:3, 3] += 0.3 * model.diameter_m * np.array([1.0, 0.0, 0.0])
    tilted = T @ make_T(rotation_about(np.array([0.0, 1.0, 0.0]), np.radians(60.0)))
    for wrong in (shifted, tilted):
        v = verifier.verify(wrong, model, obs)
        assert not v.accepted and v.confidence < true.confidence - 0.2, v


def test_a_part_is_held_to_its_own_threshold_where_it_has_one(scene):
    obs, T = _obs(scene, 0, NUT), scene.poses[0].copy()
    T[0, 3] += 0.1 * NUT.diameter_m  # a pose the outline agrees with in part
    confidence = PoseVerifier().verify(T, NUT, obs).confidence
    assert 0.1 < confidence < 0.99
    strict = VerifyConfig(min_confidence=0.0, part_min_confidence={"hex_nut": min(confidence + 0.01, 1.0)})
    lenient = VerifyConfig(min_confidence=1.0, part_min_confidence={"hex_nut": confidence - 0.01})
    assert not PoseVerifier(strict).verify(T, NUT, obs).accepted
    assert PoseVerifier(lenient).verify(T, NUT, obs).accepted
    assert strict.threshold("washer") == 0.0 and lenient.threshold("washer") == 1.0  # the others: min_confidence
    with pytest.raises(ValueError, match="part_min_confidence must be in"):
        VerifyConfig(part_min_confidence={"hex_nut": 1.5})


@pytest.mark.parametrize(("k", "model"), [(0, NUT), (1, WASHER), (2, BRACKET)])
def test_a_half_pixel_error_costs_little(scene, k, model):
    """The true pose seen half a pixel off (the principal point moved): an edge is known to a pixel at best, so the
    pixels along silhouettes and depth steps still agree within their footprint and the confidence stays high
    (at their centres alone, 5-7 % of them here do not)."""
    camera = dataclasses.replace(CAMERA, cx=CAMERA.cx + 0.5, cy=CAMERA.cy + 0.5)
    obs = Observation.of_detection(scene.depth, detection(model, scene.masks[k]), camera)
    verifier = PoseVerifier()
    v = verifier.verify(scene.poses[k], model, obs, footprint=True)
    assert v.confidence > 0.98 and v.coverage > 0.98, v
    assert verifier.verify(scene.poses[k], model, obs).confidence < v.confidence  # ranking: at the centres


def test_a_wrong_class_fit_is_refused(scene):
    """The washer's model fitted (the full depth strategy) into the nut's mask, and the nut's into the washer's:
    the best each can do still disagrees with the depth, and the verification refuses it; the right model passes."""
    runner = StrategyRunner()
    for k, model, wrong in ((0, NUT, WASHER), (1, WASHER, NUT)):
        det = detection(model, scene.masks[k], obj_id=wrong.obj_id)
        fitted = runner.estimate("depth+icp", det, scene.depth, CAMERA, wrong)
        assert fitted is not None and fitted.verified is False, fitted.details["verify"]
        right = runner.estimate("depth+icp", detection(model, scene.masks[k]), scene.depth, CAMERA, model)
        assert right.verified and right.score > fitted.score + 0.2


def test_an_occluder_in_front_is_no_evidence_against_the_pose():
    T_nut = on_floor(NUT, 0.0, 0.0, 20.0)
    # a washer floating 6 mm above the nut's top, half over it: it hides part of the nut from the camera
    T_washer = T_nut @ make_T(t=[0.008, 0.0, 0.0114])
    scene = render([(NUT, T_nut), (WASHER, T_washer)])
    visible_share = scene.masks[0].sum() / render([(NUT, T_nut)]).masks[0].sum()
    assert 0.2 < visible_share < 0.8  # the washer does hide part of it
    v = PoseVerifier().verify(T_nut, NUT, _obs(scene, 0, NUT))
    assert v.accepted and v.confidence > 0.97 and v.occluded > 0


def test_tolerance_grows_with_depth_noise_and_the_visibility_test_sees_the_front():
    quiet, noisy = PoseVerifier(), PoseVerifier(VerifyConfig(depth_noise_m=0.002))
    assert quiet.tolerance_m(NUT, 1.0) == pytest.approx(max(0.001, VerifyConfig().tolerance_fraction * NUT.diameter_m))
    assert noisy.tolerance_m(NUT, 1.0) == pytest.approx(quiet.tolerance_m(NUT, 1.0) + 0.006)
    T = make_T(t=[0.0, 0.0, 0.3])  # the nut's z axis along the view: its top face (z max) faces away
    top_bottom = np.array([[0.0, 0.0, NUT.bounds_m[0, 2]], [0.0, 0.0, NUT.bounds_m[1, 2]]])
    # points on the axis lie in the hole, which the ray crosses: both visible; a point on the far face behind
    # the near face is not
    far = np.array([[0.007, 0.0, NUT.bounds_m[1, 2]], [0.007, 0.0, NUT.bounds_m[0, 2]]])
    assert raycaster(NUT).visible(T, top_bottom).tolist() == [True, True]
    assert raycaster(NUT).visible(T, far).tolist() == [False, True]
    with pytest.raises(ValueError, match="min_confidence"):
        VerifyConfig(min_confidence=1.5)


def test_where_depth_cannot_tell_the_outline_does():
    """A washer on the floor whose metal returns no depth but a glint's patch, verified with a noise allowance wider
    than its thickness (its top and the floor agree within it): slid by a fifth of its diameter it still explains
    the patch and the floor, so its depth agreement alone would pass it, but its outline leaves the part's
    silhouette and it is refused; the true pose is accepted."""
    T = on_floor(WASHER, 0.0, 0.0, 0.0)
    scene = render([(WASHER, T)])
    mask = scene.masks[0]
    ys, xs = np.nonzero(mask)
    yy, xx = np.mgrid[: mask.shape[0], : mask.shape[1]]
    radius = (xs.max() - xs.min()) / 2
    patch = mask & (xx > xs.mean() + 0.5 * radius) & (np.abs(yy - ys.mean()) < 0.3 * radius)
    depth = np.where(mask & ~patch, 0.0, scene.depth)
    obs = Observation.of_detection(depth, detection(WASHER, mask), CAMERA)
    verifier = PoseVerifier(VerifyConfig(depth_noise_m=0.008))
    true = verifier.verify(T, WASHER, obs, footprint=True)
    assert true.accepted and true.confidence > 0.97 and true.iou > 0.97
    slid = verifier.verify(T @ make_T(t=[0.0, 0.2 * WASHER.diameter_m, 0.0]), WASHER, obs, footprint=True)
    assert slid.depth_confidence > 0.95 and slid.iou < 0.4
    assert not slid.accepted and slid.confidence < 0.7
    assert slid.confidence == pytest.approx(np.sqrt(slid.fit * slid.coverage * slid.iou))


def test_a_mask_without_depth_is_judged_by_the_fit_around_it_and_the_outline():
    """A washer whose top returns no depth over all the segmenter drew (a stereo dropout; the mask a pixel tight):
    no mask pixel is left for the model to explain, so coverage cannot speak (1); the depth around the mask, where
    the model's rim renders, and the outline decide. The true pose is accepted, the pose slid off the silhouette is
    refused."""
    T = on_floor(WASHER, 0.0, 0.0, 0.0)
    scene = render([(WASHER, T)])
    mask = cv2.erode(scene.masks[0].astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    obs = Observation.of_detection(np.where(mask, 0.0, scene.depth), detection(WASHER, mask), CAMERA)
    verifier = PoseVerifier()
    true = verifier.verify(T, WASHER, obs, footprint=True)
    assert true.mask_pixels == 0 and true.coverage == 1.0
    assert true.accepted and true.confidence == pytest.approx(np.sqrt(true.fit * true.iou)) and true.fit == 1.0
    slid = verifier.verify(T @ make_T(t=[0.0, 0.3 * WASHER.diameter_m, 0.0]), WASHER, obs, footprint=True)
    assert not slid.accepted and slid.confidence < true.confidence - 0.2, slid


def test_the_outline_is_the_segmenters_mask_before_the_clean_up(scene):
    """The mask cleaned down to a third (the clean-up dropping pixels whose depth it distrusts) leaves the part's
    silhouette as the segmenter drew it: the true pose's outline still matches it."""
    obs = _obs(scene, 1, WASHER)
    cols = np.arange(obs.mask.shape[1])[None, :]
    kept = obs.mask & (cols < np.nonzero(obs.mask.any(axis=0))[0].mean())
    cleaned = obs.with_mask(kept).with_mask(kept)  # cleaned twice: still the first mask's outline
    assert np.array_equal(cleaned.seen_mask, obs.mask) and np.array_equal(cleaned.mask, kept)
    assert obs.silhouette is None and np.array_equal(obs.seen_mask, obs.mask)
    v = PoseVerifier().verify(scene.poses[1], WASHER, cleaned, footprint=True)
    assert v.accepted and v.iou > 0.97 and v.mask_pixels < 0.6 * obs.mask.sum()


def test_part_of_the_part_the_segmenter_missed_is_no_evidence_against_the_pose(scene):
    """A mask covering only half of the bracket (a detector's under-segmentation): where the model shows its surface
    in the depth, clear of the floor it lies on, the outline missing from the mask counts neither way, and the true
    pose keeps its outline agreement; without the floor plane nothing tells those pixels from a wrong pose's."""
    normal = -T_CAMERA_FLOOR[:3, 2] if T_CAMERA_FLOOR[2, 2] > 0 else T_CAMERA_FLOOR[:3, 2]
    floor = np.append(normal, -normal @ T_CAMERA_FLOOR[:3, 3])  # normal towards the camera
    full = _obs(scene, 2, BRACKET)
    cols = np.arange(full.mask.shape[1])[None, :]
    half = full.mask & (cols < np.nonzero(full.mask.any(axis=0))[0].mean())
    obs = Observation(full.depth_m, half, full.x0, full.y0, CAMERA)
    verifier = PoseVerifier()
    with_floor = verifier.verify(scene.poses[2], BRACKET, obs.with_mask(half, floor), footprint=True)
    assert with_floor.accepted and with_floor.iou > 0.9
    without = verifier.verify(scene.poses[2], BRACKET, obs, footprint=True)
    assert without.iou < 0.7 and without.confidence < with_floor.confidence


def test_the_models_holes_are_the_outside_pixels_cut_off_from_the_border():
    from scipy import ndimage

    ring = np.zeros((9, 9), bool)
    ring[2:7, 2:7] = True
    ring[4, 4] = False  # a washer's hole
    ring[3:6, 8] = True  # a piece touching the border leaves the border's pixels outside
    holes = mask_holes(ring)
    assert np.argwhere(holes).tolist() == [[4, 4]]
    diagonal = np.zeros((5, 5), bool)
    diagonal[[1, 2, 3, 2], [2, 1, 2, 3]] = True  # the centre joined to the outside only diagonally: still a hole
    assert np.argwhere(mask_holes(diagonal)).tolist() == [[2, 2]]
    rng = np.random.default_rng(3)  # scipy's definition, 4-connected background, on random masks
    for _ in range(200):
        mask = rng.random(tuple(rng.integers(1, 40, 2))) < rng.uniform(0.3, 0.9)
        assert np.array_equal(mask_holes(mask), ndimage.binary_fill_holes(mask) & ~mask)


def test_the_observations_mask_box_bounds_the_mask():
    mask = np.zeros((10, 12), bool)
    mask[3:6, 4:9] = True
    obs = Observation(np.ones((10, 12)), mask, 0, 0, CAMERA)
    assert obs.mask_box == (4, 3, 9, 6)
    assert Observation(np.ones((10, 12)), np.zeros((10, 12), bool), 0, 0, CAMERA).mask_box is None
