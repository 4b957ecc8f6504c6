"""What the pick cycle (``robot.picker.Picker``) needs of each part it is given: every method and attribute it calls
or reads, and nothing else, so the simulated cell, the real one and the unit tests' fakes can stand in for each other.

Poses are 4x4 homogeneous transforms ``T_a_b`` in metres, joint angles ``q`` (6,) in radians, widths in metres.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any, Protocol, runtime_checkable

import numpy as np

from perception.camera import Frame


class RobotLike(Protocol):
    """``robot.ur.URRobot``: raises ``robot.ur_errors`` errors (``MotionRefusedError``: checked and refused, nothing
    sent; a recoverable ``MotionFailedError``: a protective stop, a dropped link; ``RecoveryError``)."""

    def q(self) -> np.ndarray: ...
    def T_base_tcp(self) -> np.ndarray: ...
    def move_l(
        self,
        T_base_tcp: np.ndarray,
        speed_m_s: float | None = None,
        accel_m_s2: float | None = None,
        max_force_n: float | None = None,
        stop_on_contact: bool = False,
    ) -> Any: ...  # a result with ``contact_force_n`` (None, or the TCP force a guarded move stopped on)
    def move_j(self, q: np.ndarray, speed_rad_s: float | None = None, accel_rad_s2: float | None = None) -> Any: ...
    def recover(self, timeout_s: float | None = None) -> None: ...
    def stop(self, decel: float | None = None) -> None: ...  # from another thread, while a motion runs


@runtime_checkable
class ForceLimitedRobotLike(Protocol):
    """A ``RobotLike`` with force-limited motion (``robot.ur.URRobot``, ``robot.ur_force``): a straight move that
    stops on contact, and a linear move that presses with a bounded force along one direction (base frame)."""

    def move_until_contact(
        self, direction: np.ndarray, speed_m_s: float, max_travel_m: float, accel_m_s2: float | None = None
    ) -> Any: ...
    def move_l_pressing(
        self,
        T_base_tcp: np.ndarray,
        direction: np.ndarray,
        force_n: float,
        speed_m_s: float | None = None,
        accel_m_s2: float | None = None,
        max_press_speed_m_s: float | None = None,
    ) -> Any: ...


class GripperLike(Protocol):
    """``robot.gripper.Gripper``: ``can_set_width`` says whether ``open(width_m=...)`` works; ``stroke_m`` is the
    fully open width (None: not known); ``width_m()`` and ``object_detected()`` return None where the gripper cannot
    tell. Raises ``robot.gripper.GripperError``."""

    can_set_width: bool

    @property
    def stroke_m(self) -> float | None: ...
    def open(self, width_m: float | None = None, speed_m_s: float | None = None) -> None: ...
    def close(self, force_n: float | None = None, speed_m_s: float | None = None) -> bool | None: ...
    def width_m(self) -> float | None: ...
    def object_detected(self) -> bool | None: ...


class CameraLike(Protocol):
    """A camera whose frames carry RGB, depth (m), intrinsics and a timestamp (s)."""

    def capture(self) -> Frame: ...


class PoseLike(Protocol):
    """``perception.results.ObjectPose``: one part's estimate in the camera frame."""

    @property
    def obj_id(self) -> int: ...
    @property
    def T_camera_object(self) -> np.ndarray: ...


class PerceptionResultLike(Protocol):
    """``perception.pipeline.PerceptionResult``: the poses, the detections they came from, stage times (ms); where
    it has a ``depth_tare`` (``perception.depth_tare.Tare``) that was applied, the picker plans on the frame's depth
    corrected by it, as the poses were fitted; where it has ``refused`` (the poses the verification refused), the
    picker names them when nothing is left to pick."""

    @property
    def poses(self) -> list[Any]: ...
    @property
    def detections(self) -> Sequence[Any]: ...
    @property
    def timings_ms(self) -> dict[str, float]: ...


class PerceptionLike(Protocol):
    """``perception.pipeline.PerceptionPipeline`` (or the simulated cell's oracle).

    ``refine_more(poses, frame)``: the poses with more of them depth-refined, or None when nothing is left to refine;
    the picker calls it while nothing is safe to pick among the refined ones. ``rescue(poses, frame)``: the poses with
    the parts found on the depth they do not explain, or None when there are none; the picker calls it (once a
    cycle) when a look would otherwise leave parts in the bin. ``run`` may be called from the picker's look-ahead
    thread (``PickerConfig.look_while_placing``), never while another call is running."""

    def run(self, frame: Frame) -> PerceptionResultLike: ...
    def refine_more(self, poses: list[Any], frame: Frame) -> list[Any] | None: ...
    def rescue(self, poses: list[Any], frame: Frame) -> list[Any] | None: ...


class GraspLike(Protocol):
    """``robot.grasp_plan.PlannedGrasp``: the poses of the approach (pre-grasp, grasp, lift: base frame), the joint
    angles of the lift and place poses, and the widths: opening (the approach was checked with the fingers this far
    apart), the planned grasp width and the narrowest width the part can be held at."""

    @property
    def part_index(self) -> int: ...
    @property
    def obj_id(self) -> int: ...
    @property
    def T_base_obj(self) -> np.ndarray: ...
    @property
    def T_base_pregrasp(self) -> np.ndarray: ...
    @property
    def T_base_grasp(self) -> np.ndarray: ...
    @property
    def T_base_lift(self) -> np.ndarray: ...
    @property
    def q_lift(self) -> np.ndarray: ...
    @property
    def q_place(self) -> np.ndarray: ...
    @property
    def opening_width_m(self) -> float: ...
    @property
    def grasp_width_m(self) -> float: ...
    @property
    def min_hold_width_m(self) -> float: ...


class PlanLike(Protocol):
    """``robot.grasp_plan.GraspPlan``: the grasps best first (empty: nothing is safe to pick), how many of the parts
    planned from lie in the bin (0: the bin is empty whatever else the camera saw), and a one-line summary."""

    @property
    def grasps(self) -> Sequence[GraspLike]: ...
    @property
    def nothing_safe(self) -> bool: ...
    @property
    def n_in_bin(self) -> int: ...
    def summary(self) -> str: ...


class PlannerLike(Protocol):
    """``robot.grasp_planner.GraspPlanner``: plans from poses in the camera frame, each pick let go at the place
    grid's ``place_slot``; ``pile_area_m2`` is how much of the bin (m2) the depth frame shows covered by something
    above its floor."""

    def plan(
        self,
        poses: Sequence[Any],
        T_base_camera: np.ndarray,
        depth_m: np.ndarray | None = None,
        intrinsics: Any = None,
        q_seed: np.ndarray | None = None,
        place_slot: int = 0,
        touches: Sequence[tuple[np.ndarray, float | None]] = (),
    ) -> PlanLike: ...

    def pile_area_m2(self, depth_m: np.ndarray, intrinsics: Any, T_base_camera: np.ndarray) -> float: ...


class NudgeLike(Protocol):
    """``robot.nudge.PlannedNudge``: the part, why it needs a nudge, the paddle's tilt (deg) and the drag (m), the
    joint angles above the press, the straight-line poses press -> end -> retreat (base frame) and the drag speed."""

    @property
    def part_index(self) -> int: ...
    @property
    def obj_id(self) -> int: ...
    @property
    def cause(self) -> str: ...
    @property
    def T_base_obj(self) -> np.ndarray: ...
    @property
    def tilt_deg(self) -> float: ...
    @property
    def distance_m(self) -> float: ...
    @property
    def q_above(self) -> np.ndarray: ...
    @property
    def T_base_press(self) -> np.ndarray: ...
    @property
    def T_base_end(self) -> np.ndarray: ...
    @property
    def T_base_retreat(self) -> np.ndarray: ...
    @property
    def speed_m_s(self) -> float: ...


class NudgerLike(Protocol):
    """``robot.nudge.NudgePlanner``: a nudge for a part ``plan`` left for a wall or a neighbour, None when there is
    none (``skip(part_index)``: parts not to nudge). ``q_from``: where the arm is; ``q_after``: where it goes after."""

    def plan(
        self, poses: Sequence[Any], T_base_camera: np.ndarray, plan: Any, q_from: np.ndarray, q_after: np.ndarray,
        skip: Callable[[int], bool] | None = None,
    ) -> NudgeLike | None: ...  # fmt: skip
