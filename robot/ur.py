"""The UR5e over ur_rtde: checked motion with 4x4 poses, safety recovery, digital IO.

``URRobot`` drives a Universal Robots e-Series arm through the stock ``ur_rtde`` client. It talks to whatever
answers on ``URConfig.host``: a real UR5e, or ``sim.controller`` on a loopback address. Poses are 4x4 ``T_base_tcp``
in the controller's base frame; UR rotation-vector poses exist only inside the adapter (``pose_to_T``/``T_to_pose``
from ``sygrid.robots.kinematics``).

Where each part lives: ``robot.ur_config`` (``URConfig``, ``WorkspaceBox`` and the checks before anything is
sent), ``robot.ur_errors`` (the errors), ``robot.ur_connection`` (the clients, bounded connect, reconnect and
recovery), ``robot.ur_motion`` (a motion in flight, watched until it ends, and ``MotionResult``), ``robot.ur_force``
(force-limited motion: move until contact, a linear move in force mode).

API (all lengths m, angles rad, times s)::

    with URRobot(URConfig(host="192.168.1.10", workspace=WorkspaceBox((-0.8, -0.6, 0.0), (0.2, 0.6, 0.7)),
                          T_flange_tcp=T_flange_tcp)) as robot:       # connect() ... close()
        robot.q(); robot.T_base_tcp(); robot.T_base_flange(); robot.status()
        robot.move_l(T_base_tcp, speed_m_s=None, accel_m_s2=None) -> MotionResult     # blocking
        robot.move_j(q, speed_rad_s=None, accel_rad_s2=None) -> MotionResult
        robot.move_j_to_pose(T_base_tcp, ..., q_near=None) -> MotionResult             # local IK (ik_nearest)
        robot.start_move_l(...) / start_move_j(...) / start_move_j_to_pose(...)        # non-blocking, then
        robot.wait_for_motion(timeout_s=None) -> MotionResult;  robot.stop()           # stop() from any thread
        robot.move_until_contact(direction, speed_m_s, max_travel_m) -> ContactResult   # force-limited contact
        robot.move_l_pressing(T_base_tcp, direction, force_n, speed_m_s=None) -> MotionResult  # in force mode
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

Checks before anything is sent (``robot.ur_config``): the pose is rigid; speed and acceleration are positive and
within the maxima; ``move_j`` targets are within the joint limits (minus a margin); the **TCP stays in the workspace
box** (at the target, and along ``movej``'s joint-space path, sampled; a start outside the box may move in).
"""

from __future__ import annotations

import contextlib
import math
import time
from typing import Any

import numpy as np

from robot.ur_config import (
    URConfig,
    check_joint_path,
    check_joint_target,
    check_rate,
    check_rigid,
    check_target_in_workspace,
    trapezoid_duration_s,
)
from robot.ur_connection import POLL_S, RobotStatus, URConnection
from robot.ur_errors import MotionRefusedError, RobotError, UnreachableError
from robot.ur_force import ContactResult, contact_move, force_mode
from robot.ur_motion import MotionResult, MotionWatch
from sygrid.robots.kinematics import T_to_pose, forward_kinematics, ik_nearest
from sygrid.transforms import invert, is_rigid, pose_difference

__all__ = ["DIGITAL_IO_KINDS", "URRobot"]

#: Digital IO banks: kind -> (number of pins, bit offset in the RTDE digital input/output bit words).
DIGITAL_IO_KINDS = {"standard": (8, 0), "configurable": (8, 8), "tool": (2, 16)}


class URRobot:
    """A UR e-Series arm through ur_rtde; see the module docstring. Not connected until ``connect()`` (or
    ``with``). Motion methods may be called from one thread at a time; ``stop()`` from any thread."""

    def __init__(self, config: URConfig) -> None:
        if not isinstance(config, URConfig):
            raise TypeError(f"URRobot needs a URConfig, got {type(config).__name__}")
        self._link = URConnection(config)
        self._motion = MotionWatch(self._link)

    # --- lifecycle -------------------------------------------------------------------------------------------
    def __enter__(self) -> URRobot:
        self.connect()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def config(self) -> URConfig:
        return self._link.config

    @config.setter
    def config(self, config: URConfig) -> None:
        if not isinstance(config, URConfig):
            raise TypeError(f"URRobot needs a URConfig, got {type(config).__name__}")
        self._link.config = config

    @property
    def host(self) -> str:
        return self._link.host

    def connect(self) -> None:
        """Connects every ur_rtde client and sets the TCP (``URConnection.connect``: ``RobotConnectionError`` when
        the controller is absent, silent or refuses; a safety stop raises its ``MotionFailedError``)."""
        self._link.connect()

    def close(self) -> None:
        """Stops a motion in flight, optionally the control script, and disconnects everything (errors ignored)."""
        with self._link.lock:
            if self._motion.in_flight and self._link.rtde_c is not None and self._link.link_ok():
                with contextlib.suppress(RuntimeError):
                    self._motion.stop()
            self._link.close()
            self._motion.forget()

    def is_connected(self) -> bool:
        """All clients up and the controller's state advancing."""
        return self._link.is_connected()

    def reconnect(self) -> None:
        """Re-establishes every client after a dropped link (or a restarted controller), then sets the TCP.
        Raises ``RobotConnectionError`` when the controller does not answer (a later call can try again)."""
        with self._link.lock:
            self._motion.forget()
            self._link.reconnect()

    def recover(self, timeout_s: float | None = None) -> None:
        """Back to a running control program with the TCP set (``URConnection.recover``): reconnects, unlocks a
        protective stop (retrying while the controller refuses, e.g. within 5 s of the stop on e-Series),
        re-uploads the control script. ``RecoveryError`` on an emergency stop or when ``timeout_s`` (default
        ``recovery_timeout_s``) passes."""
        with self._link.lock:
            self._motion.forget()
            self._link.recover(timeout_s)

    # --- state -----------------------------------------------------------------------------------------------
    def q(self) -> np.ndarray:
        """Measured joint angles (6,) rad. ``ConnectionLostError`` when the received state is not current."""
        return self._link.q()

    def T_base_tcp(self) -> np.ndarray:
        """Measured TCP pose in the base frame (the controller's active TCP, ``T_flange_tcp``).
        ``ConnectionLostError`` when the received state is not current."""
        return self._link.T_base_tcp()

    def T_base_flange(self) -> np.ndarray:
        return self.T_base_tcp() @ invert(self._link.T_flange_tcp)

    @property
    def T_flange_tcp(self) -> np.ndarray:
        return self._link.T_flange_tcp.copy()

    def status(self) -> RobotStatus:
        return self._link.status()

    def is_protective_stopped(self) -> bool:
        return bool(self._link.receiver().isProtectiveStopped())

    # --- checks (public so a planner can ask before committing) --------------------------------------------------
    def ik(self, T_base_tcp: np.ndarray, q_near: np.ndarray | None = None) -> np.ndarray | None:
        """The joint solution for ``T_base_tcp`` (with this robot's TCP) nearest ``q_near`` (default: the current
        joints) within the joint limits less the margin, or None. Local closed-form IK: no controller round trip,
        and an unreachable pose cannot halt the control script as the controller's IK would."""
        T = check_rigid(T_base_tcp)
        q_ref = self.q() if q_near is None else np.asarray(q_near, dtype=float)
        return ik_nearest(T, q_ref, self._link.T_flange_tcp, self.config.joint_limits_with_margin_rad)

    def check_pose(self, T_base_tcp: np.ndarray) -> None:
        """``OutsideWorkspaceError`` when the TCP position of ``T_base_tcp`` is outside the workspace box."""
        check_target_in_workspace(self.config, T_base_tcp)

    def check_joint_path(self, q_from: np.ndarray, q_to: np.ndarray) -> None:
        """``OutsideWorkspaceError`` when the TCP leaves the box along movej's path; ``MotionRefusedError`` when
        ``q_to`` is outside the joint limits less the margin."""
        check_joint_path(self.config, self._link.T_flange_tcp, q_from, q_to)

    # --- motion ----------------------------------------------------------------------------------------------
    def move_l(
        self,
        T_base_tcp: np.ndarray,
        speed_m_s: float | None = None,
        accel_m_s2: float | None = None,
        max_force_n: float | None = None,
        stop_on_contact: bool = False,
    ) -> MotionResult:
        """Straight-line TCP move to ``T_base_tcp``; blocks until the arm is there, or, guarded by ``max_force_n``
        [N], until the TCP force passes it (the arm stopped short: ``contact_force_n`` in the result).
        ``stop_on_contact``: the controller's own contact detection watches the move (against its direction) and
        stops the arm on the tick a contact shows, then moves it back to where the contact began: no round trip
        through this client, so the arm presses far less into what it met (``contact_force_n`` is the TCP force
        read when the client learnt of it). See the module docstring for what it raises."""
        if max_force_n is not None and not (math.isfinite(max_force_n) and max_force_n > 0):
            raise MotionRefusedError(f"max_force_n must be a positive number of newtons, got {max_force_n!r}")
        direction = _travel_direction(self.T_base_tcp(), T_base_tcp) if stop_on_contact else None
        self.start_move_l(T_base_tcp, speed_m_s, accel_m_s2)
        if direction is not None:
            self._link.rtde_c.startContactDetection([*direction, 0.0, 0.0, 0.0])
        return self._motion.wait(max_force_n=max_force_n, detecting_contact=direction is not None)

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
        with self._link.lock:
            self._ensure_ready()
            T_now = self.T_base_tcp()
            distance, angle = pose_difference(T_now, T)
            duration = max(trapezoid_duration_s(distance, v, a), trapezoid_duration_s(angle, v, a))
            pose = T_to_pose(T).tolist()
            self._motion.send("move_l", T, duration, lambda: self._link.rtde_c.moveL(pose, v, a, True))

    def start_move_j(self, q: np.ndarray, speed_rad_s: float | None = None, accel_rad_s2: float | None = None) -> None:
        """Checks and sends a joint move without waiting; finish with ``wait_for_motion()``."""
        cfg = self.config
        v = check_rate(speed_rad_s, cfg.joint_speed_rad_s, cfg.max_joint_speed_rad_s, "speed_rad_s")
        a = check_rate(accel_rad_s2, cfg.joint_accel_rad_s2, cfg.max_joint_accel_rad_s2, "accel_rad_s2")
        q_to = check_joint_target(cfg, q)
        with self._link.lock:
            self._ensure_ready()
            q_from = self.q()
            check_joint_path(cfg, self._link.T_flange_tcp, q_from, q_to)
            duration = trapezoid_duration_s(float(np.max(np.abs(q_to - q_from))), v, a)
            T = forward_kinematics(q_to, self._link.T_flange_tcp)
            self._motion.send("move_j", T, duration, lambda: self._link.rtde_c.moveJ(q_to.tolist(), v, a, True))

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
            with self._link.lock:
                self._ensure_ready()  # the IK starts from the current joints: make sure they are current
        q = self.ik(T, q_near)
        if q is None:
            raise UnreachableError(
                f"no IK solution for TCP pose {np.round(T_to_pose(T), 4).tolist()} (UR pose) within the joint "
                f"limits less {self.config.joint_limit_margin_rad:g} rad; nothing was sent"
            )
        self.start_move_j(q, speed_rad_s, accel_rad_s2)

    # --- force-limited motion (robot.ur_force) -------------------------------------------------------------
    def move_until_contact(
        self, direction: np.ndarray, speed_m_s: float, max_travel_m: float, accel_m_s2: float | None = None
    ) -> ContactResult:
        """Straight along ``direction`` (base frame, any length) at ``speed_m_s`` (at most ``max_contact_speed_m_s``)
        until the controller's TCP force shows a contact, then back to where it began; blocks. ``NoContactError``
        when nothing is met within ``max_travel_m`` (the program is stopped: ``recover()``); the other errors as
        ``move_l``. The end of the whole travel must lie in the workspace box."""
        with self._link.lock:
            self._ensure_ready()
            return contact_move(self._link, direction, speed_m_s, max_travel_m, accel_m_s2)

    def move_l_pressing(
        self,
        T_base_tcp: np.ndarray,
        direction: np.ndarray,
        force_n: float,
        speed_m_s: float | None = None,
        accel_m_s2: float | None = None,
        max_press_speed_m_s: float | None = None,
    ) -> MotionResult:
        """A linear move to ``T_base_tcp`` in force mode: compliant along ``direction`` (base frame), pushing with
        ``force_n`` (at most ``max_press_force_n``) along it, which the target's own motion should not move along.
        Force mode ends whatever happens. Errors as ``move_l``."""
        with self._link.lock:
            self._ensure_ready()
        with force_mode(self._link, direction, force_n, max_press_speed_m_s):
            self.start_move_l(T_base_tcp, speed_m_s, accel_m_s2)
            return self.wait_for_motion()

    def wait_for_motion(self, timeout_s: float | None = None, max_force_n: float | None = None) -> MotionResult:
        """Waits for the motion in flight to end (``robot.ur_motion``); see the module docstring for the errors.
        ``timeout_s`` overrides the one derived from the motion's duration; ``max_force_n`` guards it."""
        return self._motion.wait(timeout_s, max_force_n)

    def stop(self, decel: float | None = None) -> None:
        """Decelerates the motion in flight to rest (``stopJ`` after a joint move, ``stopL`` after a linear one);
        ``decel`` in rad/s^2 or m/s^2. Safe to call from another thread while ``wait_for_motion`` runs, and when
        nothing moves."""
        self._motion.stop(decel)

    # --- TCP and IO ------------------------------------------------------------------------------------------
    def set_tcp(self, T_flange_tcp: np.ndarray) -> None:
        """Sets the controller's TCP (and the one used for IK and the workspace check)."""
        T = np.array(T_flange_tcp, dtype=float)
        if T.shape != (4, 4) or not is_rigid(T):
            raise MotionRefusedError(f"T_flange_tcp must be a 4x4 rigid transform, got {T.tolist()}")
        self._link.set_tcp(T)

    def set_digital_out(self, index: int, value: bool, kind: str = "standard", confirm_timeout_s: float = 0.5) -> None:
        """Sets a digital output through rtde_io (``kind``: standard 0-7, configurable 0-7, tool 0-1) and waits
        until the received state shows it (``confirm_timeout_s``; 0 to not wait)."""
        bit = _io_bit(index, kind)
        io: Any = self._link.require(self._link.rtde_io, "rtde_io")
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
            time.sleep(POLL_S)

    def digital_out(self, index: int, kind: str = "standard") -> bool:
        bit = _io_bit(index, kind)
        return bool((int(self._link.receiver().getActualDigitalOutputBits()) >> bit) & 1)

    def digital_in(self, index: int, kind: str = "standard") -> bool:
        bit = _io_bit(index, kind)
        return bool((int(self._link.receiver().getActualDigitalInputBits()) >> bit) & 1)

    # --- internals -------------------------------------------------------------------------------------------
    def _ensure_ready(self) -> None:
        """Before sending: no motion in flight, then a live link, no safety stop, a running program."""
        self._motion.require_idle()
        self._link.make_ready()


def _io_bit(index: int, kind: str) -> int:
    if kind not in DIGITAL_IO_KINDS:
        raise ValueError(f"digital IO kind must be one of {sorted(DIGITAL_IO_KINDS)}, got {kind!r}")
    count, offset = DIGITAL_IO_KINDS[kind]
    if not (isinstance(index, int) and 0 <= index < count):
        raise ValueError(f"{kind} digital IO index must be 0..{count - 1}, got {index!r}")
    return offset + index


def _travel_direction(T_from: np.ndarray, T_to: np.ndarray) -> list[float] | None:
    """The unit vector (base frame) a straight line from ``T_from`` to ``T_to`` travels along; None in place."""
    travel = np.asarray(T_to, dtype=float)[:3, 3] - np.asarray(T_from, dtype=float)[:3, 3]
    norm = float(np.linalg.norm(travel))
    return (travel / norm).tolist() if norm > 1e-9 else None
