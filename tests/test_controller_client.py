"""The controller emulator driven by the stock ur_rtde 1.6.5 client over loopback (kinematic backend).

The emulator runs in a child process (``ControllerProcess``): the client's constructors hold the GIL while they
wait for it. Every client is disconnected and every emulator stopped in fixture teardown, and each test has a
timeout. The module uses 127.0.0.21 (and 127.0.0.22 for the second cell) so other test modules can run beside it.
"""

from __future__ import annotations

import contextlib
import os
import socket
import threading
import time
from pathlib import Path

import numpy as np
import pytest

dashboard_client = pytest.importorskip("dashboard_client")
rtde_control = pytest.importorskip("rtde_control")
rtde_io = pytest.importorskip("rtde_io")
rtde_receive = pytest.importorskip("rtde_receive")

from sim.controller import ControllerProcess  # noqa: E402
from sim.controller.process import EMULATOR_NICENESS, raise_priority  # noqa: E402
from sim.controller.rtde_probe import RtdeProbe  # noqa: E402
from sygrid.robots.kinematics import T_to_pose, pose_to_T  # noqa: E402

HOST, HOST_2 = "127.0.0.21", "127.0.0.22"
Q0 = [0.0, -np.pi / 2, np.pi / 2, -np.pi / 2, -np.pi / 2, 0.0]
Q_WORK = [0.3, -1.2, 1.4, -1.8, -1.5708, 0.2]  # a well-conditioned pose away from singularities
GRIPPER_OBJECT_M = 0.03

pytestmark = pytest.mark.timeout(60)


def wait_until(predicate, timeout_s: float = 2.0, period_s: float = 0.005) -> bool:
    """Also used right after a call returns: the receive connection may decode a package later than the control
    connection that saw "done"."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if predicate():
            return True
        time.sleep(period_s)
    return predicate()


def assert_listening(host: str, port: int = 30004) -> None:
    """Guards the client constructors, which wait without timeout and hold the GIL."""
    with socket.create_connection((host, port), timeout=2.0):
        pass


class Cell:
    """The emulator plus one receive, one control and one IO client."""

    def __init__(self, host: str) -> None:
        self.host = host
        self.emulator = ControllerProcess(host, backend_kwargs={"object_width_m": GRIPPER_OBJECT_M})
        self.emulator.start()
        assert_listening(host)
        self.r = rtde_receive.RTDEReceiveInterface(host)
        self.c = rtde_control.RTDEControlInterface(host)
        self.io = rtde_io.RTDEIOInterface(host)
        self.dash = dashboard_client.DashboardClient(host)
        self.dash.connect()

    def reconnect_control(self) -> rtde_control.RTDEControlInterface:
        self.c.disconnect()
        assert_listening(self.host)
        self.c = rtde_control.RTDEControlInterface(self.host)
        return self.c

    def recover(self) -> None:
        """Back to a running program, no protective stop, at Q_WORK."""
        self.emulator.inject_collision_force(0.0)
        if self.r.isProtectiveStopped():
            self.dash.unlockProtectiveStop()  # the 1.6.5 binding returns None
        if not self.c.isProgramRunning():
            assert self.c.reuploadScript()
            assert wait_until(self.c.isProgramRunning)
        assert self.c.moveJ(Q_WORK, 3.0, 6.0)

    def close(self) -> None:
        for client in (self.dash, self.io, self.c, self.r):
            with contextlib.suppress(RuntimeError):
                client.disconnect()
        self.emulator.stop()


@pytest.fixture(scope="module")
def cell():
    cell = Cell(HOST)
    try:
        yield cell
    finally:
        cell.close()


def test_receive_reports_start_pose_and_fk_matches_reference(cell):
    assert np.allclose(cell.r.getActualQ(), Q0)
    assert cell.r.getRobotMode() == 7
    assert cell.r.getSafetyMode() == 1
    pose = cell.c.getForwardKinematics()
    assert np.allclose(pose[:3], [-0.4919, -0.1333, 0.4879], atol=1e-4)
    assert np.allclose(pose, cell.r.getActualTCPPose(), atol=1e-9)
    t0 = cell.r.getTimestamp()
    time.sleep(0.05)
    assert cell.r.getTimestamp() > t0


def test_movej_is_a_synchronised_trapezoid(cell):
    q_start = np.array(cell.r.getActualQ())
    target = q_start + np.array([0.3, 0.2, 0.0, 0.0, 0.0, -0.1])
    t = cell.r.getTimestamp()
    assert cell.c.moveJ(target.tolist(), 1.05, 1.4)
    elapsed = cell.r.getTimestamp() - t  # controller time: wall time would measure this machine's load
    assert wait_until(lambda: np.allclose(cell.r.getActualQ(), target, atol=1e-9), 0.5)
    assert 0.9 < elapsed < 1.15  # triangle profile: 2*sqrt(0.3/1.4) = 0.926 s, plus the receive thread's lag
    assert cell.c.moveJ(Q_WORK, 3.0, 6.0)


def test_movel_ends_within_half_a_millimetre_on_a_straight_line(cell):
    start = np.array(cell.r.getActualTCPPose())
    target = start + np.array([0.05, -0.04, 0.06, 0.0, 0.0, 0.0])
    samples = []
    mover = threading.Thread(target=lambda: samples.append(cell.c.moveL(target.tolist(), 0.25, 1.2)))
    mover.start()
    path = []
    while mover.is_alive():
        path.append(cell.r.getActualTCPPose()[:3])
        time.sleep(0.01)
    mover.join()
    assert samples == [True]
    assert np.linalg.norm(np.array(cell.r.getActualTCPPose()[:3]) - target[:3]) < 0.5e-3
    direction = (target[:3] - start[:3]) / np.linalg.norm(target[:3] - start[:3])
    offsets = [np.linalg.norm((p - start[:3]) - np.dot(p - start[:3], direction) * direction) for p in np.array(path)]
    assert max(offsets) < 1e-5  # on the line to 10 um (a joint-space move bows off it by millimetres)


def test_ik_fk_round_trips_through_the_client(cell):
    rng = np.random.default_rng(7)
    tcp = [0.0, 0.0, 0.05, 0.0, 0.0, 0.0]
    assert cell.c.setTcp(tcp)
    try:
        for _ in range(15):
            q = np.array(Q_WORK) + rng.uniform(-0.4, 0.4, 6)
            pose = cell.c.getForwardKinematics(q.tolist(), tcp)
            q_ik = cell.c.getInverseKinematics(pose, (q + rng.normal(0, 0.05, 6)).tolist())
            assert np.allclose(q_ik, q, atol=1e-8), (q, q_ik)
            assert np.allclose(cell.c.getForwardKinematics(q_ik, tcp), pose, atol=1e-9)
        pose = cell.c.getForwardKinematics()
        assert np.allclose(cell.c.getInverseKinematics(pose), cell.r.getActualQ(), atol=1e-8)
        assert cell.c.getInverseKinematicsHasSolution(pose)
    finally:
        assert cell.c.setTcp([0.0] * 6)


def test_forward_kinematics_with_q_uses_stale_tcp_registers(cell):
    """getForwardKinematics(q) (recipe 6) never writes d6..d11, so the script's TCP argument is whatever the
    last command left there; with tcp = zeros the client sends 12 doubles under recipe 6 and the controller
    applies the first 6, so d6..d11 stay stale too."""
    q = Q_WORK
    with_tcp = cell.c.getForwardKinematics(q, [0.0, 0.0, 0.1, 0.0, 0.0, 0.0])
    assert not np.allclose(with_tcp, cell.c.getForwardKinematics(q, [0.0, 0.0, 0.2, 0.0, 0.0, 0.0]))
    cell.c.getForwardKinematics(q, [0.0, 0.0, 0.1, 0.0, 0.0, 0.0])
    assert np.allclose(cell.c.getForwardKinematics(q), with_tcp)
    assert np.allclose(cell.c.getForwardKinematics(q, [0.0] * 6), with_tcp)


def test_set_tcp_shifts_reported_pose_and_reads_back(cell):
    flange = np.array(cell.r.getActualTCPPose())
    assert cell.c.setTcp([0.0, 0.0, 0.1, 0.0, 0.0, 0.0])
    try:
        assert np.allclose(cell.c.getTCPOffset(), [0.0, 0.0, 0.1, 0.0, 0.0, 0.0])
        assert wait_until(lambda: not np.allclose(cell.r.getActualTCPPose(), flange))
        shifted = np.array(cell.r.getActualTCPPose())
        assert abs(np.linalg.norm(shifted[:3] - flange[:3]) - 0.1) < 1e-9
        assert np.allclose(cell.c.getForwardKinematics(), shifted, atol=1e-9)
    finally:
        assert cell.c.setTcp([0.0] * 6)


def test_payload_is_reported(cell):
    assert cell.c.setPayload(1.5, [0.0, 0.01, 0.05])
    assert wait_until(lambda: cell.r.getPayload() == 1.5)
    assert np.allclose(cell.r.getPayloadCog(), [0.0, 0.01, 0.05])
    assert cell.c.setPayload(0.5, [0.0, 0.0, 0.0])  # zero CoG keeps the previous one (PolyScope 5 behaviour)
    assert wait_until(lambda: cell.r.getPayload() == 0.5)
    assert np.allclose(cell.r.getPayloadCog(), [0.0, 0.01, 0.05])


def test_async_movel_progress_and_stopl_on_path(cell):
    start = np.array(cell.r.getActualTCPPose())
    target = start + np.array([0.0, 0.0, 0.15, 0.0, 0.0, 0.0])
    assert cell.c.moveL(target.tolist(), 0.1, 0.5, True)
    assert not np.allclose(cell.r.getActualTCPPose(), target, atol=1e-3)  # returned long before the 1.7 s move ends
    assert wait_until(lambda: cell.c.getAsyncOperationProgress() >= 0, 0.5)
    time.sleep(0.3)
    assert not cell.c.isSteady()
    cell.c.stopL(2.0)
    assert cell.c.getAsyncOperationProgress() < 0
    assert wait_until(lambda: np.allclose(cell.r.getActualTCPSpeed(), 0.0, atol=1e-9), 0.5)
    stopped = np.array(cell.r.getActualTCPPose())
    assert 0.01 < stopped[2] - start[2] < 0.1
    assert np.allclose(stopped[:2], start[:2], atol=1e-9)  # stopl decelerates along the line
    assert wait_until(cell.c.isSteady, 1.0)


def test_async_movej_and_stopj(cell):
    q = np.array(cell.r.getActualQ())
    assert cell.c.moveJ((q + 0.5).tolist(), 0.5, 1.0, True)
    time.sleep(0.3)
    cell.c.stopJ(4.0)
    assert wait_until(lambda: np.allclose(cell.r.getActualQd(), 0.0, atol=1e-9), 0.5)
    moved = np.array(cell.r.getActualQ()) - q
    assert np.all(moved > 0.01) and np.all(moved < 0.5)
    assert np.allclose(moved / moved[0], 1.0)  # synchronised joints
    assert cell.c.moveJ(Q_WORK, 3.0, 6.0)


def test_servoj_follows_then_servo_stop(cell):
    q0 = np.array(cell.r.getActualQ())
    for i in range(150):
        t_cycle = cell.c.initPeriod()
        target = q0 + np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.3 * min(i / 100, 1.0)])
        assert cell.c.servoJ(target.tolist(), 0.5, 0.5, 0.002, 0.05, 300)
        cell.c.waitPeriod(t_cycle)
    assert cell.c.servoStop(5.0)
    assert cell.r.getActualQ()[5] - q0[5] > 0.2
    assert wait_until(lambda: np.allclose(cell.r.getActualQd(), 0.0, atol=1e-9), 1.0)
    assert cell.c.moveJ(Q_WORK, 3.0, 6.0)


def test_speedj_and_speedl_then_speed_stop(cell):
    q0 = np.array(cell.r.getActualQ())
    assert cell.c.speedJ([0.2, 0, 0, 0, 0, 0], 2.0, 0.002)
    time.sleep(0.4)
    assert abs(cell.r.getActualQd()[0] - 0.2) < 1e-9
    assert cell.c.speedStop(5.0)
    assert wait_until(lambda: np.allclose(cell.r.getActualQd(), 0.0, atol=1e-9), 0.5)
    assert cell.r.getActualQ()[0] - q0[0] > 0.04
    z0 = cell.r.getActualTCPPose()[2]
    assert cell.c.speedL([0.0, 0.0, 0.05, 0.0, 0.0, 0.0], 0.5, 0.002)
    time.sleep(0.4)
    assert abs(cell.r.getActualTCPSpeed()[2] - 0.05) < 1e-6
    assert cell.c.speedStop(1.0)
    assert cell.r.getActualTCPPose()[2] - z0 > 0.01
    assert cell.c.moveJ(Q_WORK, 3.0, 6.0)


def test_joint_torques_and_is_steady(cell):
    cell.c.getJointTorques()  # realtime: the first call reads the previous cycle's registers
    time.sleep(0.01)
    assert cell.c.getJointTorques() == [0.0] * 6  # the kinematic backend has no dynamics
    assert cell.c.getForwardKinematics() is not None  # clears the latched realtime command
    assert wait_until(cell.c.isSteady, 1.0)


def test_further_queries_and_moves(cell):
    q = np.array(cell.r.getActualQ())
    pose = cell.c.getForwardKinematics()
    assert np.allclose(
        cell.c.poseTrans(pose, [0.0, 0.0, 0.1, 0.0, 0.0, 0.0])[:3],
        T_to_pose(pose_to_T(pose) @ pose_to_T([0, 0, 0.1, 0, 0, 0]))[:3],
    )
    assert cell.c.isJointsWithinSafetyLimits(q.tolist())
    assert not cell.c.isJointsWithinSafetyLimits([0.0, 0.0, 4.0, 0.0, 0.0, 0.0])  # elbow limit +-pi
    assert cell.c.isPoseWithinSafetyLimits(pose)
    assert not cell.c.isPoseWithinSafetyLimits([3.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    assert not cell.c.getInverseKinematicsHasSolution([3.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    assert cell.c.zeroFtSensor() and cell.c.setGravity([0.0, 0.0, 9.82])
    assert cell.c.setTargetPayload(0.8, [0.0, 0.0, 0.04], [0.001] * 6)
    assert wait_until(lambda: cell.r.getPayload() == 0.8)
    assert np.allclose(cell.r.getPayloadInertia(), [0.001] * 6)
    target_q = q + np.array([0.1, -0.05, 0.05, 0.0, 0.0, 0.0])
    assert cell.c.moveL_FK(target_q.tolist(), 0.25, 1.2)
    assert wait_until(lambda: np.allclose(cell.r.getActualQ(), target_q, atol=1e-8), 0.5)
    assert np.allclose(cell.c.getTargetWaypoint(), cell.r.getActualTCPPose(), atol=1e-9)
    assert cell.c.moveJ_IK(pose, 1.0, 2.0)
    assert wait_until(lambda: np.allclose(cell.r.getActualQ(), q, atol=1e-8), 0.5)
    # realtime queries return the registers of the previous cycle: call, let a cycle pass, call again
    cell.c.getStepTime()
    time.sleep(0.01)
    assert cell.c.getStepTime() == 0.002
    cell.c.getActualToolFlangePose()
    time.sleep(0.01)
    assert np.allclose(cell.c.getActualToolFlangePose(), pose, atol=1e-9)  # TCP is the flange here
    assert cell.c.getForwardKinematics() is not None  # clears the latched realtime command


def test_protective_stop_from_collision_fails_blocking_movej_and_recovers(cell):
    q = np.array(cell.r.getActualQ())
    result = []
    mover = threading.Thread(target=lambda: result.append(cell.c.moveJ((q + 0.8).tolist(), 0.5, 1.0)))
    mover.start()
    time.sleep(0.3)
    cell.emulator.inject_collision_force(400.0)
    mover.join(5.0)
    assert result == [False]
    assert wait_until(cell.r.isProtectiveStopped)
    assert cell.r.getSafetyMode() == 3
    state = cell.emulator.state()
    assert state.runtime_state == 4 and "contact force" in state.last_error
    assert wait_until(lambda: np.allclose(cell.r.getActualQd(), 0.0))
    assert np.max(np.abs(np.array(cell.r.getActualQ()) - q)) < 0.7  # stopped short of the target
    assert not cell.c.moveJ(Q_WORK, 1.0, 1.0)  # fails at once while stopped
    cell.emulator.inject_collision_force(0.0)
    cell.dash.unlockProtectiveStop()
    assert wait_until(lambda: not cell.r.isProtectiveStopped())
    assert cell.c.reuploadScript()
    assert wait_until(cell.c.isProgramRunning)
    assert cell.c.moveJ(Q_WORK, 3.0, 6.0)


def test_protective_stop_command_and_dashboard_unlock(cell):
    cell.c.triggerProtectiveStop()
    assert wait_until(cell.r.isProtectiveStopped)
    dashboard = dashboard_client.DashboardClient(cell.host)
    dashboard.connect()
    try:
        assert dashboard.safetystatus() == "Safetystatus: PROTECTIVE_STOP"
        dashboard.send("unlock protective stop\n")
        assert dashboard.receive() == "Protective stop releasing"
        assert dashboard.safetystatus() == "Safetystatus: NORMAL"
    finally:
        dashboard.disconnect()
    cell.recover()


def test_watchdog_stops_the_program_when_not_kicked(cell):
    assert cell.c.setWatchdog(10.0)
    for _ in range(10):
        assert cell.c.kickWatchdog()
        time.sleep(0.05)
    assert cell.c.isProgramRunning()
    time.sleep(0.4)
    assert not cell.c.isProgramRunning()
    assert "watchdog" in cell.emulator.state().last_error
    assert not cell.c.moveJ(Q_WORK, 1.0, 1.0)
    cell.recover()


def test_unsupported_command_fails_cleanly_and_is_logged(cell):
    assert not cell.c.teachMode()
    assert any("teachMode is not supported" in line for line in cell.emulator.log_messages())
    assert wait_until(cell.c.isProgramRunning)
    assert np.allclose(cell.c.getForwardKinematics(), cell.r.getActualTCPPose(), atol=1e-9)


def test_unreachable_ik_halts_the_program_like_a_urscript_error(cell):
    assert cell.c.getInverseKinematics([2.0, 0.0, 0.5, 0.0, 3.14, 0.0]) == []
    assert not cell.c.isProgramRunning()
    assert "no solution" in cell.emulator.state().last_error
    cell.recover()


def test_digital_and_analog_outputs_through_rtde_io(cell):
    assert cell.io.setStandardDigitalOut(3, True)
    assert wait_until(lambda: cell.r.getActualDigitalOutputBits() == 0b1000)
    assert cell.r.getDigitalOutState(3)
    assert cell.io.setToolDigitalOut(1, True)
    assert cell.io.setConfigurableDigitalOut(0, True)
    assert wait_until(lambda: cell.r.getActualDigitalOutputBits() == (1 << 3) | (1 << 8) | (1 << 17))
    assert cell.io.setStandardDigitalOut(3, False)
    assert wait_until(lambda: cell.r.getActualDigitalOutputBits() == (1 << 8) | (1 << 17))
    assert cell.io.setAnalogOutputVoltage(0, 0.25)
    assert wait_until(lambda: cell.r.getStandardAnalogOutput0() == 0.25)
    assert cell.io.setSpeedSlider(0.5)
    assert wait_until(lambda: cell.r.getSpeedScaling() == 0.5)
    assert cell.r.getTargetSpeedFraction() == 0.5
    q = np.array(cell.r.getActualQ())
    t = cell.r.getTimestamp()
    assert cell.c.moveJ((q + 0.2).tolist(), 1.05, 1.4)
    assert cell.r.getTimestamp() - t > 1.2  # 0.76 s at full speed, twice that at 50 %
    assert cell.io.setSpeedSlider(1.0)
    assert wait_until(lambda: cell.r.getSpeedScaling() == 1.0)


def _gripper(sock: socket.socket, line: str) -> str:
    sock.sendall((line + "\n").encode())
    return sock.recv(1024).decode()


def test_gripper_socket_activates_closes_on_object_and_opens(cell):
    with socket.create_connection((cell.host, 63352), timeout=2.0) as sock:
        assert _gripper(sock, "SET ACT 1") == "ack"
        assert wait_until(lambda: _gripper(sock, "GET STA") == "STA 3\n", 1.0)
        assert _gripper(sock, "SET GTO 1") == "ack"
        assert _gripper(sock, "SET POS 255 SPE 255 FOR 100") == "ack"
        assert _gripper(sock, "GET OBJ") == "OBJ 0\n"
        assert wait_until(lambda: _gripper(sock, "GET OBJ") == "OBJ 2\n", 2.0)  # stopped on the 30 mm object
        expected = round(255 * (1 - GRIPPER_OBJECT_M / 0.085))
        assert _gripper(sock, "GET POS") == f"POS {expected}\n"
        assert _gripper(sock, "GET PRE") == "PRE 255\n"
        assert abs(cell.emulator.state().gripper_width_m - GRIPPER_OBJECT_M) < 1e-9
        assert _gripper(sock, "SET POS 0") == "ack"
        assert wait_until(lambda: _gripper(sock, "GET OBJ") == "OBJ 3\n", 2.0)
        assert _gripper(sock, "GET POS\nGET FLT") == "POS 0\nFLT 0\n"  # batched GETs answer in one packet


def test_reconnect_stops_running_script_with_255_and_dashboard_stop(cell):
    assert cell.c.isProgramRunning()
    cell.c.disconnect()
    time.sleep(0.1)
    assert cell.emulator.state().runtime_state == 2  # the program outlives its client
    before = len(cell.emulator.log_messages())
    assert_listening(cell.host)
    t = time.monotonic()
    cell.c = rtde_control.RTDEControlInterface(cell.host)
    assert time.monotonic() - t < 2.0
    new_lines = cell.emulator.log_messages()[before:]
    assert any("stopScript" in line for line in new_lines)
    assert any("dashboard: stop" in line for line in new_lines)
    assert cell.c.isProgramRunning()
    assert cell.c.moveJ(Q_WORK, 3.0, 6.0)


def test_script_intake_refuses_other_programs(cell):
    with socket.create_connection((cell.host, 30002), timeout=2.0) as sock:
        sock.sendall(b"def my_prog():\n  movej([0,0,0,0,0,0])\nend\n")
        sock.sendall(b"set_standard_digital_out(1, True)\n")
        time.sleep(0.2)
    lines = cell.emulator.log_messages()
    assert any("'my_prog' refused" in line for line in lines)
    assert any("statement outside a program refused" in line for line in lines)
    assert cell.c.isProgramRunning()  # the running rtde_control program is untouched


def test_two_cells_side_by_side_with_upper_range_registers(cell):
    other = ControllerProcess(HOST_2)
    other.start()
    clients = []
    try:
        assert_listening(HOST_2)
        flags = (
            rtde_control.RTDEControlInterface.FLAG_UPLOAD_SCRIPT
            | rtde_control.RTDEControlInterface.FLAG_UPPER_RANGE_REGISTERS
        )
        c2 = rtde_control.RTDEControlInterface(HOST_2, -1.0, flags)
        clients.append(c2)
        r2 = rtde_receive.RTDEReceiveInterface(HOST_2, -1.0, [], False, True)
        clients.append(r2)
        assert other.state().register_offset == 24
        target_1 = (np.array(Q_WORK) + 0.1).tolist()
        target_2 = (np.array(Q0) - 0.2).tolist()
        results = []
        threads = [
            threading.Thread(target=lambda: results.append(cell.c.moveJ(target_1, 1.0, 2.0))),
            threading.Thread(target=lambda: results.append(c2.moveJ(target_2, 1.0, 2.0))),
        ]
        for th in threads:
            th.start()
        for th in threads:
            th.join(10.0)
        assert results == [True, True]
        assert wait_until(lambda: np.allclose(cell.r.getActualQ(), target_1) and np.allclose(r2.getActualQ(), target_2))
        assert np.allclose(c2.getForwardKinematics(), r2.getActualTCPPose(), atol=1e-9)
    finally:
        for client in clients:
            client.disconnect()
        other.stop()


def test_stream_and_query_round_trip_work(cell, record_property):
    """The stream delivers consecutive controller ticks and commands answer. Rates and latencies are figures for
    ``sygrid bench sim``, not assertions here: on a loaded CI machine they measure the machine."""
    with RtdeProbe(cell.host) as probe:
        assert probe.negotiate()
        probe.setup_outputs(["timestamp", "actual_q", "actual_TCP_pose", "runtime_state"], 500.0)
        assert probe.start()
        timing = probe.stream_timing(1.0)
        assert probe.pause()
    round_trips = []
    for _ in range(50):
        t = time.perf_counter()
        assert len(cell.c.getForwardKinematics()) == 6
        round_trips.append(time.perf_counter() - t)
    figures = {**timing, "fk_p50_ms": float(np.percentile(round_trips, 50)) * 1e3}
    for key, value in figures.items():
        record_property(key, value)
    assert timing["packages"] > 50


def _task_niceness(pid: int) -> list[int]:
    """The niceness of each thread of a process (field 19 of /proc/PID/task/TID/stat)."""
    values = []
    for stat in Path(f"/proc/{pid}/task").glob("*/stat"):
        fields = stat.read_text().rsplit(")", 1)[1].split()  # after "pid (comm)": field 3 onwards
        values.append(int(fields[19 - 3]))
    return values


@pytest.mark.skipif(not Path("/proc/self/task").exists(), reason="Linux /proc")
def test_the_emulator_runs_every_thread_ahead_of_the_program_it_serves(cell):
    """The emulator's process raises the priority of all its threads, so the tick, the physics stepper and
    the protocol servers all run ahead of the client program's perception where the process may (root here in CI);
    else every thread stays at the program's niceness."""
    expected = EMULATOR_NICENESS if os.geteuid() == 0 else os.getpriority(os.PRIO_PROCESS, 0)
    niceness = _task_niceness(cell.emulator.pid)
    assert len(niceness) >= 4  # the main thread, the tick, the servers' threads
    assert set(niceness) == {expected}


def test_a_refused_priority_leaves_the_niceness_and_says_why(monkeypatch, caplog):
    def refuse(*args: object) -> None:
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(os, "setpriority", refuse)
    now = os.getpriority(os.PRIO_PROCESS, 0)
    with caplog.at_level("WARNING"):
        assert raise_priority(now - 1) is False
    assert f"runs at niceness {now}, not {now - 1}" in caplog.text and "Operation not permitted" in caplog.text
    assert raise_priority(now) is True  # already there: nothing to ask for
