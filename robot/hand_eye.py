"""The eye-to-hand hand-eye solver: pairs (``T_base_flange``, ``T_camera_board``) in, ``T_base_camera`` and the
board mount ``T_flange_board`` out, with their residuals. ``robot.calibration`` collects the pairs.

``solve_hand_eye`` runs OpenCV's linear hand-eye solvers (``cv2.calibrateHandEye``: TSAI, PARK, HORAUD, ANDREFF,
DANIILIDIS), keeps the method whose result reprojects the detected board corners best and, with ``refine=True``,
then fits ``T_base_camera`` and ``T_flange_board`` by least squares to every detected corner.

Eye-to-hand with OpenCV's eye-in-hand solver: ``cv2.calibrateHandEye`` solves ``T_gripper_camera`` from
``T_base_gripper`` and ``T_camera_target``; fed the inverted robot poses ``T_flange_base`` it returns
``T_base_camera`` (the camera is then "on" the base, seen from the flange). The unknown board mount comes out as
``T_flange_board``.

OpenCV version: pyproject.toml allows 4.x only (constraints.txt pins the version tested), because the 5.0.0.93
wheel's Python bindings lack ``cv2.calibrateHandEye`` (opencv/opencv#29565, fixed after that release). Every 4.x
release the project allows has it, so there is no fallback solver; a build without it raises CalibrationError.

Refinement is off by default. It is the maximum-likelihood estimate when only the pixels are noisy and the robot's
reported flange poses are exact, but it fits any error in those poses too, where the linear result is less
sensitive to it; turn it on for a robot whose reported poses are much more accurate than the corner detection.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from robot.charuco import BoardObservation, CharucoBoard
from sygrid.camera import CameraIntrinsics, project_points
from sygrid.errors import SygridError
from sygrid.transforms import invert, is_rigid, make_T, rotation_angle_deg, transform_points

log = logging.getLogger(__name__)

#: OpenCV's hand-eye methods (``cv2.CALIB_HAND_EYE_<name>``), all tried by default.
OPENCV_METHODS = ("TSAI", "PARK", "HORAUD", "ANDREFF", "DANIILIDIS")
MIN_POSES = 3  # two relative motions with non-parallel rotation axes is the minimum of AX = XB

__all__ = [
    "MIN_POSES",
    "OPENCV_METHODS",
    "CalibrationError",
    "HandEyeCalibration",
    "HandEyeSample",
    "solve_hand_eye",
]


class CalibrationError(SygridError, RuntimeError):
    """The calibration could not produce a trustworthy result (too few usable poses, degenerate motion)."""


@dataclass(frozen=True, eq=False)
class HandEyeSample:
    """One usable pose: where the flange was and how the camera saw the board."""

    T_base_flange: np.ndarray
    observation: BoardObservation


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
        return _overall_rms(np.asarray(self.per_pose_reprojection_rms_px))

    @property
    def n_poses(self) -> int:
        return len(self.per_pose_reprojection_rms_px)


def solve_hand_eye(
    samples: Sequence[HandEyeSample],
    board: CharucoBoard,
    intrinsics: CameraIntrinsics,
    *,
    methods: Sequence[str] = OPENCV_METHODS,
    refine: bool = False,
    skipped: Sequence[str] = (),
) -> HandEyeCalibration:
    """``T_base_camera`` from the samples: every OpenCV method in ``methods``, the one with the lowest reprojection
    RMS kept, then with ``refine`` a least-squares fit of ``T_base_camera`` and ``T_flange_board`` to every
    detected corner (see the module docstring). ``skipped`` (the poses left out and why) is kept in the result."""
    if len(samples) < MIN_POSES:
        raise CalibrationError(f"hand-eye calibration needs at least {MIN_POSES} usable poses, got {len(samples)}")
    methods = list(methods)
    unknown = [m for m in methods if m not in OPENCV_METHODS]
    if unknown or not methods:
        raise ValueError(f"unknown hand-eye methods {unknown}; valid: {list(OPENCV_METHODS)}")
    if not hasattr(cv2, "calibrateHandEye"):
        raise CalibrationError(
            f"this OpenCV build ({cv2.__version__}) has no cv2.calibrateHandEye (the 5.0.0.93 wheel lacks it: "
            "opencv/opencv#29565); run scripts/setup.sh, which installs the versions pinned in constraints.txt"
        )
    F = np.array([s.T_base_flange for s in samples])
    C = np.array([s.observation.T_camera_board for s in samples])
    _check_motion(F)
    corners_board = board.corners_board()
    obs = [(corners_board[s.observation.corner_ids], s.observation.corners_px) for s in samples]
    K = intrinsics.K

    candidates: dict[str, tuple[np.ndarray, np.ndarray, float]] = {}
    for method in methods:
        X = _opencv_hand_eye(method, F, C)
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


def _opencv_hand_eye(method: str, F: np.ndarray, C: np.ndarray) -> np.ndarray | None:
    """``T_base_camera`` from (n, 4, 4) ``T_base_flange`` and ``T_camera_board`` by one of OpenCV's methods; None
    when its result is not a finite rigid transform."""
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
