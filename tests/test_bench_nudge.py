"""The nudge benchmark's placements and bookkeeping (its trials run in the emulator; a nudge in the loop is
tests/test_pick_sim.py's)."""

from __future__ import annotations

import numpy as np
import pytest

from launch.bench_nudge import CORNER_MARGIN_M, PARTS, chart, format_results, placement, run, summarize, wall_gap_m
from launch.cli import build_parser
from sim.cell_config import CellConfig
from sygrid.errors import ConfigError
from sygrid.objects import builtin_part


@pytest.mark.parametrize("kind", PARTS)
def test_a_placement_lies_the_drawn_gap_from_its_wall_inside_the_bin_and_away_from_the_corners(kind):
    vertices = np.asarray(builtin_part(kind).mesh.vertices)
    half = np.array(CellConfig().bin_inner_size_m[:2]) / 2.0
    walls = set()
    for seed in range(12):
        T, wall = placement(kind, seed, (0.003, 0.012))
        walls.add(wall)
        assert 0.003 - 1e-9 <= wall_gap_m(T, wall, vertices) <= 0.012 + 1e-9
        points = vertices @ T[:3, :3].T + T[:3, 3]
        assert np.all(np.abs(points[:, :2]) < half)  # inside the bin
        assert points[:, 2].min() == pytest.approx(0.001)  # set down 1 mm above the floor
        along = 1 - wall // 2
        assert abs(T[along, 3]) <= half[along] - CORNER_MARGIN_M
        # the same seed, the same placement
        np.testing.assert_array_equal(placement(kind, seed, (0.003, 0.012))[0], T)
    assert len(walls) >= 3  # the seeds spread over the walls


def test_the_summary_counts_cleared_parts_and_how_the_first_nudges_left_them():
    def trial(part, first_end, nudge, tilt, moved, cleared, nudges, cycles):
        return {
            "part": part, "first_end": first_end, "first_nudge": nudge, "tilt_deg": tilt, "moved_away_mm": moved,
            "cleared": cleared, "n_nudges": nudges, "n_cycles": cycles, "protective_stops": 0,
        }  # fmt: skip

    trials = [
        trial("hex_nut", "nudged", "done", 2.0, 20.0, True, 1, 2),  # moved out, then picked
        trial("hex_nut", "nudged", "done", 80.0, 4.0, False, 2, 4),  # tipped
        trial("hex_nut", "nudged", "done", 1.0, 0.5, False, 2, 3),  # stayed
        trial("spur_gear", "nothing_safe", None, 0.0, 0.0, False, 0, 1),  # no safe nudge
        trial("spur_gear", "picked", None, 0.0, -30.0, True, 0, 1),
    ]
    s = summarize(trials)
    assert s["hex_nut"] == {
        "trials": 3, "cleared": 1, "first_end": {"nudged": 3}, "first_nudged": 3, "tipped": 1, "stayed": 1,
        "nudges": 5, "cycles": 9, "protective_stops": 0,
    }  # fmt: skip
    assert s["spur_gear"]["first_end"] == {"nothing_safe": 1, "picked": 1} and s["spur_gear"]["first_nudged"] == 0
    assert s["all"]["trials"] == 5 and s["all"]["cleared"] == 2 and s["all"]["nudges"] == 5
    results = {"trials_per_part": 3, "gap_mm": [3.0, 12.0], "max_cycles": 4, "summary": {"statics": s}}
    assert "hex_nut" in format_results(results) and chart(results) is not None


def test_unknown_parts_variants_and_gaps_name_the_option(tmp_path):
    parser = build_parser("bench")
    for argv, option in (
        (["--parts", "hex_nut,washer"], "--parts"),
        (["--variants", "magic"], "--variants"),
        (["--gap-mm", "12,3"], "--gap-mm"),
        (["--trials", "0"], "--trials"),
    ):
        args = parser.parse_args(["bench", "--out-dir", str(tmp_path), "nudge", *argv])
        with pytest.raises(ConfigError, match=option):
            run(args, out_dir=tmp_path)
    assert not list(tmp_path.iterdir())  # nothing written
