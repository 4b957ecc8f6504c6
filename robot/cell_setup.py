"""A picking cell's configuration file (TOML): which robot, gripper, camera, calibration, perception, planner and
cycle settings, so the same runtime drives the simulated cell and a real UR5e with an OAK camera.

Sections (see ``launch/cells/sim.toml`` and ``launch/cells/ur5e_oak.toml``)::

    [cell]        kind = "sim" | "hardware"
    [sim]         host, scene, seed, unlock_delay_s         (sim cells only: the emulator on a loopback address)
    [robot]       robot.ur_config.URConfig fields (host defaults to [sim] host), workspace = {lo_m, hi_m}
    [gripper]     robot.gripper config: kind = "robotiq_socket" | "digital_output", ... (host defaults to the robot)
    [camera]      kind = "sim" | "oak", oak settings (device, rgb_size, fps); sim only: sensor = a sygrid.sensor
                  preset the exact frames go through ("ideal", the default: exact; "oak-d", "d435", ...)
    [calibration] source = "sim" (the sim camera's known pose) | "file", file = "calib.json" (robot.calibration)
    [perception]  kind = "models" | "oracle" (sim only, ground truth), models_dir, refine, max_refined,
                  conf_threshold, detector_input_size, detector_scale, detector_tile_px, detect_in_bin,
                  ignore_floor, floor_margin_m, min_fitness, mask_erosion_px (refinement settings)
    [bin]         T_base_bin (4x4: the inner floor's centre, z up), inner_size_m, wall/floor_thickness_m
    [place]       T_base_place (4x4: the TCP pose where parts are let go, tool pointing down)
    [planner]     robot.grasp_config.PlannerConfig scalar fields (approach_cone_deg, lift_height_m, ...)
    [picker]      robot.pick_config.PickerConfig fields

Relative paths are taken from the configuration file's folder. Errors name the file and the field.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
import tomllib
from pydantic import BaseModel, ConfigDict, Field, StrictBool, StrictFloat, StrictInt, ValidationError

from robot.pick_config import PickerConfig
from robot.ur_config import URConfig
from sygrid.errors import ConfigError
from sygrid.scene import validation_message
from sygrid.sensor import sensor_preset

if TYPE_CHECKING:
    from robot.grasp_config import PlannerConfig


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class CellSection(_Strict):
    kind: Literal["sim", "hardware"]
    name: str = ""


class SimSection(_Strict):
    host: str = "127.0.0.50"
    scene: str | None = None  # None: the generator's default scene
    seed: int = Field(default=0, ge=0)
    unlock_delay_s: float = Field(default=5.0, ge=0)  # e-Series refuses an unlock for 5 s after a stop


class CameraSection(_Strict):
    kind: Literal["sim", "oak"]
    device: str | None = None
    rgb_size: tuple[int, int] | None = None
    fps: float | None = None
    sensor: str = "ideal"


class CalibrationSection(_Strict):
    source: Literal["sim", "file"]
    file: str | None = None


class PerceptionSection(_Strict):
    kind: Literal["models", "oracle"] = "models"
    models_dir: str = "models/builtin"
    refine: bool | None = None
    max_refined: int | None = Field(default=None, ge=1)
    conf_threshold: float | None = Field(default=None, gt=0, lt=1)
    detector_input_size: int | None = Field(default=None, ge=32, le=4096)
    detector_scale: float | None = Field(default=None, ge=0.05, le=8)  # network px per image px (manifest's: None)
    detector_tile_px: int | None = Field(default=None, ge=0, le=4096)  # tiles over the bin's box (0: none)
    detect_in_bin: bool = True  # the detector looks only at the bin's image box (the planner's bin, calibration)
    ignore_floor: bool = True  # refinement ignores depth on the bin's floor (seen through holes in a part's mask)
    floor_margin_m: float | None = Field(default=None, ge=0, lt=0.05)  # None: perception.pipeline.FLOOR_MARGIN_M
    min_fitness: float | None = Field(default=None, ge=0, le=1)  # refinement acceptance; None: RefineConfig's
    mask_erosion_px: int | None = Field(default=None, ge=0, le=5)  # mask border not refined on; None: RefineConfig's
    num_threads: int = Field(default=2, ge=1)


Matrix4 = tuple[
    tuple[float, float, float, float],
    tuple[float, float, float, float],
    tuple[float, float, float, float],
    tuple[float, float, float, float],
]


class BinSection(_Strict):
    """The bin as measured in the cell (``robot.grasp_scene.BinGeometry``): the pose of its inner floor's centre in
    the robot base frame (z up, out of the bin) and its inner size, metres."""

    T_base_bin: Matrix4
    inner_size_m: tuple[float, float, float]
    wall_thickness_m: float = Field(default=0.01, gt=0)
    floor_thickness_m: float = Field(default=0.02, gt=0)


class PlaceSection(_Strict):
    T_base_place: Matrix4  # the TCP pose where parts are let go (tool pointing down), also where the camera looks


class CellFile(_Strict):
    cell: CellSection
    sim: SimSection | None = None
    robot: dict[str, Any]
    gripper: dict[str, Any]
    camera: CameraSection
    calibration: CalibrationSection
    perception: PerceptionSection = PerceptionSection()
    bin: BinSection | None = None  # None: the simulated cell's bin
    place: PlaceSection | None = None  # None: above the simulated cell's tray
    planner: dict[str, float | int | bool] = Field(default_factory=dict)
    picker: dict[str, StrictBool | StrictInt | StrictFloat | None] = Field(default_factory=dict)  # TOML is typed


class CellSetup:
    """A validated cell file: the sections as objects, paths resolved against the file's folder."""

    def __init__(self, data: CellFile, path: Path) -> None:
        self.data, self.path = data, path
        where = str(path)
        if data.cell.kind == "sim":
            if data.sim is None:
                raise ConfigError(f"{where}: [cell] kind = 'sim' needs a [sim] section (host, scene, seed)")
            if data.camera.kind != "sim":
                raise ConfigError(f"{where}: camera.kind must be 'sim' in a simulated cell, got {data.camera.kind!r}")
            sensor_preset(data.camera.sensor, f"{where}: camera.sensor")
        else:
            if data.camera.sensor != "ideal":
                raise ConfigError(f"{where}: camera.sensor is for the simulated camera (a real one is its own sensor)")
            if data.perception.kind == "oracle":
                raise ConfigError(f"{where}: perception.kind = 'oracle' exists only in the simulated cell")
            if data.calibration.source == "sim":
                raise ConfigError(f"{where}: calibration.source = 'sim' exists only in the simulated cell; use 'file'")
        if data.calibration.source == "file" and not data.calibration.file:
            raise ConfigError(f"{where}: calibration.file is required when calibration.source = 'file'")
        robot = dict(data.robot)
        if data.sim is not None:
            robot.setdefault("host", data.sim.host)
        self.robot = URConfig.from_dict(robot, f"{where}: [robot]")
        from robot.gripper import gripper_config_from_dict

        self.gripper = gripper_config_from_dict(data.gripper, f"{where}: [gripper]", default_host=self.robot.host)
        try:
            self.picker = PickerConfig(**data.picker)
        except (TypeError, ConfigError) as exc:
            raise ConfigError(f"{where}: [picker]: {exc}") from None
        self.planner_overrides = dict(data.planner)
        self.planner_config()  # bad [bin], [place] or [planner] fields fail here, before anything starts

    def planner_config(self) -> PlannerConfig:
        """``robot.grasp_config.PlannerConfig`` from [bin], [place], [planner] and the robot's workspace."""
        from robot.grasp_config import PlannerConfig
        from robot.grasp_scene import BinGeometry

        d, fields = self.data, {"workspace": self.robot.workspace, **self.planner_overrides}
        if d.bin is not None:
            try:
                fields["bin"] = BinGeometry(**{**d.bin.model_dump(), "T_base_bin": np.array(d.bin.T_base_bin)})
            except ConfigError as exc:
                raise ConfigError(f"{self.path}: [bin]: {exc}") from None
        if d.place is not None:
            fields["T_base_place"] = np.array(d.place.T_base_place)
        try:
            return PlannerConfig(**fields)
        except (TypeError, ConfigError) as exc:
            section = "[place]" if "T_base_place" in str(exc) else "[planner]"
            raise ConfigError(f"{self.path}: {section}: {exc}") from None

    @property
    def is_sim(self) -> bool:
        return self.data.cell.kind == "sim"

    def resolve(self, value: str | None) -> Path | None:
        """A path from the file, relative to the file's folder."""
        if value is None:
            return None
        p = Path(value)
        return p if p.is_absolute() else (self.path.parent / p)


def load_cell_setup(path: str | Path) -> CellSetup:
    """Reads and validates a cell file; ``ConfigError`` naming the file and the field on bad input."""
    path = Path(path)
    try:
        raw = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such cell configuration file") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from None
    try:
        data = CellFile.model_validate(raw)
    except ValidationError as exc:
        raise ConfigError(validation_message(exc, str(path))) from None
    return CellSetup(data, path)
