"""``sygrid pick --config launch/cells/sim.toml``: the picking runtime on a cell file.

On a simulated cell it starts the UR controller emulator (MuJoCo backend) on the file's loopback address with the
scene's parts dropped with the seed, then runs ``robot.picker.Picker`` until the bin is empty or nothing is safe,
prints the success rate and cycle times and writes ``pick_report.json`` and ``pick_report.png`` (per-cycle
timeline of the stage timings, and the first frame with the estimated poses drawn) to ``--out``, and on a simulated
cell the emulator's log (``emulator.log``).
On a hardware cell the same code connects to the robot, gripper and camera named in the file (OAK or RealSense).

A simulated cell's scene must hold parts its model folder knows, by obj_id and name (one catalogue for both): the
run is refused before anything starts otherwise. ``--dry-run`` stops after these checks: it loads the cell file, the
model folder's pipeline and the scene's parts, and starts no emulator, robot or camera.

SIGINT and SIGTERM stop the run cleanly (``launch.pick_stops``): the arm's motion is stopped, the gripper keeps its
state, the report is written with every finished cycle and the interrupted one, and the command says where it
stopped. The report is written whatever ends the run (an error included); a simulated cell's emulator process that
dies is named. Exit codes: ``launch.pick_stops.EXIT_CODES``.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from launch.part_check import cell_warnings, check_scene_parts, log_warnings
from launch.pick_stops import EXIT_CODES, EmulatorWatch, Interrupted, StopSignals, exit_code
from robot.cell_setup import CellSetup, load_cell_setup
from robot.pick_report import RunReport, Stage, StopReason
from robot.picker import Picker
from sygrid.errors import ConfigError, SygridError
from sygrid.sensor import sensor_preset, sensor_rng

log = logging.getLogger(__name__)

DEFAULT_CONFIG = Path(__file__).parent / "cells" / "sim.toml"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.epilog = EXIT_CODES
    parser.add_argument("--config", type=Path, default=DEFAULT_CONFIG, help="cell file (TOML)")
    parser.add_argument("--max-cycles", type=int, default=None, help="stop after this many cycles")
    parser.add_argument("--out", type=Path, default=Path("out/pick"), help="report folder")
    parser.add_argument("--seed", type=int, default=None, help="sim cells: override the drop seed")
    parser.add_argument("--perception", choices=("models", "oracle"), default=None, help="override the file's")
    parser.add_argument(
        "--dry-run", action="store_true",
        help="load the cell file, its models and its scene's parts, check them, and stop (nothing started)",
    )  # fmt: skip


@dataclass
class SceneShot:
    """The first cycle's frame and the poses its plan was made from, for the report picture."""

    frame: Any = None
    poses: list[Any] | None = None


@contextlib.contextmanager
def open_cell(
    setup: CellSetup,
    seed: int | None = None,
    perception_kind: str | None = None,
    controller_kwargs: dict | None = None,
    calibration_info: dict | None = None,
    T_camera_error: np.ndarray | None = None,
) -> Iterator[tuple[Picker, Any]]:
    """Starts (sim) or connects to (hardware) everything the cell file names; yields ``(picker, process)``
    (``process``: the emulator's ``ControllerProcess``, None on hardware). Everything is stopped on exit.
    ``calibration_info`` (a dict) receives where the camera pose came from (``camera_pose_info``).
    ``T_camera_error``: a 4x4 rigid error composed onto the camera pose (``T_base_camera @ T_camera_error``, in the
    camera frame) before anything uses it, as a wrong hand-eye calibration would be (``sygrid bench stability``); the
    oracle perception keeps the pose without it (the camera's own), so its poses carry the error as a camera's
    would."""
    from robot.grasp_planner import GraspPlanner
    from robot.gripper import make_gripper
    from robot.nudge import NudgePlanner
    from robot.ur import URRobot

    d = setup.data
    kind = perception_kind or d.perception.kind
    setup.require_gripper_calibration()  # a hardware cell does not start uncalibrated
    with contextlib.ExitStack() as stack:
        process = None
        T_base_camera, info = camera_pose(setup, seed)
        T_oracle_camera = T_base_camera
        if T_camera_error is not None:
            T_base_camera = T_base_camera @ np.asarray(T_camera_error, dtype=float)
        if calibration_info is not None:
            calibration_info.update(info)
        if setup.is_sim:
            from sim.cell_config import CellConfig
            from sim.controller import ControllerProcess
            from sim.emulator_camera import EmulatorCamera

            scene = setup.resolve(d.sim.scene)
            kwargs = {"parts_scene": str(scene) if scene else None, "parts_seed": d.sim.seed if seed is None else seed}
            process = stack.enter_context(
                ControllerProcess(
                    d.sim.host, backend="mujoco", backend_kwargs=kwargs, start_timeout_s=120.0,
                    unlock_delay_s=d.sim.unlock_delay_s, **(controller_kwargs or {}),
                )
            )  # fmt: skip
            camera = EmulatorCamera(
                process, sensor=sensor_preset(d.camera.sensor), rng=sensor_rng(kwargs["parts_seed"])
            )
            cell = CellConfig()
        else:
            camera = stack.enter_context(setup.open_camera())
        planner_config = setup.planner_config()
        sensor = setup.depth_sensor()
        if planner_config.bin is not None:  # the depth noise where the camera sees the bin's far corners
            far_z = float(planner_config.bin.inner_corners_camera(T_base_camera)[:, 2].max())
            planner_config = planner_config.for_depth_noise(float(sensor.depth_noise_sigma_m(far_z)))
        if kind == "oracle":
            if process is None:
                raise ConfigError(f"{setup.path}: perception 'oracle' exists only in the simulated cell")
            from sim.oracle_perception import OraclePerception

            parts = scene_models(setup)
            perception = OraclePerception(process, cell.T_world_base, T_oracle_camera, parts)
            models = {m.obj_id: m for m in parts}
        else:
            from perception.pipeline import PerceptionPipeline

            models_dir = setup.resolve(d.perception.models_dir)
            overrides = cell_overrides(setup)
            region = floor = corners = None
            if planner_config.bin is not None:
                corners = planner_config.bin.inner_corners_camera(T_base_camera)
                if d.perception.detect_in_bin:
                    region = corners
                if d.perception.ignore_floor:
                    floor = planner_config.bin.floor_plane_camera(T_base_camera)
            perception = PerceptionPipeline.from_folder(
                models_dir, overrides, region_camera_m=region, floor_plane_camera=floor,
                floor_bounds_camera_m=corners if floor is not None else None,
                floor_margin_m=d.perception.floor_margin_m, sensor=sensor,
            )  # fmt: skip
            models = perception.models
            if planner_config.bin is not None:  # parts on the bin's floor, as far as its farthest corner
                floor = planner_config.bin.inner_corners_camera(T_base_camera)[::2]
                warnings = cell_warnings(perception.detector, models_dir, models.values(), camera.intrinsics, floor)
                log_warnings(warnings, "pixels per part")
        planner = GraspPlanner(models, planner_config)
        robot = stack.enter_context(URRobot(setup.robot))
        gripper = stack.enter_context(make_gripper(setup.gripper, io=robot))
        gripper.activate()
        q_observe = robot.ik(planner_config.T_base_place, planner.q_reference)
        if q_observe is None:
            raise ConfigError(f"{setup.path}: the place pose (planner T_base_place) is unreachable for the robot")
        nudger = NudgePlanner(planner) if setup.picker.max_nudges else None
        picker = Picker(
            robot, gripper, camera, perception, planner, T_base_camera, q_observe, setup.picker, nudger=nudger
        )
        yield picker, process


def cell_overrides(setup: CellSetup) -> Any:
    """The pipeline settings the cell file's ``[perception]`` overrides (``PipelineOverrides``)."""
    from perception.pipeline import PipelineOverrides

    p = setup.data.perception
    return PipelineOverrides(
        detector_input_size=p.detector_input_size, conf_threshold=p.conf_threshold, detector_scale=p.detector_scale,
        detector_tile_px=p.detector_tile_px, refine=p.refine, max_refined=p.max_refined, min_fitness=p.min_fitness,
        mask_erosion_px=p.mask_erosion_px, num_threads=p.num_threads,
    )  # fmt: skip


def scene_models(setup: CellSetup) -> list[Any]:
    """The parts of a simulated cell's scene (``[sim] scene``, its catalogue relative to the scene file; the default
    scene where none is named), as the emulator drops them."""
    from sygrid.drop import resolve_objects
    from sygrid.scene import default_scene, load_scene

    scene = setup.resolve(setup.data.sim.scene)
    if scene is None:
        return resolve_objects(default_scene(), Path("."))
    return resolve_objects(load_scene(scene), scene.parent)


def check_cell(setup: CellSetup, kind: str) -> dict[int, Any]:
    """Before anything starts: a "models" cell's model folder has a manifest, and a simulated cell's scene holds
    only parts of that folder (by obj_id and name). Returns the folder's models (obj_id -> ObjectModel; {} for an
    oracle cell)."""
    if kind != "models":
        return {}
    from perception.manifest import load_manifest, manifest_models

    folder = setup.resolve(setup.data.perception.models_dir)
    if folder is None or not (folder / "manifest.json").is_file():
        raise ConfigError(
            f"{setup.path}: perception.models_dir {folder} has no manifest.json (train the built-in models first, "
            "or run with --perception oracle in the simulated cell)"
        )
    models = manifest_models(folder, load_manifest(folder))
    if setup.is_sim:
        check_scene_parts(scene_models(setup), models, f"{setup.path}: [sim] scene and [perception] models_dir")
    return models


def dry_run(setup: CellSetup, kind: str) -> int:
    """``--dry-run``: the checks of ``check_cell``, and the model folder's pipeline loaded; nothing started."""
    check_cell(setup, kind)
    d = setup.data
    print(f"cell {d.cell.name or setup.path} ({d.cell.kind}), perception {kind}")
    if kind == "models":
        from perception.pipeline import PerceptionPipeline

        folder = setup.resolve(d.perception.models_dir)
        pipeline = PerceptionPipeline.from_folder(folder, cell_overrides(setup))
        parts = ", ".join(f"{i} {m.name}" for i, m in sorted(pipeline.models.items()))
        print(f"models {folder}: detector {pipeline.detector.path.name} (classes "
              f"{', '.join(pipeline.detector.class_names)}), parts {parts}")  # fmt: skip
    if setup.is_sim:
        scene = scene_models(setup)
        print(f"scene {setup.resolve(d.sim.scene) or 'default'}: parts "
              f"{', '.join(f'{m.obj_id} {m.name}' for m in scene)}")  # fmt: skip
    print("dry run: the cell file, its models and its parts load and agree; nothing was started")
    return 0


def camera_pose(setup: CellSetup, seed: int | None = None) -> tuple[np.ndarray, dict]:
    """``T_base_camera`` from the cell file's ``[calibration]`` and a summary for the report: the hand-eye
    calibration's file ("file"), the ChArUco calibration run in the simulated cell ("sim_handeye", with its error
    against the true pose; ``launch.sim_calibration``), or the simulated camera's true pose ("sim")."""
    d = setup.data
    source = d.calibration.source
    if source == "file":
        from robot.calibration import load_calibration

        path = setup.resolve(d.calibration.file)
        return load_calibration(path).T_base_camera, {"source": source, "file": str(path)}
    from launch.sim_calibration import calibrate_sim_cell, true_T_base_camera
    from sim.cell_config import CellConfig

    cell = CellConfig()
    if source == "sim":
        return true_T_base_camera(cell), {"source": source, "error_mm": 0.0, "error_deg": 0.0}
    result = calibrate_sim_cell(cell, sensor_preset(d.camera.sensor), d.sim.seed if seed is None else seed)
    return result.T_base_camera, result.to_json()


def run(args: argparse.Namespace) -> int:
    if args.dry_run:
        setup = load_cell_setup(args.config)
        return dry_run(setup, args.perception or setup.data.perception.kind)
    return run_with_report(args)[0]


def run_with_report(args: argparse.Namespace) -> tuple[int, RunReport]:
    """``sygrid pick``: the exit code (``launch.pick_stops.EXIT_CODES``) and the report written."""
    setup = load_cell_setup(args.config)
    kind = args.perception or setup.data.perception.kind
    check_cell(setup, kind)
    with StopSignals() as signals:
        return _pick(args, setup, kind, signals)


def _pick(args: argparse.Namespace, setup: CellSetup, kind: str, signals: StopSignals) -> tuple[int, RunReport]:
    """Sets the cell up, runs the picker, and writes the report whatever ends the run; returns the exit code and
    the report."""
    shot = SceneShot()
    calibration: dict = {}
    t0 = time.perf_counter()
    picker: Picker | None = None
    models: Any = {}
    failure = death = None
    try:
        with open_cell(setup, args.seed, args.perception, calibration_info=calibration) as (picker, process):

            def keep_first(record: Any, frame: Any, result: Any, poses: list[Any]) -> None:
                if shot.frame is None:
                    shot.frame, shot.poses = frame, poses

            picker.on_cycle = keep_first
            models = {k: getattr(v, "model", v) for k, v in picker.planner._models.items()}
            signals.target = picker.request_stop
            watch = EmulatorWatch(process, picker.request_stop)
            print(f"picking on {setup.data.cell.name or args.config} (perception: {kind}) ...", flush=True)
            try:
                with watch:
                    picker.run(args.max_cycles)
            except SygridError as exc:  # a device failed mid-run: the report keeps the cycles so far
                failure = exc
            finally:
                death = watch.death or (process.describe_exit() if process is not None else None)
                if process is not None:
                    _save_emulator_log(process, args.out)
    except Interrupted:
        pass  # the report says how far the run got
    except BaseException:  # an unexpected error: keep the run's report, then let it through
        if picker is not None and picker.last_report is not None:
            write_report(picker.last_report, args.out, shot, picker.T_base_camera, setup, kind, models, calibration)
        raise
    report = picker.last_report if picker is not None else None
    if report is None:
        detail = f"{signals.name} while setting up the cell" if signals.signum else "the run did not start"
        report = RunReport([], StopReason.INTERRUPTED, detail)
    if death is not None and death not in report.stop_detail:
        report.stop_detail = f"{death}; {report.stop_detail}"  # the cause of whatever error the run ended with
    print_summary(report, time.perf_counter() - t0, calibration)
    T_base_camera = picker.T_base_camera if picker is not None else np.eye(4)
    out_json, out_png = write_report(report, args.out, shot, T_base_camera, setup, kind, models, calibration)
    print(f"wrote {out_json}\nwrote {out_png}")
    if death is not None:
        print(f"sygrid pick: {death}", file=sys.stderr)
    if failure is not None:
        print(f"sygrid pick: error: {failure}", file=sys.stderr)
    code = exit_code(report, signals.signum)
    if signals.signum is not None:
        print(f"sygrid pick: interrupted by {signals.name} (exit code {code})", file=sys.stderr)
    return code, report


def _save_emulator_log(process: Any, out: Path) -> None:
    """The emulator's recent log lines to ``out/emulator.log`` (nothing when its process is gone)."""
    from sygrid.fileio import write_bytes_atomic

    if process.exitcode is not None:
        return
    try:
        lines = process.log_messages()
    except SygridError as exc:
        log.warning("could not read the emulator's log: %s", exc)
        return
    write_bytes_atomic(out / "emulator.log", ("\n".join(lines) + "\n").encode())


def print_summary(report: RunReport, wall_s: float, calibration: dict | None = None) -> None:
    if calibration and "error_mm" in calibration:
        print(
            f"camera pose: {calibration['source']}, {calibration['error_mm']:.2f} mm / {calibration['error_deg']:.3f} "
            "deg from the true pose"
        )
    times = report.sim_cycle_times_s()
    rate = report.success_rate
    print(
        f"stopped: {report.stop_reason} ({report.stop_detail})\n"
        f"picked {report.n_picked} part(s) in {len(report.attempts)} attempt(s) over {len(report.cycles)} cycle(s): "
        f"success rate {100 * rate:.0f}%"
        + (f", failures {report.failures_by_cause()}" if report.failures_by_cause() else "")
        + (f"; {report.n_nudges} nudge(s)" if report.n_nudges else "")
    )
    if times:
        print(
            f"cycle time (simulated/robot s): median {np.median(times):.2f}, p90 {np.percentile(times, 90):.2f}; "
            f"wall {wall_s:.1f} s in all"
        )
    pp = [c.stage_wall_s["perceive"] + c.stage_wall_s["plan"] for c in report.cycles if c.n_poses]
    if pp:
        line = f"perception + planning wall per cycle: median {1e3 * np.median(pp):.0f} ms waited"
        own = [c.perception_ms["total"] for c in report.cycles if c.n_poses and "total" in c.perception_ms]
        if own:
            ahead = sum(c.looked_ahead for c in report.cycles)
            line += f" (perception {np.median(own):.0f} ms a look; {ahead} look(s) perceived while the arm let go)"
        print(line)


def write_report(
    report: RunReport,
    out: Path,
    shot: SceneShot,
    T_base_camera: np.ndarray,
    setup: CellSetup,
    kind: str,
    models: Any,
    calibration: dict | None = None,
) -> tuple[Path, Path]:
    from sygrid.fileio import write_bytes_atomic

    out.mkdir(parents=True, exist_ok=True)
    data = {"config": str(setup.path), "perception": kind, "calibration": calibration or {}, **report.to_json()}
    json_path = write_bytes_atomic(out / "pick_report.json", json.dumps(data, indent=1, default=float).encode())
    png_path = out / "pick_report.png"
    save_report_picture(report, shot, models, png_path)
    return json_path, png_path


def save_report_picture(report: RunReport, shot: SceneShot, models: Any, path: Path) -> Path:
    """``report_figure`` saved as a PNG."""
    fig = report_figure(report, shot, models)  # selects the Agg backend before pyplot is imported here
    import matplotlib.pyplot as plt

    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def report_figure(report: RunReport, shot: SceneShot, models: Any) -> Any:
    """Per-cycle stage timeline (wall s, stacked bars) beside the first frame with the estimated poses drawn."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from sygrid.visualize import bounds_from_extents, draw_3d_box, draw_axes, draw_bbox

    fig, (ax_t, ax_i) = plt.subplots(1, 2, figsize=(13, 4.8), gridspec_kw={"width_ratios": [1.1, 1]})
    idx = np.arange(len(report.cycles))
    bottom = np.zeros(len(report.cycles))
    for stage in Stage:
        vals = np.array([c.stage_wall_s.get(stage, 0.0) for c in report.cycles])
        ax_t.bar(idx, vals, bottom=bottom, label=stage.value)
        bottom += vals
    for c in report.cycles:
        mark = "ok" if c.picked else c.end.value.replace("_", " ")
        ax_t.text(c.index, bottom[c.index], mark, ha="center", va="bottom", fontsize=7, rotation=90)
    ax_t.set(xlabel="cycle", ylabel="wall time [s]", title=f"pick cycles ({report.stop_reason})")
    ax_t.set_ylim(0.0, 1.2 * max(float(bottom.max(initial=0.0)), 1e-3))  # room for the labels above the bars
    ax_t.legend(fontsize=7, ncols=2)
    if shot.frame is not None:
        img = shot.frame.rgb.copy()
        K = shot.frame.intrinsics.K
        for pose in shot.poses:
            x0, y0, x1, y1 = pose.detection.bbox_xyxy
            img = draw_bbox(img, (x0, y0, x1 - x0, y1 - y0), (255, 255, 0))
            model = models.get(pose.obj_id) if hasattr(models, "get") else None
            if model is not None:
                img = draw_3d_box(img, K, pose.T_camera_object, bounds_from_extents(model.extents_m), (0, 255, 0))
            img = draw_axes(img, K, pose.T_camera_object, 0.02)
        ax_i.imshow(img)
        ax_i.set_title(f"first frame: {len(shot.poses)} estimated pose(s)")
    ax_i.axis("off")
    fig.tight_layout()
    return fig
