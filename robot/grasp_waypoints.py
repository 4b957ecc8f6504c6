"""From a part's ranked grasp candidates to planned picks: the waypoints (pre-grasp, grasp, lift, place), their
inverse kinematics and the checks on the arm's motion between them.

For each candidate, best first, until ``max_grasps_per_part`` succeed: the tool may turn half a turn about its
approach (the pads are interchangeable) to stay near the seed's wrist; the grasp's IK solution is the one nearest
``q_reference`` (one IK branch for every pick), the pre-grasp's and lift's are nearest the grasp's, the place's
nearest the lift's; every waypoint's TCP lies in the workspace box (``unreachable``); no joint moves more than
``max_joint_step_rad`` on the straight lines in and out (``singular``); the wrist links keep ``bin_clearance_m``
from the walls at the pre-grasp, grasp and lift (``collision_bin``); and the joint moves from the seed to the lift
and from the lift to the place pose keep ``transit_clearance_m`` from the walls and the elbow above
``min_elbow_height_m``, with the lift raised further back along the approach when they do not
(``collision_transit``).
"""

from __future__ import annotations

import logging

import numpy as np

from robot.grasp_collision import CollisionChecker
from robot.grasp_config import PlannerConfig
from robot.grasp_plan import PartEstimate, PlannedGrasp
from sygrid.errors import ConfigError
from sygrid.robots import ur5e
from sygrid.robots.kinematics import forward_kinematics, ik_nearest
from sygrid.transforms import make_T

log = logging.getLogger(__name__)

_LIFT_RAISES_M = (0.05, 0.1)  # further back along the approach when the joint moves from the lift are not clear


class WaypointSolver:
    """The waypoints and IK of a ``PlannerConfig``'s picks.

    Raises:
        ConfigError: ``joint_limit_margin_rad`` leaves no joint range.
    """

    def __init__(self, config: PlannerConfig, collision: CollisionChecker) -> None:
        self.config = config
        self.collision = collision
        margin = config.joint_limit_margin_rad
        self._limits = np.asarray(ur5e.JOINT_LIMITS_RAD) + np.array([margin, -margin])
        if np.any(self._limits[:, 0] >= self._limits[:, 1]):
            raise ConfigError(f"PlannerConfig.joint_limit_margin_rad {margin} leaves no joint range")
        #: The configuration the grasps' IK solutions stay near (``_reference_configuration``).
        self.q_reference = self._reference_configuration()

    @property
    def joint_limits_rad(self) -> np.ndarray:
        """``(6, 2)`` the joint limits less ``joint_limit_margin_rad``: what IK solutions must stay within."""
        return self._limits

    def solve(
        self,
        part_index: int,
        part: PartEstimate,
        ranked: dict,
        min_hold_width_m: float,
        rejections: dict[str, int],
        q_seed: np.ndarray,
        T_base_place: np.ndarray,
    ) -> list[PlannedGrasp]:
        """The planned picks of one part, best first, at most ``max_grasps_per_part``; each candidate that fails is
        counted in ``rejections`` under its cause.

        ``ranked``: the candidates that passed the geometric checks, best first, as arrays: ``T_grasp`` (TCP poses,
        base frame, already moved back), ``width``, ``opening``, ``score``, ``angle`` (rad from straight down),
        ``backoff``, ``engagement``, ``clearance``, ``lift`` (how far back along the approach the lift is),
        ``part_box`` (the part's box in the TCP frame) and ``terms`` (the score terms by name).
        ``min_hold_width_m``: the part's narrowest candidate width. ``T_base_place``: where this pick lets go (the
        tool turns about its approach axis to keep the grasp's pad direction)."""
        cfg = self.config
        r = ranked
        T_flange_tcp = cfg.gripper.T_flange_tcp
        x_seed = forward_kinematics(q_seed, T_flange_tcp)[:3, 0]
        out: list[PlannedGrasp] = []
        for k in range(len(r["score"])):
            T_grasp = r["T_grasp"][k].copy()
            # the pads are interchangeable: turn the tool half a turn about z if that keeps the wrist nearer the seed
            if T_grasp[:3, 0] @ x_seed < 0:
                T_grasp[:3, :2] *= -1.0
            T_pre = T_grasp @ make_T(t=(0.0, 0.0, -cfg.pre_grasp_distance_m))
            T_lift = T_grasp @ make_T(t=(0.0, 0.0, -float(r["lift"][k])))
            # the half-turn about z above mirrors the part's box (TCP frame) in x and y
            part_box = r["part_box"][k]
            if T_grasp[:3, 0] @ r["T_grasp"][k][:3, 0] < 0:
                part_box = part_box * np.array([-1.0, -1.0, 1.0])[None, :]
                part_box = np.stack([part_box.min(axis=0), part_box.max(axis=0)])
            T_place = place_pose(T_base_place, T_grasp[:3, 0], part_box)
            # the grasp's IK branch is the reference's, wherever the arm is: every pick on one branch (seeded from the
            # arm's configuration, the branch would drift from pick to pick)
            q_grasp = ik_nearest(T_grasp, self.q_reference, T_flange_tcp, self._limits)
            q_pre = q_lift = q_place = None
            if q_grasp is not None:
                q_pre = ik_nearest(T_pre, q_grasp, T_flange_tcp, self._limits)
                q_lift = ik_nearest(T_lift, q_grasp, T_flange_tcp, self._limits)
            if q_pre is not None and q_lift is not None:
                q_place = ik_nearest(T_place, q_lift, T_flange_tcp, self._limits)
            outside = cfg.workspace is not None and not np.all(
                cfg.workspace.contains(np.array([T[:3, 3] for T in (T_pre, T_grasp, T_lift, T_place)]))
            )
            if outside or q_grasp is None or q_pre is None or q_lift is None or q_place is None:
                rejections["unreachable"] += 1
                continue
            step = max(np.abs(q_pre - q_grasp).max(), np.abs(q_lift - q_grasp).max())
            if step > cfg.max_joint_step_rad:
                rejections["singular"] += 1
                continue
            if self.collision.wrist_gap_m(np.stack([q_pre, q_grasp, q_lift])).min() < cfg.bin_clearance_m:
                rejections["collision_bin"] += 1
                continue
            lifted = self._clear_transits(q_seed, T_grasp, q_grasp, (T_lift, q_lift, q_place), T_place, part_box, r, k)
            if lifted is None:
                rejections["collision_transit"] += 1
                continue
            T_lift, q_lift, q_place = lifted
            out.append(
                PlannedGrasp(
                    part_index=part_index,
                    obj_id=part.obj_id,
                    score=float(r["score"][k]),
                    T_base_obj=np.array(part.T_base_obj, dtype=float),
                    T_base_pregrasp=T_pre,
                    T_base_grasp=T_grasp,
                    T_base_lift=T_lift,
                    T_base_place=T_place,
                    q_pregrasp=q_pre,
                    q_grasp=q_grasp,
                    q_lift=q_lift,
                    q_place=q_place,
                    opening_width_m=float(r["opening"][k]),
                    grasp_width_m=float(r["width"][k]),
                    min_hold_width_m=min_hold_width_m,
                    approach_angle_deg=float(np.degrees(r["angle"][k])),
                    backoff_m=float(r["backoff"][k]),
                    engagement_m=float(r["engagement"][k]),
                    clearance_m=float(r["clearance"][k]),
                    pose_score=float(part.score),
                    score_terms={name: float(v[k]) for name, v in r["terms"].items()},
                )
            )
            if len(out) >= cfg.max_grasps_per_part:
                break
        return out

    def _clear_transits(
        self,
        q_seed: np.ndarray,
        T_grasp: np.ndarray,
        q_grasp: np.ndarray,
        lift: tuple[np.ndarray, np.ndarray, np.ndarray],
        T_place: np.ndarray,
        part_box: np.ndarray,
        r: dict,
        k: int,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:  # fmt: skip
        """``(T_lift, q_lift, q_place)`` whose joint moves (in: from ``q_seed``, fingers open; out: to the place
        pose ``T_place``, fingers open or closed on the part) keep ``transit_clearance_m`` from the walls: the given
        lift, else one ``_LIFT_RAISES_M`` further back along the approach (a joint move between two higher poses
        swings less low); None when none does."""
        cfg = self.config
        if cfg.transit_clearance_m is None:
            return lift
        # out with the fingers open or closed (a failed grasp leaves the lift open): the open boxes and the part
        open_boxes = cfg.gripper.boxes(float(r["opening"][k]))
        out_boxes = np.concatenate([open_boxes, part_box[None]], axis=0)
        T_flange_tcp = cfg.gripper.T_flange_tcp
        for raise_m in (0.0, *_LIFT_RAISES_M):
            if raise_m:
                T_lift = T_grasp @ make_T(t=(0.0, 0.0, -float(r["lift"][k]) - raise_m))
                q_lift = ik_nearest(T_lift, q_grasp, T_flange_tcp, self._limits)
                if q_lift is None or np.abs(q_lift - q_grasp).max() > cfg.max_joint_step_rad:
                    return None
                if cfg.workspace is not None and not cfg.workspace.contains(T_lift[:3, 3]):
                    return None
                q_place = ik_nearest(T_place, q_lift, T_flange_tcp, self._limits)
                if q_place is None:
                    return None
                lift = (T_lift, q_lift, q_place)
            _, q_lift, q_place = lift
            if (
                self.collision.transit_gap_m(q_seed, q_lift, open_boxes) >= cfg.transit_clearance_m
                and self.collision.transit_gap_m(q_lift, q_place, out_boxes) >= cfg.transit_clearance_m
                and self.collision.elbow_clear(q_seed, q_lift)
                and self.collision.elbow_clear(q_lift, q_place)
            ):
                return lift
        return None

    def _reference_configuration(self) -> np.ndarray:
        """``q_reference_rad``, else the IK solution nearest ``HOME_Q`` for the tool pointing down 0.3 m above the
        bin's floor centre, else ``HOME_Q``."""
        cfg = self.config
        if cfg.q_reference_rad is not None:
            return np.asarray(cfg.q_reference_rad, dtype=float)
        home = np.asarray(ur5e.HOME_Q, dtype=float)
        if cfg.bin is None:
            return home
        T_above = make_T(np.diag([1.0, -1.0, -1.0]), cfg.bin.floor_point + 0.3 * cfg.bin.floor_normal)
        q = ik_nearest(T_above, home, cfg.gripper.T_flange_tcp, self._limits)
        if q is None:
            log.warning("no IK solution above the bin centre; IK seeds stay near HOME_Q")
            return home
        return q


def place_pose(T_base_place: np.ndarray, x_grasp: np.ndarray, part_box: np.ndarray | None = None) -> np.ndarray:
    """The place pose turned about its approach axis so that the pads keep the grasp's direction (the wrist does
    not spin on the way), and moved across that axis so that the held part's box (``(2, 3)`` in the TCP frame) is
    centred on it: the place grid's slots are where parts land, and a long part held near one end (an L-bracket
    pinched at its edge) would otherwise reach its whole length toward the tray's wall."""
    z = T_base_place[:3, 2]
    x = x_grasp - (x_grasp @ z) * z
    T = T_base_place.copy()
    if np.linalg.norm(x) >= 1e-6:
        x /= np.linalg.norm(x)
        T[:3, 0], T[:3, 1] = x, np.cross(z, x)
    if part_box is not None:
        centre = T[:3, :3] @ np.asarray(part_box, dtype=float).mean(axis=0)
        T[:3, 3] -= centre - (centre @ z) * z
    return T
