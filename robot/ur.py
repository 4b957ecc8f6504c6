"""The UR5e over ur_rtde: connection, safety recovery and checked motion with 4x4 poses.

``URRobot`` drives a Universal Robots e-Series arm through the stock ``ur_rtde`` client (``rtde_receive`` for state,
``rtde_control`` for motion, ``rtde_io`` for outputs, ``dashboard_client`` for recovery). It talks to whatever
answers on ``URConfig.host``: a real UR5e, or ``sim.controller`` on a loopback address. Poses are 4x4 ``T_base_tcp``
in the controller's base frame; UR rotation-vector poses exist only inside this module (``pose_to_T``/``T_to_pose``
from ``sygrid.robots.kinematics``, re-exported here).

API (all lengths m, angles rad, times s)::

    with URRobot(URConfig(host="192.168.1.10", workspace=WorkspaceBox((-0.8, -0.6, 0.0), (0.2, 0.6, 0.7)),
                          T_flange_tcp=T_flange_tcp)) as robot:       # connect() ... close()
        robot.q(); robot.T_base_tcp(); robot.T_base_flange(); robot.status()
        robot.move_l(T_base_tcp, speed_m_s=None, accel_m_s2=None) -> MotionResult     # blocking
        robot.move_j(q, speed_rad_s=None, accel_rad_s2=None) -> MotionResult
        robot.move_j_to_pose(T_base_tcp, ..., q_near=None) -> MotionResult             # local IK (ik_nearest)
        robot.start_move_l(...) / start_move_j(...) / start_move_j_to_pose(...)        # non-blocking, then
        robot.wait_for_motion(timeout_s=None) -> MotionResult;  robot.stop()           # stop() from any thread
        robot.ik(T_base_tcp, q_near=None) -> q or None;  robot.check_pose(T_base_tcp)
        robot.set_tcp(T_flange_tcp);  robot.set_digital_out(i, value, kind);  robot.digital_in(i, kind)
        robot.recover()     # reconnect / unlock protective stop / re-upload the control script, as needed
        robot.reconnect()

Errors (all ``RobotError``, a ``SygridError``), and what a caller (the picker's state machine) does with them:

- ``MotionRefusedError`` (a ``ValueError``; subclasses ``OutsideWorkspaceError``, ``UnreachableError``): the motion
  was checked and **nothing was sent** (target or path outside the workspace box, joint limits, speed/acceleration
  above the configured maxima, a non-rigid pose, no IK solution). Try another candidate.
- ``MotionFailedError``: the motion was sent but did not complete; the arm is at rest (or stopped) somewhere on the
  way. Subclasses: ``ProtectiveStopError`` (safety stop, ``recoverable``), ``ConnectionLostError`` (the link
  dropped), ``EmergencyStopError`` (not recoverable in software). For the recoverable ones: ``robot.recover()``,
  then re-plan from ``robot.T_base_tcp()`` and retry. The exception carries ``q`` and ``T_base_tcp`` where the arm
  was when the failure was seen (None when the link was lost).
- ``RobotConnectionError`` (a ``ConnectionError``): connecting failed; the message names the host and the port.
- ``RecoveryError``: ``recover()`` could not get back to a running control program within its timeout.

A pick cycle's motion step, for example::

    try:
        robot.move_l(T_base_pregrasp)
    except MotionRefusedError:        # unreachable / outside the box / too fast: nothing moved
        ...                           # next grasp candidate
    except MotionFailedError as exc:  # protective stop, dropped link, script stopped; the arm is at rest
        if not exc.recoverable:
            raise                     # emergency stop: a person must act
        robot.recover()
        ...                           # re-plan from robot.T_base_tcp() (the part may have moved)

A motion asked for while the robot is already protective-stopped raises ``ProtectiveStopError`` without sending.
With ``auto_reconnect`` (default) a dropped link is re-established before the next motion; with
``restart_stopped_program`` (default) a control script that stopped without a safety stop is re-uploaded first.

How motions run: every move is sent to the controller **asynchronously** and awaited here, polling the received
state: completion (the control script's async-operation word), protective/emergency stop, the program state, the
link (``isConnected`` and advancing controller timestamps) and a timeout derived from the trapezoidal duration. A
blocking ur_rtde move would wait up to 300 s on a dead link and cannot be stopped from another thread.

Checks before anything is sent (``robot.ur_config``): the pose is rigid; speed and acceleration are positive and
within the maxima; ``move_j`` targets are within the joint limits (minus a margin); the **TCP stays in the workspace
box** (at the target, and along ``movej``'s joint-space path, sampled; a start outside the box may move in). The
configuration (``URConfig``, ``WorkspaceBox``) lives there too, the errors in ``robot.ur_errors``; both are
re-exported here.

Connecting: ur_rtde's constructors wait without a timeout (holding the GIL) for the controller's first state
package. ``connect``/``reconnect`` first do a short RTDE protocol-version handshake and a dashboard TCP connect of
their own, each bounded by ``connect_timeout_s``, so an absent or silent controller gives a clear error instead of
a hang.

Recovery (``recover``): dashboard ``close safety popup`` and ``unlock protective stop`` (retried until accepted:
e-Series refuses within 5 s of the stop), ``reuploadScript()``, wait for ``isProgramRunning()``, set the TCP again
(a program restart resets the active TCP to the installation's).
"""

from __future__ import annotations

import contextlib
import ctypes
import logging
import math
import socket
import struct
import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from robot.ur_config import (
    URConfig,
    WorkspaceBox,
    check_joint_path,
    check_joint_target,
    check_rate,
    check_rigid,
    check_target_in_workspace,
    trapezoid_duration_s,
)
from robot.ur_errors import (
    ConnectionLostError,
    EmergencyStopError,
    MotionFailedError,
    MotionRefusedError,
    OutsideWorkspaceError,
    ProtectiveStopError,
    RecoveryError,
    RobotConnectionError,
    RobotError,
    UnreachableError,
)
from sygrid.robots.kinematics import T_to_pose, forward_kinematics, ik_nearest, pose_to_T
from sygrid.transforms import invert, is_rigid, rotation_angle_deg

log = logging.getLogger(__name__)

__all__ = [
    "DIGITAL_IO_KINDS",
    "ConnectionLostError",
    "EmergencyStopError",
    "MotionFailedError",
    "MotionRefusedError",
    "MotionResult",
    "OutsideWorkspaceError",
    "ProtectiveStopError",
    "RecoveryError",
    "RobotConnectionError",
    "RobotError",
    "RobotStatus",
    "T_to_pose",
    "URConfig",
    "URRobot",
    "UnreachableError",
    "WorkspaceBox",
    "pose_to_T",
    "probe_rtde",
]

RTDE_PORT = 30004
DASHBOARD_PORT = 29999
RUNTIME_PLAYING = 2  # runtime_state: 0 stopping, 1 stopped, 2 playing, 3 pausing, 4 paused, 5 resuming
ROBOT_MODE_RUNNING = 7
_ROBOT_MODES = {
    -1: "NO_CONTROLLER", 0: "DISCONNECTED", 1: "CONFIRM_SAFETY", 2: "BOOTING", 3: "POWER_OFF", 4: "POWER_ON",
    5: "IDLE", 6: "BACKDRIVE", 7: "RUNNING", 8: "UPDATING_FIRMWARE",
}  # fmt: skip
_RUNTIME_STATES = {0: "STOPPING", 1: "STOPPED", 2: "PLAYING", 3: "PAUSING", 4: "PAUSED", 5: "RESUMING"}
#: Digital IO banks: kind -> (number of pins, bit offset in the RTDE digital input/output bit words).
DIGITAL_IO_KINDS = {"standard": (8, 0), "configurable": (8, 8), "tool": (2, 16)}

_POLL_S = 0.002  # one controller tick at 500 Hz
_STATE_SETTLE_S = 0.2  # how long the receive connection may lag the control connection on one event
_UNLOCK_RETRY_S = 0.25


# ---------------------------------------------------------------------------------------------- results


@dataclass(frozen=True, eq=False)
class MotionResult:
    """How a motion ended. ``reached``: the controller finished it (False when ``stop()`` cut it short).
    ``target_error_m``: TCP distance from the target at the end (measured)."""

    kind: str  # "move_l" or "move_j"
    reached: bool
    q: np.ndarray
    T_base_tcp: np.ndarray
    target_error_m: float
    duration_s: float


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
            f"robot mode {_ROBOT_MODES.get(self.robot_mode, self.robot_mode)}, safety mode {self.safety_mode}, "
            f"program {_RUNTIME_STATES.get(self.runtime_state, self.runtime_state)}"
            + (", PROTECTIVE STOP" if self.protective_stopped else "")
            + (", EMERGENCY STOP" if self.emergency_stopped else "")
            + ("" if self.connected else ", link DOWN")
        )


@dataclass
class _Pending:
    kind: str
    T_target: np.ndarray
    op_id_before: int
    started_s: float
    deadline_s: float
    stopped: bool = False


# ---------------------------------------------------------------------------------------------- probing


def probe_rtde(host: str, port: int = RTDE_PORT, timeout_s: float = 2.0) -> None:
    """Connects to the RTDE port and asks for protocol version 2, bounded by ``timeout_s`` at every step.

    Written by hand because ur_rtde's constructors have no timeout here: they block (holding the GIL) until the
    controller streams. Raises ``RobotConnectionError`` naming the host and port."""
    try:
        sock = socket.create_connection((host, port), timeout=timeout_s)
    except OSError as exc:
        raise RobotConnectionError(
            f"UR controller {host}: nothing answers on port {port} (RTDE) within {timeout_s:g} s ({exc}); "
            "check the address, the network and that the controller is on"
        ) from exc
    with sock:
        try:
            sock.settimeout(timeout_s)
            sock.sendall(struct.pack(">HBH", 5, ord("V"), 2))  # size (with header), 'V', protocol version 2
            header = _recv_exact(sock, 3)
            size, kind = struct.unpack(">HB", header)
            if kind != ord("V") or size < 4:
                raise RobotConnectionError(
                    f"UR controller {host}:{port} answered the RTDE version request with message type {kind} "
                    "(expected 'V'); is this a UR controller?"
                )
            accepted = _recv_exact(sock, size - 3)[0]
        except TimeoutError as exc:
            raise RobotConnectionError(
                f"UR controller {host}:{port} (RTDE) accepted a connection but did not answer the protocol "
                f"version request within {timeout_s:g} s"
            ) from exc
        except OSError as exc:
            raise RobotConnectionError(f"UR controller {host}:{port} (RTDE): {exc}") from exc
    if not accepted:
        raise RobotConnectionError(f"UR controller {host}:{port} refused RTDE protocol version 2 (software < 3.5?)")


def _recv_exact(sock: socket.socket, n: int) -> bytes:
    data = b""
    while len(data) < n:
        chunk = sock.recv(n - len(data))
        if not chunk:
            raise ConnectionResetError("the controller closed the connection")
        data += chunk
    return data


def _probe_tcp(host: str, port: int, what: str, timeout_s: float) -> None:
    try:
        with socket.create_connection((host, port), timeout=timeout_s):
            pass
    except OSError as exc:
        raise RobotConnectionError(
            f"UR controller {host}: nothing answers on port {port} ({what}) within {timeout_s:g} s ({exc})"
        ) from exc


def _keep_forever(client: object) -> None:
    """Holds a reference that is never released, not even at interpreter shutdown, so the object's C++
    destructor never runs (see ``URRobot._drop_clients``). Costs one socket per dropped link."""
    log.info("keeping a disconnected %s alive for the life of the process (its destructor would abort)", client)
    ctypes.pythonapi.Py_IncRef(ctypes.py_object(client))


# ---------------------------------------------------------------------------------------------- the robot


class URRobot:
    """A UR e-Series arm through ur_rtde; see the module docstring. Not connected until ``connect()`` (or
    ``with``). Motion methods may be called from one thread at a time; ``stop()`` from any thread."""

    def __init__(self, config: URConfig) -> None:
        if not isinstance(config, URConfig):
            raise TypeError(f"URRobot needs a URConfig, got {type(config).__name__}")
        self.config = config
        self._T_flange_tcp = np.array(config.T_flange_tcp)
        self._r: Any = None
        self._c: Any = None
        self._io: Any = None
        self._dash: Any = None
        self._lock = threading.RLock()  # connect/reconnect/recover/motion start
        self._pending: _Pending | None = None
        self._last_ts = -1.0
        self._last_ts_at = 0.0

    # --- lifecycle -------------------------------------------------------------------------------------------
    def __enter__(self) -> URRobot:
        self.connect()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def host(self) -> str:
        return self.config.host

    def connect(self) -> None:
        """Connects the dashboard, receive, control and IO interfaces and sets the TCP.

        Raises ``RobotConnectionError`` (host and port named) when the controller is absent, silent or refuses;
        ``ProtectiveStopError``/``EmergencyStopError`` when it is safety-stopped (the dashboard and receive
        interfaces stay connected: ``recover()`` finishes the connection after a protective stop)."""
        import dashboard_client
        import rtde_receive

        cfg = self.config
        with self._lock:
            self._probe()
            if self._dash is None:
                dash = dashboard_client.DashboardClient(cfg.host)
                try:
                    dash.connect(int(cfg.connect_timeout_s * 1000))
                except RuntimeError as exc:
                    raise RobotConnectionError(
                        f"UR controller {cfg.host}: dashboard (port {DASHBOARD_PORT}) connection failed: {exc}"
                    ) from exc
                self._dash = dash
            if self._r is None:
                try:
                    self._r = rtde_receive.RTDEReceiveInterface(
                        cfg.host, self._frequency, [], False, cfg.upper_range_registers
                    )
                except RuntimeError as exc:
                    raise RobotConnectionError(f"UR controller {cfg.host}: RTDE receive interface: {exc}") from exc
            self._mark_fresh()
            status = self.status()
            if status.robot_mode != ROBOT_MODE_RUNNING:
                raise RobotConnectionError(
                    f"UR controller {cfg.host}: robot mode is {_ROBOT_MODES.get(status.robot_mode, status.robot_mode)}"
                    ", not RUNNING: power it on and release the brakes (pendant, or dashboard 'power on' and "
                    "'brake release')"
                )
            self._raise_if_safety_stopped("connecting")
            self._connect_control()
            log.info("connected to UR controller %s (%s)", cfg.host, self.status().describe())

    def close(self) -> None:
        """Stops a motion in flight, optionally the control script, and disconnects everything (errors ignored)."""
        with self._lock:
            if self._pending is not None and self._c is not None and self._link_ok():
                with contextlib.suppress(RuntimeError):
                    self.stop()
            link_ok = self._r is not None and self._link_ok()
            if self._c is not None and self.config.stop_script_on_close and link_ok:
                with contextlib.suppress(RuntimeError):
                    self._c.stopScript()
            self._drop_clients(link_ok)
            self._pending = None

    def is_connected(self) -> bool:
        """All interfaces up and the controller's state advancing."""
        return self._c is not None and self._io is not None and self._link_ok()

    def reconnect(self) -> None:
        """Re-establishes every interface after a dropped link (or a restarted controller), then sets the TCP.
        Raises ``RobotConnectionError`` when the controller does not answer (the old interfaces are kept, so a
        later call can try again)."""
        with self._lock:
            log.warning("reconnecting to UR controller %s", self.host)
            link_ok = self._r is not None and self._link_ok()
            self._pending = None
            self._probe()
            # Rebuilt rather than ur_rtde's reconnect(): on a live link that crashed the process (segfault or abort
            # in 2 of 3 test runs, ur_rtde 1.6.5); rebuilding did not in 20 reconnects (10 live, 10 after a restart).
            self._drop_clients(link_ok)
            self.connect()

    # --- state -----------------------------------------------------------------------------------------------
    def q(self) -> np.ndarray:
        """Measured joint angles (6,) rad. ``ConnectionLostError`` when the received state is not current."""
        self._raise_if_link_lost("reading the joints")
        return np.array(self._r.getActualQ(), dtype=float)

    def T_base_tcp(self) -> np.ndarray:
        """Measured TCP pose in the base frame (the controller's active TCP, ``T_flange_tcp``).
        ``ConnectionLostError`` when the received state is not current."""
        self._raise_if_link_lost("reading the TCP pose")
        return pose_to_T(np.array(self._r.getActualTCPPose(), dtype=float))

    def T_base_flange(self) -> np.ndarray:
        return self.T_base_tcp() @ invert(self._T_flange_tcp)

    @property
    def T_flange_tcp(self) -> np.ndarray:
        return self._T_flange_tcp.copy()

    def status(self) -> RobotStatus:
        r = self._receive()
        runtime = int(r.getRuntimeState())
        return RobotStatus(
            connected=self._link_ok(),
            robot_mode=int(r.getRobotMode()),
            safety_mode=int(r.getSafetyMode()),
            runtime_state=runtime,
            protective_stopped=bool(r.isProtectiveStopped()),
            emergency_stopped=bool(r.isEmergencyStopped()),
            program_running=runtime == RUNTIME_PLAYING,
        )

    def is_protective_stopped(self) -> bool:
        return bool(self._receive().isProtectiveStopped())

    # --- checks (public so a planner can ask before committing) --------------------------------------------------
    def ik(self, T_base_tcp: np.ndarray, q_near: np.ndarray | None = None) -> np.ndarray | None:
        """The joint solution for ``T_base_tcp`` (with this robot's TCP) nearest ``q_near`` (default: the current
        joints) within the joint limits less the margin, or None. Local closed-form IK: no controller round trip,
        and an unreachable pose cannot halt the control script as the controller's IK would."""
        T = check_rigid(T_base_tcp)
        q_ref = self.q() if q_near is None else np.asarray(q_near, dtype=float)
        return ik_nearest(T, q_ref, self._T_flange_tcp, self.config.joint_limits_with_margin_rad)

    def check_pose(self, T_base_tcp: np.ndarray) -> None:
        """``OutsideWorkspaceError`` when the TCP position of ``T_base_tcp`` is outside the workspace box."""
        check_target_in_workspace(self.config, T_base_tcp)

    def check_joint_path(self, q_from: np.ndarray, q_to: np.ndarray) -> None:
        """``OutsideWorkspaceError`` when the TCP leaves the box along movej's path; ``MotionRefusedError`` when
        ``q_to`` is outside the joint limits less the margin."""
        check_joint_path(self.config, self._T_flange_tcp, q_from, q_to)

    # --- motion ----------------------------------------------------------------------------------------------
    def move_l(
        self, T_base_tcp: np.ndarray, speed_m_s: float | None = None, accel_m_s2: float | None = None
    ) -> MotionResult:
        """Straight-line TCP move to ``T_base_tcp``; blocks until the arm is there. See the module docstring for
        what it raises."""
        self.start_move_l(T_base_tcp, speed_m_s, accel_m_s2)
        return self.wait_for_motion()

    def move_j(
        self, q: np.ndarray, speed_rad_s: float | None = None, accel_rad_s2: float | None = None
    ) -> MotionResult:
        """Joint-space move to ``q`` (6,) rad; blocks until the arm is there."""
        self.start_move_j(q, speed_rad_s, accel_rad_s2)
        return self.wait_for_motion()

    def move_j_to_pose(
        self,
        T_base_tcp: np.ndarray,
        speed_rad_s: float | None = None,
        accel_rad_s2: float | None = None,
        q_near: np.ndarray | None = None,
    ) -> MotionResult:
        """Joint-space move to the IK solution of ``T_base_tcp`` nearest ``q_near`` (default: the current joints);
        ``UnreachableError`` when there is none."""
        self.start_move_j_to_pose(T_base_tcp, speed_rad_s, accel_rad_s2, q_near)
        return self.wait_for_motion()

    def start_move_l(
        self, T_base_tcp: np.ndarray, speed_m_s: float | None = None, accel_m_s2: float | None = None
    ) -> None:
        """Checks and sends a linear move without waiting; finish with ``wait_for_motion()``."""
        cfg = self.config
        v = check_rate(speed_m_s, cfg.linear_speed_m_s, cfg.max_linear_speed_m_s, "speed_m_s")
        a = check_rate(accel_m_s2, cfg.linear_accel_m_s2, cfg.max_linear_accel_m_s2, "accel_m_s2")
        T = check_rigid(T_base_tcp)
        check_target_in_workspace(cfg, T)
        with self._lock:
            self._ensure_ready()
            T_now = self.T_base_tcp()
            distance = float(np.linalg.norm(T[:3, 3] - T_now[:3, 3]))
            angle = math.radians(rotation_angle_deg(T_now[:3, :3], T[:3, :3]))
            duration = max(trapezoid_duration_s(distance, v, a), trapezoid_duration_s(angle, v, a))
            pose = T_to_pose(T).tolist()
            self._send("move_l", T, duration, lambda: self._c.moveL(pose, v, a, True))

    def start_move_j(self, q: np.ndarray, speed_rad_s: float | None = None, accel_rad_s2: float | None = None) -> None:
        """Checks and sends a joint move without waiting; finish with ``wait_for_motion()``."""
        cfg = self.config
        v = check_rate(speed_rad_s, cfg.joint_speed_rad_s, cfg.max_joint_speed_rad_s, "speed_rad_s")
        a = check_rate(accel_rad_s2, cfg.joint_accel_rad_s2, cfg.max_joint_accel_rad_s2, "accel_rad_s2")
        q_to = check_joint_target(cfg, q)
        with self._lock:
            self._ensure_ready()
            q_from = self.q()
            check_joint_path(cfg, self._T_flange_tcp, q_from, q_to)
            duration = trapezoid_duration_s(float(np.max(np.abs(q_to - q_from))), v, a)
            T = forward_kinematics(q_to, self._T_flange_tcp)
            self._send("move_j", T, duration, lambda: self._c.moveJ(q_to.tolist(), v, a, True))

    def start_move_j_to_pose(
        self,
        T_base_tcp: np.ndarray,
        speed_rad_s: float | None = None,
        accel_rad_s2: float | None = None,
        q_near: np.ndarray | None = None,
    ) -> None:
        """Checks and sends a joint move to the IK solution of ``T_base_tcp`` without waiting."""
        T = check_rigid(T_base_tcp)
        check_target_in_workspace(self.config, T)
        if q_near is None:
            with self._lock:
                self._ensure_ready()  # the IK starts from the current joints: make sure they are current
        q = self.ik(T, q_near)
        if q is None:
            raise UnreachableError(
                f"no IK solution for TCP pose {np.round(T_to_pose(T), 4).tolist()} (UR pose) within the joint "
                f"limits less {self.config.joint_limit_margin_rad:g} rad; nothing was sent"
            )
        self.start_move_j(q, speed_rad_s, accel_rad_s2)

    def wait_for_motion(self, timeout_s: float | None = None) -> MotionResult:
        """Waits for the motion in flight to end; see the module docstring for the errors. ``timeout_s``
        overrides the one derived from the motion's duration."""
        pending = self._pending
        if pending is None:
            raise RobotError("wait_for_motion: no motion in flight (start_move_* first)")
        deadline = pending.deadline_s if timeout_s is None else time.monotonic() + timeout_s
        try:
            while True:
                self._raise_if_link_lost(f"during {pending.kind}")
                self._raise_if_safety_stopped(f"during {pending.kind}")
                runtime = int(self._r.getRuntimeState())
                status = self._c.getAsyncOperationProgressEx()
                finished = status.operationId() != pending.op_id_before and not status.isAsyncOperationRunning()
                if runtime != RUNTIME_PLAYING or (finished and not self._c.isProgramRunning()):
                    self._raise_program_stopped(f"during {pending.kind}", runtime)
                if finished:
                    break
                if time.monotonic() > deadline:
                    with contextlib.suppress(RuntimeError):
                        self._stop_now(pending)
                    raise MotionFailedError(
                        f"{pending.kind} did not finish within {deadline - pending.started_s:.1f} s; stopped",
                        *self._where_now(),
                    )
                time.sleep(_POLL_S)
            self._settle_receive()
            # The receive connection may show a safety stop a package after the control connection saw the end.
            self._raise_if_safety_stopped(f"at the end of {pending.kind}")
            T_end = self.T_base_tcp()
            return MotionResult(
                kind=pending.kind,
                reached=not pending.stopped,
                q=self.q(),
                T_base_tcp=T_end,
                target_error_m=float(np.linalg.norm(T_end[:3, 3] - pending.T_target[:3, 3])),
                duration_s=time.monotonic() - pending.started_s,
            )
        finally:
            self._pending = None

    def stop(self, decel: float | None = None) -> None:
        """Decelerates the motion in flight to rest (``stopJ`` after a joint move, ``stopL`` after a linear one);
        ``decel`` in rad/s^2 or m/s^2. Safe to call from another thread while ``wait_for_motion`` runs, and when
        nothing moves."""
        pending = self._pending
        if self._c is None or not self._c.isProgramRunning():
            return  # no program, no programmed motion (and a stop command would wait for one)
        if pending is None:
            self._c.stopJ(decel or self.config.stop_decel_rad_s2, False)
            return
        self._stop_now(pending, decel)

    def recover(self, timeout_s: float | None = None) -> None:
        """Back to a running control program with the TCP set: reconnects when the link is down, unlocks a
        protective stop through the dashboard (retrying while the controller refuses, e.g. within 5 s of the stop
        on e-Series), re-uploads the control script and waits for it to run. Raises ``RecoveryError`` on an
        emergency stop or when ``timeout_s`` (default ``recovery_timeout_s``) passes."""
        timeout_s = self.config.recovery_timeout_s if timeout_s is None else timeout_s
        deadline = time.monotonic() + timeout_s
        with self._lock:
            self._pending = None
            if self._r is None or self._dash is None or not self._link_ok():
                try:
                    self.reconnect()
                except (ProtectiveStopError, RobotConnectionError) as exc:
                    if not isinstance(exc, ProtectiveStopError):
                        raise RecoveryError(f"recover: cannot reach UR controller {self.host}: {exc}") from exc
            if self._r.isEmergencyStopped():
                raise RecoveryError(
                    f"UR controller {self.host} is emergency-stopped: release the e-stop button and reset on the "
                    "pendant, then call recover() again"
                )
            if self._r.isProtectiveStopped():
                self._unlock_protective_stop(deadline)
            if self._c is None:
                try:
                    self._connect_control()
                except RobotConnectionError as exc:
                    raise RecoveryError(f"recover: {exc}") from exc
            elif not self._c.isProgramRunning():
                self._restart_program(deadline)
            self._apply_tcp()
            log.info("UR controller %s recovered (%s)", self.host, self.status().describe())

    # --- TCP and IO ------------------------------------------------------------------------------------------
    def set_tcp(self, T_flange_tcp: np.ndarray) -> None:
        """Sets the controller's TCP (and the one used for IK and the workspace check)."""
        T = np.array(T_flange_tcp, dtype=float)
        if T.shape != (4, 4) or not is_rigid(T):
            raise MotionRefusedError(f"T_flange_tcp must be a 4x4 rigid transform, got {T.tolist()}")
        with self._lock:
            self._T_flange_tcp = T
            if self._c is not None:
                self._apply_tcp()

    def set_digital_out(self, index: int, value: bool, kind: str = "standard", confirm_timeout_s: float = 0.5) -> None:
        """Sets a digital output through rtde_io (``kind``: standard 0-7, configurable 0-7, tool 0-1) and waits
        until the received state shows it (``confirm_timeout_s``; 0 to not wait)."""
        bit = self._io_bit(index, kind)
        io = self._require(self._io, "rtde_io")
        setter = {
            "standard": io.setStandardDigitalOut,
            "configurable": io.setConfigurableDigitalOut,
            "tool": io.setToolDigitalOut,
        }[kind]
        if not setter(index, bool(value)):
            raise RobotError(f"UR controller {self.host}: setting {kind} digital output {index} failed")
        end = time.monotonic() + confirm_timeout_s
        while confirm_timeout_s > 0 and self.digital_out(index, kind) != bool(value):
            if time.monotonic() > end:
                raise RobotError(
                    f"UR controller {self.host}: {kind} digital output {index} (bit {bit}) did not read back "
                    f"{bool(value)} within {confirm_timeout_s:g} s"
                )
            time.sleep(_POLL_S)

    def digital_out(self, index: int, kind: str = "standard") -> bool:
        bit = self._io_bit(index, kind)
        return bool((int(self._receive().getActualDigitalOutputBits()) >> bit) & 1)

    def digital_in(self, index: int, kind: str = "standard") -> bool:
        bit = self._io_bit(index, kind)
        return bool((int(self._receive().getActualDigitalInputBits()) >> bit) & 1)

    # --- internals -------------------------------------------------------------------------------------------
    @property
    def _frequency(self) -> float:
        return -1.0 if self.config.rtde_frequency_hz is None else float(self.config.rtde_frequency_hz)

    def _probe(self) -> None:
        probe_rtde(self.host, RTDE_PORT, self.config.connect_timeout_s)
        _probe_tcp(self.host, DASHBOARD_PORT, "dashboard", self.config.connect_timeout_s)

    def _connect_control(self) -> None:
        import rtde_control
        import rtde_io

        cfg = self.config
        flags = rtde_control.RTDEControlInterface.FLAG_UPLOAD_SCRIPT
        if cfg.upper_range_registers:
            flags |= rtde_control.RTDEControlInterface.FLAG_UPPER_RANGE_REGISTERS
        if self._c is None:
            try:
                self._c = rtde_control.RTDEControlInterface(cfg.host, self._frequency, flags)
            except RuntimeError as exc:
                raise RobotConnectionError(
                    f"UR controller {cfg.host}: RTDE control interface (ports {RTDE_PORT}, 30003, "
                    f"{DASHBOARD_PORT}): {exc}"
                ) from exc
        if self._io is None:
            try:
                self._io = rtde_io.RTDEIOInterface(cfg.host, False, cfg.upper_range_registers)
            except RuntimeError as exc:
                raise RobotConnectionError(f"UR controller {cfg.host}: RTDE IO interface: {exc}") from exc
        deadline = time.monotonic() + cfg.program_start_timeout_s
        if not self._c.isProgramRunning():
            self._restart_program(deadline)
        self._apply_tcp()

    def _drop_clients(self, link_ok: bool) -> None:
        """Disconnects and forgets every interface.

        ur_rtde 1.6.5's destructors disconnect again, and an exception there (a write on a closed socket) aborts
        the whole process (std::terminate; seen with ``RTDEIOInterface`` on any dead link and with
        ``RTDEControlInterface`` whose disconnect had failed). So an interface whose ``disconnect()`` raised is
        never destroyed (``_keep_forever``), and ``RTDEIOInterface`` on a dead link is not even disconnected: its
        disconnect waits, with no timeout, for the reply to an RTDE pause request."""
        if self._io is not None and not link_ok:
            _keep_forever(self._io)
            self._io = None
        for client in (self._dash, self._io, self._c, self._r):
            if client is None:
                continue
            try:
                client.disconnect()
            except RuntimeError as exc:
                log.info("%s.disconnect() failed: %s", type(client).__name__, exc)
                _keep_forever(client)
        self._dash = self._io = self._c = self._r = None

    def _apply_tcp(self) -> None:
        if not self._c.setTcp(T_to_pose(self._T_flange_tcp).tolist()):
            raise RobotError(f"UR controller {self.host}: setTcp failed (is the control script running?)")

    def _receive(self) -> Any:
        return self._require(self._r, "rtde_receive")

    def _require(self, client: Any, what: str) -> Any:
        if client is None:
            raise ConnectionLostError(f"UR controller {self.host}: not connected ({what}); call connect()")
        return client

    def _mark_fresh(self) -> None:
        self._last_ts = float(self._r.getTimestamp())
        self._last_ts_at = time.monotonic()

    def _link_ok(self) -> bool:
        """The receive connection is up and the controller's timestamp advanced within the stale timeout."""
        r = self._r
        if r is None or not r.isConnected():
            return False
        ts, now = float(r.getTimestamp()), time.monotonic()
        if ts != self._last_ts:
            self._last_ts, self._last_ts_at = ts, now
            return True
        return now - self._last_ts_at < self.config.stale_state_timeout_s

    def _where_now(self) -> tuple[np.ndarray | None, np.ndarray | None]:
        """``(q, T_base_tcp)`` for an exception: the last received state, or Nones when it is not current."""
        if self._r is None or not self._link_ok():
            return None, None
        return np.array(self._r.getActualQ(), dtype=float), pose_to_T(np.array(self._r.getActualTCPPose()))

    def _raise_if_link_lost(self, when: str) -> None:
        if self._r is None:
            raise ConnectionLostError(f"UR controller {self.host}: not connected ({when}); call connect()")
        if not self._link_ok():
            raise ConnectionLostError(
                f"lost the link to UR controller {self.host} {when} (no state for "
                f"{self.config.stale_state_timeout_s:g} s or socket closed); call recover() or reconnect()"
            )

    def _raise_if_safety_stopped(self, when: str) -> None:
        r = self._r
        if r.isEmergencyStopped():
            raise EmergencyStopError(f"UR controller {self.host} is emergency-stopped ({when})", *self._where_now())
        if r.isProtectiveStopped():
            raise ProtectiveStopError(
                f"UR controller {self.host} is in a protective stop ({when}); call recover(), then re-plan",
                *self._where_now(),
            )

    def _raise_program_stopped(self, when: str, runtime: int) -> None:
        # The receive connection may lag the control one: give it a moment to show a safety stop first.
        end = time.monotonic() + _STATE_SETTLE_S
        while time.monotonic() < end:
            self._raise_if_safety_stopped(when)
            time.sleep(_POLL_S)
        runtime = int(self._r.getRuntimeState())
        raise MotionFailedError(
            f"UR controller {self.host}: the control script stopped {when} (program "
            f"{_RUNTIME_STATES.get(runtime, runtime)}; a script error, a watchdog or a stop from the pendant or "
            "dashboard); call recover()",
            *self._where_now(),
        )

    def _ensure_ready(self) -> None:
        """Before sending: a live link, no safety stop, a running program, no motion in flight."""
        if self._pending is not None:
            raise RobotError(f"a {self._pending.kind} is still in flight: wait_for_motion() or stop() first")
        if self._c is None or self._io is None or not self._link_ok():
            if not self.config.auto_reconnect or self._r is None:
                raise ConnectionLostError(f"not connected to UR controller {self.host}; call connect() or recover()")
            self.reconnect()
        self._raise_if_safety_stopped("before the motion; nothing was sent")
        if not self._c.isProgramRunning():
            runtime = int(self._r.getRuntimeState())
            if not self.config.restart_stopped_program:
                raise MotionFailedError(
                    f"UR controller {self.host}: the control script is not running (program "
                    f"{_RUNTIME_STATES.get(runtime, runtime)}); nothing was sent; call recover()",
                    *self._where_now(),
                )
            log.warning("control script not running (program %s); re-uploading it", _RUNTIME_STATES.get(runtime))
            self._restart_program(time.monotonic() + self.config.program_start_timeout_s)
            self._apply_tcp()

    def _restart_program(self, deadline: float) -> None:
        if not self._c.reuploadScript():
            raise RecoveryError(f"UR controller {self.host}: reuploadScript() failed")
        self._wait_program_running(deadline)

    def _wait_program_running(self, deadline: float) -> None:
        # reuploadScript returns before the state shows the program running (a client race): poll.
        while not self._c.isProgramRunning():
            if time.monotonic() > deadline:
                runtime = int(self._r.getRuntimeState())
                raise RecoveryError(
                    f"UR controller {self.host}: the control script did not start (program "
                    f"{_RUNTIME_STATES.get(runtime, runtime)}; {self.status().describe()})"
                )
            time.sleep(_POLL_S)

    def _unlock_protective_stop(self, deadline: float) -> None:
        dash = self._dash
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
        while self._r.isProtectiveStopped():
            if time.monotonic() > deadline:
                raise RecoveryError(f"UR controller {self.host}: still protective-stopped after {reply!r}")
            time.sleep(_POLL_S)
        log.warning("protective stop on %s unlocked", self.host)

    def _settle_receive(self) -> None:
        """Waits until the receive connection has decoded a package newer than the one seen now (2 ticks)."""
        ts0 = float(self._r.getTimestamp())
        end = time.monotonic() + _STATE_SETTLE_S
        while float(self._r.getTimestamp()) < ts0 + 0.003 and time.monotonic() < end:
            time.sleep(_POLL_S)

    def _send(self, kind: str, T_target: np.ndarray, duration_s: float, command: Any) -> None:
        cfg = self.config
        scaling = float(self._r.getSpeedScaling()) if self._r is not None else 1.0
        timeout = cfg.motion_timeout_factor * duration_s / max(scaling, 0.05) + cfg.motion_timeout_margin_s
        op_id = int(self._c.getAsyncOperationProgressEx().operationId())
        now = time.monotonic()
        try:
            ok = command()
        except RuntimeError as exc:  # the client raises on a broken socket
            raise ConnectionLostError(f"UR controller {self.host}: sending {kind} failed: {exc}") from exc
        if not ok:
            self._settle_receive()
            self._raise_if_link_lost(f"sending {kind}")
            self._raise_if_safety_stopped(f"sending {kind}")
            raise MotionFailedError(
                f"UR controller {self.host} refused {kind} ({self.status().describe()}); call recover()",
                *self._where_now(),
            )
        self._pending = _Pending(kind, np.array(T_target), op_id, now, now + timeout)

    def _stop_now(self, pending: _Pending, decel: float | None = None) -> None:
        pending.stopped = True
        if pending.kind == "move_l":
            self._c.stopL(decel or self.config.stop_decel_m_s2, False)
        else:
            self._c.stopJ(decel or self.config.stop_decel_rad_s2, False)

    @staticmethod
    def _io_bit(index: int, kind: str) -> int:
        if kind not in DIGITAL_IO_KINDS:
            raise ValueError(f"digital IO kind must be one of {sorted(DIGITAL_IO_KINDS)}, got {kind!r}")
        count, offset = DIGITAL_IO_KINDS[kind]
        if not (isinstance(index, int) and 0 <= index < count):
            raise ValueError(f"{kind} digital IO index must be 0..{count - 1}, got {index!r}")
        return offset + index
