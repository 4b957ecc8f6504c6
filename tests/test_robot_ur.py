"""robot.ur.URRobot against the controller emulator (kinematic backend) through the stock ur_rtde client.

The emulator runs in a child process (``ControllerProcess``; the client's constructors hold the GIL). Addresses:
127.0.0.41 the cell, 127.0.0.42 nothing listening, 127.0.0.43 a port that accepts and never answers, 127.0.0.48 the
cell of the shutdown test (in its own process).
"""

from __future__ import annotations

import dataclasses
import logging
import os
import socket
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

pytest.importorskip("rtde_control")
dashboard_client = pytest.importorskip("dashboard_client")

from robot.ur import URRobot  # noqa: E402
from robot.ur_config import URConfig, WorkspaceBox, check_joint_path, trapezoid_duration_s  # noqa: E402
from robot.ur_errors import (  # noqa: E402
    ConnectionLostError,
    MotionFailedError,
    MotionRefusedError,
    OutsideWorkspaceError,
    ProtectiveStopError,
    RobotConnectionError,
    UnreachableError,
)
from sim.controller import ControllerProcess  # noqa: E402
from sygrid.errors import ConfigError  # noqa: E402
from sygrid.robots.kinematics import T_to_pose, forward_kinematics, pose_to_T  # noqa: E402
from sygrid.transforms import make_T, rotation_about  # noqa: E402

HOST, DEAD_HOST, SILENT_HOST, SHUTDOWN_HOST = "127.0.0.41", "127.0.0.42", "127.0.0.43", "127.0.0.48"
T_FLANGE_TCP = make_T(t=(0.0, 0.0, 0.145))
BOX = WorkspaceBox((-0.75, -0.45, 0.10), (-0.25, 0.25, 0.60))
Q_WORK = np.array([0.3, -1.2, 1.4, -1.8, -1.5708, 0.2])
# Joint moves from Q_WORK that keep the TCP inside BOX all the way.
DQ_A = np.array([-0.4, 0.0, 0.0, 0.0, 0.0, 0.4])
DQ_B = np.array([-0.3, 0.1, -0.1, 0.0, 0.0, 0.3])
TOOL_DOWN = np.diag([1.0, -1.0, -1.0])
# The emulator refuses to unlock a protective stop this soon after it (e-Series: 5 s); long enough that recover()
# is always called within it, so the retry path runs.
UNLOCK_DELAY_S = 1.0

pytestmark = pytest.mark.timeout(60)


def config(**overrides: object) -> URConfig:
    return URConfig(**{"host": HOST, "workspace": BOX, "T_flange_tcp": T_FLANGE_TCP, **overrides})


def wait_until(predicate, timeout_s: float = 3.0) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if predicate():
            return True
        time.sleep(0.01)
    return predicate()


def emulator_T_base_tcp(cell: ControllerProcess) -> np.ndarray:
    return pose_to_T(np.array(cell.state().actual_tcp_pose))


@pytest.fixture(scope="module")
def cell():
    with ControllerProcess(HOST, unlock_delay_s=UNLOCK_DELAY_S) as cell:
        yield cell


@pytest.fixture(scope="module")
def robot(cell):
    robot = URRobot(config())
    robot.connect()
    try:
        yield robot
    finally:
        robot.close()


@pytest.fixture
def at_work(robot):
    """Each motion test starts recovered, at rest at Q_WORK."""
    robot.recover()
    robot.move_j(Q_WORK, 3.0, 6.0)
    return robot


def test_connect_sets_the_tcp_and_reads_the_state(cell, robot):
    state = cell.state()
    assert np.allclose(state.tcp_offset, T_to_pose(T_FLANGE_TCP))
    assert state.program == "rtde_control" and state.runtime_state == 2
    assert np.allclose(robot.q(), state.actual_q)
    assert np.allclose(robot.T_base_tcp(), forward_kinematics(robot.q(), T_FLANGE_TCP), atol=1e-9)
    assert np.allclose(robot.T_base_flange(), forward_kinematics(robot.q()), atol=1e-9)
    status = robot.status()
    assert status.connected and status.program_running and not status.protective_stopped
    assert robot.is_connected()


def test_move_l_reaches_the_target_pose(cell, at_work):
    robot = at_work
    T_start = robot.T_base_tcp()
    T_target = T_start.copy()
    T_target[:3, :3] = rotation_about([0, 0, 1], np.radians(10)) @ T_start[:3, :3]
    T_target[:3, 3] += [0.05, -0.04, 0.06]
    result = robot.move_l(T_target, 0.25, 1.2)
    assert result.reached and result.kind == "move_l"
    assert result.target_error_m < 1e-6
    np.testing.assert_allclose(emulator_T_base_tcp(cell), T_target, atol=1e-6)
    np.testing.assert_allclose(result.T_base_tcp, T_target, atol=1e-6)


def test_move_j_and_move_j_to_pose_reach_their_targets(cell, at_work):
    robot = at_work
    q_target = Q_WORK + np.array([0.2, -0.1, 0.15, 0.0, 0.1, -0.3])
    result = robot.move_j(q_target, 3.0, 6.0)
    assert result.reached
    np.testing.assert_allclose(cell.state().actual_q, q_target, atol=1e-9)
    np.testing.assert_allclose(result.q, q_target, atol=1e-9)

    T_target = make_T(TOOL_DOWN, (-0.45, 0.05, 0.30))
    result = robot.move_j_to_pose(T_target, 3.0, 6.0)
    assert result.reached and result.kind == "move_j"
    np.testing.assert_allclose(emulator_T_base_tcp(cell), T_target, atol=1e-6)
    np.testing.assert_allclose(robot.ik(T_target), robot.q(), atol=1e-6)  # at the solution nearest where it is


def test_stop_cuts_an_asynchronous_move_short(cell, at_work):
    robot = at_work
    T_start = robot.T_base_tcp()
    T_target = T_start @ make_T(t=(0.0, 0.0, -0.2))  # 20 cm up (tool z points down)
    robot.start_move_l(T_target, 0.1, 0.5)
    stopper = threading.Timer(0.4, robot.stop)
    stopper.start()
    result = robot.wait_for_motion()
    stopper.join()
    assert not result.reached
    travelled = np.linalg.norm(result.T_base_tcp[:3, 3] - T_start[:3, 3])
    assert 0.01 < travelled < 0.15
    assert np.isclose(result.target_error_m, 0.2 - travelled, atol=1e-6)  # stopped on the line
    assert wait_until(lambda: np.allclose(cell.state().target_q, cell.state().actual_q))


def test_refused_motions_send_nothing(cell, at_work):
    robot = at_work
    before = cell.state()
    outside = make_T(TOOL_DOWN, (-0.5, 0.0, 0.05))  # 5 cm below the box floor
    with pytest.raises(OutsideWorkspaceError, match=r"outside the workspace box .*z 0\.100\.\.0\.600"):
        robot.move_l(outside)
    with pytest.raises(OutsideWorkspaceError):
        robot.move_j_to_pose(outside)
    # Both ends inside, but a full turn of the base swings the TCP through +x, out of the box.
    with pytest.raises(OutsideWorkspaceError, match="along the path"):
        robot.move_j(Q_WORK - np.array([2 * np.pi, 0, 0, 0, 0, 0]))
    with pytest.raises(UnreachableError, match="no IK solution"):
        robot.move_j_to_pose(make_T(TOOL_DOWN, (-0.74, 0.24, 0.59)))
    with pytest.raises(MotionRefusedError, match=r"speed_m_s must be in \(0, 1\]"):
        robot.move_l(robot.T_base_tcp(), speed_m_s=1.5)
    with pytest.raises(MotionRefusedError, match="accel_rad_s2"):
        robot.move_j(Q_WORK, accel_rad_s2=0.0)
    with pytest.raises(MotionRefusedError, match=r"elbow 4\.0000 not in"):
        robot.move_j(np.array([0.0, -1.5, 4.0, -1.5, -1.5, 0.0]))
    with pytest.raises(MotionRefusedError, match="rigid"):
        robot.move_l(np.diag([2.0, 1.0, 1.0, 1.0]))
    time.sleep(0.05)
    after = cell.state()
    assert after.target_q == before.target_q and after.actual_q == before.actual_q
    assert after.runtime_state == 2


def test_protective_stop_mid_move_is_reported_then_recovered(cell, at_work, caplog):
    robot = at_work
    T_start = robot.T_base_tcp()
    T_target = T_start @ make_T(t=(0.1, 0.0, 0.0))
    robot.start_move_l(T_target, 0.1, 0.5)
    threading.Timer(0.3, cell.trigger_protective_stop).start()
    with pytest.raises(ProtectiveStopError, match="protective stop") as info:
        robot.wait_for_motion()
    assert info.value.recoverable
    stopped_at = info.value.T_base_tcp[:3, 3]
    assert 0.005 < np.linalg.norm(stopped_at - T_start[:3, 3]) < 0.09  # stopped on the way
    assert robot.status().protective_stopped and cell.state().protective_stopped
    with pytest.raises(ProtectiveStopError, match="nothing was sent"):
        robot.move_l(T_target)
    with caplog.at_level(logging.INFO, logger="robot.ur_connection"):
        robot.recover()  # refused for UNLOCK_DELAY_S, as e-Series does for 5 s
    assert any("unlock refused" in r.getMessage() for r in caplog.records)
    assert not cell.state().protective_stopped and cell.state().runtime_state == 2
    assert np.allclose(cell.state().tcp_offset, T_to_pose(T_FLANGE_TCP))
    result = robot.move_l(T_target)
    assert result.reached
    np.testing.assert_allclose(emulator_T_base_tcp(cell), T_target, atol=1e-6)


def test_collision_during_move_j_is_a_protective_stop(cell, at_work):
    robot = at_work
    robot.start_move_j(Q_WORK + DQ_A, 0.5, 1.0)
    time.sleep(0.3)
    cell.inject_collision_force(400.0)
    try:
        with pytest.raises(ProtectiveStopError):
            robot.wait_for_motion()
    finally:
        cell.inject_collision_force(0.0)
    assert "contact force" in cell.state().last_error
    robot.recover()
    assert robot.move_j(Q_WORK + DQ_A, 3.0, 6.0).reached


def test_program_stopped_mid_move_fails_and_is_restarted_before_the_next_one(cell, at_work):
    robot = at_work
    dash = dashboard_client.DashboardClient(HOST)
    dash.connect()
    try:
        robot.start_move_j(Q_WORK + DQ_A, 0.3, 1.0)
        time.sleep(0.2)
        dash.stop()  # as the pendant's stop button would
        with pytest.raises(MotionFailedError, match="control script stopped") as info:
            robot.wait_for_motion()
        assert not isinstance(info.value, ProtectiveStopError)
        assert cell.state().runtime_state == 1
        assert robot.move_j(Q_WORK, 3.0, 6.0).reached  # re-uploaded before sending (restart_stopped_program)
        dash.stop()
        assert wait_until(lambda: not robot.status().program_running)
        robot.config = dataclasses.replace(robot.config, restart_stopped_program=False)
        # (if the control connection has not seen the stop yet, the client refuses the command instead)
        with pytest.raises(MotionFailedError, match=r"nothing was sent|refused move_j"):
            robot.move_j(Q_WORK + DQ_B)
    finally:
        robot.config = config()
        dash.disconnect()


def test_digital_outputs_through_rtde_io(cell, robot):
    robot.set_digital_out(3, True)
    assert cell.state().digital_output_bits & (1 << 3)
    robot.set_digital_out(1, True, kind="tool")
    assert cell.state().digital_output_bits == (1 << 3) | (1 << 17)
    assert robot.digital_out(1, kind="tool") and not robot.digital_out(2)
    robot.set_digital_out(3, False)
    robot.set_digital_out(1, False, kind="tool")
    assert cell.state().digital_output_bits == 0
    assert not robot.digital_in(0)
    with pytest.raises(ValueError, match=r"tool digital IO index must be 0\.\.1"):
        robot.set_digital_out(2, True, kind="tool")


def test_dropped_connection_is_reconnected(cell, at_work):
    """The controller restarts under the client: mid-move this is a ConnectionLostError; with auto_reconnect off
    the next motion says so; with it on the robot reconnects before sending; reconnect() works on a live link."""
    robot = at_work
    robot.start_move_j(Q_WORK + DQ_B, 0.3, 1.0)
    time.sleep(0.2)
    cell.stop()
    with pytest.raises(ConnectionLostError, match="lost the link"):
        robot.wait_for_motion()
    cell.start()  # a fresh controller: arm at home, TCP at the flange, no program
    assert not robot.is_connected()
    robot.config = dataclasses.replace(robot.config, auto_reconnect=False)
    try:
        with pytest.raises(ConnectionLostError, match="not connected"):
            robot.move_j(Q_WORK)
    finally:
        robot.config = config()
    assert robot.move_j(Q_WORK, 3.0, 6.0).reached
    assert robot.is_connected()
    state = cell.state()
    np.testing.assert_allclose(state.actual_q, Q_WORK, atol=1e-9)
    assert np.allclose(state.tcp_offset, T_to_pose(T_FLANGE_TCP))  # the TCP is set again
    robot.reconnect()
    assert robot.move_j(Q_WORK + DQ_B, 3.0, 6.0).reached


# Connects, closes on a live link; connects again, stops the controller under the client, closes on the dead link;
# then the interpreter shuts down. Without robot.ur_connection._never_destroy the close on the dead link aborts the
# process (std::terminate from a ur_rtde destructor).
SHUTDOWN_SCRIPT = """
import time
from robot.ur import URRobot
from robot.ur_config import URConfig, WorkspaceBox
from sim.controller import ControllerProcess

if __name__ == "__main__":
    config = URConfig(host=HOST, workspace=WorkspaceBox((-1.0, -1.0, -0.2), (1.0, 1.0, 1.2)))
    with ControllerProcess(HOST) as cell:
        robot = URRobot(config)
        robot.connect()
        robot.close()
        print("closed on a live link", flush=True)
        robot.connect()
        cell.stop()
        end = time.monotonic() + 5.0
        while robot.is_connected() and time.monotonic() < end:
            time.sleep(0.02)
        print("link down:", not robot.is_connected(), flush=True)
        robot.close()
        print("closed on a dead link", flush=True)
    print("exiting", flush=True)
"""
_SHUTDOWN_LINES = ("closed on a live link", "link down: True", "closed on a dead link", "exiting")


def test_closing_on_a_live_and_a_dead_link_then_exiting_does_not_crash(tmp_path):
    script = tmp_path / "shutdown.py"
    script.write_text(f"HOST = {SHUTDOWN_HOST!r}\n" + SHUTDOWN_SCRIPT)
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [root, os.environ.get("PYTHONPATH")]))}
    done = subprocess.run([sys.executable, str(script)], cwd=root, env=env, capture_output=True, text=True, timeout=50)
    assert done.returncode == 0, f"exit code {done.returncode}\nstdout:\n{done.stdout}\nstderr:\n{done.stderr}"
    lines = [line for line in done.stdout.splitlines() if line in _SHUTDOWN_LINES]
    assert lines == list(_SHUTDOWN_LINES), done.stdout


@pytest.mark.timeout(10)
def test_connecting_to_a_dead_host_fails_with_the_address():
    with pytest.raises(RobotConnectionError, match=r"127\.0\.0\.42: nothing answers on port 30004"):
        URRobot(config(host=DEAD_HOST, connect_timeout_s=0.5)).connect()


@pytest.mark.timeout(10)
def test_a_port_that_never_answers_does_not_hang_the_client():
    with socket.socket() as listener:
        listener.bind((SILENT_HOST, 30004))
        listener.listen()
        with pytest.raises(RobotConnectionError, match=r"127\.0\.0\.43:30004 .* did not answer"):
            URRobot(config(host=SILENT_HOST, connect_timeout_s=0.3)).connect()


def test_a_joint_path_may_enter_the_box_but_not_leave_it():
    cfg = config()
    q_outside = Q_WORK + np.array([0.8, 0.0, 0.0, 0.0, 0.0, 0.0])  # base turned: TCP at y < -0.45
    assert not BOX.contains(forward_kinematics(q_outside, T_FLANGE_TCP)[:3, 3])
    check_joint_path(cfg, T_FLANGE_TCP, q_outside, Q_WORK)  # moving in is allowed
    with pytest.raises(OutsideWorkspaceError, match="outside the workspace box"):
        check_joint_path(cfg, T_FLANGE_TCP, Q_WORK, q_outside)
    with pytest.raises(OutsideWorkspaceError, match="along the path"):  # out and back in
        check_joint_path(cfg, T_FLANGE_TCP, Q_WORK, Q_WORK - np.array([2 * np.pi, 0, 0, 0, 0, 0]))
    # the same test for a planner, which has no URConfig: where along the path the TCP first leaves the box
    step = cfg.path_check_step_rad
    assert BOX.joint_path_exit(T_FLANGE_TCP, q_outside, Q_WORK, step) is None
    fraction, p = BOX.joint_path_exit(T_FLANGE_TCP, Q_WORK, q_outside, step)
    assert 0.0 < fraction <= 1.0 and not BOX.contains(p)
    fraction, p = BOX.joint_path_exit(T_FLANGE_TCP, Q_WORK, Q_WORK - np.array([2 * np.pi, 0, 0, 0, 0, 0]), step)
    assert 0.0 < fraction < 1.0 and not BOX.contains(p)
    assert trapezoid_duration_s(0.3, 1.05, 1.4) == pytest.approx(2 * np.sqrt(0.3 / 1.4))  # triangular
    assert trapezoid_duration_s(2.0, 1.0, 2.0) == pytest.approx(2.0 + 0.5)


def test_config_from_dict_and_its_errors():
    cfg = URConfig.from_dict(
        {
            "host": "192.168.1.10",
            "workspace": {"lo_m": [-0.8, -0.6, 0.0], "hi_m": [0.2, 0.6, 0.7]},
            "T_flange_tcp": T_FLANGE_TCP.tolist(),
            "linear_speed_m_s": 0.5,
        },
        "cell.toml [robot]",
    )
    assert cfg.workspace.contains([0.0, 0.0, 0.5]) and not cfg.workspace.contains([0.0, 0.0, 0.8])
    assert np.array_equal(cfg.T_flange_tcp, T_FLANGE_TCP) and cfg.linear_speed_m_s == 0.5
    with pytest.raises(ConfigError, match=r"cell.toml \[robot\]: unknown keys \['speed'\]"):
        URConfig.from_dict(
            {"host": "h", "workspace": {"lo_m": [0, 0, 0], "hi_m": [1, 1, 1]}, "speed": 1}, "cell.toml [robot]"
        )
    with pytest.raises(ConfigError, match="missing 'workspace'"):
        URConfig.from_dict({"host": "h"})
    with pytest.raises(ConfigError, match="lo_m < hi_m"):
        URConfig.from_dict({"host": "h", "workspace": {"lo_m": [0, 0, 1], "hi_m": [1, 1, 1]}})
    with pytest.raises(ConfigError, match=r"linear_speed_m_s = 2\.0 exceeds max_linear_speed_m_s"):
        config(linear_speed_m_s=2.0)
    with pytest.raises(ConfigError, match="rigid"):
        config(T_flange_tcp=np.diag([1.0, 1.0, 2.0, 1.0]))
