"""Sim in the loop: whole pick cycles of ``robot.picker`` with the stock ur_rtde client and the gripper socket against
the UR controller emulator (MuJoCo cell) and the emulator's camera, built by the demo's own ``launch.pick.open_cell``
from a cell file.

The perception is the oracle (ground-truth poses: perception is not what is tested here; the shipped models in the
loop are ``tests/test_pick_sim_models.py``'s). One emulator serves the module (127.0.0.70; no other test module uses
127.0.0.70): a bin of five parts dropped with a fixed seed. Each test puts the parts back where the drop left them (or
parks some of them out of the cell) and then runs the picker.

The emulator runs in real time, so two runs of one test differ (a grasp can slip once, a part can roll): the tests
assert what a correct picker does in every run (the bin emptied within a few cycles, the faults they inject handled,
no protective stop of its own, a complete report), never exact sequences of outcomes or wall time.
"""

from __future__ import annotations

import json
import re
import threading
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rtde_control")

from launch.pick import open_cell
from robot.cell_setup import CellSetup, load_cell_setup
from robot.pick_report import RunReport
from sim.cell_config import CellConfig
from sygrid.objects import builtin_part
from sygrid.transforms import invert, make_T

HOST = "127.0.0.70"
SEED = 6  # the drop leaves all five parts pickable (the planner finds a safe grasp for each in turn)
SCENE = {
    "name": "pick_five",
    "objects": [
        {"builtin": "hex_nut", "count": 2},
        {"builtin": "l_bracket", "count": 1},
        {"builtin": "pipe", "count": 1},
        {"builtin": "spur_gear", "count": 1},
    ],
}
# Above the bin, 0.17 m below the overhead camera, out of the UR5e's reach (its flange would be 0.89 m from the
# shoulder), floating there.
T_WORLD_UNREACHABLE = make_T(t=(-0.5, 0.0, 0.75))

pytestmark = [pytest.mark.slow, pytest.mark.timeout(300)]


@pytest.fixture(scope="module")
def cell(tmp_path_factory: pytest.TempPathFactory):
    """``(picker, process, T_world_obj at the start)`` of the five-part cell, built from a cell file."""
    setup = _cell_setup(tmp_path_factory.mktemp("pick_sim"), SCENE, HOST, SEED)
    with open_cell(setup, perception_kind="oracle") as (picker, process):
        yield picker, process, process.part_poses()


def _cell_setup(folder: Path, scene: dict, host: str, seed: int) -> CellSetup:
    """The simulated cell's file (``launch/cells/sim.toml``, its models folder as an absolute path) with ``scene``,
    ``host`` and ``seed``, written to ``folder``."""
    (folder / "scene.json").write_text(json.dumps(scene))
    cells = Path("launch/cells").resolve()
    text = (cells / "sim.toml").read_text()
    text, n_models = re.subn(
        r'^models_dir = "(.*)"', lambda m: f'models_dir = "{(cells / m[1]).resolve()}"', text, flags=re.MULTILINE
    )
    assert n_models == 1, "the cell file's [perception] models_dir line was not found"
    text = text.replace('host = "127.0.0.50"', f'host = "{host}"').replace("seed = 0", f"seed = {seed}")
    text, n_scenes = re.subn(r"^scene = .*$", 'scene = "scene.json"', text, flags=re.MULTILINE)
    assert n_scenes == 1, "the cell file's [sim] scene line was not found"
    (folder / "cell.toml").write_text(text)
    setup = load_cell_setup(folder / "cell.toml")
    assert setup.robot.host == host and setup.data.sim.seed == seed
    return setup


@pytest.fixture
def fresh(cell):
    """The cell as the drop left it: every part back in the bin, the arm at the observe pose, the gripper open, the
    picker's memory of earlier runs cleared."""
    picker, process, start = cell
    picker.robot.recover()
    picker.gripper.open()
    picker.arm.to_observe()
    process.place_parts(start)
    picker.memory.clear()
    time.sleep(0.2)  # a few hundred physics steps: the parts are at rest where they were
    return picker, process, start


def _keep_only(process, start: np.ndarray, keep: int, T_world_keep: np.ndarray | None = None, hold=False) -> None:
    """Parks every part but ``keep`` far out of the cell (held against gravity); ``keep`` goes to its start pose or
    ``T_world_keep`` (held there when ``hold``)."""
    T = start.copy()
    parked = [i for i in range(len(T)) if i != keep]
    for i in parked:
        T[i] = make_T(t=(5.0 + 0.5 * i, 5.0, 3.0))
    if T_world_keep is not None:
        T[keep] = T_world_keep
    process.place_parts(T, held=parked + ([keep] if hold else []))


def _in_bin(T_world_obj: np.ndarray) -> np.ndarray:
    cfg = CellConfig()
    p = (invert(cfg.T_world_bin) @ T_world_obj)[:, :3, 3]
    half = np.array(cfg.bin_inner_size_m) / 2
    return (np.abs(p[:, 0]) < half[0]) & (np.abs(p[:, 1]) < half[1]) & (p[:, 2] > -0.01) & (p[:, 2] < half[2] * 2)


def _nut(process) -> int:
    """A nut of the five (the first in the part list)."""
    return next(i for i, name in enumerate(process.part_names()) if name.endswith("hex_nut"))


def _assert_complete(report: RunReport) -> None:
    """No lost record: every cycle ended and is numbered in turn, every cycle but the last has its robot time (the
    next look's), and the JSON report holds every cycle and attempt with counts that agree."""
    assert [c.index for c in report.cycles] == list(range(len(report.cycles)))
    assert all(c.end is not None for c in report.cycles)
    assert all(c.sim_cycle_s is not None and c.sim_cycle_s > 0 for c in report.cycles[:-1])
    data = json.loads(json.dumps(report.to_json(), default=float))
    attempts = [a for c in data["cycles"] for a in c["attempts"]]
    assert len(data["cycles"]) == len(report.cycles) and data["n_attempts"] == len(attempts) == len(report.attempts)
    assert data["n_picked"] == sum(a["outcome"] == "picked" for a in attempts) == report.n_picked
    assert data["stop_reason"] == report.stop_reason and all(a["stage"] for a in attempts)


def _assert_no_protective_stop(picker, report: RunReport) -> None:
    assert "protective_stop" not in report.failures_by_cause(), report.failures_by_cause()
    assert not any(c.nudge is not None and c.nudge["outcome"] == "protective_stop" for c in report.cycles)
    assert not picker.robot.is_protective_stopped()


def test_clears_a_bin_of_five_parts(fresh):
    picker, process, start = fresh
    assert _in_bin(start).all()
    report = picker.run(max_cycles=8)  # five picks, up to two failed cycles, the look at the empty bin
    assert report.stop_reason == "bin_empty", (report.stop_detail, report.failures_by_cause())
    assert not _in_bin(process.part_poses()).any(), "every part has left the bin"
    assert report.n_picked >= 5 and report.success_rate >= 5 / 7, report.failures_by_cause()
    _assert_no_protective_stop(picker, report)
    # the first test on this emulator: no contact of the arm with the bin ever stopped it
    assert not any("protective stop" in line for line in process.log_messages())
    _assert_complete(report)
    # the cycle's record: robot time between two looks, and the stages that ran
    assert len(report.sim_cycle_times_s()) == report.n_picked and min(report.sim_cycle_times_s()) > 1.0
    assert all(c.stage_wall_s["place"] > 0 and c.n_planned >= 1 for c in report.cycles if c.picked)


def test_an_empty_bin_stops_at_once(fresh):
    picker, process, start = fresh
    process.park_parts(list(range(len(start))))
    report = picker.run()
    assert report.stop_reason == "bin_empty" and "no parts" in report.stop_detail
    assert len(report.cycles) == 1 and report.cycles[0].n_detections == 0 and report.attempts == []


def test_a_gear_in_a_corner_is_nudged_out_and_then_picked(fresh):
    picker, process, start = fresh
    gear = next(i for i, name in enumerate(process.part_names()) if name.endswith("spur_gear"))
    cfg = CellConfig()
    extents = builtin_part("spur_gear").extents_m
    radius, height = extents[0] / 2, extents[2]
    # 24 mm from the +x wall and 5 mm from the -y wall (bin frame): no grasp fits beside it
    half_x, half_y = cfg.bin_inner_size_m[0] / 2, cfg.bin_inner_size_m[1] / 2
    T_bin_gear = make_T(t=(half_x - 0.024 - radius, -half_y + 0.005 + radius, height / 2 + 0.0005))
    _keep_only(process, start, gear, cfg.T_world_bin @ T_bin_gear)
    time.sleep(0.3)
    report = picker.run(max_cycles=5)
    first = report.cycles[0]
    assert first.end == "nudged" and first.nudge["cause"] == "collision_bin", first.plan_summary
    assert first.attempts == []
    assert report.stop_reason == "bin_empty", report.stop_detail
    assert report.n_picked >= 1 and not _in_bin(process.part_poses()).any()
    _assert_no_protective_stop(picker, report)
    _assert_complete(report)


def test_a_nut_near_a_wall_is_dragged_out_by_the_middle_of_its_hole_without_tipping_and_then_picked(fresh):
    picker, process, start = fresh
    nut = _nut(process)
    cfg = CellConfig()
    extents = builtin_part("hex_nut").extents_m
    # flat, 12 mm from the +y wall (bin frame): too close for a finger. The press is the middle of the nut's hole
    # (robot.nudge): a press on the top's ring nearer its leading edge would tip it over.
    T_bin_nut = make_T(t=(0.0, cfg.bin_inner_size_m[1] / 2 - 0.012 - extents[1] / 2, extents[2] / 2 + 0.0005))
    _keep_only(process, start, nut, cfg.T_world_bin @ T_bin_nut)
    time.sleep(0.3)
    nudged = picker.run(max_cycles=1).cycles[0]
    assert nudged.end == "nudged" and nudged.nudge["cause"] == "collision_bin", nudged.plan_summary
    assert nudged.nudge["outcome"] == "done", nudged.nudge
    time.sleep(0.3)
    T_bin_after = invert(cfg.T_world_bin) @ process.part_poses()[nut]
    assert abs(T_bin_after[2, 2]) > 0.95, "the nut still lies flat"
    assert T_bin_after[1, 3] < T_bin_nut[1, 3] - 0.01, "the nut has moved away from the wall"
    report = picker.run(max_cycles=3)
    assert report.stop_reason == "bin_empty", (report.stop_detail, [c.end for c in report.cycles])
    assert report.n_picked == 1
    _assert_no_protective_stop(picker, report)


def test_an_l_bracket_standing_on_its_sheet_edges_is_picked_by_a_pinch_of_the_sheet(fresh):
    """Standing on its sheet edges an L-bracket's only grasps pinch the 2 mm sheet: the gripper's object detection
    reads "no object" (the pads squeeze the sheet to 1.3 mm, under its 1.5 mm), but the fingers stopped apart
    hold it, and it is placed."""
    picker, process, start = fresh
    bracket = next(i for i, name in enumerate(process.part_names()) if name.endswith("l_bracket"))
    cfg = CellConfig()
    width = builtin_part("l_bracket").extents_m[1]  # the sheet's width, along the object's y
    R_standing = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # object y up
    _keep_only(process, start, bracket, cfg.T_world_bin @ make_T(R_standing, (0.0, -0.03, width / 2 + 0.0005)))
    time.sleep(0.3)
    T_bin_bracket = invert(cfg.T_world_bin) @ process.part_poses()[bracket]
    assert T_bin_bracket[2, 1] > 0.99, "the bracket fell over"
    report = picker.run(max_cycles=3)  # a pick (at most one failed cycle before it) and the look at the empty bin
    assert report.n_picked >= 1, [(a.outcome, a.detail) for a in report.attempts]
    assert report.stop_reason == "bin_empty" and not _in_bin(process.part_poses()[[bracket]]).any()
    _assert_no_protective_stop(picker, report)
    _assert_complete(report)


def test_an_unreachable_part_is_refused_with_the_reason(fresh):
    picker, process, start = fresh
    nut = _nut(process)
    _keep_only(process, start, nut, T_WORLD_UNREACHABLE, hold=True)
    q_before = picker.robot.q()
    report = picker.run()
    assert report.stop_reason == "nothing_safe" and report.attempts == [], (report.stop_detail, report.attempts)
    assert report.cycles[0].n_poses == 1
    assert "unreachable" in report.stop_detail, report.stop_detail
    np.testing.assert_allclose(picker.robot.q(), q_before, atol=1e-3)  # nothing moved
    _assert_complete(report)


def test_a_grasp_that_slips_fails_verification_and_is_retried(fresh):
    """The part leaves the fingers while the arm lifts it (moved back to the bin floor as the lift ends): the
    fingers close on nothing, the attempt is "slipped", and the next look picks it where it lies."""
    picker, process, start = fresh
    nut = _nut(process)
    _keep_only(process, start, nut)
    gripper = picker.gripper
    real = gripper.object_detected
    slipped = []

    def slip_once() -> bool:
        if not slipped:
            T = process.part_poses()
            T[nut] = start[nut]  # out of the fingers, back where it lay
            process.place_parts(T, held=[i for i in range(len(T)) if i != nut])
            slipped.append(True)
            time.sleep(0.3)  # the fingers close on the empty space
        return real()

    gripper.object_detected = slip_once
    try:
        report = picker.run(max_cycles=4)
    finally:
        del gripper.object_detected
    outcomes = [a.outcome for a in report.attempts]
    assert outcomes[0] == "slipped" and report.attempts[0].stage == "verify", [a.detail for a in report.attempts]
    assert "picked" in outcomes[1:], [a.detail for a in report.attempts]
    assert report.stop_reason == "bin_empty" and not _in_bin(process.part_poses()[[nut]]).any()
    _assert_no_protective_stop(picker, report)
    _assert_complete(report)


def _during_first_transit(picker, action) -> list:
    """Runs ``action`` 0.3 s into the first joint move towards a part (the arm is moving)."""
    robot, fired = picker.robot, []
    real = robot.move_j

    def move_j(q, speed_rad_s=None, accel_rad_s2=None):
        if not fired and np.max(np.abs(np.asarray(q) - picker.q_observe)) > 0.1:
            fired.append(threading.Timer(0.3, action))
            fired[0].start()
        return real(q, speed_rad_s, accel_rad_s2)

    robot.move_j = move_j
    return fired


def test_a_protective_stop_mid_move_is_recovered_and_the_run_goes_on(fresh):
    picker, process, start = fresh
    nut = _nut(process)
    _keep_only(process, start, nut)
    fired = _during_first_transit(picker, lambda: process.trigger_protective_stop("test: a person in the cell"))
    try:
        report = picker.run(max_cycles=4)
    finally:
        del picker.robot.move_j
    assert fired, "the arm never moved towards the part"
    outcomes = [a.outcome for a in report.attempts]
    assert outcomes[0] == "protective_stop" and report.attempts[0].stage == "approach", outcomes
    assert "picked" in outcomes[1:], [a.detail for a in report.attempts]
    assert report.stop_reason == "bin_empty" and not picker.robot.is_protective_stopped()
    assert any("protective stop: test" in line for line in process.log_messages())
    _assert_complete(report)


def test_a_dropped_connection_is_reconnected_and_the_run_goes_on(fresh):
    picker, process, start = fresh
    nut = _nut(process)
    _keep_only(process, start, nut)
    dropped = []
    fired = _during_first_transit(picker, lambda: dropped.append(process.drop_connections(down_s=2.0)))
    try:
        report = picker.run(max_cycles=4)
    finally:
        del picker.robot.move_j
    assert fired and dropped and dropped[0] >= 3  # receive, control, IO (and the dashboard, the script port)
    assert any("link down" in line for line in process.log_messages())
    outcomes = [a.outcome for a in report.attempts]
    assert outcomes[0] == "connection_lost" and "picked" in outcomes[1:], (outcomes, report.stop_detail)
    assert report.stop_reason == "bin_empty" and picker.robot.is_connected()
    _assert_no_protective_stop(picker, report)
    _assert_complete(report)
