"""What the grasp planner knows of the scene besides the parts' poses: the bin, the depth camera's points, and the
obstacles they make together with the estimated parts.

The bin is an open box (``sygrid.mjspec.open_box_parts``, the same five boxes the simulated cell and the
generator's drop build), given by the pose of the centre of its inner floor in the robot base frame. The depth
frame becomes points in the base frame; the points that are the bin itself (floor, walls, anything outside it)
are dropped, because the planner checks the bin exactly from its geometry, and what is left is the pile. The pile's
points and a sample of every estimated part's surface are the obstacles (``scene_obstacles``); a part with them
above much of its top is covered (``covered_fraction``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from sygrid.camera import CameraIntrinsics
from sygrid.errors import ConfigError
from sygrid.mjspec import open_box_parts
from sygrid.scene import bin_inner_corners
from sygrid.transforms import invert, is_rigid, make_T, transform_points

_NEIGHBOUR_SAMPLES = 400  # of a part's surface sample, the points it contributes as obstacles
_COVER_CELL_M = 0.004  # height-map cell of the covered test
_UPWARD_COS = 0.5  # a surface point faces up when its normal is within 60 degrees of up


def _default_bin_pose() -> np.ndarray:
    """The simulated cell's bin (``sim.cell_config.CellConfig``: robot base at the world origin)."""
    return make_T(t=(-0.5, 0.0, 0.02))


@dataclass(frozen=True, eq=False)
class BinGeometry:
    """An open bin: ``T_base_bin`` is the centre of its inner floor (z up, out of the bin), metres.

    Defaults: the simulated cell's bin (300 x 200 x 120 mm inside, 10 mm walls, 20 mm floor).
    """

    T_base_bin: np.ndarray = field(default_factory=_default_bin_pose)
    inner_size_m: tuple[float, float, float] = (0.30, 0.20, 0.12)
    wall_thickness_m: float = 0.01
    floor_thickness_m: float = 0.02

    def __post_init__(self) -> None:
        T = np.array(self.T_base_bin, dtype=float)
        if not is_rigid(T):
            raise ConfigError(f"BinGeometry.T_base_bin must be a 4x4 rigid transform, got {T.tolist()}")
        T.flags.writeable = False
        object.__setattr__(self, "T_base_bin", T)
        if len(self.inner_size_m) != 3 or min(self.inner_size_m) <= 0:
            raise ConfigError(f"BinGeometry.inner_size_m must be 3 lengths > 0 m, got {self.inner_size_m}")
        if self.wall_thickness_m <= 0 or self.floor_thickness_m <= 0:
            raise ConfigError(
                f"BinGeometry wall and floor thickness must be > 0 m, got {self.wall_thickness_m}, "
                f"{self.floor_thickness_m}"
            )

    @property
    def floor_normal(self) -> np.ndarray:
        """(3,) the floor's normal (the bin's z axis) in the base frame."""
        return self.T_base_bin[:3, 2].copy()

    @property
    def floor_point(self) -> np.ndarray:
        """(3,) the centre of the inner floor in the base frame."""
        return self.T_base_bin[:3, 3].copy()

    def wall_boxes(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The four walls as oriented boxes in the base frame: centres ``(4, 3)``, rotations ``(4, 3, 3)``, half
        sizes ``(4, 3)`` (the floor is checked as a plane, see ``height_above_floor_m``)."""
        parts = open_box_parts(self.inner_size_m, self.wall_thickness_m, self.floor_thickness_m)
        walls = [parts[name] for name in ("wall_xp", "wall_xn", "wall_yp", "wall_yn")]
        centres = transform_points(self.T_base_bin, np.array([c for c, _ in walls], dtype=float))
        halves = np.array([h for _, h in walls], dtype=float)
        return centres, np.broadcast_to(self.T_base_bin[:3, :3], (4, 3, 3)).copy(), halves

    def inner_corners_camera(self, T_base_camera: np.ndarray) -> np.ndarray:
        """(8, 3) the corners of the inner volume (floor and rim), where parts can be, in the camera frame."""
        return transform_points(invert(T_base_camera) @ self.T_base_bin, bin_inner_corners(self.inner_size_m))

    def floor_plane_camera(self, T_base_camera: np.ndarray) -> np.ndarray:
        """(4,) the inner floor's plane ``(a, b, c, d)`` in the camera frame: a point p lies ``(a, b, c) . p + d``
        above the floor."""
        T_camera_bin = invert(T_base_camera) @ self.T_base_bin
        normal = T_camera_bin[:3, 2]
        return np.append(normal, -normal @ T_camera_bin[:3, 3])

    def height_above_floor_m(self, points_base: np.ndarray) -> np.ndarray:
        """(...,) signed height of points ``(..., 3)`` above the inner floor's plane."""
        return (np.asarray(points_base) - self.floor_point) @ self.floor_normal

    def holds(self, point_base: np.ndarray) -> bool:
        """Whether a point (a part's centre, base frame) is in the bin: inside its inner footprint and above its
        floor, at any height (a part above the bin, held or falling, is still the bin's)."""
        p = transform_points(invert(self.T_base_bin), np.asarray(point_base, dtype=float).reshape(1, 3))[0]
        return bool(abs(p[0]) < self.inner_size_m[0] / 2 and abs(p[1]) < self.inner_size_m[1] / 2 and p[2] > 0.0)

    def pile_points(self, points_base: np.ndarray, surface_tolerance_m: float) -> np.ndarray:
        """The points ``(n, 3)`` that lie inside the bin, more than ``surface_tolerance_m`` from its floor and walls
        (those are the bin itself, or beyond it); parts sticking out over the rim are kept."""
        points_base = np.asarray(points_base, dtype=float)
        p_bin = transform_points(invert(self.T_base_bin), points_base)
        return points_base[self.in_pile_bin_frame(p_bin, surface_tolerance_m)]

    def in_pile_bin_frame(self, points_bin: np.ndarray, surface_tolerance_m: float) -> np.ndarray:
        """``(n,)`` bool: ``pile_points``'s test for points ``(n, 3)`` already in the bin frame."""
        half_x, half_y = self.inner_size_m[0] / 2, self.inner_size_m[1] / 2
        return (
            (np.abs(points_bin[:, 0]) < half_x - surface_tolerance_m)
            & (np.abs(points_bin[:, 1]) < half_y - surface_tolerance_m)
            & (points_bin[:, 2] > surface_tolerance_m)
        )

    def pile_points_from_depth(
        self,
        depth_m: np.ndarray,
        intrinsics: CameraIntrinsics | np.ndarray,
        T_base_camera: np.ndarray,
        stride_px: int,
        surface_tolerance_m: float,
    ) -> np.ndarray:
        """``(n, 3)`` the points of a depth frame (``depth_points``, every ``stride_px``-th pixel) that are the pile
        (``pile_points``), in the bin frame."""
        T_bin_camera = invert(self.T_base_bin) @ T_base_camera
        points_bin = depth_points(depth_m, intrinsics, T_bin_camera, stride_px)
        return points_bin[self.in_pile_bin_frame(points_bin, surface_tolerance_m)]

    def pile_area_m2(
        self,
        depth_m: np.ndarray,
        intrinsics: CameraIntrinsics | np.ndarray,
        T_base_camera: np.ndarray,
        stride_px: int,
        surface_tolerance_m: float,
    ) -> float:
        """How much of the bin the depth frame shows covered by something above its floor (m2: the footprints of
        the pile's depth pixels, ``pile_points_from_depth``, at their distance from the camera)."""
        points_bin = self.pile_points_from_depth(depth_m, intrinsics, T_base_camera, stride_px, surface_tolerance_m)
        K = intrinsics.K if isinstance(intrinsics, CameraIntrinsics) else np.asarray(intrinsics, dtype=float)
        camera_bin = (invert(self.T_base_bin) @ T_base_camera)[:3, 3]
        distance2 = np.sum((points_bin - camera_bin) ** 2, axis=1)
        return float(distance2.sum() * stride_px**2 / (K[0, 0] * K[1, 1]))


def depth_points(
    depth_m: np.ndarray,
    intrinsics: CameraIntrinsics | np.ndarray,
    T_frame_camera: np.ndarray,
    stride_px: int = 1,
) -> np.ndarray:
    """``(n, 3)`` points of a depth frame (metres, 0 = no data) in the frame ``T_frame_camera`` maps to (e.g. the
    robot base), every ``stride_px``-th pixel in each direction (the cloud's spacing; the planner needs a few
    millimetres, not every pixel).

    Raises:
        ValueError: the depth is not a 2-D array, or the intrinsics do not match its size.
    """
    depth = np.asarray(depth_m, dtype=np.float32)
    if depth.ndim != 2:
        raise ValueError(f"depth_m must be a (H, W) array in metres, got shape {depth.shape}")
    if isinstance(intrinsics, CameraIntrinsics):
        if (intrinsics.height, intrinsics.width) != depth.shape:
            raise ValueError(
                f"depth_m is {depth.shape[1]}x{depth.shape[0]} but the intrinsics are for "
                f"{intrinsics.width}x{intrinsics.height}"
            )
        K = intrinsics.K
    else:
        K = np.asarray(intrinsics, dtype=float)
        if K.shape != (3, 3):
            raise ValueError(f"intrinsics must be a CameraIntrinsics or a 3x3 K matrix, got shape {K.shape}")
    stride = max(int(stride_px), 1)
    z = depth[::stride, ::stride]
    v, u = np.nonzero(z > 0)
    z = z[v, u]
    # sygrid.camera.unproject_depth's pinhole model, only at the pixels with data, in float32 element-wise
    # arithmetic (no BLAS threads: this runs beside the perception stack on two cores)
    x = (u * stride - np.float32(K[0, 2])) * z / np.float32(K[0, 0])
    y = (v * stride - np.float32(K[1, 2])) * z / np.float32(K[1, 1])
    T = np.asarray(T_frame_camera, dtype=np.float32)
    out = np.empty((len(z), 3))
    for i in range(3):
        out[:, i] = T[i, 0] * x + T[i, 1] * y + T[i, 2] * z + T[i, 3]
    return out


def pile_cloud(
    bin_geometry: BinGeometry | None,
    depth_m: np.ndarray,
    intrinsics: CameraIntrinsics | np.ndarray,
    T_base_camera: np.ndarray,
    stride_px: int,
    surface_tolerance_m: float,
) -> np.ndarray:
    """``(n, 3)`` a depth frame's points of the pile (``BinGeometry.pile_points_from_depth``) in the base frame;
    without a bin, all its points (``depth_points``)."""
    if bin_geometry is None:
        return depth_points(depth_m, intrinsics, T_base_camera, stride_px)
    points_bin = bin_geometry.pile_points_from_depth(depth_m, intrinsics, T_base_camera, stride_px, surface_tolerance_m)
    return transform_points(bin_geometry.T_base_bin, points_bin)


def scene_obstacles(
    cloud: np.ndarray, surfaces: list[np.ndarray | None], own_points_tolerance_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """Every obstacle point of the scene, ``(m, 3)`` base frame, with the index of the part it belongs to (``(m,)``,
    -1: none): the ``cloud`` points (``(n, 3)``; a point within ``own_points_tolerance_m`` of a part's estimated
    surface belongs to the nearest such part) and a sample of each part's estimated surface (``surfaces[i]``:
    ``(s, 3)`` base frame, None for a part without a model), which also stands for its unseen sides."""
    known = [i for i, s in enumerate(surfaces) if s is not None]
    owner = cloud_owners(cloud, surfaces, own_points_tolerance_m)
    samples = [surfaces[i][:_NEIGHBOUR_SAMPLES] for i in known]
    points = np.concatenate([cloud, *samples]) if samples else cloud
    owner = np.concatenate([owner, *[np.full(len(s), i) for i, s in zip(known, samples, strict=True)]])
    return points, owner


def cloud_owners(cloud: np.ndarray, surfaces: list[np.ndarray | None], own_points_tolerance_m: float) -> np.ndarray:
    """``(n,)`` the index of the part each ``cloud`` point (``(n, 3)`` base frame) belongs to: the part whose estimated
    surface (``surfaces[i]``, ``(s, 3)`` base frame; None: no model) lies nearest within ``own_points_tolerance_m``;
    -1 for a point on none of them (an unseen part, or a seen one where its estimate is off)."""
    known = [i for i, s in enumerate(surfaces) if s is not None]
    owner = np.full(len(cloud), -1)
    if len(cloud) and known:
        points = np.concatenate([surfaces[i] for i in known])
        labels = np.concatenate([np.full(len(surfaces[i]), i) for i in known])
        dist, nearest = cKDTree(points).query(cloud, k=1, distance_upper_bound=own_points_tolerance_m)
        hit = np.isfinite(dist)
        owner[hit] = labels[nearest[hit]]
    return owner


def covered_fraction(
    surface_obj: np.ndarray,
    normals_obj: np.ndarray,
    T_base_obj: np.ndarray,
    obstacles: np.ndarray,
    up: np.ndarray,
    cover_tolerance_m: float,
) -> float:
    """Share of a part's upward-facing surface points (``surface_obj`` and their ``normals_obj``, ``(n, 3)`` object
    frame; the part at ``T_base_obj``) with an obstacle point (``(m, 3)`` base frame) more than
    ``cover_tolerance_m`` above them (along ``up``, in the same cell of a height map); 0 when there are none."""
    normals = normals_obj @ T_base_obj[:3, :3].T
    top = transform_points(T_base_obj, surface_obj[normals @ up > _UPWARD_COS])
    if not len(top) or not len(obstacles):
        return 0.0
    lo = top[:, :2].min(axis=0) - _COVER_CELL_M
    shape = np.ceil((top[:, :2].max(axis=0) + _COVER_CELL_M - lo) / _COVER_CELL_M).astype(int) + 1
    over = obstacles[np.all((obstacles[:, :2] >= lo) & (obstacles[:, :2] < lo + shape * _COVER_CELL_M), axis=1)]
    cells = np.clip(np.floor((over[:, :2] - lo) / _COVER_CELL_M).astype(int), 0, shape - 1)
    height = np.full(shape, -np.inf)
    np.maximum.at(height, (cells[:, 0], cells[:, 1]), over @ up)
    top_cells = np.floor((top[:, :2] - lo) / _COVER_CELL_M).astype(int)
    above = height[top_cells[:, 0], top_cells[:, 1]] > top @ up + cover_tolerance_m
    return float(above.mean())
