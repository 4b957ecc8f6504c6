"""The emulator's RTDE and script ports spoken to byte by byte (``RtdeProbe``, raw sockets): handshakes, recipes,
NOT_FOUND, pause, input-only connections, lenient input parsing, the native program's register protocol, and a
stream that sends every tick's package, in order, while the backend stalls or another client stops reading. The
controller runs in this process (no ur_rtde client). Stream rates are measured by ``sygrid bench sim``."""

from __future__ import annotations

import itertools
import logging
import socket
import struct
import time

import numpy as np
import pytest

from sim.controller import EmulatedController, KinematicBackend
from sim.controller import rtde_wire as wire
from sim.controller.backend import StallingBackend
from sim.controller.controller import MAX_LAG_TICKS
from sim.controller.rtde_probe import RtdeProbe
from sim.controller.snapshot import TICK_S
from sim.controller.stepper import CHUNK_TARGETS
from sygrid.robots import ur5e
from sygrid.robots.kinematics import T_to_pose, forward_kinematics

HOST, HOST_SLOW, HOST_SLOWER = "127.0.0.23", "127.0.0.25", "127.0.0.26"
pytestmark = pytest.mark.timeout(30)

RTDE_CONTROL_UPPER = (
    "def rtde_control():\n"
    "    global reg_offset_float = # float register offset\n24\n"
    "    global reg_offset_int = # int register offset\n24\n"
    '    textmsg("the real script\'s body is not read: the emulator runs its loop natively")\n'
    "end\n"
)


@pytest.fixture(scope="module")
def controller():
    with EmulatedController(KinematicBackend(), host=HOST) as ctl:
        yield ctl


@pytest.fixture
def probe(controller):
    with RtdeProbe(HOST) as p:
        assert p.negotiate()
        yield p


def tick_steps(stamps: list[float]) -> np.ndarray:
    """Controller ticks between consecutive packages, from their timestamps (the emulator's own clock)."""
    return np.round(np.diff(stamps) / TICK_S)


def wait_until(predicate, timeout_s: float = 2.0) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if predicate():
            return True
        time.sleep(0.005)
    return predicate()


def test_version_handshakes(probe):
    assert probe.controller_version() == (5, 15, 0, 106767)
    assert not probe.negotiate(1)  # only protocol version 2 is served


def test_output_setup_types_not_found_and_start_before_data(probe):
    recipe_id, types = probe.setup_outputs(["timestamp", "no_such_output", "actual_q"])
    assert recipe_id == 0 and types == ["DOUBLE", "NOT_FOUND", "VECTOR6D"]
    recipe_id, types = probe.setup_outputs(["timestamp", "joint_mode", "payload_cog", "input_int_register_3"])
    assert recipe_id == 2 and types == ["DOUBLE", "VECTOR6INT32", "VECTOR3D", "INT32"]
    probe.send(wire.START)
    assert probe.receive() == (wire.START, b"\x01")  # the reply precedes the first data package
    state = probe.next_state()
    assert state["joint_mode"] == (253,) * 6 and len(state["payload_cog"]) == 3


def test_pause_is_answered_and_stops_the_stream(probe):
    probe.setup_outputs(["timestamp"], 500.0)
    assert probe.start()
    probe.next_state()
    assert probe.pause()
    time.sleep(0.05)
    probe.sock.settimeout(0.05)
    with pytest.raises((TimeoutError, socket.timeout)):
        probe.receive(0.1)


def test_frequency_is_thinned_per_connection(probe):
    probe.setup_outputs(["timestamp"], 125.0)
    assert probe.start()
    stamps = [probe.next_state()["timestamp"] for _ in range(125)]
    assert np.all(tick_steps(stamps) == 4)  # every 4th tick (8 ms), in order, none missed


def test_input_recipe_ids_count_per_connection_and_never_started_connections_apply(controller, probe):
    assert probe.setup_inputs(["input_int_register_23"])[0] == 1
    assert probe.setup_inputs(["input_int_register_23", "standard_digital_output_mask", "standard_digital_output"]) == (
        2,
        ["INT32", "UINT8", "UINT8"],
    )
    assert probe.setup_inputs(["speed_slider_mask", "no_such_input"]) == (0, ["UINT32", "NOT_FOUND"])
    with RtdeProbe(HOST) as other:
        assert other.setup_inputs(["input_double_register_20"])[0] == 1
    probe.send_inputs(2, struct.pack(">iBB", 13, 0x10, 0x10))  # never started (like RTDEIOInterface)
    assert wait_until(lambda: controller.state().digital_output_bits & 0x10)
    probe.send_inputs(2, struct.pack(">iBB", 13, 0x10, 0x00))
    assert wait_until(lambda: not controller.state().digital_output_bits & 0x10)


def test_long_input_packages_apply_their_prefix_and_short_ones_are_dropped(controller, probe, caplog):
    assert probe.setup_inputs(["input_int_register_40", "input_double_register_40"])[0] == 1
    with caplog.at_level(logging.WARNING):
        probe.send_inputs(1, struct.pack(">id", 7, 1.25) + struct.pack(">6d", *range(6)))
        assert wait_until(lambda: controller.regs.input_double[40] == 1.25)
        probe.send_inputs(1, struct.pack(">i", 9))
        time.sleep(0.05)
    assert controller.regs.input_int[40] == 7
    assert "applying the first 12" in caplog.text and "dropped" in caplog.text


def test_input_registers_read_back_as_outputs(probe):
    probe.setup_inputs(["input_int_register_41"])
    probe.setup_outputs(["input_int_register_41"])
    probe.send_inputs(1, struct.pack(">i", -42))
    assert probe.start()
    assert wait_until(lambda: probe.next_state()["input_int_register_41"] == -42)


def test_native_program_protocol_with_upper_range_registers(controller, probe):
    """Upload on 30003 (nothing is sent back there), then drive the command registers by hand: ready (1), a
    getForwardKinematics() command (43) answered with done (2) and the pose, clear, ready again."""
    with socket.create_connection((HOST, 30003), timeout=2.0) as script:
        script.sendall(RTDE_CONTROL_UPPER.encode())
        assert wait_until(lambda: controller.state().runtime_state == 2)
        assert controller.state().register_offset == 24
        script.settimeout(0.1)
        with pytest.raises((TimeoutError, socket.timeout)):
            script.recv(1)
    probe.setup_outputs(
        ["runtime_state", "output_int_register_24"] + [f"output_double_register_{24 + i}" for i in range(6)]
    )
    probe.setup_inputs(["input_int_register_24"])
    assert probe.start()
    assert wait_until(lambda: probe.next_state()["output_int_register_24"] == 1)
    probe.send_inputs(1, struct.pack(">i", 43))
    assert wait_until(lambda: probe.next_state()["output_int_register_24"] == 2)
    state = probe.next_state()
    pose = [state[f"output_double_register_{24 + i}"] for i in range(6)]
    assert np.allclose(pose, T_to_pose(forward_kinematics(ur5e.HOME_Q)))
    probe.send_inputs(1, struct.pack(">i", 0))
    assert wait_until(lambda: probe.next_state()["output_int_register_24"] == 1)
    probe.send_inputs(1, struct.pack(">i", 255))  # stopScript
    assert wait_until(lambda: probe.next_state()["runtime_state"] == 1)


def longest_run(flags: list[bool]) -> int:
    best = run = 0
    for flag in flags:
        run = run + 1 if flag else 0
        best = max(best, run)
    return best


def test_stream_sends_every_tick_while_the_backend_stalls():
    """The tick does not wait for a blocked step: the packages keep coming, one per tick, with target_q moving on
    while actual_q stays at the backend's last sample."""
    backend = StallingBackend(stall_s=0.1, every=20)
    with EmulatedController(backend, host=HOST_SLOW) as ctl, RtdeProbe(HOST_SLOW) as probe:
        probe.negotiate()
        probe.setup_outputs(["timestamp", "actual_q", "target_q"], 500.0)
        assert probe.start()
        with ctl._lock:
            ctl.arm.movej(ur5e.HOME_Q + 0.5, 0.25, 1.0)  # 2.25 s
        states = [probe.next_state() for _ in range(400)]
    assert np.all(tick_steps([s["timestamp"] for s in states]) == 1)  # every tick's package, in order
    lagging = [np.max(np.abs(np.subtract(s["target_q"], s["actual_q"]))) > 0 for s in states]
    assert any(lagging)  # actual_q trailed target_q while the backend caught up
    held = [a["actual_q"] == b["actual_q"] and a["target_q"] != b["target_q"] for a, b in itertools.pairwise(states)]
    assert longest_run(held) >= 10  # ticks went on through a stall (a stall is 50 ticks long)
    assert ctl._runner.max_advance_s >= 0.1


def test_a_backend_slower_than_real_time_slows_the_arm_and_never_drops_its_targets():
    """Every backend call takes longer than the simulated time it covers: the tick holds the motion while the backend
    trails by more than ``MAX_LAG_TICKS`` (counted in ``paced_ticks``), so the reported arm keeps within a few ticks
    of motion of the controller's target and arrives, where it once fell 0.5 s behind and jumped (dropped targets)."""
    backend = StallingBackend(stall_s=0.03, every=1)  # at most 10 targets (20 ms) per 30 ms call
    with EmulatedController(backend, host=HOST_SLOWER) as ctl, RtdeProbe(HOST_SLOWER) as probe:
        probe.negotiate()
        probe.setup_outputs(["actual_q", "target_q"], 500.0)
        assert probe.start()
        goal = ur5e.HOME_Q + 0.5
        with ctl._lock:
            ctl.arm.movej(goal, 0.25, 1.0)  # 2.25 s at the clock's pace
        states = [probe.next_state() for _ in range(1000)]  # 2 s of packages
        assert wait_until(lambda: np.allclose(ctl.state().actual_q, goal, atol=1e-6), 10.0)
        status = ctl.state()
    trail = [np.max(np.abs(np.subtract(s["target_q"], s["actual_q"]))) for s in states]
    bound = (MAX_LAG_TICKS + CHUNK_TARGETS + 5) * TICK_S * 0.25  # ticks of motion at the joint speed, rad
    assert max(trail) <= bound
    assert status.backend_dropped_targets == 0 and status.tick.paced_ticks > 100


def test_a_client_that_stops_reading_costs_the_tick_nothing(controller):
    """Its state packages pile up to the pending limit, then are dropped whole; other clients keep streaming."""
    stalled = socket.create_connection((HOST, 30004), timeout=2.0)
    stalled.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    try:
        stalled.sendall(wire.frame(wire.REQUEST_PROTOCOL_VERSION, struct.pack(">H", 2)))
        fields = ["actual_q", "actual_qd", "target_q", "target_qd", "actual_TCP_pose", "target_TCP_pose"] * 30
        stalled.sendall(wire.frame(wire.SETUP_OUTPUTS, struct.pack(">d", 500.0) + ",".join(fields).encode()))
        stalled.sendall(wire.frame(wire.START))  # large packages at 500 Hz: the kernel buffers fill, then ours

        def dropped() -> int:
            return sum(c.dropped_messages for c in list(controller.rtde.service.connections))

        assert wait_until(lambda: dropped() > 0, 10.0)
        resyncs = controller.stats.resyncs
        with RtdeProbe(HOST) as probe:
            probe.negotiate()
            probe.setup_outputs(["timestamp"], 500.0)
            before = dropped()
            assert probe.start()
            stamps = [probe.next_state()["timestamp"] for _ in range(500)]
        assert np.all(tick_steps(stamps) == 1)  # the reading client got every tick's package, in order
        assert dropped() >= before + len(stamps) - 1  # while each of those ticks dropped the stalled client's, whole
        assert controller.stats.resyncs == resyncs
    finally:
        stalled.close()
