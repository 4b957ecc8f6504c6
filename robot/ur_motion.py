"""A motion in flight on a UR controller: sent asynchronously, then watched until it ends.

Every move is sent to the controller **asynchronously** (ur_rtde's ``async=True``) and awaited here by polling the
received state: completion (the control script's async-operation word), protective/emergency stop, the program
state, the link (``URConnection.link_ok``) and a timeout derived from the motion's trapezoidal duration. A blocking
ur_rtde move would wait up to 300 s on a dead link and cannot be stopped from another thread; this one can
(``MotionWatch.stop``).

Errors (``robot.ur_errors``): ``ProtectiveStopError``/``EmergencyStopError`` on a safety stop, ``ConnectionLostError``
when the link drops, ``MotionFailedError`` when the control script stops, the controller refuses the command or the
timeout passes (the arm is then stopped). Each carries where the arm was when the failure was seen.

A **guarded** motion (``wait(max_force_n=...)``) also watches the TCP force the controller reports: above the
guard the arm is stopped at ``URConfig.contact_stop_decel_m_s2`` and the result says so (``contact_force_n``). It
is not an error: it lets a cell stop on an unexpected contact (a finger meeting a part that lies elsewhere than
estimated) well below the safety system's force limit, which would otherwise stop the arm with a protective stop.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from robot.ur_connection import POLL_S, RUNTIME_PLAYING, RUNTIME_STATES, STATE_SETTLE_S, URConnection
from robot.ur_errors import ConnectionLostError, MotionFailedError, RobotError

__all__ = ["MotionResult", "MotionWatch", "settle_receive"]


def settle_receive(link: URConnection) -> None:
    """Waits until the receive connection has decoded a package newer than the one seen now (2 ticks)."""
    r = link.rtde_r
    ts0 = float(r.getTimestamp())
    end = time.monotonic() + STATE_SETTLE_S
    while float(r.getTimestamp()) < ts0 + 0.003 and time.monotonic() < end:
        time.sleep(POLL_S)


@dataclass(frozen=True, eq=False)
class MotionResult:
    """How a motion ended. ``reached``: the controller finished it (False when ``stop()`` cut it short).
    ``target_error_m``: TCP distance from the target at the end, from the received state."""

    kind: str  # "move_l" or "move_j"
    reached: bool
    q: np.ndarray
    T_base_tcp: np.ndarray
    target_error_m: float
    duration_s: float
    contact_force_n: float | None = None  # a guarded motion stopped on this TCP force [N]; None: no contact


@dataclass
class _Pending:
    kind: str
    T_target: np.ndarray
    op_id_before: int
    started_s: float
    deadline_s: float
    stopped: bool = False


class MotionWatch:
    """At most one motion in flight on ``link``. ``send`` and ``wait`` from one thread at a time (the owner holds
    ``link.lock`` around a send); ``stop`` from any thread."""

    def __init__(self, link: URConnection) -> None:
        self.link = link
        self._pending: _Pending | None = None

    @property
    def in_flight(self) -> bool:
        return self._pending is not None

    def require_idle(self) -> None:
        """``RobotError`` when a motion is still in flight."""
        if self._pending is not None:
            raise RobotError(f"a {self._pending.kind} is still in flight: wait_for_motion() or stop() first")

    def forget(self) -> None:
        """Drops the motion in flight without stopping it (the link is being rebuilt or recovered)."""
        self._pending = None

    def send(self, kind: str, T_target: np.ndarray, duration_s: float, command: Callable[[], bool]) -> None:
        """Runs ``command`` (an asynchronous ur_rtde move) and records it as in flight, with a timeout of
        ``motion_timeout_factor * duration_s / speed scaling + motion_timeout_margin_s``."""
        link, cfg = self.link, self.link.config
        scaling = float(link.rtde_r.getSpeedScaling()) if link.rtde_r is not None else 1.0
        timeout = cfg.motion_timeout_factor * duration_s / max(scaling, 0.05) + cfg.motion_timeout_margin_s
        op_id = int(link.rtde_c.getAsyncOperationProgressEx().operationId())
        now = time.monotonic()
        try:
            ok = command()
        except RuntimeError as exc:  # the client raises on a broken socket
            raise ConnectionLostError(f"UR controller {link.host}: sending {kind} failed: {exc}") from exc
        if not ok:
            self._settle_receive()
            link.raise_if_link_lost(f"sending {kind}")
            link.raise_if_safety_stopped(f"sending {kind}")
            raise MotionFailedError(
                f"UR controller {link.host} refused {kind} ({link.status().describe()}); call recover()",
                *link.where_now(),
            )
        self._pending = _Pending(kind, np.array(T_target), op_id, now, now + timeout)

    def wait(
        self, timeout_s: float | None = None, max_force_n: float | None = None, detecting_contact: bool = False
    ) -> MotionResult:
        """Waits for the motion in flight to end; ``timeout_s`` overrides the one derived from its duration.
        ``max_force_n``: a guard [N] on the TCP force's magnitude: above it the arm is stopped (the result's
        ``contact_force_n``, ``reached`` False). ``detecting_contact``: the controller's contact detection runs
        (``startContactDetection`` sent after the move): a contact it reports ends the motion the same way, once
        the controller has stopped the arm and moved it back to where the contact began; the detection is stopped
        whatever happens."""
        pending = self._pending
        if pending is None:
            raise RobotError("wait_for_motion: no motion in flight (start_move_* first)")
        link = self.link
        deadline = pending.deadline_s if timeout_s is None else time.monotonic() + timeout_s
        contact: float | None = None
        try:
            while True:
                link.raise_if_link_lost(f"during {pending.kind}")
                link.raise_if_safety_stopped(f"during {pending.kind}")
                if detecting_contact and contact is None and link.rtde_c.readContactDetection():
                    contact = link.tcp_force_n()
                    pending.stopped = True  # the controller stops the arm and moves it back by itself
                if max_force_n is not None and contact is None:
                    force = link.tcp_force_n()
                    if force > max_force_n:
                        contact = force
                        self._stop_now(pending, link.config.contact_stop_decel_m_s2)
                runtime = int(link.rtde_r.getRuntimeState())
                status = link.rtde_c.getAsyncOperationProgressEx()
                finished = status.operationId() != pending.op_id_before and not status.isAsyncOperationRunning()
                if runtime != RUNTIME_PLAYING or (finished and not link.rtde_c.isProgramRunning()):
                    self._raise_program_stopped(f"during {pending.kind}")
                if finished and (not detecting_contact or link.rtde_c.isSteady()):
                    break
                if time.monotonic() > deadline:
                    with contextlib.suppress(RuntimeError):
                        self._stop_now(pending)
                    raise MotionFailedError(
                        f"{pending.kind} did not finish within {deadline - pending.started_s:.1f} s; stopped",
                        *link.where_now(),
                    )
                time.sleep(POLL_S)
            self._settle_receive()
            # The receive connection may show a safety stop a package after the control connection saw the end.
            link.raise_if_safety_stopped(f"at the end of {pending.kind}")
            T_end = link.T_base_tcp()
            return MotionResult(
                kind=pending.kind,
                reached=not pending.stopped,
                q=link.q(),
                T_base_tcp=T_end,
                target_error_m=float(np.linalg.norm(T_end[:3, 3] - pending.T_target[:3, 3])),
                duration_s=time.monotonic() - pending.started_s,
                contact_force_n=contact,
            )
        finally:
            self._pending = None
            if detecting_contact:
                with contextlib.suppress(RuntimeError):
                    link.rtde_c.stopContactDetection()

    def stop(self, decel: float | None = None) -> None:
        """Decelerates the motion in flight to rest (``stopJ`` after a joint move, ``stopL`` after a linear one);
        ``decel`` in rad/s^2 or m/s^2. Safe from another thread while ``wait`` runs, and when nothing moves."""
        pending, c = self._pending, self.link.rtde_c
        if c is None or not c.isProgramRunning():
            return  # no program, no programmed motion (and a stop command would wait for one)
        if pending is None:
            c.stopJ(decel or self.link.config.stop_decel_rad_s2, False)
            return
        self._stop_now(pending, decel)

    # --- internals -------------------------------------------------------------------------------------------
    def _stop_now(self, pending: _Pending, decel: float | None = None) -> None:
        pending.stopped = True
        cfg = self.link.config
        if pending.kind == "move_l":
            self.link.rtde_c.stopL(decel or cfg.stop_decel_m_s2, False)
        else:
            self.link.rtde_c.stopJ(decel or cfg.stop_decel_rad_s2, False)

    def _settle_receive(self) -> None:
        settle_receive(self.link)

    def _raise_program_stopped(self, when: str) -> None:
        link = self.link
        # The receive connection may lag the control one: give it a moment to show a safety stop first.
        end = time.monotonic() + STATE_SETTLE_S
        while time.monotonic() < end:
            link.raise_if_safety_stopped(when)
            time.sleep(POLL_S)
        runtime = int(link.rtde_r.getRuntimeState())
        raise MotionFailedError(
            f"UR controller {link.host}: the control script stopped {when} (program "
            f"{RUNTIME_STATES.get(runtime, runtime)}; a script error, a watchdog or a stop from the pendant or "
            "dashboard); call recover()",
            *link.where_now(),
        )
