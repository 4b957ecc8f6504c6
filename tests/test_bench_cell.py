"""The cell benchmark's bookkeeping on hand-made bin outcomes (the bins themselves run in the emulator: see
tests/test_pick_sim.py for whole cycles)."""

from __future__ import annotations

import math

import pytest

from launch.bench_cell import TARGETS, chart, format_results, summarize


def _bin(seed: int, n_left: int, picked: int, tried: int, cycles: list[float], stop: str, left_why: dict) -> dict:
    return {
        "seed": seed, "n_parts": 10, "n_left": n_left, "n_picked": picked, "n_tried": tried,
        "failures": {"gripper_empty": tried - picked} if tried > picked else {}, "stop_reason": stop,
        "parts_by_kind": {"hex_nut": 6, "pipe": 4}, "left_by_kind": {"hex_nut": n_left},
        "left_why": left_why, "cycle_s": cycles, "perceive_plan_ms": [100.0 * (k + 1) for k in range(len(cycles))],
        "perceive_ms": [50.0], "plan_ms": [20.0],
    }  # fmt: skip


def test_summary_counts_parts_picks_cycles_and_causes():
    bins = [
        _bin(0, 2, 8, 9, [5.0, 6.0, 7.0], "nothing_safe", {"hex_nut: collision_bin": 2}),
        _bin(1, 0, 10, 10, [4.0], "bin_empty", {}),
    ]
    s = summarize(bins)
    assert s["parts_cleared"] == pytest.approx(18 / 20) and s["pick_success_rate"] == pytest.approx(18 / 19)
    assert s["cycle_median_s"] == pytest.approx(5.5) and s["perceive_plan_median_ms"] == pytest.approx(150.0)
    assert s["failures_by_cause"] == {"gripper_empty": 1}
    assert s["stop_reasons"] == {"nothing_safe": 1, "bin_empty": 1}
    assert s["cleared_by_kind"] == {"hex_nut": "10/12", "pipe": "8/8"}
    assert s["left_by_cause"] == {"hex_nut: collision_bin": 2}
    empty = summarize([_bin(2, 10, 0, 0, [], "nothing_safe", {})])
    assert math.isnan(empty["pick_success_rate"]) and math.isnan(empty["cycle_median_s"])


def test_report_and_chart_from_partial_results():
    variants = {"oracle": {"description": "ground truth", **summarize([_bin(0, 1, 9, 9, [5.0], "nothing_safe", {})])}}
    results = {"targets": TARGETS, "seeds": list(range(30)), "seeds_done": [0], "variants": variants}
    assert "oracle" in format_results(results)
    figure = chart(results)
    assert figure.axes[0].get_title() == "1 bin(s) per variant"  # what was measured, not what was asked for
