"""The link to one UR controller: the four ur_rtde clients, a bounded connect, link freshness, the control script's
state and recovery from a protective stop.

``URConnection`` owns ``rtde_receive`` (state), ``rtde_control`` (motion, the uploaded control script), ``rtde_io``
(outputs) and ``dashboard_client`` (recovery); ``robot.ur.URRobot`` drives motion through it. Every client is None
until connected.

Connecting: ur_rtde's constructors wait without a timeout (holding the GIL) for the controller's first state
package. ``connect``/``reconnect`` first do a short RTDE protocol-version handshake and a dashboard TCP connect of
their own (``robot.ur_probe``), each bounded by ``URConfig.connect_timeout_s``, so an absent or silent controller
gives a clear ``RobotConnectionError`` (host and port named) instead of a hang.

The link is up when the receive client is connected and the controller's timestamp advanced within
``URConfig.stale_state_timeout_s``.

Recovery (``recover``): dashboard ``close safety popup`` and ``unlock protective stop`` (retried until accepted:
e-Series refuses within 5 s of the stop), ``reuploadScript()``, wait for ``isProgramRunning()``, set the TCP again
(a program restart resets the active TCP to the installation's).

Shutdown: a client whose destructor could abort the process is never destroyed (``_never_destroy`` says why).
"""

from __future__ import annotations

import contextlib
import ctypes
import logging
import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from robot.ur_config import URConfig
from robot.ur_errors import (
    ConnectionLostError,
    EmergencyStopError,
    MotionFailedError,
    ProtectiveStopError,
    RecoveryError,
    RobotConnectionError,
    RobotError,
)
from robot.ur_probe import DASHBOARD_PORT, RTDE_PORT, probe_rtde, probe_tcp
from sygrid.robots.kinematics import T_to_pose, pose_to_T

log = logging.getLogger(__name__)

__all__ = ["RUNTIME_STATES", "RobotStatus", "URConnection"]

RUNTIME_PLAYING = 2  # runtime_state: 0 stopping, 1 stopped, 2 playing, 3 pausing, 4 paused, 5 resuming
ROBOT_MODE_RUNNING = 7
ROBOT_MODES = {
    -1: "NO_CONTROLLER", 0: "DISCONNECTED", 1: "CONFIRM_SAFETY", 2: "BOOTING", 3: "POWER_OFF", 4: "POWER_ON",
    5: "IDLE", 6: "BACKDRIVE", 7: "RUNNING", 8: "UPDATING_FIRMWARE",
}  # fmt: skip
RUNTIME_STATES = {0: "STOPPING", 1: "STOPPED", 2: "PLAYING", 3: "PAUSING", 4: "PAUSED", 5: "RESUMING"}

POLL_S = 0.002  # one controller tick at 500 Hz
STATE_SETTLE_S = 0.2  # how long the receive connection may lag the control connection on one event
_UNLOCK_RETRY_S = 0.25


@dataclass(frozen=True)
class RobotStatus:
    """The controller's state as received (``connected`` False: the other fields are stale)."""

    connected: bool
    robot_mode: int
    safety_mode: int
    runtime_state: int
    protective_stopped: bool
    emergency_stopped: bool
    program_running: bool

    def describe(self) -> str:
        return (
            f"robot mode {ROBOT_MODES.get(self.robot_mode, self.robot_mode)}, safety mode {self.safety_mode}, "
            f"program {RUNTIME_STATES.get(self.runtime_state, self.runtime_state)}"
            + (", PROTECTIVE STOP" if self.protective_stopped else "")
            + (", EMERGENCY STOP" if self.emergency_stopped else "")
            + ("" if self.connected else ", link DOWN")
        )


def _never_destroy(client: object) -> None:
    """Leaks one reference to a ur_rtde client on purpose, so that its C++ destructor never runs, not even at
    interpreter shutdown.

    The crash it avoids: ur_rtde 1.6.5's destructors call ``disconnect()`` again, and when that throws (a
    ``boost::system::system_error`` such as ``read: End of file`` on a socket the controller has closed) the
    exception leaves a destructor, so the C++ runtime calls ``std::terminate`` and the whole process aborts
    (SIGABRT). It happens as soon as the last Python reference goes (``close()``, ``reconnect()``, ``recover()``,
    or interpreter exit) for an ``RTDEIOInterface`` whose link is dead (a dropped link, a stopped or restarted
    controller) and for any client whose own ``disconnect()`` raised. Cost: the client's socket and memory for the
    rest of the process, one set per dropped link. ``tests/test_robot_ur.py`` closes a robot on a dead link in a
    child process and checks that the process exits cleanly."""
    log.info("keeping a disconnected %s alive for the life of the process (its destructor would abort)", client)
    ctypes.pythonapi.Py_IncRef(ctypes.py_object(client))


# ---------------------------------------------------------------------------------------------- the link


class URConnection:
    """The clients of one controller and what is known of its state. ``lock`` serialises connect, reconnect,
    recover and motion starts (the owner takes it around a motion start). ``T_flange_tcp`` is the TCP set on the
    controller on connect and after every program restart."""

    def __init__(self, config: URConfig) -> None:
        self.config = config
        self.T_flange_tcp = np.array(config.T_flange_tcp)
        self.rtde_r: Any = None
        self.rtde_c: Any = None
        self.rtde_io: Any = None
        self.dash: Any = None
        self.lock = threading.RLock()
        self._last_ts = -1.0
        self._last_ts_at = 0.0

    @property
    def host(self) -> str:
        return self.config.host

    # --- connect and disconnect ------------------------------------------------------------------------------
    def connect(self) -> None:
        """Connects the dashboard, receive, control and IO clients and sets the TCP.

        Raises ``RobotConnectionError`` (host and port named) when the controller is absent, silent or refuses;
        ``ProtectiveStopError``/``EmergencyStopError`` when it is safety-stopped (the dashboard and receive
        clients stay connected: ``recover()`` finishes the connection after a protective stop)."""
        import dashboard_client
        import rtde_receive

        cfg = self.config
        with self.lock:
            self._probe()
            if self.dash is None:
                dash = dashboard_client.DashboardClient(cfg.host)
                try:
                    dash.connect(int(cfg.connect_timeout_s * 1000))
                except RuntimeError as exc:
                    raise RobotConnectionError(
                        f"UR controller {cfg.host}: dashboard (port {DASHBOARD_PORT}) connection failed: {exc}"
                    ) from exc
                self.dash = dash
            if self.rtde_r is None:
                try:
                    self.rtde_r = rtde_receive.RTDEReceiveInterface(
                        cfg.host, self._frequency, [], False, cfg.upper_range_registers
                    )
                except RuntimeError as exc:
                    raise RobotConnectionError(f"UR controller {cfg.host}: RTDE receive interface: {exc}") from exc
            self._mark_fresh()
            status = self.status()
            if status.robot_mode != ROBOT_MODE_RUNNING:
                raise RobotConnectionError(
                    f"UR controller {cfg.host}: robot mode is {ROBOT_MODES.get(status.robot_mode, status.robot_mode)}"
                    ", not RUNNING: power it on and release the brakes (pendant, or dashboard 'power on' and "
                    "'brake release')"
                )
            self.raise_if_safety_stopped("connecting")
            self._connect_control()
            log.info("connected to UR controller %s (%s)", cfg.host, self.status().describe())

    def close(self) -> None:
        """Stops the control script (``URConfig.stop_script_on_close``, when the link is up) and disconnects every
        client (errors ignored)."""
        with self.lock:
            link_ok = self.rtde_r is not None and self.link_ok()
            if self.rtde_c is not None and self.config.stop_script_on_close and link_ok:
                with contextlib.suppress(RuntimeError):
                    self.rtde_c.stopScript()
            self._drop_clients(link_ok)

    def reconnect(self) -> None:
        """Re-establishes every client after a dropped link (or a restarted controller), then sets the TCP.
        Raises ``RobotConnectionError`` when the controller does not answer."""
        with self.lock:
            log.warning("reconnecting to UR controller %s", self.host)
            link_ok = self.rtde_r is not None and self.link_ok()
            self._probe()
            # Rebuilt rather than ur_rtde's own reconnect(), which can crash the process on a live link (1.6.5).
            self._drop_clients(link_ok)
            self.connect()

    def is_connected(self) -> bool:
        """All clients up and the controller's state advancing."""
        return self.rtde_c is not None and self.rtde_io is not None and self.link_ok()

    # --- state -----------------------------------------------------------------------------------------------
    def receiver(self) -> Any:
        """The receive client; ``ConnectionLostError`` when not connected."""
        return self.require(self.rtde_r, "rtde_receive")

    def require(self, client: Any, what: str) -> Any:
        if client is None:
            raise ConnectionLostError(f"UR controller {self.host}: not connected ({what}); call connect()")
        return client

    def q(self) -> np.ndarray:
        """Measured joint angles (6,) rad. ``ConnectionLostError`` when the received state is not current."""
        self.raise_if_link_lost("reading the joints")
        return np.array(self.rtde_r.getActualQ(), dtype=float)

    def T_base_tcp(self) -> np.ndarray:
        """Measured pose of the active TCP in the base frame. ``ConnectionLostError`` when the received state is not
        current."""
        self.raise_if_link_lost("reading the TCP pose")
        return pose_to_T(np.array(self.rtde_r.getActualTCPPose(), dtype=float))

    def tcp_force_n(self) -> float:
        """Magnitude of the measured force on the TCP [N] (the controller's ``actual_TCP_force``, its force part).
        ``ConnectionLostError`` when the received state is not current."""
        self.raise_if_link_lost("reading the TCP force")
        return float(np.linalg.norm(self.rtde_r.getActualTCPForce()[:3]))

    def status(self) -> RobotStatus:
        r = self.receiver()
        runtime = int(r.getRuntimeState())
        return RobotStatus(
            connected=self.link_ok(),
            robot_mode=int(r.getRobotMode()),
            safety_mode=int(r.getSafetyMode()),
            runtime_state=runtime,
            protective_stopped=bool(r.isProtectiveStopped()),
            emergency_stopped=bool(r.isEmergencyStopped()),
            program_running=runtime == RUNTIME_PLAYING,
        )

    def link_ok(self) -> bool:
        """The receive connection is up and the controller's timestamp advanced within the stale timeout."""
        r = self.rtde_r
        if r is None or not r.isConnected():
            return False
        ts, now = float(r.getTimestamp()), time.monotonic()
        if ts != self._last_ts:
            self._last_ts, self._last_ts_at = ts, now
            return True
        return now - self._last_ts_at < self.config.stale_state_timeout_s

    def where_now(self) -> tuple[np.ndarray | None, np.ndarray | None]:
        """``(q, T_base_tcp)`` for an exception: the last received state, or Nones when it is not current."""
        if self.rtde_r is None or not self.link_ok():
            return None, None
        return np.array(self.rtde_r.getActualQ(), dtype=float), pose_to_T(np.array(self.rtde_r.getActualTCPPose()))

    def raise_if_link_lost(self, when: str) -> None:
        if self.rtde_r is None:
            raise ConnectionLostError(f"UR controller {self.host}: not connected ({when}); call connect()")
        if not self.link_ok():
            raise ConnectionLostError(
                f"lost the link to UR controller {self.host} {when} (no state for "
                f"{self.config.stale_state_timeout_s:g} s or socket closed); call recover() or reconnect()"
            )

    def raise_if_safety_stopped(self, when: str) -> None:
        r = self.rtde_r
        if r.isEmergencyStopped():
            raise EmergencyStopError(f"UR controller {self.host} is emergency-stopped ({when})", *self.where_now())
        if r.isProtectiveStopped():
            raise ProtectiveStopError(
                f"UR controller {self.host} is in a protective stop ({when}); call recover(), then re-plan",
                *self.where_now(),
            )

    # --- the control script and the TCP ----------------------------------------------------------------------
    def make_ready(self) -> None:
        """Before a motion is sent: a live link (reconnected when ``auto_reconnect``), no safety stop, a running
        control script (re-uploaded when ``restart_stopped_program``)."""
        if self.rtde_c is None or self.rtde_io is None or not self.link_ok():
            if not self.config.auto_reconnect or self.rtde_r is None:
                raise ConnectionLostError(f"not connected to UR controller {self.host}; call connect() or recover()")
            self.reconnect()
        self.raise_if_safety_stopped("before the motion; nothing was sent")
        if not self.rtde_c.isProgramRunning():
            runtime = int(self.rtde_r.getRuntimeState())
            if not self.config.restart_stopped_program:
                raise MotionFailedError(
                    f"UR controller {self.host}: the control script is not running (program "
                    f"{RUNTIME_STATES.get(runtime, runtime)}); nothing was sent; call recover()",
                    *self.where_now(),
                )
            log.warning("control script not running (program %s); re-uploading it", RUNTIME_STATES.get(runtime))
            self._restart_program(time.monotonic() + self.config.program_start_timeout_s)
            self.apply_tcp()

    def set_tcp(self, T_flange_tcp: np.ndarray) -> None:
        """Keeps ``T_flange_tcp`` (a checked rigid 4x4) and sets it on the controller when connected."""
        with self.lock:
            self.T_flange_tcp = T_flange_tcp
            if self.rtde_c is not None:
                self.apply_tcp()

    def apply_tcp(self) -> None:
        if not self.rtde_c.setTcp(T_to_pose(self.T_flange_tcp).tolist()):
            raise RobotError(f"UR controller {self.host}: setTcp failed (is the control script running?)")

    def recover(self, timeout_s: float | None = None) -> None:
        """Back to a running control script with the TCP set: reconnects when the link is down, unlocks a
        protective stop through the dashboard (retrying while the controller refuses), re-uploads the control
        script and waits for it to run. ``RecoveryError`` on an emergency stop or when ``timeout_s`` (default
        ``recovery_timeout_s``) passes."""
        timeout_s = self.config.recovery_timeout_s if timeout_s is None else timeout_s
        deadline = time.monotonic() + timeout_s
        with self.lock:
            if self.rtde_r is None or self.dash is None or not self.link_ok():
                try:
                    self.reconnect()
                except (ProtectiveStopError, RobotConnectionError) as exc:
                    if not isinstance(exc, ProtectiveStopError):
                        raise RecoveryError(f"recover: cannot reach UR controller {self.host}: {exc}") from exc
            if self.rtde_r.isEmergencyStopped():
                raise RecoveryError(
                    f"UR controller {self.host} is emergency-stopped: release the e-stop button and reset on the "
                    "pendant, then call recover() again"
                )
            if self.rtde_r.isProtectiveStopped():
                self._unlock_protective_stop(deadline)
            if self.rtde_c is None:
                try:
                    self._connect_control()
                except RobotConnectionError as exc:
                    raise RecoveryError(f"recover: {exc}") from exc
            elif not self.rtde_c.isProgramRunning():
                self._restart_program(deadline)
            self.apply_tcp()
            log.info("UR controller %s recovered (%s)", self.host, self.status().describe())

    # --- internals -------------------------------------------------------------------------------------------
    @property
    def _frequency(self) -> float:
        return -1.0 if self.config.rtde_frequency_hz is None else float(self.config.rtde_frequency_hz)

    def _probe(self) -> None:
        probe_rtde(self.host, RTDE_PORT, self.config.connect_timeout_s)
        probe_tcp(self.host, DASHBOARD_PORT, "dashboard", self.config.connect_timeout_s)

    def _connect_control(self) -> None:
        import rtde_control
        import rtde_io

        cfg = self.config
        flags = rtde_control.RTDEControlInterface.FLAG_UPLOAD_SCRIPT
        if cfg.upper_range_registers:
            flags |= rtde_control.RTDEControlInterface.FLAG_UPPER_RANGE_REGISTERS
        if self.rtde_c is None:
            try:
                self.rtde_c = rtde_control.RTDEControlInterface(cfg.host, self._frequency, flags)
            except RuntimeError as exc:
                raise RobotConnectionError(
                    f"UR controller {cfg.host}: RTDE control interface (ports {RTDE_PORT}, 30003, "
                    f"{DASHBOARD_PORT}): {exc}"
                ) from exc
        if self.rtde_io is None:
            try:
                self.rtde_io = rtde_io.RTDEIOInterface(cfg.host, False, cfg.upper_range_registers)
            except RuntimeError as exc:
                raise RobotConnectionError(f"UR controller {cfg.host}: RTDE IO interface: {exc}") from exc
        deadline = time.monotonic() + cfg.program_start_timeout_s
        if not self.rtde_c.isProgramRunning():
            self._restart_program(deadline)
        self.apply_tcp()

    def _drop_clients(self, link_ok: bool) -> None:
        """Disconnects and forgets every client. A client whose ``disconnect()`` raises is never destroyed, and an
        ``RTDEIOInterface`` on a dead link is not even disconnected (its disconnect waits, with no timeout, for the
        reply to an RTDE pause request): both go to ``_never_destroy``, which names the crash."""
        if self.rtde_io is not None and not link_ok:
            _never_destroy(self.rtde_io)
            self.rtde_io = None
        for client in (self.dash, self.rtde_io, self.rtde_c, self.rtde_r):
            if client is None:
                continue
            try:
                client.disconnect()
            except RuntimeError as exc:
                log.info("%s.disconnect() failed: %s", type(client).__name__, exc)
                _never_destroy(client)
        self.dash = self.rtde_io = self.rtde_c = self.rtde_r = None

    def _mark_fresh(self) -> None:
        self._last_ts = float(self.rtde_r.getTimestamp())
        self._last_ts_at = time.monotonic()

    def _restart_program(self, deadline: float) -> None:
        if not self.rtde_c.reuploadScript():
            raise RecoveryError(f"UR controller {self.host}: reuploadScript() failed")
        # reuploadScript returns before the state shows the program running (a client race): poll.
        while not self.rtde_c.isProgramRunning():
            if time.monotonic() > deadline:
                runtime = int(self.rtde_r.getRuntimeState())
                raise RecoveryError(
                    f"UR controller {self.host}: the control script did not start (program "
                    f"{RUNTIME_STATES.get(runtime, runtime)}; {self.status().describe()})"
                )
            time.sleep(POLL_S)

    def _unlock_protective_stop(self, deadline: float) -> None:
        dash = self.dash
        with contextlib.suppress(RuntimeError):
            dash.closeSafetyPopup()
        reply = ""
        while True:
            # unlockProtectiveStop() returns nothing in ur_rtde 1.6.5: send the line and read the reply ourselves.
            dash.send("unlock protective stop\n")
            reply = dash.receive().strip()
            if "releasing" in reply.lower():
                break
            if time.monotonic() + _UNLOCK_RETRY_S > deadline:
                raise RecoveryError(f"UR controller {self.host}: protective stop not unlocked: {reply!r}")
            log.info("protective stop unlock refused (%s); retrying", reply)
            time.sleep(_UNLOCK_RETRY_S)
        while self.rtde_r.isProtectiveStopped():
            if time.monotonic() > deadline:
                raise RecoveryError(f"UR controller {self.host}: still protective-stopped after {reply!r}")
            time.sleep(POLL_S)
        log.warning("protective stop on %s unlocked", self.host)
