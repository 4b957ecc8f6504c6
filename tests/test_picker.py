"""robot.picker's state machine with simple fakes (no emulator): the stops, the retries and the records."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest

from perception.camera import Frame
from perception.results import Detection, ObjectPose
from robot.cell_setup import load_cell_setup
from robot.picker import Picker, PickerConfig
from robot.ur_errors import MotionRefusedError, ProtectiveStopError
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

    def run(self, frame: Frame):
        det = Detection(0, 1, 1.0, np.zeros(4))
        poses = [ObjectPose(det, make_T(t=(x, 0.0, 0.5)), 1.0, "fake") for x in self.parts]
        return type("R", (), {"poses": poses, "detections": [det] * len(poses), "timings_ms": {"total": 1.0}})()


@dataclass
class FakeGrasp:
    part_index: int
    obj_id: int
    T_base_obj: np.ndarray
    x: float
    opening_width_m: float = 0.03
    grasp_width_m: float = 0.02

    def __post_init__(self) -> None:
        self.q_lift = self.q_place = np.full(6, self.x)
        self.T_base_pregrasp = self.T_base_grasp = self.T_base_lift = make_T(t=(self.x, 0, 0.1))


class FakePlanner:
    def __init__(self, nothing_safe: bool = False) -> None:
        self.nothing_safe = nothing_safe

    def plan(self, poses, T_base_camera, depth_m=None, intrinsics=None, q_seed=None):
        grasps = (
            []
            if self.nothing_safe
            else [FakeGrasp(i, 1, p.T_camera_object, p.T_camera_object[0, 3]) for i, p in enumerate(poses)]
        )
        summary = "nothing safe: part 0: unreachable" if self.nothing_safe else f"{len(grasps)} grasps"
        return type("P", (), {"grasps": grasps, "nothing_safe": not grasps, "summary": lambda self: summary})()


class FakeRobot:
    def __init__(self, bin_: FakeBin, refuse_x: float | None = None, stop_once_x: float | None = None) -> None:
        self.bin, self.refuse_x, self.stop_once_x = bin_, refuse_x, stop_once_x
        self.q_now = np.zeros(6)
        self.recovered = 0
        self.holding: float | None = None

    def q(self):
        return self.q_now

    def T_base_tcp(self):
        return make_T(t=(0, 0, 0.05))

    def move_l(self, T, speed_m_s=None, accel_m_s2=None):
        if self.refuse_x is not None and abs(T[0, 3] - self.refuse_x) < 1e-9:
            raise MotionRefusedError("outside the box")
        if self.stop_once_x is not None and abs(T[0, 3] - self.stop_once_x) < 1e-9:
            self.stop_once_x = None
            raise ProtectiveStopError("contact")

    def move_j(self, q, speed_rad_s=None, accel_rad_s2=None):
        self.q_now = np.asarray(q)

    def recover(self, timeout_s=None):
        self.recovered += 1


class FakeGripper:
    can_set_width = True

    def __init__(self, robot: FakeRobot, bin_: FakeBin, empty_once: bool = False) -> None:
        self.robot, self.bin, self.empty_once = robot, bin_, empty_once
        self.held = False

    def open(self, width_m=None, speed_m_s=None):
        if self.held:
            self.bin.parts.remove(self.robot.q_now[0]) if self.robot.q_now[0] in self.bin.parts else None
        self.held = False

    def close(self, force_n=None, speed_m_s=None):
        if self.empty_once:
            self.empty_once = False
            return False
        self.held = True
        return True

    def width_m(self):
        return 0.02 if self.held else 0.0

    def object_detected(self):
        return self.held


def make_picker(bin_: FakeBin, planner=None, **robot_kw) -> tuple[Picker, FakeRobot]:
    robot = FakeRobot(bin_, **robot_kw)
    gripper = FakeGripper(robot, bin_)
    return Picker(robot, gripper, FakeCamera(), bin_, planner or FakePlanner(), np.eye(4), np.full(6, -1.0)), robot


def test_clears_the_bin_and_stops_when_empty():
    bin_ = FakeBin()
    picker, _ = make_picker(bin_)
    report = picker.run()
    assert report.stop_reason == "bin_empty" and bin_.parts == []
    assert report.n_picked == 3 and report.success_rate == 1.0
    assert report.sim_cycle_times_s() == [5.0, 5.0, 5.0]  # camera time from one capture to the next


def test_nothing_safe_is_a_clean_stop_with_the_reasons():
    picker, _ = make_picker(FakeBin(), FakePlanner(nothing_safe=True))
    report = picker.run()
    assert report.stop_reason == "nothing_safe" and "unreachable" in report.stop_detail
    assert report.attempts == []


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


def test_gripper_closing_on_air_fails_verification_and_retries():
    bin_ = FakeBin([0.0])
    picker, _ = make_picker(bin_)
    picker.gripper.empty_once = True
    report = picker.run()
    assert [a.outcome for a in report.attempts] == ["gripper_empty", "picked"]
    assert report.failures_by_cause() == {"gripper_empty": 1}


def test_part_still_there_after_its_pick_is_marked_failed():
    bin_ = FakeBin([0.0])
    picker, _ = make_picker(bin_)
    picker.gripper.open = lambda width_m=None, speed_m_s=None: setattr(picker.gripper, "held", False)  # never removes
    report = picker.run(max_cycles=2)
    assert report.attempts[0].outcome == "part_still_in_bin"


def test_cell_files_load_and_bad_fields_name_the_file(tmp_path):
    setup = load_cell_setup("launch/cells/sim.toml")
    assert setup.is_sim and setup.robot.host == "127.0.0.50" and setup.data.perception.kind == "models"
    hw = load_cell_setup("launch/cells/ur5e_oak.toml")
    assert not hw.is_sim and hw.data.camera.kind == "oak" and hw.robot.host == "192.168.1.10"
    bad = tmp_path / "bad.toml"
    bad.write_text(Path("launch/cells/sim.toml").read_text().replace('kind = "sim"\nname', 'kind = "moon"\nname'))
    with pytest.raises(ConfigError, match=r"bad\.toml"):
        load_cell_setup(bad)
    with pytest.raises(ConfigError, match=r"PickerConfig\.max_cycles"):
        PickerConfig(max_cycles=0)
