"""Force-limited motion: the emulator's moveUntilContact, toolContact and forceMode (``sim.controller.force``) from
the measured TCP wrench, driven by the stock ur_rtde client, and ``URRobot``'s force-limited moves
(``robot.ur_force``) over them; in the MuJoCo cell the press stops on a part with a bounded force and the drag in
force mode moves it. Addresses: 127.0.0.33 (kinematic arm above a stiff surface), 127.0.0.34 (MuJoCo cell)."""

from __future__ import annotations

import socket
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from sim.controller.arm import ArmController
from sim.controller.force import CONTACT_FORCE_N, tool_contact_steps
from sygrid.robots import gripper_2f85
from sygrid.robots.kinematics import forward_kinematics
from sygrid.transforms import make_T

rtde_control = pytest.importorskip("rtde_control")
rtde_receive = pytest.importorskip("rtde_receive")

from robot.ur import URRobot  # noqa: E402
from robot.ur_config import URConfig, WorkspaceBox  # noqa: E402
from robot.ur_errors import MotionRefusedError, NoContactError, OutsideWorkspaceError  # noqa: E402
from sim.controller import ControllerProcess  # noqa: E402
from tests.emulator_recovery import unlock_and_restart  # noqa: E402

HOST, MUJOCO_HOST = "127.0.0.33", "127.0.0.34"
Q_WORK = np.array([0.3, -1.2, 1.4, -1.8, -1.5708, 0.2])
FLANGE_Z = float(forward_kinematics(Q_WORK)[2, 3])
SURFACE_Z = FLANGE_Z - 0.03  # the kinematic backend's surface, 30 mm below the flange at Q_WORK
STIFFNESS_N_M = 2e4
DOWN = np.array([0.0, 0.0, -1.0])
BOX = WorkspaceBox((-0.8, -0.6, 0.0), (0.3, 0.6, 0.8))
SCENE = Path(__file__).resolve().parents[1] / "launch" / "scenes" / "pick_bin_10_grippable.json"

pytestmark = pytest.mark.timeout(120)


# ---------------------------------------------------------------------------------------------- units


def test_tool_contact_counts_back_to_just_before_the_contact_began():
    def pushing_up(*fz: float) -> list[np.ndarray]:
        return [np.array([0.0, 0.0, f, 0.0, 0.0, 0.0]) for f in fz]

    history = pushing_up(0.0, 0.0, 1.0, 3.0, 8.0, 12.0)
    assert tool_contact_steps(history, DOWN) == 3  # back to the 1 N sample, below the onset
    assert tool_contact_steps(history, np.zeros(3)) == 3  # any direction
    assert tool_contact_steps(history, -DOWN) == 0  # the force pulls along an upward motion: no contact
    assert tool_contact_steps(pushing_up(0.0, 9.0), DOWN) == 0  # below the threshold
    assert tool_contact_steps([], DOWN) == 0
    # already touching for a long time: a move until contact that begins now counts from its own start
    pressing = pushing_up(*([20.0] * 50))
    assert tool_contact_steps(pressing, DOWN) == 49 and tool_contact_steps(pressing, DOWN, max_steps=0) == 1
    assert tool_contact_steps(pressing, DOWN, max_steps=5) == 5


def test_force_mode_presses_with_the_commanded_force_and_ends_where_it_is():
    """ArmController against a spring under the flange (ideal tracking): the compliant axis settles where the spring
    pushes back with the commanded force; the other axes do not move; ending force mode keeps the pose."""
    arm = ArmController(Q_WORK)
    surface = FLANGE_Z - 0.002

    def wrench() -> np.ndarray:
        depth = surface - forward_kinematics(arm.target_q)[2, 3]
        return np.array([0.0, 0.0, STIFFNESS_N_M * max(depth, 0.0), 0.0, 0.0, 0.0])

    arm.force_mode(np.zeros(6), np.array([0, 0, 1, 0, 0, 0]), np.array([0, 0, -12.0, 0, 0, 0]), 2, np.full(6, 0.05))
    for _ in range(1500):
        assert arm.step(0.002, 1.0, wrench()) is None
    assert wrench()[2] == pytest.approx(12.0, abs=0.2)
    moved = forward_kinematics(arm.target_q)[:3, 3] - forward_kinematics(Q_WORK)[:3, 3]
    np.testing.assert_allclose(moved[:2], 0.0, atol=1e-6)
    before = arm.target_q.copy()
    arm.end_force_mode()
    assert arm.step(0.002, 1.0, wrench()) is None
    np.testing.assert_allclose(arm.target_q, before, atol=1e-12)


# ---------------------------------------------------------------------------------------------- kinematic cell


def _listening(host: str) -> None:
    with socket.create_connection((host, 30004), timeout=2.0):
        pass


@pytest.fixture(scope="module")
def surface_cell():
    with ControllerProcess(
        HOST, backend_kwargs={"surface_z_m": SURFACE_Z, "surface_stiffness_n_m": STIFFNESS_N_M}
    ) as em:
        _listening(HOST)
        r = rtde_receive.RTDEReceiveInterface(HOST)
        c = rtde_control.RTDEControlInterface(HOST)
        try:
            yield em, r, c
        finally:
            c.disconnect()
            r.disconnect()


def _fz(r) -> float:
    return float(r.getActualTCPForce()[2])


def test_move_until_contact_stops_where_the_contact_began(surface_cell):
    _, r, c = surface_cell
    assert c.moveJ(Q_WORK.tolist(), 3.0, 6.0)
    assert _fz(r) == 0.0 and c.toolContact([0, 0, -1, 0, 0, 0]) == 0
    assert c.moveUntilContact([0, 0, -0.02, 0, 0, 0], [0, 0, -1, 0, 0, 0], 0.5)
    depth = SURFACE_Z - r.getActualTCPPose()[2]
    # back at the last step before the force rose above the onset (2 N on a 20 N/mm surface: 0.1 mm deep)
    assert -0.5e-3 < depth < 0.1e-3 and _fz(r) < 2.5
    assert c.moveJ(Q_WORK.tolist(), 3.0, 6.0)


def test_force_mode_presses_and_follows_the_programmed_motion_on_the_other_axes(surface_cell):
    _, r, c = surface_cell
    assert c.moveJ(Q_WORK.tolist(), 3.0, 6.0)
    assert c.moveUntilContact([0, 0, -0.02, 0, 0, 0], [0, 0, -1, 0, 0, 0], 0.5)
    assert c.forceMode([0.0] * 6, [0, 0, 1, 0, 0, 0], [0, 0, -14.0, 0, 0, 0], 2, [0.01, 0.01, 0.02, 0.1, 0.1, 0.1])
    end = time.monotonic() + 3.0
    while abs(_fz(r) - 14.0) > 0.2 and time.monotonic() < end:
        time.sleep(0.01)
    assert _fz(r) == pytest.approx(14.0, abs=0.2)
    c.toolContact([0, 0, -1, 0, 0, 0])  # realtime: the client reads the result register without waiting for it
    time.sleep(0.02)
    assert c.toolContact([0, 0, -1, 0, 0, 0]) > 0
    pose = r.getActualTCPPose()
    target = list(pose)
    target[0] += 0.02
    assert c.moveL(target, 0.05, 0.5)
    assert r.getActualTCPPose()[0] == pytest.approx(target[0], abs=1e-4)
    assert _fz(r) == pytest.approx(14.0, abs=1.0)
    assert c.forceModeStop()
    z = r.getActualTCPPose()[2]
    time.sleep(0.1)
    assert r.getActualTCPPose()[2] == pytest.approx(z, abs=1e-6)  # force mode off: the arm stays where it is
    assert c.moveJ(Q_WORK.tolist(), 3.0, 6.0)


def test_pressing_past_the_force_limit_is_a_protective_stop_and_the_arm_may_then_back_off(surface_cell):
    """A position-controlled move into the surface stops where the TCP force passes the 150 N limit (7.5 mm deep on
    20 N/mm), though nothing collides with the arm; once unlocked, the arm may move back out although the force is
    still above the limit there."""
    em, r, c = surface_cell
    assert c.moveJ(Q_WORK.tolist(), 3.0, 6.0)
    target = r.getActualTCPPose()
    target[2] = SURFACE_Z - 0.015  # 300 N deep
    assert not c.moveL(target, 0.02, 0.5)
    state = em.state()
    assert state.protective_stopped and "TCP force" in state.last_error and "force limit" in state.last_error
    depth = SURFACE_Z - r.getActualTCPPose()[2]
    assert 7.5e-3 <= depth < 9e-3 and 150.0 < _fz(r) < 180.0
    unlock_and_restart(HOST, c)
    assert c.moveJ(Q_WORK.tolist(), 1.0, 2.0) and not em.state().protective_stopped
    assert _fz(r) == 0.0


@pytest.fixture(scope="module")
def robot(surface_cell):
    config = URConfig(host=HOST, workspace=BOX, recovery_timeout_s=10.0)
    with URRobot(config) as robot:
        yield robot


def test_urrobot_move_until_contact_then_pressing_move(robot):
    robot.move_j(Q_WORK, 3.0, 6.0)
    contact = robot.move_until_contact(DOWN, 0.02, 0.05)
    assert contact.travel_m == pytest.approx(0.03, abs=5e-4)
    assert CONTACT_FORCE_N < contact.peak_force_n < 40.0
    T = robot.T_base_tcp()
    T[0, 3] += 0.02
    result = robot.move_l_pressing(T, DOWN, 12.0, 0.05)
    assert result.reached and abs(result.T_base_tcp[0, 3] - T[0, 3]) < 1e-4
    assert robot._link.rtde_r.getActualTCPForce()[2] == pytest.approx(12.0, abs=1.0)
    robot.move_j(Q_WORK, 3.0, 6.0)  # force mode ended: a plain move leaves the surface
    assert robot._link.rtde_r.getActualTCPForce()[2] == 0.0


def _line_into_the_surface(robot, *args, **kwargs):
    """From the work pose, a straight line aimed 15 mm into the kinematic surface: (its target, the result)."""
    robot.move_j(Q_WORK, 3.0, 6.0)
    T = robot.T_base_tcp()
    T[2, 3] = SURFACE_Z - 0.015
    return T, robot.move_l(T, *args, **kwargs)


def test_a_guarded_move_at_the_picks_approach_speed_stops_on_contact_well_below_the_force_limit(robot, surface_cell):
    """The picker's approach (0.25 m/s, 1.2 m/s2) aimed 15 mm into the stiff surface, guarded at 30 N: the arm stops
    a few millimetres in, with no protective stop (unguarded, the same move is one: the test above), and a plain
    move leaves. A guard that is not a positive force is refused before anything moves."""
    em = surface_cell[0]
    T, result = _line_into_the_surface(robot, 0.25, 1.2, max_force_n=30.0)
    depth = SURFACE_Z - result.T_base_tcp[2, 3]
    assert not result.reached and 30.0 < result.contact_force_n < 60.0
    assert 0.0015 < depth < 0.0075 and not em.state().protective_stopped  # 150 N is 7.5 mm deep
    robot.move_j(Q_WORK, 3.0, 6.0)
    with pytest.raises(MotionRefusedError, match="max_force_n"):
        robot.move_l(T, 0.25, 1.2, max_force_n=0.0)
    up = robot.T_base_tcp()
    up[2, 3] += 0.01
    free = robot.move_l(up, 0.25, 1.2, max_force_n=30.0)  # through the air: nothing stops it
    assert free.reached and free.contact_force_n is None


def test_at_the_final_approach_speed_a_guarded_move_stops_just_past_the_guard(robot, surface_cell):
    """The picker's last stretch (0.05 m/s): the same guard stops the arm far closer to where the force passed it
    than at the approach speed (stop distance v^2 / 2a + a tick of travel): a fraction of a millimetre past it."""
    em = surface_cell[0]
    _, result = _line_into_the_surface(robot, 0.05, 1.2, max_force_n=30.0)
    depth = SURFACE_Z - result.T_base_tcp[2, 3]
    assert not result.reached and 30.0 < result.contact_force_n < 40.0
    # where it came to rest the surface pushes back with under 50 N (at 0.25 m/s: over 100 N, near the 150 N limit)
    assert 0.0 < depth * STIFFNESS_N_M < 50.0 and not em.state().protective_stopped
    robot.move_j(Q_WORK, 3.0, 6.0)


def test_the_controllers_contact_detection_stops_a_move_where_the_contact_began(robot, surface_cell):
    """``move_l(stop_on_contact=True)``: ur_rtde's start/read/stopContactDetection. The controller stops the arm on
    the tick the contact shows and moves it back to where it began: at the approach's 0.25 m/s it ends within a
    millimetre of the surface, pressing on it with far less than the client-side guard's stop left; a move
    through the air reaches its target."""
    em = surface_cell[0]
    _, result = _line_into_the_surface(robot, 0.25, 1.2, stop_on_contact=True)
    depth = SURFACE_Z - result.T_base_tcp[2, 3]
    assert not result.reached and result.contact_force_n is not None
    assert depth < 0.001 and not em.state().protective_stopped
    assert robot._link.rtde_r.getActualTCPForce()[2] < 20.0
    up = robot.T_base_tcp()
    up[2, 3] += 0.01
    free = robot.move_l(up, 0.25, 1.2, stop_on_contact=True)
    assert free.reached and free.contact_force_n is None
    robot.move_j(Q_WORK, 3.0, 6.0)


def test_urrobot_contact_moves_are_checked_and_a_missed_contact_stops_the_program(robot):
    robot.move_j(Q_WORK, 3.0, 6.0)
    with pytest.raises(MotionRefusedError, match="speed_m_s"):
        robot.move_until_contact(DOWN, 0.5, 0.05)
    with pytest.raises(OutsideWorkspaceError):
        robot.move_until_contact(DOWN, 0.02, 1.0)
    with pytest.raises(MotionRefusedError, match="force_n"):
        robot.move_l_pressing(robot.T_base_tcp(), DOWN, 500.0)
    with pytest.raises(NoContactError, match="met nothing within 20 mm"):
        robot.move_until_contact(DOWN, 0.02, 0.02)  # the surface is 30 mm down
    assert robot.T_base_tcp()[2, 3] > SURFACE_Z  # stopped short of it
    robot.recover()
    robot.move_j(Q_WORK, 3.0, 6.0)


# ---------------------------------------------------------------------------------------------- MuJoCo cell


@pytest.fixture(scope="module")
def part_cell():
    """The MuJoCo cell with one spur gear lying flat in the middle of the bin (the scene's other parts parked)."""
    from sim.cell_config import CellConfig
    from sygrid.objects import builtin_part

    em = ControllerProcess(
        MUJOCO_HOST, backend="mujoco", backend_kwargs={"parts_scene": str(SCENE), "parts_seed": 0},
        start_timeout_s=120.0,
    )  # fmt: skip
    with em:
        names = em.part_names()
        gear = next(i for i, n in enumerate(names) if n.endswith("spur_gear"))
        em.park_parts([i for i in range(len(names)) if i != gear])
        T = em.part_poses()
        height = builtin_part("spur_gear").extents_m[2]
        T[gear] = CellConfig().T_world_bin @ make_T(t=(0.0, 0.0, height / 2 + 0.0005))
        em.place_parts(T, held=[i for i in range(len(names)) if i != gear])
        time.sleep(0.3)
        _listening(MUJOCO_HOST)
        # The emulator paces force-sensitive motion by the physics, which runs slower than real time on a loaded
        # machine (pads pressing on the gear's convex pieces): the wall-clock motion deadlines derived from the
        # moves' durations get a generous margin here.
        config = URConfig(
            host=MUJOCO_HOST, workspace=BOX, T_flange_tcp=make_T(t=(0.0, 0.0, 0.145)), motion_timeout_margin_s=30.0
        )
        with URRobot(config) as robot:
            yield em, robot, gear, height


def test_press_on_a_part_stops_on_contact_with_a_bounded_force_and_the_pressing_drag_moves_it(part_cell):
    em, robot, gear, height = part_cell
    T_world_gear = em.part_poses()[gear]
    top = T_world_gear[:3, 3] + np.array([0.0, 0.0, height / 2])  # world = base in the default cell
    T_above = make_T(np.diag([1.0, -1.0, -1.0]), top + np.array([0.0, 0.0, 0.03 + gripper_2f85.PAD_LENGTH_M / 2]))
    _close_fingers()
    robot.move_j_to_pose(T_above, 2.0, 3.0)
    forces: list[float] = []
    done = threading.Event()

    def watch() -> None:
        while not done.is_set():
            forces.append(float(np.linalg.norm(robot._link.rtde_r.getActualTCPForce()[:3])))
            time.sleep(0.002)

    watcher = threading.Thread(target=watch)
    watcher.start()
    try:
        contact = robot.move_until_contact(DOWN, 0.01, 0.05)
    finally:
        done.set()
        watcher.join()
    state = em.state()
    assert not state.protective_stopped, state.last_error
    # stopped at the gear's top (the closed pads' tips, half a pad below the TCP at the pads' centre)
    pad_tip_z = contact.T_base_tcp[2, 3] - gripper_2f85.PAD_LENGTH_M / 2
    assert pad_tip_z == pytest.approx(top[2], abs=2e-3), (pad_tip_z, top[2])
    assert max(forces) < 80.0 and contact.peak_force_n < 80.0  # bounded, far below the 150 N protective stop
    moved = em.part_poses()[gear][:3, 3] - T_world_gear[:3, 3]
    assert np.linalg.norm(moved) < 1e-3  # the press did not push the gear around
    # The drag: force mode pressing down with 25 N while the TCP moves 30 mm along +y; the gear follows (the pads
    # slip on it for part of the way).
    T_end = robot.T_base_tcp()
    T_end[1, 3] += 0.03
    robot.move_l_pressing(T_end, DOWN, 25.0, 0.03)
    dragged = em.part_poses()[gear][:3, 3] - T_world_gear[:3, 3]
    assert dragged[1] > 0.015, dragged
    assert not em.state().protective_stopped
    T_up = robot.T_base_tcp()
    T_up[2, 3] += 0.05
    robot.move_l(T_up, 0.1)


def _close_fingers() -> None:
    """Closes the gripper through the emulator's URCap socket (the two pads together are the paddle)."""
    with socket.create_connection((MUJOCO_HOST, 63352), timeout=2.0) as sock:
        for line in ("SET ACT 1", "SET GTO 1", "SET POS 255 SPE 255 FOR 50"):
            sock.sendall((line + "\n").encode())
            assert sock.recv(16) == b"ack"
    time.sleep(1.0)
