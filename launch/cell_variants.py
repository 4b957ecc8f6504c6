"""The variants of the cell benchmark (``launch.bench_cell``): each a named change to the cell file's settings
(perception kind and overrides, planner and picker fields, calibration source, camera sensor, where the clients
connect), and ``cell_for_bin``, the cell file's setup for one bin with a variant applied. A variant changes only
its own settings, so two variants of one run differ in what their names say."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from robot.cell_setup import CellSetup


@dataclass(frozen=True)
class Variant:
    """One setting of the cell: the perception (``oracle``: ground truth; ``models``: the trained pipeline, with
    optional overrides), and ``robot.grasp_config.PlannerConfig`` / ``robot.pick_config.PickerConfig`` fields to
    change."""

    perception: str
    description: str
    planner: dict[str, Any] = field(default_factory=dict)
    picker: dict[str, Any] = field(default_factory=dict)
    refine: bool | None = None
    detector_input_size: int | None = None
    models_dir: str | None = None  # another model folder than the cell file's
    detect_in_bin: bool | None = None
    ignore_floor: bool | None = None
    min_fitness: float | None = None
    mask_erosion_px: int | None = None
    max_refined: int | None = None  # parts posed per look (nearest first; more when none of them is safe)
    calibration: str | None = None  # another [calibration] source than the cell file's ("sim": the true pose)
    sensor: str | None = None  # another [camera] sensor than the cell file's (a sygrid.sensor preset)
    robot_host: str | None = None  # where the robot and gripper clients connect (a delaying proxy); None: the bin's
    camera_error: tuple[tuple[float, ...], ...] | None = None  # 4x4 onto the camera pose (launch.pick.open_cell)


_BUILTIN_MODELS = str(Path(__file__).resolve().parents[1] / "models" / "builtin")
_SIM_CELL_MODELS = str(Path(__file__).resolve().parents[1] / "models" / "sim_cell")

_FAST = {
    "approach_speed_m_s": 0.5,
    "transit_linear_speed_m_s": 1.0,
    "approach_accel_m_s2": 2.5,
    "transit_speed_rad_s": 3.0,
    "transit_accel_rad_s2": 6.0,
}
VARIANTS: dict[str, Variant] = {
    "oracle": Variant("oracle", "ground-truth poses; default planner and speeds"),
    "oracle_fast": Variant("oracle", "ground-truth poses; 2x approach speed, faster transits", picker=_FAST),
    "oracle_cone30": Variant(
        "oracle", "ground-truth poses; approach within 30 deg of vertical", {"approach_cone_deg": 30.0}
    ),
    "oracle_no_nudge": Variant("oracle", "ground-truth poses; no nudges", picker={"max_nudges": 0}),
    "oracle_position_nudge": Variant(
        "oracle", "ground-truth poses; nudges pressed under position control", picker={"nudge_contact": "position"}
    ),
    "models": Variant("models", "trained detector + pose net, the cell file's settings"),
    "models_floor2": Variant(
        "models", "the cell file's models; pad tips 2 mm above the bin floor (not 1 mm)", {"floor_clearance_m": 0.002}
    ),
    "models_no_nudge": Variant("models", "the cell file's models; no nudges", picker={"max_nudges": 0}),
    "models_true_camera": Variant(
        "models", "the cell file's models; the camera's true pose, not the hand-eye calibration", calibration="sim"
    ),
    "models_oak_d": Variant(
        "models",
        "the cell file's models and hand-eye calibration; frames through the OAK-D stereo model (realistic sensing)",
        sensor="oak-d",
    ),
    "models_oak_d_800p": Variant(
        "models",
        "the cell file's models and hand-eye calibration; frames through the OAK-D stereo model, its stereo pair at "
        "1280x800 (800P: half the per-pixel depth noise of 400P, nearest depth 0.70 m)",
        sensor="oak-d-800p",
    ),
    "models_oak_d_look_at_start": Variant(
        "models",
        "as models_oak_d (realistic sensing), every frame taken at the start of its cycle (no look taken at the "
        "place pose and perceived while the arm lets go)",
        sensor="oak-d",
        picker={"look_while_placing": False},
    ),
    "models_oak_d_refine2": Variant(
        "models",
        "as models_oak_d (realistic sensing), 2 parts posed per look, not the cell file's 4 (the next ones where "
        "neither is safe)",
        sensor="oak-d",
        max_refined=2,
    ),
    "models_no_sheet": Variant(
        "models",
        "the cell file's models; no grasp narrower than 4 mm (no pinch of a 2 mm sheet: the previous planner default)",
        {"min_grasp_width_m": 0.004},
    ),
    "models_planned_width": Variant(
        "models",
        "the cell file's models; a part held at another width than the planned one is dropped back (slipped)",
        picker={"hold_any_width": False},
    ),
    "models_refine": Variant("models", "trained models, with depth refinement", refine=True),
    "models_norefine": Variant("models", "trained models, without depth refinement", refine=False),
    "models_480": Variant("models", "trained models, detector at its training size 480 px", detector_input_size=480),
    "models_640": Variant("models", "trained models, detector at 640 px", detector_input_size=640),
    "models_builtin": Variant(
        "models",
        "the general built-in models at 800 px (their best size on the cell's frames), masks peeled by a pixel",
        models_dir=_BUILTIN_MODELS,
        detector_input_size=800,
        mask_erosion_px=1,
    ),
    "models_full_frame": Variant(
        "models", "the cell file's models; the detector on the whole frame, not the bin's box", detect_in_bin=False
    ),
    "models_with_floor": Variant(
        "models",
        "the cell file's models; refinement also fits the floor seen through the parts' masks",
        ignore_floor=False,
    ),
    "models_fitness08": Variant(
        "models",
        "the cell file's models; a refinement is accepted only when 80 % of the depth lies on the model (not 30 %)",
        min_fitness=0.8,
    ),
    "models_erosion0": Variant(
        "models",
        "the built-in models at 800 px; refinement on the whole mask (no border pixel peeled off)",
        models_dir=_BUILTIN_MODELS,
        detector_input_size=800,
        mask_erosion_px=0,
    ),
    "models_sim_cell_erosion0": Variant(
        "models",
        "models/sim_cell at 960 px; refinement on the whole mask (no border pixel peeled off)",
        models_dir=_SIM_CELL_MODELS,
        detector_input_size=960,
        mask_erosion_px=0,
    ),
    "models_sim_cell": Variant(
        "models",
        "models/sim_cell (detector fine-tuned on the cell's views) at 960 px, masks peeled by a pixel",
        models_dir=_SIM_CELL_MODELS,
        detector_input_size=960,
        mask_erosion_px=1,
    ),
}
QUICK_VARIANTS = ("oracle", "oracle_fast", "models")


def cell_for_bin(base: CellSetup, variant: Variant, seed: int, scene: Path | None, host: str) -> CellSetup:
    """The cell file's setup for one bin: the emulator on ``host``, the seed (and scene), the variant's settings
    where it has them and the cell file's elsewhere."""
    d = base.data
    sim = d.sim.model_copy(update={"host": host, "seed": seed, **({"scene": str(scene.resolve())} if scene else {})})
    # the variant's settings where it has them, the cell file's elsewhere
    overrides = {
        "refine": variant.refine,
        "detector_input_size": variant.detector_input_size,
        "models_dir": variant.models_dir,
        "detect_in_bin": variant.detect_in_bin,
        "ignore_floor": variant.ignore_floor,
        "min_fitness": variant.min_fitness,
        "mask_erosion_px": variant.mask_erosion_px,
        "max_refined": variant.max_refined,
    }
    perception = d.perception.model_copy(
        update={"kind": variant.perception, **{k: v for k, v in overrides.items() if v is not None}}
    )
    robot = {**d.robot, "host": variant.robot_host or host}
    gripper = {**d.gripper, "host": variant.robot_host or host}
    picker = {**d.picker, **variant.picker}
    calibration = d.calibration.model_copy(update={"source": variant.calibration or d.calibration.source})
    camera = d.camera.model_copy(update={"sensor": variant.sensor or d.camera.sensor})
    data = d.model_copy(
        update={
            "sim": sim, "perception": perception, "robot": robot, "gripper": gripper, "picker": picker,
            "calibration": calibration, "camera": camera,
        }
    )  # fmt: skip
    setup = CellSetup(data, base.path)
    setup.planner_overrides = {**setup.planner_overrides, **variant.planner}
    return setup
