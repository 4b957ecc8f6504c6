"""The emulator's RTDE and script ports spoken to byte by byte (``RtdeProbe``, raw sockets): handshakes, recipes,
NOT_FOUND, pause, input-only connections, lenient input parsing, the native program's register protocol, and a
stream that keeps its rate while the backend stalls. The controller runs in this process (no ur_rtde client)."""

from __future__ import annotations

import logging
import socket
import struct
import time
from collections.abc import Sequence

import numpy as np
import pytest

from sim.controller import ArmSample, EmulatedController, KinematicBackend
from sim.controller import rtde_wire as wire
from sim.controller.rtde_probe import RtdeProbe
from sygrid.robots import ur5e
from sygrid.robots.kinematics import T_to_pose, forward_kinematics

HOST, HOST_SLOW = "127.0.0.23", "127.0.0.25"
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
    timing = probe.stream_timing(1.0)
    assert 110 < timing["rate_hz"] < 140
    stamps = [probe.next_state()["timestamp"] for _ in range(3)]
    assert np.allclose(np.diff(stamps), 0.008)


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


class _StallingBackend(KinematicBackend):
    """A backend whose step sometimes blocks for ``stall_s`` (like a world whose lock a renderer holds)."""

    step_may_block = True

    def __init__(self, stall_s: float, every: int) -> None:
        super().__init__()
        self.stall_s, self.every, self.calls = stall_s, every, 0

    def advance(self, targets: Sequence[tuple[np.ndarray, np.ndarray]], steps_per_target: int) -> ArmSample:
        self.calls += 1
        if self.calls % self.every == 0:
            time.sleep(self.stall_s)
        return super().advance(targets, steps_per_target)


def test_stream_keeps_its_rate_while_the_backend_stalls(record_property):
    backend = _StallingBackend(stall_s=0.1, every=20)
    with EmulatedController(backend, host=HOST_SLOW) as ctl, RtdeProbe(HOST_SLOW) as probe:
        probe.negotiate()
        probe.setup_outputs(["timestamp", "actual_q", "target_q"], 500.0)
        assert probe.start()
        with ctl._lock:
            ctl.arm.movej(ur5e.HOME_Q + 0.5, 0.25, 1.0)  # 2.25 s
        lagging = []
        for _ in range(200):
            s = probe.next_state()
            lagging.append(np.max(np.abs(np.subtract(s["target_q"], s["actual_q"]))) > 0)
        timing = probe.stream_timing(1.5)
    for key, value in timing.items():
        record_property(f"stalling_backend_{key}", value)
    print("stream with a backend stalling 100 ms every 20 calls:", {k: round(v, 2) for k, v in timing.items()})
    assert timing["rate_hz"] > 400 and timing["skipped_ticks"] < 0.05 * timing["packages"]
    assert any(lagging)  # actual_q trailed target_q while the backend caught up
    assert ctl._runner.max_advance_s >= 0.1


def test_a_client_that_stops_reading_costs_the_tick_nothing(controller):
    """Its state packages pile up to the pending limit, then are dropped whole; other clients keep streaming."""
    stalled = socket.create_connection((HOST, 30004), timeout=2.0)
    stalled.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    try:
        stalled.sendall(wire.frame(wire.REQUEST_PROTOCOL_VERSION, struct.pack(">H", 2)))
        fields = ["actual_q", "actual_qd", "target_q", "target_qd", "actual_TCP_pose", "target_TCP_pose"] * 30
        stalled.sendall(wire.frame(wire.SETUP_OUTPUTS, struct.pack(">d", 500.0) + ",".join(fields).encode()))
        stalled.sendall(wire.frame(wire.START))  # 8.6 kB packages, 4.3 MB/s: the kernel buffers fill in about 1 s

        def dropped() -> int:
            return sum(c.dropped_messages for c in list(controller.rtde.service.connections))

        assert wait_until(lambda: dropped() > 0, 10.0)
        resyncs = controller.stats.resyncs
        with RtdeProbe(HOST) as probe:
            probe.negotiate()
            probe.setup_outputs(["timestamp"], 500.0)
            assert probe.start()
            before = dropped()
            timing = probe.stream_timing(1.0)
        assert dropped() > before + 400  # still dropping the stalled client's packages, whole
        assert timing["rate_hz"] > 400 and timing["skipped_ticks"] < 0.05 * timing["packages"]
        assert controller.stats.resyncs == resyncs
    finally:
        stalled.close()
