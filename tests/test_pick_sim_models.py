"""Sim in the loop with the shipped models: the demo's pipeline (``launch.pick.open_cell`` on the simulated cell's
file) with its own perception, ``models/sim_cell`` through ``perception.pipeline``, on a small bin of the demo's
grippable parts in the UR controller emulator (127.0.0.71; no other test module uses it).

The emulator runs in real time and the models miss or misplace a part now and then, so the test asserts what every
good run shows: parts picked at a success rate above a conservative bar, no protective stop, a clean stop and a
complete report; never exact outcomes.
"""

from __future__ import annotations

import pytest

pytest.importorskip("rtde_control")

from launch.pick import open_cell
from tests.test_pick_sim import _assert_complete, _assert_no_protective_stop, _cell_setup, _in_bin

HOST = "127.0.0.71"
SEED = 0
SCENE = {
    "name": "pick_four_grippable",
    "objects": [
        {"builtin": "hex_nut", "count": 1},
        {"builtin": "hex_bolt", "count": 1},
        {"builtin": "pipe", "count": 1},
        {"builtin": "spur_gear", "count": 1},
    ],
}
MAX_CYCLES = 6
MIN_SUCCESS_RATE = 0.5  # conservative: the cell benchmark's runs of these models pick far more often than this

pytestmark = [pytest.mark.slow, pytest.mark.timeout(300)]


def test_the_shipped_models_pick_from_a_small_bin(tmp_path):
    setup = _cell_setup(tmp_path, SCENE, HOST, SEED)
    assert setup.data.perception.kind == "models" and setup.resolve(setup.data.perception.models_dir).is_dir()
    with open_cell(setup) as (picker, process):
        start = process.part_poses()
        assert _in_bin(start).all(), "the drop left a part outside the bin"
        report = picker.run(max_cycles=MAX_CYCLES)
        end = process.part_poses()
        log = process.log_messages()
        _assert_no_protective_stop(picker, report)
    assert report.stop_reason != "needs_operator", report.stop_detail
    assert report.n_picked >= 1, (report.stop_reason, report.stop_detail, report.failures_by_cause())
    assert report.success_rate >= MIN_SUCCESS_RATE, report.failures_by_cause()
    assert (_in_bin(start) & ~_in_bin(end)).sum() >= 1, "no part left the bin"
    assert not any("protective stop" in line for line in log)
    assert all(c.n_detections >= 1 for c in report.cycles if c.picked)  # the picks came from the models' estimates
    _assert_complete(report)
