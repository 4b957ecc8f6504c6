"""The depth tare on the bin's floor: a known stereo offset recovered from a synthetic floor with boxes on it, no
correction without a visible floor, no data kept as no data, and the evaluation giving the pipeline each image's
floor."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from perception.depth_tare import TareConfig, apply_tare, estimate_tare, floor_polygon, tared_depth
from sygrid.camera import CameraIntrinsics
from sygrid.transforms import make_T

K = CameraIntrinsics(fx=600.0, fy=600.0, cx=319.5, cy=239.5, width=640, height=480)
HALF = (0.15, 0.10)  # the floor's half sizes, metres


def _scene(
    offset_inv_m: float,
    noise_inv_m: float,
    seed: int = 0,
    quantum_inv_m: float = 0.0,
    tilt_deg: float = 20.0,
    boxes: int = 12,
    heights: tuple[float, float] = (0.01, 0.06),
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(observed depth, plane, bounds): a floor tilted ``tilt_deg`` at 0.8 m with ``boxes`` boxes ``heights`` tall
    on it (12 cover about a third of it), the walls' rim beyond it, seen with an inverse-depth offset and noise
    (rounded to ``quantum_inv_m``, as a stereo camera's subpixel disparity steps round it), and a few holes."""
    rng = np.random.default_rng(seed)
    c, s = np.cos(np.radians(tilt_deg)), np.sin(np.radians(tilt_deg))
    R = np.array([[1, 0, 0], [0, -c, s], [0, -s, -c]])  # bin z (up) towards the camera, tilted about x
    T_camera_bin = make_T(R, np.array([0.02, -0.01, 0.8]))
    normal = T_camera_bin[:3, 2]
    plane = np.append(normal, -normal @ T_camera_bin[:3, 3])
    u, v = np.meshgrid(np.arange(K.width), np.arange(K.height))
    rays = np.stack([(u - K.cx) / K.fx, (v - K.cy) / K.fy, np.ones(u.shape)], axis=-1)
    z = -plane[3] / (rays @ normal)  # the floor's depth at every pixel
    # points in the bin frame where each ray meets the floor: boxes where their footprint is, the rim outside the floor
    p_bin = (rays * z[..., None] - T_camera_bin[:3, 3]) @ R
    outside = (np.abs(p_bin[..., 0]) > HALF[0]) | (np.abs(p_bin[..., 1]) > HALF[1])
    height = np.where(outside, 0.12, 0.0)
    for _ in range(boxes):
        x, y = rng.uniform(-0.13, 0.13), rng.uniform(-0.08, 0.08)
        box = (np.abs(p_bin[..., 0] - x) < 0.02) & (np.abs(p_bin[..., 1] - y) < 0.015)
        height = np.where(box & ~outside, rng.uniform(*heights), height)
    # a surface ``height`` above the floor, parallel to it: its plane's d shrinks by the height
    z = -(plane[3] - height) / (rays @ normal)
    inv = 1.0 / z + offset_inv_m + noise_inv_m * rng.standard_normal(z.shape)
    if quantum_inv_m:
        inv = np.round(inv / quantum_inv_m) * quantum_inv_m
    depth = (1.0 / inv).astype(np.float32)
    depth[rng.random(depth.shape) < 0.02] = 0.0
    corners = np.array([(x, y, h) for x in (-HALF[0], HALF[0]) for y in (-HALF[1], HALF[1]) for h in (0.0, 0.12)])
    return depth, plane, corners @ R.T + T_camera_bin[:3, 3]


@pytest.mark.parametrize("offset", [-0.012, 0.0, 0.007])
def test_a_known_offset_is_recovered_under_noise(offset: float):
    depth, plane, bounds = _scene(offset, noise_inv_m=0.003)
    tare = estimate_tare(depth, K, plane, bounds)
    assert tare.applied and tare.reason == ""
    assert tare.offset_inv_m == pytest.approx(offset, abs=4e-4)  # 0.4 mm of depth at 1 m
    assert tare.offset_mm_at_1m == pytest.approx(-1e3 * tare.offset_inv_m)
    assert tare.gain == 1.0 and tare.floor_px > 15_000
    exact, _, _ = _scene(0.0, noise_inv_m=0.0)
    fixed = apply_tare(depth, tare)
    both = (fixed > 0) & (exact > 0)
    assert abs(np.median(fixed[both] - exact[both])) < 3e-4
    if offset:
        assert abs(np.median(depth[both] - exact[both])) > 3e-3


@pytest.mark.parametrize("offset", [-0.005, 0.0019, 0.007])
def test_a_quantised_floor_is_tared_to_its_mean_not_to_one_of_its_levels(offset: float):
    """The OAK-D model's disparity step (1/8 px: 3.8e-3 /m of inverse depth, 2.4 mm at 0.8 m) and about its noise,
    on a floor facing the camera (as a cell's camera looks down into its bin; a tilted floor dithers the levels by
    itself): told the step, the tare recovers the offset within a sixth of a step; not told, it sticks on a level
    (the lowest dense one) for some offsets."""
    from sygrid.sensor import sensor_preset

    oak = sensor_preset("oak-d")
    config = TareConfig().for_sensor(oak)
    quantum = oak.disparity_step_px / (oak.stereo_focal_px * oak.baseline_m)
    assert config.quantum_inv_m == pytest.approx(quantum) and TareConfig().quantum_inv_m == 0.0
    errors = []
    for seed in range(3):
        depth, plane, bounds = _scene(offset, noise_inv_m=0.003, seed=seed, quantum_inv_m=quantum, tilt_deg=0.0)
        tare = estimate_tare(depth, K, plane, bounds, config)
        assert tare.applied and tare.offset_inv_m == pytest.approx(offset, abs=quantum / 6)
        errors.append(abs(estimate_tare(depth, K, plane, bounds).offset_inv_m - offset))
    assert TareConfig().for_sensor(sensor_preset("ideal")).quantum_inv_m == 0.0
    if offset == 0.0019:  # half a step: the levels straddle the offset and the old estimate takes the lower one
        assert min(errors) > quantum / 3


def test_exact_depth_gives_no_offset_and_the_gain_stays_one_without_an_error():
    depth, plane, bounds = _scene(0.0, noise_inv_m=0.0)
    tare = estimate_tare(depth, K, plane, bounds, TareConfig(fit_gain=True, min_gain_span=0.01))
    assert tare.applied and abs(tare.offset_inv_m) < 1e-5 and tare.gain == pytest.approx(1.0, abs=1e-5)


def test_no_visible_floor_gives_no_correction():
    depth, plane, bounds = _scene(0.01, noise_inv_m=0.003)
    polygon = floor_polygon(plane, bounds, K)
    assert polygon is not None and len(polygon) == 4  # the rim corners project onto the floor's
    no_data = np.zeros_like(depth)
    tare = estimate_tare(no_data, K, plane, bounds)
    assert not tare.applied and "fewer than" in tare.reason and tare.offset_inv_m == 0.0
    assert apply_tare(depth, tare) is depth
    beside = bounds + np.array([5.0, 0.0, 0.0])  # the floor out of view
    assert not estimate_tare(depth, K, plane, beside).applied
    behind = bounds * np.array([1.0, 1.0, -1.0])
    assert not estimate_tare(depth, K, plane, behind).applied
    assert tared_depth(depth, K, None, bounds, TareConfig()) == (depth, None)
    assert tared_depth(depth, K, plane, bounds, None) == (depth, None)


def test_a_floor_the_parts_cover_is_not_taken_for_the_floor():
    """A bin so full that the lowest dense cluster is the boxes' tops at many heights: told the sensor's noise, the
    tare sees a spread no plane under that noise has and corrects nothing (taking the tops for the floor would push
    every depth centimetres too deep); the same noise on the usual bin is tared as before."""
    noise = 0.003
    config = TareConfig(noise_inv_m=noise)
    assert config.max_spread_inv_m == pytest.approx(1.5 * noise) and TareConfig().max_spread_inv_m == np.inf
    full, plane, bounds = _scene(0.004, noise_inv_m=noise, boxes=2000, heights=(0.015, 0.03))
    tare = estimate_tare(full, K, plane, bounds, config)
    assert not tare.applied and "spreads" in tare.reason and tare.offset_inv_m == 0.0
    assert estimate_tare(full, K, plane, bounds).offset_inv_m > 0.01  # not told the noise: the tops taken
    usual, plane, bounds = _scene(0.004, noise_inv_m=noise)
    assert estimate_tare(usual, K, plane, bounds, config).offset_inv_m == pytest.approx(0.004, abs=4e-4)


def test_no_data_stays_no_data():
    depth, plane, bounds = _scene(-0.01, noise_inv_m=0.003)
    fixed, tare = tared_depth(depth, K, plane, bounds, TareConfig())
    assert tare is not None and tare.applied and fixed.dtype == np.float32
    assert np.array_equal(fixed == 0, depth == 0) and (depth == 0).any()


def test_the_evaluation_gives_the_pipeline_each_images_floor(tiny_dataset: Path):
    from perception.evaluation import EvalSettings, bin_floor_camera, eval_items, evaluate
    from perception.pipeline import PerceptionResult
    from sygrid.dataset import DatasetBin
    from sygrid.drop import resolve_objects
    from sygrid.scene import parse_scene
    from sygrid.writers import load_bop_item
    from tests.conftest import TINY_SCENE

    class _Recorder:
        """What `evaluate` needs of a pipeline: it records the floor it was given with each frame."""

        pose_method, refiner, strategies = "direct", None, None
        floor_plane_camera = floor_bounds_camera_m = None

        def __init__(self) -> None:
            self.models = {m.obj_id: m for m in resolve_objects(parse_scene(TINY_SCENE, "tiny"), Path("."))}
            self.detector = SimpleNamespace(conf_threshold=0.5)
            self.seen, self.sensors = [], []

        def use_sensor(self, sensor) -> None:
            self.sensors.append(sensor.name)

        def run(self, frame) -> PerceptionResult:
            self.seen.append((frame, self.floor_plane_camera, self.floor_bounds_camera_m))
            return PerceptionResult([], [], {"total": 1.0})

    recorder = _Recorder()
    evaluate(recorder, tiny_dataset, EvalSettings(max_images=2), progress=False)  # type: ignore[arg-type]
    root, split, items = eval_items(tiny_dataset, EvalSettings(max_images=2))
    assert len(recorder.seen) == 2 and recorder.sensors == ["ideal"]
    for (scene_id, image_id), (frame, plane, bounds) in zip(items, recorder.seen, strict=True):
        ann, _, _ = load_bop_item(root, scene_id, image_id, split=split)
        expected_plane, expected_bounds = bin_floor_camera(DatasetBin(tiny_dataset), ann)
        assert np.allclose(plane, expected_plane) and np.allclose(bounds, expected_bounds)
        tare = estimate_tare(frame.depth_m, frame.intrinsics, plane, bounds, TareConfig(min_floor_px=200))
        assert tare.applied and abs(tare.offset_inv_m) < 1e-3  # exact depth lies on the plane given
    without = _Recorder()
    evaluate(without, tiny_dataset, EvalSettings(max_images=1, floor=False), progress=False)  # type: ignore[arg-type]
    assert without.seen[0][1] is None and without.seen[0][2] is None


def test_the_verification_allows_the_sensors_depth_noise_unless_set_higher():
    from perception.pipeline import PerceptionPipeline
    from perception.verify import VerifyConfig
    from sygrid.sensor import IDEAL, sensor_preset

    oak = sensor_preset("oak-d")
    assert oak.depth_noise_sigma_m(1.0) > 0
    assert VerifyConfig().for_sensor(oak).depth_noise_m == pytest.approx(oak.depth_noise_sigma_m(1.0))
    assert VerifyConfig(depth_noise_m=0.01).for_sensor(oak).depth_noise_m == 0.01
    assert VerifyConfig().for_sensor(IDEAL) == VerifyConfig()
    pipeline = PerceptionPipeline(None, None, {1: None}, strategies={1: "depth"})  # type: ignore[arg-type]
    pipeline.use_sensor(oak)
    assert pipeline.runner.verifier.config.depth_noise_m == pytest.approx(oak.depth_noise_sigma_m(1.0))
    pipeline.use_sensor(IDEAL)  # from the pipeline's own settings, not the previous sensor's
    assert pipeline.runner.verifier.config.depth_noise_m == 0.0


def test_a_level_quantised_floor_is_tared_wherever_its_offset_falls_between_two_steps():
    """A floor facing the camera, under the OAK-D model's steps and noise, sits on a few levels one step apart; where
    its offset falls between two of them decides how its pixels split, and the spread check must not read a level's
    step as parts covering the floor (the simulated cell stopped with parts in its bin, every depth a centimetre
    off, when it did)."""
    from sygrid.sensor import sensor_preset

    config = TareConfig().for_sensor(sensor_preset("oak-d"))
    quantum, noise = config.quantum_inv_m, config.noise_inv_m
    for i, offset in enumerate(np.linspace(-quantum, quantum, 9)):
        depth, plane, bounds = _scene(offset, noise_inv_m=noise, seed=i, quantum_inv_m=quantum, tilt_deg=0.0)
        tare = estimate_tare(depth, K, plane, bounds, config)
        assert tare.applied, (offset, tare.reason)
        assert tare.offset_inv_m == pytest.approx(offset, abs=quantum / 6)
