"""robot.picker's state machine with simple fakes (no emulator): the stops, the retries and the records."""

from __future__ import annotations

import json
import threading
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from perception.camera import Frame
from perception.results import Detection, ObjectPose
from robot.cell_setup import load_cell_setup
from robot.pick_arm import approach_legs
from robot.pick_config import PickerConfig
from robot.pick_memory import TOUCH_FORGET_M, PartMemory
from robot.pick_report import Attempt, CycleEnd, Outcome, Stage, StopReason, nothing_posed_reason
from robot.pick_states import TRANSITIONS, CycleState
from robot.picker import Picker
from robot.ur_errors import (
    ConnectionLostError,
    MotionRefusedError,
    NoContactError,
    ProtectiveStopError,
    RecoveryError,
)
from sygrid.camera import CameraIntrinsics
from sygrid.errors import ConfigError
from sygrid.transforms import make_T

K = CameraIntrinsics.from_fov(64, 48, 45.0)


class FakeCamera:
    def __init__(self) -> None:
        self.t = 0.0

    def capture(self) -> Frame:
        self.t += 5.0
        return Frame(np.zeros((48, 64, 3), np.uint8), np.ones((48, 64), np.float32), K, self.t)


@dataclass
class FakeBin:
    """Parts (obj id, x); perception sees those left, the planner plans one grasp per part."""

    parts: list[float] = field(default_factory=lambda: [0.0, 0.1, 0.2])
    in_fingers: float | None = None  # the part the gripper holds: out of the camera's view of the bin

    def run(self, frame: Frame):
        det = Detection(0, 1, 1.0, np.zeros(4))
        poses = [ObjectPose(det, make_T(t=(x, 0.0, 0.5)), 1.0, "fake") for x in self.parts if x != self.in_fingers]
        return type("R", (), {"poses": poses, "detections": [det] * len(poses), "timings_ms": {"total": 1.0}})()

    def refine_more(self, poses, frame):
        return None  # every pose is as good as it gets

    def rescue(self, poses, frame):
        return None  # no part the detector missed


@dataclass
class FakePlan:
    """A plan as the picker reads it: the grasps (none: nothing safe), the parts in the bin, a summary."""

    grasps: list
    text: str = "plan"
    n_in_bin: int = 1
    parts: list = field(default_factory=list)

    @property
    def nothing_safe(self) -> bool:
        return not self.grasps

    def summary(self) -> str:
        return self.text


PLACE_X = -0.2


@dataclass
class FakeGrasp:
    part_index: int
    obj_id: int
    T_base_obj: np.ndarray
    x: float
    opening_width_m: float = 0.03
    grasp_width_m: float = 0.02
    min_hold_width_m: float = 0.01

    def __post_init__(self) -> None:
        self.q_lift = self.q_place = np.full(6, self.x)
        self.T_base_pregrasp = self.T_base_grasp = self.T_base_lift = make_T(t=(self.x, 0, 0.1))
        self.T_base_place = make_T(np.diag([1.0, -1.0, -1.0]), (PLACE_X, -0.42, 0.22))  # tool pointing down


class FakePlanner:
    def __init__(self, nothing_safe: bool = False) -> None:
        self.nothing_safe = nothing_safe

    def plan(self, poses, T_base_camera, depth_m=None, intrinsics=None, q_seed=None, place_slot=0, touches=()):
        grasps = (
            []
            if self.nothing_safe
            else [FakeGrasp(i, 1, p.T_camera_object, p.T_camera_object[0, 3]) for i, p in enumerate(poses)]
        )
        summary = "nothing safe: part 0: unreachable" if self.nothing_safe else f"{len(grasps)} grasps"
        return FakePlan(grasps, summary, n_in_bin=len(poses))

    def pile_area_m2(self, depth_m, intrinsics, T_base_camera):
        return 0.0  # the fake camera's depth shows an empty bin


def moved(T, contact_force_n=None) -> SimpleNamespace:
    """A fake robot's motion result: where the TCP ended, and the force a guarded move stopped on (or None)."""
    return SimpleNamespace(T_base_tcp=np.array(T), contact_force_n=contact_force_n)


class FakeRobot:
    def __init__(
        self,
        bin_: FakeBin,
        refuse_x: float | None = None,
        stop_once_x: float | None = None,
        contact_once_x: float | None = None,
    ) -> None:
        self.bin, self.refuse_x, self.stop_once_x, self.contact_once_x = bin_, refuse_x, stop_once_x, contact_once_x
        self.q_now = np.zeros(6)
        self.recovered = 0
        self.stops = 0
        self.holding: float | None = None

    def q(self):
        return self.q_now

    def T_base_tcp(self):
        return make_T(t=(0, 0, 0.05))

    def move_l(self, T, speed_m_s=None, accel_m_s2=None, max_force_n=None, stop_on_contact=False):
        if self.refuse_x is not None and abs(T[0, 3] - self.refuse_x) < 1e-9:
            raise MotionRefusedError("outside the box")
        if self.stop_once_x is not None and abs(T[0, 3] - self.stop_once_x) < 1e-9:
            self.stop_once_x = None
            raise ProtectiveStopError("contact")
        if max_force_n is not None and self.contact_once_x is not None and abs(T[0, 3] - self.contact_once_x) < 1e-9:
            self.contact_once_x = None  # a finger meets the part 12 mm above the grasp and presses it with 41 N
            return moved(T + make_T(t=(0.0, 0.0, 0.012)) - np.eye(4), contact_force_n=41.0)
        return moved(T)

    def move_j(self, q, speed_rad_s=None, accel_rad_s2=None):
        self.q_now = np.asarray(q)

    def recover(self, timeout_s=None):
        self.recovered += 1

    def stop(self, decel=None):
        self.stops += 1


class FakeGripper:
    """Fingers that open to the commanded width; with ``lag_reads`` the width reaches it only after that many reads
    (a gripper that answers "stopped" before its fingers have moved); ``stuck`` keeps them at the part's width."""

    can_set_width = True
    stroke_m = None

    def __init__(self, robot: FakeRobot, bin_: FakeBin, empty_once: bool = False) -> None:
        self.robot, self.bin, self.empty_once = robot, bin_, empty_once
        self.held = False
        self.width = 0.085
        self.target = 0.085
        self.lag_reads = 0
        self.stuck = False
        self.slip_at: float | None = None  # the part at this x always slips out while lifting
        self.settling_reads = 0  # object detection reads "moving" (False) this many times after each close
        self.reads_left = 0

    def open(self, width_m=None, speed_m_s=None):
        self.target = 0.085 if width_m is None else width_m
        if self.stuck:
            return
        if self.held:
            self.bin.parts.remove(self.robot.q_now[0]) if self.robot.q_now[0] in self.bin.parts else None
        self.held, self.bin.in_fingers = False, None
        self.opening = True
        self.reads_left = self.lag_reads

    def close(self, force_n=None, speed_m_s=None):
        self.opening = False
        if self.empty_once:
            self.empty_once = False
            self.width = 0.0
            return False
        self.held, self.bin.in_fingers = True, self.robot.q_now[0]
        self.width = 0.02
        self.settle_left = self.settling_reads
        return True

    def width_m(self):
        if getattr(self, "opening", True) and not self.held and not self.stuck:
            if self.reads_left > 0:
                self.reads_left -= 1
            else:
                self.width = self.target
        return self.width

    def object_detected(self):
        if self.held and self.slip_at is not None and self.robot.q_now[0] == self.slip_at:
            self.held, self.width, self.bin.in_fingers = False, 0.0, None
        if self.held and getattr(self, "settle_left", 0) > 0:
            self.settle_left -= 1
            return False
        return self.held


def make_picker(bin_: FakeBin, planner=None, config=None, **robot_kw) -> tuple[Picker, FakeRobot]:
    robot = FakeRobot(bin_, **robot_kw)
    gripper = FakeGripper(robot, bin_)
    camera, planner = FakeCamera(), planner or FakePlanner()
    return Picker(robot, gripper, camera, bin_, planner, np.eye(4), np.full(6, -1.0), config), robot


def test_clears_the_bin_and_stops_when_empty():
    bin_ = FakeBin()
    picker, _ = make_picker(bin_)
    report = picker.run()
    assert report.stop_reason == "bin_empty" and bin_.parts == []
    assert report.n_picked == 3 and report.success_rate == 1.0
    assert report.sim_cycle_times_s() == [5.0, 5.0, 5.0]  # camera time from one capture to the next


class RefusingBin(FakeBin):
    """Sees its parts; for the first ``refusals`` frames the verification refuses the poses of those at the x that
    ``refuses`` selects (every one by default)."""

    def __init__(self, parts, refusals, refuses=lambda x: True):
        super().__init__(parts)
        self.refusals, self.frames, self.refuses = refusals, 0, refuses

    def run(self, frame):
        result = super().run(frame)
        self.frames += 1
        if self.frames <= self.refusals:
            out = [self.refuses(p.T_camera_object[0, 3]) for p in result.poses]
            result.refused = [ObjectPose(p.detection, p.T_camera_object, 0.3, "fake", verified=False)
                              for p, o in zip(result.poses, out, strict=True) if o]  # fmt: skip
            result.poses = [p for p, o in zip(result.poses, out, strict=True) if not o]
        return result


class ReleaseWatchingBin(FakeBin):
    """Perception that, run off the main thread, waits (up to a second) for the gripper to let go of the part before
    it answers, and records per run its thread and whether the release came while it ran."""

    def __init__(self, parts):
        super().__init__(parts)
        self.released = threading.Event()
        self.runs: list[tuple[str, bool]] = []

    def run(self, frame):
        main = threading.current_thread() is threading.main_thread()
        self.runs.append(("main" if main else "worker", main or self.released.wait(1.0)))
        return super().run(frame)


def _watch_releases(picker: Picker, bin_: ReleaseWatchingBin) -> None:
    release = picker.gripper.open

    def open_(width_m=None, speed_m_s=None):
        if picker.gripper.held:
            bin_.released.set()
        return release(width_m, speed_m_s)

    picker.gripper.open = open_


def test_the_next_look_is_taken_at_the_place_pose_and_perceived_while_the_arm_lets_go(capsys):
    bin_ = ReleaseWatchingBin([0.0, 0.1, 0.2])
    picker, _ = make_picker(bin_, config=PickerConfig(release_drop_m=0.1))
    _watch_releases(picker, bin_)
    captures = []
    capture = picker.camera.capture
    picker.camera.capture = lambda: captures.append(picker.gripper.held) or capture()
    report = picker.run()
    assert report.n_picked == 3 and report.stop_reason == "bin_empty" and bin_.parts == []
    assert [c.looked_ahead for c in report.cycles] == [False, True, True, True]
    assert captures == [False, True, True, True]  # one frame per cycle; after the first, taken holding the part
    # the three looks ahead ran beside the main thread, which let go of the part meanwhile
    assert bin_.runs == [("main", True)] + [("worker", True)] * 3
    assert all(t.name != "look-ahead_0" for t in threading.enumerate())  # no thread outlives the run
    from launch.pick import print_summary

    print_summary(report, 1.0)
    assert "(perception 1 ms a look; 3 look(s) perceived while the arm let go)" in capsys.readouterr().out

    bin_ = ReleaseWatchingBin([0.0, 0.1])
    picker, _ = make_picker(bin_, config=PickerConfig(look_while_placing=False))
    report = picker.run()
    assert report.n_picked == 2 and not any(c.looked_ahead for c in report.cycles)
    assert bin_.runs == [("main", True)] * 3
    with pytest.raises(ConfigError, match="look_while_placing"):
        PickerConfig(look_while_placing=1)


def test_a_look_ahead_is_dropped_when_the_part_is_not_let_go_and_its_error_raised_where_it_is_used():
    bin_ = ReleaseWatchingBin([0.0, 0.1])
    picker, _ = make_picker(bin_, config=PickerConfig(open_timeout_s=0.05))
    picker.gripper.stuck = True  # the fingers close, and never open again
    report = picker.run()
    assert report.stop_reason == "gripper_blocked" and [a.outcome for a in report.attempts] == ["not_released"]
    assert [r[0] for r in bin_.runs] == ["main", "worker"]  # perceived, not used: the cycle ended the run

    class FailingBin(FakeBin):
        def run(self, frame):
            if threading.current_thread() is not threading.main_thread():
                raise RuntimeError("onnxruntime: out of memory")
            return super().run(frame)

    picker, _ = make_picker(FailingBin([0.0, 0.1]))
    with pytest.raises(RuntimeError, match="out of memory"):
        picker.run()
    assert picker.last_report.n_picked == 1 and picker.last_report.stop_reason == "error"
    assert picker.last_report.cycles[-1].interrupted_in == "perceive"


def test_the_planner_gets_the_depth_the_poses_were_fitted_in():
    """The perception measured a stereo offset on the floor and fitted the poses in the corrected depth: the planner
    and the checks after it read the same corrected depth, not the camera's raw frame."""
    from perception.depth_tare import Tare

    class TaringBin(FakeBin):
        def run(self, frame):
            result = super().run(frame)
            result.depth_tare = Tare(offset_inv_m=0.01, floor_px=5000, applied=True)  # 1 / z_obs = 1 / z + 0.01
            return result

    class RecordingPlanner(FakePlanner):
        def __init__(self) -> None:
            super().__init__()
            self.depths: list = []

        def plan(self, poses, T_base_camera, depth_m=None, intrinsics=None, q_seed=None, place_slot=0, touches=()):
            self.depths.append(depth_m)
            return super().plan(poses, T_base_camera, depth_m, intrinsics, q_seed)

    planner = RecordingPlanner()
    picker, _ = make_picker(TaringBin(parts=[0.0]), planner)
    picker.run()
    assert planner.depths and np.allclose(planner.depths[0], 1.0 / (1.0 - 0.01))  # the raw frame reads 1 m


def test_nothing_safe_is_a_clean_stop_with_the_reasons():
    picker, _ = make_picker(FakeBin(), FakePlanner(nothing_safe=True))
    report = picker.run()
    assert report.stop_reason == "nothing_safe" and "unreachable" in report.stop_detail
    assert report.attempts == []


def test_nothing_safe_among_the_refined_parts_refines_the_skipped_ones_and_plans_again():
    """A pipeline that refined only the nearest parts (``max_refined``) is asked for the next ones before the
    picker gives up; the planner here plans only refined parts."""

    class LazyBin(FakeBin):
        def run(self, frame):
            result = super().run(frame)
            result.poses = [ObjectPose(p.detection, p.T_camera_object, 1.0, "fake", {"icp": {"status": "skipped"}})
                            for p in result.poses]  # fmt: skip
            return result

        def refine_more(self, poses, frame):
            self.calls = getattr(self, "calls", 0) + 1
            if not any(p.details["icp"]["status"] == "skipped" for p in poses):
                return None
            first = next(i for i, p in enumerate(poses) if p.details["icp"]["status"] == "skipped")
            return [ObjectPose(p.detection, p.T_camera_object, 1.0, "fake", {"icp": {"status": "refined"}})
                    if i == first else p for i, p in enumerate(poses)]  # fmt: skip

    class RefinedOnly(FakePlanner):
        def plan(self, poses, T_base_camera, depth_m=None, intrinsics=None, q_seed=None, place_slot=0, touches=()):
            refined = [p if p.details["icp"]["status"] == "refined" else None for p in poses]
            grasps = [FakeGrasp(i, 1, p.T_camera_object, p.T_camera_object[0, 3]) for i, p in enumerate(refined) if p]
            return FakePlan(grasps, n_in_bin=len(poses))

    bin_ = LazyBin([0.0, 0.1])
    picker = make_picker(bin_, RefinedOnly())[0]
    seen = []
    picker.on_cycle = lambda record, frame, result, poses: seen.append([p.details["icp"]["status"] for p in poses])
    report = picker.run()
    assert report.n_picked == 2 and report.stop_reason == "bin_empty"
    assert bin_.calls == 2  # once per cycle: the first refinement gave a plan
    assert seen[0] == ["refined", "skipped"]  # the report's picture shows the poses the plan was made from
    empty = LazyBin([0.0])
    empty.refine_more = lambda poses, frame: None  # nothing was skipped: the plan's answer stands
    assert make_picker(empty, RefinedOnly())[0].run().stop_reason == "nothing_safe"


def test_nothing_safe_with_refused_poses_looks_again_before_it_stops():
    """Nothing safe to pick (the part at x < 0 lies at a wall) and a pose refused: a new frame may confirm it."""

    class WallPlanner(FakePlanner):
        def plan(self, poses, T_base_camera, depth_m=None, intrinsics=None, q_seed=None, place_slot=0, touches=()):
            grasps = [FakeGrasp(i, 1, p.T_camera_object, p.T_camera_object[0, 3])
                      for i, p in enumerate(poses) if p.T_camera_object[0, 3] >= 0]  # fmt: skip
            return FakePlan(grasps, "nothing safe: part 0: collision_bin", n_in_bin=len(poses))

    bin_ = RefusingBin([-0.1, 0.1], refusals=1, refuses=lambda x: x > 0)
    report = make_picker(bin_, WallPlanner())[0].run()
    assert report.cycles[0].end == "picked" and report.n_picked == 1 and bin_.parts == [-0.1]
    assert bin_.frames == 3 and report.stop_reason == "nothing_safe"  # the second cycle refuses nothing
    bin_ = RefusingBin([-0.1, 0.1], refusals=100, refuses=lambda x: x > 0)
    report = make_picker(bin_, WallPlanner())[0].run()
    assert bin_.frames == 3 and report.n_picked == 0 and report.stop_reason == "nothing_safe"
    bin_ = RefusingBin([-0.1, 0.1], refusals=1, refuses=lambda x: x > 0)
    assert make_picker(bin_, WallPlanner(), config=PickerConfig(relooks=0))[0].run().stop_reason == "nothing_safe"
    assert bin_.frames == 1


def test_parts_the_detector_misses_are_rescued_once_a_cycle_when_the_look_would_leave_them():
    """A look that poses nothing, or nothing safe, asks the perception for the parts on the depth no pose explains
    (``rescue``) before it ends the run; once a cycle, and not while something is safe to pick."""

    class MissingBin(FakeBin):
        def __init__(self, parts, missed):
            super().__init__(parts)
            self.missed, self.rescues = missed, 0

        def run(self, frame):
            result = super().run(frame)
            result.poses = [p for p in result.poses if p.T_camera_object[0, 3] not in self.missed]
            return result

        def rescue(self, poses, frame):
            self.rescues += 1
            det = Detection(0, 1, 0.0, np.zeros(4))
            found = [ObjectPose(det, make_T(t=(x, 0.0, 0.5)), 0.9, "fake") for x in self.parts if x in self.missed]
            return [*poses, *found] if found else None

    bin_ = MissingBin([0.0, 0.1, 0.2], missed={0.1, 0.2})
    picker = make_picker(bin_)[0]
    report = picker.run()
    assert report.stop_reason == "bin_empty" and bin_.parts == [] and report.n_picked == 3
    # cycle 1 picks the posed part (no rescue); cycles 2 and 3 each rescue one; cycle 4 rescues nothing: empty
    assert bin_.rescues == 3
    assert [c.n_rescued for c in report.cycles] == [0, 2, 1, 0]

    class Unsafe(FakePlanner):  # nothing safe among the posed parts: the rescued one is planned with them
        def plan(self, poses, T_base_camera, depth_m=None, intrinsics=None, q_seed=None, place_slot=0, touches=()):
            grasps = [FakeGrasp(i, 1, p.T_camera_object, p.T_camera_object[0, 3]) for i, p in enumerate(poses)
                      if p.T_camera_object[0, 3] != 0.0]  # fmt: skip
            return FakePlan(grasps, "part at 0.0: collision_bin", n_in_bin=len(poses))

    bin_ = MissingBin([0.0, 0.2], missed={0.2})
    report = make_picker(bin_, Unsafe())[0].run()
    assert report.n_picked == 1 and bin_.parts == [0.0] and report.stop_reason == "nothing_safe"
    assert bin_.rescues == 2  # the cycle that picked the rescued part, and the last one (nothing found)


def test_parts_seen_only_outside_the_bin_mean_the_bin_is_empty():
    class OutsidePlanner(FakePlanner):
        def plan(self, poses, T_base_camera, depth_m=None, intrinsics=None, q_seed=None, place_slot=0, touches=()):
            parts = [type("P", (), {"status": "outside_bin"})() for _ in poses]
            return FakePlan([], "nothing safe: part 0: outside_bin", n_in_bin=0, parts=parts)

    report = make_picker(FakeBin([0.0]), OutsidePlanner())[0].run()
    assert report.stop_reason == "bin_empty" and "outside it" in report.stop_detail and report.attempts == []

    class OutsideButCovered(OutsidePlanner):
        def pile_area_m2(self, depth_m, intrinsics, T_base_camera):
            return 5e-4

    # estimates outside the bin while the depth shows it covered: parts estimated wrong, not an empty bin
    report = make_picker(FakeBin([0.0]), OutsideButCovered())[0].run()
    assert report.stop_reason == "parts_unseen" and report.stop_detail.startswith("no part estimated in the bin (1")
    assert report.stop_detail.endswith("5.0 cm2 of the bin covered")


def test_refused_motion_moves_on_to_the_next_candidate():
    bin_ = FakeBin([0.0, 0.1])
    picker, _ = make_picker(bin_, refuse_x=0.0)
    record = picker.cycle()
    assert [a.outcome for a in record.attempts] == ["motion_refused", "picked"]
    assert record.end == "picked"


def test_protective_stop_is_recovered_and_the_cycle_looks_again():
    bin_ = FakeBin([0.0])
    picker, robot = make_picker(bin_, stop_once_x=0.0)
    report = picker.run()
    assert robot.recovered == 1
    assert [a.outcome for a in report.attempts] == ["protective_stop", "picked"]
    assert report.stop_reason == "bin_empty"


def test_a_finger_meeting_a_part_on_the_guarded_approach_stops_backs_out_and_the_cycle_looks_again():
    """Only the line down to the grasp is guarded; a contact there is a failed attempt ("contact"), backed out along
    the approach with no protective stop to recover from; the next look picks the part. Unguarded, nothing stops."""
    picker, robot = make_picker(FakeBin([0.0]), contact_once_x=0.0)
    guards: list[float | None] = []
    move_l = robot.move_l

    detecting: list[bool] = []

    def log_guard(T, speed_m_s=None, accel_m_s2=None, max_force_n=None, stop_on_contact=False):
        guards.append(max_force_n)
        detecting.append(stop_on_contact)
        return move_l(T, speed_m_s, accel_m_s2, max_force_n, stop_on_contact)

    robot.move_l = log_guard
    report = picker.run()
    assert [a.outcome for a in report.attempts] == ["contact", "picked"] and robot.recovered == 0
    assert report.attempts[0].stage == "approach" and report.attempts[0].detail == (
        "the fingers met something 12 mm short of the grasp (TCP force 41 N, above the approach's 30 N guard): "
        "stopped and backed out"
    )
    # pre-grasp, the guarded line down, back out to the lift; then the next cycle's pick
    assert guards[:3] == [None, 30.0, None] and guards[3:5] == [None, 30.0]
    # the line down (here all of it the slow last stretch) also runs under the controller's contact detection
    assert detecting[:3] == [False, True, False]
    picker, robot = make_picker(FakeBin([0.0]), config=PickerConfig(approach_max_force_n=None), contact_once_x=0.0)
    assert [a.outcome for a in picker.run().attempts] == ["picked"]
    with pytest.raises(ConfigError, match="approach_max_force_n must be > 0"):
        PickerConfig(approach_max_force_n=0.0)


def test_where_a_finger_met_something_later_plans_keep_clear_of_until_a_part_there_is_picked():
    """A contact on the approach is remembered as a touch (the TCP pose the arm stopped at, the pads' opening) and
    handed to the plans after it; a pick of a part within ``TOUCH_FORGET_M`` of it forgets it (that part may have been
    what the fingers met), a pick further away does not, and ``PartMemory.clear`` forgets every one."""
    picker, _ = make_picker(FakeBin([0.0, 0.2]), contact_once_x=0.0)
    handed: list[list] = []
    plan = picker.planner.plan

    def spy(*args, touches=(), **kwargs):
        handed.append([(np.array(T), opening) for T, opening in touches])
        return plan(*args, touches=touches, **kwargs)

    picker.planner.plan = spy
    report = picker.run()
    assert [a.outcome for a in report.attempts] == ["contact", "picked", "picked"]
    assert [len(t) for t in handed] == [0, 1, 0]  # the part at x 0 picked in the second cycle: the touch forgotten
    ((T_touch, opening),) = handed[1]
    np.testing.assert_allclose(T_touch[:3, 3], [0.0, 0.0, 0.112])  # 12 mm short of the grasp, where the arm stopped
    assert opening == pytest.approx(picker.fingers.grasp_opening(FakeGrasp(0, 1, np.eye(4), 0.0)))

    memory = PartMemory(PickerConfig(), np.eye(4))
    memory.add_touch(make_T(t=(0.0, 0.0, 0.1)), None)
    far = Attempt(0, 1, Outcome.PICKED, Stage.VERIFY, T_base_obj=make_T(t=(TOUCH_FORGET_M, 0.0, 0.0)).tolist())
    memory.remember_pick(far)
    assert len(memory.touches) == 1
    near = Attempt(0, 1, Outcome.PICKED, Stage.VERIFY, T_base_obj=make_T(t=(0.03, 0.03, 0.0)).tolist())
    memory.remember_pick(near)
    assert memory.touches == []
    memory.add_touch(make_T(t=(0.0, 0.0, 0.1)), None)
    memory.clear()
    assert memory.touches == []


def test_the_last_stretch_of_the_approach_runs_at_the_final_speed():
    """At the approach speed to ``final_approach_m`` short of the grasp, then at the final speed (never faster than
    the approach speed); an approach shorter than that stretch runs slow all the way. Bad values are refused."""
    grasp = SimpleNamespace(T_base_pregrasp=make_T(t=(0.1, 0.0, 0.2)), T_base_grasp=make_T(t=(0.1, 0.0, 0.1)))
    (T_slow, fast), (T_end, slow) = approach_legs(grasp, PickerConfig())
    assert np.allclose(T_slow[:3, 3], [0.1, 0.0, 0.13]) and np.allclose(T_slow[:3, :3], np.eye(3))
    assert fast == 0.25 and slow == 0.05 and T_end is grasp.T_base_grasp
    legs = approach_legs(grasp, PickerConfig(approach_speed_m_s=0.02, final_approach_m=0.2))
    assert [speed for _, speed in legs] == [0.02]
    with pytest.raises(ConfigError, match="final_approach_speed_m_s must be > 0"):
        PickerConfig(final_approach_speed_m_s=0.0)


def test_after_a_protective_stop_the_fingers_are_held_until_the_arm_is_up():
    """Fingers that go on moving after a stop push on whatever stopped them (a finger opening into a wall stops the
    arm again as soon as it is unlocked): hold them at their width, recover, go straight up, and only then open."""
    picker, robot = make_picker(FakeBin([0.0]), stop_once_x=0.0)
    events: list[str] = []
    gripper_open, move_l, recover = picker.gripper.open, robot.move_l, robot.recover

    def log_open(width_m=None, speed_m_s=None):
        events.append("open" if width_m is None else f"open to {1e3 * width_m:.0f} mm")
        gripper_open(width_m, speed_m_s)

    def log_move_l(T, speed_m_s=None, accel_m_s2=None, max_force_n=None):
        result = move_l(T, speed_m_s, accel_m_s2, max_force_n)
        events.append(f"move_l to z {T[2, 3]:.2f}")
        return result

    def log_recover(timeout_s=None):
        events.append("recover")
        recover(timeout_s)

    picker.gripper.open, robot.move_l, robot.recover = log_open, log_move_l, log_recover
    attempt = picker.run(max_cycles=1).attempts[0]
    assert attempt.outcome == "protective_stop" and attempt.stage == "approach"
    # opened to the grasp's 30 mm, stopped on the way to the pre-grasp (no move_l logged), then the recovery
    assert events == ["open to 30 mm", "open to 30 mm", "recover", "move_l to z 0.10", "open"]


def test_fingers_that_close_on_air_back_out_at_the_opening_the_approach_was_checked_with():
    picker, _ = make_picker(FakeBin([0.0]))
    picker.gripper.empty_once = True
    widths: list[float | None] = []
    gripper_open = picker.gripper.open

    def log_open(width_m=None, speed_m_s=None):
        widths.append(width_m)
        gripper_open(width_m, speed_m_s)

    picker.gripper.open = log_open
    attempt = picker.run(max_cycles=1).attempts[0]
    assert attempt.outcome == "gripper_empty" and widths == [0.03, 0.03]  # not fully open (None) near the walls


def test_a_stop_the_cell_cannot_release_ends_the_run_with_its_report():
    bin_ = FakeBin([0.0, 0.1])
    picker, robot = make_picker(bin_, stop_once_x=0.1)

    def pinned(timeout_s=None):
        raise RecoveryError("still protective-stopped after 'Protective stop releasing'")

    picker.run(max_cycles=1)  # picks the part at x = 0.0
    robot.recover = pinned
    report = picker.run()
    assert report.stop_reason == "needs_operator" and "still protective-stopped" in report.stop_detail
    assert bin_.parts == [0.1]  # nothing more was tried after the stop


def test_gripper_closing_on_air_fails_verification_and_retries():
    bin_ = FakeBin([0.0])
    picker, _ = make_picker(bin_)
    picker.gripper.empty_once = True
    report = picker.run()
    assert [a.outcome for a in report.attempts] == ["gripper_empty", "picked"]
    assert report.failures_by_cause() == {"gripper_empty": 1}


def test_each_part_let_go_moves_the_next_pick_to_the_next_place_slot():
    """A failed attempt lets nothing go: the slot advances only with a part released over the tray."""

    class SlotPlanner(FakePlanner):
        def __init__(self) -> None:
            super().__init__()
            self.slots: list[int] = []

        def plan(self, poses, T_base_camera, depth_m=None, intrinsics=None, q_seed=None, place_slot=0, touches=()):
            self.slots.append(place_slot)
            return super().plan(poses, T_base_camera, depth_m, intrinsics, q_seed)

    planner = SlotPlanner()
    picker, _ = make_picker(FakeBin([0.0, 0.1]), planner)
    picker.gripper.empty_once = True
    report = picker.run()
    assert [a.outcome for a in report.attempts] == ["gripper_empty", "picked", "picked"]
    assert planner.slots == [0, 0, 1] and picker.n_placed == 2


def test_a_part_is_lowered_into_the_tray_before_it_is_let_go_and_the_arm_goes_back_up():
    picker, robot = make_picker(FakeBin([0.0]), config=PickerConfig(release_drop_m=0.1))
    moves, real = [], robot.move_l

    def record(T, speed_m_s=None, accel_m_s2=None, max_force_n=None, stop_on_contact=False):
        moves.append((np.array(T), max_force_n, picker.gripper.held))
        return real(T, speed_m_s, accel_m_s2, max_force_n, stop_on_contact)

    robot.move_l = record
    assert picker.run().n_picked == 1
    # down along the tool's approach, guarded, holding the part; back up to the place pose with the fingers open
    (T_low, guard, held_low), (T_up, _, held_up) = [m for m in moves if abs(m[0][0, 3] - PLACE_X) < 1e-9]
    np.testing.assert_allclose(T_low[:3, 3], [PLACE_X, -0.42, 0.12], atol=1e-12)
    assert guard == PickerConfig().approach_max_force_n and held_low
    np.testing.assert_allclose(T_up[:3, 3], [PLACE_X, -0.42, 0.22], atol=1e-12)
    assert not held_up
    # a lowering the robot refuses lets go at the place pose
    picker, robot = make_picker(FakeBin([0.0]), config=PickerConfig(release_drop_m=0.1), refuse_x=PLACE_X)
    report = picker.run()
    assert [a.outcome for a in report.attempts] == ["picked"] and report.stop_reason == "bin_empty"


def test_part_still_there_after_its_pick_is_marked_failed():
    bin_ = FakeBin([0.0])
    picker, _ = make_picker(bin_)
    gripper = picker.gripper

    def open_without_removing(width_m=None, speed_m_s=None):  # the fingers open, but nothing leaves the bin
        gripper.held, gripper.opening = False, True

    def close_on_nothing(force_n=None, speed_m_s=None):  # a hold is read, but the part stays where it lies
        closed = close(force_n, speed_m_s)
        bin_.in_fingers = None
        return closed

    close = gripper.close
    gripper.open, gripper.close = open_without_removing, close_on_nothing
    report = picker.run(max_cycles=2)
    assert report.attempts[0].outcome == "part_still_in_bin"


def test_fingers_slow_to_open_are_waited_for_before_the_arm_moves_in():
    """A gripper may answer "stopped" while its fingers still move (the emulator does so when it opens from a
    squeeze): the arm must not go down, nor the next part be grasped, before they are open."""
    bin_ = FakeBin([0.0, 0.1])
    picker, robot = make_picker(bin_)
    picker.gripper.lag_reads = 5
    widths_at_move_j = []
    move_j = robot.move_j

    def watch(q, speed_rad_s=None, accel_rad_s2=None):
        if not picker.gripper.held:  # the transits to the part (holding one, the fingers are on it)
            widths_at_move_j.append(picker.gripper.width)
        move_j(q, speed_rad_s, accel_rad_s2)

    robot.move_j = watch
    report = picker.run()
    assert report.stop_reason == "bin_empty" and report.n_picked == 2 and report.failures_by_cause() == {}
    assert len(widths_at_move_j) >= 2 and min(widths_at_move_j) >= 0.03 - picker.config.open_tolerance_m


def test_object_detection_lost_while_the_fingers_settle_is_not_a_slip():
    """The emulated 2F-85 reads "moving" (no object) much of the time while its pads hold a part: a detection that
    comes back, or fingers that rest at the part's width, mean the part is held."""
    bin_ = FakeBin([0.0, 0.1])
    picker, _ = make_picker(bin_)
    picker.gripper.settling_reads = 3
    assert [a.outcome for a in picker.run(max_cycles=1).attempts] == ["picked"]
    picker.gripper.settling_reads = 10**6  # never comes back, but the fingers rest at the part's width
    report = picker.run()
    assert [a.outcome for a in report.attempts] == ["picked"] and report.stop_reason == "bin_empty"


def test_a_part_held_at_another_of_its_widths_is_placed_not_dropped():
    """The fingers stop at 20 mm on a grasp planned at 30 mm, above the part's narrowest hold (10 mm): the part
    turned in the fingers (in the simulated cell: nuts closed on at 10.8 mm across their faces, not their 18 mm
    flats) and is held. It is placed, with a note; only near the planned width (``hold_any_width=False``) it is
    dropped back as slipped."""

    class WideGrasps(FakePlanner):
        def plan(self, poses, T_base_camera, depth_m=None, intrinsics=None, q_seed=None, place_slot=0, touches=()):
            plan = super().plan(poses, T_base_camera, depth_m, intrinsics, q_seed)
            for g in plan.grasps:
                g.grasp_width_m = 0.03
            return plan

    picker, _ = make_picker(FakeBin([0.0]), WideGrasps())
    report = picker.run()
    assert [a.outcome for a in report.attempts] == ["picked"] and report.stop_reason == "bin_empty"
    assert report.attempts[0].detail.startswith("held at 20.0 mm, not at the planned 30.0 mm")
    picker, _ = make_picker(FakeBin([0.0]), WideGrasps(), config=PickerConfig(hold_any_width=False))
    first = picker.run(max_cycles=1).attempts[0]
    assert first.outcome == "slipped" and "closed to 20.0 mm, the part is 30.0 mm wide" in first.detail


def test_fingers_closed_below_the_parts_narrowest_hold_are_a_slip():
    bin_ = FakeBin([0.0])
    picker, _ = make_picker(bin_)
    close = picker.gripper.close

    def close_on_a_sliver(force_n=None, speed_m_s=None):
        held = close(force_n, speed_m_s)
        picker.gripper.width = 0.004  # something 4 mm wide, or the pads on the part's edge: not a hold of a 10 mm part
        return held

    picker.gripper.close = close_on_a_sliver
    first = picker.run(max_cycles=1).attempts[0]
    assert first.outcome == "slipped" and first.detail.endswith("(10.0 mm at its narrowest hold)")


class SheetGrasps(FakePlanner):
    """Pinches of a 2 mm sheet (an L-bracket standing on its edges)."""

    def plan(self, poses, T_base_camera, depth_m=None, intrinsics=None, q_seed=None, place_slot=0, touches=()):
        plan = super().plan(poses, T_base_camera, depth_m, intrinsics, q_seed)
        for g in plan.grasps:
            g.grasp_width_m = g.min_hold_width_m = 0.002
            g.opening_width_m = 0.012
        return plan


def _close_on_a_sheet(gripper: FakeGripper, width_m: float) -> None:
    """The gripper's close reports no object (it stopped under 1.5 mm short of closed) with the fingers at
    ``width_m``: 1.3 mm on a 2 mm sheet (the pads squeeze it), 0 mm on air."""

    def close(force_n=None, speed_m_s=None):
        gripper.opening = False
        gripper.held = width_m > 0
        gripper.bin.in_fingers = gripper.robot.q_now[0] if gripper.held else None
        gripper.width = width_m
        return False

    gripper.close = close
    gripper.object_detected = lambda: False


def test_fingers_stopped_on_a_thin_sheet_hold_it_although_the_gripper_detects_no_object():
    picker, _ = make_picker(FakeBin([0.0]), SheetGrasps())
    _close_on_a_sheet(picker.gripper, 85e-3 / 255)  # one register count of a 2F-85 apart: squeezed hard
    report = picker.run()
    assert [a.outcome for a in report.attempts] == ["picked"] and report.stop_reason == "bin_empty"


def test_fingers_closed_on_air_are_no_hold_of_a_thin_sheet():
    bin_ = FakeBin([0.0])
    picker, _ = make_picker(bin_, SheetGrasps())
    _close_on_a_sheet(picker.gripper, 0.0)
    first = picker.run(max_cycles=1).attempts[0]
    assert first.outcome == "gripper_empty" and bin_.parts == [0.0]
    # closed after lifting: the sheet slid out, whatever the slip tolerance (4 mm) below its 2 mm leaves
    picker, _ = make_picker(bin_, SheetGrasps())
    _close_on_a_sheet(picker.gripper, 0.0013)

    def slide_out(T, speed_m_s=None, accel_m_s2=None, max_force_n=None, stop_on_contact=False):
        picker.gripper.width = 0.0001
        return moved(T)

    picker.robot.move_l = slide_out
    first = picker.run(max_cycles=1).attempts[0]
    assert first.outcome == "slipped" and "closed to 0.1 mm, the part is 2.0 mm wide" in first.detail


def test_a_part_lost_on_the_way_to_the_place_pose_is_dropped_not_picked():
    """Held after lifting, gone at the place pose (it fell out during the joint move): the attempt is ``dropped``,
    not a pick; the next look finds it (here back in the bin) and picks it."""
    bin_ = FakeBin([0.0])
    picker, robot = make_picker(bin_)
    move_j, moves_to_the_part = robot.move_j, []

    def drop_on_the_way(q, speed_rad_s=None, accel_rad_s2=None):
        move_j(q, speed_rad_s, accel_rad_s2)
        if np.allclose(q, 0.0):  # the fake grasp's lift and place poses: the second is the place
            moves_to_the_part.append(q)
            if len(moves_to_the_part) == 2:
                picker.gripper.held, picker.gripper.width = False, 0.0

    robot.move_j = drop_on_the_way
    report = picker.run()
    assert [a.outcome for a in report.attempts] == ["dropped", "picked"] and report.n_picked == 1
    assert report.attempts[0].stage == "place" and "lost on the way to the place pose" in report.attempts[0].detail
    assert report.stop_reason == "bin_empty" and bin_.parts == []


def test_a_part_stuck_in_the_fingers_stops_the_run_as_gripper_blocked():
    bin_ = FakeBin([0.0, 0.1])
    picker, _ = make_picker(bin_, config=PickerConfig(open_timeout_s=0.05))
    close = picker.gripper.close

    def close_and_stick(force_n=None, speed_m_s=None):
        picker.gripper.stuck = True  # e.g. a tube wedged on a finger
        return close(force_n, speed_m_s)

    picker.gripper.close = close_and_stick
    report = picker.run()
    assert report.stop_reason == "gripper_blocked" and "stuck in the gripper" in report.stop_detail
    assert [a.outcome for a in report.attempts] == ["not_released"]
    assert report.n_picked == 0


def test_fingers_that_do_not_open_keep_the_arm_out_of_the_bin():
    bin_ = FakeBin([0.0])
    picker, robot = make_picker(bin_, config=PickerConfig(open_timeout_s=0.05))
    picker.gripper.stuck, picker.gripper.width = True, 0.0
    report = picker.run()
    assert report.stop_reason == "gripper_blocked" and [a.outcome for a in report.attempts] == ["gripper_blocked"]
    np.testing.assert_array_equal(robot.q_now, np.full(6, -1.0))  # never left the observe pose


def test_a_part_that_keeps_failing_is_given_up_and_the_run_does_not_loop():
    bin_ = FakeBin([0.0, 0.1])
    picker, _ = make_picker(bin_, config=PickerConfig(max_failures_per_part=2))
    picker.gripper.slip_at = 0.0  # the part at x = 0 slips out every time
    report = picker.run()
    assert [a.outcome for a in report.attempts] == ["slipped", "slipped", "picked"]
    assert report.stop_reason == "gave_up" and bin_.parts == [0.0]
    assert report.cycles[-1].n_excluded == 1 and report.cycles[2].n_excluded == 1


def test_a_failing_part_found_again_by_refine_more_is_given_up():
    """The pipeline's first estimate of a skipped part lies centimetres off; refine_more puts it where two
    attempts failed already: the refined pose is left out too (else one part tried again and again at one spot
    ends the run with failed cycles)."""

    class SkippedFarOff(FakeBin):
        def run(self, frame):
            result = super().run(frame)
            result.poses = [ObjectPose(p.detection, make_T(t=(p.T_camera_object[0, 3] + 0.05, 0.0, 0.5)), 1.0, "fake",
                                       {"icp": {"status": "skipped"}}) for p in result.poses]  # fmt: skip
            return result

        def refine_more(self, poses, frame):
            if not any(p.details["icp"]["status"] == "skipped" for p in poses):
                return None
            return [ObjectPose(p.detection, make_T(t=(p.T_camera_object[0, 3] - 0.05, 0.0, 0.5)), 1.0, "fake",
                               {"icp": {"status": "refined"}}) for p in poses]  # fmt: skip

    class RefinedOnly(FakePlanner):
        def plan(self, poses, T_base_camera, depth_m=None, intrinsics=None, q_seed=None, place_slot=0, touches=()):
            grasps = [FakeGrasp(i, 1, p.T_camera_object, p.T_camera_object[0, 3])
                      for i, p in enumerate(poses) if p.details["icp"]["status"] == "refined"]  # fmt: skip
            return FakePlan(grasps, n_in_bin=len(poses))

    bin_ = SkippedFarOff([0.0])
    picker, _ = make_picker(bin_, RefinedOnly(), config=PickerConfig(max_failures_per_part=2, max_failed_cycles=5))
    picker.gripper.slip_at = 0.0  # the part slips out every time
    report = picker.run()
    assert [a.outcome for a in report.attempts] == ["slipped", "slipped"]
    assert report.stop_reason == "gave_up" and report.cycles[-1].n_excluded == 1


def test_cell_files_load_and_bad_fields_name_the_file(tmp_path):
    setup = load_cell_setup("launch/cells/sim.toml")
    assert setup.is_sim and setup.robot.host == "127.0.0.50" and setup.data.perception.kind == "models"
    perception = setup.data.perception
    assert perception.min_fitness is None  # RefineConfig's (see the README: 0.8 picked fewer)
    # the cell's models on the whole mask (docs/decisions.md: the peeled nut masks were refused)
    assert perception.models_dir.endswith("models/sim_cell") and perception.detector_input_size == 960
    assert perception.mask_erosion_px == 0
    hw = load_cell_setup("launch/cells/ur5e_oak.toml")
    assert not hw.is_sim and hw.data.camera.kind == "oak" and hw.robot.host == "192.168.1.10"
    bad = tmp_path / "bad.toml"
    bad.write_text(Path("launch/cells/sim.toml").read_text().replace('kind = "sim"\nname', 'kind = "moon"\nname'))
    with pytest.raises(ConfigError, match=r"bad\.toml"):
        load_cell_setup(bad)
    with pytest.raises(ConfigError, match=r"PickerConfig\.max_cycles"):
        PickerConfig(max_cycles=0)
    strict = tmp_path / "strict.toml"
    strict.write_text(
        Path("launch/cells/sim.toml").read_text().replace("[picker]\n", "[picker]\nhold_any_width = false\n")
    )
    assert load_cell_setup(strict).picker.hold_any_width is False
    bad.write_text(strict.read_text().replace("hold_any_width = false", 'hold_any_width = "no"'))
    with pytest.raises(ConfigError, match=r"bad\.toml.*picker"):
        load_cell_setup(bad)
    bad.write_text(strict.read_text().replace("[perception]\n", "[perception]\nmin_fitness = 1.5\n"))
    with pytest.raises(ConfigError, match=r"bad\.toml.*min_fitness"):
        load_cell_setup(bad)


def test_a_hardware_cell_nudges_only_force_limited_and_says_so(tmp_path):
    assert load_cell_setup("launch/cells/ur5e_oak.toml").picker.nudge_contact == "force_limited"
    assert load_cell_setup("launch/cells/sim.toml").picker.nudge_contact == "force_limited"
    text = Path("launch/cells/ur5e_oak.toml").read_text()
    bad = tmp_path / "bad.toml"
    bad.write_text(text.replace('nudge_contact = "force_limited"', 'nudge_contact = "position"'))
    with pytest.raises(ConfigError, match=r"bad\.toml: \[picker\] nudge_contact = 'position'.*refuses"):
        load_cell_setup(bad)
    off = tmp_path / "off.toml"
    off.write_text(bad.read_text().replace("[picker]\n", "[picker]\nmax_nudges = 0\n"))
    assert load_cell_setup(off).picker.max_nudges == 0  # no nudges: nothing to refuse
    sim = tmp_path / "sim.toml"
    sim.write_text(Path("launch/cells/sim.toml").read_text().replace('"force_limited"', '"position"'))
    sim.write_text(sim.read_text().replace('"../', '"' + str(Path("launch/cells").resolve()) + "/../"))
    assert load_cell_setup(sim).picker.nudge_contact == "position"  # a variant of the simulated cell
    with pytest.raises(ConfigError, match=r"nudge_contact must be one of"):
        PickerConfig(nudge_contact="gently")


def test_the_bin_and_place_pose_come_from_the_cell_file(tmp_path):
    from robot.grasp_config import PlannerConfig

    hw = load_cell_setup("launch/cells/ur5e_oak.toml").planner_config()
    default = PlannerConfig()  # the simulated cell's bin and tray, which the hardware file starts from
    np.testing.assert_allclose(hw.bin.T_base_bin, default.bin.T_base_bin)
    np.testing.assert_allclose(hw.T_base_place, default.T_base_place)
    assert (hw.place_grid, hw.place_pitch_m) == (default.place_grid, default.place_pitch_m)
    assert hw.floor_clearance_m == 0.002 and hw.bin.inner_size_m == (0.30, 0.20, 0.12)
    text = Path("launch/cells/ur5e_oak.toml").read_text()
    moved = tmp_path / "moved.toml"
    moved.write_text(text.replace("inner_size_m = [0.30, 0.20, 0.12]", "inner_size_m = [0.40, 0.30, 0.15]")
                     .replace("[1, 0, 0, -0.5]", "[1, 0, 0, -0.45]"))  # fmt: skip
    config = load_cell_setup(moved).planner_config()
    assert config.bin.inner_size_m == (0.40, 0.30, 0.15) and config.bin.T_base_bin[0, 3] == -0.45
    for old, new, where in [
        ("[0, 0, 1, 0.02]", "[0, 0, 2, 0.02]", r"bad\.toml: \[bin\]: BinGeometry\.T_base_bin must be a 4x4 rigid"),
        ("[0, -1, 0, -0.42]", "[0, -1, 0, -0.42, 1]", r"bad\.toml.*place\.T_base_place"),
        ("wall_thickness_m = 0.01", "wall_thickness_m = -0.01", r"bad\.toml.*bin\.wall_thickness_m"),
        ("grid = [4, 3]", "grid = [4, 0]", r"bad\.toml: place\.grid\[1\]: must be >= 1, got 0"),
        ("pitch_m = [0.05, 0.04]", "pitch_m = [0.05]", r"bad\.toml.*place\.pitch_m"),
        ("floor_clearance_m = 0.002", "floor_clearance = 0.002", r"bad\.toml: \[planner\]: .*floor_clearance"),
    ]:
        bad = tmp_path / "bad.toml"
        bad.write_text(text.replace(old, new, 1))
        with pytest.raises(ConfigError, match=where):
            load_cell_setup(bad)


# ---------------------------------------------------------------------------------------------- nudges


class WallPlanner(FakePlanner):
    """Nothing is safe while a part lies at x < 0 (against the wall); then one grasp per part."""

    def plan(self, poses, T_base_camera, depth_m=None, intrinsics=None, q_seed=None, place_slot=0, touches=()):
        self.nothing_safe = any(p.T_camera_object[0, 3] < 0 for p in poses)
        return super().plan(poses, T_base_camera, depth_m, intrinsics, q_seed)


@dataclass
class FakeNudge:
    part_index: int
    obj_id: int
    T_base_obj: np.ndarray
    cause: str = "collision_bin"
    tilt_deg: float = 45.0
    distance_m: float = 0.03
    speed_m_s: float = 0.05

    def __post_init__(self) -> None:
        self.q_above = np.full(6, 7.0)
        self.T_base_press = make_T(t=(-1.0, 0, 0.02))
        self.T_base_end = make_T(t=(-2.0, 0, 0.02))  # the robot below drags the part when it gets here
        self.T_base_retreat = make_T(t=(-3.0, 0, 0.1))


class FakeNudger:
    def __init__(self) -> None:
        self.calls = 0

    def plan(self, poses, T_base_camera, plan, q_from, q_after, skip=None):
        self.calls += 1
        for i, p in enumerate(poses):
            if p.T_camera_object[0, 3] < 0 and not (skip is not None and skip(i)):
                return FakeNudge(i, 1, p.T_camera_object)
        return None


class DraggingRobot(FakeRobot):
    """Drags the part at the end of a nudge's drag (position control: the straight line to ``T_base_end``; force-
    limited: the pressing move); ``stop_at_press`` stops it once where the paddle meets the part."""

    def __init__(self, bin_: FakeBin, drags: bool = True, stop_at_press: bool = False) -> None:
        super().__init__(bin_)
        self.drags, self.stop_at_press = drags, stop_at_press

    def move_l(self, T, speed_m_s=None, accel_m_s2=None, max_force_n=None, stop_on_contact=False):
        if T[0, 3] == -1.0:
            self._press()
        if T[0, 3] == -2.0:
            self._drag()
        return moved(T)

    def move_until_contact(self, direction, speed_m_s, max_travel_m, accel_m_s2=None):
        self._press()

    def move_l_pressing(self, T, direction, force_n, speed_m_s=None, accel_m_s2=None, max_press_speed_m_s=None):
        self._drag()

    def _press(self) -> None:
        if self.stop_at_press:
            self.stop_at_press = False
            raise ProtectiveStopError("contact")

    def _drag(self) -> None:
        if self.drags:
            self.bin.parts = [0.1 if x < 0 else x for x in self.bin.parts]


def _nudging_picker(bin_: FakeBin, robot: FakeRobot, config: PickerConfig | None = None) -> Picker:
    gripper = FakeGripper(robot, bin_)
    return Picker(
        robot, gripper, FakeCamera(), bin_, WallPlanner(), np.eye(4), np.full(6, -1.0), config, nudger=FakeNudger()
    )


def test_a_part_at_the_wall_is_nudged_away_and_then_picked():
    bin_ = FakeBin([-0.05])
    report = _nudging_picker(bin_, DraggingRobot(bin_)).run()
    assert report.stop_reason == "bin_empty" and report.n_picked == 1 and report.n_nudges == 1
    first = report.cycles[0]
    assert first.end == "nudged" and first.nudge["outcome"] == "done" and first.attempts == []
    assert "nudged part 0" in first.plan_summary
    assert report.to_json()["n_nudges"] == 1


def test_a_nudge_that_moves_nothing_is_repeated_at_most_per_part_and_is_not_a_failed_cycle():
    bin_ = FakeBin([-0.05])
    config = PickerConfig(max_nudges_per_part=3, max_failed_cycles=1)
    report = _nudging_picker(bin_, DraggingRobot(bin_, drags=False), config).run()
    assert report.stop_reason == "nothing_safe" and report.n_nudges == 3
    assert [c.end for c in report.cycles] == ["nudged"] * 3 + ["nothing_safe"]


def test_nudges_stop_at_the_run_limit_and_none_without_a_nudger():
    bin_ = FakeBin([-0.05])
    report = _nudging_picker(bin_, DraggingRobot(bin_, drags=False), PickerConfig(max_nudges=1)).run()
    assert report.stop_reason == "nothing_safe" and report.n_nudges == 1
    picker, _ = make_picker(FakeBin([-0.05]), WallPlanner())
    assert picker.run().n_nudges == 0


def test_a_protective_stop_during_a_nudge_is_recovered_and_the_run_goes_on():
    bin_ = FakeBin([-0.05])
    robot = DraggingRobot(bin_, stop_at_press=True)
    report = _nudging_picker(bin_, robot).run()
    assert robot.recovered == 1
    assert report.cycles[0].nudge["outcome"] == "protective_stop"
    assert report.stop_reason == "bin_empty" and report.n_nudges == 2 and report.n_picked == 1


def test_a_position_controlled_nudge_drags_with_straight_lines():
    bin_ = FakeBin([-0.05])
    report = _nudging_picker(bin_, DraggingRobot(bin_), PickerConfig(nudge_contact="position")).run()
    assert report.stop_reason == "bin_empty" and report.n_nudges == 1 and report.n_picked == 1


def test_a_robot_without_force_limited_motion_refuses_force_limited_nudges_and_says_so():
    bin_ = FakeBin([-0.05])
    robot = FakeRobot(bin_)  # move_l and move_j only
    report = _nudging_picker(bin_, robot, PickerConfig(max_nudges=1, max_failed_cycles=1)).run()
    first = report.cycles[0]
    assert first.nudge["outcome"] == "motion_refused" and "no force-limited motion" in first.nudge["detail"]
    assert robot.q_now.tolist() != [7.0] * 6  # nothing moved toward the part
    assert report.stop_reason == "nothing_safe"


def test_a_press_that_meets_nothing_is_recovered_as_no_contact():
    """Recovered, then straight up to the observe pose's height (not only the planned retreat's: the arm stopped
    elsewhere), the fingers kept closed as the paddle whose paths were checked (opened, a pad reached the wall)."""

    class MissesThePart(DraggingRobot):
        z = 0.3  # the TCP's height: at the observe pose until the press goes down

        def T_base_tcp(self):
            return make_T(t=(0, 0, self.z))

        def move_until_contact(self, direction, speed_m_s, max_travel_m, accel_m_s2=None):
            self.z = 0.02
            raise NoContactError("met nothing within 25 mm")

        def move_l(self, T, speed_m_s=None, accel_m_s2=None, max_force_n=None, stop_on_contact=False):
            if self.recovered:
                self.after_recovery.append(("move_l", round(float(T[2, 3]), 3)))
            return super().move_l(T, speed_m_s, accel_m_s2, max_force_n)

    bin_ = FakeBin([-0.05])
    robot = MissesThePart(bin_)
    robot.after_recovery = []
    picker = _nudging_picker(bin_, robot, PickerConfig(max_nudges=1, max_failed_cycles=1))
    gripper_open = picker.gripper.open

    def log_open(width_m=None, speed_m_s=None):
        if robot.recovered:
            robot.after_recovery.append(("open", width_m))
        gripper_open(width_m, speed_m_s)

    picker.gripper.open = log_open
    report = picker.run()
    assert report.cycles[0].nudge["outcome"] == "no_contact" and robot.recovered == 1
    assert robot.after_recovery == [("move_l", 0.3)]  # up to the observe height (the retreat is at 0.1), no open


def test_a_protective_stop_on_the_way_to_the_observe_pose_is_recovered_once():
    class StopsOnTheWayBack(FakeRobot):
        """After its first move to the observe pose, stops on the next ``stops`` joint moves back to it."""

        def __init__(self, bin_: FakeBin, stops: int) -> None:
            super().__init__(bin_)
            self.stops, self.been_there, self.moves_l = stops, False, []

        def move_l(self, T, speed_m_s=None, accel_m_s2=None, max_force_n=None, stop_on_contact=False):
            self.moves_l.append(np.array(T))
            return moved(T)

        def recover(self, timeout_s=None):
            super().recover(timeout_s)
            self.moves_l = []  # the moves from here on

        def move_j(self, q, speed_rad_s=None, accel_rad_s2=None):
            if np.allclose(q, -1.0):
                if self.been_there and self.stops:
                    self.stops -= 1
                    raise ProtectiveStopError("contact")
                self.been_there = True
            self.q_now = np.asarray(q)

    def run(stops: int):
        bin_ = FakeBin([0.0])
        robot = StopsOnTheWayBack(bin_, stops)
        gripper = FakeGripper(robot, bin_, empty_once=True)  # the first close meets nothing: back to observe
        picker = Picker(robot, gripper, FakeCamera(), bin_, FakePlanner(), np.eye(4), np.full(6, -1.0))
        return picker.run(), robot

    report, robot = run(stops=1)
    assert [a.outcome for a in report.attempts] == ["gripper_empty", "picked"] and robot.recovered == 1
    assert report.stop_reason == "bin_empty"
    assert robot.moves_l[0][2, 3] == pytest.approx(0.05)  # straight up to the observe pose's height first
    # a second stop on the retried move: the cell needs an operator, nothing more is sent
    report, robot = run(stops=2)
    assert report.stop_reason == "needs_operator" and "contact" in report.stop_detail and robot.recovered == 1
    assert len(robot.moves_l) == 1  # the move straight up, then nothing after the second stop


def test_no_detections_in_a_bin_the_depth_shows_is_not_empty_stops_as_parts_unseen():
    class CoveredBin(FakePlanner):
        def pile_area_m2(self, depth_m, intrinsics, T_base_camera):
            return 3e-4  # a nut's top

    bin_ = FakeBin([])
    picker, _ = make_picker(bin_, CoveredBin())
    report = picker.run()
    assert report.stop_reason == "parts_unseen" and report.stop_detail == (
        "the camera sees no parts (no detections), but the depth shows 3.0 cm2 of the bin covered"
    )
    picker, _ = make_picker(FakeBin([]), CoveredBin(), PickerConfig(min_unseen_area_m2=5e-4))
    assert picker.run().stop_reason == "bin_empty"


def test_the_report_picture_keeps_the_cycle_labels_inside_the_axes(tmp_path):
    from launch.pick import SceneShot, report_figure, save_report_picture
    from robot.pick_report import CycleRecord, RunReport

    cycles = [CycleRecord(k, 5.0 * k, {"approach": 3.0 + 4.0 * (k == 1), "place": 1.0}, end="failed") for k in range(3)]
    report = RunReport(cycles, "nothing_safe", "")
    timeline = report_figure(report, SceneShot(), {}).axes[0]
    assert timeline.get_ylim()[1] >= 1.2 * 8.0  # the tallest bar (8 s) with room for its label
    assert save_report_picture(report, SceneShot(), {}, tmp_path / "report.png").stat().st_size > 0


# ------------------------------------------------------------------------ stopping from outside (signals, a dead cell)


def _commands_after_a_stop(picker: Picker, robot: FakeRobot, gripper) -> list[str]:
    """Wraps the fakes' commands: the list gets every one sent after a stop was requested."""
    sent: list[str] = []
    for target, names in ((robot, ("move_l", "move_j", "recover")), (gripper, ("open", "close"))):
        for name in names:
            original = getattr(target, name)

            def command(*args, _original=original, _name=name, **kwargs):
                if picker.stop_switch.requested:
                    sent.append(_name)
                return _original(*args, **kwargs)

            setattr(target, name, command)
    return sent


def test_a_stop_requested_during_a_motion_ends_the_run_there_and_keeps_every_cycle():
    """As a SIGTERM arriving while the arm moves in: the arm is stopped, nothing more is sent (the fingers stay open
    where they were), and the report holds the finished cycle and the interrupted one with its attempt."""
    bin_ = FakeBin([0.0, 0.1])
    picker, robot = make_picker(bin_)
    move_l = robot.move_l

    signals = ["SIGTERM"]

    def move_l_then_signal(T, speed_m_s=None, accel_m_s2=None, max_force_n=None, stop_on_contact=False):
        result = move_l(T, speed_m_s, accel_m_s2, max_force_n, stop_on_contact)
        if abs(T[0, 3] - 0.1) < 1e-9 and signals:
            picker.request_stop(signals.pop())  # arrives while this motion runs
        return result

    robot.move_l = move_l_then_signal
    sent_after = _commands_after_a_stop(picker, robot, picker.gripper.target)
    report = picker.run()
    assert report.stop_reason == "interrupted" and sent_after == [] and robot.stops >= 1
    assert [c.end for c in report.cycles] == ["picked", "interrupted"] and report.cycles[1].interrupted_in == "approach"
    assert [a.outcome for a in report.attempts] == ["picked", "interrupted"] and bin_.parts == [0.1]
    assert report.attempts[1].detail == "stop requested (SIGTERM) during approach"
    assert report.success_rate == 1.0 and report.failures_by_cause() == {}  # an interrupted attempt did not fail
    assert report.stop_detail.startswith(
        "stop requested (SIGTERM): stopped in cycle 1 during approach (attempt on part 0, obj 1); the arm at rest at "
        "TCP (0.000, 0.000, 0.050) m"
    )
    assert "the gripper left as it was, at 30.0 mm" in report.stop_detail  # opened to the grasp's opening, kept
    data = json.loads(json.dumps(report.to_json()))
    assert data["stop_reason"] == "interrupted" and data["n_attempts"] == 2
    assert data["cycles"][1]["end"] == "interrupted" and data["cycles"][1]["interrupted_in"] == "approach"
    # the stop stays requested until cleared: a new run sends nothing
    assert picker.run().cycles == [] and sent_after == []
    picker.clear_stop()
    assert picker.run().stop_reason == "bin_empty" and bin_.parts == []


def test_a_stop_requested_between_steps_or_before_the_run_sends_nothing():
    picker, robot = make_picker(FakeBin([0.0]))
    picker.request_stop("SIGINT")
    report = picker.run()
    assert report.stop_reason == "interrupted" and report.cycles == [] and robot.q_now[0] == 0.0
    assert report.stop_detail.startswith("stop requested (SIGINT): stopped before the first cycle")

    class SlowBin(FakeBin):
        def run(self, frame):  # the perception is running when the request comes
            picker.request_stop("SIGINT")
            return super().run(frame)

    bin_ = SlowBin([0.0])
    picker, robot = make_picker(bin_)
    report = picker.run()
    assert report.cycles[0].end == "interrupted" and report.cycles[0].interrupted_in == "perceive"
    assert report.attempts == [] and bin_.parts == [0.0] and robot.stops >= 1


def test_the_guarded_robot_refuses_commands_after_a_stop_and_passes_the_rest_through():
    from robot.pick_stop import StopRequestedError

    picker, robot = make_picker(FakeBin([0.0]))
    picker.robot.refuse_x = 0.5  # written through to the fake
    assert robot.refuse_x == 0.5 and picker.robot.target is robot
    picker.gripper.close = lambda force_n=None, speed_m_s=None: "replaced"
    assert picker.gripper.close() == "replaced"
    del picker.gripper.close  # the fake's own method again
    picker.request_stop("test")
    with pytest.raises(StopRequestedError, match="test"):
        picker.robot.move_j(np.zeros(6))
    with pytest.raises(StopRequestedError):
        picker.gripper.open()
    assert picker.robot.q() is robot.q_now and picker.gripper.width_m() == 0.085  # reads are never guarded


def test_a_cell_lost_during_an_attempt_keeps_that_attempt_in_the_report():
    """The emulator's process died: the link is lost during an approach and the recovery fails. The report has the
    attempt (connection_lost) in the interrupted cycle, not one attempt fewer than the log."""
    bin_ = FakeBin([0.0, 0.1])
    picker, robot = make_picker(bin_)
    move_l = robot.move_l

    def link_lost_at_the_second_part(T, speed_m_s=None, accel_m_s2=None, max_force_n=None, stop_on_contact=False):
        if abs(T[0, 3] - 0.1) < 1e-9:
            raise ConnectionLostError("lost the link to UR controller 127.0.0.81 during move_l")
        return move_l(T, speed_m_s, accel_m_s2, max_force_n, stop_on_contact)

    def gone(timeout_s=None):
        raise RecoveryError("UR controller 127.0.0.81 does not answer")

    robot.move_l, robot.recover = link_lost_at_the_second_part, gone
    report = picker.run()
    assert report.stop_reason == "needs_operator" and "does not answer" in report.stop_detail
    assert [c.end for c in report.cycles] == ["picked", "interrupted"]
    assert [a.outcome for a in report.attempts] == ["picked", "connection_lost"]
    assert report.attempts[1].detail.endswith("then RecoveryError: UR controller 127.0.0.81 does not answer")


def test_an_unexpected_error_is_raised_after_the_report_kept_the_cycles():
    bin_ = FakeBin([0.0, 0.1])
    picker, robot = make_picker(bin_)
    move_j = robot.move_j

    def broken(q, speed_rad_s=None, accel_rad_s2=None):
        if np.allclose(q, 0.1):
            raise KeyError("a bug")
        move_j(q, speed_rad_s, accel_rad_s2)

    robot.move_j = broken
    with pytest.raises(KeyError):
        picker.run()
    report = picker.last_report
    assert report.stop_reason == "error" and report.stop_detail == "KeyError: 'a bug'"
    assert [c.end for c in report.cycles] == ["picked", "interrupted"] and report.attempts[1].outcome == "interrupted"


# ---------------------------------------------------------------------------------------------- the machine itself


def test_every_state_has_a_step_and_every_transition_is_listed():
    picker, _ = make_picker(FakeBin())
    assert set(TRANSITIONS) == set(CycleState)
    assert set(picker._steps) == set(CycleState) - {CycleState.DONE}
    reachable, todo = {CycleState.CAPTURE}, [CycleState.CAPTURE]
    while todo:
        for after in TRANSITIONS[todo.pop()]:
            if after not in reachable:
                reachable.add(after)
                todo.append(after)
    assert reachable == set(CycleState)  # no step the cycle cannot get to


def test_outcomes_are_the_report_strings():
    """The enums compare, format and serialise as the strings the JSON report and the benchmark read."""
    bin_ = FakeBin([0.0])
    picker, _ = make_picker(bin_)
    picker.gripper.empty_once = True
    report = picker.run()
    assert report.stop_reason is StopReason.BIN_EMPTY and report.stop_reason == "bin_empty"
    assert [a.outcome for a in report.attempts] == [Outcome.GRIPPER_EMPTY, Outcome.PICKED]
    assert [c.end for c in report.cycles] == [CycleEnd.FAILED, CycleEnd.PICKED, CycleEnd.BIN_EMPTY]
    assert f"{report.stop_reason}" == "bin_empty" and str(report.attempts[0].stage) == "grasp"
    data = json.loads(json.dumps(report.to_json()))
    assert data["stop_reason"] == "bin_empty" and data["failures_by_cause"] == {"gripper_empty": 1}
    assert [c["end"] for c in data["cycles"]] == ["failed", "picked", "bin_empty"]
    assert data["cycles"][0]["attempts"][0]["outcome"] == "gripper_empty"
    assert set(data["cycles"][0]["stage_wall_s"]) == {"capture", "perceive", "plan", "approach", "grasp", "verify",
                                                      "place", "nudge"}  # fmt: skip
    assert all(type(k) is str for k in report.to_json()["cycles"][0]["stage_wall_s"])  # plain strings, not enums


def test_detections_whose_poses_were_all_refused_are_named_when_the_cycle_finds_nothing_to_pick():
    det = Detection(0, 1, 0.9, np.zeros(4))
    refused = [ObjectPose(det, make_T(t=(0.0, 0.0, 0.5)), s, "fake", verified=False) for s in (0.42, 0.61)]

    def result(detections, refused_poses=None):
        fields = {"poses": [], "detections": detections, "timings_ms": {}}
        if refused_poses is not None:
            fields["refused"] = refused_poses
        return type("R", (), fields)()

    assert nothing_posed_reason(result([])) == "the camera sees no parts (no detections)"
    assert nothing_posed_reason(result([det, det], refused)) == (
        "the camera sees 2 part(s) but the verification refused every pose (2 refused, best confidence 0.61)"
    )
    # an oracle perception has no verification: detections it gave no pose are named as such
    assert nothing_posed_reason(result([det])) == "the camera sees 1 part(s) but none could be posed"

    # every frame refused: two more looks, then "parts_unseen" though the depth shows no more than a small part's
    bin_ = RefusingBin([0.0], refusals=100)
    picker, _ = make_picker(bin_)
    report = picker.run()
    assert bin_.frames == 3 and report.stop_reason == "parts_unseen"
    assert report.stop_detail.startswith("the camera sees 1 part(s) but the verification refused every pose")
    # the second look's pose is accepted: the part is picked in the same cycle
    bin_ = RefusingBin([0.0], refusals=1)
    picker, _ = make_picker(bin_)
    report = picker.run()
    assert report.n_picked == 1 and report.cycles[0].end == "picked" and report.stop_reason == "bin_empty"
    picker, _ = make_picker(RefusingBin([0.0], refusals=1), config=PickerConfig(relooks=0))
    assert picker.run().stop_reason == "parts_unseen"
    with pytest.raises(ConfigError, match="relooks"):
        PickerConfig(relooks=-1)
