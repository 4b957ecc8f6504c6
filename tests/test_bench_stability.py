"""``sygrid bench stability``: the sweep machinery on a tiny axis (saved per point, resumed, settings checked), the
failure point on synthetic curves, the summary table from a fixture result, and the pieces the axes are made of."""

from __future__ import annotations

import json
import math
import socket
import threading
import time
from dataclasses import replace

import numpy as np
import pytest

from launch.cli import main
from launch.stability.cell_axes import bin_measurements, camera_error, run_cell_bin, starved
from launch.stability.delay_proxy import DelayProxy
from launch.stability.failure import (
    BELOW_FROM_START,
    FAILS,
    HOLDS,
    NO_DATA,
    Criterion,
    CurvePoint,
    binomial_se,
    failure_point,
)
from launch.stability.generated import point_recipe_json, spread_counts
from launch.stability.options import Options
from launch.stability.perception_pass import part_family
from launch.stability.report import axis_result, summary_markdown
from launch.stability.soak import slower_p, soak_notes
from launch.stability.sweep import CLAIM_FILE, Axis, Measurement, Method, Point, point_path, run_axis
from sim.render_process import NO_ANSWER
from sygrid.bench.common import dataset_digest, folder_digest
from sygrid.camera import CameraIntrinsics
from sygrid.errors import ConfigError
from sygrid.fileio import read_json
from sygrid.sensor import sensor_preset, sensor_rng
from sygrid.transforms import rotation_angle_deg


def _curve(values: list[float], n: int = 100, xs: list[float] | None = None) -> list[CurvePoint]:
    xs = xs or [float(i) for i in range(len(values))]
    return [CurvePoint(f"p{i}", x, round(v * n), n) for i, (x, v) in enumerate(zip(xs, values, strict=True))]


# ------------------------------------------------------------------------------------------- the failure point
def test_a_method_that_never_fails_holds_through_the_last_point():
    f = failure_point(_curve([0.95, 0.94, 0.9, 0.85]), Criterion(fraction=0.8, floor=0.5))
    assert f["status"] == HOLDS and f["x"] is None and f["label"] is None
    assert f["best"] == pytest.approx(0.95) and f["threshold"] == pytest.approx(0.76)


def test_a_method_that_fails_between_points_is_interpolated_with_an_uncertainty():
    curve = _curve([0.9, 0.8, 0.4], n=200, xs=[0.0, 1.0, 3.0])
    f = failure_point(curve, Criterion(fraction=0.8, floor=0.3))
    assert f["status"] == FAILS and f["between"] == ["p1", "p2"] and f["label"] == "p2"
    assert f["threshold"] == pytest.approx(0.72)
    assert f["x"] == pytest.approx(1.0 + 2.0 * (0.8 - 0.72) / 0.4)  # linear between (1, 0.8) and (3, 0.4)
    # the delta method on the binomial errors of the two points around the crossing
    se0, se1 = math.sqrt(0.8 * 0.2 / 200), math.sqrt(0.4 * 0.6 / 200)
    expected = 2.0 * math.hypot((0.72 - 0.4) / 0.4**2 * se0, (0.8 - 0.72) / 0.4**2 * se1)
    assert f["sigma_x"] == pytest.approx(expected)
    bigger = failure_point(_curve([0.9, 0.8, 0.4], n=20, xs=[0.0, 1.0, 3.0]), Criterion(0.8, 0.3))
    assert bigger["sigma_x"] > f["sigma_x"]  # fewer samples, a less certain failure point


def test_a_method_below_the_floor_from_the_start_and_one_without_data():
    f = failure_point(_curve([0.3, 0.25, 0.1]), Criterion(fraction=0.8, floor=0.5))
    assert f["status"] == BELOW_FROM_START and f["label"] == "p0" and f["x"] == 0.0
    assert failure_point([CurvePoint("a", 1.0, 0, 0)], Criterion())["status"] == NO_DATA


def test_a_categorical_axis_names_the_points_below():
    curve = [
        CurvePoint("painted", None, 40, 100),
        CurvePoint("steel", None, 90, 100),
        CurvePoint("zinc", None, 50, 100),
    ]
    f = failure_point(curve, Criterion(0.8, 0.3))
    assert f["status"] == FAILS and f["label"] == "painted" and f["below"] == ["painted", "zinc"] and f["x"] is None


def test_binomial_errors_stay_positive_at_perfect_scores():
    assert binomial_se(50, 100) == pytest.approx(0.05)
    assert 0 < binomial_se(100, 100) < 0.01 and binomial_se(0, 100) == pytest.approx(binomial_se(100, 100))
    assert math.isnan(binomial_se(0, 0))


# --------------------------------------------------------------------------------------- the sweep machinery
def _depth_within_5mm(factor: float, seed: int) -> tuple[int, int]:
    """A real, cheap measurement: the pixels of a plane 0.8 m away that the OAK-D model, its noise scaled by
    ``factor``, reports within 5 mm."""
    K = CameraIntrinsics(300.0, 300.0, 32.0, 24.0, 64, 48)
    depth = np.full((48, 64), 0.8, dtype=np.float32)
    sensed = sensor_preset("oak-d").scaled(factor).sense_depth(depth, K, sensor_rng(seed, 0))
    return int(np.count_nonzero(np.abs(sensed - depth) < 0.005)), depth.size


def _tiny_axis(calls: list, settings: dict | None = None) -> Axis:
    def measure(point: Point, seed: int) -> dict[str, Measurement]:
        calls.append((point.label, seed))
        k, n = _depth_within_5mm(point.params["scale"], seed)
        return {"oak-d": Measurement(k, n, {"family all": [k, n]})}

    return Axis(
        name="tiny", title="Tiny", x_label="noise scale",
        points=(Point("0x", 0.0, {"scale": 0.0}), Point("3x", 3.0, {"scale": 3.0})),
        methods=(Method("oak-d", "depth within 5 mm"),), measure=measure, seeds=(0,),
        criterion=Criterion(0.9, 0.5), summary="holds to {x} x", unit="x", settings=settings or {"size": [64, 48]},
    )  # fmt: skip


def test_the_sweep_saves_each_point_and_resumes_without_measuring_it_again(tmp_path):
    calls: list = []
    records = run_axis(_tiny_axis(calls), tmp_path, log=lambda s: None)
    assert calls == [("0x", 0), ("3x", 0)] and len(records) == 2
    saved = read_json(point_path(tmp_path, "tiny", "3x", 0, "oak-d"), "point")
    assert saved["n"] == 64 * 48 and saved["x"] == 3.0 and saved["settings"] == {"size": [64, 48]}
    quiet, noisy = (r["value"] for r in records)
    assert quiet > noisy  # three times the noise leaves fewer pixels within 5 mm
    calls.clear()
    again = run_axis(_tiny_axis(calls), tmp_path, log=lambda s: None)
    assert calls == [] and [r["k"] for r in again] == [r["k"] for r in records]
    point_path(tmp_path, "tiny", "3x", 0, "oak-d").unlink()  # a lost file: only its (point, seed) again
    run_axis(_tiny_axis(calls), tmp_path, log=lambda s: None)
    assert calls == [("3x", 0)]
    with pytest.raises(ConfigError, match="other settings"):
        run_axis(_tiny_axis(calls, {"size": [32, 24]}), tmp_path, log=lambda s: None)
    result = axis_result(_tiny_axis(calls), again)
    m = result["methods"]["oak-d"]
    assert [p["n"] for p in m["curve"]] == [3072, 3072] and m["groups"]["family all"]["curve"][1]["k"] == noisy * 3072
    assert result["points_measured"] == 2 and result["seconds"] >= 0
    ungrouped = replace(_tiny_axis(calls), methods=(Method("oak-d", "depth within 5 mm", grouped=False),))
    assert axis_result(ungrouped, again)["methods"]["oak-d"]["groups"] == {}  # saved, not reported


def test_runs_sharing_an_axis_skip_a_point_claimed_by_a_live_process_and_take_over_a_dead_ones(tmp_path):
    import subprocess
    import sys

    calls: list = []
    live = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    try:
        claim_0x = point_path(tmp_path, "tiny", "0x", 0, "oak-d").parent / CLAIM_FILE
        claim_3x = point_path(tmp_path, "tiny", "3x", 0, "oak-d").parent / CLAIM_FILE
        for claim, pid in ((claim_0x, live.pid), (claim_3x, dead.pid)):
            claim.parent.mkdir(parents=True)
            claim.write_text(str(pid))
        logged: list[str] = []
        records = run_axis(_tiny_axis(calls), tmp_path, log=logged.append)
        assert calls == [("3x", 0)] and [r["point"] for r in records] == ["3x"]
        assert any(f"being measured by process {live.pid}" in line for line in logged)
        assert claim_0x.read_text() == str(live.pid) and not claim_3x.exists()  # the live claim kept, ours released
    finally:
        live.kill()
        live.wait()
    run_axis(_tiny_axis(calls), tmp_path, log=lambda s: None)  # its owner gone, the point is measured here
    assert calls == [("3x", 0), ("0x", 0)] and not claim_0x.exists()


def test_a_repacked_model_folder_is_a_new_pass_key(tmp_path):
    (tmp_path / "manifest.json").write_text("{}")
    (tmp_path / "pose.onnx").write_bytes(b"one")
    before = folder_digest(tmp_path)
    assert folder_digest(tmp_path) == before
    (tmp_path / "pose.onnx").write_bytes(b"two")
    assert folder_digest(tmp_path) != before


def test_a_dataset_generated_again_with_other_annotations_is_a_new_pass_key(tmp_path):
    info = tmp_path / "bop" / "test" / "000000" / "scene_gt_info.json"
    info.parent.mkdir(parents=True)
    (tmp_path / "dataset.json").write_text("{}")
    info.write_text('{"0": [{"visib_fract": 1.0}]}')
    before = dataset_digest(tmp_path)
    assert dataset_digest(tmp_path) == before
    info.write_text('{"0": [{"visib_fract": 0.2}]}')  # the same scene, its visible fraction corrected
    assert dataset_digest(tmp_path) != before


def test_the_seeds_of_a_point_are_pooled():
    axis = _tiny_axis([])
    records = [{"method": "oak-d", "point": "3x", "seed": s, "k": k, "n": 10, "groups": {}, "seconds": 1.0}
               for s, k in ((0, 4), (1, 6))]  # fmt: skip
    result = axis_result(axis, records)
    curve = result["methods"]["oak-d"]["curve"]
    assert curve[0]["n"] == 0 and (curve[1]["k"], curve[1]["n"]) == (10, 20)
    assert result["seconds"] == 2.0


# ---------------------------------------------------------------------------------------------- the summary
FIXTURE = {
    "axis": "part_size", "title": "Part size in pixels", "description": "Binned.", "x_label": "nominal size [px]",
    "unit": "px", "categorical": False, "summary": "works down to {x} px", "criterion": {"fraction": 0.8, "floor": 0.3},
    "seeds": [0], "settings": {}, "seconds": 600.0, "points_measured": 3, "notes": None,
    "points": [{"label": "64px", "x": 64.0, "params": {}}, {"label": "32px", "x": 32.0, "params": {}},
               {"label": "16px", "x": 16.0, "params": {}}],
    "methods": {
        "detector": {
            "metric": "detection recall",
            "curve": [{"label": "64px", "x": 64.0, "k": 90, "n": 100, "value": 0.9, "se": 0.03},
                      {"label": "32px", "x": 32.0, "k": 80, "n": 100, "value": 0.8, "se": 0.04},
                      {"label": "16px", "x": 16.0, "k": 40, "n": 100, "value": 0.4, "se": 0.05}],
            "failure": {"status": "fails", "x": 26.0, "sigma_x": 1.5, "label": "16px", "between": ["32px", "16px"],
                        "best": 0.9, "threshold": 0.72, "last_measured": "16px"},
            "groups": {"family thin": {"curve": [], "failure": {"status": "fails", "x": 40.0, "sigma_x": 3.0,
                                                                "label": "32px", "between": ["64px", "32px"],
                                                                "best": 0.9, "threshold": 0.72}}},
        },
        "rgbd+icp": {
            "metric": "pose accuracy",
            "curve": [],
            "failure": {"status": "holds", "x": None, "sigma_x": None, "label": None, "between": None, "best": 0.95,
                        "threshold": 0.76, "last_measured": "16px"},
            "groups": {},
        },
    },
}  # fmt: skip


def test_the_summary_table_is_generated_from_the_results():
    md = summary_markdown([FIXTURE])
    assert "| Part size in pixels | detection recall: works down to 26 ± 1.5 px |" in md
    assert "pose accuracy: works down to 16 px or further: it holds at the hardest point measured |" in md
    row = "| detector | detection recall | fails at 26 ± 1.5 px (between 32px and 16px) | 90.0 % | 72.0 % | 100 |"
    assert row in md
    assert "thin: fails at 40 ± 3 px (between 64px and 32px)" in md  # a family that fails before the method
    assert "holds through the hardest point measured (16px)" in md and "10.0 min" in md


# ----------------------------------------------------------------------------------------------- the pieces
def test_scaled_sensor_scales_the_depth_errors_and_keeps_probabilities_valid():
    oak = sensor_preset("oak-d")
    twice, none, many = oak.scaled(2.0), oak.scaled(0.0), oak.scaled(3.0)
    assert twice.disparity_noise_px == pytest.approx(2 * oak.disparity_noise_px)
    assert twice.hole_fraction == pytest.approx(2 * oak.hole_fraction) and twice.baseline_m == oak.baseline_m
    assert none.disparity_bias_px == 0 and none.edge_dropout == 0 and none.exposure_sigma == oak.exposure_sigma
    assert many.edge_dropout + many.flying_pixel_fraction == pytest.approx(1.0) and many.dark_dropout == 1.0
    with pytest.raises(ConfigError, match="factor"):
        oak.scaled(-1.0)


def test_generated_points_change_the_recipe():
    base = {"sensor": "ideal", "scene": {"objects": [{"builtin": "hex_nut", "count": 4}, {"builtin": "washer",
            "count": 2}], "camera": {"pose_sampling": {"distance_m": [0.55, 0.95]}}}}  # fmt: skip
    out = point_recipe_json(base, {"parts_per_bin": 9, "material": "steel", "sensor": "oak-d",
                                   "scene.camera.pose_sampling.distance_m": [1.0, 1.0]})  # fmt: skip
    assert [o["count"] for o in out["scene"]["objects"]] == [6, 3] and out["sensor"] == "oak-d"
    assert {o["material"] for o in out["scene"]["objects"]} == {"steel"}
    assert out["scene"]["camera"]["pose_sampling"]["distance_m"] == [1.0, 1.0]
    assert base["scene"]["objects"][0]["count"] == 4  # the base is left as it was
    assert spread_counts([4, 3, 4, 3, 2, 2, 2], 5) == [1, 1, 1, 1, 1, 0, 0]  # largest remainders, ties to the first
    assert sum(spread_counts([4, 3, 4, 3, 2, 2, 2], 60)) == 60
    with pytest.raises(ConfigError, match="no object"):
        point_recipe_json(base, {"scene.lights.strength": 1.0})


def test_part_families_come_from_symmetry_and_thickness():
    from sygrid.objects import builtin_part

    families = {n: part_family(builtin_part(n)) for n in ("washer", "l_bracket", "pipe", "hex_nut", "flange")}
    assert families == {"washer": "thin", "l_bracket": "thin", "pipe": "rotational", "hex_nut": "n-fold symmetric",
                        "flange": "n-fold symmetric"}  # fmt: skip


def test_a_bin_run_becomes_measurements_per_family():
    outcome = {"n_picked": 3, "n_tried": 5, "n_parts": 6, "n_left": 2, "stop_reason": "max_cycles", "cycle_s": [5.0],
               "attempts_by_kind": {"hex_nut": [2, 2], "l_bracket": [1, 3]},
               "parts_by_kind": {"hex_nut": 4, "l_bracket": 2}, "left_by_kind": {"l_bracket": 2}}  # fmt: skip
    m = bin_measurements(outcome, max_cycles=5)
    assert (m["pick success"].k, m["pick success"].n) == (3, 5) and m["pick success"].groups["family thin"] == [1, 3]
    assert (m["parts cleared"].k, m["parts cleared"].n) == (4, 5)  # of the parts 5 cycles could clear
    assert m["parts cleared"].groups["part l_bracket"] == [0, 2] and m["runs completed"].k == 1
    failed = bin_measurements(None, 0, "RobotConnectionError: no controller")
    assert (failed["runs completed"].k, failed["runs completed"].n, failed["pick success"].n) == (0, 1, 0)


def test_a_starved_bin_is_run_again_and_then_refused(monkeypatch):
    """A bin whose physics fell behind real time (or whose frames timed out) measures the machine: it is run again,
    and a point starved every time is refused rather than saved as the axis's failure."""
    import launch.bench_cell

    fine = {"n_picked": 2, "n_tried": 2, "n_parts": 6, "n_left": 4, "stop_reason": "max_cycles", "cycle_s": [5.0],
            "attempts_by_kind": {"hex_nut": [2, 2]}, "parts_by_kind": {"hex_nut": 6}, "left_by_kind": {"hex_nut": 4},
            "sim_dropped_targets": 0, "stop_detail": "stopped after 2 cycle(s)"}  # fmt: skip
    late = {**fine, "sim_dropped_targets": 500}
    assert starved(fine, None) is None and "500 robot targets dropped" in starved(late, None)
    timeout = f"RuntimeError: {NO_ANSWER} 'capture' within 10 s (the process is alive)"
    assert "render process did not answer" in starved(None, timeout) and starved(None, "OSError: refused") is None
    runs = [late, fine]
    monkeypatch.setattr(launch.bench_cell, "run_bin", lambda *a, **k: runs.pop(0))
    m = run_cell_bin(Options(), seed=0, max_cycles=2)
    assert runs == [] and (m["pick success"].k, m["pick success"].n) == (2, 2)
    monkeypatch.setattr(launch.bench_cell, "run_bin", lambda *a, **k: late)
    with pytest.raises(ConfigError, match="too busy for real-time simulation"):
        run_cell_bin(Options(), seed=0, max_cycles=2)


def test_camera_errors_have_the_asked_size():
    T = np.array(camera_error(3, mm=4.0))
    assert np.linalg.norm(T[:3, 3]) == pytest.approx(0.004)
    assert rotation_angle_deg(T[:3, :3], np.eye(3)) == pytest.approx(0.0)
    R = np.array(camera_error(3, deg=0.5))
    assert rotation_angle_deg(R[:3, :3], np.eye(3)) == pytest.approx(0.5) and np.allclose(R[:3, 3], 0)
    assert not np.allclose(camera_error(4, mm=4.0), T)  # the direction is the seed's


def test_the_delay_proxy_adds_its_latency_both_ways():
    server = socket.create_server(("127.0.0.65", 0))
    port = server.getsockname()[1]

    def echo() -> None:
        conn, _ = server.accept()
        with conn:
            while data := conn.recv(64):
                conn.sendall(data)

    threading.Thread(target=echo, daemon=True).start()
    with (
        DelayProxy("127.0.0.66", "127.0.0.65", [port], latency_s=0.05),
        socket.create_connection(("127.0.0.66", port), timeout=5.0) as client,
    ):
        start = time.perf_counter()
        client.sendall(b"ping")
        assert client.recv(64) == b"ping"
        assert time.perf_counter() - start >= 0.1  # 50 ms each way
    server.close()


def test_the_command_lists_its_axes_and_refuses_an_unknown_one(capsys):
    assert main(["bench", "stability", "--list", "--axis", "depth_noise,soak"]) == 0
    out = capsys.readouterr().out
    assert "depth_noise: Depth noise; points 0x, 0.5x, 1x, 1.5x, 2x, 3x" in out and "soak: Soak" in out
    assert main(["bench", "stability", "--list", "--axis", "nois"]) == 2
    assert "unknown ['nois']" in capsys.readouterr().err


def test_the_soak_notes_compare_the_last_tenth_with_the_first():
    rng = np.random.default_rng(0)

    def record(method: str, x: float, k: int, n: int, rss: float, make_scale: float) -> dict:
        extra = {"rss_mb": rss, "make_s": list(rng.gamma(4.0, make_scale / 4.0, 100)),
                 "write_s": list(rng.gamma(4.0, 0.01, 100))}  # fmt: skip
        return {"method": method, "x": x, "k": k, "n": n, "extra": extra}

    gen = "generator: items written"
    notes = soak_notes([record(gen, 1, 100, 100, 1000.0, 1.3), record(gen, 10, 100, 100, 1030.0, 2.0),
                        record(gen, 5, 100, 100, 1500.0, 1.3)])  # fmt: skip
    g = notes[gen]
    assert g["rss_growth_pct"] == pytest.approx(3.0)  # first to last, the middle ignored
    assert g["make_s_p_last_slower"] < 1e-6 and g["make_s_last_median"] > g["make_s_first_median"]
    assert g["write_s_p_last_slower"] > 0.01  # drawn alike: no slowdown beyond noise
    assert g["z_last_vs_first"] == 0.0
    # the same content times in both tenths: not slower
    assert slower_p([1.0, 2.0, 3.0] * 30, [1.0, 2.0, 3.0] * 30) > 0.4


def test_a_generated_set_is_verified_with_the_sensor_it_was_generated_through(tmp_path):
    from launch.stability.perception_pass import frames_sensor_of
    from sygrid.sensor import IDEAL, sensor_preset

    (tmp_path / "dataset.json").write_text(json.dumps({"recipe": {"name": "t", "sensor": "oak-d"}}))
    assert frames_sensor_of(tmp_path) == sensor_preset("oak-d")
    assert frames_sensor_of(tmp_path, IDEAL) == IDEAL  # a pass that senses the exact depth itself names its sensor
    (tmp_path / "dataset.json").write_text(json.dumps({"recipe": {"name": "t"}}))
    assert frames_sensor_of(tmp_path) == sensor_preset("ideal")
