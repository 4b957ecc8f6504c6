"""A ChArUco board (OpenCV contrib's ``cv2.aruco.CharucoBoard``): its definition, printable image and JSON form, and
its detection in an image with the board pose from PnP (``cv2.aruco.CharucoDetector`` + ``cv2.solvePnP``).

Board frame (OpenCV's): origin at the outer corner of the top-left chessboard square, x along the columns, y along
the rows, z into the board (the printed face looks along -z). The hand-eye calibration (``robot.calibration``) uses
it; the simulated cell prints ``CharucoBoard.plate`` on a plate on its flange.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from sygrid.camera import CameraIntrinsics, project_points
from sygrid.errors import ConfigError
from sygrid.transforms import make_T, transform_points

DEFAULT_MIN_CORNERS = 8
DEFAULT_MAX_PNP_RMS_PX = 1.5


@dataclass(frozen=True)
class CharucoBoard:
    """A ChArUco board: ``squares_x`` x ``squares_y`` chessboard squares of ``square_m``, ArUco markers of
    ``marker_m`` from the predefined ``dictionary`` (a ``cv2.aruco.DICT_*`` name) in the white squares.

    Board frame (OpenCV's): origin at the outer corner of the top-left square, x along the columns, y along the
    rows, z into the board (the printed face looks along -z). ``legacy_pattern`` selects the pre-4.6 layout of
    boards with an even number of rows (boards printed by old OpenCV versions).
    """

    squares_x: int = 7
    squares_y: int = 5
    square_m: float = 0.03
    marker_m: float = 0.022
    dictionary: str = "DICT_4X4_50"
    legacy_pattern: bool = False

    def __post_init__(self) -> None:
        if self.squares_x < 2 or self.squares_y < 2:
            raise ConfigError(f"CharucoBoard needs at least 2x2 squares, got {self.squares_x}x{self.squares_y}")
        if not 0.0 < self.marker_m < self.square_m:
            raise ConfigError(
                f"CharucoBoard.marker_m must be in (0, square_m = {self.square_m}) m, got {self.marker_m}"
            )
        if not self.dictionary.startswith("DICT_") or not isinstance(getattr(cv2.aruco, self.dictionary, None), int):
            names = sorted(n for n in dir(cv2.aruco) if n.startswith("DICT_"))
            raise ConfigError(f"CharucoBoard.dictionary {self.dictionary!r} is not one of {names}")
        n_markers = (self.squares_x * self.squares_y) // 2
        available = int(self._cv_dictionary().bytesList.shape[0])
        if n_markers > available:
            raise ConfigError(
                f"CharucoBoard {self.squares_x}x{self.squares_y} needs {n_markers} markers; "
                f"{self.dictionary} has only {available}"
            )

    @property
    def size_m(self) -> tuple[float, float]:
        """Width (x) and height (y) of the chessboard, metres."""
        return self.squares_x * self.square_m, self.squares_y * self.square_m

    @property
    def center_board(self) -> np.ndarray:
        """The chessboard's centre in the board frame (3,)."""
        w, h = self.size_m
        return np.array([w / 2, h / 2, 0.0])

    def corners_board(self) -> np.ndarray:
        """(n, 3) inner chessboard corners in the board frame, indexed by ChArUco corner id."""
        return np.asarray(self.cv_board().getChessboardCorners(), dtype=float).reshape(-1, 3)

    def cv_board(self) -> cv2.aruco.CharucoBoard:
        board = cv2.aruco.CharucoBoard(
            (self.squares_x, self.squares_y), self.square_m, self.marker_m, self._cv_dictionary()
        )
        board.setLegacyPattern(self.legacy_pattern)
        return board

    def image(self, px_per_square: int = 100, margin_px: int = 0) -> np.ndarray:
        """The printable board: (H, W) uint8, ``px_per_square`` per square and a white margin of ``margin_px``."""
        if px_per_square < 20 or margin_px < 0:
            raise ValueError(f"px_per_square must be >= 20 and margin_px >= 0, got {px_per_square}, {margin_px}")
        size = (self.squares_x * px_per_square + 2 * margin_px, self.squares_y * px_per_square + 2 * margin_px)
        return self.cv_board().generateImage(size, marginSize=margin_px, borderBits=1)

    def plate(
        self, px_per_square: int = 100, margin_squares: float = 0.5
    ) -> tuple[np.ndarray, tuple[float, float], np.ndarray]:
        """The board printed on a plate with a white margin of ``margin_squares`` squares: (RGB image (H, W, 3)
        uint8, plate size (x, y) in metres, ``T_plate_board``), where the plate frame is the image's top-left corner
        (same axes as the board frame). For ``sim.cell_config.BoardPlate``."""
        margin_px = round(margin_squares * px_per_square)
        gray = self.image(px_per_square, margin_px)
        margin_m = margin_px / px_per_square * self.square_m
        w, h = self.size_m
        rgb = np.repeat(gray[:, :, None], 3, axis=2)
        return rgb, (w + 2 * margin_m, h + 2 * margin_m), make_T(t=(margin_m, margin_m, 0.0))

    def to_json(self) -> dict[str, Any]:
        return {
            "type": "charuco",
            "squares_x": self.squares_x,
            "squares_y": self.squares_y,
            "square_m": self.square_m,
            "marker_m": self.marker_m,
            "dictionary": self.dictionary,
            "legacy_pattern": self.legacy_pattern,
        }

    @classmethod
    def from_json(cls, data: Any, where: str) -> CharucoBoard:
        """Parses ``to_json``'s dict; errors name ``where`` (the file and field)."""
        if not isinstance(data, dict) or data.get("type") != "charuco":
            raise ConfigError(f"{where}: expected a board object with type 'charuco', got {data!r}")
        fields = {
            "squares_x": _as_int(data, "squares_x", where),
            "squares_y": _as_int(data, "squares_y", where),
            "square_m": _as_float(data, "square_m", where),
            "marker_m": _as_float(data, "marker_m", where),
            "dictionary": str(data.get("dictionary", "")),
            "legacy_pattern": bool(data.get("legacy_pattern", False)),
        }
        try:
            return cls(**fields)
        except ConfigError as err:
            raise ConfigError(f"{where}: {err}") from None

    def _cv_dictionary(self) -> cv2.aruco.Dictionary:
        return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))


# ---------------------------------------------------------------------------------------------- detection


@dataclass(frozen=True, eq=False)
class BoardObservation:
    """The board seen in one image: ``T_camera_board``, the detected ChArUco corners (ids (n,), pixels (n, 2))
    and the RMS reprojection error of the PnP pose over them (pixels)."""

    T_camera_board: np.ndarray
    corner_ids: np.ndarray
    corners_px: np.ndarray
    pnp_rms_px: float


class BoardDetector:
    """Detects a ``CharucoBoard`` in undistorted RGB images and estimates its pose.

    An observation is refused (with the reason) when fewer than ``min_corners`` ChArUco corners are found, when
    they lie on one line (no pose from them), or when the PnP pose fits them worse than ``max_pnp_rms_px`` (a
    corner displaced by an occluding edge, a wrong interpolation)."""

    def __init__(
        self,
        board: CharucoBoard,
        min_corners: int = DEFAULT_MIN_CORNERS,
        max_pnp_rms_px: float = DEFAULT_MAX_PNP_RMS_PX,
    ) -> None:
        if min_corners < 4:
            raise ValueError(f"min_corners must be at least 4 (a PnP pose), got {min_corners}")
        self.board = board
        self.min_corners = min_corners
        self.max_pnp_rms_px = max_pnp_rms_px
        self._cv_board = board.cv_board()
        self._detector = cv2.aruco.CharucoDetector(self._cv_board)

    def detect(self, rgb: np.ndarray, intrinsics: CameraIntrinsics) -> tuple[BoardObservation | None, str]:
        """(the observation, "") or (None, why not)."""
        gray = cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY)
        corners, ids, _, _ = self._detector.detectBoard(gray)
        n = 0 if ids is None else len(ids)
        if n < self.min_corners:
            return None, f"{n} ChArUco corners found (need {self.min_corners})"
        ids = ids.reshape(-1).astype(np.int32)
        if self._cv_board.checkCharucoCornersCollinear(ids):
            return None, f"the {n} corners found lie on one line"
        obj, img = self._cv_board.matchImagePoints(corners, ids)
        K = intrinsics.K
        # IPPE is the planar-target PnP (closed form, both mirror solutions compared); LM polishes it on all corners.
        ok, rvec, tvec = cv2.solvePnP(obj, img, K, None, flags=cv2.SOLVEPNP_IPPE)
        if not ok:
            return None, f"solvePnP failed on {n} corners"
        rvec, tvec = cv2.solvePnPRefineLM(obj, img, K, None, rvec, tvec)
        T_camera_board = make_T(cv2.Rodrigues(rvec)[0], tvec.reshape(3))
        corners_px = img.reshape(-1, 2).astype(float)
        residual = project_points(K, transform_points(T_camera_board, obj.reshape(-1, 3))) - corners_px
        rms = float(np.sqrt(np.mean(np.sum(residual**2, axis=1))))
        if T_camera_board[2, 3] <= 0:
            return None, "the PnP pose puts the board behind the camera"
        if rms > self.max_pnp_rms_px:
            return None, f"the PnP pose fits the {n} corners to {rms:.2f} px RMS (limit {self.max_pnp_rms_px})"
        return BoardObservation(T_camera_board, ids, corners_px, rms), ""


def detect_board(
    board: CharucoBoard,
    rgb: np.ndarray,
    intrinsics: CameraIntrinsics,
    min_corners: int = DEFAULT_MIN_CORNERS,
    max_pnp_rms_px: float = DEFAULT_MAX_PNP_RMS_PX,
) -> BoardObservation | None:
    """The board in one image, or None when it is not seen well enough (see ``BoardDetector``)."""
    return BoardDetector(board, min_corners, max_pnp_rms_px).detect(rgb, intrinsics)[0]


def _as_float(data: dict, key: str, where: str) -> float:
    value = data.get(key)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ConfigError(f"{where}: {key} must be a finite number, got {value!r}")
    return float(value)


def _as_int(data: dict, key: str, where: str) -> int:
    value = data.get(key)
    if isinstance(value, bool) or not isinstance(value, int):
        raise ConfigError(f"{where}: {key} must be an integer, got {value!r}")
    return value
