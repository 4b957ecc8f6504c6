"""The dashboard server (port 29999): one text line in, one line out, as PolyScope 5 answers.

ur_rtde compares some replies exactly (``stop`` -> ``Stopped``, ``unlock protective stop`` -> ``Protective stop
releasing``, ``play`` -> ``Starting program``, ``pause`` -> ``Pausing program``), parses ``PolyscopeVersion`` with
a ``\\d+.\\d+.\\d+.\\d+`` regex and wants digits only from ``get serial number``. ``stop`` always answers
``Stopped`` (the client's reuploadScript sends it after the program has already ended). A line longer than
``tcp_service.MAX_LINE_BYTES`` is answered ``could not understand: line longer than N bytes; closing`` and the
connection is closed.
"""

from __future__ import annotations

import logging
from typing import Protocol

from sim.controller.state import (
    ROBOT_MODE_IDLE,
    ROBOT_MODE_NAMES,
    ROBOT_MODE_POWER_OFF,
    ROBOT_MODE_RUNNING,
    RUNTIME_NAMES,
    RUNTIME_PLAYING,
)
from sim.controller.status import ControllerStatus
from sim.controller.tcp_service import MAX_LINE_BYTES, Connection, LineTooLongError, TcpService

log = logging.getLogger(__name__)

WELCOME = "Connected: Universal Robots Dashboard Server"
_STATE_CHANGING = frozenset(
    {"stop", "play", "pause", "unlock protective stop", "power on", "power off", "brake release", "restart safety"}
)


class DashboardHost(Protocol):
    """What the dashboard needs of the controller it serves (``EmulatedController`` has it)."""

    controller_version: tuple[int, int, int, int]
    serial_number: str

    def state(self) -> ControllerStatus: ...
    def stop_program(self, reason: str) -> None: ...
    def resume_program(self) -> bool: ...
    def pause_program(self) -> bool: ...
    def unlock_protective_stop(self) -> str: ...
    def set_robot_mode(self, mode: int) -> None: ...


class DashboardServer:
    def __init__(self, host: str, port: int, controller: DashboardHost) -> None:
        self._ctl = controller
        self.service = TcpService("dashboard", host, port, self._serve)

    def start(self) -> None:
        self.service.start()

    def stop(self) -> None:
        self.service.stop()

    def _serve(self, conn: Connection) -> None:
        if not conn.send_blocking((WELCOME + "\n").encode()):
            return
        try:
            for batch in self.service.lines(conn):
                for line in batch:
                    reply = self.reply(line)
                    log.debug("dashboard %r -> %r", line, reply)
                    if not conn.send_blocking((reply + "\n").encode()):
                        return
                    if line == "quit":
                        return
        except LineTooLongError:
            log.warning("%r sent a line longer than %d bytes; answered and closed", conn, MAX_LINE_BYTES)
            conn.close_after_reply(f"could not understand: line longer than {MAX_LINE_BYTES} bytes; closing\n".encode())

    def reply(self, line: str) -> str:
        """The reply to one command line (public for tests)."""
        ctl = self._ctl
        cmd = line.lower()
        major, minor, bugfix, build = ctl.controller_version
        version = f"{major}.{minor}.{bugfix}.{build}"
        status = ctl.state()
        if cmd in _STATE_CHANGING:
            log.info("dashboard: %s (runtime %s)", line, RUNTIME_NAMES[status.runtime_state])
        if cmd == "polyscopeversion":
            return f"URSoftware {version} (emulated)"
        if cmd == "version":
            return version
        if cmd == "get serial number":
            return ctl.serial_number
        if cmd == "get robot model":
            return "UR5"
        if cmd == "is in remote control":
            return "true"
        if cmd == "stop":
            ctl.stop_program("dashboard stop")
            return "Stopped"
        if cmd == "play":
            return "Starting program" if ctl.resume_program() else "Failed to execute: play"
        if cmd == "pause":
            return "Pausing program" if ctl.pause_program() else "Failed to execute: pause"
        if cmd == "unlock protective stop":
            return ctl.unlock_protective_stop()
        if cmd == "close safety popup":
            return "closing safety popup"
        if cmd == "close popup":
            return "closing popup"
        if cmd.startswith("popup "):
            return "showing popup"
        if cmd == "robotmode":
            return f"Robotmode: {ROBOT_MODE_NAMES.get(status.robot_mode, str(status.robot_mode))}"
        if cmd in ("safetymode", "safetystatus"):
            word = "Safetymode" if cmd == "safetymode" else "Safetystatus"
            return f"{word}: {'PROTECTIVE_STOP' if status.protective_stopped else 'NORMAL'}"
        if cmd == "running":
            return f"Program running: {'true' if status.runtime_state == RUNTIME_PLAYING else 'false'}"
        if cmd == "programstate":
            name = status.program or "<unnamed>"
            return f"{RUNTIME_NAMES[status.runtime_state]} {name}"
        if cmd == "get loaded program":
            return f"Loaded program: {status.program}" if status.program else "No program loaded"
        if cmd == "isprogramsaved":
            return f"true {status.program}" if status.program else "false"
        if cmd == "power on":
            ctl.set_robot_mode(ROBOT_MODE_IDLE)
            return "Powering on"
        if cmd == "power off":
            ctl.set_robot_mode(ROBOT_MODE_POWER_OFF)
            return "Powering off"
        if cmd == "brake release":
            ctl.set_robot_mode(ROBOT_MODE_RUNNING)
            return "Brake releasing"
        if cmd == "restart safety":
            ctl.unlock_protective_stop()
            ctl.set_robot_mode(ROBOT_MODE_POWER_OFF)
            return "Restarting safety"
        if cmd.startswith("load "):
            log.warning("dashboard: 'load' of URP programs is not supported (%s)", line)
            return f"File not found: {line[5:].strip()}"
        if cmd.startswith("addtolog "):
            log.info("dashboard log: %s", line[9:])
            return "Added log message"
        if cmd.startswith("setuserrole "):
            return f"Setting user role: {line[12:].strip()}"
        if cmd == "get operational mode":
            return "NONE"
        if cmd == "quit":
            return "Disconnected"
        if cmd == "shutdown":
            log.warning("dashboard: 'shutdown' received; the emulator keeps running (stop it from its own process)")
            return "Shutting down"
        log.warning("dashboard: unknown command %r", line)
        return f"could not understand: '{line}'"
