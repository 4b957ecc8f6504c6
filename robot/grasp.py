"""The grasp planner: from estimated part poses (and a depth frame) to an ordered list of safe picks, each with its
pre-grasp, grasp, lift and place waypoints, or a clear "nothing safe to pick" with the reasons.

For each estimated part, in the robot base frame (``T_base_obj = T_base_camera @ T_camera_object``), its grasp
candidates (``robot.grasps``) go through these checks, cheapest first; the first one a candidate fails is its
rejection cause (``REJECTION_CAUSES``):

1. part level: a model for its id (``no_model``), inside the bin (``outside_bin``: its origin outside the bin's
   inner footprint or below its floor; the camera may also see the place tray, whose walls the planner does not
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

Geometry is boxes against points and oriented boxes (``robot.grasp_geometry``); the robot arm itself is not
checked against the bin (only the gripper and the wrist link behind it; the sim-in-the-loop runs and
``sygrid bench cell`` check the whole arm in MuJoCo).
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
    WRIST_LINKS,
    GripperGeometry,
    box_corners,
    lowest_elbow_point_m,
    obb_gap_m,
    points_box_distance_m,
    required_backoff_m,
    wrist_link_boxes_m,
    wrist_link_frames,
)
from robot.grasp_scene import BinGeometry, depth_points
from robot.grasps import GraspSet, GraspSetParams, grasp_candidates
from robot.ur_config import WorkspaceBox
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
    "outside_bin",
    "low_confidence",
    "unrefined",
    "no_candidates",
    "covered",
    "approach_angle",
    "collision_floor",
    "collision_bin",
    "collision_parts",
    "unreachable",
    "singular",
    "collision_transit",
)
_PART_LEVEL = ("no_model", "outside_bin", "low_confidence", "unrefined", "no_candidates", "covered")
_DOWN = np.array([0.0, 0.0, -1.0])
_SURFACE_SAMPLES = 2000  # per model: own-point test, neighbour obstacles, covered test
_NEIGHBOUR_SAMPLES = 400  # of those, the ones a neighbour contributes as obstacles
_COVER_CELL_M = 0.004  # height-map cell of the covered test
_UPWARD_COS = 0.5  # a surface point faces up when its normal is within 60 degrees of up
_LIFT_RAISES_M = (0.05, 0.1)  # further back along the approach when the joint moves from the lift are not clear
_UNDER_FRACTION = 0.02  # a part with more of its top than this covered is "under" another: it is ranked after


def _default_place_pose() -> np.ndarray:
    """Above the simulated cell's place tray (centre of its floor at (-0.2, -0.42, 0.005)), tool pointing down.

    0.22 m up: the pads' tips 0.2 m above the tray floor and 0.06 m above the bin's rim (0.14 m), so that the joint
    moves between the tray and the bin pass over the bin's wall (at 0.12 m they swung the fingers through it)."""
    return make_T(np.diag([1.0, -1.0, -1.0]), (-0.2, -0.42, 0.22))


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
    approach_cone_deg: largest angle between the approach and straight down (base -z). 45 degrees: tilting away
    from a wall is what lets the 86 x 62 mm housing reach a part near it (a planner-only replay of 10 bins of
    ``launch/scenes/pick_bin_10.json``, every planned pick taken as done: 35 % of the parts cleared with 30 degrees
    and 12 approach steps, 42 % with 45 degrees and 16 steps).
    pre_grasp_distance_m: the pre-grasp is this far back along the approach. lift_height_m: the lift is at least
    this far back out along the approach (the way the gripper came in, so the checked path), and further when the
    gripper or the held part would not yet clear the bin's rim by ``rim_clearance_m``. T_base_place: where the
    part is let go (its position and approach axis; the tool turns about that axis to keep the grasp's pad
    direction); the arm also waits there while the camera looks.
    transit_clearance_m: the gripper (and the held part) to the bin walls along the joint moves to the lift and to
    the place pose, sampled every ``transit_step_rad`` of the largest joint change (None: not checked, for
    comparisons only). min_elbow_height_m: the upper arm and forearm stay this high above the base's xy plane along
    those joint moves (the default cell's table is at 0 and its tray's rim at 0.035 m; None: not checked).
    workspace: the robot's workspace box (``URConfig.workspace``): waypoints whose TCP lies
    outside it are unreachable (None: not checked).
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
    require_refined: parts whose depth refinement refused the estimate or was skipped (the RGB estimate alone:
        centimetres off on this stack's models) are not picked (``unrefined``); poses without refinement (ground
        truth) are.
    own_points_tolerance_m: depth points this close to a part's estimated surface are that part.
    bin_surface_tolerance_m: depth points this close to the bin's floor or walls are the bin.
    depth_stride_px: every n-th depth pixel in each direction becomes a point.
    max_covered_fraction / cover_tolerance_m: a part is covered when more than this share of its upward surface
    has something more than ``cover_tolerance_m`` above it.
    duplicate_distance_ratio: another estimate of the same object id whose origin is within this fraction of the
    diameter is taken for a duplicate detection, not a neighbour.
    clearance_saturation_m / engagement_saturation_m: where those score terms reach 1. height_spread_m: height
    differences in the pile smaller than this count less (the height term divides by at least this).
    max_grasps_per_part: planned grasps per part (alternatives for retries). max_planned_parts: plan this many
    parts, best first (None: all parts); the other parts' candidates are checked only if they could still rank
    among them, which saves most of the time in a full bin. min_grasp_width_m: candidates narrower than this are
    not used (0: all). A 2 mm sheet is held: the picker takes fingers that stopped apart for a hold even when the
    gripper's object detection, which needs them 1.5 mm or more short of closed, says "no object"
    (``PickerConfig.min_held_width_m``); these pinches are an L-bracket standing on its sheet edges' only grasps.
    """

    grasp_params: GraspSetParams = field(default_factory=GraspSetParams)
    bin: BinGeometry | None = field(default_factory=BinGeometry)
    approach_cone_deg: float = 45.0
    pre_grasp_distance_m: float = 0.10
    lift_height_m: float = 0.15
    rim_clearance_m: float = 0.01
    T_base_place: np.ndarray = field(default_factory=_default_place_pose)
    transit_clearance_m: float | None = 0.005
    min_elbow_height_m: float | None = 0.06
    transit_step_rad: float = 0.02
    workspace: WorkspaceBox | None = None
    clearance_m: float = 0.003
    bin_clearance_m: float = 0.003
    floor_clearance_m: float = 0.001
    min_engagement_m: float = 0.0025
    joint_limit_margin_rad: float = 0.1
    max_joint_step_rad: float = 1.0
    q_reference_rad: tuple[float, ...] | None = None
    min_pose_score: float = 0.0
    require_refined: bool = True
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
    min_grasp_width_m: float = 0.0

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
            "cover_tolerance_m", "duplicate_distance_ratio", "rim_clearance_m", "transit_clearance_m",
            "min_grasp_width_m",
        )  # fmt: skip
        for name in non_negative:
            if getattr(self, name) is not None and getattr(self, name) < 0:
                raise ConfigError(f"PlannerConfig.{name} must be >= 0, got {getattr(self, name)}")
        for name in (
            "max_joint_step_rad", "clearance_saturation_m", "engagement_saturation_m", "height_spread_m",
            "transit_step_rad",
        ):  # fmt: skip
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
    """A part to plan for: its object id, pose in the robot base frame, pose confidence in [0, 1], and whether
    depth refinement confirmed the pose (None: no refinement was run, e.g. ground truth or an RGB-only cell)."""

    obj_id: int
    T_base_obj: np.ndarray
    score: float = 1.0
    refined: bool | None = None

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
    closes on the part). min_hold_width_m: the narrowest of the part's candidate widths: a part that turns in the
    closing fingers, or whose estimate was off, is held at another of its widths, not lost. backoff_m: how far the
    grasp was moved back along the approach from the candidate to clear the floor or neighbours. engagement_m: the
    length of pad that holds the part. clearance_m: distance from the open fingers (at the grasp) to the nearest
    obstacle (capped at the saturation). score_terms: the score's terms.
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
    min_hold_width_m: float
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

    @property
    def n_in_bin(self) -> int:
        """Parts that are in the bin (all of them without a bin): 0 means the bin is empty whatever else the camera
        saw."""
        return sum(p.status != "outside_bin" for p in self.parts)

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
        self._wrist_boxes = wrist_link_boxes_m()
        self.q_reference = self._reference_configuration()

    @property
    def joint_limits_rad(self) -> np.ndarray:
        """``(6, 2)`` the joint limits less ``joint_limit_margin_rad``: what IK solutions must stay within."""
        return self._limits

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
            PartEstimate(p.obj_id, T_base_camera @ np.asarray(p.T_camera_object, dtype=float), float(p.score),
                         _refined(p))
            for p in poses
        ]  # fmt: skip
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

        surfaces = [self.surface_base(p) for p in parts]
        obstacles, owner = self._scene_obstacles(cloud, parts, surfaces)
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
            grasps = self._solve_ik(ev, q_seed)
            timings["ik"] += time.perf_counter() - start
            report = reports[ev.part_index]
            report["n_planned"] = len(grasps)
            report["status"] = "planned" if grasps else _main_cause(report["rejections"])
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
        plan = GraspPlan(tuple(planned), part_reports, totals, timings)
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
        """The part-level checks (``_PART_LEVEL``); for a part that passes them, what the candidate checks need
        (``pending``) and an upper bound on its best candidate's score (``best_score``): the order in which parts
        are worth checking further."""
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
        if cfg.bin is not None and not cfg.bin.holds(part.T_base_obj[:3, 3]):
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
        obstacles = scene_obstacles[~np.isin(owner, duplicates)]
        covered = self._covered_fraction(part, data, obstacles)
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
            weights = {name: getattr(w, name) for name in terms}
            best = sum(weights[k] * terms[k] for k in terms) / sum(weights.values())
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
        d_floor = np.maximum(self._floor_backoff(Ti, boxes, cos_angle[idx]), 0.0)
        floor_fail = _engagement(contact, d_floor, g) < cfg.min_engagement_m
        wall_fail = ~floor_fail & self._walls_at_every_backoff(Ti, boxes, d_floor, contact, sweep)
        cause[idx[floor_fail]] = _code("collision_floor")
        cause[idx[wall_fail]] = _code("collision_bin")
        keep = ~(floor_fail | wall_fail)
        idx, d_floor, Ti, boxes = idx[keep], d_floor[keep], Ti[keep], boxes[keep]
        width, opening, contact = width[keep], opening[keep], contact[keep]
        # the points near each grasp's gripper (near enough to count for its clearance), in its TCP frame
        P, valid = _local_points(obstacles, Ti, boxes, sweep, max(cfg.clearance_m, cfg.clearance_saturation_m))
        d_parts = required_backoff_m(P, boxes, cfg.clearance_m, valid=valid, sweep_length_m=sweep)
        d = np.maximum(d_floor, d_parts)
        parts_fail = _engagement(contact, d, g) < cfg.min_engagement_m
        cause[idx[parts_fail]] = _code("collision_parts")
        keep = ~parts_fail
        idx, d, Ti, P, valid, boxes = idx[keep], d[keep], Ti[keep], P[keep], valid[keep], boxes[keep]
        width, opening, contact = width[keep], opening[keep], contact[keep]
        back = np.tile(np.eye(4), (len(idx), 1, 1))
        back[:, 2, 3] = -d
        Tg = Ti @ back  # the grasps, moved back
        P = P + np.stack([np.zeros_like(d), np.zeros_like(d), d], axis=1)[:, None, :].astype(P.dtype)

        # the lift: back out along the approach until the gripper and the part in it clear the bin's rim
        part_box = _part_box_tcp(Tg, part.T_base_obj, data.model.bounds_m)
        lift = self._lift_distance(Tg, g.boxes(width), surfaces[index], cos_angle[idx])

        # bin walls: the boxes swept along the approach from the grasp to the lift (a box moved along its own z
        # stays a box)
        wall_gap = np.full(len(idx), np.inf)
        if cfg.bin is not None and len(idx):
            swept = boxes.copy()
            swept[..., 0, 2] -= np.maximum(lift, cfg.pre_grasp_distance_m)[:, None]
            wall_gap = self.wall_gap_m(Tg, swept)
        wall_fail = wall_gap < cfg.bin_clearance_m
        cause[idx[wall_fail]] = _code("collision_bin")
        keep = ~wall_fail
        idx, d, Tg, P, valid, wall_gap = idx[keep], d[keep], Tg[keep], P[keep], valid[keep], wall_gap[keep]
        width, opening, contact, lift, part_box = width[keep], opening[keep], contact[keep], lift[keep], part_box[keep]

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
            "lift": lift[order],
            "part_box": part_box[order],
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
        min_hold_width = float(self._models[ev.part.obj_id].grasps.width_m.min())  # the part's, for every grasp
        out: list[PlannedGrasp] = []
        for k in range(len(r["score"])):
            T_grasp = r["T_grasp"][k].copy()
            # the pads are interchangeable: turn the tool half a turn about z if that keeps the wrist nearer the seed
            if T_grasp[:3, 0] @ x_seed < 0:
                T_grasp[:3, :2] *= -1.0
            T_pre = T_grasp @ make_T(t=(0.0, 0.0, -cfg.pre_grasp_distance_m))
            T_lift = T_grasp @ make_T(t=(0.0, 0.0, -float(r["lift"][k])))
            T_place = _place_pose(cfg.T_base_place, T_grasp[:3, 0])
            # the grasp's IK branch is the reference's, wherever the arm is: seeded from the arm's configuration, the
            # branch drifted pick by pick (the shoulder ended up turned back and the elbow swung down to the tray)
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
                ev.report["rejections"]["unreachable"] += 1
                continue
            step = max(np.abs(q_pre - q_grasp).max(), np.abs(q_lift - q_grasp).max())
            if step > cfg.max_joint_step_rad:
                ev.report["rejections"]["singular"] += 1
                continue
            if self.wrist_gap_m(np.stack([q_pre, q_grasp, q_lift])).min() < cfg.bin_clearance_m:
                ev.report["rejections"]["collision_bin"] += 1
                continue
            # the half-turn about z above mirrors the part's box (TCP frame) in x and y
            part_box = r["part_box"][k]
            if T_grasp[:3, 0] @ r["T_grasp"][k][:3, 0] < 0:
                part_box = part_box * np.array([-1.0, -1.0, 1.0])[None, :]
                part_box = np.stack([part_box.min(axis=0), part_box.max(axis=0)])
            lifted = self._clear_transits(q_seed, T_grasp, q_grasp, (T_lift, q_lift, q_place), part_box, r, k)
            if lifted is None:
                ev.report["rejections"]["collision_transit"] += 1
                continue
            T_lift, q_lift, q_place = lifted
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
                    min_hold_width_m=min_hold_width,
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
        c_bin = _rotate(T_bin_tcp, corners.reshape(k, nb * 8, 3)).reshape(k, nb, 8, 3) + T_bin_tcp[:, None, None, :3, 3]
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

    def _clear_transits(
        self,
        q_seed: np.ndarray,
        T_grasp: np.ndarray,
        q_grasp: np.ndarray,
        lift: tuple[np.ndarray, np.ndarray, np.ndarray],
        part_box: np.ndarray,
        r: dict,
        k: int,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:  # fmt: skip
        """``(T_lift, q_lift, q_place)`` whose joint moves (in: from ``q_seed``, fingers open; out: to the place
        pose, fingers open or closed on the part) keep ``transit_clearance_m`` from the walls: the given lift, else
        one ``_LIFT_RAISES_M`` further back along the approach (a joint move between two higher poses swings less
        low); None when none does."""
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
                q_place = ik_nearest(_place_pose(cfg.T_base_place, T_grasp[:3, 0]), q_lift, T_flange_tcp, self._limits)
                if q_place is None:
                    return None
                lift = (T_lift, q_lift, q_place)
            _, q_lift, q_place = lift
            if (
                self.transit_gap_m(q_seed, q_lift, open_boxes) >= cfg.transit_clearance_m
                and self.transit_gap_m(q_lift, q_place, out_boxes) >= cfg.transit_clearance_m
                and self.elbow_clear(q_seed, q_lift)
                and self.elbow_clear(q_lift, q_place)
            ):
                return lift
        return None

    def transit_gap_m(self, q_from: np.ndarray, q_to: np.ndarray, boxes_tcp: np.ndarray) -> float:
        """The smallest gap (m; < 0: overlap; inf without a bin) between the bin walls and ``boxes_tcp``
        (``(b, 2, 3)`` in the TCP frame, e.g. the gripper's) carried along the straight joint-space line from
        ``q_from`` to ``q_to`` (what a joint move does), sampled every ``transit_step_rad`` of the largest joint
        change."""
        cfg = self.config
        if cfg.bin is None:
            return math.inf
        q = _joint_line(q_from, q_to, cfg.transit_step_rad)
        n = len(q)
        T = forward_kinematics(q, cfg.gripper.T_flange_tcp)
        boxes = np.broadcast_to(np.asarray(boxes_tcp, dtype=float), (n, *np.shape(boxes_tcp)))
        gripper = float(self.wall_gap_m(T, boxes, cfg.transit_clearance_m or 0.0).min())
        return min(gripper, float(self.wrist_gap_m(q, cfg.transit_clearance_m or 0.0).min()))

    def elbow_clear(self, q_from: np.ndarray, q_to: np.ndarray) -> bool:
        """Whether the upper arm and forearm stay above ``min_elbow_height_m`` along the joint move."""
        if self.config.min_elbow_height_m is None:
            return True
        q = _joint_line(q_from, q_to, self.config.transit_step_rad)
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

    def _lift_distance(
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
        points = _rotate(T, corners) + T[:, None, :3, 3]
        low = np.minimum(
            cfg.bin.height_above_floor_m(points).min(axis=1), float(cfg.bin.height_above_floor_m(surface_base).min())
        )
        # moving back by d along the approach raises everything by d * cos(angle)
        need = (cfg.bin.inner_size_m[2] + cfg.rim_clearance_m - low) / np.maximum(cos_angle, 1e-6)
        return np.maximum(lift, need)

    def _walls_at_every_backoff(
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

    def _floor_backoff(self, T: np.ndarray, boxes: np.ndarray, cos_angle: np.ndarray) -> np.ndarray:
        """``(k,)`` how far each grasp must move back along its approach so that every gripper box is at least
        ``floor_clearance_m`` above the bin floor (-inf without a bin)."""
        cfg = self.config
        if cfg.bin is None or not len(T):
            return np.full(len(T), -np.inf)
        corners = box_corners(boxes)  # (k, b * 8, 3), TCP frame
        points = _rotate(T, corners) + T[:, None, :3, 3]
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
        return transform_points(cfg.bin.T_base_bin, self._pile_points_bin(depth_m, intrinsics, T_base_camera))

    def _pile_points_bin(
        self, depth_m: np.ndarray, intrinsics: CameraIntrinsics | np.ndarray, T_base_camera: np.ndarray
    ) -> np.ndarray:
        cfg = self.config
        assert cfg.bin is not None
        T_bin_camera = invert(cfg.bin.T_base_bin) @ T_base_camera
        points_bin = depth_points(depth_m, intrinsics, T_bin_camera, cfg.depth_stride_px)
        return points_bin[cfg.bin.in_pile_bin_frame(points_bin, cfg.bin_surface_tolerance_m)]

    def pile_area_m2(
        self, depth_m: np.ndarray, intrinsics: CameraIntrinsics | np.ndarray, T_base_camera: np.ndarray
    ) -> float:
        """How much of the bin the depth frame shows covered by something above its floor (m2: the footprints of
        the depth pixels more than ``bin_surface_tolerance_m`` off the floor and walls, at their distance from the
        camera). What tells an empty bin from one holding parts the detector does not find; 0 without a bin."""
        if self.config.bin is None:
            return 0.0
        points_bin = self._pile_points_bin(depth_m, intrinsics, T_base_camera)
        K = intrinsics.K if isinstance(intrinsics, CameraIntrinsics) else np.asarray(intrinsics, dtype=float)
        camera_bin = (invert(self.config.bin.T_base_bin) @ T_base_camera)[:3, 3]
        distance2 = np.sum((points_bin - camera_bin) ** 2, axis=1)
        return float(distance2.sum() * self.config.depth_stride_px**2 / (K[0, 0] * K[1, 1]))

    def surface_base(self, part: PartEstimate) -> np.ndarray | None:
        """``(n, 3)`` a sample of the part's surface in the base frame (None: no model for its id)."""
        data = self._models.get(part.obj_id)
        return None if data is None else transform_points(part.T_base_obj, data.surface)

    def _prepare(self, model: ObjectModel, cache_dir: str | Path | None) -> _ModelData:
        grasps = grasp_candidates(model, self.config.grasp_params, cache_dir)
        grasps = grasps.subset(grasps.width_m >= self.config.min_grasp_width_m)
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
    pending: dict | None = None  # what the candidate checks need (a part that passed the part-level checks)


# ---------------------------------------------------------------------------------------------- helpers


def _joint_line(q_from: np.ndarray, q_to: np.ndarray, step_rad: float) -> np.ndarray:
    """``(n, 6)`` the straight joint-space line from ``q_from`` to ``q_to`` (what a joint move does), sampled every
    ``step_rad`` of the largest joint change, both ends included."""
    q_from, q_to = np.asarray(q_from, dtype=float), np.asarray(q_to, dtype=float)
    n = max(2, math.ceil(float(np.abs(q_to - q_from).max()) / step_rad) + 1)
    return q_from[None] + np.linspace(0.0, 1.0, n)[:, None] * (q_to - q_from)[None]


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
    corners = box_corners(np.stack([lo, hi], axis=1)[:, None])  # (k, 8, 3)
    corners_base = _rotate(T, corners) + T[:, None, :3, 3]
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


def _rotate(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``(k, p, 3)`` points rotated by each ``T[k]``'s rotation (a batched matrix product: faster than einsum)."""
    return np.matmul(points, np.swapaxes(T[:, :3, :3], 1, 2))


def _part_box_tcp(T_base_tcp: np.ndarray, T_base_obj: np.ndarray, bounds_m: np.ndarray) -> np.ndarray:
    """``(k, 2, 3)`` the axis-aligned box, in each grasp's TCP frame, around the part's bounds (``(2, 3)``, object
    frame): what the gripper carries out of the bin."""
    lo, hi = np.asarray(bounds_m, dtype=float)
    corners_obj = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    corners_base = transform_points(T_base_obj, corners_obj)
    T_inv = np.linalg.inv(T_base_tcp)
    local = np.einsum("kij,pj->kpi", T_inv[:, :3, :3], corners_base) + T_inv[:, None, :3, 3]
    return np.stack([local.min(axis=1), local.max(axis=1)], axis=1)


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


def _refined(pose: ObjectPose) -> bool | None:
    """Did depth refinement confirm this estimate (``perception.refine``'s ``details["icp"]["status"]``)?"""
    status = (pose.details or {}).get("icp", {}).get("status")
    return None if status is None else status == "refined"
