"""A minimal RTDE client for probing a controller (emulated or real): handshakes, output streaming with arrival
times, input packages, and raw messages for protocol tests. Not a replacement for ur_rtde.

    with RtdeProbe("127.0.0.2") as probe:
        probe.setup_outputs(["timestamp", "actual_q"], 500.0)
        probe.start()
        rates = probe.stream_timing(2.0)
"""

from __future__ import annotations

import socket
import struct
import time

import numpy as np

from sim.controller import rtde_wire as wire
from sim.controller.rtde_names import recipe_struct, type_width


class RtdeProbe:
    def __init__(self, host: str, port: int = 30004, timeout_s: float = 3.0) -> None:
        self.sock = socket.create_connection((host, port), timeout=timeout_s)
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._reader = wire.FrameReader()
        self._queue: list[tuple[int, bytes]] = []
        self.output_names: list[str] = []
        self.output_types: list[str] = []
        self._output_struct: struct.Struct | None = None

    def __enter__(self) -> RtdeProbe:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self.sock.close()

    # --- raw messages --------------------------------------------------------------------------------------
    def send(self, msg_type: int, payload: bytes = b"") -> None:
        self.sock.sendall(wire.frame(msg_type, payload))

    def receive(self, timeout_s: float = 3.0) -> tuple[int, bytes]:
        """The next message, or ``TimeoutError``."""
        deadline = time.monotonic() + timeout_s
        while not self._queue:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise TimeoutError(f"no RTDE message within {timeout_s:g} s")
            self.sock.settimeout(remaining)
            data = self.sock.recv(65536)
            if not data:
                raise ConnectionError("controller closed the RTDE connection")
            self._queue.extend(self._reader.feed(data))
        return self._queue.pop(0)

    def request(self, msg_type: int, payload: bytes = b"", timeout_s: float = 3.0) -> bytes:
        """Sends a request and returns the payload of the first reply of the same type (skipping data packages)."""
        self.send(msg_type, payload)
        deadline = time.monotonic() + timeout_s
        while True:
            reply_type, reply = self.receive(max(deadline - time.monotonic(), 0.001))
            if reply_type == msg_type:
                return reply

    # --- handshakes ----------------------------------------------------------------------------------------
    def negotiate(self, version: int = wire.PROTOCOL_VERSION) -> bool:
        return self.request(wire.REQUEST_PROTOCOL_VERSION, struct.pack(">H", version)) == b"\x01"

    def controller_version(self) -> tuple[int, ...]:
        return struct.unpack(">IIII", self.request(wire.GET_URCONTROL_VERSION))

    def setup_outputs(self, names: list[str], frequency_hz: float = 500.0) -> tuple[int, list[str]]:
        reply = self.request(wire.SETUP_OUTPUTS, struct.pack(">d", frequency_hz) + (",".join(names) + ",").encode())
        types = reply[1:].decode().split(",")
        if "NOT_FOUND" not in types:
            self.output_names, self.output_types = names, types
            self._output_struct = recipe_struct(types)
        return reply[0], types

    def setup_inputs(self, names: list[str]) -> tuple[int, list[str]]:
        reply = self.request(wire.SETUP_INPUTS, (",".join(names) + ",").encode())
        return reply[0], reply[1:].decode().split(",")

    def start(self) -> bool:
        return self.request(wire.START) == b"\x01"

    def pause(self) -> bool:
        return self.request(wire.PAUSE) == b"\x01"

    def send_inputs(self, recipe_id: int, body: bytes) -> None:
        self.send(wire.DATA_PACKAGE, bytes([recipe_id]) + body)

    # --- data packages -------------------------------------------------------------------------------------
    def decode(self, payload: bytes) -> dict[str, object]:
        """Decodes one output package with the declared types."""
        if self._output_struct is None:
            raise RuntimeError("no valid output recipe; call setup_outputs first")
        flat = self._output_struct.unpack_from(payload, 1)
        out: dict[str, object] = {}
        i = 0
        for name, type_name in zip(self.output_names, self.output_types, strict=True):
            width = type_width(type_name)
            out[name] = flat[i] if width == 1 else flat[i : i + width]
            i += width
        return out

    def next_state(self, timeout_s: float = 3.0) -> dict[str, object]:
        while True:
            msg_type, payload = self.receive(timeout_s)
            if msg_type == wire.DATA_PACKAGE:
                return self.decode(payload)

    def stream_timing(self, duration_s: float) -> dict[str, float]:
        """Receives for ``duration_s`` and reports rate [Hz] and inter-package gaps (p50/p99/max [ms]) measured at
        arrival, plus how many controller timestamps were skipped or repeated."""
        arrivals, stamps = [], []
        end = time.monotonic() + duration_s
        while time.monotonic() < end:
            msg_type, payload = self.receive(3.0)
            if msg_type != wire.DATA_PACKAGE:
                continue
            arrivals.append(time.perf_counter())
            if "timestamp" in self.output_names:
                stamps.append(self.decode(payload)["timestamp"])
        gaps_ms = np.diff(arrivals) * 1e3
        steps = np.round(np.diff(stamps) / 0.002) if len(stamps) > 1 else np.zeros(0)
        return {
            "packages": float(len(arrivals)),
            "rate_hz": (len(arrivals) - 1) / (arrivals[-1] - arrivals[0]) if len(arrivals) > 1 else 0.0,
            "gap_p50_ms": float(np.percentile(gaps_ms, 50)) if len(gaps_ms) else float("nan"),
            "gap_p99_ms": float(np.percentile(gaps_ms, 99)) if len(gaps_ms) else float("nan"),
            "gap_max_ms": float(gaps_ms.max()) if len(gaps_ms) else float("nan"),
            "skipped_ticks": float(np.sum(steps[steps > 1] - 1)),
        }
