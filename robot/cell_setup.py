"""A picking cell's configuration file (TOML): which robot, gripper, camera, calibration, perception, planner and
cycle settings, so the same runtime drives the simulated cell and a real UR5e with an OAK or RealSense camera.

Sections (see ``launch/cells/sim.toml`` and ``launch/cells/ur5e_oak.toml``)::

    [cell]        kind = "sim" | "hardware"
    [sim]         host, scene, seed, unlock_delay_s         (sim cells only: the emulator on a loopback address)
    [robot]       robot.ur_config.URConfig fields (host defaults to [sim] host), workspace = {lo_m, hi_m}
    [gripper]     robot.gripper config: kind = "robotiq_socket" | "digital_output", ... (host defaults to the robot);
                  calibration = "gripper.json": robot.gripper_calibration's file (``sygrid calibrate gripper``)
    [camera]      kind = "sim" | "oak" | "realsense"; oak: device, rgb_size, stereo_size, fps
                  (perception.oak.OakConfig); realsense: serial, rgb_size, depth_size, fps, visual_preset,
                  emitter_enabled, laser_power_mw (perception.realsense.RealSenseConfig); sim only: sensor = a
                  sygrid.sensor preset the exact frames go through ("ideal", the default: exact; "oak-d", "d435", ...)
    [calibration] source = "sim_handeye" (sim: the ChArUco hand-eye calibration run in the simulated cell,
                  launch.sim_calibration) | "sim" (sim: the camera's true pose) | "file", file = "calib.json"
                  (robot.calibration's file, written by ``sygrid calibrate hand-eye``); board (CharucoBoard's
                  fields, type = "charuco"), T_flange_board_guess (4x4): the board on the flange, for that command
    [perception]  kind = "models" | "oracle" (sim only, ground truth), models_dir, refine, max_refined,
                  conf_threshold, detector_input_size, detector_scale, detector_tile_px, detect_in_bin,
                  ignore_floor, floor_margin_m, min_fitness, mask_erosion_px (refinement settings)
    [bin]         T_base_bin (4x4: the inner floor's centre, z up), inner_size_m, wall/floor_thickness_m
    [place]       T_base_place (4x4: the TCP pose where parts are let go, tool pointing down), grid = [nx, ny] and
                  pitch_m = [px, py] (successive parts let go side by side around it; default one spot)
    [planner]     robot.grasp_config.PlannerConfig scalar fields (approach_cone_deg, lift_height_m, ...)
    [picker]      robot.pick_config.PickerConfig fields; a hardware cell nudges only with nudge_contact =
                  "force_limited" (or max_nudges = 0)

Relative paths are taken from the configuration file's folder. Errors name the file and the field.

Gripper calibration: a socket gripper's calibration file, when it exists, sets the gripper's width mapping and
raises ``[picker] min_held_width_m`` to its hold threshold. A hardware cell with a socket gripper needs it before
it starts (``require_gripper_calibration``, which ``launch.pick.open_cell`` calls); loading the file does not, so
``sygrid calibrate gripper`` can read the cell to make it.
"""

from __future__ import annotations

import dataclasses
import logging
import tomllib
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, StrictBool, StrictFloat, StrictInt, StrictStr, ValidationError

from robot.pick_config import PickerConfig
from robot.ur_config import URConfig
from sygrid.errors import ConfigError
from sygrid.scene import validation_message
from sygrid.sensor import SensorModel, sensor_preset

if TYPE_CHECKING:
    from perception.camera import Camera
    from perception.oak import OakConfig
    from perception.realsense import RealSenseConfig
    from robot.charuco import CharucoBoard
    from robot.grasp_config import PlannerConfig
    from robot.gripper_calibration import GripperCalibration

log = logging.getLogger(__name__)

# The sygrid.sensor model of each hardware camera kind's depth: what its noise allowances assume.
HARDWARE_SENSORS = {"oak": "oak-d", "realsense": "d435"}
# [camera] fields per kind (besides kind); the rest must stay unset.
_CAMERA_FIELDS = {
    "sim": ("sensor",),
    "oak": ("device", "rgb_size", "stereo_size", "fps"),
    "realsense": ("serial", "rgb_size", "depth_size", "fps", "visual_preset", "emitter_enabled", "laser_power_mw"),
}


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
    kind: Literal["sim", "oak", "realsense"]
    device: str | None = None
    serial: str | None = None
    rgb_size: tuple[int, int] | None = None
    depth_size: tuple[int, int] | None = None
    stereo_size: tuple[int, int] | None = None
    fps: float | None = None
    visual_preset: str | None = None
    emitter_enabled: StrictBool | None = None
    laser_power_mw: float | None = None
    sensor: str = "ideal"


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


class CalibrationSection(_Strict):
    source: Literal["sim_handeye", "sim", "file"]
    file: str | None = None
    # `sygrid calibrate hand-eye`: the ChArUco board on the flange (robot.charuco.CharucoBoard's JSON fields; default
    # the 7 x 5 board of 30 mm squares) and where it sits on the flange, to a few cm and degrees
    board: dict[str, Any] | None = None
    T_flange_board_guess: Matrix4 | None = None


class BinSection(_Strict):
    """The bin as measured in the cell (``robot.grasp_scene.BinGeometry``): the pose of its inner floor's centre in
    the robot base frame (z up, out of the bin) and its inner size, metres."""

    T_base_bin: Matrix4
    inner_size_m: tuple[float, float, float]
    wall_thickness_m: float = Field(default=0.01, gt=0)
    floor_thickness_m: float = Field(default=0.02, gt=0)


class PlaceSection(_Strict):
    T_base_place: Matrix4  # the TCP pose where parts are let go (tool pointing down), also where the camera looks
    # successive parts are let go on this grid around T_base_place, along its x and y (PlannerConfig.place_grid)
    grid: tuple[Annotated[int, Field(ge=1)], Annotated[int, Field(ge=1)]] = (1, 1)
    pitch_m: tuple[Annotated[float, Field(ge=0)], Annotated[float, Field(ge=0)]] = (0.0, 0.0)


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
    picker: dict[str, StrictBool | StrictInt | StrictFloat | StrictStr | None] = Field(default_factory=dict)


class CellSetup:
    """A validated cell file: the sections as objects, paths resolved against the file's folder."""

    def __init__(self, data: CellFile, path: Path, load_gripper_calibration: bool = True) -> None:
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
            if data.calibration.source != "file":
                raise ConfigError(
                    f"{where}: calibration.source = {data.calibration.source!r} exists only in the simulated cell; "
                    "use 'file'"
                )
        if data.calibration.source == "file" and not data.calibration.file:
            raise ConfigError(f"{where}: calibration.file is required when calibration.source = 'file'")
        robot = dict(data.robot)
        if data.sim is not None:
            robot.setdefault("host", data.sim.host)
        self.robot = URConfig.from_dict(robot, f"{where}: [robot]")
        self.camera = self._camera_config()
        from robot.gripper import gripper_config_from_dict

        gripper = dict(data.gripper)
        calibration = gripper.pop("calibration", None)
        if calibration is not None and not (isinstance(calibration, str) and calibration):
            raise ConfigError(f"{where}: gripper.calibration must be a file path, got {calibration!r}")
        self.gripper = gripper_config_from_dict(gripper, f"{where}: [gripper]", default_host=self.robot.host)
        try:
            self.picker = PickerConfig(**data.picker)
        except (TypeError, ConfigError) as exc:
            raise ConfigError(f"{where}: [picker]: {exc}") from None
        self.gripper_calibration_path = self.resolve(calibration)
        self.gripper_calibration: GripperCalibration | None = None
        if load_gripper_calibration and self.gripper_calibration_path is not None:
            self._apply_gripper_calibration(self.gripper_calibration_path)
        if not self.is_sim and self.picker.max_nudges and self.picker.nudge_contact != "force_limited":
            raise ConfigError(
                f"{where}: [picker] nudge_contact = {self.picker.nudge_contact!r} presses parts under position control "
                "only, which a hardware cell refuses: set nudge_contact = 'force_limited' (the controller's "
                "moveUntilContact and force mode) or max_nudges = 0"
            )
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
            fields["place_grid"], fields["place_pitch_m"] = d.place.grid, d.place.pitch_m
        try:
            return PlannerConfig(**fields)
        except (TypeError, ConfigError) as exc:
            section = "[place]" if "T_base_place" in str(exc) else "[planner]"
            raise ConfigError(f"{self.path}: {section}: {exc}") from None

    @property
    def is_sim(self) -> bool:
        return self.data.cell.kind == "sim"

    def depth_sensor(self) -> SensorModel:
        """The sensor model of the cell's depth, which the verification and the planner allow for: the simulated
        camera's ``sensor``, or the stereo model of the hardware camera's kind (``HARDWARE_SENSORS``) at the stereo
        resolution the camera runs (an OAK's ``stereo_size``, a RealSense's ``depth_size``; the preset's otherwise):
        the depth noise scales with it."""
        cam = self.data.camera
        if cam.kind == "sim":
            return sensor_preset(cam.sensor)
        model = sensor_preset(HARDWARE_SENSORS[cam.kind])
        size = cam.stereo_size if cam.kind == "oak" else cam.depth_size
        if size is None or tuple(size) == model.stereo_size_px:
            return model
        return model.at_stereo_size(*size)

    def _camera_config(self) -> OakConfig | RealSenseConfig | None:
        """The hardware camera's config from [camera] (None for the simulated camera); ConfigError for a field of
        another kind or a bad value."""
        cam, where = self.data.camera, f"{self.path}: [camera]"
        given = {k: v for k, v in cam.model_dump(exclude={"kind"}).items() if v is not None and k != "sensor"}
        if cam.sensor != "ideal":
            given["sensor"] = cam.sensor
        stray = sorted(set(given) - set(_CAMERA_FIELDS[cam.kind]))
        if stray:
            raise ConfigError(
                f"{where}: {stray} are not settings of a {cam.kind!r} camera {list(_CAMERA_FIELDS[cam.kind])}"
            )
        if cam.kind == "sim":
            return None
        try:
            if cam.kind == "oak":
                from perception.oak import OakConfig

                return OakConfig(**given)
            from perception.realsense import RealSenseConfig

            if "fps" in given:
                if not float(given["fps"]).is_integer():
                    raise ConfigError(f"RealSenseConfig.fps must be a whole number, got {given['fps']}")
                given["fps"] = int(given["fps"])
            return RealSenseConfig(**given)
        except ConfigError as exc:
            raise ConfigError(f"{where}: {exc}") from None

    def open_camera(self) -> Camera:
        """Starts the hardware camera of [camera]; ConfigError for the simulated camera (``launch.pick`` builds that
        one from the emulator)."""
        kind = self.data.camera.kind
        if kind == "realsense":
            from perception.realsense import RealSenseCamera

            return RealSenseCamera(self.camera)
        if kind == "oak":
            from perception.oak import OakCamera

            return OakCamera(self.camera)
        raise ConfigError(f"{self.path}: the simulated camera comes from the emulator, not from open_camera")

    def _apply_gripper_calibration(self, path: Path) -> None:
        from robot.gripper import RobotiqGripperConfig
        from robot.gripper_calibration import load_gripper_calibration

        where = f"{self.path}: gripper.calibration"
        if not isinstance(self.gripper, RobotiqGripperConfig):
            raise ConfigError(f"{where}: only a socket gripper (kind 'robotiq_socket') has a calibration")
        if not path.is_file():
            log.log(
                logging.INFO if self.is_sim else logging.WARNING,
                "%s: no gripper calibration at %s (make it with: sygrid calibrate gripper --config %s)",
                self.path, path, self.path,
            )  # fmt: skip
            return
        calibration = load_gripper_calibration(path)
        self.gripper = calibration.apply(self.gripper, f"{where} {path}")
        threshold = calibration.hold_threshold_m
        if threshold > self.picker.min_held_width_m:
            self.picker = dataclasses.replace(self.picker, min_held_width_m=threshold)
        self.gripper_calibration = calibration

    def require_gripper_calibration(self) -> None:
        """ConfigError, naming the command that makes it, unless this cell may start: a hardware cell with a socket
        gripper needs its gripper calibration (``[gripper] calibration``, the file present and loaded)."""
        from robot.gripper import RobotiqGripperConfig

        if self.is_sim or not isinstance(self.gripper, RobotiqGripperConfig) or self.gripper_calibration is not None:
            return
        command = f"sygrid calibrate gripper --config {self.path}"
        if self.gripper_calibration_path is None:
            raise ConfigError(
                f'{self.path}: a hardware cell needs a gripper calibration: set [gripper] calibration = "..." (a '
                f"JSON path) and run `{command}` with nothing between the fingers"
            )
        raise ConfigError(
            f"{self.path}: no gripper calibration at {self.gripper_calibration_path}: run `{command}` with nothing "
            "between the fingers before a hardware run"
        )

    def hand_eye_board(self) -> CharucoBoard:
        """The ChArUco board of ``[calibration] board`` (``CharucoBoard()``'s fields where it leaves them out); errors
        name the file and field."""
        from robot.charuco import CharucoBoard

        fields = {**CharucoBoard().to_json(), **(self.data.calibration.board or {})}  # left out: the default's
        return CharucoBoard.from_json(fields, f"{self.path}: [calibration] board")

    def flange_board_guess(self) -> np.ndarray:
        """``[calibration] T_flange_board_guess`` as a rigid 4x4; ConfigError naming the field when it is missing or
        not rigid."""
        from sygrid.transforms import is_rigid

        where = f"{self.path}: [calibration] T_flange_board_guess"
        T = self.data.calibration.T_flange_board_guess
        if T is None:
            raise ConfigError(
                f"{where} is not set: where the ChArUco board sits on the flange (a 4x4 pose of the board frame, its "
                "outer top-left corner, in the flange frame; a few cm and degrees are enough)"
            )
        T = np.array(T, dtype=float)
        if not is_rigid(T):
            raise ConfigError(f"{where}: expected a rigid 4x4 transform, got {T.tolist()}")
        return T

    def resolve(self, value: str | None) -> Path | None:
        """A path from the file, relative to the file's folder."""
        if value is None:
            return None
        p = Path(value)
        return p if p.is_absolute() else (self.path.parent / p)


def load_cell_setup(path: str | Path, load_gripper_calibration: bool = True) -> CellSetup:
    """Reads and validates a cell file; ``ConfigError`` naming the file and the field on bad input.
    ``load_gripper_calibration=False`` leaves the gripper uncalibrated (for the calibration itself)."""
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
    return CellSetup(data, path, load_gripper_calibration)
