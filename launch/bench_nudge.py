"""``sygrid bench nudge``: parts lying too close to a wall for the fingers, nudged in the simulated cell.

A nudge drags a part the gripper cannot take away from a wall (``robot.nudge``). Per trial (seeded, the same for
every variant): one built-in part lies in its resting pose near a wall of the bin (its gap to the wall uniform in
``--gap-mm``, a random wall, position along it at least ``CORNER_MARGIN_M`` from the corners, a random turn about
the vertical), every other part parked out of the cell; the picker (ground-truth poses: the nudge is measured here,
not perception) runs up to ``--max-cycles`` cycles with the variant's ``NudgeConfig``. Per variant and part it
reports the parts cleared (picked out of the bin), the first cycle's end, how the first nudge left the part
(tipped: its up axis turned by more than ``TIP_DEG``; stayed: moved less than ``STAYED_MM`` away from the wall)
and the nudges per trial.

Variants: ``straight`` (drags straight away from the wall only, no tipping check: the planner before it had one),
``statics_0.5`` (the tipping check with the simulated floor's friction, 0.5) and ``statics`` (the planner's
default). Writes ``bench/results/nudge.json`` and ``nudge.png``; the emulator runs in real time (a trial takes
up to half a minute).
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import tempfile
import time
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

from robot.cell_setup import load_cell_setup
from robot.nudge import NudgeConfig, NudgePlanner, wall_gaps_m
from sygrid.bench.common import DEFAULT_RESULTS_DIR, replot, save_results
from sygrid.errors import ConfigError
from sygrid.objects import builtin_part
from sygrid.transforms import invert, make_T, rotation_about, transform_points

log = logging.getLogger(__name__)

HOST = "127.0.0.67"  # bench cell's emulator listens on .63, the stability cell axes' proxy on .64
CELL_FILE = Path(__file__).parent / "cells" / "sim.toml"
PARTS = ("hex_nut", "spur_gear", "hex_bolt", "pipe")
# the resting pose of each part on the floor, before the turn about the vertical: flat, or lying on its side
_LYING = {"hex_nut": False, "spur_gear": False, "hex_bolt": True, "pipe": True}
VARIANTS: dict[str, NudgeConfig] = {
    "straight": NudgeConfig(floor_friction=0.0, roll_deg=90.0, slants_deg=(0.0,), press_sideways=(0.0,)),
    "statics_0.5": NudgeConfig(floor_friction=0.5),
    "statics": NudgeConfig(),
}
CORNER_MARGIN_M = 0.05
TIP_DEG = 30.0
STAYED_MM = 3.0
_SETTLE_S = 0.5  # a placed part comes to rest within this (it is set down 1 mm above the floor)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--trials", type=int, default=8, help="trials per part (seeds 0..N-1)")
    parser.add_argument("--parts", default=",".join(PARTS), help=f"comma-separated, from {', '.join(PARTS)}")
    parser.add_argument("--variants", default=",".join(VARIANTS), help=f"comma-separated, from {', '.join(VARIANTS)}")
    parser.add_argument("--gap-mm", default="3,12", help="the part's gap to the wall: lo,hi (mm)")
    parser.add_argument("--max-cycles", type=int, default=4, help="per trial")
    parser.add_argument("--replot", action="store_true", help="redraw the chart from the saved JSON")


def run(args: argparse.Namespace, out_dir: Path = DEFAULT_RESULTS_DIR) -> int:
    if args.replot:
        replot("nudge", chart, out_dir)
        return 0
    parts, variants = _names(args.parts, PARTS, "--parts"), _names(args.variants, VARIANTS, "--variants")
    gap = tuple(float(g) * 1e-3 for g in args.gap_mm.split(","))
    if len(gap) != 2 or not 0 < gap[0] <= gap[1]:
        raise ConfigError(f"--gap-mm: expected lo,hi with 0 < lo <= hi, got {args.gap_mm!r}")
    trials = [(kind, seed) for kind in parts for seed in range(args.trials)]
    results: dict[str, Any] = {
        "trials_per_part": args.trials, "gap_mm": [1e3 * g for g in gap], "max_cycles": args.max_cycles,
        "variants": {name: {"config": _config_summary(VARIANTS[name]), "trials": []} for name in variants},
    }  # fmt: skip
    if args.trials < 1 or args.max_cycles < 1:
        raise ConfigError(f"--trials and --max-cycles must be >= 1, got {args.trials} and {args.max_cycles}")
    meshes = {kind: np.asarray(builtin_part(kind).mesh.vertices) for kind in parts}
    start = time.perf_counter()
    with (
        tempfile.TemporaryDirectory(prefix="sygrid_nudge_") as folder,
        _cell(parts, Path(folder)) as (
            picker,
            process,
        ),
    ):
        for kind, seed in trials:
            T_bin_part, wall = placement(kind, seed, gap)
            for name in variants:
                picker.nudger = NudgePlanner(picker.planner, VARIANTS[name])
                trial = run_trial(picker, process, parts.index(kind), T_bin_part, wall, meshes[kind], args.max_cycles)
                results["variants"][name]["trials"].append({"part": kind, "seed": seed, **trial})
                print(f"{name} {kind} seed {seed}: {_trial_line(trial)}")
    results["wall_s"] = time.perf_counter() - start
    results["summary"] = {name: summarize(v["trials"]) for name, v in results["variants"].items()}
    print(format_results(results))
    json_path, png_path = save_results("nudge", results, chart(results), out_dir)
    print(f"wrote {json_path} and {png_path}")
    return 0


def _names(text: str, known: Any, option: str) -> list[str]:
    names = [n.strip() for n in text.split(",") if n.strip()]
    unknown = [n for n in names if n not in known]
    if not names or unknown:
        raise ConfigError(f"{option}: unknown {unknown or 'nothing given'}; expected names from {', '.join(known)}")
    return names


def _config_summary(cfg: NudgeConfig) -> dict[str, Any]:
    return {
        "floor_friction": cfg.floor_friction, "roll_deg": cfg.roll_deg, "slants_deg": cfg.slants_deg,
        "press_sideways": cfg.press_sideways,
    }  # fmt: skip


def _cell(parts: list[str], folder: Path):
    """The simulated cell (``launch/cells/sim.toml``, oracle perception) with one of each part, on ``HOST``; its
    scene file is written into ``folder``."""
    from launch.cell_variants import VARIANTS as CELL_VARIANTS
    from launch.cell_variants import cell_for_bin
    from launch.pick import open_cell

    scene = folder / "scene.json"
    scene.write_text(json.dumps({"name": "nudge", "objects": [{"builtin": k, "count": 1} for k in parts]}))
    setup = cell_for_bin(load_cell_setup(CELL_FILE), CELL_VARIANTS["oracle"], 0, scene, HOST)
    return open_cell(setup, 0, "oracle")


def placement(kind: str, seed: int, gap_m: tuple[float, float]) -> tuple[np.ndarray, int]:
    """``(T_bin_part, wall)``: the part in its resting pose (1 mm above the floor), its nearest point a seeded
    uniform gap from one wall (0: +x, 1: -x, 2: +y, 3: -y; the simulated cell's bin frame)."""
    from sim.cell_config import CellConfig

    rng = np.random.default_rng(seed)
    half = np.array(CellConfig().bin_inner_size_m[:2]) / 2.0
    wall = int(rng.integers(4))
    axis, sign = wall // 2, (1.0 if wall % 2 == 0 else -1.0)
    R = rotation_about((0.0, 0.0, 1.0), rng.uniform(0.0, 2.0 * math.pi))
    if _LYING[kind]:
        R = R @ rotation_about((1.0, 0.0, 0.0), math.pi / 2.0)
    vertices = np.asarray(builtin_part(kind).mesh.vertices) @ R.T
    t = np.zeros(3)
    t[2] = 0.001 - vertices[:, 2].min()
    reach = float((sign * vertices[:, axis]).max())  # how far the part reaches toward the wall from its origin
    t[axis] = sign * (half[axis] - rng.uniform(*gap_m) - reach)
    along = half[1 - axis] - CORNER_MARGIN_M
    t[1 - axis] = rng.uniform(-along, along)
    return make_T(R, t), wall


def run_trial(
    picker: Any, process: Any, index: int, T_bin_part: np.ndarray, wall: int, vertices: np.ndarray, max_cycles: int
) -> dict:
    """One trial: the part (mesh ``vertices``) placed, the others parked; the first cycle, how it left the part
    (gap to ``wall``, tilt), the rest of the run."""
    from sim.cell_config import CellConfig

    cfg = CellConfig()
    picker.robot.recover()
    picker.gripper.open()
    picker.arm.to_observe()
    picker.memory.clear()
    T = process.part_poses()
    parked = [i for i in range(len(T)) if i != index]
    for i in parked:
        T[i] = make_T(t=(5.0 + 0.5 * i, 5.0, 3.0))
    T[index] = cfg.T_world_bin @ T_bin_part
    process.place_parts(T, held=parked)
    time.sleep(_SETTLE_S)
    before = invert(cfg.T_world_bin) @ process.part_poses()[index]
    first = picker.run(max_cycles=1)
    time.sleep(_SETTLE_S)
    after = invert(cfg.T_world_bin) @ process.part_poses()[index]
    go_on = max_cycles > 1 and first.stop_reason == "max_cycles"  # not picked, not stopped: nudged, or failed
    rest = picker.run(max_cycles=max_cycles - 1) if go_on else None
    cycles = first.cycles + (rest.cycles if rest else [])
    nudge = first.cycles[0].nudge
    gap_before, gap_after = wall_gap_m(before, wall, vertices), wall_gap_m(after, wall, vertices)
    return {
        "gap_mm": 1e3 * gap_before,
        "first_end": str(first.cycles[0].end.value),
        "first_nudge": None if nudge is None else str(nudge["outcome"].value),
        # how the first nudge left the part (None: the first cycle was no nudge)
        "tilt_deg": None if nudge is None else _tilt_deg(before, after),
        "moved_away_mm": None if nudge is None else 1e3 * (gap_after - gap_before),
        "cleared": bool(first.n_picked + (rest.n_picked if rest else 0) > 0),
        "n_nudges": sum(c.nudge is not None for c in cycles),
        "n_cycles": len(cycles),
        "protective_stops": sum(c.nudge is not None and c.nudge["outcome"] == "protective_stop" for c in cycles)
        + sum(a.outcome == "protective_stop" for c in cycles for a in c.attempts),
    }


def wall_gap_m(T_bin_part: np.ndarray, wall: int, vertices: np.ndarray) -> float:
    """The gap (m) between a part (its mesh ``vertices`` in its own frame, posed at ``T_bin_part``) and a wall."""
    from sim.cell_config import CellConfig

    half = np.array(CellConfig().bin_inner_size_m[:2]) / 2.0
    return float(wall_gaps_m(transform_points(T_bin_part, vertices), half)[wall])


def _tilt_deg(T_before: np.ndarray, T_after: np.ndarray) -> float:
    """How far the part's axis that pointed up before turned away from the vertical (degrees)."""
    up_in_part = T_before[:3, :3].T @ np.array([0.0, 0.0, 1.0])
    return float(np.degrees(np.arccos(np.clip((T_after[:3, :3] @ up_in_part)[2], -1.0, 1.0))))


def _trial_line(t: dict) -> str:
    nudge = "" if t["first_nudge"] is None else f" ({t['first_nudge']}: tilt {t['tilt_deg']:.0f} deg, moved "
    nudge += "" if t["first_nudge"] is None else f"{t['moved_away_mm']:+.1f} mm)"
    return (
        f"gap {t['gap_mm']:.1f} mm, first {t['first_end']}{nudge}, "
        f"{'cleared' if t['cleared'] else 'left'} after {t['n_cycles']} cycles"
    )


def summarize(trials: list[dict]) -> dict[str, Any]:
    """Per part and over all: trials, cleared, first cycle a nudge, of those tipped / stayed, nudges, stops."""
    out: dict[str, Any] = {}
    for part in [*sorted({t["part"] for t in trials}), "all"]:
        rows = [t for t in trials if part in ("all", t["part"])]
        nudged = [t for t in rows if t["first_nudge"] == "done"]
        out[part] = {
            "trials": len(rows),
            "cleared": sum(t["cleared"] for t in rows),
            "first_end": dict(Counter(t["first_end"] for t in rows)),
            "first_nudged": len(nudged),
            "tipped": sum(t["tilt_deg"] > TIP_DEG for t in nudged),
            "stayed": sum(t["moved_away_mm"] < STAYED_MM and t["tilt_deg"] <= TIP_DEG for t in nudged),
            "nudges": sum(t["n_nudges"] for t in rows),
            "cycles": sum(t["n_cycles"] for t in rows),
            "protective_stops": sum(t["protective_stops"] for t in rows),
        }
    return out


def format_results(results: dict[str, Any]) -> str:
    lines = ["variant       part       cleared  first nudged  tipped  stayed  nudges  cycles  stops"]
    for name, summary in results["summary"].items():
        for part, s in summary.items():
            lines.append(
                f"{name:<13} {part:<10} {s['cleared']:>3}/{s['trials']:<3} {s['first_nudged']:>8}      "
                f"{s['tipped']:>5}  {s['stayed']:>6}  {s['nudges']:>6}  {s['cycles']:>6}  {s['protective_stops']:>5}"
            )
    return "\n".join(lines)


def chart(results: dict[str, Any]):
    """Per variant and part: the share cleared, and how the first nudges left the parts (turned over, not moved)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(results["summary"])
    parts = [p for p in next(iter(results["summary"].values())) if p != "all"] + ["all"]
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4))
    width = 0.8 / max(len(names), 1)
    x = np.arange(len(parts))
    for k, name in enumerate(names):
        s = results["summary"][name]
        ax1.bar(x + k * width, [s[p]["cleared"] / max(s[p]["trials"], 1) for p in parts], width, label=name)
        nudged = np.array([max(s[p]["first_nudged"], 1) for p in parts], dtype=float)
        tipped = np.array([s[p]["tipped"] for p in parts]) / nudged
        stayed = np.array([s[p]["stayed"] for p in parts]) / nudged
        ax2.bar(x + k * width, tipped, width, color=f"C{k}", label=f"{name}: turned over")
        ax2.bar(x + k * width, stayed, width, bottom=tipped, color=f"C{k}", alpha=0.4, hatch="//",
                label=f"{name}: not moved")  # fmt: skip
    titles = (ax1, "parts cleared"), (ax2, "first nudges: the part turned over (rolled, tipped) or not moved")
    for ax, title in titles:
        ax.set_xticks(x + width * (len(names) - 1) / 2, parts)
        ax.set_ylim(0, 1.05)
        ax.set_title(title)
    ax1.legend(fontsize=8, loc="lower left")
    ax2.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.0, 1.0))
    fig.suptitle(
        f"sygrid bench nudge: {results['trials_per_part']} trials per part, gap to the wall "
        f"{results['gap_mm'][0]:.0f}-{results['gap_mm'][1]:.0f} mm, up to {results['max_cycles']} cycles"
    )
    fig.tight_layout()
    return fig
