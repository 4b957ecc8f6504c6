"""The parallel gripper's collision volumes and the box maths the grasp generator and planner share.

The gripper is a handful of boxes in the TCP frame (``GraspAnnotation``'s convention: z the approach direction,
pointing into the part; x the line between the pads; origin between the pads): two pads, two finger links, the
housing and the wrist (coupling plus the UR wrist-3 link). Defaults are the cell's 2F-85-like gripper
(``sygrid.robots.gripper_2f85``, which the simulated gripper is built from too).

Why boxes and hand-written maths: FCL is not installed and trimesh's collision manager needs it; the planner asks the
same few questions of hundreds of grasps against thousands of points at once, which numpy does in a few array
operations when the volumes are boxes:

- ``required_backoff_m``: the gripper comes in along its z axis (and leaves the same way); how far must it stay
  back (along -z) so that no point lies in any box's swept column? One number per grasp, and a grasp can then be
  slid back to clear the floor or a neighbour (the pads still have to reach the part).
- ``points_box_distance_m``: the clearance of a grasp (distance from the boxes to the nearest point).
- ``obb_gap_m``: separating-axis gap between oriented boxes (gripper against the bin's walls): > 0 means apart,
  and a lower bound on their distance.

Shapes: ``lo``/``hi`` are box corners ``(..., k, 3)`` in the TCP frame; points ``(n, m, 3)`` are already in each
grasp's TCP frame (n grasps, m points).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sygrid.errors import ConfigError
from sygrid.robots import gripper_2f85, ur5e
from sygrid.robots.kinematics import link_transforms
from sygrid.transforms import make_T, transform_points

# Number of boxes returned by GripperGeometry.boxes, in this order.
BOX_NAMES = ("pad_pos", "pad_neg", "link_pos", "link_neg", "housing", "wrist")
FINGER_BOXES = slice(0, 4)
BODY_BOXES = slice(4, 6)


@dataclass(frozen=True)
class GripperGeometry:
    """Collision boxes of a two-finger parallel gripper, metres, in the TCP frame (z approach, x between the pads).

    Defaults: the cell's 2F-85-like gripper (``sygrid.robots.gripper_2f85``: pads and finger links, the housing),
    and the coupling plus UR wrist-3 link as one box (80 x 80 mm, from the housing's back to 100 mm behind the
    flange, which is ``tcp_offset_m`` behind the TCP).
    """

    stroke_m: float = gripper_2f85.STROKE_M
    tcp_offset_m: float = gripper_2f85.TCP_OFFSET_M
    pad_thickness_m: float = gripper_2f85.PAD_THICKNESS_M
    pad_width_m: float = gripper_2f85.PAD_WIDTH_M
    pad_length_m: float = gripper_2f85.PAD_LENGTH_M
    link_thickness_m: float = gripper_2f85.LINK_THICKNESS_M
    link_width_m: float = gripper_2f85.LINK_WIDTH_M
    link_z_range_m: tuple[float, float] = gripper_2f85.LINK_Z_RANGE_M
    housing_half_xy_m: tuple[float, float] = gripper_2f85.HOUSING_HALF_XY_M
    housing_z_range_m: tuple[float, float] = gripper_2f85.HOUSING_Z_RANGE_M
    wrist_half_xy_m: tuple[float, float] = (0.040, 0.040)
    wrist_z_range_m: tuple[float, float] = (-0.245, -0.130)

    def __post_init__(self) -> None:
        positive = {
            "stroke_m": self.stroke_m,
            "tcp_offset_m": self.tcp_offset_m,
            "pad_thickness_m": self.pad_thickness_m,
            "pad_width_m": self.pad_width_m,
            "pad_length_m": self.pad_length_m,
            "link_thickness_m": self.link_thickness_m,
            "link_width_m": self.link_width_m,
        }
        for name, value in positive.items():
            if not value > 0:
                raise ConfigError(f"GripperGeometry.{name} must be > 0 m, got {value}")
        for name in ("link_z_range_m", "housing_z_range_m", "wrist_z_range_m"):
            lo, hi = getattr(self, name)
            if not lo < hi:
                raise ConfigError(f"GripperGeometry.{name} must be (lower, upper) with lower < upper, got {(lo, hi)}")

    @property
    def T_flange_tcp(self) -> np.ndarray:
        """The TCP (pad centre) in the flange frame: ``tcp_offset_m`` along the flange z axis."""
        return make_T(t=(0.0, 0.0, self.tcp_offset_m))

    @property
    def pad_tip_z_m(self) -> float:
        """z of the pad tips in the TCP frame (the part of the gripper that goes deepest)."""
        return self.pad_length_m / 2.0

    def boxes(self, opening_m: np.ndarray | float, inner_half_m: np.ndarray | float | None = None) -> np.ndarray:
        """``(..., 6, 2, 3)`` boxes ``[lo, hi]`` in the TCP frame, in ``BOX_NAMES`` order, for pads opened to
        ``opening_m`` (distance between the pad faces).

        ``inner_half_m``: where each pad's inner face starts (x, per side); default ``opening_m / 2``. Set it to the
        part's half width to cover the pads' whole closing stroke.
        """
        opening = np.asarray(opening_m, dtype=float)
        if inner_half_m is None:
            inner = opening / 2.0
        else:
            inner = np.broadcast_to(np.asarray(inner_half_m, dtype=float), opening.shape)
        out = np.zeros((*opening.shape, 6, 2, 3))
        outer_pad = opening / 2.0 + self.pad_thickness_m
        outer_link = outer_pad + self.link_thickness_m
        half_pad_w, half_link_w, half_pad_l = self.pad_width_m / 2, self.link_width_m / 2, self.pad_length_m / 2
        for k, sign in ((0, 1.0), (1, -1.0)):
            # pads
            x0, x1 = sign * inner, sign * outer_pad
            out[..., k, 0, 0], out[..., k, 1, 0] = np.minimum(x0, x1), np.maximum(x0, x1)
            out[..., k, 0, 1:] = (-half_pad_w, -half_pad_l)
            out[..., k, 1, 1:] = (half_pad_w, half_pad_l)
            # finger links
            x0, x1 = sign * outer_pad, sign * outer_link
            out[..., 2 + k, 0, 0], out[..., 2 + k, 1, 0] = np.minimum(x0, x1), np.maximum(x0, x1)
            out[..., 2 + k, 0, 1:] = (-half_link_w, self.link_z_range_m[0])
            out[..., 2 + k, 1, 1:] = (half_link_w, self.link_z_range_m[1])
        for k, (half_xy, z_range) in (
            (4, (self.housing_half_xy_m, self.housing_z_range_m)),
            (5, (self.wrist_half_xy_m, self.wrist_z_range_m)),
        ):
            out[..., k, 0, :] = (-half_xy[0], -half_xy[1], z_range[0])
            out[..., k, 1, :] = (half_xy[0], half_xy[1], z_range[1])
        return out


# ---------------------------------------------------------------------------------------------- points vs boxes


def box_corners(boxes: np.ndarray) -> np.ndarray:
    """``(..., b, 2, 3)`` boxes -> ``(..., b * 8, 3)`` corners."""
    lo, hi = boxes[..., 0, :], boxes[..., 1, :]
    corners = [
        np.stack([(hi if i else lo)[..., 0], (hi if j else lo)[..., 1], (hi if k else lo)[..., 2]], axis=-1)
        for i in (0, 1)
        for j in (0, 1)
        for k in (0, 1)
    ]
    stacked = np.stack(corners, axis=-2)  # (..., b, 8, 3)
    return stacked.reshape(*stacked.shape[:-3], -1, 3)


def part_box_tcp(T_base_tcp: np.ndarray, T_base_obj: np.ndarray, bounds_m: np.ndarray) -> np.ndarray:
    """``(k, 2, 3)`` the axis-aligned box, in each grasp's TCP frame (``T_base_tcp`` ``(k, 4, 4)``), around a part's
    bounds (``(2, 3)``, object frame; the part at ``T_base_obj``): what the gripper carries out of the bin."""
    lo, hi = np.asarray(bounds_m, dtype=float)
    corners_obj = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    corners_base = transform_points(T_base_obj, corners_obj)
    T_inv = np.linalg.inv(T_base_tcp)
    local = np.einsum("kij,pj->kpi", T_inv[:, :3, :3], corners_base) + T_inv[:, None, :3, 3]
    return np.stack([local.min(axis=1), local.max(axis=1)], axis=1)


def rotate(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``(k, p, 3)`` points rotated by each ``T[k]``'s rotation (a batched matrix product: faster than einsum)."""
    return np.matmul(points, np.swapaxes(T[:, :3, :3], 1, 2))


def required_backoff_m(
    points: np.ndarray,
    boxes: np.ndarray,
    clearance_m: float,
    valid: np.ndarray | None = None,
    sweep_length_m: float | None = None,
) -> np.ndarray:
    """How far each grasp must stay back along its -z axis so that no point is within ``clearance_m`` of the
    gripper's boxes swept along z on the approach; ``(n,)`` metres (negative: it could go that much deeper).

    points: ``(n, m, 3)`` in each grasp's TCP frame. boxes: ``(n, k, 2, 3)`` or ``(k, 2, 3)``. valid: ``(n, m)``
    mask of the points to consider (None: all). sweep_length_m: the approach starts that far back (the
    pre-grasp); points behind a box's back face by more than this are not on the path. None: no limit.
    """
    n, m = points.shape[:2]
    if m == 0:
        return np.full(n, -np.inf)
    boxes = np.broadcast_to(boxes, (n, *boxes.shape[-3:]))
    out = np.full(n, -np.inf)
    x, y, z = (np.ascontiguousarray(points[..., i]) for i in range(3))  # contiguous rows compare faster
    for b in range(boxes.shape[1]):
        lo, hi = boxes[:, b, 0, :], boxes[:, b, 1, :]
        inside = (
            (x >= lo[:, None, 0] - clearance_m)
            & (x <= hi[:, None, 0] + clearance_m)
            & (y >= lo[:, None, 1] - clearance_m)
            & (y <= hi[:, None, 1] + clearance_m)
        )
        if sweep_length_m is not None:
            inside &= z >= lo[:, None, 2] - clearance_m - sweep_length_m
        if valid is not None:
            inside &= valid
        need = np.where(inside, hi[:, None, 2] + clearance_m - z, -np.inf)
        out = np.maximum(out, need.max(axis=1))
    return out


def points_box_distance_m(
    points: np.ndarray, boxes: np.ndarray, valid: np.ndarray | None = None, cap_m: float = np.inf
) -> np.ndarray:
    """``(n,)`` the smallest distance from any (valid) point to any box (0 inside), capped at ``cap_m``."""
    n, m = points.shape[:2]
    if m == 0:
        return np.full(n, cap_m)
    boxes = np.broadcast_to(boxes, (n, *boxes.shape[-3:]))
    best = np.full(n, cap_m)
    for b in range(boxes.shape[1]):
        lo, hi = boxes[:, b, 0, :][:, None, :], boxes[:, b, 1, :][:, None, :]
        outside = np.maximum(np.maximum(lo - points, points - hi), 0.0)
        dist2 = np.einsum("nmi,nmi->nm", outside, outside)
        if valid is not None:
            dist2 = np.where(valid, dist2, np.inf)
        best = np.minimum(best, np.sqrt(dist2.min(axis=1)))
    return best


# ---------------------------------------------------------------------------------------------- oriented boxes


def obb_gap_m(
    centre_a: np.ndarray, R_a: np.ndarray, half_a: np.ndarray, centre_b: np.ndarray, R_b: np.ndarray, half_b: np.ndarray
) -> np.ndarray:
    """Separating-axis gap between oriented boxes, broadcast over leading dimensions.

    centre ``(..., 3)``, R ``(..., 3, 3)`` (box axes as columns), half ``(..., 3)`` half sizes. Returns ``(...)``:
    the largest gap along the 15 candidate axes (3 + 3 face normals, 9 edge cross products). > 0: the boxes are
    apart by at least that much (a lower bound on their distance, exact when the closest features are faces);
    <= 0: they overlap.
    """
    centre_a, R_a, half_a = np.asarray(centre_a), np.asarray(R_a), np.asarray(half_a)
    centre_b, R_b, half_b = np.asarray(centre_b), np.asarray(R_b), np.asarray(half_b)
    shape = np.broadcast_shapes(centre_a.shape[:-1], centre_b.shape[:-1], R_a.shape[:-2], R_b.shape[:-2])
    axes_a = np.broadcast_to(np.swapaxes(R_a, -1, -2), (*shape, 3, 3))  # rows: A's axes
    axes_b = np.broadcast_to(np.swapaxes(R_b, -1, -2), (*shape, 3, 3))
    cross = np.cross(axes_a[..., :, None, :], axes_b[..., None, :, :]).reshape(*shape, 9, 3)
    norm = np.linalg.norm(cross, axis=-1, keepdims=True)
    # parallel edges give no axis: their cross product is dropped (its face axes already cover the case)
    cross = np.where(norm > 1e-9, cross / np.maximum(norm, 1e-12), 0.0)
    axes = np.concatenate([axes_a, axes_b, cross], axis=-2)  # (..., 15, 3)
    usable = np.concatenate(
        [np.ones((*shape, 6), dtype=bool), np.broadcast_to(norm[..., 0] > 1e-9, (*shape, 9))], axis=-1
    )
    delta = np.broadcast_to(centre_b - centre_a, (*shape, 3))
    # batched matrix products (matmul is several times faster than the equivalent einsum here)
    dist = np.abs(np.matmul(axes, delta[..., None])[..., 0])
    half_a = np.broadcast_to(half_a, (*shape, 3))[..., None]
    half_b = np.broadcast_to(half_b, (*shape, 3))[..., None]
    r_a = np.matmul(np.abs(np.matmul(axes, np.swapaxes(axes_a, -1, -2))), half_a)[..., 0]
    r_b = np.matmul(np.abs(np.matmul(axes, np.swapaxes(axes_b, -1, -2))), half_b)[..., 0]
    gap = np.where(usable, dist - r_a - r_b, -np.inf)
    return gap.max(axis=-1)


#: The wrist links (wrist 1, 2, 3) whose boxes the planner keeps clear of the bin walls: near a wall, with an inclined
#: approach, the wrist reaches over the rim before the fingers do. Indices into ``ur5e.LINK_NAMES``.
WRIST_LINKS = (3, 4, 5)


def link_frames(q: np.ndarray) -> np.ndarray:
    """``(n, 6, 4, 4)`` ``T_base_link`` of the six arm links at configurations ``q`` ``(n, 6)``: each link's body
    frame is its joint frame, DH frame ``i`` (``link_transforms``) turned by ``q_i`` (as ``sim.cell_model`` builds
    it), so ``ur5e.LINK_CYLINDERS_M[i + 1]`` are in it."""
    q = np.atleast_2d(np.asarray(q, dtype=float))
    c, s = np.cos(q), np.sin(q)
    Rz = np.zeros((*q.shape, 4, 4))
    Rz[..., 0, 0], Rz[..., 0, 1], Rz[..., 1, 0], Rz[..., 1, 1] = c, -s, s, c
    Rz[..., 2, 2] = Rz[..., 3, 3] = 1.0
    return link_transforms(q)[:, :6] @ Rz


def wrist_link_frames(q: np.ndarray) -> np.ndarray:
    """``(n, 3, 4, 4)`` ``T_base_link`` of the wrist links (``link_frames``)."""
    return link_frames(q)[:, WRIST_LINKS]


#: The upper arm and forearm: on a joint move between the tray and a grasp far into the bin the elbow can swing
#: low over the tray.
ELBOW_LINKS = (1, 2)


def lowest_elbow_point_m(q: np.ndarray) -> np.ndarray:
    """``(n,)`` the lowest point (base-frame z, m) of the upper arm's and forearm's collision cylinders at each
    configuration ``q`` ``(n, 6)``; exact for the cylinders: an end's z less the radius times the sine of the
    axis's tilt from vertical."""
    frames = link_frames(q)
    lowest = np.full(len(frames), np.inf)
    for i in ELBOW_LINKS:
        for p0, p1, r in ur5e.LINK_CYLINDERS_M[i + 1]:
            ends = np.array([p0, p1], dtype=float)
            ends_base = np.einsum("nij,cj->nci", frames[:, i, :3, :3], ends) + frames[:, i, None, :3, 3]
            axis = ends_base[:, 1] - ends_base[:, 0]
            cos_z = np.abs(axis[:, 2]) / np.linalg.norm(axis, axis=1)
            low = ends_base[:, :, 2].min(axis=1) - r * np.sqrt(np.clip(1.0 - cos_z**2, 0.0, 1.0))
            lowest = np.minimum(lowest, low)
    return lowest


def wrist_link_boxes_m() -> np.ndarray:
    """``(3, 2, 3)`` ``[lo, hi]`` of each wrist link's collision cylinders (``ur5e.LINK_CYLINDERS_M``, all along the
    link frame's z) as one box in that link's body frame (``link_frames``)."""
    boxes = []
    for i in WRIST_LINKS:
        cyl = ur5e.LINK_CYLINDERS_M[i + 1]  # index 0 is the robot base
        ends = np.array([(p0, p1) for p0, p1, _ in cyl])  # (c, 2, 3)
        radius = np.array([r for _, _, r in cyl])[:, None] * np.array([1.0, 1.0, 0.0])
        assert np.allclose(ends[:, 0, :2], ends[:, 1, :2]), "wrist link cylinders run along z"
        boxes.append([(ends.min(axis=1) - radius).min(axis=0), (ends.max(axis=1) + radius).max(axis=0)])
    return np.array(boxes, dtype=float)
