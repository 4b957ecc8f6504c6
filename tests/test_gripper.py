"""robot.gripper against the controller emulator's gripper socket (kinematic backend) and its digital outputs.

Addresses: 127.0.0.44 a cell whose gripper closes on a 30 mm object, 127.0.0.45 one with nothing between the fingers
(also driven by URRobot for the digital-output gripper), 127.0.0.46 nothing listening, 127.0.0.47 a socket that
accepts and never answers.
"""

from __future__ import annotations

import socket

import numpy as np
import pytest

pytest.importorskip("rtde_control")

from robot.gripper import (
    DigitalOutputGripper,
    DigitalOutputGripperConfig,
    GripperError,
    RobotiqGripperConfig,
    RobotiqSocketGripper,
    gripper_config_from_dict,
    make_gripper,
)
from robot.ur import URRobot
from robot.ur_config import URConfig, WorkspaceBox
from sim.controller import ControllerProcess
from sygrid.errors import ConfigError

HOST_OBJECT, HOST_EMPTY, DEAD_HOST, SILENT_HOST = "127.0.0.44", "127.0.0.45", "127.0.0.46", "127.0.0.47"
OBJECT_M = 0.03
POS_STEP_M = 0.085 / 255  # the width resolution of the register
TOOL_OUT_0_BIT = 1 << 16

pytestmark = pytest.mark.timeout(60)


@pytest.fixture(scope="module")
def cell_object():
    with ControllerProcess(HOST_OBJECT, backend_kwargs={"object_width_m": OBJECT_M}) as cell:
        yield cell


@pytest.fixture(scope="module")
def cell_empty():
    with ControllerProcess(HOST_EMPTY) as cell:
        yield cell


@pytest.fixture(scope="module")
def robot_empty(cell_empty):
    config = URConfig(host=HOST_EMPTY, workspace=WorkspaceBox((-1.0, -1.0, -0.2), (1.0, 1.0, 1.2)))
    with URRobot(config) as robot:
        yield robot


def test_socket_gripper_closes_on_an_object_and_opens(cell_object):
    with make_gripper(RobotiqGripperConfig(HOST_OBJECT)) as gripper:
        assert isinstance(gripper, RobotiqSocketGripper) and gripper.can_set_width
        gripper.activate()
        assert gripper.get("STA") == 3 and gripper.get("GTO") == 1
        gripper.open()
        assert gripper.width_m() == pytest.approx(0.085, abs=1e-9)
        assert gripper.close(force_n=100.0, speed_m_s=0.15) is True
        assert gripper.object_detected() is True
        assert gripper.width_m() == pytest.approx(OBJECT_M, abs=POS_STEP_M / 2)
        state = cell_object.state()
        assert state.gripper_object_detected and state.gripper_width_m == pytest.approx(OBJECT_M, abs=1e-9)
        # force and speed reach the register map: 100 N of 20..235 N, 0.15 m/s is the top of 0.02..0.15 m/s
        assert gripper.get("FOR") == round(255 * 80 / 215) and gripper.get("SPE") == 255
        gripper.open(width_m=0.05)
        assert gripper.width_m() == pytest.approx(0.05, abs=POS_STEP_M)
        assert gripper.object_detected() is False
        assert cell_object.state().gripper_width_m == pytest.approx(0.05, abs=POS_STEP_M)
        gripper.open()
        assert gripper.width_m() == pytest.approx(0.085, abs=1e-9)
        gripper.activate()  # already active: no reset, still ready
        assert gripper.get("STA") == 3


def test_socket_gripper_closing_on_nothing_reports_no_object(cell_empty):
    gripper = RobotiqSocketGripper(RobotiqGripperConfig(HOST_EMPTY, speed_m_s=0.15))
    try:
        gripper.activate()
        gripper.open()
        assert gripper.close() is False
        assert gripper.object_detected() is False
        assert gripper.width_m() == pytest.approx(0.0, abs=1e-9)
        assert not cell_empty.state().gripper_object_detected
        gripper.open()
    finally:
        gripper.disconnect()


def test_socket_gripper_refuses_bad_requests(cell_empty):
    gripper = RobotiqSocketGripper(RobotiqGripperConfig(HOST_EMPTY))
    try:
        gripper.set(ACT=0)  # a gripper that was never activated
        with pytest.raises(GripperError, match=r"not activated \(STA 0\); call activate\(\) first"):
            gripper.close()
        gripper.activate()
        with pytest.raises(GripperError, match=r"speed_m_s must be within \[0\.02, 0\.15\]"):
            gripper.close(speed_m_s=0.5)
        with pytest.raises(GripperError, match=r"force_n must be within \[20, 235\]"):
            gripper.close(force_n=5.0)
        with pytest.raises(GripperError, match=r"width_m must be within \[0, 0\.085\] m"):
            gripper.open(width_m=0.1)
        with pytest.raises(GripperError, match=r"'GET XYZ' answered 'XYZ \?'"):
            gripper.get("XYZ")
        assert gripper.get("STA") == 3  # the link survives a refused request
    finally:
        gripper.disconnect()


@pytest.mark.timeout(10)
def test_socket_gripper_errors_name_the_address():
    with pytest.raises(GripperError, match=r"gripper at 127\.0\.0\.46:63352: cannot connect"):
        RobotiqSocketGripper(RobotiqGripperConfig(DEAD_HOST, timeout_s=0.5)).activate()
    with socket.socket() as listener:
        listener.bind((SILENT_HOST, 63352))
        listener.listen()
        gripper = RobotiqSocketGripper(RobotiqGripperConfig(SILENT_HOST, timeout_s=0.3))
        with pytest.raises(GripperError, match=r"127\.0\.0\.47:63352: no reply to 'GET STA' within 0\.3 s"):
            gripper.activate()


def test_digital_output_gripper_switches_the_tool_output(cell_empty, robot_empty):
    gripper = make_gripper(DigitalOutputGripperConfig(output=0, output_kind="tool", actuation_time_s=0.05), robot_empty)
    assert isinstance(gripper, DigitalOutputGripper) and not gripper.can_set_width
    gripper.activate()
    assert not cell_empty.state().digital_output_bits & TOOL_OUT_0_BIT
    assert gripper.close() is None  # no sensor: the caller must verify another way
    assert cell_empty.state().digital_output_bits & TOOL_OUT_0_BIT
    assert gripper.width_m() is None and gripper.object_detected() is None
    gripper.open()
    assert not cell_empty.state().digital_output_bits & TOOL_OUT_0_BIT
    with pytest.raises(GripperError, match="only opens fully"):
        gripper.open(width_m=0.04)
    with pytest.raises(GripperError, match="no force or speed setting"):
        gripper.close(force_n=50.0)


def test_digital_output_gripper_with_inverted_output_and_a_sensor_input(cell_empty, robot_empty):
    """Closes by switching standard output 5 off; the object sensor is standard input 2, which reads low in the
    emulator (nothing drives its inputs): low = present here, so the grasp reads as held."""
    robot_empty.set_digital_out(5, True)
    config = DigitalOutputGripperConfig(
        output=5, output_kind="standard", close_level=False, actuation_time_s=0.0,
        object_input=2, object_input_kind="standard", object_present_level=False,
    )  # fmt: skip
    gripper = make_gripper(config, robot_empty)
    assert gripper.close() is True
    assert not cell_empty.state().digital_output_bits & (1 << 5)
    gripper.open()
    assert cell_empty.state().digital_output_bits & (1 << 5)
    high_means_present = make_gripper(
        DigitalOutputGripperConfig(
            output=5, output_kind="standard", actuation_time_s=0.0, object_input=2, object_input_kind="standard"
        ),
        robot_empty,
    )
    assert high_means_present.object_detected() is False
    robot_empty.set_digital_out(5, False)


def test_gripper_configs_from_tables_and_their_errors():
    config = gripper_config_from_dict({"kind": "robotiq_socket", "force_n": 60}, "cell.toml [gripper]", "10.0.0.2")
    assert config == RobotiqGripperConfig(host="10.0.0.2", force_n=60)
    config = gripper_config_from_dict({"kind": "digital_output", "output": 1, "object_input": 0})
    assert config == DigitalOutputGripperConfig(output=1, object_input=0)
    with pytest.raises(ConfigError, match=r"cell.toml \[gripper\]: kind must be one of \['digital_output', "):
        gripper_config_from_dict({"kind": "vacuum"}, "cell.toml [gripper]")
    with pytest.raises(ConfigError, match=r"unknown keys \['force_n'\] for kind 'digital_output'"):
        gripper_config_from_dict({"kind": "digital_output", "output": 0, "force_n": 10})
    with pytest.raises(ConfigError, match=r"output must be a tool pin 0\.\.1, got 2"):
        DigitalOutputGripperConfig(output=2)
    with pytest.raises(ConfigError, match=r"force_n must be within \[20, 235\]"):
        RobotiqGripperConfig("h", force_n=300.0)
    with pytest.raises(ConfigError, match="needs the robot's digital IO"):
        make_gripper({"kind": "digital_output", "output": 0})
    assert isinstance(make_gripper({"kind": "robotiq_socket", "host": "h"}), RobotiqSocketGripper)
    assert np.isclose(RobotiqGripperConfig("h").stroke_m, 0.085)
