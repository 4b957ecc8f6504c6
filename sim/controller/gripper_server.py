"""A Robotiq 2F-85 URCap-style gripper socket (port 63352) driving the backend's gripper.

ASCII commands, one per line: ``SET VAR n [VAR n ...]`` answers ``ack`` (no newline, as the URCap does; ur_rtde
compares it exactly), ``GET VAR`` answers ``VAR n`` and a newline. Several ``GET`` lines in one packet get their
answers in one packet. Values are 0-255: ``POS`` 0 = open (85 mm) .. 255 = closed (0 mm), ``SPE`` 20-150 mm/s,
``FOR`` 20-235 N. ``STA``: 0 reset, 1 activating, 3 active. ``OBJ``: 0 moving, 1 stopped on an object while
opening, 2 while closing, 3 at the requested position. ``FLT`` is always 0.

Every line gets an answer: a ``SET`` value must be a decimal integer (an optional sign, then digits) and is clamped to
0-255; an unknown variable, a value that is not an integer or a line that is neither form answers ``?`` (a ``SET``
with any bad pair changes nothing). A line longer than ``tcp_service.MAX_LINE_BYTES`` answers ``? line longer than N
bytes; closing`` and the connection is closed.
"""

from __future__ import annotations

import logging
import re
import threading
import time

from sim.controller.backend import GRIPPER_STROKE_M
from sim.controller.stepper import BackendRunner
from sim.controller.tcp_service import MAX_LINE_BYTES, Connection, LineTooLongError, TcpService
from sygrid.robots import gripper_2f85

log = logging.getLogger(__name__)

ACTIVATION_S = 0.1  # time from SET ACT 1 until STA reads 3
_SPEED_M_S = gripper_2f85.SPEED_RANGE_M_S
_FORCE_N = gripper_2f85.FORCE_RANGE_N
_VARIABLES = ("ACT", "GTO", "ATR", "ARD", "MOD", "POS", "SPE", "FOR", "STA", "PRE", "OBJ", "FLT")
_INTEGER = re.compile(r"[+-]?[0-9]{1,12}")  # a SET value; longer numbers are refused, not clamped


def position_to_width(pos: int) -> float:
    return GRIPPER_STROKE_M * (1.0 - min(max(pos, 0), 255) / 255.0)


def width_to_position(width_m: float) -> int:
    return round(255.0 * (1.0 - min(max(width_m, 0.0), GRIPPER_STROKE_M) / GRIPPER_STROKE_M))


class GripperServer:
    def __init__(self, host: str, port: int, runner: BackendRunner) -> None:
        self._runner = runner
        self._lock = threading.Lock()
        self.registers = {name: 0 for name in _VARIABLES}
        self.registers.update(SPE=255, FOR=255)
        self._activated_at: float | None = None
        self._commanded_width_m: float | None = None
        self.service = TcpService("gripper", host, port, self._serve)

    def start(self) -> None:
        self.service.start()

    def stop(self) -> None:
        self.service.stop()

    def _serve(self, conn: Connection) -> None:
        try:
            for batch in self.service.lines(conn, encoding="ascii"):
                if not conn.send_blocking("".join(self.handle(line) for line in batch).encode()):
                    return
        except LineTooLongError:
            log.warning("%r sent a line longer than %d bytes; answered and closed", conn, MAX_LINE_BYTES)
            conn.close_after_reply(f"? line longer than {MAX_LINE_BYTES} bytes; closing\n".encode())

    def handle(self, line: str) -> str:
        """The reply to one command line (public for tests)."""
        words = line.split()
        verb = words[0].upper()
        with self._lock:
            if verb == "GET" and len(words) == 2:
                name = words[1].upper()
                if name not in self.registers:
                    log.warning("gripper: GET of unknown variable %r (known: %s)", name, ", ".join(_VARIABLES))
                    return f"{name} ?\n"
                return f"{name} {self._read(name)}\n"
            if verb == "SET" and len(words) >= 3 and len(words) % 2 == 1:
                pairs = list(zip(words[1::2], words[2::2], strict=True))
                for name, value in pairs:
                    if name.upper() not in self.registers or not _INTEGER.fullmatch(value):
                        log.warning("gripper: bad SET %r (variables: %s, values 0-255)", line, ", ".join(_VARIABLES))
                        return "?"
                for name, value in pairs:
                    self._write(name.upper(), min(max(int(value), 0), 255))
                return "ack"
        log.warning("gripper: cannot parse %r (expected 'SET VAR n ...' or 'GET VAR')", line)
        return "?"

    def _write(self, name: str, value: int) -> None:
        regs = self.registers
        if name == "ACT":
            if value and not regs["ACT"]:
                self._activated_at = time.monotonic()
            if not value:
                self._activated_at = None
                regs["GTO"] = 0
        regs[name] = value
        if name in ("POS", "GTO", "SPE", "FOR", "ACT") and regs["ACT"] and regs["GTO"]:
            regs["PRE"] = regs["POS"]
            width = position_to_width(regs["POS"])
            speed = _SPEED_M_S[0] + (_SPEED_M_S[1] - _SPEED_M_S[0]) * regs["SPE"] / 255.0
            force = _FORCE_N[0] + (_FORCE_N[1] - _FORCE_N[0]) * regs["FOR"] / 255.0
            self._runner.call(lambda: self._runner.backend.set_gripper(width, speed, force))
            self._commanded_width_m = width

    def _read(self, name: str) -> int:
        regs = self.registers
        if name == "STA":
            if self._activated_at is None:
                return 0
            return 3 if time.monotonic() - self._activated_at >= ACTIVATION_S else 1
        sample = self._runner.latest()
        if name == "POS":
            return width_to_position(sample.gripper_width_m)
        if name == "OBJ":
            if not regs["GTO"] or not regs["ACT"]:
                return 0
            in_flight = (
                self._commanded_width_m is not None and abs(sample.gripper_target_m - self._commanded_width_m) > 1e-9
            )
            if in_flight or sample.gripper_moving:
                return 0  # the command has not reached the backend yet, or the fingers are moving
            if sample.gripper_object_detected:
                return 2 if regs["PRE"] > width_to_position(sample.gripper_width_m) else 1
            return 3
        return regs[name]
