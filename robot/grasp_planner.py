"""The grasp planner: from estimated part poses (and a depth frame) to an ordered list of safe picks, each with its
pre-grasp, grasp, lift and place waypoints, or a clear "nothing safe to pick" with the reasons.

For each estimated part, in the robot base frame (``T_base_obj = T_base_camera @ T_camera_object``), its grasp
candidates (``robot.grasp_candidates``) go through these checks, cheapest first; the first one a candidate fails is its
rejection cause (``REJECTION_CAUSES``):

1. part level: a model for its id (``no_model``), inside the bin (``outside_bin``: its centre, the middle of its
   bounding box, outside the bin's inner footprint or below its floor; not its origin, which a CAD file may put
   anywhere; the camera may also see the place tray, whose walls the planner does not
   know), a pose confidence of at least ``min_pose_score`` (``low_confidence``), a pose that depth refinement
   confirmed where refinement ran (``unrefined``, with ``require_refined``), candidates at all
   (``no_candidates``), nothing lying on it (``covered``: the share of its upward surface with a depth point or a
   neighbour's surface above it);
2. the approach within ``approach_cone_deg`` of straight down (``approach_angle``);
3. depth: the gripper comes in along the approach from the pre-grasp (fingers open) and goes back out the same
   way to the lift (fingers closed on the part); it stays back as far as the bin floor demands and must still
   hold the part over ``min_engagement_m`` of its pads (``collision_floor``);
4. the bin walls, against the gripper's boxes swept along the approach (``collision_bin``): first the stretch
   that every backoff still allowed keeps in the way (cheap, and it spares the next check most candidates near a
   wall), then, after step 5, the boxes where the grasp ends up;
5. the neighbours (depth points and the other parts' surfaces): the gripper stays back as far as they demand,
   still holding the part over ``min_engagement_m`` (``collision_parts``);
6. the score, then inverse kinematics in score order: grasp, pre-grasp, lift and place within the joint limits
   less ``joint_limit_margin_rad``, with the TCP inside the robot's ``workspace`` box (``unreachable``; the robot
   would refuse the motion), with no joint jumping more than ``max_joint_step_rad`` between
   the straight-line waypoints (``singular``: a branch switch on the way); and the wrist links (boxes around their
   collision cylinders) at least ``bin_clearance_m`` from the bin walls at the pre-grasp, grasp and lift
   (``collision_bin``): with an inclined approach near a wall, the wrist reaches over the rim before the fingers do;
7. the joint moves (from where the arm is to the lift, with the fingers open; from the lift to the place pose,
   with the part in the fingers): the gripper (and the held part's box) and the wrist links, sampled along the
   straight joint line, must keep ``transit_clearance_m`` from the bin walls (``collision_transit``). A joint
   move is not a straight line of the tool: between two poses above the bin it can swing the fingers through a
   wall.

The lift is far enough back along the approach that the gripper and the held part clear the bin's rim by
``rim_clearance_m`` (at least ``lift_height_m``): the joint moves start and end above the rim, and the straight
lines in and out of the bin are the checked approach. When a joint move from there is not clear, the lift is
tried 5 and 10 cm further back before the candidate is refused.

The plan ranks parts with nothing lying on them first (top parts first), then by score: the weighted mean of
the pose confidence, the fingers' clearance, the part's height in the pile, the approach angle, the candidate's
quality and the pad engagement (``ScoreWeights``).

Modules: the settings (``robot.grasp_config``), the results (``robot.grasp_plan``), the scene's obstacles
(``robot.grasp_scene``), the collision checks (``robot.grasp_collision``: boxes against points and oriented boxes,
``robot.grasp_geometry``) and the waypoints with their IK (``robot.grasp_waypoints``, steps 6 and 7). The robot arm
itself is not checked against the bin (only the gripper, the wrist links and the elbow's height; the
sim-in-the-loop runs and ``sygrid bench cell`` check the whole arm in MuJoCo).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from perception.results import ObjectPose
from robot.grasp_candidates import grasp_candidates
from robot.grasp_collision import CollisionChecker, engagement_m, local_points
from robot.grasp_config import PlannerConfig
from robot.grasp_geometry import FINGER_BOXES, part_box_tcp, points_box_distance_m, required_backoff_m
from robot.grasp_plan import REJECTION_CAUSES, GraspPlan, PartEstimate, PartReport, PlannedGrasp, main_cause
from robot.grasp_scene import covered_fraction, pile_cloud, scene_obstacles
from robot.grasp_set import GraspSet
from robot.grasp_waypoints import WaypointSolver
from sygrid.camera import CameraIntrinsics
from sygrid.errors import ConfigError
from sygrid.objects.model import ObjectModel
from sygrid.transforms import is_rigid, transform_points

log = logging.getLogger(__name__)

_DOWN = np.array([0.0, 0.0, -1.0])
_SURFACE_SAMPLES = 2000  # per model: own-point test, neighbour obstacles, covered test
_TOUCHED = -2  # the owner of the points where the gripper met something: no part (not even one they lie on)
_TOUCH_GRID = 3  # points along each side of a finger's leading face
_UNDER_FRACTION = 0.02  # a part with more of its top than this covered is "under" another: it is ranked after


@dataclass(frozen=True, eq=False)
class _ModelData:
    """What the planner keeps per model: its candidates and a surface sample (object frame)."""

    model: ObjectModel
    grasps: GraspSet
    surface: np.ndarray  # (n, 3)
    normals: np.ndarray  # (n, 3)


class GraspPlanner:
    """Plans picks for estimated parts. Build it once per set of models (it computes or loads their grasp
    candidates), then call ``plan`` per camera frame.

    Args:
        models: the object models, as a sequence or a mapping from object id.
        config: the planner's settings (optional; ``PlannerConfig()`` when not given).
        cache_dir: where grasp candidates are cached (see ``robot.grasp_cache.resolve_cache_dir``).
    """

    def __init__(
        self,
        models: Sequence[ObjectModel] | Mapping[int, ObjectModel],
        config: PlannerConfig | None = None,
        cache_dir: str | Path | None = None,
    ) -> None:
        self.config = PlannerConfig() if config is None else config
        self.cache_dir = cache_dir
        if not isinstance(self.config, PlannerConfig):
            raise ConfigError(f"config must be a PlannerConfig, got {type(self.config).__name__}")
        items = models.values() if isinstance(models, Mapping) else models
        self._models: dict[int, _ModelData] = {}
        for model in items:
            if model.obj_id in self._models:
                raise ValueError(f"two models share obj_id {model.obj_id} ({model.name})")
            self._models[model.obj_id] = self._prepare(model, cache_dir)
        #: The collision checks (bin walls and floor, wrist links, joint moves) with this planner's settings.
        self.collision = CollisionChecker(self.config)
        self._waypoints = WaypointSolver(self.config, self.collision)
        self._down = -self.config.bin.floor_normal if self.config.bin is not None else _DOWN
        #: The configuration the grasps' IK solutions stay near: ``q_reference_rad``, else the IK solution nearest
        #: ``ur5e.HOME_Q`` for the tool pointing down 0.3 m above the bin's floor centre, else ``HOME_Q``.
        self.q_reference = self._waypoints.q_reference

    @property
    def joint_limits_rad(self) -> np.ndarray:
        """``(6, 2)`` the joint limits less ``joint_limit_margin_rad``: what IK solutions must stay within."""
        return self._waypoints.joint_limits_rad

    def candidates(self, obj_id: int) -> GraspSet:
        """The grasp candidates (object frame) of model ``obj_id``."""
        if obj_id not in self._models:
            raise KeyError(f"no model with obj_id {obj_id}; known ids: {sorted(self._models)}")
        return self._models[obj_id].grasps

    # ------------------------------------------------------------------------------------------ entry points

    def plan(
        self,
        poses: Sequence[ObjectPose],
        T_base_camera: np.ndarray,
        depth_m: np.ndarray | None = None,
        intrinsics: CameraIntrinsics | np.ndarray | None = None,
        q_seed: np.ndarray | None = None,
        place_slot: int = 0,
        touches: Sequence[tuple[np.ndarray, float | None]] = (),
    ) -> GraspPlan:
        """Plans picks for the perception pipeline's poses (camera frame), with the depth frame when given.

        Args:
            poses: the estimated parts (``T_camera_object``, score, object id).
            T_base_camera: the camera in the robot base frame (hand-eye calibration), 4x4.
            depth_m: (H, W) depth in metres of the frame the poses came from (0 = no data); optional.
            intrinsics: the depth frame's intrinsics (``CameraIntrinsics`` or 3x3 K); required with ``depth_m``.
            q_seed: the configuration IK solutions stay near (default ``q_reference``).
            place_slot: where on the place grid the part is let go (``PlannerConfig.place_pose_at``).
            touches: where the gripper met something on earlier approaches, ``(T_base_tcp, opening_m)`` (the TCP
                pose it stopped at, 4x4; the pads' opening, None: fully open): an obstacle the frame may not show (a
                part perception did not pose, depth the camera left out). The fingers' leading faces there are kept
                clear of like the depth's points, owned by no part (not even one whose surface they lie on).
        """
        start = time.perf_counter()
        T_base_camera = np.asarray(T_base_camera, dtype=float)
        if not is_rigid(T_base_camera, atol=1e-4):
            raise ValueError(f"T_base_camera must be a 4x4 rigid transform, got {T_base_camera.tolist()}")
        parts = [
            PartEstimate(p.obj_id, T_base_camera @ np.asarray(p.T_camera_object, dtype=float), float(p.score),
                         _refined(p))
            for p in poses
        ]  # fmt: skip
        cloud = None
        if depth_m is not None:
            if intrinsics is None:
                raise ValueError("plan: depth_m was given without its intrinsics")
            cfg = self.config
            cloud = pile_cloud(
                cfg.bin, depth_m, intrinsics, T_base_camera, cfg.depth_stride_px, cfg.bin_surface_tolerance_m
            )
        depth_s = time.perf_counter() - start
        plan = self._plan(parts, cloud, q_seed, place_slot, touches)
        plan.timings_s["depth_cloud"] = depth_s
        plan.timings_s["total"] = time.perf_counter() - start
        return plan

    def plan_parts(
        self,
        parts: Sequence[PartEstimate],
        cloud_base: np.ndarray | None = None,
        q_seed: np.ndarray | None = None,
        place_slot: int = 0,
        touches: Sequence[tuple[np.ndarray, float | None]] = (),
    ) -> GraspPlan:
        """Plans picks for parts given in the base frame, with an optional point cloud ``(n, 3)`` in the base frame
        (the depth camera's points; the bin's own points are dropped here); ``place_slot`` and ``touches`` as in
        ``plan``."""
        cloud = None if cloud_base is None else np.asarray(cloud_base, dtype=float).reshape(-1, 3)
        if self.config.bin is not None and cloud is not None:
            cloud = self.config.bin.pile_points(cloud, self.config.bin_surface_tolerance_m)
        return self._plan(parts, cloud, q_seed, place_slot, touches)

    def _plan(
        self,
        parts: Sequence[PartEstimate],
        cloud: np.ndarray | None,
        q_seed: np.ndarray | None,
        place_slot: int,
        touches: Sequence[tuple[np.ndarray, float | None]] = (),
    ) -> GraspPlan:
        """``plan_parts`` for a cloud that holds only the pile (no bin points)."""
        cfg = self.config
        timings = {"checks": 0.0, "ik": 0.0}
        q_seed = self.q_reference if q_seed is None else np.asarray(q_seed, dtype=float)
        if q_seed.shape != (6,) or not np.all(np.isfinite(q_seed)):
            raise ValueError(f"q_seed must be 6 finite joint angles (rad), got {q_seed.tolist()}")
        cloud = np.zeros((0, 3)) if cloud is None else cloud
        T_base_place = cfg.place_pose_at(place_slot)

        surfaces = [self.surface_base(p) for p in parts]
        obstacles, owner = scene_obstacles(cloud, surfaces, cfg.own_points_tolerance_m)
        if touches:
            touched = np.concatenate([self._touched_points(T, opening) for T, opening in touches])
            obstacles = np.concatenate([obstacles, touched])
            owner = np.concatenate([owner, np.full(len(touched), _TOUCHED)])
        tops = np.array([s[:, 2].max() if s is not None else np.nan for s in surfaces])
        known = tops[np.isfinite(tops)]
        z_low = float(known.min()) if len(known) else 0.0
        spread = max(float(known.max() - z_low) if len(known) else 0.0, cfg.height_spread_m)

        reports: dict[int, dict] = {}
        pending: list[_Evaluated] = []
        start = time.perf_counter()
        for i, part in enumerate(parts):
            ev = self._part_level(i, part, parts, surfaces, obstacles, owner, (tops[i] - z_low) / spread)
            reports[i] = ev.report
            if ev.pending is not None:
                pending.append(ev)
        timings["checks"] += time.perf_counter() - start

        # Best parts first: a part with something lying on it comes after every part with nothing on it, then by
        # score. Parts go through the candidate checks and IK in the order of the best score they could reach; once
        # max_planned_parts are planned, a part that cannot beat the last of them is not checked at all.
        under = {e.part_index: e.report["covered_fraction"] > _UNDER_FRACTION for e in pending}
        pending.sort(key=lambda e: (under[e.part_index], -e.best_score))
        planned: list[PlannedGrasp] = []
        kept: list[tuple[bool, float, int]] = []  # (under, -best planned score, part index) of the planned parts
        for ev in pending:
            full = cfg.max_planned_parts is not None and len(kept) >= cfg.max_planned_parts
            if full and (under[ev.part_index], -ev.best_score) >= max(kept)[:2]:
                reports[ev.part_index]["status"] = "not_planned"
                continue
            start = time.perf_counter()
            ev = self._evaluate_part(ev, surfaces)
            timings["checks"] += time.perf_counter() - start
            if ev.ranked is None:
                continue
            start = time.perf_counter()
            min_hold_width = float(self._models[ev.part.obj_id].grasps.width_m.min())  # the part's, for every grasp
            grasps = self._waypoints.solve(
                ev.part_index, ev.part, ev.ranked, min_hold_width, ev.report["rejections"], q_seed, T_base_place
            )
            timings["ik"] += time.perf_counter() - start
            report = reports[ev.part_index]
            report["n_planned"] = len(grasps)
            report["status"] = "planned" if grasps else main_cause(report["rejections"])
            if not grasps:
                continue
            planned.extend(grasps)
            kept.append((under[ev.part_index], -max(g.score for g in grasps), ev.part_index))
            if cfg.max_planned_parts is not None and len(kept) > cfg.max_planned_parts:
                worst = max(kept)
                kept.remove(worst)
                planned = [g for g in planned if g.part_index != worst[2]]
                reports[worst[2]]["status"], reports[worst[2]]["n_planned"] = "not_planned", 0

        planned.sort(key=lambda g: (under[g.part_index], -g.score))
        part_reports = tuple(PartReport(**reports[i]) for i in range(len(parts)))
        totals = {cause: sum(p.rejections.get(cause, 0) for p in part_reports) for cause in REJECTION_CAUSES}
        plan = GraspPlan(tuple(planned), part_reports, totals, timings, cloud)
        log.debug("grasp plan: %s", plan.summary())
        return plan

    # ------------------------------------------------------------------------------------------ per part

    def _part_level(
        self,
        index: int,
        part: PartEstimate,
        parts: Sequence[PartEstimate],
        surfaces: list[np.ndarray | None],
        scene_obstacles: np.ndarray,
        owner: np.ndarray,
        height_term: float,
    ) -> _Evaluated:
        """The part-level checks (step 1, ``no_model`` to ``covered``); for a part that passes them, what the
        candidate checks need (``pending``) and an upper bound on its best candidate's score (``best_score``): the
        order in which parts are worth checking further."""
        cfg = self.config
        report = {
            "part_index": index,
            "obj_id": part.obj_id,
            "status": "",
            "n_candidates": 0,
            "n_planned": 0,
            "rejections": dict.fromkeys(REJECTION_CAUSES, 0),
            "top_height_m": float("nan"),
            "covered_fraction": 0.0,
        }

        def part_level(cause: str, count: int) -> _Evaluated:
            report["status"] = cause
            report["rejections"][cause] = max(count, 1)
            return _Evaluated(index, report)

        data = self._models.get(part.obj_id)
        if data is None:
            return part_level("no_model", 1)
        centre_obj = data.model.bounds_m.mean(axis=0)
        if cfg.bin is not None and not cfg.bin.holds(part.T_base_obj[:3, :3] @ centre_obj + part.T_base_obj[:3, 3]):
            return part_level("outside_bin", max(len(data.grasps), 1))
        n = len(data.grasps)
        report["n_candidates"] = n
        report["top_height_m"] = float(surfaces[index][:, 2].max())
        if part.score < cfg.min_pose_score:
            return part_level("low_confidence", n)
        if cfg.require_refined and part.refined is False:
            return part_level("unrefined", n)
        if n == 0:
            return part_level("no_candidates", 1)

        # everything but this part (and a second detection of it, which is not a neighbour)
        duplicates = [
            j
            for j, other in enumerate(parts)
            if other.obj_id == part.obj_id
            and np.linalg.norm(other.T_base_obj[:3, 3] - part.T_base_obj[:3, 3])
            < cfg.duplicate_distance_ratio * data.model.diameter_m
        ]
        kept = ~np.isin(owner, duplicates)
        obstacles = scene_obstacles[kept]
        # a touch says where the gripper met something, not that it lies on this part
        covered = covered_fraction(
            data.surface, data.normals, part.T_base_obj, obstacles[owner[kept] != _TOUCHED], -self._down,
            cfg.cover_tolerance_m,
        )  # fmt: skip
        report["covered_fraction"] = covered
        if covered > cfg.max_covered_fraction:
            return part_level("covered", n)

        # the best score any candidate could reach: clearance and engagement at their best, the best approach and
        # quality among the candidates inside the cone
        angle = np.arccos(
            np.clip((part.T_base_obj[:3, :3] @ data.grasps.T_obj_grasp[:, :3, 2].T).T @ self._down, -1, 1)
        )
        inside = angle <= math.radians(cfg.approach_cone_deg)
        best = -np.inf
        if inside.any():
            w = cfg.weights
            terms = {
                "confidence": float(np.clip(part.score, 0.0, 1.0)),
                "clearance": 1.0,
                "height": float(np.clip(height_term, 0.0, 1.0)),
                "approach": 1.0 - float(angle[inside].min()) / math.radians(cfg.approach_cone_deg),
                "quality": float(np.clip(data.grasps.score[inside], 0.0, 1.0).max()),
                "engagement": 1.0,
            }
            best = w.weighted_mean(terms)
        pending = {"data": data, "obstacles": obstacles, "height_term": height_term}
        return _Evaluated(index, report, part, best_score=best, pending=pending)

    def _evaluate_part(self, ev: _Evaluated, surfaces: list[np.ndarray | None]) -> _Evaluated:
        """The candidate checks (steps 2-5) of a part that passed ``_part_level``; its ranked survivors."""
        cfg = self.config
        index, part, report = ev.part_index, ev.part, ev.report
        data, obstacles, height_term = ev.pending["data"], ev.pending["obstacles"], ev.pending["height_term"]
        n = len(data.grasps)

        g = cfg.gripper
        sweep = max(cfg.pre_grasp_distance_m, cfg.lift_height_m)  # in along the approach, and back out the same way
        cause = np.full(n, -1)  # index into REJECTION_CAUSES, -1 = still in
        T = part.T_base_obj @ data.grasps.T_obj_grasp  # (n, 4, 4) candidate TCP poses
        down = self._down
        cos_angle = np.clip(T[:, :3, 2] @ down, -1.0, 1.0)
        angle = np.arccos(cos_angle)
        cause[angle > math.radians(cfg.approach_cone_deg)] = _code("approach_angle")
        idx = np.flatnonzero(cause < 0)

        width, opening = data.grasps.width_m[idx], data.grasps.opening_m[idx]
        contact = data.grasps.contact_z_m[idx]
        Ti = T[idx]
        # the gripper on the way in (fingers open, and their closing strokes) and out (fingers closed on the part)
        boxes = np.concatenate(
            [g.boxes(opening, inner_half_m=width / 2.0 + cfg.clearance_m), g.boxes(width)[:, 2:4]], axis=1
        )
        # cheap checks first, so that the points check below (the costly one) sees fewer candidates: the floor, and
        # the walls against the part of the swept gripper that every allowed backoff keeps in the way
        d_floor = np.maximum(self.collision.floor_backoff(Ti, boxes, cos_angle[idx]), 0.0)
        floor_fail = engagement_m(contact, d_floor, g) < cfg.min_engagement_m
        wall_fail = ~floor_fail & self.collision.walls_at_every_backoff(Ti, boxes, d_floor, contact, sweep)
        cause[idx[floor_fail]] = _code("collision_floor")
        cause[idx[wall_fail]] = _code("collision_bin")
        keep = ~(floor_fail | wall_fail)
        idx, d_floor, Ti, boxes = idx[keep], d_floor[keep], Ti[keep], boxes[keep]
        width, opening, contact = width[keep], opening[keep], contact[keep]
        # the points near each grasp's gripper (near enough to count for its clearance), in its TCP frame
        P, valid = local_points(obstacles, Ti, boxes, sweep, max(cfg.clearance_m, cfg.clearance_saturation_m))
        d_parts = required_backoff_m(P, boxes, cfg.clearance_m, valid=valid, sweep_length_m=sweep)
        d = np.maximum(d_floor, d_parts)
        parts_fail = engagement_m(contact, d, g) < cfg.min_engagement_m
        cause[idx[parts_fail]] = _code("collision_parts")
        keep = ~parts_fail
        idx, d, Ti, P, valid, boxes = idx[keep], d[keep], Ti[keep], P[keep], valid[keep], boxes[keep]
        width, opening, contact = width[keep], opening[keep], contact[keep]
        back = np.tile(np.eye(4), (len(idx), 1, 1))
        back[:, 2, 3] = -d
        Tg = Ti @ back  # the grasps, moved back
        P = P + np.stack([np.zeros_like(d), np.zeros_like(d), d], axis=1)[:, None, :].astype(P.dtype)

        # the lift: back out along the approach until the gripper and the part in it clear the bin's rim
        part_box = part_box_tcp(Tg, part.T_base_obj, data.model.bounds_m)
        lift = self.collision.lift_distance(Tg, g.boxes(width), surfaces[index], cos_angle[idx])

        # bin walls: the boxes swept along the approach from the grasp to the lift (a box moved along its own z
        # stays a box)
        wall_gap = np.full(len(idx), np.inf)
        if cfg.bin is not None and len(idx):
            swept = boxes.copy()
            swept[..., 0, 2] -= np.maximum(lift, cfg.pre_grasp_distance_m)[:, None]
            wall_gap = self.collision.wall_gap_m(Tg, swept)
        wall_fail = wall_gap < cfg.bin_clearance_m
        cause[idx[wall_fail]] = _code("collision_bin")
        keep = ~wall_fail
        idx, d, Tg, P, valid, wall_gap = idx[keep], d[keep], Tg[keep], P[keep], valid[keep], wall_gap[keep]
        width, opening, contact, lift, part_box = width[keep], opening[keep], contact[keep], lift[keep], part_box[keep]

        # score
        fingers = g.boxes(opening)[:, FINGER_BOXES]
        clearance = points_box_distance_m(P, fingers, valid=valid, cap_m=cfg.clearance_saturation_m)
        clearance = np.minimum(clearance, wall_gap)
        engagement = engagement_m(contact, d, g)
        w = cfg.weights
        terms = {
            "confidence": np.full(len(idx), float(np.clip(part.score, 0.0, 1.0))),
            "clearance": np.clip(clearance / cfg.clearance_saturation_m, 0.0, 1.0),
            "height": np.full(len(idx), float(np.clip(height_term, 0.0, 1.0))),
            "approach": 1.0 - angle[idx] / math.radians(cfg.approach_cone_deg),
            "quality": np.clip(data.grasps.score[idx], 0.0, 1.0),
            "engagement": np.clip(engagement / cfg.engagement_saturation_m, 0.0, 1.0),
        }
        score = w.weighted_mean(terms)
        order = np.lexsort((idx, -score))

        for code, count in enumerate(np.bincount(cause[cause >= 0], minlength=len(REJECTION_CAUSES))):
            report["rejections"][REJECTION_CAUSES[code]] += int(count)
        if not len(idx):
            report["status"] = main_cause(report["rejections"])
            return _Evaluated(index, report)
        ranked = {
            "T_grasp": Tg[order],
            "width": width[order],
            "opening": opening[order],
            "score": score[order],
            "angle": angle[idx][order],
            "backoff": d[order],
            "engagement": engagement[order],
            "clearance": clearance[order],
            "lift": lift[order],
            "part_box": part_box[order],
            "terms": {k: v[order] for k, v in terms.items()},
        }
        return _Evaluated(index, report, part, ranked, float(score[order[0]]))

    # ------------------------------------------------------------------------------------------ scene

    def pile_area_m2(
        self, depth_m: np.ndarray, intrinsics: CameraIntrinsics | np.ndarray, T_base_camera: np.ndarray
    ) -> float:
        """How much of the bin the depth frame shows covered by something above its floor (m2: the footprints of
        the depth pixels more than ``bin_surface_tolerance_m`` off the floor and walls, at their distance from the
        camera). What tells an empty bin from one holding parts the detector does not find; 0 without a bin."""
        cfg = self.config
        if cfg.bin is None:
            return 0.0
        return cfg.bin.pile_area_m2(
            depth_m, intrinsics, T_base_camera, cfg.depth_stride_px, cfg.bin_surface_tolerance_m
        )

    def _touched_points(self, T_base_tcp: np.ndarray, opening_m: float | None) -> np.ndarray:
        """``(n, 3)`` base frame: a grid on the leading faces (along the approach, the TCP's +z) of the pads and the
        finger links, opened to ``opening_m`` (None: the stroke), at the TCP pose where the gripper met something."""
        g = self.config.gripper
        boxes = g.boxes(g.stroke_m if opening_m is None else opening_m)[FINGER_BOXES]  # (4, 2, 3) TCP frame
        s = np.linspace(0.0, 1.0, _TOUCH_GRID)
        u, v = (a.ravel() for a in np.meshgrid(s, s))
        shares = np.stack([u, v, np.ones_like(u)], axis=-1)  # across each face in x and y, at the box's far z
        lo, hi = boxes[:, None, 0], boxes[:, None, 1]
        points = (lo + shares * (hi - lo)).reshape(-1, 3)
        return transform_points(np.asarray(T_base_tcp, dtype=float), points)

    def surface_base(self, part: PartEstimate) -> np.ndarray | None:
        """``(n, 3)`` a sample of the part's surface in the base frame (None: no model for its id)."""
        data = self._models.get(part.obj_id)
        return None if data is None else transform_points(part.T_base_obj, data.surface)

    def _prepare(self, model: ObjectModel, cache_dir: str | Path | None) -> _ModelData:
        grasps = grasp_candidates(model, self.config.grasp_params, cache_dir)
        grasps = grasps.subset(grasps.width_m >= self.config.min_grasp_width_m)
        rng = np.random.default_rng(self.config.grasp_params.seed)
        surface, faces = trimesh.sample.sample_surface(model.mesh, _SURFACE_SAMPLES, seed=rng)
        return _ModelData(model, grasps, surface, model.mesh.face_normals[faces])


@dataclass(eq=False)
class _Evaluated:
    """A part after the geometric checks: its report (mutable, IK adds to it) and its ranked survivors."""

    part_index: int
    report: dict
    part: PartEstimate | None = None
    ranked: dict | None = None
    best_score: float = -np.inf
    pending: dict | None = None  # what the candidate checks need (a part that passed the part-level checks)


def _code(cause: str) -> int:
    return REJECTION_CAUSES.index(cause)


def _refined(pose: ObjectPose) -> bool | None:
    """Did depth refinement confirm this estimate (``perception.refine``'s ``details["icp"]["status"]``)?"""
    status = (pose.details or {}).get("icp", {}).get("status")
    return None if status is None else status == "refined"
