"""perception.resting and its use by the pose strategies, on ray-cast scenes with known answers: stable poses, a fit
levelled back onto the floor, a washer the depth cannot see placed from its mask, a leaning part left as fitted."""

from __future__ import annotations

import re

import numpy as np
import pytest

from perception import pose_strategies
from perception.observation import Observation
from perception.pose_strategies import StrategyConfig, StrategyRunner
from perception.resting import _perpendicular, planar_search, rest_on_support, stable_poses
from perception.verify import PoseVerifier, VerifyConfig
from sygrid.metrics import pose_errors
from sygrid.objects.parts import builtin_part
from sygrid.sensor import sensor_preset
from sygrid.transforms import make_T, rotation_about
from tests.raycast_scene import CAMERA, T_CAMERA_FLOOR, detection, on_floor, render

NUT, WASHER = builtin_part("hex_nut"), builtin_part("washer")
NORMAL = T_CAMERA_FLOOR[:3, 2]
FLOOR = np.append(NORMAL, -NORMAL @ T_CAMERA_FLOOR[:3, 3])  # the floor plane, normal towards the camera


def height_above(T_camera_object: np.ndarray, model, plane: np.ndarray) -> float:
    """The lowest point of ``model`` at the pose above ``plane`` [m] (negative: through it)."""
    hull = np.asarray(model.mesh.convex_hull.vertices)
    return float(((hull @ T_camera_object[:3, :3].T + T_camera_object[:3, 3]) @ plane[:3] + plane[3]).min())


def test_a_washer_rests_on_either_face_most_often():
    poses = stable_poses(WASHER)
    z = np.asarray(WASHER.mesh.vertices)[:, 2]
    assert len(poses.up) >= 3  # both faces, and on its rim
    for k in (0, 1):  # the two faces are the likely ones, the origin half the thickness up
        assert abs(abs(poses.up[k][2]) - 1.0) < 1e-6
        assert poses.height_m[k] == pytest.approx((z.max() - z.min()) / 2, abs=1e-5)
    assert poses.probability[0] + poses.probability[1] > 0.8
    np.testing.assert_allclose(np.linalg.norm(poses.up, axis=1), 1.0)


def test_a_tilted_floating_fit_is_put_back_on_the_floor():
    T_true = on_floor(NUT, 0.01, -0.02, 25.0)
    tilted = T_true @ make_T(rotation_about(np.array([1.0, 0.3, 0.0]), np.radians(12.0)))
    tilted[:3, 3] += 0.003 * NORMAL  # and 3 mm above the floor
    T, tilt = rest_on_support(tilted, NUT, FLOOR)
    err = pose_errors(T, T_true, NUT)
    assert tilt == pytest.approx(12.0, abs=0.1)
    assert err.re_deg < 0.1 and err.te_m < 1e-5, err
    assert height_above(T, NUT, FLOOR) == pytest.approx(0.0, abs=1e-6)


def _noisy_runner(**config) -> StrategyRunner:
    """The strategies with a verification that allows the OAK-D model's depth noise at a bin 0.75 m away, here where
    the fixture's camera is (0.32 m from the floor): a washer's thickness is within that noise."""
    sigma_at_bin = float(sensor_preset("oak-d").depth_noise_sigma_m(0.75))
    verifier = PoseVerifier(VerifyConfig(depth_noise_m=sigma_at_bin / 0.32**2))
    return StrategyRunner(verifier=verifier, config=StrategyConfig(**config))


def test_a_washer_the_depth_cannot_see_is_placed_from_its_mask():
    T_true = on_floor(WASHER, 0.01, 0.005, 0.0)
    seen = render([(WASHER, T_true)])
    floor_only = render([])  # the depth as a stereo camera whose step exceeds the washer's thickness reports it
    det = detection(WASHER, seen.masks[0])
    pose = _noisy_runner().estimate("depth+icp", det, floor_only.depth, CAMERA, WASHER, None, FLOOR)
    err = pose_errors(pose.T_camera_object, T_true, WASHER)
    assert pose.details["hypothesis"] == "mask_rest"
    assert err.correct() and err.te_m < 0.001, err
    assert pose.verified, pose.details["verify"]
    # without the resting hypotheses there is nothing to fit
    assert _noisy_runner(rest=False).estimate("depth+icp", det, floor_only.depth, CAMERA, WASHER, None, FLOOR) is None


def test_a_one_pixel_mask_without_depth_is_placed_not_crashed():
    """A far, tiny part: one mask pixel and no depth on it (it crashed the mask placement's principal axis)."""
    T_true = on_floor(WASHER, 0.01, 0.005, 0.0)
    seen = render([(WASHER, T_true)]).masks[0]
    mask = np.zeros_like(seen)
    ys, xs = np.nonzero(seen)
    mask[int(np.median(ys)), int(np.median(xs))] = True
    pose = _noisy_runner().estimate("depth+icp", detection(WASHER, mask), render([]).depth, CAMERA, WASHER, None, FLOOR)
    assert pose is not None and np.isfinite(pose.T_camera_object).all()
    assert pose.details["hypothesis"] == "mask_rest"


def test_a_part_leaning_out_of_any_stable_pose_keeps_its_free_fit():
    leaning = on_floor(WASHER, 0.0, 0.0, 0.0, rotation_about(np.array([1.0, 0.0, 0.0]), np.radians(60.0)))
    seen = render([(WASHER, leaning)])
    pose = StrategyRunner().estimate(
        "depth+icp", detection(WASHER, seen.masks[0]), seen.depth, CAMERA, WASHER, None, FLOOR
    )
    assert not pose.details["hypothesis"].endswith("+rest")
    assert pose_errors(pose.T_camera_object, leaning, WASHER).correct()


def test_a_fit_already_at_rest_is_left_as_it_is():
    T_true = on_floor(NUT, -0.01, 0.01, 10.0)
    seen = render([(NUT, T_true)])
    pose = StrategyRunner().estimate("depth+icp", detection(NUT, seen.masks[0]), seen.depth, CAMERA, NUT, None, FLOOR)
    err = pose_errors(pose.T_camera_object, T_true, NUT)
    assert not pose.details["hypothesis"].endswith("+rest") and err.te_m < 5e-4 and err.re_deg < 1.0, err


def test_a_level_fit_the_outline_refuses_is_still_searched_in_the_plane():
    """A washer flat on the floor, in depth noise the verification allows for (its thickness within it): its depth
    agrees wherever it lies on the floor, so a fit slid across the floor is level and on it (nothing for the
    levelling to do), and only the outline refuses it. The in-plane search still runs and slides it home."""
    T_true = on_floor(WASHER, 0.0, 0.0, 0.0)
    seen = render([(WASHER, T_true)])
    crop = Observation.of_detection(seen.depth, detection(WASHER, seen.masks[0]), CAMERA)
    obs = crop.with_mask(crop.mask, FLOOR)
    slid = T_true.copy()
    slid[:3, 3] += 0.15 * WASHER.diameter_m * _perpendicular(NORMAL)
    runner = _noisy_runner()
    v = runner.verifier.verify(slid, WASHER, obs)
    assert v.fit > 0.95 and v.iou < 0.8 and not v.accepted, v
    rested = runner._rested(pose_strategies._Candidate(slid, "slid", v), WASHER, obs)
    assert rested.source == "slid+rest" and rested.verification.accepted, rested.verification
    assert pose_errors(rested.T, T_true, WASHER).te_m < 5e-4
    accepted = runner._rested(
        pose_strategies._Candidate(T_true, "true", runner.verifier.verify(T_true, WASHER, obs)), WASHER, obs
    )
    assert accepted.source == "true"  # an accepted fit at rest is left as it is


def test_a_fit_to_noisy_depth_is_levelled_onto_the_floor():
    T_true = on_floor(NUT, 0.0, 0.0, 20.0)
    seen = render([(NUT, T_true)])
    noise = np.random.default_rng(3).normal(0.0, 0.0015, seen.depth.shape)  # a stereo camera's noise, per pixel
    noisy = np.where(seen.depth > 0, seen.depth + noise, 0.0).astype(np.float32)
    det = detection(NUT, seen.masks[0])
    free = _noisy_runner(rest=False).estimate("depth+icp", det, noisy, CAMERA, NUT, None, FLOOR)
    rested = _noisy_runner().estimate("depth+icp", det, noisy, CAMERA, NUT, None, FLOOR)
    err_free, err = (pose_errors(p.T_camera_object, T_true, NUT) for p in (free, rested))
    assert rested.details["hypothesis"].endswith("+rest")
    assert height_above(rested.T_camera_object, NUT, FLOOR) == pytest.approx(0.0, abs=1e-6)
    assert err_free.re_deg > 3.0 and err.re_deg < 0.3 * err_free.re_deg, (err, err_free)  # the tilt is gone
    assert err.add_m < err_free.add_m and err.correct(), (err, err_free)
    confident = _noisy_runner(rest_confident=free.details["rank_confidence"])  # the score the search compares
    trusting = confident.estimate("depth+icp", det, noisy, CAMERA, NUT, None, FLOOR)
    assert not trusting.details["hypothesis"].endswith("+rest")  # a free fit this confident is left as it is


def test_a_noisy_fit_is_tried_at_rest_before_escaping_from_it(monkeypatch):
    """Depth noise beyond the verification's allowance here leaves the right ICP fit short of the search's bar: the
    fit levelled onto the floor is searched first and confirmed there, instead of escaping from it (turns, slides:
    a dozen ICP runs more) and then polishing it."""
    T_true = on_floor(NUT, 0.0, 0.0, 20.0)
    seen = render([(NUT, T_true)])
    noise = np.random.default_rng(1).normal(0.0, 0.003, seen.depth.shape)
    noisy = np.where(seen.depth > 0, seen.depth + noise, 0.0).astype(np.float32)
    det = detection(NUT, seen.masks[0])
    runs = []
    counted = pose_strategies.icp
    monkeypatch.setattr(pose_strategies, "icp", lambda *a, **k: runs.append(1) or counted(*a, **k))
    poses = {}
    for gate in (0.85, 2.0):  # 2: never at rest first
        runs.clear()
        pose = _noisy_runner(rest_first_gate=gate).estimate("depth+icp", det, noisy, CAMERA, NUT, None, FLOOR)
        poses[gate] = (pose, len(runs))
    (first, n_first), (late, n_late) = poses[0.85], poses[2.0]
    # a ranked start refined and levelled, no turn, slide or polish: the ranked starts' ICP runs only
    assert re.fullmatch(r"axes_\d+\+icp\+rest", first.details["hypothesis"]) and n_first == 3
    assert "polish" in late.details["hypothesis"] and n_late > 10
    for pose in (first, late):
        assert pose.verified and pose_errors(pose.T_camera_object, T_true, NUT).correct()


def test_bad_rest_settings_are_refused():
    with pytest.raises(ValueError, match="rest_max_tilt_deg"):
        StrategyConfig(rest_max_tilt_deg=200.0)
    with pytest.raises(ValueError, match="rest_steps"):
        StrategyConfig(rest_steps=((0.0, 1.0),))
    with pytest.raises(ValueError, match="rest_confident"):
        StrategyConfig(rest_confident=0.0)
    with pytest.raises(ValueError, match="rest_first_gate"):
        StrategyConfig(rest_first_gate=0.0)


class _Counting:
    """A verifier that counts the poses it is asked to verify."""

    def __init__(self, verifier: PoseVerifier) -> None:
        self.verifier, self.calls = verifier, 0

    def verify(self, *args, **kwargs):
        self.calls += 1
        return self.verifier.verify(*args, **kwargs)


def test_the_planar_search_walks_a_slid_and_turned_part_back_one_evaluation_a_step():
    T_true = on_floor(NUT, 0.0, 0.0, 20.0)
    seen = render([(NUT, T_true)])
    crop = Observation.of_detection(seen.depth, detection(NUT, seen.masks[0]), CAMERA)
    obs = crop.with_mask(crop.mask, FLOOR)
    step_m = 0.05 * NUT.diameter_m
    start = T_true.copy()
    start[:3, 3] -= 4 * step_m * _perpendicular(NORMAL)  # four steps of the first move (the first in-plane axis)
    counting = _Counting(PoseVerifier())
    T, v = planar_search(start, NUT, obs, FLOOR, counting, ((0.05, 5.0),))
    np.testing.assert_allclose(T, T_true, atol=1e-9)
    assert v.confidence > 0.99
    # one evaluation to start, one for each step of the walk (the move that paid is tried first), then the five
    # moves that confirm no step improves (the move back to where the last step came from is known to be worse):
    # steepest ascent would have evaluated all six moves for every step
    assert counting.calls == 1 + 4 + 5
    turned = T_true.copy()
    turned[:3, :3] = rotation_about(NORMAL, np.radians(-15.0)) @ T_true[:3, :3]  # three turns of 5 degrees
    T, _ = planar_search(turned, NUT, obs, FLOOR, PoseVerifier(), ((0.05, 5.0),))
    assert pose_errors(T, T_true, NUT).re_deg < 0.1
