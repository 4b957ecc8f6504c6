"""The cell benchmark's bookkeeping on hand-made bin outcomes (the bins themselves run in the emulator: see
tests/test_pick_sim.py for whole cycles)."""

from __future__ import annotations

import math

import pytest

from launch.bench_cell import TARGETS, bins_to_resume, chart, format_results, merge_results, run, summarize
from launch.cli import build_parser
from sygrid.errors import ConfigError
from sygrid.fileio import write_json_atomic


def _bin(seed: int, n_left: int, picked: int, tried: int, cycles: list[float], stop: str, left_why: dict) -> dict:
    return {
        "seed": seed, "n_parts": 10, "n_left": n_left, "n_picked": picked, "n_tried": tried, "n_in_tray": picked - 1,
        "elsewhere": [{"part": "pipe", "xyz_m": [0.1, 0.2, 0.0]}],
        "failures": {"gripper_empty": tried - picked} if tried > picked else {}, "stop_reason": stop,
        "parts_by_kind": {"hex_nut": 6, "pipe": 4}, "left_by_kind": {"hex_nut": n_left},
        "left_why": left_why, "cycle_s": cycles, "perceive_plan_ms": [100.0 * (k + 1) for k in range(len(cycles))],
        "perceive_ms": [50.0], "plan_ms": [20.0], "sim_paced_s": 0.25 * seed, "sim_dropped_targets": 0,
        "perception_ms": [400.0 + seed], "looked_ahead": len(cycles) - 1,
    }  # fmt: skip


def test_summary_counts_parts_picks_cycles_and_causes():
    bins = [
        _bin(0, 2, 8, 9, [5.0, 6.0, 7.0], "nothing_safe", {"hex_nut: collision_bin": 2}),
        _bin(1, 0, 10, 10, [4.0], "bin_empty", {}),
    ]
    s = summarize(bins)
    assert s["parts_cleared"] == pytest.approx(18 / 20) and s["pick_success_rate"] == pytest.approx(18 / 19)
    assert s["cycle_median_s"] == pytest.approx(5.5) and s["perceive_plan_median_ms"] == pytest.approx(150.0)
    assert s["failures_by_cause"] == {"gripper_empty": 1} and s["n_in_tray"] == 16
    assert s["out_of_bin_not_in_tray"][1] == {"seed": 1, "part": "pipe", "xyz_m": [0.1, 0.2, 0.0]}
    assert s["stop_reasons"] == {"nothing_safe": 1, "bin_empty": 1}
    assert s["cleared_by_kind"] == {"hex_nut": "10/12", "pipe": "8/8"}
    assert s["left_by_cause"] == {"hex_nut: collision_bin": 2}
    assert s["sim_paced_s"] == pytest.approx(0.25) and s["sim_dropped_targets"] == 0
    assert s["perception_median_ms"] == pytest.approx(400.5) and s["n_looked_ahead"] == 2
    text = format_results(
        {"targets": TARGETS, "seeds": [0, 1], "seeds_done": [0, 1], "variants": {"m": {"description": "", **s}}}
    )
    assert "physics behind the clock: arm held 0.2 s, 0 targets dropped" in text
    assert "perception 400 ms median per look (the pipeline's own time), the cycle waiting 50 ms" in text
    empty = summarize([_bin(2, 10, 0, 0, [], "nothing_safe", {})])
    assert math.isnan(empty["pick_success_rate"]) and math.isnan(empty["cycle_median_s"])


def test_parts_in_the_tray_are_those_inside_its_inner_footprint():
    import numpy as np

    from launch.bench_cell import _in_box
    from sim.cell_config import CellConfig
    from sygrid.transforms import make_T

    cell = CellConfig()
    T_tray = cell.T_world_tray
    poses = np.stack([
        T_tray @ make_T(t=(0.0, 0.0, 0.01)),  # on the tray's floor
        T_tray @ make_T(t=(0.11, 0.07, 0.01)),  # in a corner (inner size 0.24 x 0.16)
        T_tray @ make_T(t=(0.13, 0.0, 0.01)),  # beyond the wall
        T_tray @ make_T(t=(0.0, 0.0, -0.05)),  # under it: fell past it onto the table
    ])  # fmt: skip
    assert _in_box(poses, T_tray, cell.tray_inner_size_m).tolist() == [True, True, False, False]


def test_report_and_chart_from_partial_results():
    variants = {"oracle": {"description": "ground truth", **summarize([_bin(0, 1, 9, 9, [5.0], "nothing_safe", {})])}}
    results = {"targets": TARGETS, "seeds": list(range(30)), "seeds_done": [0], "variants": variants}
    assert "oracle" in format_results(results)
    figure = chart(results)
    assert figure.axes[0].get_title() == "1 bin(s) per variant"  # what was measured, not what was asked for


def test_every_cause_left_in_the_bin_has_its_own_look_in_the_chart():
    causes = {f"part_{k}: why_{k}": 1 for k in range(25)}  # more than tab20's colours
    variants = {"models": {"description": "", **summarize([_bin(0, 10, 0, 0, [], "nothing_safe", causes)])}}
    figure = chart({"targets": TARGETS, "seeds": [0], "seeds_done": [0], "variants": variants})
    bars = next(a for a in figure.axes if a.get_legend() and len(a.get_legend().get_texts()) == 25)
    looks = {(tuple(h.get_facecolor()), h.get_hatch()) for h in bars.get_legend().legend_handles}
    assert len(looks) == 25


def test_cell_detector_recall_and_precision_on_hand_made_detections():
    import numpy as np

    from launch.bench_cell_detector import best_scores, is_right, size_row
    from launch.bench_cell_detector import chart as detector_chart
    from perception.results import Detection

    truth = [(1, np.array([0.0, 0.0, 10.0, 10.0])), (2, np.array([20.0, 20.0, 30.0, 30.0]))]
    right = Detection(0, 1, 0.9, np.array([2.0, 2.0, 8.0, 8.0]))
    wrong_class = Detection(1, 3, 0.8, np.array([22.0, 22.0, 28.0, 28.0]))
    weak = Detection(1, 2, 0.3, np.array([21.0, 21.0, 29.0, 29.0]))
    detections = [right, wrong_class, weak]
    assert [is_right(d, truth) for d in detections] == [True, False, True]
    assert best_scores(truth, detections) == [0.9, 0.3]
    row = size_row(640, [0.02, 0.03, 0.04], np.array(best_scores(truth, detections)),
                   [(d.score, is_right(d, truth)) for d in detections], conf=0.4)  # fmt: skip
    assert row["ms_median"] == pytest.approx(30.0) and row["recall"] == 0.5 and row["precision"] == 0.5
    at_02 = next(b for b in row["by_threshold"] if b["conf"] == 0.2)
    assert at_02["recall"] == 1.0 and at_02["precision"] == pytest.approx(2 / 3)
    results = {"config": {"conf_threshold": 0.4, "seeds": 1, "parts_seen": 2}, "sizes": [row]}
    assert detector_chart(results).axes[0].get_xlabel() == "detector ms per frame (median)"
    # two model folders, each on the whole frame and on the bin's box: one recall-against-time line each
    results["sizes"] = [{**row, "models": m, "region": r} for m in ("builtin", "sim_cell") for r in ("frame", "bin")]
    legend = detector_chart(results).axes[0].get_legend()
    assert [t.get_text() for t in legend.get_texts()] == [
        "builtin, frame", "builtin, bin", "sim_cell, frame", "sim_cell, bin"
    ]  # fmt: skip


def test_saved_runs_over_the_same_bins_merge_and_others_are_refused(tmp_path):
    def saved(variant: str, seeds: list[int], cleared_left: int) -> dict:
        bins = [_bin(s, cleared_left, 10 - cleared_left, 10 - cleared_left, [5.0], "nothing_safe", {}) for s in seeds]
        return {"targets": TARGETS, "seeds": seeds, "seeds_done": seeds, "scene": "bin.json",
                "variants": {variant: {"description": variant, **summarize(bins)}}}  # fmt: skip

    before, after = saved("models", [0, 1], 5), saved("models", [0, 1], 3)
    merged = merge_results({"before": before, "after": after})
    assert list(merged["variants"]) == ["before: models", "after: models"]
    assert merged["variants"]["after: models"]["parts_cleared"] == pytest.approx(0.7)
    with pytest.raises(ConfigError, match="'other' measured seeds"):
        merge_results({"before": before, "other": saved("models", [0, 1, 2], 3)})
    # through the command: --merge writes NAME.json/png, --replot redraws NAME.png
    write_json_atomic(tmp_path / "before.json", before)
    write_json_atomic(tmp_path / "after.json", after)
    args = build_parser("bench").parse_args(["bench", "cell", "--merge", "before,after", "--name", "both"])
    assert run(args, out_dir=tmp_path) == 0
    assert (tmp_path / "both.json").is_file() and (tmp_path / "both.png").is_file()
    (tmp_path / "both.png").unlink()
    args = build_parser("bench").parse_args(["bench", "cell", "--replot", "--name", "both"])
    assert run(args, out_dir=tmp_path) == 0 and (tmp_path / "both.png").is_file()


def test_a_stopped_run_resumes_with_its_bins_and_only_the_same_run_can_resume(tmp_path):
    from launch.bench_cell import CELL_FILE
    from robot.cell_setup import load_cell_setup

    scene = str(load_cell_setup(CELL_FILE).data.sim.scene)
    bins = [_bin(s, 2, 8, 8, [5.0], "nothing_safe", {}) for s in (0, 1, 2)]
    stopped = {"targets": TARGETS, "seeds": [0, 1, 2], "seeds_done": [0, 1], "scene": scene,
               "variants": {"models": {"description": "models", **summarize(bins), "bins": bins}}}  # fmt: skip
    path = tmp_path / "cell.json"
    planned = {"seeds": [0, 1, 2], "scene": scene}
    # only the bins of the seeds done are kept (a bin written after the last save is not trusted)
    assert [b["seed"] for b in bins_to_resume(stopped, planned, ["models"], path)["models"]] == [0, 1]
    with pytest.raises(ConfigError, match=r"cell.json: field 'variants' is \['models'\]"):
        bins_to_resume(stopped, planned, ["oracle"], path)
    with pytest.raises(ConfigError, match="field 'seeds'"):
        bins_to_resume(stopped, {**planned, "seeds": [0, 1, 2, 3]}, ["models"], path)
    # through the command, on a run with every seed done: nothing runs, the results are written again
    write_json_atomic(path, {**stopped, "seeds_done": [0, 1, 2]})
    args = build_parser("bench").parse_args(["bench", "cell", "--seeds", "3", "--variants", "models", "--resume"])
    assert run(args, out_dir=tmp_path) == 0
    assert (tmp_path / "cell.png").is_file()


def test_a_variant_changes_only_its_own_settings_of_the_cell_file():
    from launch.bench_cell import CELL_FILE, HOST
    from launch.cell_variants import VARIANTS, cell_for_bin
    from robot.cell_setup import load_cell_setup

    base = load_cell_setup(CELL_FILE)
    plain = cell_for_bin(base, VARIANTS["models"], 7, None, HOST).data
    strict = cell_for_bin(base, VARIANTS["models_fitness08"], 7, None, HOST).data
    assert plain.sim.seed == strict.sim.seed == 7 and plain.sim.host == HOST
    assert plain.perception.min_fitness == base.data.perception.min_fitness and strict.perception.min_fitness == 0.8
    assert strict.perception.model_copy(update={"min_fitness": plain.perception.min_fitness}) == plain.perception
    realistic = cell_for_bin(base, VARIANTS["models_oak_d"], 7, None, HOST).data
    assert plain.camera.sensor == base.data.camera.sensor == "ideal" and realistic.camera.sensor == "oak-d"
    assert realistic.calibration == plain.calibration and realistic.perception == plain.perception
    fewer = cell_for_bin(base, VARIANTS["models_oak_d_refine2"], 7, None, HOST).data
    assert base.data.perception.max_refined == 4 and fewer.perception.max_refined == 2
    assert fewer.perception.model_copy(update={"max_refined": 4}) == plain.perception and fewer.camera.sensor == "oak-d"
    tuned = cell_for_bin(base, VARIANTS["models_sim_cell_erosion0"], 7, None, HOST).data.perception
    assert tuned.mask_erosion_px == 0 and tuned.detector_input_size == 960 and tuned.models_dir.endswith("sim_cell")
    # variants that name their models keep measuring the same thing whatever the cell file runs
    for name, peel in (("models_builtin", 1), ("models_erosion0", 0)):
        general = cell_for_bin(base, VARIANTS[name], 7, None, HOST).data.perception
        assert general.models_dir.endswith("builtin") and general.detector_input_size == 800
        assert general.mask_erosion_px == peel


def test_each_attempt_is_judged_against_the_true_pose_of_the_nearest_part_of_its_kind_at_its_plan():
    import numpy as np

    from launch.cell_attempts import TruthAtPlan, attempt_pose_error, format_attempt_errors, summarize_attempt_errors
    from sygrid.objects import builtin_part
    from sygrid.transforms import make_T

    nut, washer = builtin_part("hex_nut"), builtin_part("washer")
    T_world_base = make_T(t=(0.1, 0.0, 0.0))
    truth = TruthAtPlan([nut.obj_id, washer.obj_id, nut.obj_id])
    T_true = np.stack([make_T(t=(0.4, 0.0, 0.01)), make_T(t=(0.45, 0.0, 0.01)), make_T(t=(0.5, 0.1, 0.01))])
    near_first = make_T(t=(0.3, 0.0, 0.012))  # base frame: 2 mm above the first nut
    far_off = make_T(t=(0.4, 0.1, 0.03))  # 20 mm above the second nut: a wrong estimate
    truth.add(T_true, [near_first, far_off])
    right = attempt_pose_error(T_world_base, near_first.tolist(), nut.obj_id, truth, nut)
    wrong = attempt_pose_error(T_world_base, far_off.tolist(), nut.obj_id, truth, nut)
    assert right["dz_mm"] == pytest.approx(2.0) and right["te_mm"] == pytest.approx(2.0)
    # ADD-S (the nut is symmetric) is at most the 2 mm shift: a shifted point lands near another of the surface
    assert 0 < right["add_d"] <= 0.002 / nut.diameter_m and right["re_deg"] == pytest.approx(0)
    assert wrong["dz_mm"] == pytest.approx(20.0) and wrong["add_d"] >= 0.1
    assert attempt_pose_error(T_world_base, make_T(t=(0.3, 0.0, 0.5)).tolist(), nut.obj_id, truth, nut) is None
    gear = builtin_part("spur_gear")  # no part of its kind in the bin: a false detection
    assert attempt_pose_error(T_world_base, near_first.tolist(), gear.obj_id, truth, gear) is None
    later = make_T(t=(0.3, 0.0, 0.011))
    truth.add(T_true + make_T(t=(0.0, 0.0, 0.001)) - np.eye(4), [later, near_first])  # the parts settled 1 mm up
    assert attempt_pose_error(T_world_base, near_first.tolist(), nut.obj_id, truth, nut)["dz_mm"] == pytest.approx(1)
    summary = summarize_attempt_errors([
        {"outcome": "picked", "pose_error": right}, {"outcome": "gripper_empty", "pose_error": wrong},
        {"outcome": "gripper_empty", "pose_error": None},
    ])  # fmt: skip
    assert summary["picked"]["n_wrong_estimate"] == 0 and summary["gripper_empty"] == {
        "n": 2, "n_with_truth": 1, "n_wrong_estimate": 1, "te_median_mm": pytest.approx(wrong["te_mm"]),
        "abs_dz_median_mm": pytest.approx(20.0), "re_median_deg": pytest.approx(0.0),
    }  # fmt: skip
    assert "gripper_empty 1/1 wrong" in format_attempt_errors("v", summary)


def test_refused_poses_are_judged_against_the_simulator_and_name_their_weakest_term():
    """A right estimate the verification refused for its outline, a wrong one, and poses left out: a kind not in the
    bin (a false detection) and a pose without the verification's figures."""
    from types import SimpleNamespace

    import numpy as np

    from launch.cell_attempts import format_refused, refused_pose_figures, summarize_refused
    from sygrid.objects import builtin_part
    from sygrid.transforms import make_T

    bracket, nut, gear = builtin_part("l_bracket"), builtin_part("hex_nut"), builtin_part("spur_gear")
    T_world_camera = make_T(t=(0.0, 0.0, 0.9))
    T_world_obj = np.stack([make_T(t=(0.1, 0.0, 0.0)), make_T(t=(-0.1, 0.0, 0.0))])
    ids = [bracket.obj_id, nut.obj_id]

    def refused(obj_id: int, t: tuple, **figures: float) -> SimpleNamespace:
        details = {"verify": {"confidence": 0.7, "fit": 0.97, "coverage": 1.0, "iou": 0.5, **figures}}
        return SimpleNamespace(obj_id=obj_id, T_camera_object=make_T(t=t), details=details)

    poses = [
        refused(bracket.obj_id, (0.1005, 0.0, -0.9)),  # 0.5 mm off the bracket, its outline refused
        refused(nut.obj_id, (-0.05, 0.0, -0.9), iou=0.9, fit=0.4),  # 50 mm off the nut: wrong
        refused(gear.obj_id, (0.1, 0.0, -0.9)),  # no gear in the bin
        SimpleNamespace(obj_id=nut.obj_id, T_camera_object=make_T(t=(-0.1, 0.0, -0.9)), details={}),
    ]
    models = {m.obj_id: m for m in (bracket, nut)}
    figures = refused_pose_figures(T_world_camera, poses, T_world_obj, ids, models)
    assert [(f["part"], f["right"], f["weakest"]) for f in figures] == [
        ("l_bracket", True, "iou"),
        ("hex_nut", False, "fit"),
    ]
    assert figures[0]["te_mm"] == pytest.approx(0.5, abs=1e-6) and figures[0]["confidence"] == 0.7
    summary = summarize_refused(figures)
    assert summary["n"] == 2 and summary["n_right"] == 1 and summary["right_weakest"] == {"iou": 1}
    assert summary["right_median_iou"] == pytest.approx(0.5)
    assert summary["right_by_part"] == {"hex_nut": "0/1", "l_bracket": "1/1"}
    assert "right 1" in format_refused("v", summary)


def test_a_bin_whose_run_raises_is_counted_as_an_error_and_the_bench_goes_on(monkeypatch):
    """``run_bin`` with the cell faked: the picker's run raises after recording its report (``last_report``, as
    ``robot.picker`` does); the bin comes back with stop reason ``error`` and the part left in the bin."""
    import contextlib
    from types import SimpleNamespace

    import numpy as np

    import launch.bench_cell as bench_cell
    import launch.pick
    from launch.cell_variants import VARIANTS
    from robot.cell_setup import load_cell_setup
    from robot.pick_report import RunReport, StopReason
    from sim.cell_config import CellConfig

    T = CellConfig().T_world_bin.copy()
    T[2, 3] += 0.01  # one part, in the bin
    process = SimpleNamespace(
        part_names=lambda: ["p0_hex_nut"], part_poses=lambda: T[None].copy(), thrown_parts=lambda: {},
        state=lambda: SimpleNamespace(backend_dropped_targets=0, tick=SimpleNamespace(paced_ticks=0)),
    )  # fmt: skip

    class Picker:
        planner = SimpleNamespace(plan=lambda *a, **k: None)
        T_base_camera = np.eye(4)
        last_report = RunReport([], StopReason.ERROR, "GripperError: the fingers did not stop")

        def run(self, max_cycles):
            raise RuntimeError("the fingers did not stop")

    @contextlib.contextmanager
    def fake_cell(*args, **kwargs):
        yield Picker(), process

    monkeypatch.setattr(launch.pick, "open_cell", fake_cell)
    base = load_cell_setup(bench_cell.CELL_FILE)
    result = bench_cell.run_bin(base, VARIANTS["oracle"], 0, None, 3)
    assert result["stop_reason"] == "error" and "did not stop" in result["stop_detail"]
    assert result["n_parts"] == 1 and result["n_left"] == 1 and result["n_picked"] == 0
    # without a report to keep (the error came before the run began), the error is raised on
    Picker.last_report = None
    with pytest.raises(RuntimeError, match="did not stop"):
        bench_cell.run_bin(base, VARIANTS["oracle"], 0, None, 3)

    class RefusingPicker(Picker):
        """Sees the nut, refuses its pose (and a false detection's of a kind not in the bin), stops."""

        on_cycle = None

        def run(self, max_cycles):
            refused = [  # hex_nut; flange: not in this bin
                SimpleNamespace(obj_id=i, T_camera_object=np.eye(4), details={}) for i in (1, 7)
            ]
            self.on_cycle(None, None, SimpleNamespace(poses=[], refused=refused), [])
            return RunReport([], StopReason.PARTS_UNSEEN, "the verification refused every pose")

    @contextlib.contextmanager
    def refusing_cell(*args, **kwargs):
        yield RefusingPicker(), process

    monkeypatch.setattr(launch.pick, "open_cell", refusing_cell)
    result = bench_cell.run_bin(base, VARIANTS["oracle"], 0, None, 3)
    assert result["left_why"] == {"seen, pose refused": 1}
    assert result["refused_last_frame"] == []  # the nut's pose came without the verification's figures


def test_a_result_is_reported_against_the_targets_it_was_run_with():
    old = {"success_rate": 0.95, "cycle_median_s": 8.0, "perceive_plan_ms": 300.0}  # saved before clearing had one
    for targets, line in ((TARGETS, "pick success >= 97 %, parts cleared >= 90 %"), (old, "pick success >= 95 %,")):
        text = format_results({"targets": targets, "seeds": [0], "seeds_done": [0], "variants": {}})
        assert text.splitlines()[0].startswith(f"targets: {line}")
    assert chart({"targets": old, "seeds": [0], "seeds_done": [0], "variants": {}}) is not None
