"""The emulator's ports against clients that misbehave: a 64 MiB line on the dashboard and gripper ports (a clear
reply, then the connection closed, after reading little of it), an RTDE client that sends requests and never reads
the replies (dropped, its buffer released), bad gripper values and malformed RTDE messages (answered, never a
traceback). The controller runs in this process on 127.0.0.83 (no other test module uses it). The stream's gaps
while a 64 MiB line arrives are measured by ``sygrid bench sim --scenarios long-line``."""

from __future__ import annotations

import contextlib
import logging
import socket
import struct
import threading
import time

import pytest

from sim.controller import EmulatedController, KinematicBackend
from sim.controller import rtde_wire as wire
from sim.controller.rtde_probe import RtdeProbe
from sim.controller.tcp_service import MAX_LINE_BYTES, MAX_PENDING_BYTES, MAX_QUEUED_BYTES, Connection

HOST = "127.0.0.83"
LONG_LINE = b"x" * (64 * 1024 * 1024) + b"\n"
pytestmark = pytest.mark.timeout(60)


@pytest.fixture(scope="module")
def controller():
    with EmulatedController(KinematicBackend(), host=HOST) as ctl:
        yield ctl


def _rss_bytes() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * 4096


def _send_and_read_reply(port: int, payload: bytes, greeting: bool) -> tuple[bytes, float]:
    """Sends ``payload`` from a thread (the server may close before it is all sent) and reads until the server
    closes; returns what came back (less the dashboard's greeting) and the seconds it took."""
    with socket.create_connection((HOST, port), timeout=10.0) as sock:
        if greeting:
            assert sock.recv(100).startswith(b"Connected: Universal Robots Dashboard Server")

        def send() -> None:
            with contextlib.suppress(OSError):  # reset once the server has answered and closed
                sock.sendall(payload)

        start = time.monotonic()
        sender = threading.Thread(target=send, daemon=True)
        sender.start()
        reply = b""
        try:
            while chunk := sock.recv(4096):
                reply += chunk
        except ConnectionResetError:
            pass
        elapsed = time.monotonic() - start
        sender.join(10.0)
    return reply, elapsed


@pytest.mark.parametrize(
    "port, greeting, expected",
    [
        (29999, True, f"could not understand: line longer than {MAX_LINE_BYTES} bytes; closing\n".encode()),
        (63352, False, f"? line longer than {MAX_LINE_BYTES} bytes; closing\n".encode()),
    ],
    ids=["dashboard", "gripper"],
)
def test_a_64_mib_line_is_answered_and_closed_without_reading_it_all(controller, port, greeting, expected):
    rss_before = _rss_bytes()
    reply, elapsed = _send_and_read_reply(port, LONG_LINE, greeting)
    assert reply == expected
    assert elapsed < 5.0  # the unbounded buffer took tens of seconds of copying
    assert _rss_bytes() - rss_before < 32 * 1024 * 1024  # it once kept the whole line (and its copies)
    # the port serves the next client as before
    with socket.create_connection((HOST, port), timeout=5.0) as sock:
        if greeting:
            sock.recv(100)
            sock.sendall(b"PolyscopeVersion\n")
            assert sock.recv(100).startswith(b"URSoftware 5.15.0.106767")
        else:
            sock.sendall(b"GET STA\n")
            assert sock.recv(100) == b"STA 0\n"


def test_bad_gripper_values_are_answered_and_the_connection_goes_on(controller, caplog):
    lines = [b"SET POS ---5", b"SET POS 1e3", b"SET POS 12345678901234", b"SET POS \xef\xbc\x95", b"SET POS",
             b"GET", b"GET POS 3", b"SET XYZ 3", b"FROB", b"SET POS 3 SPE"]  # fmt: skip
    with caplog.at_level(logging.WARNING), socket.create_connection((HOST, 63352), timeout=5.0) as sock:
        for line in lines:
            sock.sendall(line + b"\n")
            assert sock.recv(100) == b"?", line
        sock.sendall(b"SET ACT 1 GTO 1 POS -5\n")  # an integer outside 0-255 is clamped, as before
        assert sock.recv(100) == b"ack"
        sock.sendall(b"GET PRE\n")
        assert sock.recv(100) == b"PRE 0\n"
    assert not [r for r in caplog.records if r.exc_info], "a handler raised"


def test_a_connection_whose_replies_pile_up_is_closed_and_its_buffer_released(caplog):
    """``Connection.send`` on a socket whose peer never reads: stream packages are dropped whole above their limit
    (the connection stays), a reply that would pass ``MAX_QUEUED_BYTES`` closes it and frees the buffer."""
    with socket.create_server((HOST, 0)) as listener:
        peer = socket.create_connection(listener.getsockname())
        ours, address = listener.accept()
    conn = Connection(ours, address, "test")
    try:
        while conn.send(b"p" * 1000, droppable=True):
            pass
        assert not conn.closed and conn.dropped_messages == 1 and len(conn._pending) <= MAX_PENDING_BYTES + 1000
        with caplog.at_level(logging.WARNING):
            replies = 0
            while conn.send(b"r" * 19):
                replies += 1
        assert conn.closed and len(conn._pending) == 0 and replies > 0
        assert any("does not read its replies" in r.getMessage() for r in caplog.records)
    finally:
        conn.close()
        peer.close()


def test_an_rtde_client_that_never_reads_its_replies_is_dropped_and_its_buffer_released(controller, caplog):
    """The same through the RTDE port. On loopback both directions can stall when neither side reads (the kernel's
    queues full both ways, retransmissions backing off), before the emulator's queue reaches its limit: its
    memory stays bounded then too, and a stalled attempt is tried again with a new connection."""
    dropped = False
    for _ in range(3):
        sock = socket.create_connection((HOST, 30004), timeout=5.0)
        try:
            sock.sendall(wire.frame(wire.GET_URCONTROL_VERSION))
            deadline = time.monotonic() + 5.0
            while not controller.rtde.service.connections and time.monotonic() < deadline:
                time.sleep(0.01)
            (conn,) = controller.rtde.service.connections
            request = wire.frame(wire.GET_URCONTROL_VERSION) * 1000  # 19-byte replies to 3-byte requests
            sock.settimeout(0.2)
            deadline, most = time.monotonic() + 10.0, 0
            with caplog.at_level(logging.WARNING):
                while not conn.closed and time.monotonic() < deadline:
                    with contextlib.suppress(TimeoutError, OSError):
                        sock.sendall(request)
                    most = max(most, len(conn._pending))
            assert most <= MAX_QUEUED_BYTES  # bounded, dropped or not
            if conn.closed:
                assert len(conn._pending) == 0
                assert any("does not read its replies" in r.getMessage() for r in caplog.records)
                deadline = time.monotonic() + 5.0
                while controller.rtde.session_count and time.monotonic() < deadline:
                    time.sleep(0.01)
                assert controller.rtde.session_count == 0
                dropped = True
                break
        finally:
            sock.close()
        deadline = time.monotonic() + 5.0
        while controller.rtde.service.connections and time.monotonic() < deadline:
            time.sleep(0.01)
    assert dropped


def test_malformed_rtde_messages_are_answered(controller, caplog):
    with caplog.at_level(logging.WARNING), RtdeProbe(HOST) as probe:
        assert probe.negotiate()
        assert probe.request(wire.SETUP_OUTPUTS, b"\x00\x01") == b"\x00"  # no frequency: failed, recipe id 0
        too_many = ",".join(["actual_q"] * 2000).encode()  # a 96 kB package: more than one message holds
        assert probe.request(wire.SETUP_OUTPUTS, struct.pack(">d", 125.0) + too_many)[0] == 0
        recipe_id, types = probe.setup_outputs(["timestamp"], 125.0)  # the connection goes on
        assert recipe_id > 0 and types == ["DOUBLE"]
    with socket.create_connection((HOST, 30004), timeout=5.0) as sock:
        sock.sendall(struct.pack(">HB", 1, ord("V")))  # a header announcing less than itself: framing lost
        reply = b""
        while chunk := sock.recv(4096):
            reply += chunk
        size, msg_type = struct.unpack_from(">HB", reply)
        assert msg_type == wire.TEXT_MESSAGE and size == len(reply)
        assert b"malformed RTDE message" in reply
    assert not [r for r in caplog.records if r.exc_info], "a handler raised"
