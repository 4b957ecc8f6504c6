"""The grasp planner: from estimated part poses (and a depth frame) to an ordered list of safe picks, each with its
pre-grasp, grasp, lift and place waypoints, or a clear "nothing safe to pick" with the reasons.

For each estimated part, in the robot base frame (``T_base_obj = T_base_camera @ T_camera_object``), its grasp
candidates (``robot.grasps``) go through these checks, cheapest first; the first one a candidate fails is its
rejection cause (``REJECTION_CAUSES``):

1. part level: a model for its id (``no_model``), a pose confidence of at least ``min_pose_score``
   (``low_confidence``), candidates at all (``no_candidates``), nothing lying on it (``covered``: the share of its
   upward surface with a depth point or a neighbour's surface above it);
2. the approach within ``approach_cone_deg`` of straight down (``approach_angle``);
3. depth: the gripper comes in along the approach from the pre-grasp (fingers open) and goes back out the same
   way to the lift (fingers closed on the part); it stays back as far as the bin floor (``collision_floor``) and
   the neighbours (depth points and the other parts' surfaces, ``collision_parts``) demand, and must still hold
   the part over ``min_engagement_m`` of its pads;
4. the bin walls, against the gripper's boxes swept from the pre-grasp (``collision_bin``);
5. the score, then inverse kinematics in score order: grasp, pre-grasp, lift and place within the joint limits
   less ``joint_limit_margin_rad`` (``unreachable``), with no joint jumping more than ``max_joint_step_rad`` between
   the straight-line waypoints (``singular``: a branch switch on the way).

The plan ranks parts with nothing lying on them first (top parts first), then by score: the weighted mean of
the pose confidence, the fingers' clearance, the part's height in the pile, the approach angle, the candidate's
quality and the pad engagement (``ScoreWeights``).

Geometry is boxes against points and oriented boxes (``robot.grasp_geometry``); the robot arm itself is not
checked against the bin (only the gripper and the wrist link behind it).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from perception.results import ObjectPose
from robot.grasp_geometry import (
    FINGER_BOXES,
    GripperGeometry,
    obb_gap_m,
    points_box_distance_m,
    required_backoff_m,
)
from robot.grasp_scene import BinGeometry, depth_points
from robot.grasps import GraspSet, GraspSetParams, grasp_candidates
from sygrid.camera import CameraIntrinsics
from sygrid.errors import ConfigError
from sygrid.objects.model import ObjectModel
from sygrid.robots import ur5e
from sygrid.robots.kinematics import forward_kinematics, ik_nearest
from sygrid.transforms import invert, is_rigid, make_T, transform_points

log = logging.getLogger(__name__)

#: Why a part or a grasp candidate was not planned, in the order the checks run.
REJECTION_CAUSES = (
    "no_model",
    "low_confidence",
    "no_candidates",
    "covered",
    "approach_angle",
    "collision_floor",
    "collision_parts",
    "collision_bin",
    "unreachable",
    "singular",
)
_PART_LEVEL = ("no_model", "low_confidence", "no_candidates", "covered")
_DOWN = np.array([0.0, 0.0, -1.0])
_SURFACE_SAMPLES = 2000  # per model: own-point test, neighbour obstacles, covered test
_NEIGHBOUR_SAMPLES = 400  # of those, the ones a neighbour contributes as obstacles
_COVER_CELL_M = 0.004  # height-map cell of the covered test
_UPWARD_COS = 0.5  # a surface point faces up when its normal is within 60 degrees of up
_UNDER_FRACTION = 0.02  # a part with more of its top than this covered is "under" another: it is ranked after


def _default_place_pose() -> np.ndarray:
    """Above the simulated cell's place tray (centre of its floor at (-0.2, -0.42, 0.005)), tool pointing down."""
    return make_T(np.diag([1.0, -1.0, -1.0]), (-0.2, -0.42, 0.12))


@dataclass(frozen=True)
class ScoreWeights:
    """Relative weights of the score terms (each in [0, 1]); the score is their weighted mean.

    confidence: the pose estimate's score. clearance: distance from the open fingers to the nearest obstacle
    (saturating at ``PlannerConfig.clearance_saturation_m``). height: how high the part lies in the pile (top parts
    first). approach: how close to straight down. quality: the candidate's own score (friction margin, centre of
    mass, contact area). engagement: how much pad holds the part (saturating at
    ``PlannerConfig.engagement_saturation_m``).
    """

    confidence: float = 1.0
    clearance: float = 1.0
    height: float = 2.0
    approach: float = 0.5
    quality: float = 0.5
    engagement: float = 0.5

    def __post_init__(self) -> None:
        values = [self.confidence, self.clearance, self.height, self.approach, self.quality, self.engagement]
        if min(values) < 0 or sum(values) <= 0:
            raise ConfigError(f"ScoreWeights must be >= 0 with a positive sum, got {values}")


@dataclass(frozen=True, eq=False)
class PlannerConfig:
    """Settings of the grasp planner; lengths in metres, angles as named. Defaults match the simulated cell.

    grasp_params: candidate generation, including the gripper's geometry (``grasp_params.gripper``).
    bin: the bin (None: no bin, nothing checked against walls or floor).
    approach_cone_deg: largest angle between the approach and straight down (base -z).
    pre_grasp_distance_m: the pre-grasp is this far back along the approach. lift_height_m: the lift is this far
    back out along the approach (the way the gripper came in, so the checked path; at least
    ``cos(approach_cone_deg) * lift_height_m`` above the grasp). T_base_place: where the part is let go (its
    position and approach axis; the tool turns about that axis to keep the grasp's pad direction).
    clearance_m: gripper to neighbouring parts and depth points. bin_clearance_m: gripper to the bin walls.
    floor_clearance_m: pad tips above the bin floor. min_engagement_m: the least length of the pads over which the
    part must be held after the gripper has stayed back to clear the floor or neighbours. With the defaults a washer
    lying flat on the floor (2.5 mm thick) is refused (``collision_floor``): in the simulated cell grasps holding it
    over 2 mm of pad slipped every time. On hardware, with calibration and pose errors of a millimetre or more,
    raise the floor clearance.
    joint_limit_margin_rad: kept from every joint limit. max_joint_step_rad: the largest joint change allowed
    between the grasp and its pre-grasp or lift (straight-line moves). q_reference_rad: the configuration IK
    solutions stay near (None: the one above the bin centre nearest ``ur5e.HOME_Q``).
    min_pose_score: parts whose pose score is lower are not picked.
    own_points_tolerance_m: depth points this close to a part's estimated surface are that part.
    bin_surface_tolerance_m: depth points this close to the bin's floor or walls are the bin.
    depth_stride_px: every n-th depth pixel in each direction becomes a point.
    max_covered_fraction / cover_tolerance_m: a part is covered when more than this share of its upward surface
    has something more than ``cover_tolerance_m`` above it.
    duplicate_distance_ratio: another estimate of the same object id whose origin is within this fraction of the
    diameter is taken for a duplicate detection, not a neighbour.
    clearance_saturation_m / engagement_saturation_m: where those score terms reach 1. height_spread_m: height
    differences in the pile smaller than this count less (the height term divides by at least this).
    max_grasps_per_part: planned grasps per part (alternatives for retries). max_planned_parts: stop planning
    (IK) once this many parts have a grasp, best parts first (None: all parts).
    """

    grasp_params: GraspSetParams = field(default_factory=GraspSetParams)
    bin: BinGeometry | None = field(default_factory=BinGeometry)
    approach_cone_deg: float = 30.0
    pre_grasp_distance_m: float = 0.10
    lift_height_m: float = 0.15
    T_base_place: np.ndarray = field(default_factory=_default_place_pose)
    clearance_m: float = 0.003
    bin_clearance_m: float = 0.003
    floor_clearance_m: float = 0.001
    min_engagement_m: float = 0.0025
    joint_limit_margin_rad: float = 0.1
    max_joint_step_rad: float = 1.0
    q_reference_rad: tuple[float, ...] | None = None
    min_pose_score: float = 0.0
    own_points_tolerance_m: float = 0.005
    bin_surface_tolerance_m: float = 0.003
    depth_stride_px: int = 2
    max_covered_fraction: float = 0.3
    cover_tolerance_m: float = 0.005
    duplicate_distance_ratio: float = 0.25
    clearance_saturation_m: float = 0.01
    engagement_saturation_m: float = 0.008
    height_spread_m: float = 0.02
    weights: ScoreWeights = field(default_factory=ScoreWeights)
    max_grasps_per_part: int = 1
    max_planned_parts: int | None = None

    def __post_init__(self) -> None:
        T = np.array(self.T_base_place, dtype=float)
        if not is_rigid(T):
            raise ConfigError(f"PlannerConfig.T_base_place must be a 4x4 rigid transform, got {T.tolist()}")
        T.flags.writeable = False
        object.__setattr__(self, "T_base_place", T)
        if not 0.0 < self.approach_cone_deg <= 90.0:
            raise ConfigError(f"PlannerConfig.approach_cone_deg must be in (0, 90], got {self.approach_cone_deg}")
        non_negative = (
            "pre_grasp_distance_m", "lift_height_m", "clearance_m", "bin_clearance_m", "floor_clearance_m",
            "min_engagement_m", "joint_limit_margin_rad", "own_points_tolerance_m", "bin_surface_tolerance_m",
            "cover_tolerance_m", "duplicate_distance_ratio",
        )  # fmt: skip
        for name in non_negative:
            if getattr(self, name) < 0:
                raise ConfigError(f"PlannerConfig.{name} must be >= 0, got {getattr(self, name)}")
        for name in ("max_joint_step_rad", "clearance_saturation_m", "engagement_saturation_m", "height_spread_m"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"PlannerConfig.{name} must be > 0, got {getattr(self, name)}")
        if not 0.0 <= self.max_covered_fraction <= 1.0:
            raise ConfigError(f"PlannerConfig.max_covered_fraction must be in [0, 1], got {self.max_covered_fraction}")
        if self.depth_stride_px < 1 or self.max_grasps_per_part < 1:
            raise ConfigError(
                f"PlannerConfig.depth_stride_px and max_grasps_per_part must be >= 1, got {self.depth_stride_px}, "
                f"{self.max_grasps_per_part}"
            )
        if self.max_planned_parts is not None and self.max_planned_parts < 1:
            raise ConfigError(f"PlannerConfig.max_planned_parts must be >= 1 or None, got {self.max_planned_parts}")
        if self.q_reference_rad is not None and np.shape(self.q_reference_rad) != (6,):
            raise ConfigError(f"PlannerConfig.q_reference_rad must be 6 joint angles (rad), got {self.q_reference_rad}")

    @property
    def gripper(self) -> GripperGeometry:
        return self.grasp_params.gripper


@dataclass(frozen=True, eq=False)
class PartEstimate:
    """A part to plan for: its object id, pose in the robot base frame and pose confidence in [0, 1]."""

    obj_id: int
    T_base_obj: np.ndarray
    score: float = 1.0

    def __post_init__(self) -> None:
        if not is_rigid(self.T_base_obj, atol=1e-4):
            raise ValueError(
                f"PartEstimate.T_base_obj must be a 4x4 rigid transform, got {np.asarray(self.T_base_obj).tolist()}"
            )


@dataclass(frozen=True, eq=False)
class PlannedGrasp:
    """One safe pick. Poses are TCP poses ``T_base_tcp`` (4x4, metres), joint solutions ``q_*`` (6,) radians.

    part_index: index of the part in the planner's input. opening_width_m: open the gripper to this before it
    reaches the pre-grasp (the approach was checked with the fingers at this opening: fully open they may hit the
    bin or a neighbour). grasp_width_m: the part's width between the pads (the gripper should stop about there when it
    closes on the part). backoff_m: how far the grasp was moved back along the approach from the candidate to clear
    the floor or neighbours. engagement_m: the length of pad that holds the part. clearance_m: distance from the
    open fingers (at the grasp) to the nearest obstacle (capped at the saturation). score_terms: the score's terms.
    """

    part_index: int
    obj_id: int
    score: float
    T_base_obj: np.ndarray
    T_base_pregrasp: np.ndarray
    T_base_grasp: np.ndarray
    T_base_lift: np.ndarray
    T_base_place: np.ndarray
    q_pregrasp: np.ndarray
    q_grasp: np.ndarray
    q_lift: np.ndarray
    q_place: np.ndarray
    opening_width_m: float
    grasp_width_m: float
    approach_angle_deg: float
    backoff_m: float
    engagement_m: float
    clearance_m: float
    pose_score: float
    score_terms: dict[str, float]

    @property
    def waypoints(self) -> tuple[tuple[str, np.ndarray], ...]:
        """``(name, T_base_tcp)`` in the order the robot visits them: pre_grasp, grasp, lift, place."""
        return (
            ("pre_grasp", self.T_base_pregrasp),
            ("grasp", self.T_base_grasp),
            ("lift", self.T_base_lift),
            ("place", self.T_base_place),
        )

    @property
    def joint_waypoints(self) -> tuple[tuple[str, np.ndarray], ...]:
        """``(name, q)`` for the same waypoints."""
        return (
            ("pre_grasp", self.q_pregrasp),
            ("grasp", self.q_grasp),
            ("lift", self.q_lift),
            ("place", self.q_place),
        )


@dataclass(frozen=True, eq=False)
class PartReport:
    """What the planner made of one part: ``status`` is ``"planned"``, ``"not_planned"`` (``max_planned_parts``
    was reached first) or the cause that ended it (the part-level cause, or the last check its candidates failed).
    ``rejections``: candidates per cause (a part-level cause counts every candidate). ``top_height_m``: its highest
    point (base z); ``covered_fraction``: share of its upward surface with something above it."""

    part_index: int
    obj_id: int
    status: str
    n_candidates: int
    n_planned: int
    rejections: dict[str, int]
    top_height_m: float
    covered_fraction: float


@dataclass(frozen=True, eq=False)
class GraspPlan:
    """The planner's answer: ``grasps`` best first (empty: nothing is safe to pick), a report per part, the
    rejection counts over all parts per cause, and the time each stage took (seconds).

    Order: grasps of parts with nothing lying on them (``covered_fraction`` at most 2 %) come first, then the
    others (a part under another comes after it); within each group, by score."""

    grasps: tuple[PlannedGrasp, ...]
    parts: tuple[PartReport, ...]
    rejections: dict[str, int]
    timings_s: dict[str, float]

    @property
    def nothing_safe(self) -> bool:
        return not self.grasps

    @property
    def best(self) -> PlannedGrasp | None:
        return self.grasps[0] if self.grasps else None

    def summary(self) -> str:
        """One line for logs: what was planned, or that nothing is safe, with the rejection counts."""
        causes = ", ".join(f"{c} {n}" for c, n in self.rejections.items() if n) or "none"
        statuses = ", ".join(f"part {p.part_index} (obj {p.obj_id}): {p.status}" for p in self.parts)
        if self.nothing_safe:
            return f"nothing safe to pick among {len(self.parts)} part(s): {statuses}; rejected candidates: {causes}"
        planned = len({g.part_index for g in self.grasps})
        return (
            f"{len(self.grasps)} grasp(s) for {planned} of {len(self.parts)} part(s), best on part "
            f"{self.grasps[0].part_index} (score {self.grasps[0].score:.2f}); rejected candidates: {causes}"
        )


@dataclass(frozen=True, eq=False)
class _ModelData:
    """What the planner keeps per model: its candidates and a surface sample (object frame)."""

    model: ObjectModel
    grasps: GraspSet
    surface: np.ndarray  # (n, 3)
    normals: np.ndarray  # (n, 3)
    tree: cKDTree


class GraspPlanner:
    """Plans picks for estimated parts. Build it once per set of models (it computes or loads their grasp
    candidates), then call ``plan`` per camera frame.

    Args:
        models: the object models, as a sequence or a mapping from object id.
        config: the planner's settings (optional; ``PlannerConfig()`` when not given).
        cache_dir: where grasp candidates are cached (see ``robot.grasps.resolve_cache_dir``).
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
        margin = self.config.joint_limit_margin_rad
        self._limits = np.asarray(ur5e.JOINT_LIMITS_RAD) + np.array([margin, -margin])
        if np.any(self._limits[:, 0] >= self._limits[:, 1]):
            raise ConfigError(f"PlannerConfig.joint_limit_margin_rad {margin} leaves no joint range")
        self._down = -self.config.bin.floor_normal if self.config.bin is not None else _DOWN
        self.q_reference = self._reference_configuration()

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
    ) -> GraspPlan:
        """Plans picks for the perception pipeline's poses (camera frame), with the depth frame when given.

        Args:
            poses: the estimated parts (``T_camera_object``, score, object id).
            T_base_camera: the camera in the robot base frame (hand-eye calibration), 4x4.
            depth_m: (H, W) depth in metres of the frame the poses came from (0 = no data); optional.
            intrinsics: the depth frame's intrinsics (``CameraIntrinsics`` or 3x3 K); required with ``depth_m``.
            q_seed: the configuration IK solutions stay near (default ``q_reference``).
        """
        start = time.perf_counter()
        T_base_camera = np.asarray(T_base_camera, dtype=float)
        if not is_rigid(T_base_camera, atol=1e-4):
            raise ValueError(f"T_base_camera must be a 4x4 rigid transform, got {T_base_camera.tolist()}")
        parts = [
            PartEstimate(p.obj_id, T_base_camera @ np.asarray(p.T_camera_object, dtype=float), float(p.score))
            for p in poses
        ]
        cloud = None
        if depth_m is not None:
            if intrinsics is None:
                raise ValueError("plan: depth_m was given without its intrinsics")
            cloud = self._depth_cloud(depth_m, intrinsics, T_base_camera)
        depth_s = time.perf_counter() - start
        plan = self._plan(parts, cloud, q_seed)
        plan.timings_s["depth_cloud"] = depth_s
        plan.timings_s["total"] = time.perf_counter() - start
        return plan

    def plan_parts(
        self,
        parts: Sequence[PartEstimate],
        cloud_base: np.ndarray | None = None,
        q_seed: np.ndarray | None = None,
    ) -> GraspPlan:
        """Plans picks for parts given in the base frame, with an optional point cloud ``(n, 3)`` in the base frame
        (the depth camera's points; the bin's own points are dropped here)."""
        cloud = None if cloud_base is None else np.asarray(cloud_base, dtype=float).reshape(-1, 3)
        if self.config.bin is not None and cloud is not None:
            cloud = self.config.bin.pile_points(cloud, self.config.bin_surface_tolerance_m)
        return self._plan(parts, cloud, q_seed)

    def _plan(self, parts: Sequence[PartEstimate], cloud: np.ndarray | None, q_seed: np.ndarray | None) -> GraspPlan:
        """``plan_parts`` for a cloud that holds only the pile (no bin points)."""
        cfg = self.config
        timings = {"checks": 0.0, "ik": 0.0}
        q_seed = self.q_reference if q_seed is None else np.asarray(q_seed, dtype=float)
        if q_seed.shape != (6,) or not np.all(np.isfinite(q_seed)):
            raise ValueError(f"q_seed must be 6 finite joint angles (rad), got {q_seed.tolist()}")
        cloud = np.zeros((0, 3)) if cloud is None else cloud

        surfaces = [self._surface_base(p) for p in parts]
        obstacles, owner = self._scene_obstacles(cloud, parts, surfaces)
        tops = np.array([s[:, 2].max() if s is not None else np.nan for s in surfaces])
        known = tops[np.isfinite(tops)]
        z_low = float(known.min()) if len(known) else 0.0
        spread = max(float(known.max() - z_low) if len(known) else 0.0, cfg.height_spread_m)

        evaluated: list[_Evaluated] = []
        reports: dict[int, dict] = {}
        for i, part in enumerate(parts):
            start = time.perf_counter()
            result = self._evaluate_part(i, part, parts, surfaces, obstacles, owner, (tops[i] - z_low) / spread)
            timings["checks"] += time.perf_counter() - start
            reports[i] = result.report
            if result.ranked is not None:
                evaluated.append(result)

        # IK in score order: best parts first, each part's candidates best first
        start = time.perf_counter()
        # top parts first: a part with something lying on it comes after every part with nothing on it
        under = {e.part_index: e.report["covered_fraction"] > _UNDER_FRACTION for e in evaluated}
        evaluated.sort(key=lambda e: (under[e.part_index], -e.best_score))
        planned: list[PlannedGrasp] = []
        parts_planned = 0
        for ev in evaluated:
            if cfg.max_planned_parts is not None and parts_planned >= cfg.max_planned_parts:
                reports[ev.part_index]["status"] = "not_planned"
                continue
            grasps = self._solve_ik(ev, q_seed)
            report = reports[ev.part_index]
            report["n_planned"] = len(grasps)
            if grasps:
                parts_planned += 1
                planned.extend(grasps)
            report["status"] = "planned" if grasps else _main_cause(report["rejections"])
        timings["ik"] = time.perf_counter() - start

        planned.sort(key=lambda g: (under[g.part_index], -g.score))
        part_reports = tuple(PartReport(**reports[i]) for i in range(len(parts)))
        totals = {cause: sum(p.rejections.get(cause, 0) for p in part_reports) for cause in REJECTION_CAUSES}
        plan = GraspPlan(tuple(planned), part_reports, totals, timings)
        log.debug("grasp plan: %s", plan.summary())
        return plan

    # ------------------------------------------------------------------------------------------ per part

    def _evaluate_part(
        self,
        index: int,
        part: PartEstimate,
        parts: Sequence[PartEstimate],
        surfaces: list[np.ndarray | None],
        scene_obstacles: np.ndarray,
        owner: np.ndarray,
        height_term: float,
    ) -> _Evaluated:
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
        n = len(data.grasps)
        report["n_candidates"] = n
        report["top_height_m"] = float(surfaces[index][:, 2].max())
        if part.score < cfg.min_pose_score:
            return part_level("low_confidence", n)
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
        obstacles = scene_obstacles[~np.isin(owner, duplicates)]
        covered = self._covered_fraction(part, data, obstacles)
        report["covered_fraction"] = covered
        if covered > cfg.max_covered_fraction:
            return part_level("covered", n)

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
        # the points near each grasp's gripper (near enough to count for its clearance), in its TCP frame
        P, valid = _local_points(obstacles, Ti, boxes, sweep, max(cfg.clearance_m, cfg.clearance_saturation_m))
        d_parts = required_backoff_m(P, boxes, cfg.clearance_m, valid=valid, sweep_length_m=sweep)
        d_floor = np.maximum(self._floor_backoff(Ti, boxes, cos_angle[idx]), 0.0)
        d = np.maximum(d_floor, d_parts)
        floor_fail = _engagement(contact, d_floor, g) < cfg.min_engagement_m
        parts_fail = ~floor_fail & (_engagement(contact, d, g) < cfg.min_engagement_m)
        cause[idx[floor_fail]] = _code("collision_floor")
        cause[idx[parts_fail]] = _code("collision_parts")
        keep = ~(floor_fail | parts_fail)
        idx, d, Ti, P, valid, boxes = idx[keep], d[keep], Ti[keep], P[keep], valid[keep], boxes[keep]
        width, opening, contact = width[keep], opening[keep], contact[keep]
        back = np.tile(np.eye(4), (len(idx), 1, 1))
        back[:, 2, 3] = -d
        Tg = Ti @ back  # the grasps, moved back
        P = P + np.stack([np.zeros_like(d), np.zeros_like(d), d], axis=1)[:, None, :].astype(P.dtype)

        # bin walls: the boxes swept along the approach (a box moved along its own z stays a box)
        wall_gap = np.full(len(idx), np.inf)
        if cfg.bin is not None and len(idx):
            swept = boxes.copy()
            swept[..., 0, 2] -= sweep
            wall_gap = self._wall_gap(Tg, swept)
        wall_fail = wall_gap < cfg.bin_clearance_m
        cause[idx[wall_fail]] = _code("collision_bin")
        keep = ~wall_fail
        idx, d, Tg, P, valid, wall_gap = idx[keep], d[keep], Tg[keep], P[keep], valid[keep], wall_gap[keep]
        width, opening, contact = width[keep], opening[keep], contact[keep]

        # score
        fingers = g.boxes(opening)[:, FINGER_BOXES]
        clearance = points_box_distance_m(P, fingers, valid=valid, cap_m=cfg.clearance_saturation_m)
        clearance = np.minimum(clearance, wall_gap)
        engagement = _engagement(contact, d, g)
        w = cfg.weights
        terms = {
            "confidence": np.full(len(idx), float(np.clip(part.score, 0.0, 1.0))),
            "clearance": np.clip(clearance / cfg.clearance_saturation_m, 0.0, 1.0),
            "height": np.full(len(idx), float(np.clip(height_term, 0.0, 1.0))),
            "approach": 1.0 - angle[idx] / math.radians(cfg.approach_cone_deg),
            "quality": np.clip(data.grasps.score[idx], 0.0, 1.0),
            "engagement": np.clip(engagement / cfg.engagement_saturation_m, 0.0, 1.0),
        }
        weights = {name: getattr(w, name) for name in terms}
        score = sum(weights[k] * terms[k] for k in terms) / sum(weights.values())
        order = np.lexsort((idx, -score))

        for code, count in enumerate(np.bincount(cause[cause >= 0], minlength=len(REJECTION_CAUSES))):
            report["rejections"][REJECTION_CAUSES[code]] += int(count)
        if not len(idx):
            report["status"] = _main_cause(report["rejections"])
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
            "terms": {k: v[order] for k, v in terms.items()},
        }
        return _Evaluated(index, report, part, ranked, float(score[order[0]]))

    def _solve_ik(self, ev: _Evaluated, q_seed: np.ndarray) -> list[PlannedGrasp]:
        """IK for the ranked candidates of one part, best first, until ``max_grasps_per_part`` succeed; the ones
        that fail are counted as ``unreachable`` or ``singular``."""
        cfg = self.config
        r = ev.ranked
        T_flange_tcp = cfg.gripper.T_flange_tcp
        x_seed = forward_kinematics(q_seed, T_flange_tcp)[:3, 0]
        out: list[PlannedGrasp] = []
        for k in range(len(r["score"])):
            T_grasp = r["T_grasp"][k].copy()
            # the pads are interchangeable: turn the tool half a turn about z if that keeps the wrist nearer the seed
            if T_grasp[:3, 0] @ x_seed < 0:
                T_grasp[:3, :2] *= -1.0
            T_pre = T_grasp @ make_T(t=(0.0, 0.0, -cfg.pre_grasp_distance_m))
            T_lift = T_grasp @ make_T(t=(0.0, 0.0, -cfg.lift_height_m))
            T_place = _place_pose(cfg.T_base_place, T_grasp[:3, 0])
            q_grasp = ik_nearest(T_grasp, q_seed, T_flange_tcp, self._limits)
            q_pre = q_lift = q_place = None
            if q_grasp is not None:
                q_pre = ik_nearest(T_pre, q_grasp, T_flange_tcp, self._limits)
                q_lift = ik_nearest(T_lift, q_grasp, T_flange_tcp, self._limits)
            if q_pre is not None and q_lift is not None:
                q_place = ik_nearest(T_place, q_lift, T_flange_tcp, self._limits)
            if q_grasp is None or q_pre is None or q_lift is None or q_place is None:
                ev.report["rejections"]["unreachable"] += 1
                continue
            step = max(np.abs(q_pre - q_grasp).max(), np.abs(q_lift - q_grasp).max())
            if step > cfg.max_joint_step_rad:
                ev.report["rejections"]["singular"] += 1
                continue
            out.append(
                PlannedGrasp(
                    part_index=ev.part_index,
                    obj_id=ev.part.obj_id,
                    score=float(r["score"][k]),
                    T_base_obj=np.array(ev.part.T_base_obj, dtype=float),
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
                    approach_angle_deg=float(np.degrees(r["angle"][k])),
                    backoff_m=float(r["backoff"][k]),
                    engagement_m=float(r["engagement"][k]),
                    clearance_m=float(r["clearance"][k]),
                    pose_score=float(ev.part.score),
                    score_terms={name: float(v[k]) for name, v in r["terms"].items()},
                )
            )
            if len(out) >= cfg.max_grasps_per_part:
                break
        return out

    # ------------------------------------------------------------------------------------------ scene helpers

    def _scene_obstacles(
        self, cloud: np.ndarray, parts: Sequence[PartEstimate], surfaces: list[np.ndarray | None]
    ) -> tuple[np.ndarray, np.ndarray]:
        """Every obstacle point of the scene, ``(m, 3)`` base frame, with the index of the part it belongs to
        (``(m,)``, -1: none): the cloud points (a point within ``own_points_tolerance_m`` of a part's estimated
        surface belongs to the nearest such part) and a sample of each part's estimated surface (which also stands
        for its unseen sides)."""
        known = [i for i, s in enumerate(surfaces) if s is not None]
        owner = np.full(len(cloud), -1)
        if len(cloud) and known:
            points = np.concatenate([surfaces[i] for i in known])
            labels = np.concatenate([np.full(len(surfaces[i]), i) for i in known])
            tol = self.config.own_points_tolerance_m
            dist, nearest = cKDTree(points).query(cloud, k=1, distance_upper_bound=tol)
            hit = np.isfinite(dist)
            owner[hit] = labels[nearest[hit]]
        samples = [surfaces[i][:_NEIGHBOUR_SAMPLES] for i in known]
        points = np.concatenate([cloud, *samples]) if samples else cloud
        owner = np.concatenate([owner, *[np.full(len(s), i) for i, s in zip(known, samples, strict=True)]])
        return points, owner

    def _covered_fraction(self, part: PartEstimate, data: _ModelData, obstacles: np.ndarray) -> float:
        """Share of the part's upward-facing surface points with an obstacle point more than ``cover_tolerance_m``
        above them (same height-map cell)."""
        up = -self._down
        normals = data.normals @ part.T_base_obj[:3, :3].T
        top = transform_points(part.T_base_obj, data.surface[normals @ up > _UPWARD_COS])
        if not len(top) or not len(obstacles):
            return 0.0
        lo = top[:, :2].min(axis=0) - _COVER_CELL_M
        shape = np.ceil((top[:, :2].max(axis=0) + _COVER_CELL_M - lo) / _COVER_CELL_M).astype(int) + 1
        over = obstacles[np.all((obstacles[:, :2] >= lo) & (obstacles[:, :2] < lo + shape * _COVER_CELL_M), axis=1)]
        cells = np.clip(np.floor((over[:, :2] - lo) / _COVER_CELL_M).astype(int), 0, shape - 1)
        height = np.full(shape, -np.inf)
        np.maximum.at(height, (cells[:, 0], cells[:, 1]), over @ up)
        top_cells = np.floor((top[:, :2] - lo) / _COVER_CELL_M).astype(int)
        above = height[top_cells[:, 0], top_cells[:, 1]] > top @ up + self.config.cover_tolerance_m
        return float(above.mean())

    def _wall_gap(self, T: np.ndarray, boxes: np.ndarray) -> np.ndarray:
        """``(k,)`` gap between each grasp's boxes (``(k, b, 2, 3)``, TCP frame) and the bin walls (a lower bound
        on the distance; < 0: they overlap).

        Boxes whose corners all lie inside the bin's inner prism (extended upwards) cannot touch a wall: their gap
        is the corners' distance to the walls. Only the others go through the separating-axis test."""
        b = self.config.bin
        corners = _box_corners(boxes)  # (k, b * 8, 3)
        T_bin_tcp = invert(b.T_base_bin) @ T
        c_bin = np.einsum("kij,kpj->kpi", T_bin_tcp[:, :3, :3], corners) + T_bin_tcp[:, None, :3, 3]
        half_xy = np.array(b.inner_size_m[:2]) / 2.0
        gap = (half_xy - np.abs(c_bin[..., :2])).min(axis=(1, 2))
        hard = np.flatnonzero(gap < self.config.bin_clearance_m)
        if len(hard):
            sub = boxes[hard]
            centre_tcp, half = sub.mean(axis=-2), (sub[..., 1, :] - sub[..., 0, :]) / 2.0  # (h, b, 3)
            R = T[hard, :3, :3]
            centre = np.einsum("kij,kbj->kbi", R, centre_tcp) + T[hard, None, :3, 3]
            wc, wR, wh = b.wall_boxes()
            sat = obb_gap_m(centre[:, :, None, :], R[:, None, None], half[:, :, None, :], wc, wR, wh)
            gap[hard] = sat.reshape(len(hard), -1).min(axis=1)
        return gap

    def _floor_backoff(self, T: np.ndarray, boxes: np.ndarray, cos_angle: np.ndarray) -> np.ndarray:
        """``(k,)`` how far each grasp must move back along its approach so that every gripper box is at least
        ``floor_clearance_m`` above the bin floor (-inf without a bin)."""
        cfg = self.config
        if cfg.bin is None or not len(T):
            return np.full(len(T), -np.inf)
        corners = _box_corners(boxes)  # (k, b * 8, 3), TCP frame
        points = np.einsum("kij,kpj->kpi", T[:, :3, :3], corners) + T[:, None, :3, 3]
        height = cfg.bin.height_above_floor_m(points).min(axis=1)
        # moving back by d along the approach raises the gripper by d * cos(angle)
        return (cfg.floor_clearance_m - height) / np.maximum(cos_angle, 1e-6)

    def _depth_cloud(
        self, depth_m: np.ndarray, intrinsics: CameraIntrinsics | np.ndarray, T_base_camera: np.ndarray
    ) -> np.ndarray:
        """The depth frame's points of the pile, base frame (with a bin: cropped in the bin frame, one transform)."""
        cfg = self.config
        if cfg.bin is None:
            return depth_points(depth_m, intrinsics, T_base_camera, cfg.depth_stride_px)
        T_bin_camera = invert(cfg.bin.T_base_bin) @ T_base_camera
        points_bin = depth_points(depth_m, intrinsics, T_bin_camera, cfg.depth_stride_px)
        points_bin = points_bin[cfg.bin.in_pile_bin_frame(points_bin, cfg.bin_surface_tolerance_m)]
        return transform_points(cfg.bin.T_base_bin, points_bin)

    def _surface_base(self, part: PartEstimate) -> np.ndarray | None:
        data = self._models.get(part.obj_id)
        return None if data is None else transform_points(part.T_base_obj, data.surface)

    def _prepare(self, model: ObjectModel, cache_dir: str | Path | None) -> _ModelData:
        grasps = grasp_candidates(model, self.config.grasp_params, cache_dir)
        rng = np.random.default_rng(self.config.grasp_params.seed)
        surface, faces = trimesh.sample.sample_surface(model.mesh, _SURFACE_SAMPLES, seed=rng)
        return _ModelData(model, grasps, surface, model.mesh.face_normals[faces], cKDTree(surface))

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


@dataclass(eq=False)
class _Evaluated:
    """A part after the geometric checks: its report (mutable, IK adds to it) and its ranked survivors."""

    part_index: int
    report: dict
    part: PartEstimate | None = None
    ranked: dict | None = None
    best_score: float = -np.inf


# ---------------------------------------------------------------------------------------------- helpers


def _code(cause: str) -> int:
    return REJECTION_CAUSES.index(cause)


def _main_cause(rejections: dict[str, int]) -> str:
    """The cause that stopped the candidates that got furthest (the last check any candidate failed): for a part
    whose candidates mostly miss the approach cone, that says why the ones inside the cone were not planned."""
    seen = [c for c in REJECTION_CAUSES if rejections.get(c, 0)]
    return seen[-1] if seen else "no_candidates"


def _local_points(
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
    corners = _box_corners(np.stack([lo, hi], axis=1)[:, None])  # (k, 8, 3)
    corners_base = np.einsum("kij,kpj->kpi", T[:, :3, :3], corners) + T[:, None, :3, 3]
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


def _engagement(contact_z: np.ndarray, backoff: np.ndarray, g: GripperGeometry) -> np.ndarray:
    """Length along z over which the pads, moved back by ``backoff``, overlap the contact span."""
    half = g.pad_length_m / 2.0
    return np.minimum(half - backoff, contact_z[:, 1]) - np.maximum(-half - backoff, contact_z[:, 0])


def _box_corners(boxes: np.ndarray) -> np.ndarray:
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


def _place_pose(T_base_place: np.ndarray, x_grasp: np.ndarray) -> np.ndarray:
    """The place pose turned about its approach axis so that the pads keep the grasp's direction (the wrist does
    not spin on the way)."""
    z = T_base_place[:3, 2]
    x = x_grasp - (x_grasp @ z) * z
    if np.linalg.norm(x) < 1e-6:
        return T_base_place.copy()
    x /= np.linalg.norm(x)
    T = T_base_place.copy()
    T[:3, 0], T[:3, 1] = x, np.cross(z, x)
    return T
