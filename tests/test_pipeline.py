"""The perception pipeline from a model folder, and `sygrid eval`, with smoke-trained models of the tiny dataset."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from launch.cli import build_parser
from perception.camera import Frame
from perception.evaluation import EvalSettings, bop_items, evaluate, format_table
from perception.pipeline import PerceptionPipeline, PipelineOverrides
from perception.refine import RefineConfig
from sygrid.errors import ConfigError
from sygrid.writers import load_bop_item

ROOT = Path(__file__).resolve().parents[1]

pytestmark = [pytest.mark.slow, pytest.mark.filterwarnings("ignore:__array__ implementation:DeprecationWarning")]

MANIFEST = {
    "format": "sygrid-models/1",
    "objects": [{"builtin": "hex_nut"}, {"builtin": "washer"}, {"builtin": "l_bracket"}],
    "detector": {"onnx": "detector.onnx", "conf_threshold": 0.01},
    "pose": {"onnx": "pose.onnx", "method": "direct"},
    "refine": {"enabled": True},
}


@pytest.fixture(scope="module")
def runs(tiny_dataset: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A detector run (``det``) and a pose run (``pose``) trained for a few iterations (untrained in effect: the
    tests check the plumbing and the error handling, not accuracy)."""
    pytest.importorskip("torch")
    from sygrid.train.detector.config import TrainConfig as DetectorConfig
    from sygrid.train.detector.trainer import train as train_detector
    from sygrid.train.pose.train import TrainConfig as PoseConfig
    from sygrid.train.pose.train import train as train_pose

    out = tmp_path_factory.mktemp("runs")
    train_detector(
        DetectorConfig(data=str(tiny_dataset), out=str(out / "det"), imgsz=128, batch=2, size="p", seed=0,
                       threads=1, epochs=1, max_iters=1, progress=False)
    )  # fmt: skip
    train_pose(
        PoseConfig(data_dir=tiny_dataset, out_dir=out / "pose", epochs=1, batch_size=4, input_size=32,
                   output_stride=4, width=8, num_regions=8, max_iters=1, threads=1, progress=False, val_max=4)
    )  # fmt: skip
    return out


def _pack(detector: Path, pose: Path, out: Path, tiny_dataset: Path) -> None:
    pack = build_parser("models").parse_args(
        ["models", "pack", "--detector", str(detector), "--pose", str(pose), "--out", str(out),
         "--conf-threshold", "0.01", "--test-data", str(tiny_dataset), "--max-images", "2"]
    )  # fmt: skip
    assert pack._run(pack) == 0


@pytest.fixture(scope="module")
def model_dir(runs: Path, tiny_dataset: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A model folder packed from ``runs``."""
    folder = tmp_path_factory.mktemp("models") / "tiny"
    _pack(runs / "det", runs / "pose", folder, tiny_dataset)
    return folder


def test_pack_writes_the_manifest_and_model_cards_from_the_runs(model_dir: Path, tiny_dataset: Path):
    manifest = json.loads((model_dir / "manifest.json").read_text())
    assert manifest == {**MANIFEST, "detector": {"onnx": "detector.onnx", "conf_threshold": 0.01}}
    card = (model_dir / "detector.card.md").read_text()
    assert "--imgsz 128 --batch 2 --width p" in card and "3 classes: hex_nut, washer, l_bracket" in card
    assert "recipe `tiny` (sha256" in card and "seed 7, 8 items (0 failed)" in card  # the dataset's ledger
    pose_card = (model_dir / "pose.card.md").read_text()
    assert "--input-size 32 --output-stride 4 --width 8" in pose_card and "| all | " in pose_card
    for label in ("direct", "refined"):
        report = json.loads((model_dir / f"eval_{label}.json").read_text())
        assert report["n_images"] == 2 and report["refine"] == (label == "refined")
        assert report["conf_threshold"] == 0.01
    detector = json.loads((model_dir / "eval_detector.json").read_text())
    assert detector["conf_threshold"] == 0.001 and detector["n_images"] == 2 and "box_map50" in detector
    assert "confidence threshold 0.001" in card and "operating threshold 0.01" in card


def test_pack_keeps_a_model_folders_pose_network_and_its_choices(
    runs: Path, model_dir: Path, tiny_dataset: Path, tmp_path: Path
):
    """A new detector beside a shipped pose network: --pose names the model folder (here the output folder itself);
    the pose entry (strategies), verification and the card's training and strategy sections stay, the held-out
    evaluation is measured again."""
    folder = tmp_path / "tiny"
    shutil.copytree(model_dir, folder)
    manifest = json.loads((folder / "manifest.json").read_text())
    manifest["pose"]["strategies"] = {"hex_nut": "depth+icp", "washer": "depth+icp", "l_bracket": "depth+search"}
    manifest["verify"] = {"min_confidence": 0.8}
    (folder / "manifest.json").write_text(json.dumps(manifest))
    card = (folder / "pose.card.md").read_text().replace("| all | ", "| all (old) | ")
    (folder / "pose.card.md").write_text(card + "\n### Pose strategies per part\n\nthe chosen table\n")
    pose_bytes = (folder / "pose.onnx").read_bytes()
    _pack(runs / "det", folder, folder, tiny_dataset)
    kept = json.loads((folder / "manifest.json").read_text())
    assert kept["pose"] == {"onnx": "pose.onnx", "method": "direct", "strategies": manifest["pose"]["strategies"]}
    assert kept["verify"] == {"min_confidence": 0.8} and (folder / "pose.onnx").read_bytes() == pose_bytes
    new_card = (folder / "pose.card.md").read_text()
    assert "--input-size 32 --output-stride 4 --width 8" in new_card  # the training lines
    assert "| all (old) | " not in new_card and "| all | " in new_card  # the evaluation measured again
    assert new_card.rstrip().endswith("### Pose strategies per part\n\nthe chosen table")
    assert new_card.count("## Held-out test set: ") == 1 and "| ADD(-S) strategies |" in new_card
    assert (folder / "eval_strategies.json").is_file() and not (folder / "eval_refined.json").exists()


def test_pack_keeps_a_model_folders_detector_for_another_folder(model_dir: Path, tiny_dataset: Path, tmp_path: Path):
    """--detector names a model folder: its network and its card's training lines go into the new folder beside
    another pose network, and the held-out evaluation is measured on the new test data; a folder without the
    detector's card is refused by name."""
    source = tmp_path / "source"
    shutil.copytree(model_dir, source)
    card = (source / "detector.card.md").read_text()
    (source / "detector.card.md").write_text(card.replace("| obj_id |", "| obj_id (old) |") + "\n## Transfer\n\nx\n")
    out = tmp_path / "cell"
    _pack(source, model_dir, out, tiny_dataset)
    assert (out / "detector.onnx").read_bytes() == (source / "detector.onnx").read_bytes()
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["objects"] == MANIFEST["objects"] and manifest["detector"]["conf_threshold"] == 0.01
    new_card = (out / "detector.card.md").read_text()
    assert "--imgsz 128 --batch 2 --width p" in new_card and f"packed from the model folder `{source}`" in new_card
    assert "| obj_id (old) |" not in new_card and "| obj_id |" in new_card and "## Transfer" not in new_card
    assert new_card.count("## Held-out test set: ") == 1
    _pack(out, out, out, tiny_dataset)  # packed again from itself: one line names where the network came from
    assert (out / "detector.card.md").read_text().count("packed from the model folder") == 1
    (source / "detector.card.md").unlink()
    with pytest.raises(ConfigError, match=r"without detector\.card\.md"):
        _pack(source, model_dir, tmp_path / "other", tiny_dataset)


def test_pipeline_turns_a_frame_into_poses(model_dir: Path, tiny_dataset: Path):
    pipeline = PerceptionPipeline.from_folder(model_dir)
    assert sorted(pipeline.models) == [1, 3, 4] and pipeline.refiner is not None
    assert pipeline.refiner.config.min_fitness == RefineConfig().min_fitness
    strict = PerceptionPipeline.from_folder(model_dir, PipelineOverrides(min_fitness=0.8, mask_erosion_px=0))
    assert strict.refiner is not None and strict.refiner.config.min_fitness == 0.8
    assert strict.refiner.config.mask_erosion_px == 0 and pipeline.refiner.config.mask_erosion_px == 1
    scene_id, image_id = bop_items(tiny_dataset / "bop", "val_pbr")[0]
    ann, rgb, depth = load_bop_item(tiny_dataset / "bop", scene_id, image_id, split="val_pbr")
    result = pipeline.run(Frame(rgb, depth, ann.intrinsics, timestamp_s=0.0))
    assert set(result.timings_ms) == {"detect", "pose", "refine", "total"}
    assert [p.score for p in result.poses] == sorted((p.score for p in result.poses), reverse=True)
    for pose in result.poses:
        assert pose.T_camera_object.shape == (4, 4) and np.all(np.isfinite(pose.T_camera_object))
        assert pose.obj_id in (1, 3, 4)
    empty = Frame(np.zeros_like(rgb), np.zeros_like(depth), ann.intrinsics, timestamp_s=0.0)
    assert isinstance(pipeline.run(empty).poses, list)


def test_eval_reports_detection_and_pose_metrics(model_dir: Path, tiny_dataset: Path):
    pipeline = PerceptionPipeline.from_folder(model_dir, PipelineOverrides(pose_method="pnp", refine=False))
    report = evaluate(pipeline, tiny_dataset, EvalSettings(max_images=2), progress=False)
    assert report["split"] == "val_pbr" and report["n_images"] == 2 and report["pose_method"] == "pnp"
    assert 0.0 <= report["detection"]["box_map50"] <= 1.0 or np.isnan(report["detection"]["box_map50"])
    assert report["pose"]["all"]["n"] >= 1  # every visible instance is counted, found or missed
    assert 0.0 <= report["pose"]["all"]["add_recall"] <= 1.0
    assert "ADD(-S)<0.1d" in format_table(report)
    assert report["rescue"] is None  # asked for only with EvalSettings.rescue
    # without pose strategies there is no verification, so nothing is rescued; the figures are reported all the same
    rescued = evaluate(pipeline, tiny_dataset, EvalSettings(max_images=1, rescue=True), progress=False)["rescue"]
    assert rescued["accepted"] == rescued["correct"] == 0 and rescued["ms_median"] >= 0.0


def test_bad_model_folders_name_the_file_and_field(model_dir: Path, tmp_path: Path):
    with pytest.raises(ConfigError, match=r"not a model folder \(no manifest.json\)"):
        PerceptionPipeline.from_folder(tmp_path)
    broken = tmp_path / "broken"
    shutil.copytree(model_dir, broken)
    (broken / "pose.onnx").unlink()
    with pytest.raises(ConfigError, match=r"manifest.json: pose.onnx: no file .*pose.onnx"):
        PerceptionPipeline.from_folder(broken)
    (broken / "manifest.json").write_text(
        json.dumps({**MANIFEST, "detector": {"onnx": "detector.onnx", "conf_threshold": 2}})
    )
    with pytest.raises(ConfigError, match=r"manifest.json: detector.conf_threshold: must be < 1"):
        PerceptionPipeline.from_folder(broken)
    with pytest.raises(ConfigError, match=r"no bop/ folder"):
        evaluate(PerceptionPipeline.from_folder(model_dir), tmp_path, progress=False)


class _RecordingRefiner:
    """Refines by marking the pose (refuses obj_id 4), recording the order it was asked in."""

    def __init__(self) -> None:
        self.order: list[float] = []

    def refine(self, pose, depth_m, intrinsics, model):
        from perception.results import ObjectPose

        self.order.append(float(pose.T_camera_object[2, 3]))
        status = "kept_initial" if pose.obj_id == 4 else "refined"
        return ObjectPose(pose.detection, pose.T_camera_object, pose.score, pose.method, {"icp": {"status": status}})


def test_max_refined_refines_the_nearest_parts_until_enough_are_refined():
    from perception.results import Detection, ObjectPose
    from robot.grasp_planner import _refined
    from sygrid.camera import CameraIntrinsics

    depth = np.zeros((40, 60), np.float32)
    poses = []
    for k, (obj_id, z) in enumerate([(1, 0.90), (4, 0.80), (1, 0.85), (1, 0.95), (1, 0.70)]):
        mask = np.zeros_like(depth, dtype=bool)
        mask[5:15, 10 * k : 10 * k + 8] = True
        depth[mask] = z  # the pose's own z is ignored where the mask has depth
        T = np.eye(4)
        T[2, 3] = 2.0 - z
        poses.append(ObjectPose(Detection(0, obj_id, 0.9, np.array([0.0, 0, 1, 1]), mask), T, 0.9, "direct"))
    refiner = _RecordingRefiner()
    pipeline = PerceptionPipeline(None, None, {1: None, 4: None}, refiner, max_refined=2)  # type: ignore[arg-type]
    frame = Frame(np.zeros((40, 60, 3), np.uint8), depth, CameraIntrinsics(100, 100, 30, 20, 60, 40), 0.0)
    out = pipeline._refine(poses, frame)
    # nearest first (0.70, 0.80 refused, 0.85): two refined, then the rest skipped
    assert refiner.order == pytest.approx([2.0 - 0.70, 2.0 - 0.80, 2.0 - 0.85])
    statuses = [p.details["icp"]["status"] for p in out]
    assert statuses == ["refined", "kept_initial", "refined", "skipped", "skipped"]
    assert [_refined(p) for p in out] == [True, False, True, False, False]  # the planner picks none of the others
    more = pipeline.refine_more(out, frame)  # the next two skipped ones, nearest first; the others stay as they were
    assert refiner.order[3:] == pytest.approx([2.0 - 0.90, 2.0 - 0.95])
    assert sorted(p.details["icp"]["status"] for p in more) == ["kept_initial"] + ["refined"] * 4
    assert pipeline.refine_more(more, frame) is None
    with pytest.raises(ConfigError, match="max_refined must be >= 1"):
        PerceptionPipeline(None, None, {}, refiner, max_refined=0)  # type: ignore[arg-type]


def test_region_of_interest_is_the_box_of_the_projected_points():
    from perception.pipeline import region_of_interest
    from sygrid.camera import CameraIntrinsics

    K = CameraIntrinsics(100.0, 100.0, 50.0, 40.0, 100, 80)
    points = np.array([[-0.1, -0.1, 1.0], [0.1, 0.05, 1.0], [0.0, 0.0, 0.5]])  # u 40..60, v 30..45
    assert region_of_interest(points, K, margin_px=2) == (38, 28, 62, 47)
    assert region_of_interest(points * [5.0, 8.0, 1.0], K, margin_px=2) == (0, 0, 100, 80)  # clipped to the image
    assert region_of_interest(points + np.array([2.0, 0.0, 0.0]), K) is None  # all of it right of the image


def test_the_bin_box_finds_what_the_whole_frame_finds():
    """The shipped detector on the simulated cell's first frame (seed 0): looking only at the bin's box at the same
    scale finds the same parts as the whole frame finds in that box, in the same places, with about the same scores
    (the network sees a different neighbourhood around the crop, so a score may move; the median one does not)."""
    from launch.bench_cell_detector import first_frame
    from perception.detector import YoloSegDetector
    from robot.cell_setup import load_cell_setup

    bin_ = load_cell_setup(ROOT / "launch" / "cells" / "sim.toml").planner_config().bin
    rgb, roi, _ = first_frame(ROOT / "launch" / "scenes" / "pick_bin_10_grippable.json", 0, bin_)
    x0, y0, x1, y1 = roi
    assert 0 < x0 < x1 < rgb.shape[1] and 0 < y0 < y1 < rgb.shape[0]
    assert (x1 - x0) * (y1 - y0) < 0.2 * rgb.shape[0] * rgb.shape[1]  # the bin is a small part of the frame
    detector = YoloSegDetector(ROOT / "models" / "builtin" / "detector.onnx", conf_threshold=0.4, input_size=800)
    whole, in_bin = detector.detect(rgb), detector.detect(rgb, roi)
    # what the whole frame finds beyond the bin's box (the tray, the arm) the box cannot see
    centres = [((d.bbox_xyxy[0] + d.bbox_xyxy[2]) / 2, (d.bbox_xyxy[1] + d.bbox_xyxy[3]) / 2) for d in whole]
    inside = [d for d, (u, v) in zip(whole, centres, strict=True) if x0 <= u <= x1 and y0 <= v <= y1]
    assert len(inside) >= len(whole) - 2
    whole = inside
    assert len(in_bin) >= 6 and abs(len(in_bin) - len(whole)) <= 1
    score_changes = []
    for d in whole:
        twins = [b for b in in_bin if b.obj_id == d.obj_id and np.abs(b.bbox_xyxy - d.bbox_xyxy).max() < 3.0]
        if twins:
            score_changes.append(abs(twins[0].score - d.score))
    assert len(score_changes) >= len(whole) - 1
    assert np.median(score_changes) < 0.1, score_changes
    for d in in_bin:
        ys, xs = np.nonzero(d.mask)
        assert xs.min() >= x0 and xs.max() < x1 and ys.min() >= y0 and ys.max() < y1


@pytest.mark.parametrize("cell_file", sorted((ROOT / "launch" / "cells").glob("*.toml")), ids=lambda p: p.stem)
def test_every_shipped_cell_runs_a_verified_pose_strategy_per_part(cell_file):
    """A cell file's model folder with its [perception] overrides keeps the per-part pose strategies and their
    verification (an override of the pose method or of the refinement would switch them off, and the cell would
    pick on unverified network poses)."""
    from launch.pick import cell_overrides
    from perception.manifest import MANIFEST_NAME
    from robot.cell_setup import load_cell_setup

    setup = load_cell_setup(cell_file)
    models_dir = setup.resolve(setup.data.perception.models_dir)
    pipeline = PerceptionPipeline.from_folder(models_dir, cell_overrides(setup))
    assert pipeline.strategies is not None and set(pipeline.strategies) == set(pipeline.models)
    # the verification threshold chosen with the strategies (sygrid models choose-pose), not the default
    assert "min_confidence" in json.loads((models_dir / MANIFEST_NAME).read_text()).get("verify", {})


def test_a_region_outside_the_image_is_a_configuration_error():
    from sygrid.camera import CameraIntrinsics

    K = CameraIntrinsics(100.0, 100.0, 30.0, 20.0, 60, 40)
    behind_the_image = np.array([[5.0, 0.0, 1.0], [6.0, 1.0, 1.0]])
    pipeline = PerceptionPipeline(None, None, {}, None, region_camera_m=behind_the_image)  # type: ignore[arg-type]
    frame = Frame(np.zeros((40, 60, 3), np.uint8), np.zeros((40, 60), np.float32), K, 0.0)
    with pytest.raises(ConfigError, match=r"region of interest .* lies outside the 60x40 image; check the camera"):
        pipeline.run(frame)
    with pytest.raises(ConfigError, match="in front of the camera"):
        PerceptionPipeline(None, None, {}, None, region_camera_m=-behind_the_image)  # type: ignore[arg-type]


def test_without_floor_drops_the_pixels_on_a_tilted_floor_and_keeps_what_lies_on_it():
    from perception.pipeline import without_floor
    from robot.grasp_scene import BinGeometry
    from sygrid.camera import CameraIntrinsics, unproject_depth
    from sygrid.transforms import make_T, rotation_about

    camera = CameraIntrinsics.from_fov(80, 60, 50.0)
    # the camera 0.6 m above the floor, looking down, tilted 20 deg; the floor is the bin's (base frame z = 0.02)
    bin_ = BinGeometry(T_base_bin=make_T(t=(-0.5, 0.0, 0.02)))
    R_base_camera = rotation_about(np.array([1.0, 0.0, 0.0]), np.radians(180 - 20))
    T_base_camera = make_T(R_base_camera, (-0.5, 0.1, 0.62))
    plane = bin_.floor_plane_camera(T_base_camera)
    assert np.linalg.norm(plane[:3]) == pytest.approx(1.0)
    # ray-plane depth of the floor for every pixel, then a 10 mm block on it in the middle of the image
    rays = unproject_depth(camera.K, np.ones((camera.height, camera.width)))
    floor_depth = -plane[3] / (rays @ plane[:3])
    block = np.zeros(floor_depth.shape, bool)
    block[25:35, 35:45] = True
    depth = np.where(block, floor_depth + 0.010 / (rays @ plane[:3]), floor_depth).astype(np.float32)
    height = unproject_depth(camera.K, depth.astype(float)) @ plane[:3] + plane[3]
    assert np.allclose(height[~block], 0.0, atol=1e-6) and np.allclose(height[block], 0.010, atol=1e-6)
    depth[0, 0] = 0.0  # no data stays no data
    before = depth.copy()
    out = without_floor(depth, camera, plane, 0.0015)
    assert out.dtype == np.float32 and np.array_equal(depth, before)  # a copy, the frame is untouched
    assert np.all(out[~block] == 0) and np.array_equal(out[block], depth[block])
    with pytest.raises(ConfigError, match="floor_plane_camera must be"):
        PerceptionPipeline(None, None, {}, None, floor_plane_camera=np.array([0.0, 0, 2, 1]))  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="floor_margin_m must be"):
        PerceptionPipeline(None, None, {}, None, floor_margin_m=-0.001)  # type: ignore[arg-type]
