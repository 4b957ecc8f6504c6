"""The simulated cell's hand-eye calibration: the ChArUco procedure of ``robot.calibration`` run in the simulated
cell, so that the picking runtime uses the camera pose a calibration gives (with its error), as on hardware.

``calibrate_sim_cell`` builds the cell (``sim.cell_config.CellConfig``, the one the emulator simulates) with a ChArUco
plate on the flange (``board_plate_on_flange``), renders the overhead camera through the cell file's sensor model,
and runs ``robot.calibration.calibrate`` through a pose set drawn around an operator's guess (the true camera pose
off by ``GUESS_OFFSET_M`` and ``GUESS_TILT_DEG`` in directions drawn from the seed). The arm is placed at each pose
directly (``CellWorld.reset_arm``: the flange pose is exact, as a robot's encoders and kinematics nearly are); the
error comes from detecting the board in the rendered images. The result is kept per cell, sensor and seed in
``cache_dir_for("sim_handeye")`` (``robot.calibration``'s file), so a run calibrates once; ``SimCalibration`` carries
the error against the true camera pose for the pick report.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from robot.calibration import calibrate, generate_pose_set, load_calibration, pose_error, save_calibration
from robot.charuco import CharucoBoard
from robot.hand_eye import HandEyeCalibration
from robot.ur_config import WorkspaceBox
from sim.cell_config import BoardPlate, CellConfig
from sygrid.fileio import cache_dir_for
from sygrid.robots.kinematics import ik_nearest
from sygrid.sensor import SensorModel, sensor_rng
from sygrid.transforms import invert, make_T, rotation_about

log = logging.getLogger(__name__)

BOARD = CharucoBoard()  # 7 x 5 squares of 30 mm, 22 mm 4x4 markers
#: Flange pointing up, elbow up: the IK seed of the presenting poses (the board faces the overhead camera).
Q_PRESENT = np.array([0.0, -1.2, 1.6, 0.8, -math.pi / 2, 0.0])
#: Where the flange may go: the far side of the camera axis from the robot, so the upper arm hides less of the board.
WORKSPACE = WorkspaceBox((-0.8, -0.3, 0.1), (-0.42, 0.3, 0.6))
N_POSES = 12
#: The operator's guess of the camera pose: this far off the true one, in directions drawn from the seed.
GUESS_OFFSET_M = 0.03
GUESS_TILT_DEG = 4.0
_CACHE_VERSION = 1


def board_plate_on_flange(board: CharucoBoard = BOARD) -> tuple[BoardPlate, np.ndarray]:
    """The board on a plate 0.17 m out from the flange, past the gripper's fingers, printed face outwards and centred
    on the flange axis. Returns the plate and the true ``T_flange_board``."""
    image, size, T_plate_board = board.plate(px_per_square=100, margin_squares=0.5)
    T_flange_plate = make_T(np.diag([1.0, -1.0, -1.0]), (-size[0] / 2, size[1] / 2, 0.17))
    return BoardPlate(image, size, T_flange_plate), T_flange_plate @ T_plate_board


def reachable(T_base_flange: np.ndarray) -> bool:
    """An IK solution near ``Q_PRESENT`` exists for the flange pose."""
    return ik_nearest(T_base_flange, Q_PRESENT) is not None


def presenting_joints(
    T_base_camera: np.ndarray, T_flange_board: np.ndarray, board: CharucoBoard = BOARD, distance_m: float = 0.4
) -> np.ndarray:
    """Joints (near ``Q_PRESENT``) that hold the board ``distance_m`` in front of the camera on its optical axis,
    facing it: where an operator jogs the arm before ``sygrid calibrate hand-eye`` (in the default cell, at 0.4 m the
    wrist stays well above the bin's walls, at 0.5 m it meets them). ValueError when unreachable."""
    T_camera_board = make_T(t=np.array([0.0, 0.0, distance_m]) - board.center_board)
    q = ik_nearest(T_base_camera @ T_camera_board @ invert(T_flange_board), Q_PRESENT)
    if q is None:
        raise ValueError(f"the board {distance_m} m in front of the camera is out of the arm's reach")
    return q


class PlacedArm:
    """A ``robot.calibration.FlangeRobot`` over a ``CellWorld``: the IK solution nearest ``Q_PRESENT``, set directly."""

    def __init__(self, world: Any) -> None:
        self.world = world
        self.moves = 0

    def move_to(self, T_base_flange: np.ndarray) -> None:
        q = ik_nearest(T_base_flange, Q_PRESENT)
        if q is None:
            raise RuntimeError(f"no IK solution for the flange pose {T_base_flange.tolist()}")
        self.world.reset_arm(q)
        self.moves += 1

    def T_base_flange(self) -> np.ndarray:
        return self.world.T_base_flange()


@dataclass(frozen=True, eq=False)
class SimCalibration:
    """A hand-eye calibration of the simulated cell and how far it is from the truth (mm, degrees)."""

    calibration: HandEyeCalibration
    T_base_camera_true: np.ndarray
    error_mm: float
    error_deg: float
    path: Path
    cached: bool
    duration_s: float

    @property
    def T_base_camera(self) -> np.ndarray:
        return self.calibration.T_base_camera

    def to_json(self) -> dict[str, Any]:
        cal = self.calibration
        return {
            "source": "sim_handeye",
            "file": str(self.path),
            "cached": self.cached,
            "duration_s": self.duration_s,
            "error_mm": self.error_mm,
            "error_deg": self.error_deg,
            "n_poses": cal.n_poses,
            "reprojection_rms_px": cal.reprojection_rms_px,
            "method": cal.method,
            "T_base_camera": cal.T_base_camera.tolist(),
            "T_base_camera_true": self.T_base_camera_true.tolist(),
        }


def true_T_base_camera(config: CellConfig) -> np.ndarray:
    """The overhead camera's pose in the robot base frame, as the cell is built."""
    return invert(config.T_world_base) @ config.T_world_camera


def calibrate_sim_cell(
    config: CellConfig, sensor: SensorModel, seed: int, cache_dir: str | Path | None = None, n_poses: int = N_POSES
) -> SimCalibration:
    """The hand-eye calibration of the cell ``config`` seen through ``sensor`` with ``seed`` (the pose set, the
    guess and the sensor's noise), from the cache when it holds one; see the module docstring. Raises
    ``robot.hand_eye.CalibrationError`` when too few poses show the board."""
    T_true = true_T_base_camera(config)
    path = cache_dir_for("sim_handeye", cache_dir) / f"{_cache_key(config, sensor, seed, n_poses)}.json"
    start = time.perf_counter()
    if path.is_file():
        cal, cached = load_calibration(path), True
    else:
        cal, cached = _run(config, sensor, seed, n_poses), False
        save_calibration(path, cal)
    err_mm, err_deg = pose_error(cal.T_base_camera, T_true)
    result = SimCalibration(cal, T_true, err_mm, err_deg, path, cached, time.perf_counter() - start)
    log.info(
        "sim hand-eye calibration (%s): %.2f mm, %.3f deg from the true camera pose, %d poses, %.2f px; %.1f s",
        "cached" if cached else "ran", err_mm, err_deg, cal.n_poses, cal.reprojection_rms_px, result.duration_s,
    )  # fmt: skip
    return result


def _run(config: CellConfig, sensor: SensorModel, seed: int, n_poses: int) -> HandEyeCalibration:
    from dataclasses import replace

    from sim.camera import SimCamera
    from sim.world import CellWorld

    rng = np.random.default_rng([int(seed), 0x4E1])
    plate, T_flange_board = board_plate_on_flange()
    world = CellWorld(replace(config, calibration_board=plate))
    T_guess = true_T_base_camera(config) @ make_T(
        rotation_about(rng.normal(size=3), math.radians(GUESS_TILT_DEG)), GUESS_OFFSET_M * _unit(rng.normal(size=3))
    )
    T_flange_board_guess = T_flange_board @ make_T(t=0.01 * _unit(rng.normal(size=3)))  # the mount within 1 cm
    camera_rng = None if sensor.is_ideal else sensor_rng(seed, 0x4E1)
    with SimCamera(world, sensor=sensor, rng=camera_rng, report_T_base_camera=False) as camera:
        poses = generate_pose_set(
            BOARD, T_guess, camera.intrinsics, T_flange_board_guess, n_poses, rng,
            workspace=WORKSPACE, reachable=reachable,
        )  # fmt: skip
        return calibrate(PlacedArm(world), camera.capture, BOARD, poses)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def _cache_key(config: CellConfig, sensor: SensorModel, seed: int, n_poses: int) -> str:
    K = config.camera_intrinsics
    what = {
        "version": _CACHE_VERSION,
        "T_world_base": np.round(config.T_world_base, 9).tolist(),
        "T_world_camera": np.round(config.T_world_camera, 9).tolist(),
        "intrinsics": [K.fx, K.fy, K.cx, K.cy, K.width, K.height],
        "sensor": repr(sensor),
        "board": BOARD.to_json(),
        "seed": int(seed),
        "n_poses": int(n_poses),
        "guess": [GUESS_OFFSET_M, GUESS_TILT_DEG],
    }
    digest = hashlib.sha256(json.dumps(what, sort_keys=True).encode()).hexdigest()[:16]
    return f"seed{int(seed)}_{sensor.name}_{digest}"
