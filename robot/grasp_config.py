"""The grasp planner's settings: ``PlannerConfig`` and the score's ``ScoreWeights``. Defaults match the simulated
cell (its bin, place tray and gripper)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace

import numpy as np

from robot.grasp_geometry import GripperGeometry
from robot.grasp_scene import BinGeometry
from robot.grasp_set import GraspSetParams
from robot.ur_config import WorkspaceBox
from sygrid.errors import ConfigError
from sygrid.transforms import is_rigid, make_T


def _default_place_pose() -> np.ndarray:
    """Above the simulated cell's place tray (centre of its floor at (-0.2, -0.42, 0.005)), tool pointing down, 0.22 m
    up: the pads' tips 0.2 m above the tray floor and 0.06 m above the bin's rim (0.14 m), so that the joint moves
    between the tray and the bin pass over the bin's wall."""
    return make_T(np.diag([1.0, -1.0, -1.0]), (-0.2, -0.42, 0.22))


@dataclass(frozen=True)
class ScoreWeights:
    """Relative weights (>= 0, positive sum) of the score terms, each in [0, 1]; the score is their weighted mean.

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

    def weighted_mean(self, terms: Mapping[str, float | np.ndarray]) -> float | np.ndarray:
        """The score: the mean of ``terms`` (named as the fields; floats or arrays of one shape), weighted by these
        weights."""
        weights = {name: getattr(self, name) for name in terms}
        return sum(weights[k] * terms[k] for k in terms) / sum(weights.values())


@dataclass(frozen=True, eq=False)
class PlannerConfig:
    """Settings of the grasp planner; lengths in metres, angles as named. Defaults match the simulated cell.

    Scene and candidates: grasp_params: candidate generation, including the gripper's geometry
    (``grasp_params.gripper``). bin: the bin (None: nothing is checked against walls or floor, every part counts as
    in the bin).

    Waypoints: approach_cone_deg (in (0, 90]): largest angle between the approach and straight down (the bin
    floor's inward normal; base -z without a bin). pre_grasp_distance_m: the pre-grasp is this far back along the
    approach. lift_height_m: the lift is at least this far back out along the approach, and further until the
    gripper and the held part clear the bin's rim by ``rim_clearance_m``. T_base_place: the centre of where parts are
    let go (its position and approach axis; the tool turns about that axis to keep the grasp's pad direction) and
    where the arm waits while the camera looks. place_grid ``(nx, ny)`` (>= 1) / place_pitch_m ``(px, py)`` (>= 0):
    successive parts are let go at the points of this grid, centred on ``T_base_place`` along its x and y
    (``place_pose_at``), so that they land beside, not on, the ones before; the held part's box, not the pads, is
    centred on its point (``grasp_waypoints.place_pose``).

    Clearances: clearance_m: gripper to neighbouring parts and depth points. bin_clearance_m: gripper and wrist links
    to the bin walls. floor_clearance_m: gripper above the bin floor. min_engagement_m: the least length of pad that
    must still hold the part after the grasp moved back to clear the floor or neighbours. transit_clearance_m:
    gripper (and held part) and wrist links to the bin walls along the joint moves to the lift and on to the place
    pose, sampled every ``transit_step_rad`` (> 0) of the largest joint change (None: not checked).
    min_elbow_height_m: the upper arm and forearm stay this high above the base's xy plane along those joint moves
    (None: not checked).

    Robot: workspace: every waypoint's TCP lies inside this box (``URConfig.workspace``; None: not checked).
    joint_limit_margin_rad: kept from every joint limit. max_joint_step_rad (> 0): the largest joint change allowed
    between the grasp and its pre-grasp or lift (straight-line moves). q_reference_rad: 6 angles IK solutions stay
    near (None: the solution above the bin centre nearest ``ur5e.HOME_Q``).

    Parts: min_pose_score: parts whose pose score is lower are not picked. require_refined: parts whose depth
    refinement refused or skipped the estimate are not picked; parts without refinement information are.
    own_points_tolerance_m: depth points this close to a part's estimated surface are that part.
    bin_surface_tolerance_m: depth points this close to the bin's floor or walls are the bin. depth_stride_px
    (>= 1): every n-th depth pixel in each direction becomes a point. max_covered_fraction (in [0, 1]) /
    cover_tolerance_m: a part is covered when more than this share of its upward surface has something more than
    ``cover_tolerance_m`` above it. duplicate_distance_ratio: another estimate of the same object id whose origin is
    within this fraction of the diameter is the same part detected twice, not a neighbour.

    Score and output: clearance_saturation_m / engagement_saturation_m (> 0): where those score terms reach 1.
    height_spread_m (> 0): the height term divides by at least this. weights: the score terms' weights.
    max_grasps_per_part (>= 1): planned grasps per part (alternatives for retries). max_planned_parts: plan this many
    parts, best first (None: all); the other parts' candidates are checked only while they could still rank among
    them. min_grasp_width_m: candidates narrower than this are not used (0: all; a thin sheet's pinch then counts, and
    the picker must take fingers stopped apart for a hold, ``PickerConfig.min_held_width_m``).
    """

    grasp_params: GraspSetParams = field(default_factory=GraspSetParams)
    bin: BinGeometry | None = field(default_factory=BinGeometry)
    approach_cone_deg: float = 45.0
    pre_grasp_distance_m: float = 0.10
    lift_height_m: float = 0.15
    rim_clearance_m: float = 0.01
    T_base_place: np.ndarray = field(default_factory=_default_place_pose)
    # the simulated tray's 0.24 x 0.16 m floor: four along x, three along y, a slot for each part of a 10-part bin
    place_grid: tuple[int, int] = (4, 3)
    place_pitch_m: tuple[float, float] = (0.05, 0.04)
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
        if len(self.place_grid) != 2 or any(int(n) != n or n < 1 for n in self.place_grid):
            raise ConfigError(f"PlannerConfig.place_grid must be two whole numbers >= 1, got {self.place_grid}")
        if len(self.place_pitch_m) != 2 or not all(p >= 0 for p in self.place_pitch_m):
            raise ConfigError(f"PlannerConfig.place_pitch_m must be two distances >= 0 (m), got {self.place_pitch_m}")
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

    def place_pose_at(self, slot: int) -> np.ndarray:
        """``T_base_place`` moved to the ``slot``-th point of the place grid (row by row along its x, then on from
        the first: slot ``nx * ny`` is slot 0 again); the orientation is unchanged."""
        nx, ny = self.place_grid
        ix, iy = slot % nx, (slot // nx) % ny
        offset = ((ix - (nx - 1) / 2) * self.place_pitch_m[0], (iy - (ny - 1) / 2) * self.place_pitch_m[1], 0.0)
        return self.T_base_place @ make_T(t=offset)

    @property
    def gripper(self) -> GripperGeometry:
        return self.grasp_params.gripper

    def for_depth_noise(self, sigma_m: float) -> PlannerConfig:
        """This config with its tolerances against depth points (own points, bin surface, covered) widened by three
        times ``sigma_m``, the camera's depth noise (1 sigma, metres) where it sees the bin: a stereo camera's points
        scatter about the surface, and a part's own noisy points read as something lying on it otherwise."""
        if not sigma_m >= 0:
            raise ConfigError(f"PlannerConfig.for_depth_noise: sigma_m must be >= 0, got {sigma_m}")
        allowance = 3.0 * float(sigma_m)
        return replace(
            self,
            own_points_tolerance_m=self.own_points_tolerance_m + allowance,
            bin_surface_tolerance_m=self.bin_surface_tolerance_m + allowance,
            cover_tolerance_m=self.cover_tolerance_m + allowance,
        )
