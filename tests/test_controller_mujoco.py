"""The emulator over the MuJoCo cell (``WorldBackend`` around ``sim.world.CellWorld``) driven by ur_rtde: tracking,
joint torques, a protective stop from a real contact with the table, and the gripper."""

from __future__ import annotations

import socket
import threading
import time

import numpy as np
import pytest

pytest.importorskip("sim.world")
rtde_control = pytest.importorskip("rtde_control")
rtde_receive = pytest.importorskip("rtde_receive")

from sim.controller import ControllerProcess  # noqa: E402
from tests.emulator_recovery import unlock_and_restart  # noqa: E402

HOST = "127.0.0.24"
ABOVE_TABLE = [-0.3, 0.3, 0.35, 0.0, 3.14159, 0.0]  # flange 35 cm above the table top, tool down, clear of bin/tray
pytestmark = pytest.mark.timeout(60)


@pytest.fixture(scope="module")
def cell():
    emulator = ControllerProcess(HOST, backend="mujoco")
    emulator.start()
    clients = []
    try:
        with socket.create_connection((HOST, 30004), timeout=2.0):
            pass
        r = rtde_receive.RTDEReceiveInterface(HOST)
        clients.append(r)
        c = rtde_control.RTDEControlInterface(HOST)
        clients.append(c)
        yield emulator, r, c
    finally:
        for client in reversed(clients):
            client.disconnect()
        emulator.stop()


def test_mujoco_arm_tracks_the_trajectory_and_reports_torques(cell):
    _, r, c = cell
    assert c.moveJ_IK(ABOVE_TABLE, 3.0, 6.0)
    errors = []
    target = (np.array(r.getActualQ()) + np.array([0.3, 0.0, 0.0, 0.0, 0.0, 0.3])).tolist()
    mover = threading.Thread(target=lambda: c.moveJ(target, 1.0, 2.0))
    mover.start()
    while mover.is_alive():
        errors.append(np.max(np.abs(np.subtract(r.getTargetQ(), r.getActualQ()))))
        time.sleep(0.005)
    # two getters, so a sample can straddle packages (2 mrad each at 1 rad/s), several when this process is
    # descheduled (a clean-clone CI run measured 6.1 mrad at the 95th percentile); the physics' own lag is the 1-2
    # ticks the stepper trails the tick. A failing PD loop would be off by 0.1 rad.
    assert np.percentile(errors, 95) < 1e-2
    assert max(errors) < 2e-2
    assert wait_steady(r, target, atol=1e-4)
    c.getJointTorques()
    time.sleep(0.01)
    torques = c.getJointTorques()
    assert abs(torques[1]) > 5.0  # the shoulder holds the arm against gravity


def wait_steady(r, target, atol: float = 1e-3, timeout_s: float = 2.0) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if np.allclose(r.getActualQ(), target, atol=atol):
            return True
        time.sleep(0.01)
    return False


def test_contact_with_the_table_is_a_protective_stop(cell):
    emulator, r, c = cell
    assert c.moveJ_IK(ABOVE_TABLE, 3.0, 6.0)
    down = list(ABOVE_TABLE)
    down[2] = -0.05
    assert not c.moveL(down, 0.05, 0.5)
    state = emulator.state()
    assert state.protective_stopped, state.last_error
    end = time.monotonic() + 1.0  # the receive connection sees it a package later than the control connection
    while not r.isProtectiveStopped() and time.monotonic() < end:
        time.sleep(0.005)
    assert r.isProtectiveStopped()
    # the arm's contact with the table, or the force limit on the TCP (the gripper's contacts summed): whichever
    # passes 150 N first
    assert ("contact force" in state.last_error or "TCP force" in state.last_error) and state.runtime_state == 4
    assert r.getActualTCPPose()[2] > 0.1  # stopped on the table with the gripper, not inside it
    unlock_and_restart(HOST, c)
    assert c.moveJ_IK(ABOVE_TABLE, 1.0, 2.0)


def test_gripper_socket_drives_the_mujoco_fingers(cell):
    emulator = cell[0]
    with socket.create_connection((HOST, 63352), timeout=2.0) as sock:
        for line in ("SET ACT 1", "SET GTO 1", "SET POS 200 SPE 255 FOR 50"):
            sock.sendall((line + "\n").encode())
            assert sock.recv(16) == b"ack"
        end = time.monotonic() + 3.0
        obj = b""
        while time.monotonic() < end:
            sock.sendall(b"GET OBJ\n")
            obj = sock.recv(16)
            if obj == b"OBJ 3\n":
                break
            time.sleep(0.05)
        assert obj == b"OBJ 3\n"
        sock.sendall(b"GET POS\n")
        assert abs(int(sock.recv(16).split()[1]) - 200) <= 2
    assert abs(emulator.state().gripper_width_m - 0.085 * (1 - 200 / 255)) < 0.5e-3
