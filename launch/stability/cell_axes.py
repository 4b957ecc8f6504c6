"""The cell axes: bins of the simulated cell (``launch.bench_cell.run_bin``: the UR controller emulator, the picking
runtime through the stock ur_rtde client) with one thing made worse per point.

- ``timing`` (issue 25, axis 8): the robot's and gripper's connections through a ``DelayProxy`` adding a one-way
  latency with jitter (half the latency, uniform) on loopback.
- ``calibration_mm`` / ``calibration_deg`` (axis 6): a hand-eye error composed onto the camera pose (in the camera
  frame: a translation, or a rotation about the camera's centre, each along a direction drawn from the seed); the
  calibration is otherwise the camera's true pose.
- ``clutter_cell`` (axis 2, in the cell): the cell's scene with N parts per bin.

Methods: "pick success" (picks over the attempts that moved the arm; per part family, thin parts being the pinch
grasps), "parts cleared" (parts out of the bin, ground truth, of those the cycles could clear) and "runs completed"
(a bin run that ended without an error stop: a watchdog, a lost link or an exception). The perception is
``Options.cell_perception`` ("oracle": the ground truth, so that the grasps and the robot link alone are measured).
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import numpy as np

from launch.stability.failure import Criterion
from launch.stability.options import Options
from launch.stability.perception_pass import part_family
from launch.stability.sweep import Axis, Measurement, Method, Point
from sygrid.errors import ConfigError

log = logging.getLogger(__name__)

CELL_CRITERION = Criterion(fraction=0.8, floor=0.5)
PROXY_HOST = "127.0.0.64"  # bench_cell's emulator listens on .63
ABORTED = ("error", "needs_operator", "interrupted")
STARVED_RETRIES = 1  # a starved bin is run again this many times before the point is refused
PICKS, CLEARED, COMPLETED = "pick success", "parts cleared", "runs completed"
# Parts cleared is a whole-bin figure: a family's share of the bin's parts is not what the cycles could clear of it
# (per family, see the pick success).
CELL_METHODS = (Method(PICKS, PICKS), Method(CLEARED, CLEARED, grouped=False), Method(COMPLETED, COMPLETED))


def _family_of(kind: str) -> str:
    from sygrid.objects import builtin_part

    try:
        return part_family(builtin_part(kind))
    except Exception:  # a kind that is not a built-in part
        return "?"


def bin_measurements(
    outcome: dict[str, Any] | None, max_cycles: int, error: str | None = None
) -> dict[str, Measurement]:
    """A bin run's methods (see the module docstring) from ``bench_cell.run_bin``'s outcome of at most
    ``max_cycles`` cycles; None with ``error``: the run raised (no attempt, not completed). Parts cleared counts of
    the parts the cycles could clear (one a cycle: ``min(parts, max_cycles)``), per family of the parts in the
    bin."""
    if outcome is None:
        return {PICKS: Measurement(0, 0, extra={"error": error}), CLEARED: Measurement(0, 0, extra={"error": error}),
                COMPLETED: Measurement(0, 1, extra={"error": error})}  # fmt: skip
    picks: dict[str, list[int]] = {}
    for kind, (k, n) in outcome.get("attempts_by_kind", {}).items():
        for g in (f"family {_family_of(kind)}", f"part {kind}"):
            row = picks.setdefault(g, [0, 0])
            row[0], row[1] = row[0] + k, row[1] + n
    cleared: dict[str, list[int]] = {}
    for kind, n in outcome["parts_by_kind"].items():
        left = outcome["left_by_kind"].get(kind, 0)
        for g in (f"family {_family_of(kind)}", f"part {kind}"):
            row = cleared.setdefault(g, [0, 0])
            row[0], row[1] = row[0] + n - left, row[1] + n
    reachable = min(outcome["n_parts"], max_cycles)
    extra = {k: outcome[k] for k in ("stop_reason", "stop_detail", "failures", "wall_s") if k in outcome}
    extra["cycle_median_s"] = float(np.median(outcome["cycle_s"])) if outcome.get("cycle_s") else None
    completed = outcome["stop_reason"] not in ABORTED
    return {
        PICKS: Measurement(outcome["n_picked"], outcome["n_tried"], picks, extra),
        CLEARED: Measurement(min(outcome["n_parts"] - outcome["n_left"], reachable), reachable, cleared, extra),
        COMPLETED: Measurement(int(completed), 1, extra=extra),
    }


def run_cell_bin(
    opts: Options, seed: int, scene: Path | None = None, max_cycles: int | None = None, **variant: Any
) -> dict[str, Measurement]:
    """One bin of the cell file's setup with the variant's fields (``launch.cell_variants.Variant``), at most
    ``max_cycles`` (default ``opts.max_cycles``) cycles; an exception (the runtime could not connect, or a stop it
    raises) is a run that did not complete.

    A bin that the machine starved (``starved``: the physics fell behind real time, or the camera's render process
    did not answer) measures the machine, not the axis: it is run again, up to ``STARVED_RETRIES`` times, and then
    refused (ConfigError), so that no such point is saved."""
    from launch.bench_cell import run_bin
    from launch.cell_variants import Variant
    from robot.cell_setup import load_cell_setup

    base = load_cell_setup(opts.cell_config)
    v = Variant(opts.cell_perception, "stability point", calibration="sim", **variant)
    cycles = max_cycles or opts.max_cycles
    why = None
    for attempt in range(1 + STARVED_RETRIES):
        outcome, error = None, None
        try:
            outcome = run_bin(base, v, seed, scene, cycles)
        except Exception as exc:  # the point's failure is the measurement
            error = f"{type(exc).__name__}: {exc}"
        why = starved(outcome, error)
        if why is None:
            return bin_measurements(outcome, cycles, error)
        if attempt < STARVED_RETRIES:
            log.warning("seed %d: %s; the bin is run again (%d of %d)", seed, why, attempt + 1, STARVED_RETRIES)
    raise ConfigError(
        f"cell bin (seed {seed}, {variant}): {why}, {1 + STARVED_RETRIES} times: the machine is too busy for "
        "real-time simulation; run the cell axes with nothing else on the machine (the point was not saved)"
    )


def starved(outcome: dict[str, Any] | None, error: str | None) -> str | None:
    """Why a bin run measured a starved machine rather than the cell (None: it did not): robot targets dropped by
    a physics that fell behind real time, or the render process not answering in time."""
    if outcome is not None and outcome.get("sim_dropped_targets", 0) > 0:
        return f"the simulation fell behind real time ({outcome['sim_dropped_targets']} robot targets dropped)"
    from sim.render_process import NO_ANSWER

    text = error or (outcome or {}).get("stop_detail") or ""
    return f"the camera's {NO_ANSWER} ({text})" if NO_ANSWER in text else None


def _cell_settings(opts: Options, **more: Any) -> dict[str, Any]:
    return {"cell_config": str(opts.cell_config), "max_cycles": opts.max_cycles, "perception": opts.cell_perception,
            **more}  # fmt: skip


def timing_axis(opts: Options) -> Axis:
    from launch.bench_cell import HOST
    from launch.stability.delay_proxy import DelayProxy
    from sim.controller import ControllerPorts

    ports = ControllerPorts()
    port_list = (ports.rtde, ports.dashboard, *ports.script, ports.gripper)
    latencies = (0.0, 50.0) if opts.quick else (0.0, 5.0, 20.0, 50.0, 100.0, 200.0, 400.0, 600.0, 800.0, 1600.0)

    def measure(point: Point, seed: int) -> dict[str, Measurement]:
        latency, jitter = point.params["latency_ms"] / 1e3, point.params["jitter_ms"] / 1e3
        with DelayProxy(PROXY_HOST, HOST, port_list, latency, jitter, seed):
            return run_cell_bin(opts, seed, robot_host=PROXY_HOST)

    return Axis(
        name="timing", title="Controller timing", x_label="added one-way latency [ms] (jitter: half of it, uniform)",
        points=tuple(Point(f"{ms:g}ms", ms, {"latency_ms": ms, "jitter_ms": ms / 2}) for ms in latencies),
        methods=CELL_METHODS, measure=measure,
        seeds=opts.seeds_or((0,) if opts.quick else (0, 1, 2)), criterion=CELL_CRITERION,
        summary="the robot link holds to {x} ms of one-way latency", unit="ms", settings=_cell_settings(opts),
        description="The runtime's robot and gripper connections through a loopback proxy delaying each chunk both "
        "ways; a bin of the simulated cell per (point, seed), until ur_rtde's watchdog or the pick cycle fails.",
    )  # fmt: skip


def camera_error(seed: int, mm: float = 0.0, deg: float = 0.0) -> tuple[tuple[float, ...], ...]:
    """A 4x4 error (as nested tuples): ``mm`` along and ``deg`` about unit directions drawn from ``seed``."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng([25, seed])
    direction, axis = (v / np.linalg.norm(v) for v in rng.normal(size=(2, 3)))
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(np.radians(deg) * axis).as_matrix()
    T[:3, 3] = direction * mm / 1e3
    return tuple(tuple(float(x) for x in row) for row in T)


def calibration_axis(opts: Options, unit: str) -> Axis:
    if unit == "mm":
        values = (0.0, 4.0) if opts.quick else (0.0, 1.0, 2.0, 4.0, 6.0, 10.0)
    else:
        values = (0.0, 1.0) if opts.quick else (0.0, 0.1, 0.25, 0.5, 1.0, 2.0)

    def measure(point: Point, seed: int) -> dict[str, Measurement]:
        error = camera_error(seed, **{unit: point.x})
        return run_cell_bin(opts, seed, camera_error=error)

    what = "translation" if unit == "mm" else "rotation about the camera's centre"
    return Axis(
        name=f"calibration_{unit}", title=f"Calibration error ({unit})", x_label=f"hand-eye {what} error [{unit}]",
        points=tuple(Point(f"{v:g}{unit}", v, {unit: v}) for v in values),
        methods=CELL_METHODS, measure=measure,
        seeds=opts.seeds_or((0,) if opts.quick else (0, 1, 2)), criterion=CELL_CRITERION,
        summary=f"picks hold to {{x}} {unit} of calibration error", unit=unit, settings=_cell_settings(opts),
        description=f"A {what} error added to the camera pose the cell believes (its direction drawn from the "
        "seed); a bin of the simulated cell per (point, seed); per part family (thin: the pinch grasps).",
    )  # fmt: skip


def clutter_cell_axis(opts: Options) -> Axis:
    from launch.stability.generated import spread_counts
    from robot.cell_setup import load_cell_setup

    counts = (5, 15) if opts.quick else (5, 10, 15, 20, 30, 40)
    setup = load_cell_setup(opts.cell_config)
    base_scene = setup.resolve(setup.data.sim.scene)

    def measure(point: Point, seed: int) -> dict[str, Measurement]:
        scene = json.loads(Path(base_scene).read_text())
        objects = scene["objects"]
        for obj, n in zip(objects, spread_counts([int(o.get("count", 1)) for o in objects], point.params["parts"]),
                          strict=True):  # fmt: skip
            obj["count"] = n
        path = opts.cache_dir / "scenes" / f"cell_{point.params['parts']}_parts.json"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(scene))
        cycles = opts.max_cycles if opts.quick else max(opts.max_cycles, int(1.5 * point.params["parts"]))
        return run_cell_bin(opts, seed, scene=path, max_cycles=cycles)

    return Axis(
        name="clutter_cell", title="Clutter in the cell", x_label="parts per bin",
        points=tuple(Point(f"{n} parts", n, {"parts": n}) for n in counts),
        methods=CELL_METHODS, measure=measure,
        seeds=opts.seeds_or((0,) if opts.quick else (0, 1, 2)), criterion=CELL_CRITERION,
        summary="the cell clears bins of up to {x} parts", unit="parts",
        settings=_cell_settings(opts, scene=str(base_scene)),
        description="The cell's scene with N parts per bin (its kinds in their proportions), a bin per (point, "
        "seed), with 1.5 cycles per part (at least max_cycles; max_cycles alone with --quick).",
    )  # fmt: skip
