"""Unit tests of the controller emulator's pieces: profiles, motions, name tables, input application, script
parsing, the async progress word, IK tolerances, gripper and dashboard replies. No sockets, no client."""

from __future__ import annotations

import logging
import math
import struct
import threading
import time

import numpy as np
import pytest

from sim.controller import EmulatedController, KinematicBackend, MotionError, make_backend
from sim.controller.arm import ArmController
from sim.controller.dashboard import DashboardServer
from sim.controller.gripper_server import GripperServer, position_to_width, width_to_position
from sim.controller.ik_query import solve_ik, track_ik
from sim.controller.motion import Trapezoid
from sim.controller.program import ControlProgram
from sim.controller.rtde_names import OUTPUT_TYPES, output_types
from sim.controller.rtde_outputs import OutputRecipe
from sim.controller.rtde_server import InputRecipe
from sim.controller.script_intake import ScriptParser
from sim.controller.snapshot import pose_from_T
from sim.controller.state import IoState, Registers, StateSnapshot, apply_input_fields
from sim.controller.stepper import BackendRunner
from sygrid.robots import ur5e
from sygrid.robots.kinematics import T_to_pose, forward_kinematics, pose_to_T

pytestmark = pytest.mark.timeout(30)

Q_WORK = np.array([0.3, -1.2, 1.4, -1.8, -1.5708, 0.2])
# The receive interface's default request (ur_rtde 1.6.5, controller 5.15), as the protocol note lists it
RECEIVE_NAMES = [
    "timestamp",
    "target_q",
    "target_qd",
    "target_qdd",
    "target_current",
    "target_moment",
    "actual_q",
    "actual_qd",
    "actual_current",
    "joint_control_output",
    "actual_TCP_pose",
    "actual_TCP_speed",
    "actual_TCP_force",
    "target_TCP_pose",
    "target_TCP_speed",
    "actual_digital_input_bits",
    "joint_temperatures",
    "actual_execution_time",
    "robot_mode",
    "joint_mode",
    "safety_mode",
    "actual_tool_accelerometer",
    "speed_scaling",
    "target_speed_fraction",
    "actual_momentum",
    "actual_main_voltage",
    "actual_robot_voltage",
    "actual_robot_current",
    "actual_joint_voltage",
    "actual_digital_output_bits",
    "runtime_state",
    "standard_analog_input0",
    "standard_analog_input1",
    "standard_analog_output0",
    "standard_analog_output1",
    "robot_status_bits",
    "safety_status_bits",
    "ft_raw_wrench",
    "payload",
    "payload_cog",
    "payload_inertia",
    "output_int_register_2",
    *(f"output_int_register_{i}" for i in range(12, 20)),
    *(f"output_double_register_{i}" for i in range(12, 20)),
]


def test_trapezoid_and_triangle_durations():
    tri = Trapezoid(0.3, 1.05, 1.4)  # the protocol note's moveJ: 0.928 s observed
    assert tri.duration == pytest.approx(2 * math.sqrt(0.3 / 1.4))
    trap = Trapezoid(2.0, 1.0, 2.0)
    assert trap.duration == pytest.approx(2.0 / 1.0 + 1.0 / 2.0)
    ts = np.linspace(0, trap.duration, 400)
    s = np.array([trap.at(t)[0] for t in ts])
    assert np.all(np.diff(s) >= 0) and s[-1] == 2.0 and max(trap.at(t)[1] for t in ts) == pytest.approx(1.0)
    with pytest.raises(ValueError, match="v=0"):
        Trapezoid(1.0, 0.0, 1.0)


def test_movej_is_synchronised_and_ends_at_rest():
    arm = ArmController(ur5e.HOME_Q)
    target = ur5e.HOME_Q + np.array([0.4, -0.2, 0.1, 0.0, 0.0, 0.3])
    motion = arm.movej(target, 1.0, 2.0)
    ticks, ratios = 0, []
    while arm.motion is not None and ticks < 5000:
        arm.step(0.002, 1.0)
        ticks += 1
        moved = arm.target_q - ur5e.HOME_Q
        if abs(moved[0]) > 1e-6:
            ratios.append(moved / moved[0])
    assert np.allclose(arm.target_q, target) and np.all(arm.target_qd == 0)
    assert ticks == pytest.approx(motion.duration_s / 0.002, abs=1)
    assert np.allclose(ratios, (target - ur5e.HOME_Q) / 0.4)


def test_movej_outside_joint_limits_names_the_limits():
    arm = ArmController(ur5e.HOME_Q)
    with pytest.raises(MotionError, match="outside the UR5e joint limits"):
        arm.movej(np.array([0, 0, 3.5, 0, 0, 0]), 1.0, 1.0)


def test_movel_stop_stays_on_the_line_and_speed_slider_slows_time():
    arm = ArmController(Q_WORK)
    start = forward_kinematics(Q_WORK)[:3, 3]
    pose = T_to_pose(forward_kinematics(Q_WORK))
    pose[1] += 0.2
    arm.movel(pose, 0.25, 1.0)
    for _ in range(200):
        arm.step(0.002, 1.0)
    arm.stop(2.0, linear=True)
    while arm.motion is not None:
        arm.step(0.002, 1.0)
    p = forward_kinematics(arm.target_q)[:3, 3]
    assert 0.0 < p[1] - start[1] < 0.2 and np.allclose(p[[0, 2]], start[[0, 2]], atol=1e-9)
    slow = ArmController(Q_WORK)
    slow.movel(pose, 0.25, 1.0)
    for _ in range(200):
        slow.step(0.002, 0.5)
    fast = ArmController(Q_WORK)
    fast.movel(pose, 0.25, 1.0)
    for _ in range(100):
        fast.step(0.002, 1.0)
    assert np.allclose(slow.target_q, fast.target_q)


def test_receive_interface_names_have_the_client_types():
    types = dict(zip(RECEIVE_NAMES, output_types(RECEIVE_NAMES), strict=True))
    assert "NOT_FOUND" not in types.values()
    assert {n for n, t in OUTPUT_TYPES.items() if t == "VECTOR3D"} == {
        "actual_tool_accelerometer",
        "payload_cog",
        "elbow_position",
        "elbow_velocity",
    }
    assert types["joint_mode"] == "VECTOR6INT32" and types["runtime_state"] == "UINT32"
    assert types["actual_digital_output_bits"] == "UINT64" and types["robot_mode"] == "INT32"
    assert output_types(["timestamp", "no_such_variable"]) == ["DOUBLE", "NOT_FOUND"]
    recipe = OutputRecipe(3, RECEIVE_NAMES, 500.0)
    payload = recipe.pack(StateSnapshot(timestamp_s=1.5, runtime_state=2))
    assert payload[0] == 3 and struct.unpack_from(">d", payload, 1) == (1.5,)


def test_input_recipes_decode_and_masks_apply():
    recipe = InputRecipe(2, ["input_int_register_23", "standard_digital_output_mask", "standard_digital_output"])
    fields = recipe.decode(struct.pack(">iBB", 13, 0x08, 0x08) + b"extra")
    regs, io = Registers(), IoState(standard_do=0b0001)
    apply_input_fields(regs, io, fields)
    assert regs.input_int[23] == 13 and io.standard_do == 0b1001
    apply_input_fields(regs, io, {"standard_digital_output_mask": 0x01, "standard_digital_output": 0})
    apply_input_fields(regs, io, {"tool_digital_output_mask": 2, "tool_digital_output": 2})
    apply_input_fields(regs, io, {"speed_slider_mask": 1, "speed_slider_fraction": 1.7})
    apply_input_fields(
        regs,
        io,
        {
            "standard_analog_output_mask": 2,
            "standard_analog_output_type": 2,
            "standard_analog_output_0": 0.9,
            "standard_analog_output_1": 0.4,
        },
    )
    assert io.digital_output_bits == (1 << 3) | (1 << 17)
    assert io.speed_slider == 1.0 and io.analog_out == [0.0, 0.4] and io.analog_out_voltage_mask == 2
    apply_input_fields(regs, io, {"input_bit_register_70": True, "input_double_register_47": 2.5})
    assert regs.input_bits == 1 << 70 and regs.input_double[47] == 2.5


def test_script_parser_finds_rtde_control_and_its_offset_and_refuses_the_rest(caplog):
    parser = ScriptParser()
    text = (
        "def rtde_control():\n  global reg_offset_float = # float register offset\n24\n"
        "  global reg_offset_int = # int register offset\n24\n  textmsg(1)\nend"
    )
    programs = parser.feed(text[:30]) + parser.feed(text[30:])  # chunked, no trailing newline
    assert [(p.name, p.register_offset) for p in programs] == [("rtde_control", 24)]
    with caplog.at_level(logging.ERROR):
        assert parser.feed('popup("hi")\ndef other():\n  sleep(1)\nend\n')[0].name == "other"
    assert parser.refused == ['popup("hi")'] and "outside a program refused" in caplog.text


def test_async_progress_word_matches_the_client_decoding():
    ctl = EmulatedController(KinematicBackend(), host="127.0.0.99")
    program = ControlProgram(ctl.regs, ctl.arm, ctl, 0)
    program.tick()  # start: "finished", no running bit
    word = ctl.regs.output_int[2]
    assert not word & 0x8000 and (word >> 24) % 2 - 2 == -2
    program._write_async_progress(0)  # an operation starts
    word = ctl.regs.output_int[2]
    assert word & 0x8000 and word & 0x7FFF == 0 and (word >> 24) == 1 and (word >> 16) & 0xFF == 2
    program._write_async_progress(-1)
    assert (ctl.regs.output_int[2] >> 24) % 2 - 2 == -1  # what getAsyncOperationProgress returns after a stop


def test_ik_honours_tolerances_and_tracking_matches_analytic():
    T = forward_kinematics(np.array([0.0, -0.1, 0.0, 0.0, 0.5, 0.0]))
    T[0, 3] *= 1.0005  # just out of reach
    assert solve_ik(T, np.zeros(6)) is None
    q = solve_ik(T, np.zeros(6), None, 0.01, 0.01)
    assert q is not None and np.linalg.norm(forward_kinematics(q)[:3, 3] - T[:3, 3]) < 0.01
    rng = np.random.default_rng(0)
    for _ in range(50):
        q0 = Q_WORK + rng.uniform(-0.5, 0.5, 6)
        q1 = q0 + rng.normal(0.0, 0.002, 6)
        assert np.allclose(track_ik(forward_kinematics(q1), q0), q1, atol=1e-9)


def test_fast_snapshot_pose_equals_shared_conversion():
    rng = np.random.default_rng(1)
    for k in range(500):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        angle = math.pi if k % 5 == 0 else rng.uniform(0, math.pi)
        T = pose_to_T(np.concatenate([rng.normal(size=3), axis * angle]))
        assert np.array_equal(np.array(pose_from_T(T)), T_to_pose(T))


def test_gripper_commands_and_replies():
    backend = KinematicBackend(object_width_m=0.04)
    runner = BackendRunner(backend)
    gripper = GripperServer("127.0.0.99", 0, runner)
    assert gripper.handle("SET ACT 1") == "ack" and gripper.handle("SET GTO 1") == "ack"
    assert gripper.handle("SET POS 255 SPE 255 FOR 10") == "ack"
    assert gripper.handle("GET OBJ") == "OBJ 0\n"  # queued, not yet applied
    for _ in range(600):
        runner.push_target(ur5e.HOME_Q, np.zeros(6))
    assert gripper.handle("GET OBJ") == "OBJ 2\n"
    assert gripper.handle("GET POS") == f"POS {width_to_position(0.04)}\n"
    assert gripper.handle("GET XYZ") == "XYZ ?\n" and gripper.handle("SET POS abc") == "?"
    assert position_to_width(0) == 0.085 and position_to_width(255) == 0.0


def test_dashboard_replies_without_a_running_program():
    ctl = EmulatedController(KinematicBackend(), host="127.0.0.99")
    dash = DashboardServer("127.0.0.99", 0, ctl)
    assert dash.reply("stop") == "Stopped"
    assert dash.reply("play") == "Failed to execute: play"
    assert dash.reply("PolyscopeVersion").startswith("URSoftware 5.15.0.106767")
    assert dash.reply("get serial number").isdigit()
    assert dash.reply("is in remote control") == "true"
    assert dash.reply("robotmode") == "Robotmode: RUNNING"
    ctl.trigger_protective_stop()
    assert dash.reply("safetystatus") == "Safetystatus: PROTECTIVE_STOP"
    assert dash.reply("unlock protective stop") == "Protective stop releasing"
    assert dash.reply("safetymode") == "Safetymode: NORMAL"
    assert dash.reply("running") == "Program running: false"
    assert dash.reply("frobnicate") == "could not understand: 'frobnicate'"


def test_bad_configuration_names_the_value_and_the_choices():
    with pytest.raises(ValueError, match="unknown backend 'bullet'; choose one of: kinematic, mujoco"):
        make_backend("bullet")
    with pytest.raises(ValueError, match=r"protective_stop_runtime_state must be 4 .* or 1 .* got 2"):
        EmulatedController(KinematicBackend(), protective_stop_runtime_state=2)
    with pytest.raises(ValueError, match="initial_q must have 6 joint angles"):
        KinematicBackend(initial_q=np.zeros(5))


def test_threaded_backend_runs_commands_between_the_targets_they_came_between():
    """A gripper command handed over after some arm targets runs after those targets are simulated, even when the
    stepper trails the tick by many targets (it once ran before them: a gripper closed after the arm arrived by the
    controller's clock closed while the simulated arm was still on its way down)."""
    events: list[object] = []
    gate = threading.Event()

    class Recording(KinematicBackend):
        step_may_block = True

        def advance(self, targets, steps_per_target):
            gate.wait(5.0)  # the stepper trails until the gate opens
            events.extend(round(float(q[0]), 3) for q, _ in targets)
            return super().advance(targets, steps_per_target)

    runner = BackendRunner(Recording())
    runner.start()
    try:
        runner.push_target(np.full(6, 0.1), np.zeros(6))
        time.sleep(0.05)  # the stepper took the first target and waits at the gate
        for q0 in (0.2, 0.3):
            runner.push_target(np.full(6, q0), np.zeros(6))
        runner.call(lambda: events.append("gripper"))
        runner.push_target(np.full(6, 0.4), np.zeros(6))
        assert runner.lag_targets == 4  # the three queued and the one being simulated
        gate.set()
        end = time.monotonic() + 5.0
        while len(events) < 5 and time.monotonic() < end:
            time.sleep(0.01)
    finally:
        gate.set()
        runner.stop()
    assert events == [0.1, 0.2, 0.3, "gripper", 0.4]
