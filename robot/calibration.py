"""Eye-to-hand hand-eye calibration, the procedure: a ChArUco board on the flange, a fixed camera, ``T_base_camera``
out, kept in a JSON file.

``generate_pose_set`` makes flange poses that show the board to the camera from varied angles (within a workspace
box, reachable); ``collect_samples`` moves the robot through them, captures a ``Frame`` at each, detects the board
and estimates ``T_camera_board`` (``robot.charuco``); ``robot.hand_eye.solve_hand_eye`` turns the pairs
(``T_base_flange``, ``T_camera_board``) into ``T_base_camera``. ``calibrate`` runs all three.
``save_calibration``/``load_calibration`` keep the result in JSON with its residuals and the board definition.

Motion and capture stay abstract (``FlangeRobot``: ``move_to`` and ``T_base_flange``; ``capture``: any callable
returning a ``Frame``), so the same code drives the simulated cell (``sim.world.CellWorld`` already has
``T_base_flange``) and a real UR5e. Frames must be undistorted (``CameraIntrinsics`` has no distortion model).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from scipy.spatial.transform import Rotation

from perception.camera import Frame
from robot.charuco import (
    DEFAULT_MAX_PNP_RMS_PX,
    DEFAULT_MIN_CORNERS,
    BoardDetector,
    CharucoBoard,
    _as_float,
    _as_int,
)
from robot.hand_eye import MIN_POSES, CalibrationError, HandEyeCalibration, HandEyeSample, solve_hand_eye
from robot.ur_config import WorkspaceBox
from sygrid.camera import CameraIntrinsics, project_points
from sygrid.errors import ConfigError
from sygrid.fileio import read_json, write_json_atomic
from sygrid.transforms import invert, is_rigid, make_T, pose_difference, transform_points

log = logging.getLogger(__name__)

FILE_FORMAT = "sygrid.hand_eye_calibration"
FILE_VERSION = 1

__all__ = [
    "FlangeRobot",
    "calibrate",
    "collect_samples",
    "generate_pose_set",
    "load_calibration",
    "save_calibration",
]


# ---------------------------------------------------------------------------------------------- pose set


def generate_pose_set(
    board: CharucoBoard,
    T_base_camera_guess: np.ndarray,
    intrinsics: CameraIntrinsics,
    T_flange_board_guess: np.ndarray,
    n_poses: int,
    rng: np.random.Generator,
    *,
    distance_m: tuple[float, float] = (0.4, 0.6),
    tilt_deg: tuple[float, float] = (12.0, 35.0),
    max_spin_deg: float = 60.0,
    image_margin_frac: float = 0.08,
    workspace: WorkspaceBox | None = None,
    reachable: Callable[[np.ndarray], bool] | None = None,
    max_attempts: int = 5000,
) -> list[np.ndarray]:
    """``n_poses`` flange poses ``T_base_flange`` that show the whole board to the camera from varied angles.

    Each pose puts the board's centre at a distance in ``distance_m`` along a ray through the central part of the
    image, facing the camera, then tilts it by an angle in ``tilt_deg`` about a random axis in the board plane and
    spins it about its normal by up to ``max_spin_deg`` (the rotation diversity the hand-eye solvers need). A pose
    is kept when the board's outline projects inside the image with ``image_margin_frac`` to spare (through the
    guesses: rough values, a few centimetres and degrees, are enough), the flange origin is inside ``workspace``
    and ``reachable(T_base_flange)`` says yes (e.g. an IK check). Poses come back ordered for short moves.
    Raises CalibrationError naming the constraints when ``max_attempts`` draws do not give ``n_poses``.
    """
    if n_poses < MIN_POSES:
        raise ValueError(f"n_poses must be at least {MIN_POSES}, got {n_poses}")
    for name, T in (("T_base_camera_guess", T_base_camera_guess), ("T_flange_board_guess", T_flange_board_guess)):
        if not is_rigid(np.asarray(T, dtype=float)):
            raise ValueError(f"{name} must be a 4x4 rigid transform, got {np.asarray(T).tolist()}")
    if not 0 < distance_m[0] <= distance_m[1] or not 0 <= tilt_deg[0] <= tilt_deg[1] < 90:
        raise ValueError(
            f"distance_m must be 0 < lo <= hi and tilt_deg 0 <= lo <= hi < 90, got {distance_m}, {tilt_deg}"
        )
    T_flange_board_guess = np.asarray(T_flange_board_guess, dtype=float)
    T_board_flange = invert(T_flange_board_guess)
    w, h = board.size_m
    outline = np.array([[0, 0, 0], [w, 0, 0], [w, h, 0], [0, h, 0]], dtype=float)
    K = intrinsics.K
    mx, my = image_margin_frac * intrinsics.width, image_margin_frac * intrinsics.height
    poses: list[np.ndarray] = []
    rejected = {"image": 0, "workspace": 0, "reachable": 0}
    for _ in range(max_attempts):
        if len(poses) == n_poses:
            break
        # Board centre: a ray through the central 60% of the image at the drawn distance.
        u = intrinsics.cx + rng.uniform(-0.3, 0.3) * intrinsics.width
        v = intrinsics.cy + rng.uniform(-0.3, 0.3) * intrinsics.height
        z = rng.uniform(*distance_m)
        p_center = np.array([(u - intrinsics.cx) / intrinsics.fx * z, (v - intrinsics.cy) / intrinsics.fy * z, z])
        # Facing the camera is R_camera_board = I (board z along the camera's z); then tilt and spin.
        axis_angle = rng.uniform(0.0, 2.0 * math.pi)
        tilt = math.radians(rng.uniform(*tilt_deg))
        spin = math.radians(rng.uniform(-max_spin_deg, max_spin_deg))
        R = (
            Rotation.from_rotvec(tilt * np.array([math.cos(axis_angle), math.sin(axis_angle), 0.0]))
            * Rotation.from_rotvec([0.0, 0.0, spin])
        ).as_matrix()
        T_camera_board = make_T(R, p_center - R @ board.center_board)
        pts = transform_points(T_camera_board, outline)
        px = project_points(K, pts)
        inside = (
            np.all(pts[:, 2] > 0)
            and np.all(px[:, 0] >= mx)
            and np.all(px[:, 0] <= intrinsics.width - 1 - mx)
            and np.all(px[:, 1] >= my)
            and np.all(px[:, 1] <= intrinsics.height - 1 - my)
        )
        if not inside:
            rejected["image"] += 1
            continue
        T_base_flange = np.asarray(T_base_camera_guess, dtype=float) @ T_camera_board @ T_board_flange
        if workspace is not None and not workspace.contains(T_base_flange[:3, 3]):
            rejected["workspace"] += 1
            continue
        if reachable is not None and not reachable(T_base_flange):
            rejected["reachable"] += 1
            continue
        poses.append(T_base_flange)
    if len(poses) < n_poses:
        raise CalibrationError(
            f"found only {len(poses)} of {n_poses} calibration poses in {max_attempts} draws; rejected: "
            f"{rejected['image']} board outside the image, {rejected['workspace']} flange outside the workspace, "
            f"{rejected['reachable']} unreachable. Widen distance_m/tilt_deg or the workspace, or check the guesses"
        )
    return _order_for_short_moves(poses)


def _order_for_short_moves(poses: list[np.ndarray]) -> list[np.ndarray]:
    """Greedy nearest-neighbour order (distance in metres plus rotation in radians x 0.3 m)."""
    remaining = list(range(1, len(poses)))
    order = [0]
    while remaining:
        last = poses[order[-1]]

        def cost(i: int, last: np.ndarray = last) -> float:
            metres, radians = pose_difference(poses[i], last)
            return metres + 0.3 * radians

        nxt = min(remaining, key=cost)
        order.append(nxt)
        remaining.remove(nxt)
    return [poses[i] for i in order]


# ---------------------------------------------------------------------------------------------- collection


class FlangeRobot(Protocol):
    """What the calibration needs of a robot: move the flange to a pose (blocking until it is there and still) and
    report where the flange is (measured, not commanded). ``sim.world.CellWorld`` has ``T_base_flange``; a
    ``robot.ur`` adapter maps ``move_to`` onto a linear or joint move to the flange pose."""

    def move_to(self, T_base_flange: np.ndarray) -> None: ...

    def T_base_flange(self) -> np.ndarray: ...


def collect_samples(
    robot: FlangeRobot,
    capture: Callable[[], Frame],
    board: CharucoBoard,
    poses: Sequence[np.ndarray],
    *,
    min_corners: int = DEFAULT_MIN_CORNERS,
    max_pnp_rms_px: float = DEFAULT_MAX_PNP_RMS_PX,
) -> tuple[list[HandEyeSample], CameraIntrinsics, list[str]]:
    """Moves through ``poses``, captures and detects the board at each. Returns the usable samples, the frames'
    intrinsics, and one line per skipped pose saying why. Errors of ``move_to``/``capture`` propagate (a
    protective stop ends the calibration; it is not a skipped pose)."""
    detector = BoardDetector(board, min_corners, max_pnp_rms_px)
    samples: list[HandEyeSample] = []
    skipped: list[str] = []
    intrinsics: CameraIntrinsics | None = None
    for k, T_target in enumerate(poses):
        robot.move_to(np.asarray(T_target, dtype=float))
        T_base_flange = np.asarray(robot.T_base_flange(), dtype=float)
        frame = capture()
        if intrinsics is None:
            intrinsics = frame.intrinsics
        elif frame.intrinsics != intrinsics:
            raise CalibrationError(f"pose {k}: the camera's intrinsics changed during calibration: {frame.intrinsics}")
        observation, why = detector.detect(frame.rgb, frame.intrinsics)
        if observation is None:
            skipped.append(f"pose {k}: {why}")
            log.info("calibration pose %d/%d skipped: %s", k + 1, len(poses), why)
            continue
        samples.append(HandEyeSample(T_base_flange, observation))
        log.info(
            "calibration pose %d/%d: %d corners, PnP %.3f px",
            k + 1,
            len(poses),
            len(observation.corner_ids),
            observation.pnp_rms_px,
        )
    if intrinsics is None:
        raise CalibrationError("no calibration poses were given")
    return samples, intrinsics, skipped


def calibrate(
    robot: FlangeRobot,
    capture: Callable[[], Frame],
    board: CharucoBoard,
    poses: Sequence[np.ndarray],
    *,
    min_poses: int = 6,
    refine: bool = False,
    min_corners: int = DEFAULT_MIN_CORNERS,
    max_pnp_rms_px: float = DEFAULT_MAX_PNP_RMS_PX,
) -> HandEyeCalibration:
    """The whole procedure: ``collect_samples`` through ``poses`` and ``solve_hand_eye``. Raises
    CalibrationError, listing the skipped poses and why, when fewer than ``min_poses`` poses were usable."""
    samples, intrinsics, skipped = collect_samples(
        robot, capture, board, poses, min_corners=min_corners, max_pnp_rms_px=max_pnp_rms_px
    )
    if len(samples) < max(min_poses, MIN_POSES):
        raise CalibrationError(
            f"only {len(samples)} of {len(poses)} poses showed the board well enough (need {max(min_poses, MIN_POSES)})"
            + "".join(f"\n  {s}" for s in skipped)
        )
    return solve_hand_eye(samples, board, intrinsics, refine=refine, skipped=skipped)


def pose_error(T: np.ndarray, T_ref: np.ndarray) -> tuple[float, float]:
    """(translation error mm, rotation error deg) of ``T`` against ``T_ref``: ``sygrid.transforms.pose_difference``
    in a calibration's units."""
    metres, radians = pose_difference(T, T_ref)
    return 1000.0 * metres, math.degrees(radians)


# ---------------------------------------------------------------------------------------------- file


def save_calibration(path: str | Path, calibration: HandEyeCalibration) -> Path:
    """Writes the calibration JSON atomically (a reader sees the old file or the new one)."""
    return write_json_atomic(path, _to_json(calibration))


def _to_json(cal: HandEyeCalibration) -> dict[str, Any]:
    K = cal.intrinsics
    return {
        "format": FILE_FORMAT,
        "version": FILE_VERSION,
        "T_base_camera": cal.T_base_camera.tolist(),
        "T_flange_board": cal.T_flange_board.tolist(),
        "method": cal.method,
        "refined": cal.refined,
        "residuals": {
            "reprojection_rms_px": cal.reprojection_rms_px,
            "per_pose_reprojection_rms_px": list(cal.per_pose_reprojection_rms_px),
            "flange_board_spread_mm": list(cal.flange_board_spread_mm),
            "flange_board_spread_deg": list(cal.flange_board_spread_deg),
            "max_flange_board_spread_mm": max(cal.flange_board_spread_mm),
            "max_flange_board_spread_deg": max(cal.flange_board_spread_deg),
            "method_rms_px": dict(cal.method_rms_px),
        },
        "n_poses": cal.n_poses,
        "skipped_poses": list(cal.skipped),
        "board": cal.board.to_json(),
        "intrinsics": {"fx": K.fx, "fy": K.fy, "cx": K.cx, "cy": K.cy, "width": K.width, "height": K.height},
    }


def load_calibration(path: str | Path) -> HandEyeCalibration:
    """Reads ``save_calibration``'s JSON; a missing, corrupt or inconsistent file raises ConfigError naming the
    file and the field."""
    path = Path(path)
    data = read_json(path, "hand-eye calibration")
    where = str(path)
    if not isinstance(data, dict) or data.get("format") != FILE_FORMAT:
        raise ConfigError(f'{where}: not a hand-eye calibration file (expected "format": "{FILE_FORMAT}")')
    if data.get("version") != FILE_VERSION:
        raise ConfigError(f"{where}: version {data.get('version')!r} is not supported (expected {FILE_VERSION})")
    T_base_camera = _as_transform(data, "T_base_camera", where)
    T_flange_board = _as_transform(data, "T_flange_board", where)
    board = CharucoBoard.from_json(data.get("board"), f"{where}: board")
    intr = data.get("intrinsics")
    if not isinstance(intr, dict):
        raise ConfigError(f"{where}: intrinsics must be an object with fx, fy, cx, cy, width, height")
    intrinsics = CameraIntrinsics(
        _as_float(intr, "fx", f"{where}: intrinsics"),
        _as_float(intr, "fy", f"{where}: intrinsics"),
        _as_float(intr, "cx", f"{where}: intrinsics"),
        _as_float(intr, "cy", f"{where}: intrinsics"),
        _as_int(intr, "width", f"{where}: intrinsics"),
        _as_int(intr, "height", f"{where}: intrinsics"),
    )
    res = data.get("residuals")
    if not isinstance(res, dict):
        raise ConfigError(f"{where}: residuals must be an object")
    per_pose = _as_float_list(res, "per_pose_reprojection_rms_px", where)
    spread_mm = _as_float_list(res, "flange_board_spread_mm", where)
    spread_deg = _as_float_list(res, "flange_board_spread_deg", where)
    if not (len(per_pose) == len(spread_mm) == len(spread_deg) >= MIN_POSES):
        raise ConfigError(
            f"{where}: residuals: per-pose lists must have one entry per pose (at least {MIN_POSES}), got lengths "
            f"{len(per_pose)}, {len(spread_mm)}, {len(spread_deg)}"
        )
    methods = res.get("method_rms_px", {})
    if not isinstance(methods, dict):
        raise ConfigError(f"{where}: residuals.method_rms_px must be an object")
    return HandEyeCalibration(
        T_base_camera=T_base_camera,
        T_flange_board=T_flange_board,
        method=str(data.get("method", "")),
        refined=bool(data.get("refined", False)),
        board=board,
        intrinsics=intrinsics,
        per_pose_reprojection_rms_px=tuple(per_pose),
        flange_board_spread_mm=tuple(spread_mm),
        flange_board_spread_deg=tuple(spread_deg),
        method_rms_px={str(k): _as_float(methods, k, f"{where}: residuals.method_rms_px") for k in methods},
        skipped=tuple(str(s) for s in data.get("skipped_poses", [])),
    )


def _as_transform(data: dict, key: str, where: str) -> np.ndarray:
    try:
        T = np.array(data[key], dtype=float)
    except (KeyError, TypeError, ValueError):
        raise ConfigError(f"{where}: {key} must be a 4x4 array of numbers, got {data.get(key)!r}") from None
    if not is_rigid(T, atol=1e-5):
        raise ConfigError(f"{where}: {key} must be a 4x4 rigid transform, got {T.tolist()}")
    return T


def _as_float_list(data: dict, key: str, where: str) -> list[float]:
    values = data.get(key)
    if not isinstance(values, list):
        raise ConfigError(f"{where}: residuals.{key} must be a list of numbers, got {values!r}")
    return [_as_float({key: v}, key, f"{where}: residuals") for v in values]
