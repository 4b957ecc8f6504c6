"""``sygrid bench cell``: the whole simulated picking cell, bin after bin, for a few perception/planner/speed settings.

For each variant and each seed: the UR controller emulator (MuJoCo backend) starts on loopback with a bin of the
scene's parts (default ``launch/scenes/pick_bin_10.json``: 10 built-in parts) dropped with the seed, and the
picking runtime (``launch.pick.open_cell``: sim camera, perception, grasp planner, ``robot.picker`` through the
stock ur_rtde client) runs until it stops. Per variant it reports:

- pick success rate: picks over attempts that moved the arm (``RunReport.success_rate`` over all bins);
- parts cleared: the share of the parts that left the bin, from the simulator's ground truth (a part can be
  left because nothing was safe to pick, not only because an attempt failed);
- cycle time: median and p90 of the robot (simulated) seconds from one look to the next, over the picks;
- perception + planning wall time per cycle: median and p90 (ms, on this machine, as it is loaded);
- failures by cause, nudges by outcome (and the robot time of a nudge cycle), stop reasons, and which parts were
  left in the bin with the planner's reason;
- per attempt outcome, how many attempts were planned on a wrong estimate (``launch.cell_attempts``: each
  estimate against the simulator's pose of the part at its plan);
- the poses the verification refused in each bin's last frame against the simulator's: how many were right, and
  the weakest of the verification's terms (depth fit, coverage, outline IoU) of those.

Targets (the realistic cell's, issue "a real cell, safely"): success >= 97 %, parts cleared >= 90 %, median cycle
<= 8 s simulated, perception + planning <= 300 ms wall; a saved result keeps the targets it was run against.
Writes ``bench/results/cell.json`` and ``cell.png`` (``cell_quick.*`` with ``--quick``, ``NAME.*`` with ``--name``,
so a sweep of more variants over fewer seeds can sit beside the headline run): parts cleared and pick
success rate against the median cycle time per variant, and the parts left by cause.

The emulator runs in real time: a bin of 10 parts takes about a minute, so 30 seeds of one variant take about half
an hour. The results are saved after every seed; ``--resume`` goes on with a stopped run from the seeds it
has not done. Variants with ``models`` perception need a trained model folder (the cell file's, or the variant's own).
"""

from __future__ import annotations

import argparse
import logging
import time
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

from launch.cell_attempts import (
    TruthAtPlan,
    attempt_pose_error,
    format_attempt_errors,
    format_refused,
    refused_pose_figures,
    summarize_attempt_errors,
    summarize_refused,
)
from launch.cell_variants import QUICK_VARIANTS, VARIANTS, Variant, cell_for_bin
from robot.cell_setup import CellSetup, load_cell_setup
from robot.pick_report import Outcome
from sygrid.bench.common import DEFAULT_RESULTS_DIR, median, percentile, replot, save_results
from sygrid.errors import ConfigError
from sygrid.fileio import read_json

log = logging.getLogger(__name__)

HOST = "127.0.0.63"  # sygrid pick uses .50, sygrid bench sim .61, the sim-in-the-loop tests .70
CELL_FILE = Path(__file__).parent / "cells" / "sim.toml"
TARGETS = {"success_rate": 0.97, "parts_cleared": 0.90, "cycle_median_s": 8.0, "perceive_plan_ms": 300.0}
QUICK_SEEDS = 2


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--seeds", type=int, default=30, help="bins per variant (seeds 0..N-1)")
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument(
        "--variants", default=None, help=f"comma-separated names from {', '.join(VARIANTS)} (default: all)"
    )
    parser.add_argument(
        "--perception", choices=("oracle", "models", "all"), default="all", help="only the variants of this kind"
    )
    parser.add_argument("--scene", type=Path, default=None, help="scene JSON (default: the cell file's)")
    parser.add_argument("--config", type=Path, default=CELL_FILE, help="the simulated cell's file")
    parser.add_argument("--max-cycles", type=int, default=25, help="per bin")
    parser.add_argument("--name", default=None, help="results file name (default: cell, or cell_quick with --quick)")
    parser.add_argument(
        "--quick", action="store_true", help=f"{QUICK_SEEDS} seeds, variants {', '.join(QUICK_VARIANTS)}"
    )
    parser.add_argument("--replot", action="store_true", help="only redraw NAME.png from the saved NAME.json")
    parser.add_argument(
        "--resume", action="store_true",
        help="go on with a stopped run: keep the bins of the saved NAME.json (same seeds, variants and scene) "
        "and run the seeds it has not done",
    )  # fmt: skip
    parser.add_argument(
        "--merge", default=None, metavar="A,B,...",
        help="run nothing: put the variants of the saved results A, B, ... (same seeds) into one NAME.json/png, "
        "each named 'A: variant'",
    )  # fmt: skip


def run(args: argparse.Namespace, out_dir: Path = DEFAULT_RESULTS_DIR) -> int:
    if args.replot or args.merge:
        return _from_saved(args, out_dir)
    names = _chosen_variants(args)
    base = load_cell_setup(args.config)
    if not base.is_sim:
        raise ConfigError(f"{args.config}: sygrid bench cell needs a simulated cell ([cell] kind = 'sim')")
    seeds = list(range(args.first_seed, args.first_seed + (QUICK_SEEDS if args.quick else args.seeds)))
    results: dict[str, Any] = {"targets": TARGETS, "seeds": seeds, "scene": str(args.scene or base.data.sim.scene)}
    name_out = args.name or ("cell_quick" if args.quick else "cell")
    bins: dict[str, list] = {name: [] for name in names}
    if args.resume:
        saved_path = out_dir / f"{name_out}.json"
        bins = bins_to_resume(read_json(saved_path, "cell benchmark results"), results, names, saved_path)
    n_done = len(next(iter(bins.values())))
    if n_done:
        results.update(seeds_done=seeds[:n_done], variants=_variant_results(bins))
    # Seeds outside, variants inside, and the results saved after each seed: every variant has seen the same bins
    # at any moment, and a run stopped early keeps what it measured (``seeds_done``).
    for k, seed in enumerate(seeds[n_done:], start=n_done):
        for name in names:
            start = time.perf_counter()
            outcome = run_bin(base, VARIANTS[name], seed, args.scene, args.max_cycles)
            bins[name].append(outcome)
            print(
                f"{name} seed {seed}: {outcome['n_parts'] - outcome['n_left']}/{outcome['n_parts']} parts out, "
                f"{outcome['n_picked']}/{outcome['n_tried']} attempts picked, {outcome['n_in_tray']} in the tray, "
                f"{outcome['stop_reason']} "
                f"({time.perf_counter() - start:.0f} s)",
                flush=True,
            )
        results.update(seeds_done=seeds[: k + 1], variants=_variant_results(bins))
        if k + 1 < len(seeds):
            figure = chart(results)
            save_results(name_out, results, figure, out_dir)
            figure.clf()  # the next seed draws a new figure
    print(format_results(results))
    json_path, png_path = save_results(name_out, results, chart(results), out_dir)
    print(f"wrote {json_path} and {png_path}")
    return 0


def _variant_results(bins: dict[str, list[dict[str, Any]]]) -> dict[str, Any]:
    return {name: {"description": VARIANTS[name].description, **summarize(b), "bins": b} for name, b in bins.items()}


def _from_saved(args: argparse.Namespace, out_dir: Path) -> int:
    """``--replot`` and ``--merge``: charts from saved results, no bins run."""
    name_out = args.name or "cell"
    if not args.merge:
        replot(name_out, chart, out_dir)
        return 0
    sources = [n.strip() for n in args.merge.split(",") if n.strip()]
    merged = merge_results({n: read_json(out_dir / f"{n}.json", "cell benchmark results") for n in sources})
    print(format_results(merged))
    json_path, png_path = save_results(name_out, merged, chart(merged), out_dir)
    print(f"wrote {json_path} and {png_path}")
    return 0


def merge_results(saved: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """One result set from several saved runs over the same bins: variants renamed ``"<run>: <variant>"``.

    Raises:
        ConfigError: the runs did not measure the same seeds, or the same scene.
    """
    first_name, first = next(iter(saved.items()))
    seeds, scene = _seeds_measured(first), first["scene"]
    variants: dict[str, Any] = {}
    for name, run in saved.items():
        if _seeds_measured(run) != seeds or run["scene"] != scene:
            raise ConfigError(
                f"bench results '{name}' measured seeds {_seeds_measured(run)} of {run['scene']}, "
                f"'{first_name}' seeds {seeds} of {scene}: only runs over the same bins can be merged"
            )
        variants.update({f"{name}: {v}": r for v, r in run["variants"].items()})
    return {"targets": first["targets"], "seeds": seeds, "seeds_done": seeds, "scene": scene, "variants": variants}


def bins_to_resume(
    saved: dict[str, Any], planned: dict[str, Any], names: list[str], path: Path
) -> dict[str, list[dict[str, Any]]]:
    """The per-variant bins of a stopped run, to go on from, checked against the run now asked for.

    Raises:
        ConfigError: the saved run (``path``) measured other seeds, variants or scene than the ones asked for.
    """
    done = _seeds_measured(saved)
    expected = {"seeds": planned["seeds"], "scene": planned["scene"], "variants": sorted(names)}
    found = {"seeds": saved["seeds"], "scene": saved["scene"], "variants": sorted(saved["variants"])}
    for key in expected:
        if found[key] != expected[key]:
            raise ConfigError(
                f"{path}: field '{key}' is {found[key]}, the run asked for {expected[key]}: "
                "--resume goes on only with the same seeds, variants and scene"
            )
    return {name: list(saved["variants"][name]["bins"][: len(done)]) for name in names}


def _seeds_measured(results: dict[str, Any]) -> list[int]:
    """The seeds a (possibly stopped) run measured."""
    return results.get("seeds_done", results["seeds"])


def _chosen_variants(args: argparse.Namespace) -> list[str]:
    if args.variants:
        names = [n.strip() for n in args.variants.split(",") if n.strip()]
        unknown = [n for n in names if n not in VARIANTS]
        if unknown:
            raise ConfigError(f"--variants: unknown {unknown}; known: {', '.join(VARIANTS)}")
    else:
        names = list(QUICK_VARIANTS if args.quick else VARIANTS)
    if args.perception != "all":
        names = [n for n in names if VARIANTS[n].perception == args.perception]
    base = load_cell_setup(args.config)
    for name in [n for n in names if VARIANTS[n].perception == "models"]:
        models_dir = base.resolve(VARIANTS[name].models_dir or base.data.perception.models_dir)
        if (models_dir / "manifest.json").is_file():
            continue
        if args.variants or args.perception == "models":
            raise ConfigError(f"variant {name} needs trained models: {models_dir}/manifest.json is missing")
        print(f"skipping {name}: no trained models in {models_dir} (manifest.json missing)")
        names.remove(name)
    if not names:
        raise ConfigError("no variant left to run (see --variants and --perception)")
    return names


def run_bin(base: CellSetup, variant: Variant, seed: int, scene: Path | None, max_cycles: int) -> dict[str, Any]:
    """One bin with one variant: the run's figures and the simulator's ground truth before and after."""
    from launch.pick import open_cell
    from sim.cell_config import CellConfig
    from sim.controller.snapshot import TICK_S
    from sygrid.objects import builtin_part

    setup = cell_for_bin(base, variant, seed, scene, HOST)
    start = time.perf_counter()
    calibration: dict[str, Any] = {}
    error = None if variant.camera_error is None else np.array(variant.camera_error, dtype=float)
    with open_cell(setup, seed, variant.perception, calibration_info=calibration, T_camera_error=error) as (
        picker,
        process,
    ):
        kinds = [name.split("_", 1)[1] for name in process.part_names()]
        obj_kind = {builtin_part(k).obj_id: k for k in set(kinds)}
        plans: list[Any] = []
        plan = picker.planner.plan
        truth = TruthAtPlan([builtin_part(k).obj_id for k in kinds])

        def keep_last(*a: Any, **k: Any) -> Any:
            plans[:] = [plan(*a, **k)]
            truth.add(process.part_poses(), [g.T_base_obj for g in plans[0].grasps])
            return plans[0]

        picker.planner.plan = keep_last
        refused: list[Any] = []  # the last frame's refused poses: parts the camera saw but could not pose

        def keep_refused(record: Any, frame: Any, result: Any, seen: Any) -> None:
            refused[:] = list(getattr(result, "refused", None) or [])

        picker.on_cycle = keep_refused
        T_start = process.part_poses()
        try:
            report = picker.run(max_cycles)
        except Exception as exc:  # an unexpected error ends this bin (StopReason.ERROR, in the report): the bench
            if picker.last_report is None:  # counts it with the rest and goes on with the next bin
                raise
            log.error("%s seed %d: the run raised %s: %s", variant.perception, seed, type(exc).__name__, exc)
            report = picker.last_report
        T_end = process.part_poses()
        thrown = process.thrown_parts()
        status = process.state()
    cell = CellConfig()
    models = {i: builtin_part(k) for i, k in obj_kind.items()}
    T_world_camera = cell.T_world_base @ picker.T_base_camera  # where the picker took the camera to be

    def pose_error(a: Any) -> dict[str, float] | None:
        if a.T_base_obj is None or a.obj_id not in models:
            return None
        return attempt_pose_error(cell.T_world_base, a.T_base_obj, a.obj_id, truth, models[a.obj_id])

    in_start, in_end = _in_bin(T_start, cell), _in_bin(T_end, cell)
    in_tray = _in_box(T_end, cell.T_world_tray, cell.tray_inner_size_m) & in_start
    left = Counter(k for k, inside in zip(kinds, in_end, strict=True) if inside)
    total = Counter(k for k, inside in zip(kinds, in_start, strict=True) if inside)
    left_why: Counter[str] = Counter()
    false_detections = 0
    if plans and report.stop_reason in ("nothing_safe", "gave_up", "too_many_failures", "max_cycles"):
        for part in plans[0].parts:
            if part.status == "outside_bin":
                continue
            if part.obj_id not in obj_kind:  # a class that is not in this bin: a false detection, not a part left
                false_detections += 1
            else:
                left_why[f"{obj_kind[part.obj_id]}: {part.status}"] += 1
    unseen = int(in_end.sum()) - sum(left_why.values())
    # left in the bin but not in the last plan: seen with every pose refused by the verification (as many as the last
    # frame refused of this bin's kinds), or hidden from the camera, or given up before planning
    n_refused = min(max(unseen, 0), sum(p.obj_id in obj_kind for p in refused))
    if n_refused:
        left_why["seen, pose refused"] += n_refused
    if unseen - n_refused > 0:
        left_why["unseen or given up"] += unseen - n_refused
    cycles = report.cycles
    return {
        "seed": seed,
        "n_parts": int(in_start.sum()),
        "n_left": int(in_end.sum()),
        "n_picked": report.n_picked,
        "n_in_tray": int(in_tray.sum()),
        # parts that left the bin but are not in the tray: where they lie (world frame, m), to trace drops
        "elsewhere": [
            {"part": kind, "xyz_m": np.round(T[:3, 3], 3).tolist()}
            for kind, T, moved in zip(kinds, T_end, in_start & ~in_end & ~in_tray, strict=True)
            if moved
        ],
        # picks held at another width than planned (the picker's note), for how often the verify rule decided
        "held_off_plan": [a.detail for a in report.attempts if a.outcome == Outcome.PICKED and a.detail],
        "n_tried": sum(a.outcome != Outcome.MOTION_REFUSED for a in report.attempts),
        "attempts_by_kind": _attempts_by_kind(report.attempts, obj_kind),
        "failures": report.failures_by_cause(),
        "nudges": [c.nudge["outcome"].value for c in cycles if c.nudge is not None],
        # looks that posed parts on depth no detection explained (PerceptionPipeline.rescue), and how many of those
        # cycles picked (nothing else was safe to pick in them)
        "rescues": sum(c.n_rescued > 0 for c in cycles),
        "rescues_picked": sum(c.n_rescued > 0 and c.picked for c in cycles),
        "failed_attempts": [
            {
                "part": obj_kind.get(a.obj_id, a.obj_id),
                "outcome": a.outcome.value,
                "stage": a.stage.value,
                "detail": a.detail,
            }
            for a in report.attempts
            if a.outcome != Outcome.PICKED
        ],
        # every attempt that moved the arm, with its estimate's error against the simulator (launch.cell_attempts)
        "attempt_pose_errors": [
            {"part": obj_kind.get(a.obj_id, a.obj_id), "outcome": a.outcome.value, "pose_error": pose_error(a)}
            for a in report.attempts
            if a.outcome != Outcome.MOTION_REFUSED
        ],
        "stop_reason": report.stop_reason.value,
        "stop_detail": report.stop_detail,
        "calibration": {k: calibration[k] for k in ("source", "error_mm", "error_deg") if k in calibration},
        # parts the physics threw (sim.throw_watch): their end poses are not to be trusted
        "thrown": thrown,
        # robot targets the physics fell too far behind to play: the arm jumped (a stall the pacing did not hold)
        "sim_dropped_targets": status.backend_dropped_targets,
        # controller ticks that held the motion for the trailing physics: simulated seconds the run lagged the clock
        # (a machine slower than real time; the arm moves slower, the cycle's wall time grows)
        "sim_paced_s": status.tick.paced_ticks * TICK_S,
        "parts_by_kind": dict(total),
        "left_by_kind": dict(left),
        "left_why": dict(left_why),
        "false_detections_last_plan": false_detections,
        # the last frame's refused poses against the simulator: right estimates the verification refused, and why
        "refused_last_frame": refused_pose_figures(T_world_camera, refused, T_end, truth.obj_ids, models),
        "cycle_s": report.sim_cycle_times_s(),
        "nudge_cycle_s": [c.sim_cycle_s for c in cycles if c.nudge is not None and c.sim_cycle_s is not None],
        "perceive_plan_ms": [1e3 * (c.stage_wall_s["perceive"] + c.stage_wall_s["plan"]) for c in cycles if c.n_poses],
        "perceive_ms": [1e3 * c.stage_wall_s["perceive"] for c in cycles if c.n_poses],
        # the pipeline's own time per look (a look taken ahead ran while the arm let go: the cycle waited less)
        "perception_ms": [c.perception_ms["total"] for c in cycles if c.n_poses and "total" in c.perception_ms],
        "looked_ahead": sum(c.looked_ahead for c in cycles),
        "plan_ms": [1e3 * c.stage_wall_s["plan"] for c in cycles if c.n_planned or c.end == "nothing_safe"],
        "wall_s": time.perf_counter() - start,
    }


def _attempts_by_kind(attempts: list[Any], obj_kind: dict[int, str]) -> dict[str, list[int]]:
    """Per part kind: ``[picked, tried]`` over the attempts that moved the arm (as ``n_tried`` counts them)."""
    out: dict[str, list[int]] = {}
    for a in attempts:
        if a.outcome == Outcome.MOTION_REFUSED:
            continue
        row = out.setdefault(str(obj_kind.get(a.obj_id, a.obj_id)), [0, 0])
        row[0] += a.outcome == Outcome.PICKED
        row[1] += 1
    return out


def _in_bin(T_world_obj: np.ndarray, cell: Any) -> np.ndarray:
    """``(n,)`` which parts lie in the cell's bin (inner footprint, below twice its height)."""
    return _in_box(T_world_obj, cell.T_world_bin, cell.bin_inner_size_m)


def _in_box(T_world_obj: np.ndarray, T_world_box: np.ndarray, inner_size_m: tuple[float, ...]) -> np.ndarray:
    """``(n,)`` which parts lie in an open box (a bin, the tray; pose of its inner floor's centre): inside its inner
    footprint, below twice its height."""
    p = (np.linalg.inv(T_world_box) @ T_world_obj)[:, :3, 3]
    half = np.array(inner_size_m) / 2
    return (np.abs(p[:, 0]) < half[0]) & (np.abs(p[:, 1]) < half[1]) & (p[:, 2] > -0.01) & (p[:, 2] < 4 * half[2])


def summarize(bins: list[dict[str, Any]]) -> dict[str, Any]:
    """A variant's figures over its bins (see the module docstring)."""
    n_parts, n_left = sum(b["n_parts"] for b in bins), sum(b["n_left"] for b in bins)
    n_picked, n_tried = sum(b["n_picked"] for b in bins), sum(b["n_tried"] for b in bins)
    cycle = [t for b in bins for t in b["cycle_s"]]
    pp = [t for b in bins for t in b["perceive_plan_ms"]]
    failures, stops, left_why, nudges = Counter(), Counter(), Counter(), Counter()
    by_kind_total, by_kind_left = Counter(), Counter()
    for b in bins:
        failures.update(b["failures"])
        nudges.update(b.get("nudges", []))
        stops[b["stop_reason"]] += 1
        left_why.update(b["left_why"])
        by_kind_total.update(b["parts_by_kind"])
        by_kind_left.update(b["left_by_kind"])
    return {
        "pick_success_rate": n_picked / n_tried if n_tried else float("nan"),
        "parts_cleared": 1.0 - n_left / n_parts if n_parts else float("nan"),
        "n_parts": n_parts,
        "n_left": n_left,
        "n_picked": n_picked,
        # ground truth: parts from the bin that lie in the tray at the end (a part the picker counts as picked that
        # fell on the way is missing here)
        "n_in_tray": sum(b.get("n_in_tray", 0) for b in bins),
        "n_held_off_plan": sum(len(b.get("held_off_plan", [])) for b in bins),
        "out_of_bin_not_in_tray": [{"seed": b["seed"], **e} for b in bins for e in b.get("elsewhere", [])],
        "thrown_parts": [{"seed": b["seed"], **t} for b in bins for t in b.get("thrown", [])],
        # the physics against the clock: seconds the controller held the arm for it, targets it never played
        "sim_paced_s": sum(b.get("sim_paced_s", 0.0) for b in bins),
        "sim_dropped_targets": sum(b.get("sim_dropped_targets", 0) for b in bins),
        "n_attempts": n_tried,
        "cycle_median_s": median(cycle),
        "cycle_p90_s": percentile(cycle, 90),
        "perceive_plan_median_ms": median(pp),
        "perceive_plan_p90_ms": percentile(pp, 90),
        "perceive_median_ms": median([t for b in bins for t in b["perceive_ms"]]),
        "plan_median_ms": median([t for b in bins for t in b["plan_ms"]]),
        "perception_median_ms": median([t for b in bins for t in b.get("perception_ms", [])]),
        "n_looked_ahead": sum(b.get("looked_ahead", 0) for b in bins),
        "failures_by_cause": dict(failures),
        "nudges_by_outcome": dict(nudges),
        "rescues": sum(b.get("rescues", 0) for b in bins),
        "rescues_picked": sum(b.get("rescues_picked", 0) for b in bins),
        "nudge_cycle_median_s": median([t for b in bins for t in b.get("nudge_cycle_s", [])]),
        "camera_pose_error_median_mm": median([b["calibration"]["error_mm"] for b in bins if _calibrated(b)]),
        "camera_pose_error_median_deg": median([b["calibration"]["error_deg"] for b in bins if _calibrated(b)]),
        "stop_reasons": dict(stops),
        "left_by_cause": dict(left_why.most_common()),
        "false_detections_last_plan": sum(b.get("false_detections_last_plan", 0) for b in bins),
        "refused_last_frames": summarize_refused([r for b in bins for r in b.get("refused_last_frame", [])]),
        "attempts_by_estimate": summarize_attempt_errors([a for b in bins for a in b.get("attempt_pose_errors", [])]),
        "cleared_by_kind": {
            k: f"{by_kind_total[k] - by_kind_left[k]}/{by_kind_total[k]}" for k in sorted(by_kind_total)
        },
    }


def _calibrated(bin_: dict[str, Any]) -> bool:
    """The bin's camera pose came with an error against the true pose (a simulated cell's)."""
    return "error_mm" in bin_.get("calibration", {})


def format_results(results: dict[str, Any]) -> str:
    t = results["targets"]
    lines = [
        f"targets: pick success >= {100 * t['success_rate']:.0f} %"
        + (f", parts cleared >= {100 * t['parts_cleared']:.0f} %" if "parts_cleared" in t else "")
        + f", median cycle <= {t['cycle_median_s']:g} s "
        f"simulated, perception + planning <= {t['perceive_plan_ms']:g} ms wall",
        f"{'variant':<18}{'cleared':>9}{'success':>9}{'cycle p50':>11}{'cycle p90':>11}{'p+p p50':>10}{'p+p p90':>10}",
    ]
    for name, r in results["variants"].items():
        lines.append(
            f"{name:<18}{100 * r['parts_cleared']:>8.0f}%{100 * r['pick_success_rate']:>8.0f}%"
            f"{r['cycle_median_s']:>10.2f}s{r['cycle_p90_s']:>10.2f}s{r['perceive_plan_median_ms']:>8.0f}ms"
            f"{r['perceive_plan_p90_ms']:>8.0f}ms"
        )
    for name, r in results["variants"].items():
        if "perception_median_ms" in r:
            lines.append(
                f"{name}: perception {r['perception_median_ms']:.0f} ms median per look (the pipeline's own time), "
                f"the cycle waiting {r['perceive_median_ms']:.0f} ms for it; {r['n_looked_ahead']} looks taken at the "
                "place pose and perceived while the arm let go"
            )
        lines.append(
            f"{name}: failures {r['failures_by_cause'] or 'none'}; nudges {r.get('nudges_by_outcome') or 'none'}; "
            f"rescues {r.get('rescues', '-')} ({r.get('rescues_picked', '-')} picked); stops {r['stop_reasons']}"
        )
        lines.append(
            f"{name}: cleared by kind {r['cleared_by_kind']}; picked {r['n_picked']} (held at another width than "
            f"planned: {r.get('n_held_off_plan', '-')}), in the tray {r.get('n_in_tray', '-')}"
        )
        lines.append(f"{name}: left in the bin {r['left_by_cause'] or 'nothing'}")
        if r.get("attempts_by_estimate"):
            lines.append(format_attempt_errors(name, r["attempts_by_estimate"]))
        if r.get("refused_last_frames", {}).get("n"):
            lines.append(format_refused(name, r["refused_last_frames"]))
        thrown = r.get("thrown_parts", [])
        lines.append(
            f"{name}: parts thrown by the physics: {len(thrown)}"
            + "".join(f"; seed {t['seed']}: {t['part']} at {t['speed_m_s']:.0f} m/s" for t in thrown)
        )
        if "sim_paced_s" in r:  # results saved before the controller paced its motion have no such field
            lines.append(
                f"{name}: physics behind the clock: arm held {r['sim_paced_s']:.1f} s, "
                f"{r['sim_dropped_targets']} targets dropped"
            )
        lines.append(
            f"{name}: camera pose {r.get('camera_pose_error_median_mm', float('nan')):.2f} mm / "
            f"{r.get('camera_pose_error_median_deg', float('nan')):.3f} deg from the true pose (median over the bins)"
        )
    return "\n".join(lines)


def chart(results: dict[str, Any]):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    variants = results["variants"]
    fig, (ax, ax_left) = plt.subplots(1, 2, figsize=(14, 5), gridspec_kw={"width_ratios": [1, 1.2]})
    for i, (name, r) in enumerate(variants.items()):
        x = r["cycle_median_s"]
        ax.scatter([x], [100 * r["parts_cleared"]], marker="s", s=50)
        ax.scatter([x], [100 * r["pick_success_rate"]], marker="o", s=50, facecolors="none", edgecolors="k")
        # staggered: variants that pick alike sit on top of each other
        ax.annotate(
            name, (x, 100 * r["parts_cleared"]), textcoords="offset points", xytext=(6, -4 - 10 * (i % 4)), fontsize=8
        )
    targets = results["targets"]  # the run's own: a redrawn chart shows what it was measured against
    ax.axhline(100 * targets["success_rate"], color="grey", ls=":", lw=1)
    if "parts_cleared" in targets:
        ax.axhline(100 * targets["parts_cleared"], color="C0", ls=":", lw=1)
    ax.axvline(targets["cycle_median_s"], color="grey", ls=":", lw=1)
    ax.scatter([], [], marker="s", color="C0", label="parts cleared (ground truth)")
    ax.scatter([], [], marker="o", facecolors="none", edgecolors="k", label="pick success rate (picks / attempts)")
    ax.set(xlabel="median cycle time [simulated s]", ylabel="%", ylim=(0, 105),
           title=f"{len(_seeds_measured(results))} bin(s) per variant")  # fmt: skip
    ax.legend(fontsize=8, loc="lower left")
    ax.grid(alpha=0.3)
    causes = sorted({c for r in variants.values() for c in r["left_by_cause"]})
    names = list(variants)
    bottom = np.zeros(len(names))
    colours = matplotlib.colormaps["tab20"].colors  # more causes than tab10's colours
    for k, cause in enumerate(causes):
        vals = np.array([variants[n]["left_by_cause"].get(cause, 0) / max(variants[n]["n_parts"], 1) for n in names])
        hatch = (None, "//", "..")[k // len(colours) % 3]  # past 20 causes the colours come back hatched
        ax_left.barh(names, 100 * vals, left=100 * bottom, label=cause, color=colours[k % len(colours)], hatch=hatch)
        bottom += vals
    ax_left.set(xlabel="% of the parts left in the bin, by part and planner reason", title="what was left")
    if causes:
        ax_left.legend(fontsize=7, ncols=3, loc="upper center", bbox_to_anchor=(0.5, -0.14))
    fig.suptitle("sygrid bench cell: simulated UR5e cell, pick until the bin is empty or nothing is safe")
    fig.tight_layout()
    return fig
