"""perception.pose_strategies, perception.mask_cleanup and the strategy choice, on ray-cast scenes with known
answers: parts lying on the bin's floor (a symmetric nut, a washer, a bracket on its side, a bolt), detector-like
masks (filled and grown), and a pose network's estimate stood in for by the true pose turned and shifted."""

from __future__ import annotations

import json
import math
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from launch.choose_pose import format_choice, write_choice
from perception.manifest import load_manifest
from perception.mask_cleanup import clean_mask, support_plane
from perception.observation import Observation
from perception.pipeline import PerceptionPipeline
from perception.pose_strategies import STRATEGIES, StrategyRunner, axis_rotations
from perception.results import ObjectPose
from perception.strategy_eval import (
    StrategyRecord,
    choose,
    choose_all,
    choose_part_thresholds,
    choose_threshold,
    summarize,
    visibility_gates,
)
from sygrid.errors import ConfigError
from sygrid.metrics import pose_errors
from sygrid.objects.parts import builtin_part
from sygrid.sensor import sensor_preset
from sygrid.transforms import make_T, rotation_about
from tests.raycast_scene import CAMERA, T_CAMERA_FLOOR, blob, detection, on_floor, render

ROOT = Path(__file__).resolve().parents[1]
NUT, WASHER, BRACKET, BOLT = (builtin_part(n) for n in ("hex_nut", "washer", "l_bracket", "hex_bolt"))
R_SIDE = rotation_about(np.array([1.0, 0.0, 0.0]), np.pi / 2)


@pytest.fixture(scope="module")
def scene():
    return render(
        [
            (NUT, on_floor(NUT, 0.0, 0.0, 20.0)),
            (WASHER, on_floor(WASHER, 0.04, 0.0, 0.0)),
            (BRACKET, on_floor(BRACKET, -0.045, 0.01, 30.0, R_SIDE)),
            (BOLT, on_floor(BOLT, 0.0, 0.045, 50.0, R_SIDE)),
        ]
    )


def _network_guess(T: np.ndarray) -> np.ndarray:
    """A pose network's kind of error: 12 degrees off and 25 mm too far along the view."""
    guess = T @ make_T(rotation_about(np.array([0.3, 1.0, 0.2]), np.radians(12.0)))
    guess[:3, 3] *= 1.0 + 0.025 / np.linalg.norm(T[:3, 3])
    return guess


@pytest.mark.parametrize("k", [0, 1, 2, 3])
def test_every_strategy_on_parts_lying_on_the_floor(scene, k):
    model = (NUT, WASHER, BRACKET, BOLT)[k]
    T_true = scene.poses[k]
    det = detection(model, blob(scene.masks[k]))  # a filled, grown mask: floor in the holes and around
    network = ObjectPose(det, _network_guess(T_true), 0.7, "direct")
    runner = StrategyRunner()
    results = {s: runner.estimate(s, det, scene.depth, CAMERA, model, network) for s in STRATEGIES}
    errors = {s: pose_errors(p.T_camera_object, T_true, model) for s, p in results.items()}
    # rgb: the network's pose as it is, which the verification refuses
    np.testing.assert_array_equal(results["rgb"].T_camera_object, network.T_camera_object)
    assert results["rgb"].verified is False and results["rgb"].method == "rgb"
    # rgbd: the network's rotation, the translation from depth: far nearer than the network's 25 mm
    assert errors["rgbd"].te_m < 0.4 * errors["rgb"].te_m
    np.testing.assert_allclose(results["rgbd"].T_camera_object[:3, :3], network.T_camera_object[:3, :3])
    # the refined strategies find the pose, and the verification accepts it
    for s in ("rgbd+icp", "depth+icp", "hybrid+icp"):
        assert errors[s].correct(), (s, errors[s])
        assert errors[s].te_m < 0.001 and errors[s].re_deg < 2.0, (s, errors[s])
        # (the score includes the outline's agreement with the mask, here grown two pixels all round: a 21 px washer
        # keeps an IoU near 0.7)
        assert results[s].verified and results[s].score > 0.8, (s, results[s].details["verify"])
        assert results[s].details["strategy"] == s and results[s].details["cleanup"]["kept"] > 0
    # without ICP the depth strategies start from principal axes: a pose near the part, not a finished one
    for s in ("depth", "hybrid"):
        assert errors[s].te_m < 0.5 * model.diameter_m, (s, errors[s])
    assert runner.estimate("depth+icp", det, scene.depth, CAMERA, model).verified  # no network needed


def test_a_symmetric_part_is_found_modulo_its_symmetry(scene):
    """The nut (D6): the estimate may be any of its symmetric poses; the symmetry-aware errors are small, and the
    principal-axis hypotheses are few (the equivalent assignments of axes are merged)."""
    det = detection(NUT, scene.masks[0])
    pose = StrategyRunner().estimate("depth+icp", det, scene.depth, CAMERA, NUT)
    err = pose_errors(pose.T_camera_object, scene.poses[0], NUT)
    assert err.re_deg < 2.0 and err.te_m < 0.0005
    obs = Observation.of_detection(scene.depth, det, CAMERA)
    assert len(axis_rotations(NUT, obs.points)) == 6 and len(axis_rotations(WASHER, obs.points)) == 3
    assert len(axis_rotations(BRACKET, obs.points)) == 12


def test_mask_cleanup_removes_the_floor_in_holes_and_around_the_part(scene):
    for k, model in ((0, NUT), (1, WASHER)):
        truth = scene.masks[k]
        obs = Observation.of_detection(scene.depth, detection(model, blob(truth, grow_px=3)), CAMERA)
        cleaned, details = clean_mask(obs)
        inside = truth[obs.y0 : obs.y0 + obs.mask.shape[0], obs.x0 : obs.x0 + obs.mask.shape[1]]
        assert details["floor"] + details["hole"] + details["rim"] > 0.2 * details["pixels"], details
        assert (cleaned.mask & ~inside).sum() <= 0.02 * inside.sum(), details  # hardly any floor left
        assert (cleaned.mask & inside).sum() >= 0.9 * inside.sum(), details  # and nearly all of the part kept
    # the support plane found around the nut is the floor
    plane = support_plane(Observation.of_detection(scene.depth, detection(NUT, blob(scene.masks[0])), CAMERA))
    normal = T_CAMERA_FLOOR[:3, 2]
    assert plane is not None and abs(abs(plane[:3] @ normal) - 1.0) < 1e-3
    assert (
        abs(plane[3] + (-normal @ T_CAMERA_FLOOR[:3, 3])) < 1e-3
        or abs(plane[3] - (-normal @ T_CAMERA_FLOOR[:3, 3])) < 1e-3
    )


def test_a_floor_plane_given_by_the_cell_is_used_as_it_is(scene):
    normal = -T_CAMERA_FLOOR[:3, 2] if T_CAMERA_FLOOR[2, 2] > 0 else T_CAMERA_FLOOR[:3, 2]
    plane = np.append(normal, -normal @ T_CAMERA_FLOOR[:3, 3])  # normal towards the camera: up out of the floor
    obs = Observation.of_detection(scene.depth, detection(WASHER, blob(scene.masks[1])), CAMERA)
    cleaned, details = clean_mask(obs, floor_plane_camera=plane)
    assert details["floor"] > 0 and details["kept"] == cleaned.mask.sum()


def _record(obj_id: int, strategy: str, correct: bool, cpu_ms: float, confidence: float) -> StrategyRecord:
    return StrategyRecord(obj_id, strategy, correct, 1.0, 0.001, cpu_ms, cpu_ms, confidence, 0.2)


def test_visibility_gates_count_the_false_accepts_left_above_each_gate():
    def rec(correct: bool, confidence: float, visible: float) -> StrategyRecord:
        return StrategyRecord(1, "s", correct, 1.0, 0.001, 1.0, 1.0, confidence, visib_fract=visible)

    records = [rec(True, 0.95, 0.9)] * 6 + [rec(False, 0.97, 0.15), rec(False, 0.96, 0.35), rec(True, 0.95, 0.25),
                                            rec(True, 0.5, 0.8)]  # fmt: skip
    low, mid, high = visibility_gates(records, 0.9, (0.1, 0.3, 0.5))
    assert (low["accepted"], low["false_accept"], low["accepted_recall"]) == (9, 2 / 9, 7 / 10)
    assert (mid["accepted"], mid["false_accept"], mid["accepted_recall"]) == (7, 1 / 7, 6 / 10)
    assert (high["accepted"], high["false_accept"], high["accepted_recall"]) == (6, 0.0, 6 / 10)


def test_the_choice_is_the_cheapest_strategy_that_meets_the_bar_else_the_most_accurate():
    records = {
        (1, "rgbd+icp"): [_record(1, "rgbd+icp", k < 9, 5.0, 0.97) for k in range(10)],  # 90 %, cheap
        (1, "depth+icp"): [_record(1, "depth+icp", True, 9.0, 0.98) for _ in range(10)],  # 100 %, dearer
        (2, "rgbd+icp"): [_record(2, "rgbd+icp", k < 6, 5.0, 0.9) for k in range(10)],  # 60 %
        (2, "depth+icp"): [_record(2, "depth+icp", k < 8, 9.0, 0.9) for k in range(10)],  # 80 %
    }
    assert choose(records, 0.9, 0.9) == {1: "rgbd+icp", 2: "depth+icp"}
    assert choose(records, 0.95, 0.9) == {1: "depth+icp", 2: "depth+icp"}
    # at 0.975 rgbd+icp's 0.97 are refused; on part 2 everything is, and the cheaper of the two stays
    assert choose(records, 0.9, 0.975) == {1: "depth+icp", 2: "rgbd+icp"}
    assert choose_all(records, 0.9, 0.2) == ({1: "rgbd+icp", 2: "depth+icp"}, 0.5)
    assert choose_all(records, 0.9, 0.2, per_part=True) == ({1: "rgbd+icp", 2: "depth+icp"}, {1: 0.97, 2: 0.9})
    mixed = [_record(1, "s", True, 1.0, 0.9 + 0.001 * k) for k in range(99)] + [_record(1, "s", False, 1.0, 0.92)]
    assert choose_threshold(mixed, 0.0) == 0.93  # the one wrong estimate (0.92) is refused from 0.93 on
    row = summarize(mixed, 0.93)
    assert row["false_accept"] == 0.0 and row["wrong_class_accept"] == 0.0 and row["n"] == 100
    assert math.isclose(row["false_refuse"], 30 / 99)


def test_thresholds_per_part_spend_the_false_accept_budget_where_it_buys_most():
    """Part 1's confidence tells right from wrong at 0.85, part 2's only at 0.97: one threshold that refuses every
    wrong estimate refuses all of part 1's right ones too. Part 3's one wrong estimate lies between its right ones:
    accepting it keeps five more right ones, which a 5 % budget allows and a zero budget does not."""
    records = (
        [_record(1, "s", True, 1.0, 0.85)] * 10 + [_record(1, "s", False, 1.0, 0.80)]
        + [_record(2, "s", True, 1.0, 0.97)] * 10 + [_record(2, "s", False, 1.0, 0.95)]
        + [_record(3, "s", True, 1.0, 0.90)] * 5 + [_record(3, "s", False, 1.0, 0.88)]
        + [_record(3, "s", True, 1.0, 0.86)] * 5
    )  # fmt: skip
    strict = choose_part_thresholds(records, 0.0)
    assert strict == {1: 0.85, 2: 0.97, 3: 0.9}  # ties: the highest threshold that keeps the same right ones
    one = choose_threshold(records, 0.0)
    assert one == 0.96
    per_part, single = summarize(records, strict), summarize(records, one)
    assert per_part["false_accept"] == single["false_accept"] == 0.0
    assert per_part["accepted_recall"] == 25 / 33 and single["accepted_recall"] == 10 / 33
    budget = choose_part_thresholds(records, 0.05)
    assert budget == {1: 0.85, 2: 0.97, 3: 0.86}
    assert math.isclose(summarize(records, budget)["false_accept"], 1 / 31)
    assert choose_part_thresholds([_record(1, "s", False, 1.0, 0.999)], 0.0) == {1: 0.99}  # none meets it: the last


def test_the_choice_table_names_its_thresholds_and_sets_per_part_ones_beside_the_one():
    records = {(1, "s"): [_record(1, "s", True, 1.0, 0.85)] * 3, (2, "s"): [_record(2, "s", False, 1.0, 0.95)]}
    names = {1: "hex_nut", 2: "washer"}
    one = format_choice(records, {1: "s", 2: "s"}, 0.9, names)
    assert one.startswith("verification threshold 0.90 ") and "one 0.90" not in one
    per_part = format_choice(records, {1: "s", 2: "s"}, {1: 0.8, 2: 0.96}, names, 0.9).splitlines()
    assert per_part[0].startswith("verification thresholds hex_nut 0.80, washer 0.96 ")
    chosen, at_one = per_part[-2].split(), per_part[-1].split()
    assert chosen[:2] == ["chosen", "4"] and chosen[-3] == "0.0%"  # false accepts: the washer's wrong one refused
    assert at_one[:3] == ["chosen", "one", "0.90"] and at_one[-3] == "100.0%"  # at 0.90 only it is accepted


def test_the_manifest_choice_round_trip(tmp_path: Path):
    folder = tmp_path / "models"
    shutil.copytree(ROOT / "models" / "builtin", folder)
    names = [o["builtin"] for o in json.loads((folder / "manifest.json").read_text())["objects"]]
    choice = {n: ("depth+icp" if k % 2 else "rgbd+icp") for k, n in enumerate(names)}
    write_choice(folder, choice, 0.93)
    manifest = load_manifest(folder)
    assert manifest.pose.strategies == choice and manifest.verify.min_confidence == 0.93
    pipeline = PerceptionPipeline.from_folder(folder)
    assert {pipeline.models[i].name: s for i, s in pipeline.strategies.items()} == choice
    assert pipeline.runner.verifier.config.min_confidence == 0.93
    write_choice(folder, choice, 0.93, {names[0]: 0.81})
    config = PerceptionPipeline.from_folder(folder).runner.verifier.config
    assert config.threshold(names[0]) == 0.81 and config.threshold(names[1]) == 0.93
    write_choice(folder, choice, 0.93)  # one threshold again: the parts' own are removed
    assert load_manifest(folder).verify.part_min_confidence == {}
    data = json.loads((folder / "manifest.json").read_text())
    assert data["detector"]["onnx"] == "detector.onnx"  # everything else kept
    too_high = rf"verify.part_min_confidence.{names[0]}: must be <= 1.0, got 1.5"
    for bad, message in (({"sprocket": 0.8}, "verify.part_min_confidence: no object named sprocket"),
                         ({names[0]: 1.5}, too_high)):  # fmt: skip
        (folder / "manifest.json").write_text(json.dumps({**data, "verify": {"part_min_confidence": bad}}))
        with pytest.raises(ConfigError, match=rf"manifest.json: {message}"):
            PerceptionPipeline.from_folder(folder)
    (folder / "manifest.json").write_text(json.dumps(data))
    assert PerceptionPipeline.from_folder(folder).runner.config.good_confidence == 0.95  # the search bar's default
    (folder / "manifest.json").write_text(json.dumps({**data, "pose": {**data["pose"], "search_bar": 0.92}}))
    pipeline = PerceptionPipeline.from_folder(folder)
    assert pipeline.runner.config.good_confidence == 0.92
    pipeline.use_sensor(sensor_preset("oak-d"))  # a sensor changes the verification, not the search
    assert pipeline.runner.config.good_confidence == 0.92
    (folder / "manifest.json").write_text(json.dumps({**data, "pose": {**data["pose"], "search_bar": 0}}))
    with pytest.raises(ConfigError, match=r"manifest.json: pose.search_bar: must be > 0.0, got 0"):
        load_manifest(folder)
    data["pose"]["strategies"][names[0]] = "depth+magic"
    (folder / "manifest.json").write_text(json.dumps(data))
    with pytest.raises(ConfigError, match=rf"manifest.json: pose.strategies: .*{names[0]}: unknown pose strategy"):
        load_manifest(folder)
    del data["pose"]["strategies"][names[0]]
    (folder / "manifest.json").write_text(json.dumps(data))
    with pytest.raises(ConfigError, match=rf"manifest.json: pose.strategies: no strategy for {names[0]}"):
        PerceptionPipeline.from_folder(folder)


class _FixedDetector:
    """Returns the given detections for any frame."""

    conf_threshold = 0.5

    def __init__(self, detections) -> None:
        self.detections = detections

    def detect(self, rgb, roi=None):
        return list(self.detections)


class _TruthPoseNetwork:
    """A pose network that estimates each detection's given pose (by ``id`` of the detection)."""

    def __init__(self, poses: dict[int, np.ndarray]) -> None:
        self.poses = poses

    def estimate(self, rgb, detections, intrinsics, method=None):
        from perception.results import ObjectPose

        return [ObjectPose(d, self.poses[id(d)], 0.9, "direct") for d in detections]


def test_the_pipeline_follows_the_strategies_and_keeps_refused_poses_apart(scene):
    from perception.camera import Frame

    good = [detection(NUT, blob(scene.masks[0])), detection(WASHER, blob(scene.masks[1]))]
    wrong = detection(NUT, scene.masks[2], obj_id=NUT.obj_id)  # the bracket's mask called a nut
    models = {NUT.obj_id: NUT, WASHER.obj_id: WASHER}
    strategies = {NUT.obj_id: "depth+icp", WASHER.obj_id: "depth+icp"}  # no network: pose=None is never asked
    frame = Frame(np.zeros((CAMERA.height, CAMERA.width, 3), np.uint8), scene.depth, CAMERA, 0.0)
    pipeline = PerceptionPipeline(_FixedDetector([*good, wrong]), None, models, strategies=strategies)  # type: ignore[arg-type]
    result = pipeline.run(frame)
    assert sorted(p.obj_id for p in result.poses) == [NUT.obj_id, WASHER.obj_id]
    assert all(p.verified and p.method == "depth+icp" for p in result.poses)
    for p in result.poses:
        k = 0 if p.obj_id == NUT.obj_id else 1
        assert pose_errors(p.T_camera_object, scene.poses[k], models[p.obj_id]).correct()
    assert [p.detection for p in result.refused] == [wrong] and result.refused[0].verified is False
    assert set(result.timings_ms) == {"detect", "pose", "refine", "total"} and result.timings_ms["pose"] < 1.0
    # max_refined: the nearest part is fitted, the other waits for refine_more
    limited = PerceptionPipeline(_FixedDetector(good), None, models, max_refined=1, strategies=strategies)  # type: ignore[arg-type]
    first = limited.run(frame)
    assert sorted(p.details["icp"]["status"] for p in first.poses) == ["refined", "skipped"]
    more = limited.refine_more(first.poses, frame)
    assert more is not None and all(p.verified for p in more) and len(more) == 2
    assert limited.refine_more(more, frame) is None
    # a strategy that starts from the network: refine_more runs the network for the parts it fits
    truth = {id(d): scene.poses[k] for k, d in enumerate(good)}
    with_network = PerceptionPipeline(
        _FixedDetector(good), _TruthPoseNetwork(truth), models, max_refined=1,  # type: ignore[arg-type]
        strategies={NUT.obj_id: "rgbd+icp", WASHER.obj_id: "rgbd+icp"},
    )  # fmt: skip
    more = with_network.refine_more(with_network.run(frame).poses, frame)
    assert more is not None and len(more) == 2 and all(p.verified and p.method == "rgbd+icp" for p in more)
    with pytest.raises(ConfigError, match="strategies must name every model"):
        PerceptionPipeline(None, None, models, strategies={NUT.obj_id: "depth+icp"})  # type: ignore[arg-type]


def test_the_verification_verdicts_of_an_evaluation(scene):
    """A right pose on a partial mask is right; a pose of the wrong part or far off is wrong; unverified poses do
    not count."""
    from perception.evaluation import _verdicts, _verification_summary
    from sygrid.annotations import ImageAnnotation, InstanceAnnotation

    instances = tuple(
        InstanceAnnotation(m.obj_id, k, scene.poses[k], scene.masks[k], None, (-1,) * 4, (-1,) * 4, 1, 1, 1.0)
        for k, m in enumerate((NUT, WASHER, BRACKET, BOLT))
    )
    ann = ImageAnnotation(0, CAMERA, instances)
    partial = scene.masks[0].copy()
    partial[: np.nonzero(partial)[0].mean().astype(int)] = False  # the lower half of the nut's mask
    far = scene.poses[1].copy()
    far[:3, 3] += 0.01
    poses = [
        ObjectPose(detection(NUT, partial), scene.poses[0], 0.99, "depth+icp", verified=True),  # right
        ObjectPose(detection(WASHER, scene.masks[1]), far, 0.95, "depth+icp", verified=True),  # accepted, wrong
        ObjectPose(detection(BRACKET, scene.masks[2]), scene.poses[2], 0.5, "depth+icp", verified=False),  # refused
        ObjectPose(detection(NUT, scene.masks[3], obj_id=NUT.obj_id), scene.poses[0], 0.2, "rgb", verified=False),
        ObjectPose(detection(BOLT, scene.masks[3]), scene.poses[3], 0.9, "direct"),  # not verified
    ]
    models = {m.obj_id: m for m in (NUT, WASHER, BRACKET, BOLT)}
    verdicts = _verdicts(ann, poses, models)
    assert verdicts == [(True, True), (True, False), (False, True), (False, False)]
    assert _verification_summary(verdicts) == {"accepted": 2, "refused": 2, "false_accept": 0.5, "false_refuse": 0.5}


def test_pose_recall_matches_estimates_by_pose_error_whatever_their_masks(scene):
    """The BOP toolkit's rule: a right pose from a partial mask is a hit; a wrong pose on the full mask is a miss
    with its error; the higher-scored of two estimates of one instance takes it, and each estimate counts once."""
    from perception.evaluation import match_poses
    from sygrid.annotations import ImageAnnotation, InstanceAnnotation

    def instance(obj_id: int, k: int, visib: float = 1.0) -> InstanceAnnotation:
        ys, xs = np.nonzero(scene.masks[k])
        box = (int(xs.min()), int(ys.min()), int(np.ptp(xs)) + 1, int(np.ptp(ys)) + 1)
        n = len(xs)
        return InstanceAnnotation(obj_id, k, scene.poses[k], scene.masks[k], None, box, box, n, n, visib)

    instances = tuple(instance(m.obj_id, k) for k, m in enumerate((NUT, WASHER, BRACKET, BOLT)))
    hidden = replace(instance(NUT.obj_id, 0, 0.05), inst_id=9)
    ann = ImageAnnotation(0, CAMERA, (*instances, hidden))
    sliver = np.zeros_like(scene.masks[2])
    ys, xs = np.nonzero(scene.masks[2])
    sliver[ys[:5], xs[:5]] = True  # 5 pixels of the bracket: mask IoU far below 0.5
    far = scene.poses[1].copy()
    far[:3, 3] += 0.01
    nearly = scene.poses[0].copy()
    nearly[:3, 3] += 0.0005
    poses = [
        ObjectPose(detection(NUT, scene.masks[0]), nearly, 0.5, "depth+icp"),  # right, lower score
        ObjectPose(detection(NUT, scene.masks[0]), scene.poses[0], 0.9, "depth+icp"),  # right, higher score
        ObjectPose(detection(WASHER, scene.masks[1]), far, 0.95, "depth+icp"),  # the washer's mask, 10 mm off
        ObjectPose(detection(BRACKET, sliver), scene.poses[2], 0.8, "hybrid+search"),  # right, from a sliver
    ]
    models = {m.obj_id: m for m in (NUT, WASHER, BRACKET, BOLT)}
    matched = match_poses(ann, poses, models, min_visib=0.1, min_iou=0.5)
    assert [inst.inst_id for inst, _, _ in matched] == [0, 1, 2, 3]  # the 5 % visible nut is not evaluated
    (_, nut, e_nut), (_, washer, e_washer), (_, bracket, e_bracket), (_, bolt, e_bolt) = matched
    assert nut is poses[1] and e_nut.correct() and e_nut.add_m < 1e-9
    assert (
        washer is poses[2] and not e_washer.correct() and e_washer.te_m == pytest.approx(0.01 * math.sqrt(3))
    )  # a miss
    assert bracket is poses[3] and e_bracket.correct()  # the mask IoU rule would have left it unmatched
    assert bolt is None and not e_bolt.correct()
