"""Force-limited motion on a UR controller through ur_rtde: the deliberate contacts of a pick cycle (a nudge's press
and drag) go through the controller's own force control, never a position target inside a part.

- ``move_until_contact``: ``moveUntilContact`` (the control script moves the TCP at a speed until its TCP force
  shows a contact against the motion, stops and goes back to where the contact began). The client call blocks until
  then, so it runs in a helper thread while this one watches what a motion is watched for (``robot.ur_motion``):
  a safety stop, the link, the program, and the travel: past ``max_travel_m`` without a contact the program is
  stopped through the dashboard (the script's contact loop takes no other command) and ``NoContactError`` raised.
- ``move_l_pressing``: ``forceMode`` compliant along one axis (the robot pushes with ``force_n`` along it, at most
  ``max_press_speed_m_s``), a linear move watched like any other, and ``forceModeStop`` whatever happens.

Both check their inputs before sending (``MotionRefusedError``: speed, force, workspace) and raise the errors of
``robot.ur_errors`` as the other moves do.
"""

from __future__ import annotations

import contextlib
import math
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from robot.ur_config import check_rate, check_target_in_workspace
from robot.ur_connection import POLL_S, URConnection
from robot.ur_errors import ConnectionLostError, MotionFailedError, MotionRefusedError, NoContactError
from robot.ur_motion import settle_receive
from sygrid.robots.kinematics import T_to_pose

__all__ = ["ContactResult", "contact_move", "force_mode", "pressing_task_frame"]

#: How long to wait for the client's blocking call to return after the program was stopped.
_RETURN_TIMEOUT_S = 3.0
#: How long forceMode is repeated before the motion that follows it is sent (several controller cycles).
_FORCE_MODE_SETTLE_S = 0.05


@dataclass(frozen=True, eq=False)
class ContactResult:
    """Where a move until contact stopped (the contact's start, measured) and how far it went [m]; the largest
    TCP force seen along the way [N] (the received state, sampled at the poll rate)."""

    T_base_tcp: np.ndarray
    travel_m: float
    peak_force_n: float
    duration_s: float


def unit_direction(direction: np.ndarray) -> np.ndarray:
    """``direction`` (3,) scaled to unit length; ``MotionRefusedError`` for a zero or non-finite vector."""
    d = np.asarray(direction, dtype=float).reshape(-1)
    n = float(np.linalg.norm(d)) if d.shape == (3,) else 0.0
    if not (math.isfinite(n) and n > 1e-9):
        raise MotionRefusedError(f"a contact direction must be 3 finite numbers, not all zero, got {d.tolist()}")
    return d / n


def contact_move(
    link: URConnection,
    direction: np.ndarray,
    speed_m_s: float,
    max_travel_m: float,
    accel_m_s2: float | None = None,
) -> ContactResult:
    """Sends ``moveUntilContact`` along ``direction`` (base frame) and watches it; see the module docstring. The
    caller holds ``link.lock`` and made the link ready."""
    cfg = link.config
    d = unit_direction(direction)
    v = check_rate(speed_m_s, cfg.max_contact_speed_m_s, cfg.max_contact_speed_m_s, "speed_m_s")
    a = check_rate(accel_m_s2, cfg.linear_accel_m_s2, cfg.max_linear_accel_m_s2, "accel_m_s2")
    if not (math.isfinite(max_travel_m) and max_travel_m > 0):
        raise MotionRefusedError(f"max_travel_m must be a positive number of metres, got {max_travel_m!r}")
    T_start = link.T_base_tcp()
    T_end = T_start.copy()
    T_end[:3, 3] += max_travel_m * d
    check_target_in_workspace(cfg, T_end)
    xd = [*(v * d).tolist(), 0.0, 0.0, 0.0]
    direction6 = [*d.tolist(), 0.0, 0.0, 0.0]
    outcome: dict[str, object] = {}

    def call() -> None:
        try:
            outcome["ok"] = bool(link.rtde_c.moveUntilContact(xd, direction6, a))
        except RuntimeError as exc:  # the client raises on a broken socket
            outcome["error"] = exc

    worker = threading.Thread(target=call, name="move-until-contact", daemon=True)
    started = time.monotonic()
    deadline = started + cfg.motion_timeout_factor * max_travel_m / v + cfg.motion_timeout_margin_s
    peak = 0.0
    worker.start()
    try:
        while worker.is_alive():
            link.raise_if_link_lost("during move_until_contact")
            link.raise_if_safety_stopped("during move_until_contact")
            peak = max(peak, link.tcp_force_n())
            travel = float((link.T_base_tcp()[:3, 3] - T_start[:3, 3]) @ d)
            if travel > max_travel_m or time.monotonic() > deadline:
                _stop_program(link, worker)
                raise NoContactError(
                    f"move_until_contact met nothing within {max_travel_m * 1e3:.0f} mm along "
                    f"{np.round(d, 3).tolist()} ({time.monotonic() - started:.1f} s); the program was stopped: "
                    "call recover()",
                    *link.where_now(),
                )
            time.sleep(POLL_S)
    finally:
        worker.join(_RETURN_TIMEOUT_S)
    if "error" in outcome:
        raise ConnectionLostError(f"UR controller {link.host}: move_until_contact failed: {outcome['error']}")
    settle_receive(link)
    link.raise_if_safety_stopped("at the end of move_until_contact")
    if not outcome.get("ok"):
        raise MotionFailedError(
            f"UR controller {link.host}: move_until_contact did not finish ({link.status().describe()}); call "
            "recover()",
            *link.where_now(),
        )
    T_now = link.T_base_tcp()
    return ContactResult(
        T_base_tcp=T_now,
        travel_m=float((T_now[:3, 3] - T_start[:3, 3]) @ d),
        peak_force_n=peak,
        duration_s=time.monotonic() - started,
    )


def pressing_task_frame(direction: np.ndarray) -> list[float]:
    """A force-mode task frame (UR pose, base frame, at the origin) whose z axis is ``direction`` (unit)."""
    z = unit_direction(direction)
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)
    return T_to_pose(T).tolist()


@contextlib.contextmanager
def force_mode(
    link: URConnection, direction: np.ndarray, force_n: float, max_press_speed_m_s: float | None
) -> Iterator[None]:
    """Force mode compliant along ``direction`` (base frame), pushing with ``force_n`` [N] along it at most at
    ``max_press_speed_m_s``; the other axes follow the program. ``forceModeStop`` on exit (when the link and the
    program are still there to take it)."""
    cfg = link.config
    if not (math.isfinite(force_n) and 0 < force_n <= cfg.max_press_force_n):
        raise MotionRefusedError(f"force_n must be in (0, {cfg.max_press_force_n:g}] N, got {force_n!r}")
    speed = check_rate(max_press_speed_m_s, cfg.max_contact_speed_m_s, cfg.max_contact_speed_m_s, "max_press_speed")
    frame = pressing_task_frame(direction)
    limits = [0.005, 0.005, speed, 0.05, 0.05, 0.05]  # deviations of the non-compliant axes; the press speed
    wrench = [0.0, 0.0, float(force_n), 0.0, 0.0, 0.0]
    # A realtime command: the script acts on it only if it is still in the register at its next cycle, so it is
    # sent for a few cycles before the next command may replace it.
    end = time.monotonic() + _FORCE_MODE_SETTLE_S
    while True:
        if not link.rtde_c.forceMode(frame, [0, 0, 1, 0, 0, 0], wrench, 2, limits):
            raise MotionFailedError(f"UR controller {link.host} refused forceMode; call recover()", *link.where_now())
        if time.monotonic() > end:
            break
        time.sleep(POLL_S)
    try:
        yield
    finally:
        if link.link_ok() and link.rtde_c.isProgramRunning():
            with contextlib.suppress(RuntimeError):
                link.rtde_c.forceModeStop()


def _stop_program(link: URConnection, worker: threading.Thread) -> None:
    """Ends the control script (dashboard ``stop``), which ends the client's blocking call; the arm decelerates."""
    with contextlib.suppress(RuntimeError):
        link.dash.stop()
    worker.join(_RETURN_TIMEOUT_S)
