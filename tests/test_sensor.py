"""The stereo RGB-D sensor model (sygrid.sensor): its statistics against its parameters (seeded), the presets, the
depth metrics of a sensed frame, and where it is wired in (recipes, `sygrid eval --sensor`, the cell's cameras)."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from sygrid.camera import CameraIntrinsics
from sygrid.errors import ConfigError
from sygrid.metrics import depth_metrics, mean_depth_metrics
from sygrid.scene import METALS
from sygrid.sensor import (
    IDEAL,
    SENSOR_PRESETS,
    SensorModel,
    occlusion_shadow,
    sensor_preset,
    sensor_rng,
)

ROOT = Path(__file__).resolve().parents[1]
K = CameraIntrinsics.from_fov(200, 200, 45.0)  # fx = 241.4 px
OAK = SENSOR_PRESETS["oak-d"]
D435 = SENSOR_PRESETS["d435"]
QUIET = {  # every effect off but the stereo geometry (the working range stays)
    "disparity_step_px": 0.0, "disparity_noise_px": 0.0, "disparity_bias_px": 0.0, "noise_corr_px": 0.0,
    "second_camera_side": 0, "edge_dropout": 0.0, "flying_pixel_fraction": 0.0, "dark_dropout": 0.0,
    "saturation_threshold": 1.0, "specular_dropout": 0.0, "hole_fraction": 0.0, "exposure_sigma": 0.0,
    "white_balance_sigma": 0.0, "shot_noise_dn": 0.0, "read_noise_dn": 0.0,
}  # fmt: skip


def _quiet(model: SensorModel, **on: float) -> SensorModel:
    return replace(model, **{**QUIET, **on})


def _plane(z: float, size: int = 200) -> np.ndarray:
    return np.full((size, size), z, dtype=np.float32)


# ------------------------------------------------------------------------------------------------------ presets
def test_presets_carry_the_sensors_geometry():
    assert sorted(SENSOR_PRESETS) == ["d435", "d435i", "ideal", "oak-d", "oak-d-800p", "oak-d-pro"]
    assert SENSOR_PRESETS["ideal"].is_ideal and not any(m.is_ideal for n, m in SENSOR_PRESETS.items() if n != "ideal")
    assert (OAK.baseline_m, OAK.stereo_size_px, OAK.disparity_step_px) == (0.075, (640, 400), 1 / 8)
    assert (D435.baseline_m, D435.stereo_size_px, D435.disparity_step_px) == (0.050, (848, 480), 1 / 32)
    assert OAK.stereo_focal_px == pytest.approx(320 / math.tan(math.radians(72 / 2)), rel=0.01)  # 72 deg HFOV
    assert D435.stereo_focal_px == pytest.approx(424 / math.tan(math.radians(87 / 2)), rel=0.001)  # 87 deg HFOV
    assert OAK.min_depth_m == pytest.approx(0.35, abs=0.01) and D435.min_depth_m == pytest.approx(0.18, abs=0.01)
    assert replace(SENSOR_PRESETS["d435i"], name="d435") == D435  # the D435i is a D435 with an IMU
    pro = SENSOR_PRESETS["oak-d-pro"]
    assert replace(pro, name="oak-d", dark_dropout=OAK.dark_dropout, specular_dropout=OAK.specular_dropout) == OAK
    assert pro.dark_dropout < OAK.dark_dropout  # the IR projector gives dark surfaces texture
    # The per-frame offset sits at the stated accuracy as a mean absolute error (Gaussian: sqrt(2 / pi) sigma):
    # D435 2 % at 2 m; OAK-D 2 % at 4 m (Luxonis' 800P figure: an angular calibration error, the same relative
    # error at 400P), so 1 % at 2 m.
    mean_abs = math.sqrt(2 / math.pi)
    assert mean_abs * D435.depth_bias_sigma_m(2.0) / 2.0 == pytest.approx(0.02, rel=0.02)
    assert mean_abs * OAK.depth_bias_sigma_m(4.0) / 4.0 == pytest.approx(0.02, rel=0.02)


def test_a_finer_stereo_resolution_halves_the_per_pixel_noise_not_the_offset():
    oak800 = SENSOR_PRESETS["oak-d-800p"]
    assert oak800 == OAK.at_stereo_size(1280, 800, "oak-d-800p")
    # Luxonis: 882.5 px at 800P, twice 400P's; the RVC2's 95 px search then reaches 0.71 m at the nearest
    assert oak800.stereo_focal_px == pytest.approx(882.5) and oak800.min_depth_m == pytest.approx(0.70, abs=0.01)
    for z in (0.5, 1.0, 2.0):
        assert oak800.depth_noise_sigma_m(z) == pytest.approx(OAK.depth_noise_sigma_m(z) / 2)
        assert oak800.depth_bias_sigma_m(z) == pytest.approx(OAK.depth_bias_sigma_m(z))  # an angular error
    assert OAK.at_stereo_size(640, 400) == replace(OAK, name="oak-d@400p")
    assert D435.at_stereo_size(1280, 720).name == "d435@720p"
    # measured on sensed frames: the per-pixel spread of a flat wall at 1 m halves
    wall, camera = _plane(1.0, 400), CameraIntrinsics.from_fov(400, 400, 60.0)
    spreads = []
    for model in (OAK, oak800):
        quiet = replace(model, disparity_bias_px=0.0, edge_dropout=0.0, flying_pixel_fraction=0.0, hole_fraction=0.0)
        z = quiet.sense_depth(wall, camera, np.random.default_rng(0))
        spreads.append(float(np.std(z[z > 0])))
    assert spreads[1] == pytest.approx(spreads[0] / 2, rel=0.15)
    with pytest.raises(ConfigError, match="has no stereo pair"):
        SENSOR_PRESETS["ideal"].at_stereo_size(1280, 800)
    with pytest.raises(ConfigError, match="need a positive width and height"):
        OAK.at_stereo_size(0, 800)


def test_bad_parameters_and_names_are_refused():
    with pytest.raises(ConfigError, match=r"unknown sensor 'kinect'; valid: \['d435', 'd435i', 'ideal'"):
        sensor_preset("kinect")
    with pytest.raises(ConfigError, match="disparity_noise_px must be finite and >= 0"):
        replace(OAK, disparity_noise_px=-0.1)
    with pytest.raises(ConfigError, match=r"dark_dropout must be in \[0, 1\]"):
        replace(OAK, dark_dropout=1.5)
    with pytest.raises(ConfigError, match="needs stereo_focal_px > 0"):
        SensorModel(name="x", baseline_m=0.05)
    with pytest.raises(ConfigError, match="second_camera_side"):
        replace(OAK, second_camera_side=2)


# ------------------------------------------------------------------------------------------- depth statistics
@pytest.mark.parametrize("z", [0.5, 1.0, 2.0])
def test_depth_noise_follows_z_squared(z: float):
    white = _quiet(OAK, disparity_noise_px=0.1)
    err = white.sense_depth(_plane(z), K, np.random.default_rng(1)) - z
    assert err.std() == pytest.approx(white.depth_noise_sigma_m(z), rel=0.05)
    assert white.depth_noise_sigma_m(z) == pytest.approx(z**2 * 0.1 / (441.25 * 0.075))
    correlated = _quiet(OAK, disparity_noise_px=0.1, noise_corr_px=2.0)  # smoothing keeps the variance
    err = correlated.sense_depth(_plane(z), K, np.random.default_rng(2)) - z
    assert err.std() == pytest.approx(correlated.depth_noise_sigma_m(z), rel=0.12)
    neighbours = np.corrcoef(err[:, :-1].ravel(), err[:, 1:].ravel())[0, 1]
    assert neighbours > 0.8  # 2 stereo px = 1.1 image px of correlation length here
    stepped = _quiet(D435, disparity_noise_px=0.1, disparity_step_px=1 / 32)
    err = stepped.sense_depth(_plane(z), K, np.random.default_rng(3)) - z
    assert err.std() == pytest.approx(stepped.depth_noise_sigma_m(z), rel=0.05)


def test_per_frame_offset_matches_its_sigma():
    biased = _quiet(D435, disparity_bias_px=D435.disparity_bias_px)
    z = 1.0
    offsets = [float(biased.sense_depth(_plane(z, 8), K, np.random.default_rng(s)).mean() - z) for s in range(400)]
    assert np.std(offsets) == pytest.approx(biased.depth_bias_sigma_m(z), rel=0.1)
    frame = biased.sense_depth(_plane(z, 8), K, np.random.default_rng(0))
    assert np.ptp(frame) < 1e-6  # one offset for the whole frame


def test_depth_is_quantised_to_the_subpixel_step_and_bounded_by_the_working_range():
    z = np.linspace(0.5, 2.0, 200 * 200, dtype=np.float32).reshape(200, 200)
    out = _quiet(OAK, disparity_step_px=1 / 8).sense_depth(z, K, np.random.default_rng(0))
    steps = OAK.focal_baseline_px_m / out[out > 0] / (1 / 8)
    np.testing.assert_allclose(steps, np.round(steps), atol=1e-3)
    assert np.abs(out - z).max() <= z.max() ** 2 / OAK.focal_baseline_px_m * (1 / 16) * 1.01  # half a step
    ranged = _quiet(OAK)
    assert (ranged.sense_depth(_plane(0.3), K, np.random.default_rng(0)) == 0).all()  # nearer than 0.348 m
    assert (ranged.sense_depth(_plane(0.4), K, np.random.default_rng(0)) > 0).all()
    assert (ranged.sense_depth(_plane(12.0), K, np.random.default_rng(0)) == 0).all()  # beyond 10 m


def test_dropouts_where_expected():
    depth, rgb = _plane(0.8), np.full((200, 200, 3), 128, np.uint8)
    rgb[:, :100] = 0  # dark left half
    rgb[:20, 100:] = 255  # a saturated band
    out = _quiet(OAK, dark_threshold=0.06, dark_dropout=0.9, saturation_threshold=0.98).sense_depth(
        depth, K, np.random.default_rng(0), image=rgb
    )
    assert (out[:, :100] == 0).mean() == pytest.approx(0.9, abs=0.1)
    assert (out[:20, 100:] == 0).all() and (out[20:, 100:] > 0).all()
    metal = np.zeros((200, 200), bool)
    metal[50:150, 50:150] = True
    out = _quiet(OAK, specular_dropout=0.15).sense_depth(depth, K, np.random.default_rng(0), metal_mask=metal)
    assert (out[metal] == 0).mean() == pytest.approx(0.15, abs=0.07) and (out[~metal] > 0).all()
    holes = _quiet(OAK, hole_fraction=0.002, hole_radius_px=2).sense_depth(depth, K, np.random.default_rng(0))
    assert 0.01 < (holes == 0).mean() < 0.05  # 13-pixel diamonds around 0.2 % of the pixels


def test_occlusion_shadow_lies_beside_foreground_edges_away_from_the_second_camera():
    depth = _plane(0.8)
    depth[80:120, 80:120] = 0.6
    width = K.fx * D435.baseline_m * (1 / 0.6 - 1 / 0.8)  # the disparity difference, image pixels: 5.0
    out = _quiet(D435, second_camera_side=1).sense_depth(depth, K, np.random.default_rng(0))
    holes = np.flatnonzero(out[100] == 0)
    assert holes.min() == 80 - math.floor(width) and holes.max() == 79  # left of the box (second camera at +x)
    assert (out[:80] > 0).all() and (out[120:] > 0).all()
    mirrored = occlusion_shadow(depth, K.fx * D435.baseline_m, -1)
    assert np.flatnonzero(mirrored[100]).tolist() == list(range(120, 120 + math.floor(width)))


def test_flying_pixels_lie_between_foreground_and_background():
    depth = _plane(0.8)
    depth[:, 100:] = 0.6
    out = _quiet(OAK, flying_pixel_fraction=1.0).sense_depth(depth, K, np.random.default_rng(0))
    edge = out[:, 99:101]
    assert ((edge >= 0.6) & (edge <= 0.8)).all() and ((edge > 0.61) & (edge < 0.79)).mean() > 0.8
    np.testing.assert_array_equal(out[:, :98], depth[:, :98])  # away from the edge: exact (no noise here)
    dropped = _quiet(OAK, edge_dropout=1.0).sense_depth(depth, K, np.random.default_rng(0))
    assert (dropped[:, 99:101] == 0).all() and (dropped[:, :98] > 0).all()


def test_the_full_model_is_seeded_and_the_ideal_one_changes_nothing():
    depth, rgb = _plane(0.8), np.full((200, 200, 3), 90, np.uint8)
    a = OAK.sense(rgb, depth, K, np.random.default_rng(5))
    b = OAK.sense(rgb, depth, K, np.random.default_rng(5))
    c = OAK.sense(rgb, depth, K, np.random.default_rng(6))
    assert a[0].tobytes() == b[0].tobytes() and a[1].tobytes() == b[1].tobytes()
    assert a[1].tobytes() != c[1].tobytes() and a[0].tobytes() != c[0].tobytes()
    assert a[1].dtype == np.float32 and a[0].dtype == np.uint8
    rng = np.random.default_rng(0)
    state = rng.bit_generator.state
    assert IDEAL.sense(rgb, depth, K, rng) == (rgb, depth) and rng.bit_generator.state == state  # draws nothing
    assert sensor_rng(3, 0, 7).random() == sensor_rng(3, 0, 7).random() != sensor_rng(3, 0, 8).random()


# ------------------------------------------------------------------------------------------------- photometric
def test_photometric_variation_is_seeded_bounded_and_matches_its_sigmas():
    grey = np.full((64, 64, 3), 128, np.uint8)
    exposure = _quiet(OAK, exposure_sigma=0.1)
    lin_in = (128 / 255) ** 2.2
    logs = [math.log(((exposure.sense_rgb(grey, np.random.default_rng(s)) / 255.0) ** 2.2).mean() / lin_in)
            for s in range(300)]  # fmt: skip
    assert np.std(logs) == pytest.approx(0.1, rel=0.15) and abs(np.mean(logs)) < 0.03
    noisy = _quiet(OAK, exposure_sigma=0.5, white_balance_sigma=0.2, shot_noise_dn=2.0, read_noise_dn=5.0)
    for img in (np.zeros((32, 32, 3), np.uint8), np.full((32, 32, 3), 255, np.uint8)):
        out = noisy.sense_rgb(img, np.random.default_rng(0))
        assert out.dtype == np.uint8 and out.shape == img.shape  # clipped, not wrapped
    assert (noisy.sense_rgb(np.zeros((32, 32, 3), np.uint8), np.random.default_rng(0)) > 0).any()
    read = _quiet(OAK, read_noise_dn=1.0).sense_rgb(grey, np.random.default_rng(0)).astype(float)
    # 1 DN of linear read noise at mid grey: d(sRGB)/d(linear) = 255 / (2.4 * 255 * lin^(1/2.4 - 1) * 1.055)^-1
    slope = 1.055 / 2.4 * (lin_in ** (1 / 2.4 - 1))
    assert read.std() == pytest.approx(slope, rel=0.15)
    a, b = (noisy.sense_rgb(grey, np.random.default_rng(9)) for _ in range(2))
    assert a.tobytes() == b.tobytes()


# ------------------------------------------------------------------------------------------------ depth metrics
def test_absrel_delta1_and_fill_rate_on_a_fixture():
    ref = np.array([[1.0, 2.0, 4.0, 0.0]])
    sensed = np.array([[1.1, 0.0, 3.0, 5.0]])  # 10 %, a dropout, 25 % (ratio 4/3 > 1.25), data without truth
    m = depth_metrics(sensed, ref)
    assert (m.n_valid, m.abs_rel, m.delta1, m.fill_rate) == (2, pytest.approx((0.1 + 0.25) / 2), 0.5, 2 / 3)
    empty = depth_metrics(np.zeros((1, 4)), ref)
    assert empty.n_valid == 0 and empty.fill_rate == 0.0 and math.isnan(empty.abs_rel)
    mean = mean_depth_metrics([m, empty])
    assert mean.abs_rel == pytest.approx(m.abs_rel) and mean.fill_rate == pytest.approx(1 / 3)
    # The sensor's AbsRel on a plane is its mean absolute relative error: sqrt(2 / pi) sigma_z / z
    white = _quiet(OAK, disparity_noise_px=0.1)
    for z in (0.5, 1.0):
        sensed = white.sense_depth(_plane(z), K, np.random.default_rng(0))
        m = depth_metrics(sensed, _plane(z))
        assert m.abs_rel == pytest.approx(math.sqrt(2 / math.pi) * white.depth_noise_sigma_m(z) / z, rel=0.05)
        assert m.delta1 == 1.0 and m.fill_rate == 1.0


def test_the_metals_are_the_renderers_conductors():
    from sygrid.render.materials import MATERIALS, material_bsdf

    conductors = {m for m in MATERIALS if material_bsdf(m, np.random.default_rng(0))["type"] == "roughconductor"}
    assert conductors == METALS


# ------------------------------------------------------------------------------------------------- wiring
def test_a_recipe_names_its_sensor_and_the_generator_keeps_the_exact_depth(tmp_path: Path, tiny_dataset: Path):
    from sygrid.dataset import generate
    from sygrid.recipe import load_recipe, parse_recipe
    from sygrid.writers import load_bop_item, load_bop_true_depth
    from tests.conftest import tiny_recipe_json

    assert load_recipe(ROOT / "launch" / "recipes" / "builtin_test_noisy.json").spec.sensor == "oak-d"
    assert load_recipe(ROOT / "launch" / "recipes" / "builtin_test.json").spec.sensor == "ideal"
    with pytest.raises(ConfigError, match=r"tiny recipe: sensor: .*unknown sensor 'kinect'"):
        parse_recipe(tiny_recipe_json(sensor="kinect"), "tiny recipe", tmp_path)
    # the D435 here: the tiny bin is 0.2-0.45 m from the camera, mostly nearer than an OAK-D's 0.35 m at 400P
    recipe = parse_recipe(tiny_recipe_json(sensor="d435"), "tiny recipe", tmp_path)
    assert not generate(recipe, tmp_path, count=1, seed=7, progress=False).failed
    split = next(s for s in ("train_pbr", "val_pbr") if (tmp_path / "bop" / s).is_dir())
    ann, rgb, depth = load_bop_item(tmp_path / "bop", 0, 0, split=split)
    true = load_bop_true_depth(tmp_path / "bop", ann, split)
    _, rgb_ideal, depth_ideal = load_bop_item(tiny_dataset / "bop", 0, 0, split=split)  # the same item, seed 7
    np.testing.assert_array_equal(true, depth_ideal)  # sensing draws after rendering: the same render
    assert depth.tobytes() != true.tobytes() and rgb.tobytes() != rgb_ideal.tobytes()
    m = depth_metrics(depth, true)
    assert 0 < m.abs_rel < 0.02 and m.delta1 > 0.99 and 0.5 < m.fill_rate < 1.0
    assert load_bop_true_depth(tiny_dataset / "bop", ann, split) is None  # exact datasets have none


class _NoPipeline:
    """What `evaluate` needs of a pipeline, finding nothing: the sensing and depth metrics are under test."""

    pose_method, refiner, strategies = "direct", None, None

    def __init__(self, models: dict) -> None:
        from types import SimpleNamespace

        self.models, self.detector, self.frames = models, SimpleNamespace(conf_threshold=0.5), []

    def run(self, frame):
        from perception.pipeline import PerceptionResult

        self.frames.append(frame)
        return PerceptionResult(detections=[], poses=[], timings_ms={"total": 1.0})

    def use_sensor(self, sensor) -> None:
        pass


def test_eval_senses_each_image_seeded_and_reports_depth_metrics(tiny_dataset: Path):
    from perception.evaluation import EvalSettings, eval_items, evaluate, format_comparison, format_table
    from sygrid.drop import resolve_objects
    from sygrid.scene import parse_scene
    from tests.conftest import TINY_SCENE

    models = {m.obj_id: m for m in resolve_objects(parse_scene(TINY_SCENE, "tiny"), Path("."))}
    reports, frames = {}, {}
    for name, seed in (("ideal", 0), ("oak-d", 0), ("oak-d", 0), ("oak-d", 1)):
        pipeline = _NoPipeline(models)
        settings = EvalSettings(max_images=2, sensor=name, sensor_seed=seed)
        reports[name, seed] = evaluate(pipeline, tiny_dataset, settings, progress=False)
        frames.setdefault((name, seed), []).append(pipeline.frames)
    ideal, oak = reports["ideal", 0], reports["oak-d", 0]
    assert ideal["depth"]["abs_rel"] == 0.0 and ideal["depth"]["delta1"] == 1.0 and ideal["depth"]["fill_rate"] == 1
    assert 0 < oak["depth"]["abs_rel"] < 0.02 and oak["depth"]["fill_rate"] < 1.0 and oak["sensor"] == "oak-d"
    _, _, items = eval_items(tiny_dataset, EvalSettings(max_images=2))
    assert [(r["scene_id"], r["image_id"]) for r in oak["depth_per_image"]] == items
    assert oak["depth"]["abs_rel"] == pytest.approx(np.mean([r["abs_rel"] for r in oak["depth_per_image"]]))
    same, other = frames["oak-d", 0], frames["oak-d", 1][0]
    assert same[0][0].depth_m.tobytes() == same[1][0].depth_m.tobytes()  # seeded per image
    assert same[0][0].depth_m.tobytes() != other[0].depth_m.tobytes()
    assert same[0][0].rgb.tobytes() != frames["ideal", 0][0][0].rgb.tobytes()  # RGB is sensed too
    assert "sensor oak-d (seed 0): depth AbsRel" in format_table(oak)
    table = format_comparison([ideal, oak])
    assert table.splitlines()[1].startswith("ideal") and table.splitlines()[2].startswith("oak-d")


def test_eval_command_checks_sensor_names_before_loading_models(tmp_path: Path):
    from launch.cli import build_parser
    from launch.eval import _out_path, run

    parser = build_parser("eval")
    args = parser.parse_args(["eval", "--data", str(tmp_path), "--models", str(tmp_path / "m"), "--sensor", "x,oak-d"])
    with pytest.raises(ConfigError, match="--sensor: unknown sensor 'x'"):
        run(args)
    args = parser.parse_args(["eval", "--data", "D", "--models", "M", "--sensor", "ideal,oak-d"])
    assert [_out_path(args, s, 2).name for s in ("ideal", "oak-d")] == ["eval_M_ideal.json", "eval_M_oak-d.json"]
    assert _out_path(args, "ideal", 1).name == "eval_M.json" and _out_path(args, "d435", 1).name == "eval_M_d435.json"


def test_a_cell_file_names_the_sim_cameras_sensor(tmp_path: Path):
    from robot.cell_setup import load_cell_setup

    text = (ROOT / "launch" / "cells" / "sim.toml").read_text()
    assert load_cell_setup(ROOT / "launch" / "cells" / "sim.toml").data.camera.sensor == "ideal"  # the default
    for sensor, error in (("oak-d", None), ("kinect", r"sim_oak-d-like.toml: camera.sensor: unknown sensor")):
        path = tmp_path / "sim_oak-d-like.toml"
        path.write_text(text.replace('[camera]\nkind = "sim"\n', f'[camera]\nkind = "sim"\nsensor = "{sensor}"\n'))
        if error is None:
            assert load_cell_setup(path).data.camera.sensor == sensor
            assert load_cell_setup(path).depth_sensor() == sensor_preset(sensor)  # what the pipeline allows for
        else:
            with pytest.raises(ConfigError, match=error):
                load_cell_setup(path)
    oak = (ROOT / "launch" / "cells" / "ur5e_oak.toml").read_text()
    path = tmp_path / "oak.toml"
    path.write_text(oak.replace('[camera]\nkind = "oak"\n', '[camera]\nkind = "oak"\nsensor = "oak-d"\n'))
    with pytest.raises(ConfigError, match=r"camera\.sensor is for the simulated camera"):
        load_cell_setup(path)
    # a hardware camera's noise allowances assume its kind's stereo model
    assert load_cell_setup(ROOT / "launch" / "cells" / "ur5e_oak.toml").depth_sensor() == sensor_preset("oak-d")
    assert load_cell_setup(ROOT / "launch" / "cells" / "ur5e_realsense.toml").depth_sensor() == sensor_preset("d435")
    # ... at the stereo resolution the camera runs: an OAK's 800P pair halves the per-pixel noise it allows for
    path.write_text(oak.replace('[camera]\nkind = "oak"\n', '[camera]\nkind = "oak"\nstereo_size = [1280, 800]\n'))
    oak800 = load_cell_setup(path).depth_sensor()
    assert oak800 == OAK.at_stereo_size(1280, 800)
    assert oak800.stereo_focal_px == SENSOR_PRESETS["oak-d-800p"].stereo_focal_px
    assert oak800.depth_noise_sigma_m(0.9) == pytest.approx(OAK.depth_noise_sigma_m(0.9) / 2)


def test_the_emulator_camera_applies_its_sensor():
    from sim.emulator_camera import EmulatorCamera

    class _Process:
        def capture(self, timeout_s: float) -> dict:
            depth = np.full((120, 160), 0.9, np.float32)
            rgb = np.full((120, 160, 3), 100, np.uint8)
            K = CameraIntrinsics.from_fov(160, 120, 45.0)
            return {"rgb": rgb, "depth_m": depth, "intrinsics": K, "timestamp_s": 0.0, "T_base_camera": None}

    with pytest.raises(ValueError, match="needs an rng"):
        EmulatorCamera(_Process(), sensor=OAK)
    exact = EmulatorCamera(_Process()).capture()
    assert (exact.depth_m == 0.9).all()
    a, b = (EmulatorCamera(_Process(), sensor=OAK, rng=np.random.default_rng(4)).capture() for _ in range(2))
    assert a.depth_m.tobytes() == b.depth_m.tobytes() and a.rgb.tobytes() == b.rgb.tobytes()
    valid = a.depth_m[a.depth_m > 0]
    assert valid.size / a.depth_m.size > 0.5 and abs(valid.mean() - 0.9) < 5 * OAK.depth_bias_sigma_m(0.9)
