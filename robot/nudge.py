"""Nudges: drag a part the gripper cannot take away from what is in the fingers' way, with the closed fingers, so
that the next look finds a grasp.

A parallel gripper needs room beside a part for its fingers (on the simulated 2F-85-like gripper 24 mm of pad and
finger link per side, and a 62 x 86 mm housing behind them), so a part lying within a finger's width of a wall, or
pressed against a neighbour that cannot be picked either, cannot be grasped at all. With ground-truth poses parts
at the walls are most of what a pick run leaves in the bin (``sygrid bench cell``, docs/bench/cell.md).
A nudge (for a part the planner left for ``collision_bin`` or ``collision_parts``):

1. close the fingers (the two pads together are a 16 x 22 mm paddle);
2. tilt the tool away from the wall, leaning over the bin (the housing then clears the wall while the pad tips
   reach the part), and come straight down onto the part until the lowest pad edge sits ``press_depth_m`` below
   the part's highest point, somewhere on its top;
3. drag straight along the floor, away from the walls and the neighbour near the part, until the nearest of them
   would be ``target_gap_m`` away (or slanted from that direction along the wall, see below);
4. go straight up; the next look decides what to do.

A nudge does not topple an L-bracket standing on its sheet edges (whose only grasps pinch the 2 mm sheet): pressed
on its top edge and dragged, or pushed on its side at half its height, it moved along but stayed standing in the
simulated cell, as statics says: its centre lies about 10 mm inside its footprint and it is 20 mm tall, so a push at
its top tips it only with a force of half its weight, which is what the floor's friction (0.5) already yields to.
Away from a wall, standing, its sheet can be pinched.

A drag must slide the part, not tip it over the leading edge of what stands on the floor. The pads pull the part's
top along with a friction force F at its height h and press it down with N; the floor holds the underside with
``floor_friction`` (mu) times N plus the weight. About that leading edge F tips the part (F h) against N's lever d
(how far behind the edge the pads press, along the drag) and the weight's; the part slides once F reaches mu N.
A force-limited press pushes with newtons, far above a small part's weight, so the part slides rather than tips
only if d >= mu h. So the pads press where that holds; on the flat top, not beside a hole or an edge (they would
catch its rim), or in the middle of a hole, where the lowest pad corner sinks in and the pads bear on the rim all
round. A part that topples easily is not held to this: one lying on its side (a bolt, a pipe), whose centre
passes over the leading edge of its footprint within ``roll_deg`` of tilt, rolls on under the drag, away from the
wall, which is what the drag is for; a flat nut has to tip by about 60 degrees, so the pads lift it onto its edge
and it falls back where it was. Drags slanted along the wall (``slants_deg``) measure the lever along other
directions; they go ``1 / cos(slant)`` times as far, to leave the same gap from the wall, and never bring the part
nearer than ``target_gap_m`` to another wall. Where no press passes, the part gets no nudge.

The walls are vertical, so a gripper clear of them at the press and at the end of the drag stays clear on the way
straight down and back up: those two poses are all the wall check needs.

Friction does the work: the pads (rubber-like, friction 1.0 in the simulated cell) grip the part's top harder
than the bin floor holds its underside. The planner gives poses; how the press touches the part is the pick arm's
(``robot.pick_arm``, ``PickerConfig.nudge_contact``): force-limited (straight down until the controller detects the
contact, then the drag in force mode with a bounded pressing force: the only way on hardware), or position control
to ``T_base_press`` (``press_depth_m`` into the estimated top: simulated cells only).

Candidates (tilt, turn of the paddle about the approach, where on the part's top to press, how far back the
straight lines start) are tried in ``NudgeConfig``'s order; the first whose gripper boxes keep ``bin_clearance_m``
from the walls along the whole motion, whose wrist links clear the walls, whose joint moves in and out are clear
(``CollisionChecker.transit_gap_m``, ``elbow_clear``), whose straight lines stay on one IK branch (the branch nearest
the planner's reference configuration first, then the others: tilted over the bin in a corner, the nearest branch's
wrist links can stand out over a wall where a flipped wrist clears it) and along which the closed gripper keeps
``clearance_m`` from the other parts (their surface points, and the plan's depth points of the pile on none of the
posed parts, beyond ``own_points_tolerance_m`` of the nudged one: a part the camera sees but perception did not pose
is as solid; checked every few millimetres: a neighbour under the tilted tool is what the press would otherwise hit)
is the nudge. The drag also goes away from those depth points where they are near. Hand-written, like the grasp
planner's checks, for the same reason: these are a few box-against-box tests per candidate, which the planner's
numpy maths already answers.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.spatial import ConvexHull, QhullError, cKDTree

from robot.grasp_collision import local_points
from robot.grasp_geometry import GripperGeometry, box_corners, points_box_distance_m
from robot.grasp_plan import GraspPlan, PartEstimate
from robot.grasp_planner import GraspPlanner
from robot.grasp_scene import cloud_owners
from robot.ur_config import URConfig
from sygrid.errors import ConfigError
from sygrid.robots.kinematics import ik_nearest, ik_solutions_near
from sygrid.transforms import invert, make_T, transform_points

#: The planner's causes a nudge can help with: a wall or a neighbour in the fingers' way.
NUDGE_CAUSES = ("collision_bin", "collision_parts")
_TOP_BAND_M = 0.003  # surface points this close to a part's highest point are its top
_FLAT_BAND_M = 0.001  # ... and this close, its flat top, which the pads may press on
_FLAT_RADIUS_M = 0.001  # a press point needs a flat-top sample this close (the samples lie ~0.7 mm apart)
_RIM_CLEARANCE_M = 0.001  # ... and no sample of a surface dropping away from the top (a hole, an edge) this close
_HOLE_SECTORS = 8  # the middle of a hole: flat top in every one of these sectors around it
_FOOT_BAND_M = 0.0005  # surface points this close to a part's lowest point are what stands on the floor
_PATH_STEP_M = 0.005  # the gripper is checked against the other parts at poses this far apart along its lines


@dataclass(frozen=True)
class NudgeConfig:
    """Settings of the nudge planner; metres, degrees and m/s.

    target_gap_m: drag until the part would be this far from the walls and the neighbour near it (its nearest
    point); min_drag_m / max_drag_m bound the drag (along the direction away from them). near_m: walls and the
    nearest neighbour closer to the part than this set that direction (the sum of the directions away from them);
    with none (the housing, not the fingers, meets a wall further away), the part is dragged ``min_drag_m`` toward
    the bin centre. slants_deg: the drag directions tried, as turns (degrees, about the vertical) from that
    direction, in order.
    press_depth_m: the lowest pad edge goes this far below the part's highest point. edge_margin_m: the pressing
    edge stays this far inside the part's top. press_offsets / press_sideways: where on the top the pads press, as
    shares of the top's reach from its centre along the drag and across it (0: the centre; 1: ``edge_margin_m``
    inside its edge), tried in this order and kept where the flat top is under them and the tipping lever is long
    enough. floor_friction: the part-on-floor friction coefficient the tipping check assumes (higher is safer: it
    asks for a longer lever; 0 asks only that the pads press above the footprint). roll_deg: a part whose centre
    passes over the leading edge of its footprint within this tilt is not held to the check: tipped, it rolls or
    topples on, away from the wall (a bolt or a pipe lying on its side), where a part that needs more is only
    lifted onto the edge and falls back.
    tilts_deg / turns_deg / retreat_m: the candidates, tried in this order (retreat_m: how high above the press the
    straight line down starts, and the line up ends). speed_m_s: the press and the drag.
    max_joint_step_rad: the largest joint change along each straight line.
    """

    target_gap_m: float = 0.04
    min_drag_m: float = 0.015
    max_drag_m: float = 0.05
    near_m: float = 0.035
    press_depth_m: float = 0.002
    edge_margin_m: float = 0.004
    floor_friction: float = 0.7
    roll_deg: float = 45.0
    slants_deg: tuple[float, ...] = (0.0, 30.0, -30.0, 45.0, -45.0, 60.0, -60.0)
    tilts_deg: tuple[float, ...] = (0.0, 15.0, 30.0, 40.0, 45.0, 50.0, 55.0, 60.0, 65.0, 70.0)
    turns_deg: tuple[float, ...] = (0.0, 20.0, -20.0, 45.0, -45.0, 90.0)
    press_offsets: tuple[float, ...] = (0.0, 0.5, 1.0)
    press_sideways: tuple[float, ...] = (0.0, 0.5, -0.5, 1.0, -1.0)
    retreat_m: tuple[float, ...] = (0.05, 0.10, 0.15)
    speed_m_s: float = 0.05
    max_joint_step_rad: float = 1.0

    def __post_init__(self) -> None:
        for name in ("target_gap_m", "min_drag_m", "max_drag_m", "near_m", "speed_m_s", "max_joint_step_rad"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"NudgeConfig.{name} must be > 0, got {getattr(self, name)}")
        if self.min_drag_m > self.max_drag_m:
            raise ConfigError(f"NudgeConfig.min_drag_m {self.min_drag_m} is above max_drag_m {self.max_drag_m}")
        if self.press_depth_m < 0 or self.edge_margin_m < 0 or self.floor_friction < 0:
            raise ConfigError("NudgeConfig.press_depth_m, edge_margin_m and floor_friction must be >= 0")
        if not 0.0 <= self.roll_deg <= 90.0:
            raise ConfigError(f"NudgeConfig.roll_deg must lie in [0, 90], got {self.roll_deg}")
        if not self.slants_deg or not all(abs(a) < 90.0 for a in self.slants_deg):
            raise ConfigError(f"NudgeConfig.slants_deg needs values in (-90, 90), got {self.slants_deg}")
        if not (self.tilts_deg and self.turns_deg and self.press_offsets and self.press_sideways and self.retreat_m):
            raise ConfigError(
                "NudgeConfig: tilts_deg, turns_deg, press_offsets, press_sideways and retreat_m need a value each"
            )
        if not all(0.0 <= t < 90.0 for t in self.tilts_deg) or not all(r > 0 for r in self.retreat_m):
            raise ConfigError("NudgeConfig: tilts_deg must lie in [0, 90) and retreat_m be > 0")


@dataclass(frozen=True, eq=False)
class PlannedNudge:
    """One nudge: TCP poses ``T_base_*`` (4x4) and joint solutions ``q_*`` (6,), in the order the robot visits
    them: above (straight above the press; reached by a joint move), press (the paddle on the part's top), end
    (after the drag), retreat (straight above the end). ``direction`` (3,) is the drag direction in the base
    frame; ``speed_m_s`` the speed of the press and the drag."""

    part_index: int
    obj_id: int
    cause: str
    T_base_obj: np.ndarray
    direction: np.ndarray
    distance_m: float
    tilt_deg: float
    T_base_above: np.ndarray
    T_base_press: np.ndarray
    T_base_end: np.ndarray
    T_base_retreat: np.ndarray
    q_above: np.ndarray
    q_press: np.ndarray
    q_end: np.ndarray
    q_retreat: np.ndarray
    speed_m_s: float


class NudgePlanner:
    """Plans nudges with a ``GraspPlanner``'s models, bin, gripper geometry and checks.

    Args:
        planner: the grasp planner (its config must have a bin: a nudge is defined by the bin's walls).
        config: the nudge settings.
    """

    def __init__(self, planner: GraspPlanner, config: NudgeConfig | None = None) -> None:
        if planner.config.bin is None:
            raise ConfigError("NudgePlanner: the grasp planner has no bin (PlannerConfig.bin is None)")
        self.planner = planner
        self.config = config or NudgeConfig()

    def plan(
        self,
        poses: Sequence,
        T_base_camera: np.ndarray,
        plan: GraspPlan,
        q_from: np.ndarray,
        q_after: np.ndarray,
        skip: Callable[[int], bool] | None = None,
    ) -> PlannedNudge | None:
        """A nudge for one of the parts ``plan`` (made from ``poses``, camera frame) left for a ``NUDGE_CAUSES``
        cause, the highest such part first; None when no part needs one or none can be done safely. The obstacles of
        a part's nudge: the other parts' estimated surfaces and ``plan.cloud_base``'s points not on that part.

        q_from: where the arm is (the joint move to the first pose starts there). q_after: where it goes after the
        retreat (the observe pose). skip: part indices not to nudge (e.g. nudged often enough already)."""
        T_base_camera = np.asarray(T_base_camera, dtype=float)
        parts = [PartEstimate(p.obj_id, T_base_camera @ np.asarray(p.T_camera_object, dtype=float)) for p in poses]
        surfaces = [
            self.planner.surface_base(p) if r.status != "outside_bin" else None
            for p, r in zip(parts, plan.parts, strict=True)
        ]
        reports = sorted(
            (r for r in plan.parts if r.status in NUDGE_CAUSES), key=lambda r: -np.nan_to_num(r.top_height_m, nan=-1e9)
        )
        # the pile's depth points on no other part are obstacles too: a part the camera sees but perception could not
        # pose lies there as much as a posed one (a drag into it, or the tool coming down on it, meets it)
        cloud = np.asarray(plan.cloud_base, dtype=float).reshape(-1, 3)
        owners = cloud_owners(cloud, surfaces, self.planner.config.own_points_tolerance_m)
        for report in reports:
            i = report.part_index
            if skip is not None and skip(i):
                continue
            others = [s for k, s in enumerate(surfaces) if k != i and s is not None] + [cloud[owners != i]]
            neighbours = np.concatenate(others)  # (0, 3) when there is nothing else: every check skips it
            nudge = self.plan_part(parts[i], i, report.status, q_from, q_after, neighbours)
            if nudge is not None:
                return nudge
        return None

    def plan_part(
        self,
        part: PartEstimate,
        part_index: int,
        cause: str,
        q_from: np.ndarray,
        q_after: np.ndarray,
        neighbours_base: np.ndarray | None = None,
    ) -> PlannedNudge | None:
        """The first safe nudge of one part (base frame) left for ``cause``, or None. ``neighbours_base``: the
        other parts' surface points ``(n, 3)`` (base frame), which a drag also moves the part away from."""
        surface = self.planner.surface_base(part)
        if surface is None or cause not in NUDGE_CAUSES:
            return None
        b = self.planner.config.bin
        T_bin_base = invert(b.T_base_bin)
        points = transform_points(T_bin_base, surface)
        neighbours = None if neighbours_base is None else transform_points(T_bin_base, neighbours_base)
        half_xy = np.array(b.inner_size_m[:2]) / 2.0
        away, distance = self._drag(points, half_xy, neighbours)
        shape = _Shape.of(points)
        for direction, length in self._slanted(points, half_xy, away, distance):
            candidates = list(self._drag_poses(shape, direction, length))
            if not candidates:
                continue
            T_starts = b.T_base_bin @ np.stack([c[0] for c in candidates])
            T_ends = b.T_base_bin @ np.stack([c[1] for c in candidates])
            for k in np.flatnonzero(self._clear_of_bin(T_starts, T_ends)):
                T_start, T_end, tilt = T_starts[k], T_ends[k], candidates[k][2]
                for back in self.config.retreat_m:
                    waypoints = self._waypoints(T_start, T_end, back, q_from, q_after, neighbours_base)
                    if waypoints is not None:
                        return PlannedNudge(
                            part_index=part_index, obj_id=part.obj_id, cause=cause,
                            T_base_obj=np.array(part.T_base_obj, dtype=float),
                            direction=b.T_base_bin[:3, :3] @ direction, distance_m=length, tilt_deg=tilt,
                            speed_m_s=self.config.speed_m_s, **waypoints,
                        )  # fmt: skip
        return None

    def _slanted(
        self, points: np.ndarray, half_xy: np.ndarray, away: np.ndarray, distance: float
    ) -> Iterator[tuple[np.ndarray, float]]:
        """The drags to try, ``(direction, length)`` in the bin frame: ``away`` turned by each of ``slants_deg``,
        as long as it takes to move the part ``distance`` along ``away``; a slanted one only if it leaves the part
        at least ``target_gap_m`` (or its present gap, if smaller) from every wall."""
        cfg = self.config
        before = wall_gaps_m(points, half_xy)
        for slant in cfg.slants_deg:
            c, s = math.cos(math.radians(slant)), math.sin(math.radians(slant))
            direction = np.array([c * away[0] - s * away[1], s * away[0] + c * away[1], 0.0])
            length = distance / c
            if slant != 0.0:
                after = wall_gaps_m(points + length * direction, half_xy)
                if np.any(after < np.minimum(before, cfg.target_gap_m) - 1e-9):
                    continue
            yield direction, length

    def _drag_poses(
        self, shape: _Shape, direction: np.ndarray, distance: float
    ) -> Iterator[tuple[np.ndarray, np.ndarray, float]]:
        """The candidate ``(T_press, T_end, tilt_deg)`` of a drag of a part (``_Shape``, bin frame) along
        ``direction`` by ``distance``, in the order to try them; TCP poses in the bin frame."""
        cfg, g = self.config, self.planner.config.gripper
        centre, top, z_top = shape.centre_xy, shape.top_xy, shape.z_top
        u = direction[:2]
        side = np.array([-u[1], u[0]])
        reach = max(float(((top - centre) @ u).max()) - cfg.edge_margin_m, 0.0)
        reach_side = max(float(np.abs((top - centre) @ side).max()) - cfg.edge_margin_m, 0.0)
        presses = [
            centre + o * reach * u + s * reach_side * side
            for o, s in itertools.product(cfg.press_offsets, cfg.press_sideways)
        ]
        if shape.footprint is not None and shape.roll_deg(u) >= cfg.roll_deg:
            # statics (module docstring): at the onset of sliding the floor's centre of pressure lies mu h ahead of
            # the press; the part tips (and falls back) unless that point is inside its footprint
            shift = cfg.floor_friction * (z_top - shape.z_floor) * u
            standing = shape.on_footprint(np.array(presses) + shift)
            presses = [p for p, ok in zip(presses, standing, strict=True) if ok]
        presses = [p for p in presses if shape.pressable(p)]
        for press, tilt, turn in itertools.product(presses, cfg.tilts_deg, cfg.turns_deg):
            R = _paddle_rotation(direction, tilt, turn)
            edge = np.array([*press, z_top - cfg.press_depth_m])
            T_press = make_T(R, edge - _lowest_pad_point(R, g))
            yield T_press, make_T(R, T_press[:3, 3] + distance * direction), float(tilt)

    # ------------------------------------------------------------------------------------------ helpers

    def _drag(
        self, points_bin: np.ndarray, half_xy: np.ndarray, neighbours_bin: np.ndarray | None
    ) -> tuple[np.ndarray, float]:
        """The drag direction (bin frame, horizontal unit vector) and distance for a part's surface points: away
        from the walls and the nearest neighbour closer than ``near_m`` (the sum of those directions), until
        the nearest of them would be ``target_gap_m`` away."""
        cfg = self.config
        gaps = list(wall_gaps_m(points_bin, half_xy))
        away = [[-1.0, 0.0], [1.0, 0.0], [0.0, -1.0], [0.0, 1.0]]  # from each wall, inwards
        if neighbours_bin is not None and len(neighbours_bin):
            dist, nearest = cKDTree(points_bin[:, :2]).query(neighbours_bin[:, :2])
            k = int(np.argmin(dist))
            step = points_bin[nearest[k], :2] - neighbours_bin[k, :2]
            if np.linalg.norm(step) > 1e-9:
                gaps.append(float(dist[k]))
                away.append(list(step / np.linalg.norm(step)))
        gaps, inward = np.array(gaps), np.array(away)
        near = gaps < cfg.near_m
        if near.any():
            direction = inward[near].sum(axis=0)
            distance = float(np.clip(cfg.target_gap_m - gaps[near].min(), cfg.min_drag_m, cfg.max_drag_m))
        else:
            direction, distance = -points_bin[:, :2].mean(axis=0), cfg.min_drag_m
        norm = float(np.linalg.norm(direction))
        direction = direction / norm if norm > 1e-9 else np.array([1.0, 0.0])
        return np.array([direction[0], direction[1], 0.0]), distance

    def _clear_of_bin(self, T_press: np.ndarray, T_end: np.ndarray) -> np.ndarray:
        """``(k,)`` per candidate (``(k, 4, 4)`` TCP poses at the press and the end of the drag): the closed
        gripper keeps ``bin_clearance_m`` from the walls at both, and stays above the floor at the press (the part
        is not too thin to press)."""
        pcfg = self.planner.config
        closed = pcfg.gripper.boxes(0.0)
        k = len(T_press)
        boxes = np.broadcast_to(closed, (2 * k, *closed.shape))
        gap = self.planner.collision.wall_gap_m(np.concatenate([T_press, T_end]), boxes).reshape(2, k).min(axis=0)
        corners = box_corners(closed).reshape(-1, 3)
        at_press = corners @ T_press[:, :3, :3].transpose(0, 2, 1) + T_press[:, None, :3, 3]
        lowest = pcfg.bin.height_above_floor_m(at_press)
        return (gap >= pcfg.bin_clearance_m) & (lowest.min(axis=1) >= 0.0)

    def _waypoints(
        self,
        T_press: np.ndarray,
        T_end: np.ndarray,
        back: float,
        q_from: np.ndarray,
        q_after: np.ndarray,
        neighbours_base: np.ndarray | None = None,
    ) -> dict | None:
        """The poses and joint solutions of a candidate that ``_clear_of_bin`` passed, coming down from and going
        back up to ``back`` above it, if the rest of the checks pass (the workspace, the closed gripper along the
        three straight lines keeping ``clearance_m`` from the other parts' surface points ``neighbours_base``, and
        ``_joint_path`` on one of the arm's IK branches); else None."""
        planner = self.planner
        pcfg = planner.config
        g = pcfg.gripper
        closed = g.boxes(0.0)
        up = make_T(t=back * pcfg.bin.floor_normal)
        T_above, T_retreat = up @ T_press, up @ T_end
        if pcfg.workspace is not None and not np.all(
            pcfg.workspace.contains(np.array([X[:3, 3] for X in (T_above, T_press, T_end, T_retreat)]))
        ):
            return None
        if neighbours_base is not None and len(neighbours_base):
            path = straight_lines([T_above, T_press, T_end, T_retreat], _PATH_STEP_M)
            if gap_to_points_m(path, closed, neighbours_base, pcfg.clearance_m) < pcfg.clearance_m:
                return None
        limits, T_flange_tcp = planner.joint_limits_rad, g.T_flange_tcp
        # the arm configuration nearest the reference first; another branch where that one's wrist meets a wall (a
        # part in a corner, the tool tilted over the bin: the wrist links then stand out over one of the walls)
        for q_above in ik_solutions_near(T_above, planner.q_reference, T_flange_tcp, limits):
            q = self._joint_path(q_above, (T_press, T_end, T_retreat), q_from, q_after, closed)
            if q is not None:
                break
        else:
            return None
        return {
            "T_base_above": T_above, "T_base_press": T_press, "T_base_end": T_end, "T_base_retreat": T_retreat,
            "q_above": q[0], "q_press": q[1], "q_end": q[2], "q_retreat": q[3],
        }  # fmt: skip

    def _joint_path(
        self, q_above: np.ndarray, poses: tuple, q_from: np.ndarray, q_after: np.ndarray, closed: np.ndarray
    ) -> list[np.ndarray] | None:
        """The joint solutions from ``q_above`` along ``poses`` (press, end, retreat; each the nearest to the one
        before, no joint turning more than ``max_joint_step_rad``), if the wrist links keep ``bin_clearance_m`` from
        the walls and the joint moves in from ``q_from`` and out to ``q_after`` are clear and keep the TCP in the
        robot's workspace box; else None."""
        planner = self.planner
        pcfg = planner.config
        q = [q_above]
        for X in poses:
            q.append(ik_nearest(X, q[-1], pcfg.gripper.T_flange_tcp, planner.joint_limits_rad))
            if q[-1] is None or np.abs(q[-1] - q[-2]).max() > self.config.max_joint_step_rad:
                return None
        if planner.collision.wrist_gap_m(np.stack(q)).min() < pcfg.bin_clearance_m:
            return None
        clearance = pcfg.transit_clearance_m or 0.0
        for qa, qb in ((q_from, q[0]), (q[-1], q_after)):
            if planner.collision.transit_gap_m(qa, qb, closed) < clearance or not planner.collision.elbow_clear(qa, qb):
                return None
            # the controller refuses a joint move whose TCP leaves the workspace box (another branch swings wide)
            if pcfg.workspace is not None and pcfg.workspace.joint_path_exit(
                pcfg.gripper.T_flange_tcp, qa, qb, URConfig.path_check_step_rad
            ):
                return None
        return q


@dataclass(frozen=True, eq=False)
class _Shape:
    """What the press rules read from a part's surface samples (bin frame), computed once per part: its top (the
    samples within ``_TOP_BAND_M`` of its highest point; ``centre_xy`` their mean), its flat top (within
    ``_FLAT_BAND_M``) and the surfaces dropping away from it (a hole's wall, an edge), and its ``footprint``: the
    convex hull of its lowest points (xy) as ``(k, 3)`` edge lines ``(nx, ny, c)``, ``n . p + c <= 0`` inside, ``n``
    a unit outward normal; None for a line contact (the points span no area: a lying cylinder), which rolls
    whichever way it is dragged."""

    points: np.ndarray
    z_top: float
    z_floor: float
    top_xy: np.ndarray
    centre_xy: np.ndarray
    flat_xy: np.ndarray
    on_flat: cKDTree
    dropping: cKDTree | None
    footprint: np.ndarray | None

    @classmethod
    def of(cls, points: np.ndarray) -> _Shape:
        z_top, z_floor = float(points[:, 2].max()), float(points[:, 2].min())
        top = points[:, 2] > z_top - _TOP_BAND_M
        flat = points[:, 2] > z_top - _FLAT_BAND_M
        try:
            footprint = ConvexHull(points[points[:, 2] < z_floor + _FOOT_BAND_M, :2]).equations
        except (QhullError, ValueError):  # fewer than 3 points, or all on a line
            footprint = None
        return cls(
            points=points, z_top=z_top, z_floor=z_floor, top_xy=points[top, :2],
            centre_xy=points[top, :2].mean(axis=0), flat_xy=points[flat, :2], on_flat=cKDTree(points[flat, :2]),
            dropping=cKDTree(points[top & ~flat, :2]) if np.any(top & ~flat) else None, footprint=footprint,
        )  # fmt: skip

    def pressable(self, p: np.ndarray) -> bool:
        """Whether the pads may press at ``p`` (xy): on the flat top, no hole or edge next to it; or the middle of
        a hole in the top (the flat top rings it within ``_RIM_CLEARANCE_M``, all round), where the lowest pad
        corner sinks in and the pads bear on the rim all round it. Off the middle of a hole the pads would catch
        its far rim and push the part over."""
        gap = float(self.on_flat.query(p)[0])
        if gap <= _FLAT_RADIUS_M:
            return self.dropping is None or self.dropping.query(p)[0] >= _RIM_CLEARANCE_M
        ring = self.flat_xy[self.on_flat.query_ball_point(p, gap + _RIM_CLEARANCE_M)] - p
        sectors = np.unique(np.floor((np.arctan2(ring[:, 1], ring[:, 0]) + np.pi) / (2 * np.pi) * _HOLE_SECTORS))
        return len(sectors) == _HOLE_SECTORS

    def on_footprint(self, xy: np.ndarray) -> np.ndarray:
        """``(n,)`` which points ``xy`` ``(n, 2)`` lie in the footprint (needs one)."""
        return np.all(xy @ self.footprint[:, :2].T + self.footprint[:, 2] <= 0.0, axis=1)

    def roll_deg(self, direction_xy: np.ndarray) -> float:
        """How far (degrees) the part must tip about the edge of its footprint that a drag along ``direction_xy``
        tips it over (the edge the drag's line through its centre leaves by) before its centre (the samples' mean,
        for the centre of mass) passes over that edge (needs a footprint)."""
        centre = self.points.mean(axis=0)
        inside = -(self.footprint[:, :2] @ centre[:2] + self.footprint[:, 2])  # centre to each edge (> 0 inside)
        ahead = self.footprint[:, :2] @ direction_xy
        edges = np.flatnonzero(ahead > 1e-9)
        lever = float(inside[edges[np.argmin(inside[edges] / ahead[edges])]]) if len(edges) else 0.0
        return math.degrees(math.atan2(max(lever, 0.0), centre[2] - self.z_floor))


def straight_lines(poses: list[np.ndarray], step_m: float) -> np.ndarray:
    """``(k, 4, 4)`` poses along the straight lines between consecutive ``poses`` (one orientation along each, as
    a nudge's moves keep it), at most ``step_m`` apart, both ends included."""
    out = [poses[0]]
    for a, b in itertools.pairwise(poses):
        n = max(1, math.ceil(np.linalg.norm(b[:3, 3] - a[:3, 3]) / step_m))
        for s in np.linspace(0.0, 1.0, n + 1)[1:]:
            T = b.copy()
            T[:3, 3] = (1.0 - s) * a[:3, 3] + s * b[:3, 3]
            out.append(T)
    return np.stack(out)


def gap_to_points_m(T_base_tcp: np.ndarray, boxes: np.ndarray, points_base: np.ndarray, within_m: float) -> float:
    """The smallest distance (m) from ``points_base`` ``(n, 3)`` to ``boxes`` ``(b, 2, 3)`` (TCP frame) at any of the
    poses ``(k, 4, 4)``: exact up to ``within_m``, inf beyond (the points farther than that from the boxes' extent
    are cut first, ``grasp_collision.local_points``)."""
    per_pose = np.broadcast_to(boxes, (len(T_base_tcp), *boxes.shape))
    local, valid = local_points(points_base, T_base_tcp, per_pose, 0.0, within_m)
    return float(points_box_distance_m(local, boxes, valid).min())


def wall_gaps_m(points_bin: np.ndarray, half_xy: np.ndarray) -> np.ndarray:
    """The gaps (m) from a part's points (bin frame) to the walls at +x, -x, +y and -y."""
    lo, hi = points_bin[:, :2].min(axis=0), points_bin[:, :2].max(axis=0)
    return np.array([half_xy[0] - hi[0], half_xy[0] + lo[0], half_xy[1] - hi[1], half_xy[1] + lo[1]])


def _paddle_rotation(direction: np.ndarray, tilt_deg: float, turn_deg: float) -> np.ndarray:
    """TCP orientation (bin frame): the approach points down, tilted by ``tilt_deg`` toward the wall (the tool
    leans along ``direction``, away from it), the pads' line first along the wall, then turned about the
    approach by ``turn_deg``."""
    up = np.array([0.0, 0.0, 1.0])
    t = math.radians(tilt_deg)
    z = -math.cos(t) * up - math.sin(t) * direction
    x0 = np.cross(up, direction)
    x0 /= np.linalg.norm(x0)
    y0 = np.cross(z, x0)
    c, s = math.cos(math.radians(turn_deg)), math.sin(math.radians(turn_deg))
    x, y = c * x0 + s * y0, -s * x0 + c * y0
    return np.stack([x, y, z], axis=1)


def _lowest_pad_point(R: np.ndarray, gripper: GripperGeometry) -> np.ndarray:
    """Where the closed pads' tip face is lowest (its lowest corner, or the middle of its lowest edge), as an
    offset from the TCP in the frame ``R`` is given in."""
    hx, hy, hz = gripper.pad_thickness_m, gripper.pad_width_m / 2.0, gripper.pad_length_m / 2.0
    corners = np.array([[sx * hx, sy * hy, hz] for sx in (-1.0, 1.0) for sy in (-1.0, 1.0)]) @ R.T
    return corners[corners[:, 2] < corners[:, 2].min() + 1e-4].mean(axis=0)
