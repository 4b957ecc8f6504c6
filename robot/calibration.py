"""Eye-to-hand hand-eye calibration: a ChArUco board on the flange, a fixed camera, ``T_base_camera`` out.

The procedure: ``generate_pose_set`` makes flange poses that show the board to the camera from varied angles
(within a workspace box, reachable); ``collect_samples`` moves the robot through them, captures a ``Frame`` at each,
detects the board (``cv2.aruco.CharucoDetector``) and estimates ``T_camera_board`` (``cv2.solvePnP`` on the
matched ChArUco corners); ``solve_hand_eye`` turns the pairs (``T_base_flange``, ``T_camera_board``) into
``T_base_camera`` with OpenCV's hand-eye solvers and keeps the method whose result reprojects the board corners
best; optionally (``refine=True``) it then fits ``T_base_camera`` and ``T_flange_board`` by least squares to every
detected corner. ``calibrate`` runs all three. ``save_calibration``/``load_calibration`` keep the result in JSON
with its residuals and the board definition.

Eye-to-hand with OpenCV's eye-in-hand solver: ``cv2.calibrateHandEye`` solves ``T_gripper_camera`` from
``T_base_gripper`` and ``T_camera_target``; fed the inverted robot poses ``T_flange_base`` it returns
``T_base_camera`` (the camera is then "on" the base, seen from the flange). The unknown board mount comes out as
``T_flange_board``.

Motion and capture stay abstract (``FlangeRobot``: ``move_to`` and ``T_base_flange``; ``capture``: any callable
returning a ``Frame``), so the same code drives the simulated cell (``sim.world.CellWorld`` already has
``T_base_flange``) and a real UR5e. Frames must be undistorted (``CameraIntrinsics`` has no distortion model).

OpenCV 5.0.0.93's Python wheel lacks ``cv2.calibrateHandEye`` (opencv/opencv#29565, fixed after that release):
where it is missing, the linear step falls back to Park and Martin's closed form written here with scipy (rotation
by orthogonal Procrustes on the log-rotations of relative motions, translation by linear least squares); it gives
the same result as OpenCV's PARK (checked against opencv-contrib 4.14).

Refinement is off by default, on measurements in the simulated cell (12 poses, 640x480, 3 seeds): with image noise
only (sigma 4 grey levels) it cuts the error from 0.16-0.63 mm / 0.01-0.02 deg to about 0.05 mm / 0.006 deg, but
with noise in the robot's reported flange poses (0.2 mm, 0.02 deg) it fits that noise and ends at 0.5-1.0 mm /
0.06-0.15 deg, where the linear result stays at 0.3-0.6 mm / 0.01-0.03 deg. A real robot's kinematic error is of
that order or larger, so the linear result is the safer default; turn refinement on for a robot whose reported
poses are much better than the camera's corner detection.
"""

from __future__ import annotations

import itertools
import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from perception.camera import Frame
from robot.charuco import (
    DEFAULT_MAX_PNP_RMS_PX,
    DEFAULT_MIN_CORNERS,
    BoardDetector,
    BoardObservation,
    CharucoBoard,
    _as_float,
    _as_int,
    detect_board,
)
from robot.ur_config import WorkspaceBox
from sygrid.camera import CameraIntrinsics, project_points
from sygrid.errors import ConfigError, SygridError
from sygrid.fileio import read_json, write_json_atomic
from sygrid.transforms import invert, is_rigid, make_T, rotation_angle_deg, transform_points

log = logging.getLogger(__name__)

FILE_FORMAT = "sygrid.hand_eye_calibration"
FILE_VERSION = 1
#: OpenCV's hand-eye methods, by the names this module uses.
OPENCV_METHODS = ("TSAI", "PARK", "HORAUD", "ANDREFF", "DANIILIDIS")
#: The scipy fallback's name (used where ``cv2.calibrateHandEye`` is missing).
FALLBACK_METHOD = "PARK_MARTIN_SCIPY"
MIN_POSES = 3  # two relative motions with non-parallel rotation axes is the minimum of AX = XB

__all__ = [
    "FALLBACK_METHOD",
    "OPENCV_METHODS",
    "BoardObservation",
    "CalibrationError",
    "CharucoBoard",
    "FlangeRobot",
    "HandEyeCalibration",
    "HandEyeSample",
    "WorkspaceBox",
    "available_methods",
    "calibrate",
    "collect_samples",
    "detect_board",
    "generate_pose_set",
    "load_calibration",
    "save_calibration",
    "solve_hand_eye",
]


class CalibrationError(SygridError, RuntimeError):
    """The calibration could not produce a trustworthy result (too few usable poses, degenerate motion)."""


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
            dp = float(np.linalg.norm(poses[i][:3, 3] - last[:3, 3]))
            return dp + 0.3 * math.radians(rotation_angle_deg(poses[i][:3, :3], last[:3, :3]))

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


@dataclass(frozen=True, eq=False)
class HandEyeSample:
    """One usable pose: where the flange was and how the camera saw the board."""

    T_base_flange: np.ndarray
    observation: BoardObservation


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


# ---------------------------------------------------------------------------------------------- solving


@dataclass(frozen=True, eq=False)
class HandEyeCalibration:
    """The result: ``T_base_camera``, the board mount ``T_flange_board`` found with it, and the residuals.

    ``per_pose_reprojection_rms_px``: RMS distance (pixels) between the detected corners and the corners projected
    through ``inv(T_base_camera) @ T_base_flange @ T_flange_board``, per pose. ``flange_board_spread_mm/deg``: per
    pose, how far ``inv(T_base_flange) @ T_base_camera @ T_camera_board`` (the mount implied by that pose alone)
    lies from ``T_flange_board``. ``method_rms_px``: the overall reprojection RMS of every linear method tried.
    """

    T_base_camera: np.ndarray
    T_flange_board: np.ndarray
    method: str
    refined: bool
    board: CharucoBoard
    intrinsics: CameraIntrinsics
    per_pose_reprojection_rms_px: tuple[float, ...]
    flange_board_spread_mm: tuple[float, ...]
    flange_board_spread_deg: tuple[float, ...]
    method_rms_px: dict[str, float] = field(default_factory=dict)
    skipped: tuple[str, ...] = ()

    @property
    def reprojection_rms_px(self) -> float:
        """Overall RMS reprojection error over all poses (pixels)."""
        return float(np.sqrt(np.mean(np.square(self.per_pose_reprojection_rms_px))))

    @property
    def n_poses(self) -> int:
        return len(self.per_pose_reprojection_rms_px)

    def to_json(self) -> dict[str, Any]:
        K = self.intrinsics
        return {
            "format": FILE_FORMAT,
            "version": FILE_VERSION,
            "T_base_camera": self.T_base_camera.tolist(),
            "T_flange_board": self.T_flange_board.tolist(),
            "method": self.method,
            "refined": self.refined,
            "residuals": {
                "reprojection_rms_px": self.reprojection_rms_px,
                "per_pose_reprojection_rms_px": list(self.per_pose_reprojection_rms_px),
                "flange_board_spread_mm": list(self.flange_board_spread_mm),
                "flange_board_spread_deg": list(self.flange_board_spread_deg),
                "max_flange_board_spread_mm": max(self.flange_board_spread_mm),
                "max_flange_board_spread_deg": max(self.flange_board_spread_deg),
                "method_rms_px": dict(self.method_rms_px),
            },
            "n_poses": self.n_poses,
            "skipped_poses": list(self.skipped),
            "board": self.board.to_json(),
            "intrinsics": {"fx": K.fx, "fy": K.fy, "cx": K.cx, "cy": K.cy, "width": K.width, "height": K.height},
        }


def solve_hand_eye(
    samples: Sequence[HandEyeSample],
    board: CharucoBoard,
    intrinsics: CameraIntrinsics,
    *,
    methods: Sequence[str] | None = None,
    refine: bool = False,
    skipped: Sequence[str] = (),
) -> HandEyeCalibration:
    """``T_base_camera`` from the samples: every linear method in ``methods`` (default: OpenCV's five, or the
    scipy fallback where ``cv2.calibrateHandEye`` is missing), the one with the lowest reprojection RMS kept, then
    with ``refine`` a least-squares fit of ``T_base_camera`` and ``T_flange_board`` to every detected corner (best
    when the robot's poses are much more accurate than the corners; see the module docstring)."""
    if len(samples) < MIN_POSES:
        raise CalibrationError(f"hand-eye calibration needs at least {MIN_POSES} usable poses, got {len(samples)}")
    methods = list(methods) if methods is not None else list(available_methods())
    unknown = [m for m in methods if m not in (*OPENCV_METHODS, FALLBACK_METHOD)]
    if unknown or not methods:
        raise ValueError(f"unknown hand-eye methods {unknown}; valid: {[*OPENCV_METHODS, FALLBACK_METHOD]}")
    F = np.array([s.T_base_flange for s in samples])
    C = np.array([s.observation.T_camera_board for s in samples])
    _check_motion(F)
    corners_board = board.corners_board()
    obs = [(corners_board[s.observation.corner_ids], s.observation.corners_px) for s in samples]
    K = intrinsics.K

    candidates: dict[str, tuple[np.ndarray, np.ndarray, float]] = {}
    for method in methods:
        X = _linear_hand_eye(method, F, C)
        if X is None:
            log.warning("hand-eye method %s gave no solution", method)
            continue
        Y = _mean_mount(F, C, X)
        rms = _overall_rms(_per_pose_rms(K, F, X, Y, obs))
        candidates[method] = (X, Y, rms)
        log.info("hand-eye %s: reprojection %.3f px", method, rms)
    if not candidates:
        raise CalibrationError(f"no hand-eye method gave a solution (tried {methods})")
    best = min(candidates, key=lambda m: candidates[m][2])
    X, Y, _ = candidates[best]
    if refine:
        X, Y = _refine(K, F, X, Y, obs)
    per_pose = _per_pose_rms(K, F, X, Y, obs)
    Y_i = np.array([invert(f) @ X @ c for f, c in zip(F, C, strict=True)])
    spread_mm = 1000.0 * np.linalg.norm(Y_i[:, :3, 3] - Y[:3, 3], axis=1)
    spread_deg = [rotation_angle_deg(y[:3, :3], Y[:3, :3]) for y in Y_i]
    return HandEyeCalibration(
        T_base_camera=X,
        T_flange_board=Y,
        method=best,
        refined=refine,
        board=board,
        intrinsics=intrinsics,
        per_pose_reprojection_rms_px=tuple(float(r) for r in per_pose),
        flange_board_spread_mm=tuple(float(s) for s in spread_mm),
        flange_board_spread_deg=tuple(float(s) for s in spread_deg),
        method_rms_px={m: float(c[2]) for m, c in candidates.items()},
        skipped=tuple(skipped),
    )


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


def available_methods() -> tuple[str, ...]:
    """The linear hand-eye methods this OpenCV build offers (the scipy fallback where it has none)."""
    return OPENCV_METHODS if hasattr(cv2, "calibrateHandEye") else (FALLBACK_METHOD,)


def _linear_hand_eye(method: str, F: np.ndarray, C: np.ndarray) -> np.ndarray | None:
    """``T_base_camera`` from (n, 4, 4) ``T_base_flange`` and ``T_camera_board`` by one linear method."""
    if method == FALLBACK_METHOD:
        return _park_martin(F, C)
    if not hasattr(cv2, "calibrateHandEye"):
        raise CalibrationError(
            f"hand-eye method {method} needs cv2.calibrateHandEye, which this OpenCV build ({cv2.__version__}) lacks "
            f"(opencv/opencv#29565); use {FALLBACK_METHOD}"
        )
    F_inv = np.array([invert(f) for f in F])  # eye-to-hand: the robot poses inverted (see the module docstring)
    R, t = cv2.calibrateHandEye(
        list(F_inv[:, :3, :3]),
        list(F_inv[:, :3, 3:]),
        list(C[:, :3, :3]),
        list(C[:, :3, 3:]),
        method=getattr(cv2, f"CALIB_HAND_EYE_{method}"),
    )
    X = make_T(R, np.asarray(t).reshape(3))
    return X if np.all(np.isfinite(X)) and is_rigid(X, atol=1e-4) else None


def _relative_motions(F: np.ndarray, C: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``A X = X B`` over every pair of poses: ``A = F_j F_i^-1`` (base frame), ``B = C_j C_i^-1`` (camera frame).
    (From ``F_i Y = X C_i`` for the fixed unknowns X = T_base_camera and Y = T_flange_board.)"""
    pairs = list(itertools.combinations(range(len(F)), 2))
    A = np.array([F[j] @ invert(F[i]) for i, j in pairs])
    B = np.array([C[j] @ invert(C[i]) for i, j in pairs])
    return A, B


def _park_martin(F: np.ndarray, C: np.ndarray) -> np.ndarray:
    """Park and Martin's closed form (1994): ``log R_A = R_X log R_B`` solved by orthogonal Procrustes (scipy's
    ``align_vectors``), then ``(R_A - I) t_X = R_X t_B - t_A`` by linear least squares. Written here only because
    OpenCV 5.0.0's wheel lacks ``calibrateHandEye`` (opencv/opencv#29565)."""
    A, B = _relative_motions(F, C)
    alpha = Rotation.from_matrix(A[:, :3, :3]).as_rotvec()
    beta = Rotation.from_matrix(B[:, :3, :3]).as_rotvec()
    R_X = Rotation.align_vectors(alpha, beta)[0].as_matrix()
    M = (A[:, :3, :3] - np.eye(3)).reshape(-1, 3)
    rhs = (B[:, :3, 3] @ R_X.T - A[:, :3, 3]).reshape(-1)
    t_X = np.linalg.lstsq(M, rhs, rcond=None)[0]
    return make_T(R_X, t_X)


def _check_motion(F: np.ndarray) -> None:
    """AX = XB needs rotations about at least two non-parallel axes; refuse a pose set that lacks them."""
    A_rot = Rotation.from_matrix(np.array([f[:3, :3] for f in F[1:]]) @ F[0, :3, :3].T)
    angles = A_rot.magnitude()
    if np.max(angles) < math.radians(5.0):
        raise CalibrationError(
            f"the flange rotated at most {math.degrees(np.max(angles)):.1f} deg across the poses; hand-eye "
            "calibration needs rotations of tens of degrees about different axes"
        )
    axes = A_rot.as_rotvec()[angles > math.radians(2.0)]
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    if np.linalg.svd(axes, compute_uv=False)[1] < 0.1:
        raise CalibrationError("the flange rotated about a single axis only; vary the tilt direction of the poses")


def _mean_mount(F: np.ndarray, C: np.ndarray, X: np.ndarray) -> np.ndarray:
    """``T_flange_board`` implied by X: the mean of ``F_i^-1 X C_i`` (rotation mean by scipy, translation mean)."""
    Y = np.array([invert(f) @ X @ c for f, c in zip(F, C, strict=True)])
    return make_T(Rotation.from_matrix(Y[:, :3, :3]).mean().as_matrix(), Y[:, :3, 3].mean(axis=0))


def _per_pose_rms(
    K: np.ndarray, F: np.ndarray, X: np.ndarray, Y: np.ndarray, obs: list[tuple[np.ndarray, np.ndarray]]
) -> np.ndarray:
    X_inv = invert(X)
    out = []
    for f, (p_board, px) in zip(F, obs, strict=True):
        r = project_points(K, transform_points(X_inv @ f @ Y, p_board)) - px
        out.append(np.sqrt(np.mean(np.sum(r**2, axis=1))))
    return np.array(out)


def _overall_rms(per_pose: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(per_pose))))


def _refine(
    K: np.ndarray, F: np.ndarray, X: np.ndarray, Y: np.ndarray, obs: list[tuple[np.ndarray, np.ndarray]]
) -> tuple[np.ndarray, np.ndarray]:
    """Least squares (scipy) on every corner's reprojection error over the 12 parameters of X and Y: the maximum
    likelihood estimate when the pixels are noisy and the robot poses exact (it fits any robot pose error too)."""

    def unpack(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return (
            make_T(Rotation.from_rotvec(x[0:3]).as_matrix(), x[3:6]),
            make_T(Rotation.from_rotvec(x[6:9]).as_matrix(), x[9:12]),
        )

    def residuals(x: np.ndarray) -> np.ndarray:
        X_, Y_ = unpack(x)
        X_inv = invert(X_)
        return np.concatenate(
            [
                (project_points(K, transform_points(X_inv @ f @ Y_, p_board)) - px).ravel()
                for f, (p_board, px) in zip(F, obs, strict=True)
            ]
        )

    x0 = np.concatenate(
        [
            Rotation.from_matrix(X[:3, :3]).as_rotvec(),
            X[:3, 3],
            Rotation.from_matrix(Y[:3, :3]).as_rotvec(),
            Y[:3, 3],
        ]
    )
    # x_scale: radians vs metres; the board is tens of centimetres from the camera.
    result = least_squares(residuals, x0, method="lm", x_scale=np.tile([0.01, 0.01, 0.01, 0.005, 0.005, 0.005], 2))
    return unpack(result.x)


# ---------------------------------------------------------------------------------------------- file


def save_calibration(path: str | Path, calibration: HandEyeCalibration) -> Path:
    """Writes the calibration JSON atomically (a reader sees the old file or the new one)."""
    return write_json_atomic(path, calibration.to_json())


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
