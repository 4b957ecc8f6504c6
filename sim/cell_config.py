"""The simulated cell's layout and settings: where the robot, bin, tray and cameras are, and the controller gain."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from sygrid.camera import CameraIntrinsics
from sygrid.errors import ConfigError
from sygrid.transforms import is_rigid, make_T


@dataclass(frozen=True, eq=False)
class BoardPlate:
    """A flat printed plate rigidly mounted on the flange (a calibration target): visual only, no mass, no contacts.

    ``image`` (H, W, 3) uint8 RGB is printed on one face of a ``size_xy_m`` plate (the image stretched over the face,
    so keep its aspect ratio), ``thickness_m`` thick. ``T_flange_plate`` is the pose of the image frame in the flange
    frame, in the OpenCV board convention: origin at the image's top-left corner, x along the image columns, y along
    the rows, z into the plate (the printed face looks along -z). The sim knows nothing of the pattern; a ChArUco
    board's ``image`` comes from ``robot.charuco.CharucoBoard.plate``.
    """

    image: np.ndarray
    size_xy_m: tuple[float, float]
    T_flange_plate: np.ndarray
    thickness_m: float = 0.004

    def __post_init__(self) -> None:
        image = np.array(self.image)  # a private, read-only copy
        if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3 or min(image.shape[:2]) < 2:
            raise ConfigError(f"BoardPlate.image must be (H, W, 3) uint8 RGB, got {image.dtype} {image.shape}")
        image.flags.writeable = False
        object.__setattr__(self, "image", image)
        if len(self.size_xy_m) != 2 or min(self.size_xy_m) <= 0 or self.thickness_m <= 0:
            raise ConfigError(
                f"BoardPlate.size_xy_m and thickness_m must be > 0 m, got {self.size_xy_m}, {self.thickness_m}"
            )
        T = np.array(self.T_flange_plate, dtype=float)
        if not is_rigid(T):
            raise ConfigError(f"BoardPlate.T_flange_plate must be a 4x4 rigid transform, got {T.tolist()}")
        T.flags.writeable = False
        object.__setattr__(self, "T_flange_plate", T)


def _default_camera_pose() -> np.ndarray:
    """0.9 m above the bin floor, looking straight down (camera x along world x, image top towards +y)."""
    return make_T(np.diag([1.0, -1.0, -1.0]), (-0.5, 0.0, 0.92))


@dataclass(frozen=True, eq=False)
class CellConfig:
    """Layout and settings of the cell. Lengths in metres; poses are 4x4 in the world frame (table top, z up).

    ``T_world_bin`` and ``T_world_tray`` are the centres of the inner floors. Camera intrinsics are any pinhole
    (``fx != fy`` and an off-centre principal point included: ``sygrid.mjspec.add_camera``).
    """

    timestep_s: float = 0.002
    table_height_m: float = 0.75
    table_size_xy_m: tuple[float, float] = (1.2, 1.2)
    table_center_xy_m: tuple[float, float] = (-0.3, -0.1)
    T_world_base: np.ndarray = field(default_factory=lambda: np.eye(4))
    T_world_bin: np.ndarray = field(default_factory=lambda: make_T(t=(-0.5, 0.0, 0.02)))
    bin_inner_size_m: tuple[float, float, float] = (0.30, 0.20, 0.12)
    bin_wall_thickness_m: float = 0.01
    bin_floor_thickness_m: float = 0.02
    T_world_tray: np.ndarray = field(default_factory=lambda: make_T(t=(-0.2, -0.42, 0.005)))
    tray_inner_size_m: tuple[float, float, float] = (0.24, 0.16, 0.03)
    tray_wall_thickness_m: float = 0.005
    tray_floor_thickness_m: float = 0.005
    T_world_camera: np.ndarray = field(default_factory=_default_camera_pose)
    camera_intrinsics: CameraIntrinsics = field(default_factory=lambda: CameraIntrinsics.from_fov(640, 480, 45.0))
    wrist_camera: bool = False
    T_flange_wrist_camera: np.ndarray = field(default_factory=lambda: make_T(t=(0.0, -0.065, 0.03)))
    wrist_camera_intrinsics: CameraIntrinsics = field(default_factory=lambda: CameraIntrinsics.from_fov(640, 480, 60.0))
    #: Closed-loop bandwidth of the arm's computed-torque controller (rad/s); Kp = w^2, Kd = 2 w.
    arm_bandwidth_rad_s: float = 100.0
    #: A calibration plate on the flange (hand-eye calibration); None: no plate (the default cell).
    calibration_board: BoardPlate | None = None

    def __post_init__(self) -> None:
        if not 0.0 < self.timestep_s <= 0.01:
            raise ConfigError(f"CellConfig.timestep_s must be in (0, 0.01] s, got {self.timestep_s}")
        for name in ("T_world_base", "T_world_bin", "T_world_tray", "T_world_camera", "T_flange_wrist_camera"):
            value = np.array(getattr(self, name), dtype=float)  # a private, read-only copy
            if not is_rigid(value):
                raise ConfigError(f"CellConfig.{name} must be a 4x4 rigid transform, got {value.tolist()}")
            value.flags.writeable = False
            object.__setattr__(self, name, value)
        sizes = {
            "table_height_m": (self.table_height_m,),
            "table_size_xy_m": self.table_size_xy_m,
            "bin_inner_size_m": self.bin_inner_size_m,
            "bin_wall_thickness_m": (self.bin_wall_thickness_m,),
            "bin_floor_thickness_m": (self.bin_floor_thickness_m,),
            "tray_inner_size_m": self.tray_inner_size_m,
            "tray_wall_thickness_m": (self.tray_wall_thickness_m,),
            "tray_floor_thickness_m": (self.tray_floor_thickness_m,),
        }
        for name, values in sizes.items():
            if min(values) <= 0:
                raise ConfigError(f"CellConfig.{name} must be > 0, got {values}")
        for name in ("camera_intrinsics", "wrist_camera_intrinsics"):
            _check_intrinsics(f"CellConfig.{name}", getattr(self, name))
        if not 0.0 < self.arm_bandwidth_rad_s * self.timestep_s <= 0.5:
            raise ConfigError(
                f"CellConfig.arm_bandwidth_rad_s * timestep_s must be in (0, 0.5] for a stable controller, got "
                f"{self.arm_bandwidth_rad_s} * {self.timestep_s}"
            )
        if self.calibration_board is not None and not isinstance(self.calibration_board, BoardPlate):
            raise ConfigError(
                f"CellConfig.calibration_board must be a BoardPlate or None, got {type(self.calibration_board)}"
            )


def _check_intrinsics(name: str, K: CameraIntrinsics) -> None:
    values = (K.fx, K.fy, K.cx, K.cy)
    if not (all(math.isfinite(v) for v in values) and K.fx > 0 and K.fy > 0 and K.width > 0 and K.height > 0):
        raise ConfigError(
            f"{name}: a pinhole camera needs finite intrinsics with fx, fy > 0 and a positive image size; got "
            f"fx={K.fx}, fy={K.fy}, cx={K.cx}, cy={K.cy} for {K.width}x{K.height}"
        )
