"""How ``sygrid pick`` stops: SIGINT and SIGTERM as stop requests (``StopSignals``), the emulator process watched
while a simulated cell runs (``EmulatorWatch``), and the command's exit codes (``exit_code``, ``EXIT_CODES``).

A signal before the picker exists (the cell is starting) raises ``Interrupted`` where the program is, which unwinds
the cell's set-up; after, it only asks the picker to stop (``Picker.request_stop``: the arm is stopped, the gripper
keeps its state, the run returns "interrupted"). A second signal raises ``Interrupted`` at once (the report is
still written with what the run had).
"""

from __future__ import annotations

import logging
import signal
import threading
from collections.abc import Callable
from typing import Any

from robot.pick_report import RunReport, StopReason

log = logging.getLogger(__name__)

#: ``sygrid pick``'s exit codes (its ``--help`` epilog and docs/cell.md say the same).
EXIT_CODES = (
    "exit codes: 0 the bin was emptied or the cycle limit (--max-cycles, the cell file's max_cycles) was reached; "
    "1 the run stopped with parts left (nothing safe, given up, too many failed cycles, a gripper or robot fault, "
    "the cell's emulator process died); 2 bad input (the cell file, its models) or a cell that could not be set "
    "up; 130 interrupted by SIGINT (Ctrl-C), 143 by SIGTERM: the arm's motion is stopped, the gripper left as it "
    "is, and the report holds every finished cycle and the one interrupted."
)
#: The stop reasons that are a finished job (exit code 0).
DONE_REASONS = frozenset({StopReason.BIN_EMPTY, StopReason.MAX_CYCLES})
_SIGNALS = (signal.SIGINT, signal.SIGTERM)


class Interrupted(KeyboardInterrupt):
    """A stop signal that could not wait for a clean stop (during the cell's set-up, or the second one)."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


class StopSignals:
    """While entered (in the main thread; elsewhere it does nothing): SIGINT and SIGTERM call ``target`` with the
    signal's name (``target`` set: ``Picker.request_stop``), or raise ``Interrupted`` (no target yet, or a second
    signal). ``signum`` is the first signal received."""

    def __init__(self) -> None:
        self.signum: int | None = None
        self.target: Callable[[str], None] | None = None
        self._previous: dict[int, Any] = {}

    def __enter__(self) -> StopSignals:
        if threading.current_thread() is threading.main_thread():
            self._previous = {sig: signal.signal(sig, self._handle) for sig in _SIGNALS}
        return self

    def __exit__(self, *exc: object) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        self._previous = {}

    @property
    def name(self) -> str | None:
        return None if self.signum is None else signal.Signals(self.signum).name

    def _handle(self, signum: int, frame: object) -> None:
        first = self.signum is None
        if first:
            self.signum = signum
        if first and self.target is not None:
            self.target(signal.Signals(signum).name)  # sets a flag: the picker stops at its next command
            return
        raise Interrupted(signum)


class EmulatorWatch:
    """While entered: checks every ``poll_s`` whether the emulator's child process (``ControllerProcess``) has
    ended; when it has, logs it as an error naming the process and its exit code and calls ``on_death`` with that
    sentence, once. ``process`` None (a hardware cell): does nothing."""

    def __init__(self, process: Any, on_death: Callable[[str], None], poll_s: float = 0.25) -> None:
        self.process, self.on_death, self.poll_s = process, on_death, poll_s
        self.death: str | None = None
        self._done = threading.Event()
        self._thread: threading.Thread | None = None

    def __enter__(self) -> EmulatorWatch:
        if self.process is not None:
            self._done.clear()
            self._thread = threading.Thread(target=self._watch, name="emulator-watch", daemon=True)
            self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._done.set()
        if self._thread is not None:
            self._thread.join(2.0)
            self._thread = None

    def _watch(self) -> None:
        while not self._done.wait(self.poll_s):
            death = self.process.describe_exit()
            if death is not None:
                self.death = death
                log.error("%s: the cell is gone, the run stops", death)
                self.on_death(death)
                return


def exit_code(report: RunReport | None, signum: int | None) -> int:
    """128 + the signal after SIGINT/SIGTERM; 0 when the run finished its job (``DONE_REASONS``); else 1."""
    if signum is not None:
        return 128 + signum
    return 0 if report is not None and report.stop_reason in DONE_REASONS else 1
