"""The grasp planner's collision checks, as numpy over many grasps or configurations at once: the gripper's boxes
(``robot.grasp_geometry``) against the bin's walls (oriented boxes) and floor (a plane) and against obstacle points
(depth points, neighbours' surfaces), the wrist links against the walls, and the joint moves (straight lines in
joint space) against the walls and for the elbow's height. A move of the tool along its own z (the approach, and
back out) sweeps each box into a longer box, so the straight-line moves in and out of the bin are box checks too.

Gaps are signed (m; < 0: overlap) and infinite without a bin. Poses ``T`` are ``(k, 4, 4)`` TCP poses in the base
frame; boxes ``(k, b, 2, 3)`` ``[lo, hi]`` in each pose's TCP frame.
"""

from __future__ import annotations

import math

import numpy as np

from robot.grasp_config import PlannerConfig
from robot.grasp_geometry import (
    WRIST_LINKS,
    GripperGeometry,
    box_corners,
    lowest_elbow_point_m,
    obb_gap_m,
    rotate,
    wrist_link_boxes_m,
    wrist_link_frames,
)
from sygrid.robots.kinematics import forward_kinematics
from sygrid.transforms import invert


class CollisionChecker:
    """The collision checks of a ``PlannerConfig``: its bin, gripper and clearances."""

    def __init__(self, config: PlannerConfig) -> None:
        self.config = config
        self._wrist_boxes = wrist_link_boxes_m()

    def wall_gap_m(self, T: np.ndarray, boxes: np.ndarray, threshold_m: float | None = None) -> np.ndarray:
        """``(k,)`` the smallest gap (m; < 0: overlap) between the bin walls and each pose's boxes: ``T`` ``(k, 4,
        4)`` TCP poses in the base frame, ``boxes`` ``(k, b, 2, 3)`` in their TCP frames. Exact below
        ``threshold_m`` (default ``bin_clearance_m``), a lower bound above it."""
        return self._wall_gap_per_box(T, boxes, threshold_m).min(axis=1)

    def _wall_gap_per_box(self, T: np.ndarray, boxes: np.ndarray, threshold_m: float | None = None) -> np.ndarray:
        """``(k, b)`` gap between each grasp's boxes (``(k, b, 2, 3)``, TCP frame) and the bin walls (a lower
        bound on the distance; < 0: they overlap).

        Two cheap lower bounds per box first: a box whose corners all lie inside the bin's inner prism (extended
        upwards) is as far from the walls as its corners are; a box whose corners all lie above the rim is at least
        that high above it. Only boxes for which neither bound reaches ``threshold_m`` (default
        ``bin_clearance_m``) go through the separating-axis test."""
        b = self.config.bin
        k, nb = boxes.shape[:2]
        corners = box_corners(boxes).reshape(k, nb, 8, 3)
        T_bin_tcp = invert(b.T_base_bin) @ T
        c_bin = rotate(T_bin_tcp, corners.reshape(k, nb * 8, 3)).reshape(k, nb, 8, 3) + T_bin_tcp[:, None, None, :3, 3]
        half_xy = np.array(b.inner_size_m[:2]) / 2.0
        inside = (half_xy - np.abs(c_bin[..., :2])).min(axis=(2, 3))  # (k, b)
        above = c_bin[..., 2].min(axis=2) - b.inner_size_m[2]
        gap = np.maximum(inside, above)
        hard_k, hard_b = np.nonzero(gap < (self.config.bin_clearance_m if threshold_m is None else threshold_m))
        if len(hard_k):
            sub = boxes[hard_k, hard_b]  # (h, 2, 3)
            centre_tcp, half = sub.mean(axis=-2), (sub[:, 1, :] - sub[:, 0, :]) / 2.0  # (h, 3)
            R = T[hard_k, :3, :3]
            centre = np.einsum("hij,hj->hi", R, centre_tcp) + T[hard_k, :3, 3]
            wc, wR, wh = b.wall_boxes()
            sat = obb_gap_m(centre[:, None, :], R[:, None], half[:, None, :], wc, wR, wh)  # (h, 4)
            gap[hard_k, hard_b] = sat.min(axis=1)
        return gap

    def transit_gap_m(self, q_from: np.ndarray, q_to: np.ndarray, boxes_tcp: np.ndarray) -> float:
        """The smallest gap (m; < 0: overlap; inf without a bin) between the bin walls and ``boxes_tcp``
        (``(b, 2, 3)`` in the TCP frame, e.g. the gripper's) carried along the straight joint-space line from
        ``q_from`` to ``q_to`` (what a joint move does), sampled every ``transit_step_rad`` of the largest joint
        change."""
        cfg = self.config
        if cfg.bin is None:
            return math.inf
        q = joint_line(q_from, q_to, cfg.transit_step_rad)
        n = len(q)
        T = forward_kinematics(q, cfg.gripper.T_flange_tcp)
        boxes = np.broadcast_to(np.asarray(boxes_tcp, dtype=float), (n, *np.shape(boxes_tcp)))
        gripper = float(self.wall_gap_m(T, boxes, cfg.transit_clearance_m or 0.0).min())
        return min(gripper, float(self.wrist_gap_m(q, cfg.transit_clearance_m or 0.0).min()))

    def elbow_clear(self, q_from: np.ndarray, q_to: np.ndarray) -> bool:
        """Whether the upper arm and forearm stay above ``min_elbow_height_m`` along the joint move."""
        if self.config.min_elbow_height_m is None:
            return True
        q = joint_line(q_from, q_to, self.config.transit_step_rad)
        return bool(lowest_elbow_point_m(q).min() >= self.config.min_elbow_height_m)

    def wrist_gap_m(self, q: np.ndarray, threshold_m: float | None = None) -> np.ndarray:
        """``(n,)`` the smallest gap (m; < 0: overlap; inf without a bin) between the bin walls and the wrist links'
        boxes at each of the configurations ``q`` ``(n, 6)``."""
        q = np.atleast_2d(np.asarray(q, dtype=float))
        if self.config.bin is None:
            return np.full(len(q), math.inf)
        T_base_link = wrist_link_frames(q)
        boxes = np.broadcast_to(self._wrist_boxes[:, None], (len(q), len(WRIST_LINKS), 1, 2, 3))
        gap = self.wall_gap_m(T_base_link.reshape(-1, 4, 4), boxes.reshape(-1, 1, 2, 3), threshold_m)
        return gap.reshape(len(q), len(WRIST_LINKS)).min(axis=1)

    def lift_distance(
        self, T: np.ndarray, boxes_closed: np.ndarray, surface_base: np.ndarray, cos_angle: np.ndarray
    ) -> np.ndarray:
        """``(k,)`` how far back along the approach each grasp's lift is: ``lift_height_m``, or more until the
        gripper's boxes (``(k, b, 2, 3)``, TCP frame, closed on the part) and the part (its surface points in the
        base frame, at rest) are ``rim_clearance_m`` above the bin's rim."""
        cfg = self.config
        lift = np.full(len(T), cfg.lift_height_m)
        if cfg.bin is None or not len(T):
            return lift
        corners = box_corners(boxes_closed)
        points = rotate(T, corners) + T[:, None, :3, 3]
        low = np.minimum(
            cfg.bin.height_above_floor_m(points).min(axis=1), float(cfg.bin.height_above_floor_m(surface_base).min())
        )
        # moving back by d along the approach raises everything by d * cos(angle)
        need = (cfg.bin.inner_size_m[2] + cfg.rim_clearance_m - low) / np.maximum(cos_angle, 1e-6)
        return np.maximum(lift, need)

    def walls_at_every_backoff(
        self, T: np.ndarray, boxes: np.ndarray, d_min: np.ndarray, contact_z: np.ndarray, sweep_m: float
    ) -> np.ndarray:
        """``(k,)`` True where the gripper hits a wall at every backoff the grasp may take: from ``d_min`` (the
        floor's) to the largest that still leaves ``min_engagement_m`` of pad on the part. Over that range, the
        boxes swept back by ``sweep_m`` all contain the stretch from ``hi - d_max`` back to ``lo - d_min -
        sweep_m``; if that stretch already hits a wall, no backoff helps (an exact test, done before the costly
        points check)."""
        cfg = self.config
        if cfg.bin is None or not len(T):
            return np.zeros(len(T), dtype=bool)
        d_max = cfg.gripper.pad_length_m / 2.0 - contact_z[:, 0] - cfg.min_engagement_m  # the pads' tips that far in
        common = boxes.copy()
        common[..., 0, 2] -= (d_min + sweep_m)[:, None]
        common[..., 1, 2] -= d_max[:, None]
        empty = common[..., 1, 2] <= common[..., 0, 2]  # no stretch in common: cannot tell, keep
        common[..., 1, 2] = np.maximum(common[..., 1, 2], common[..., 0, 2])
        gap = self._wall_gap_per_box(T, common)
        return np.any((gap < cfg.bin_clearance_m) & ~empty, axis=1)

    def floor_backoff(self, T: np.ndarray, boxes: np.ndarray, cos_angle: np.ndarray) -> np.ndarray:
        """``(k,)`` how far each grasp must move back along its approach so that every gripper box is at least
        ``floor_clearance_m`` above the bin floor (-inf without a bin)."""
        cfg = self.config
        if cfg.bin is None or not len(T):
            return np.full(len(T), -np.inf)
        corners = box_corners(boxes)  # (k, b * 8, 3), TCP frame
        points = rotate(T, corners) + T[:, None, :3, 3]
        height = cfg.bin.height_above_floor_m(points).min(axis=1)
        # moving back by d along the approach raises the gripper by d * cos(angle)
        return (cfg.floor_clearance_m - height) / np.maximum(cos_angle, 1e-6)


def joint_line(q_from: np.ndarray, q_to: np.ndarray, step_rad: float) -> np.ndarray:
    """``(n, 6)`` the straight joint-space line from ``q_from`` to ``q_to`` (what a joint move does), sampled every
    ``step_rad`` of the largest joint change, both ends included."""
    q_from, q_to = np.asarray(q_from, dtype=float), np.asarray(q_to, dtype=float)
    n = max(2, math.ceil(float(np.abs(q_to - q_from).max()) / step_rad) + 1)
    return q_from[None] + np.linspace(0.0, 1.0, n)[:, None] * (q_to - q_from)[None]


def local_points(
    points: np.ndarray, T: np.ndarray, boxes: np.ndarray, sweep_m: float, margin_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """The obstacle points within ``margin_m`` of the box around each grasp's gripper boxes swept back by
    ``sweep_m`` (its way in and out), in its TCP frame: ``(k, m', 3)`` float32 and a ``(k, m')`` mask of the real
    ones (rows are padded to the longest). A first cut in the base frame keeps the points near any grasp."""
    k = len(T)
    if not len(points) or not k:
        return np.zeros((k, 0, 3), dtype=np.float32), np.zeros((k, 0), dtype=bool)
    lo, hi = boxes[..., 0, :].min(axis=1), boxes[..., 1, :].max(axis=1)  # (k, 3) around all boxes, TCP frame
    lo = lo - margin_m
    hi = hi + margin_m
    lo[:, 2] -= sweep_m
    corners = box_corners(np.stack([lo, hi], axis=1)[:, None])  # (k, 8, 3)
    corners_base = rotate(T, corners) + T[:, None, :3, 3]
    box_lo, box_hi = corners_base.reshape(-1, 3).min(axis=0), corners_base.reshape(-1, 3).max(axis=0)
    points = points[np.all((points >= box_lo) & (points <= box_hi), axis=1)]
    if not len(points):
        return np.zeros((k, 0, 3), dtype=np.float32), np.zeros((k, 0), dtype=bool)
    R_t = np.swapaxes(T[:, :3, :3], 1, 2).astype(np.float32)  # (k, 3, 3): R^T
    # (k, 3, m), one contiguous row per coordinate (fast comparisons): p_tcp = R^T (p - t)
    local = np.matmul(R_t, points.T.astype(np.float32)[None]) - np.matmul(R_t, T[:, :3, 3:4].astype(np.float32))
    lo32, hi32 = lo.astype(np.float32), hi.astype(np.float32)
    near = np.ones((k, local.shape[2]), dtype=bool)
    for axis in range(3):
        near &= (local[:, axis, :] >= lo32[:, axis, None]) & (local[:, axis, :] <= hi32[:, axis, None])
    rows, cols = np.nonzero(near)  # row-major: each row's points in order
    counts = np.bincount(rows, minlength=k)
    slot = np.arange(len(rows)) - np.repeat(np.cumsum(counts) - counts, counts)  # position within its row
    packed = np.zeros((k, int(counts.max(initial=0)), 3), dtype=np.float32)
    packed[rows, slot] = local[rows, :, cols]
    valid = np.arange(packed.shape[1])[None, :] < counts[:, None]
    return packed, valid


def engagement_m(contact_z: np.ndarray, backoff: np.ndarray, g: GripperGeometry) -> np.ndarray:
    """Length along z over which the pads, moved back by ``backoff``, overlap the contact span."""
    half = g.pad_length_m / 2.0
    return np.minimum(half - backoff, contact_z[:, 1]) - np.maximum(-half - backoff, contact_z[:, 0])
