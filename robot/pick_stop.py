"""Stopping a pick run from outside it: the request (``StopSwitch``), the guard that keeps the cycle from sending
anything once one has come (``Guarded``), and the thread that stops the arm's motion (``ArmStopper``).

``StopSwitch.request`` may be called from any thread and from a signal handler: it records the reason and sets an
event, nothing more. The picker drives its robot and gripper through ``Guarded`` views whose command methods check
the switch before they run and after they return, raising ``StopRequestedError``: nothing is sent after a request, and a
motion cut short by it does not go on into the rest of its step. Reads (joint angles, the TCP pose, the fingers'
width) are never guarded. ``ArmStopper`` runs beside a run: when a request comes it calls ``robot.stop()``
(decelerate the motion in flight; nothing else, the gripper keeps its state) and calls it again every ``repeat_s``
until the run has seen the request, so a motion sent in the instant between a request and the next check is
stopped too.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Iterable
from typing import Any

log = logging.getLogger(__name__)

#: The commands that move the arm or change the controller's state (``robot.ur.URRobot``'s names).
ROBOT_COMMANDS = frozenset(
    {
        "move_l", "move_j", "move_j_to_pose", "start_move_l", "start_move_j", "start_move_j_to_pose", "recover",
        "reconnect", "set_tcp", "set_digital_out",
    }
)  # fmt: skip
#: The commands that move the fingers (``robot.gripper.Gripper``'s names).
GRIPPER_COMMANDS = frozenset({"open", "close", "activate", "move_to_position", "set"})


class StopRequestedError(Exception):
    """Raised inside a pick cycle once a stop was requested; its message is the request's reason."""


class StopSwitch:
    """A stop request shared by a run and whoever stops it. The first request's reason is kept."""

    def __init__(self) -> None:
        self._event = threading.Event()
        self.reason = ""

    @property
    def requested(self) -> bool:
        return self._event.is_set()

    def request(self, reason: str) -> None:
        """Asks the run to stop; ``reason`` names who asked (e.g. ``"SIGTERM"``). Safe from a signal handler."""
        if not self._event.is_set():
            self.reason = reason
            self._event.set()

    def check(self) -> None:
        """``StopRequestedError`` when a stop was requested."""
        if self._event.is_set():
            raise StopRequestedError(self.reason)

    def wait(self, timeout_s: float | None = None) -> bool:
        return self._event.wait(timeout_s)

    def clear(self) -> None:
        """Forgets the request (a later run may go on)."""
        self.reason = ""
        self._event.clear()


class Guarded:
    """``target`` with its ``commands`` checked against ``switch`` before they run and after they return; every
    other attribute is ``target``'s, read, written and deleted through (a test may replace a method of the
    target)."""

    def __init__(self, target: Any, switch: StopSwitch, commands: Iterable[str]) -> None:
        object.__setattr__(self, "_target", target)
        object.__setattr__(self, "_switch", switch)
        object.__setattr__(self, "_commands", frozenset(commands))

    @property
    def target(self) -> Any:
        """The object guarded."""
        return self._target

    def __getattr__(self, name: str) -> Any:
        value = getattr(self._target, name)
        if name not in self._commands or not callable(value):
            return value
        switch = self._switch

        def command(*args: Any, **kwargs: Any) -> Any:
            switch.check()
            result = value(*args, **kwargs)
            switch.check()
            return result

        return command

    def __setattr__(self, name: str, value: Any) -> None:
        setattr(self._target, name, value)

    def __delattr__(self, name: str) -> None:
        delattr(self._target, name)

    def __repr__(self) -> str:
        return f"Guarded({self._target!r})"


class ArmStopper:
    """While entered: calls ``stop()`` once ``switch`` is set, then every ``repeat_s`` until ``acknowledge()``.
    Errors from ``stop()`` (a lost link) are logged once and do not end the thread."""

    def __init__(self, switch: StopSwitch, stop: Callable[[], None], repeat_s: float = 0.2) -> None:
        self.switch, self._stop, self.repeat_s = switch, stop, repeat_s
        self._done = threading.Event()
        self._thread: threading.Thread | None = None
        self.stops_sent = 0
        self._warned = False

    def __enter__(self) -> ArmStopper:
        self._done.clear()
        self._thread = threading.Thread(target=self._watch, name="pick-arm-stopper", daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.acknowledge()
        if self._thread is not None:
            self._thread.join(5.0)
            self._thread = None

    def acknowledge(self) -> None:
        """The run has seen the request (or ended): no more stops."""
        self._done.set()

    def _watch(self) -> None:
        while not self._done.is_set():
            if not self.switch.wait(0.05):
                continue
            self._send_stop()
            while not self._done.wait(self.repeat_s):
                self._send_stop()
            return

    def _send_stop(self) -> None:
        try:
            self._stop()
            self.stops_sent += 1
        except Exception as exc:  # a stop that cannot be sent (the link is lost) must not end the watch
            if not self._warned:
                self._warned = True
                log.warning("could not send the stop to the arm (%s: %s)", type(exc).__name__, exc)
