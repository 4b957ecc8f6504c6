"""Script intake on ports 30001-30003: gathers URScript text, cuts it into programs and starts the ones the
emulator can run. Nothing is ever sent back on these ports (ur_rtde never reads 30003; primary/secondary state
streams on 30001/30002 are not emulated).

A program is a column-0 ``def NAME():`` (or ``sec``) block closed by a column-0 ``end``. ``rtde_control`` is run
natively (``program.py``), with the register offset read from the injected ``# int register offset`` line. Any
other program, or a bare statement outside a block, is refused with a logged error: the emulator does not
interpret URScript.
"""

from __future__ import annotations

import dataclasses
import logging
import re
from collections.abc import Callable

from sim.controller.tcp_service import Connection, TcpService, start_all

log = logging.getLogger(__name__)

_BLOCK_START = re.compile(r"^(def|sec)\s+([A-Za-z_]\w*)\s*\(\s*\)\s*:")
_INT_OFFSET = re.compile(r"reg_offset_int\s*=\s*#\s*int register offset\s*\n\s*(\d+)")
_MAX_SCRIPT_BYTES = 4 * 1024 * 1024
RTDE_CONTROL = "rtde_control"


@dataclasses.dataclass(frozen=True)
class UploadedScript:
    name: str
    text: str
    register_offset: int


class ScriptParser:
    """Line-oriented: feed text as it arrives, get complete programs back."""

    def __init__(self) -> None:
        self._partial = ""
        self._block: list[str] | None = None
        self._name = ""
        self.refused: list[str] = []

    def feed(self, text: str) -> list[UploadedScript]:
        self._partial += text
        *lines, self._partial = self._partial.split("\n")
        programs = []
        if self._block is not None and self._partial.rstrip() == "end":  # closing line sent without its newline
            lines.append(self._partial)
            self._partial = ""
        for line in lines:
            program = self._line(line)
            if program is not None:
                programs.append(program)
        return programs

    def _line(self, line: str) -> UploadedScript | None:
        if self._block is None:
            match = _BLOCK_START.match(line)
            if match:
                self._block, self._name = [line], match.group(2)
            elif line.strip() and not line.lstrip().startswith("#"):
                self.refused.append(line.strip())
                log.error(
                    "script intake: statement outside a program refused (the emulator does not interpret "
                    "URScript): %.80r",
                    line.strip(),
                )
            return None
        self._block.append(line)
        if line.rstrip() != "end":
            return None
        text = "\n".join(self._block) + "\n"
        self._block = None
        match = _INT_OFFSET.search(text)
        return UploadedScript(self._name, text, int(match.group(1)) if match else 0)


class ScriptIntake:
    """The script ports; ``on_program`` is called with every complete ``rtde_control`` program."""

    def __init__(self, host: str, ports: tuple[int, ...], on_program: Callable[[UploadedScript], None]) -> None:
        self._on_program = on_program
        self.services = [TcpService(f"script-{port}", host, port, self._serve) for port in ports]
        self.refused_programs: list[str] = []
        self._stopping = False

    def start(self) -> None:
        start_all(self.services)

    def stop(self) -> None:
        self._stopping = True
        for service in self.services:
            service.stop()

    def _serve(self, conn: Connection) -> None:
        parser = ScriptParser()
        received = 0
        while not self._stopping:
            data = conn.recv()
            if data is None:
                continue
            if not data:
                break
            received += len(data)
            if received > _MAX_SCRIPT_BYTES:
                log.error("%r sent more than %d bytes without completing a program; closing", conn, _MAX_SCRIPT_BYTES)
                return
            for script in parser.feed(data.decode("utf-8", errors="replace")):
                if script.name == RTDE_CONTROL:
                    self._on_program(script)
                else:
                    self.refused_programs.append(script.name)
                    log.error(
                        "script intake: program %r refused: only the ur_rtde %r program is run (natively); "
                        "the emulator does not interpret URScript",
                        script.name,
                        RTDE_CONTROL,
                    )
