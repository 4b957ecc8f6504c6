"""``EmulatedController``: a UR e-Series controller on loopback that the stock ur_rtde client drives.

One tick thread runs at 500 Hz on absolute deadlines (a late tick is followed by shorter sleeps, never by drift):
it steps the motion, hands the target to the backend (inline, or to the stepper thread when the backend can
block), checks safety and the watchdog, runs one cycle of the uploaded program, takes one snapshot and streams it
to every started RTDE connection. Socket threads (RTDE, script intake, dashboard, gripper) only exchange data with
the tick under ``self._lock``; sends never block the tick.
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import threading
import time

import numpy as np

from sim.controller.arm import ArmController
from sim.controller.backend import ArmBackend, ArmSample
from sim.controller.dashboard import DashboardServer
from sim.controller.force import tool_contact_steps, wrench_about
from sim.controller.gripper_server import GripperServer
from sim.controller.program import ControlProgram
from sim.controller.rtde_server import RtdeServer
from sim.controller.script_intake import ScriptIntake, UploadedScript
from sim.controller.snapshot import TICK_S, SnapshotBuilder
from sim.controller.state import (
    ROBOT_MODE_RUNNING,
    RUNTIME_NAMES,
    RUNTIME_PAUSED,
    RUNTIME_PLAYING,
    RUNTIME_STOPPED,
    IoState,
    Registers,
    StateSnapshot,
    apply_input_fields,
)
from sim.controller.status import ControllerStatus, TickStats
from sim.controller.stepper import BackendRunner
from sim.controller.tcp_service import start_all
from sygrid.robots.kinematics import forward_kinematics

log = logging.getLogger(__name__)

PROTECTIVE_STOP_FORCE_N = 150.0  # UR5e default force limit of the "normal" safety configuration
#: The force limit acts on the TCP force held over this many ticks (its median): a real controller's force estimate
#: is filtered, and one physics step's contact impulse (a finger tapping a part) is not a force the arm exerts.
TCP_FORCE_WINDOW_TICKS = 5
PROGRAM_STOP_DECEL_RAD_S2 = 10.0  # how fast a stopped program brings the arm to rest
#: Motion advances only while the backend trails by at most this many ticks: a simulation slower than the clock then
#: runs slower (the client sees a slower arm) instead of falling behind, where the arm it reports would trail the
#: controller's and jump when targets are dropped.
MAX_LAG_TICKS = 20
#: Force-sensitive motion (force mode, a move until contact) keeps closer, so that it cannot run on past a contact
#: the backend has not reported yet.
FORCE_MAX_LAG_TICKS = 3
_RESYNC_AFTER_S = 0.05  # a tick later than this resets the deadline grid instead of bursting to catch up
CONTROLLER_VERSION = (5, 15, 0, 106767)


@dataclasses.dataclass(frozen=True)
class ControllerPorts:
    """TCP ports; ur_rtde itself always uses the defaults, so run several cells on distinct 127.0.0.x hosts."""

    rtde: int = 30004
    dashboard: int = 29999
    script: tuple[int, ...] = (30001, 30002, 30003)
    gripper: int = 63352


class EmulatedController:
    """The emulated controller; a context manager (``with EmulatedController(backend) as ctl: ...``)."""

    def __init__(
        self,
        backend: ArmBackend,
        host: str = "127.0.0.1",
        ports: ControllerPorts | None = None,
        protective_stop_force_n: float = PROTECTIVE_STOP_FORCE_N,
        protective_stop_runtime_state: int = RUNTIME_PAUSED,
        unlock_delay_s: float = 0.0,
        fault_hold_s: float = 1.0,
        threaded_backend: bool | None = None,
        serial_number: str = "20235500001",
    ) -> None:
        if protective_stop_runtime_state not in (RUNTIME_PAUSED, RUNTIME_STOPPED):
            raise ValueError(
                f"protective_stop_runtime_state must be {RUNTIME_PAUSED} (PAUSED) or {RUNTIME_STOPPED} (STOPPED), "
                f"got {protective_stop_runtime_state}"
            )
        if protective_stop_force_n <= 0:
            raise ValueError(f"protective_stop_force_n must be positive, got {protective_stop_force_n}")
        self.host = host
        self.ports = ports or ControllerPorts()
        self.protective_stop_force_n = protective_stop_force_n
        self.protective_stop_runtime_state = protective_stop_runtime_state
        self.unlock_delay_s = unlock_delay_s
        self.fault_hold_s = fault_hold_s
        self.serial_number = serial_number
        self.controller_version = CONTROLLER_VERSION
        self.backend = backend
        self._runner = BackendRunner(backend, threaded_backend)
        self._lock = threading.RLock()
        self.regs = Registers()
        self.io = IoState()
        sample = self._runner.latest()
        self.arm = ArmController(sample.q)
        self._actual: ArmSample = sample
        self._history: collections.deque[np.ndarray] = collections.deque(maxlen=1000)
        self._wrench_history: collections.deque[np.ndarray] = collections.deque(maxlen=1000)  # tcp_wrench per tick
        self.program: ControlProgram | None = None
        self.runtime_state = RUNTIME_STOPPED
        self.robot_mode = ROBOT_MODE_RUNNING
        self.protective_stopped = False
        self._protective_stop_time = 0.0
        self._force_recovery = False
        self.last_error = ""
        self._watchdog_hz: float | None = None
        self._last_cmd_write = time.monotonic()
        self._fault_hold: tuple[int, float] | None = None
        self._snapshots = SnapshotBuilder(sample.q)
        self._snapshot = StateSnapshot()
        self._tick_index = 0
        self.stats = TickStats()
        self._stop_event = threading.Event()
        self._thread: threading.Thread | None = None
        self.rtde = RtdeServer(host, self.ports.rtde, self._apply_inputs, self.controller_version)
        self.dashboard = DashboardServer(host, self.ports.dashboard, self)
        self.gripper = GripperServer(host, self.ports.gripper, self._runner)
        self.script = ScriptIntake(host, self.ports.script, self.load_script)

    # --- lifecycle -----------------------------------------------------------------------------------------
    def __enter__(self) -> EmulatedController:
        if self._thread is None:
            self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def start(self) -> None:
        """Binds every port and starts the tick. Raises OSError naming the port when one is taken."""
        start_all([self.rtde, self.dashboard, self.gripper, self.script])
        self._runner.start()
        self._stop_event.clear()
        self._thread = threading.Thread(target=self._tick_loop, name="controller-tick", daemon=True)
        self._thread.start()
        log.info(
            "UR controller emulator on %s: RTDE %d, dashboard %d, script %s, gripper %d",
            self.host,
            self.ports.rtde,
            self.ports.dashboard,
            self.ports.script,
            self.ports.gripper,
        )

    def stop(self) -> None:
        """Stops the tick, closes every connection and joins the threads (each bounded by a timeout)."""
        self._stop_event.set()
        if self._thread is not None:
            self._thread.join(2.0)
            self._thread = None
        for service in (self.rtde, self.dashboard, self.gripper, self.script):
            service.stop()
        self._runner.stop()

    # --- test hooks and queries ----------------------------------------------------------------------------
    def trigger_protective_stop(self, reason: str = "test hook") -> None:
        with self._lock:
            self._enter_protective_stop(reason)

    def state(self) -> ControllerStatus:
        with self._lock:
            s, a = self._snapshot, self._actual
            return ControllerStatus(
                host=self.host,
                runtime_state=self.runtime_state,
                runtime_name=RUNTIME_NAMES[self.runtime_state],
                robot_mode=self.robot_mode,
                protective_stopped=self.protective_stopped,
                program=self.program.name if self.program is not None else "",
                register_offset=(self.program.offset if self.program is not None else 0),
                actual_q=_floats(a.q),
                target_q=_floats(self.arm.target_q),
                actual_tcp_pose=_floats(s.actual_tcp_pose),
                tcp_offset=_floats(self.arm.tcp_pose),
                payload_kg=self.arm.payload_mass_kg,
                digital_output_bits=self.io.digital_output_bits,
                speed_slider=self.io.speed_slider,
                gripper_width_m=float(a.gripper_width_m),
                gripper_object_detected=a.gripper_object_detected,
                watchdog_hz=self._watchdog_hz or 0.0,
                last_error=self.last_error,
                rtde_connections=self.rtde.session_count,
                rtde_packages_sent=self.rtde.packages_sent,
                backend_lag_ticks=self._runner.lag_targets,
                backend_dropped_targets=self._runner.dropped_targets,
                tick=dataclasses.replace(self.stats),
            )

    # --- called by the program and the dashboard (under the lock) -------------------------------------------
    def actual_q(self) -> np.ndarray:
        return self._actual.q

    def actual_torque(self) -> np.ndarray:
        return self._actual.torque

    def q_history(self, steps: int) -> np.ndarray:
        if not self._history:
            return self._actual.q
        return self._history[-1 - min(max(steps, 0), len(self._history) - 1)]

    def tcp_wrench(self) -> np.ndarray:
        """The measured external wrench on the tool (base frame, torque about the active TCP)."""
        return self._wrench_history[-1] if self._wrench_history else np.zeros(6)

    def tcp_force_n(self) -> float:
        """The force the TCP exerts, as the safety system's force limit sees it: the median of the external force's
        magnitude [N] over the last ``TCP_FORCE_WINDOW_TICKS`` ticks."""
        history = self._wrench_history  # indexed from its end: the tick must not copy a thousand entries
        recent = [history[-k] for k in range(1, min(TCP_FORCE_WINDOW_TICKS, len(history)) + 1)]
        return float(np.median([np.linalg.norm(w[:3]) for w in recent])) if recent else 0.0

    def tool_contact(self, direction: np.ndarray, max_steps: int | None = None) -> int:
        """URScript ``tool_contact``: steps back (at most ``max_steps``) to the start of a contact against
        ``direction``, 0 without one."""
        return tool_contact_steps(self._wrench_history, direction, max_steps)

    def set_watchdog(self, min_frequency_hz: float) -> None:
        self._watchdog_hz = min_frequency_hz if min_frequency_hz > 0 else None
        self._last_cmd_write = time.monotonic()
        log.info(
            "RTDE watchdog on input_int_register_%d: %s",
            self._cmd_register,
            f"{min_frequency_hz:g} Hz" if self._watchdog_hz else "off",
        )

    def end_program(self, reason: str, error: bool) -> None:
        """Stops the running (or paused) program; the arm decelerates to rest."""
        if self.program is None or self.runtime_state == RUNTIME_STOPPED:
            return
        (log.error if error else log.info)("program %s stopped: %s", self.program.name, reason)
        if error:
            self.last_error = reason
        self.program.abort()
        self.runtime_state = RUNTIME_STOPPED
        self._watchdog_hz = None
        self._fault_hold = None
        self.arm.stop(PROGRAM_STOP_DECEL_RAD_S2, linear=False)

    def fault_command(self, code: int) -> None:
        self.runtime_state = RUNTIME_PAUSED
        self._fault_hold = (code, time.monotonic() + self.fault_hold_s)

    def pause_program(self) -> bool:
        with self._lock:
            if self.runtime_state != RUNTIME_PLAYING or self.program is None:
                return False
            self.program.abort()
            self.runtime_state = RUNTIME_PAUSED
            self.arm.stop(PROGRAM_STOP_DECEL_RAD_S2, linear=False)
            return True

    def resume_program(self) -> bool:
        with self._lock:
            if self.program is None or self.runtime_state != RUNTIME_PAUSED or self.protective_stopped:
                return False
            self.runtime_state = RUNTIME_PLAYING
            return True

    def stop_program(self, reason: str) -> None:
        with self._lock:
            self.end_program(reason, error=False)

    def unlock_protective_stop(self) -> str:
        """Dashboard ``unlock protective stop``; returns the reply line."""
        with self._lock:
            waited = time.monotonic() - self._protective_stop_time
            if self.protective_stopped and waited < self.unlock_delay_s:
                return (
                    f"Cannot unlock protective stop until {self.unlock_delay_s:g}s after occurrence. "
                    "Always inspect cause of protective stop before unlocking"
                )
            if self.protective_stopped:
                log.info("protective stop released")
                # As a UR's recovery lets the arm move back within its limits: a force limit still exceeded when
                # the stop is released is not a new stop until the force has fallen below the limit once.
                self._force_recovery = True
            self.protective_stopped = False
            return "Protective stop releasing"

    def set_robot_mode(self, mode: int) -> None:
        with self._lock:
            if mode != ROBOT_MODE_RUNNING:
                self.end_program(f"robot mode changed to {mode}", error=False)
                self.arm.halt()
            self.robot_mode = mode

    # --- script intake -------------------------------------------------------------------------------------
    def load_script(self, script: UploadedScript) -> None:
        with self._lock:
            if self.robot_mode != ROBOT_MODE_RUNNING or self.protective_stopped:
                reason = "protective stop active" if self.protective_stopped else f"robot mode {self.robot_mode}"
                log.error("program %s not started: robot not ready (%s)", script.name, reason)
                return
            if self.program is not None and self.runtime_state != RUNTIME_STOPPED:
                log.info("program %s replaced by a new upload", self.program.name)
                self.program.abort()
            self.program = ControlProgram(self.regs, self.arm, self, script.register_offset)
            self.runtime_state = RUNTIME_PLAYING
            self._watchdog_hz = None
            self._fault_hold = None
            log.info("program %s started (register offset %d)", script.name, script.register_offset)

    # --- RTDE inputs (socket threads) ----------------------------------------------------------------------
    @property
    def _cmd_register(self) -> int:
        return self.program.offset if self.program is not None else 0

    def _apply_inputs(self, fields: dict[str, object]) -> None:
        with self._lock:
            apply_input_fields(self.regs, self.io, fields)
            if f"input_int_register_{self._cmd_register}" in fields:
                self._last_cmd_write = time.monotonic()

    # --- the tick ------------------------------------------------------------------------------------------
    def _tick_loop(self) -> None:
        next_s = time.perf_counter()
        while not self._stop_event.is_set():
            started = time.perf_counter()
            try:
                self._tick()
            except Exception:
                log.exception("controller tick failed")
            self.stats.record(started, time.perf_counter() - started, next_s)
            next_s += TICK_S
            delay = next_s - time.perf_counter()
            if delay > 0:
                time.sleep(delay)
            elif -delay > _RESYNC_AFTER_S:
                self.stats.resyncs += 1
                next_s = time.perf_counter()

    def _tick(self) -> None:
        k = self._tick_index
        self._tick_index += 1
        with self._lock:
            # Motion waits (no new target) while the backend trails: simulated time then runs slower than the clock
            # instead of the simulated arm falling behind the controller's (force-sensitive motion: past a contact
            # that is not measured yet)
            max_lag = FORCE_MAX_LAG_TICKS if self.arm.force_sensitive else MAX_LAG_TICKS
            paced = self._runner.lag_targets > max_lag
            if paced:
                self.stats.paced_ticks += 1
            else:
                failure = self.arm.step(TICK_S, self.io.speed_slider, self.tcp_wrench())
                if failure:
                    log.error("motion stopped: %s", failure)
                    self.end_program(failure, error=True)
            q, qd = self.arm.target_q.copy(), self.arm.target_qd.copy()
        sample = self._runner.latest() if paced else self._runner.push_target(q, qd)
        t_step = time.perf_counter()
        with self._lock:
            self._actual = sample
            self._history.append(sample.q)
            self._wrench_history.append(self._tcp_wrench_of(sample))
            self._check_safety(sample)
            if self.program is not None and self.runtime_state == RUNTIME_PLAYING:
                self.program.tick()
            self.arm.update_steady(sample.qd, TICK_S)
            self._snapshot = snapshot = self._snapshots.build(
                k,
                sample,
                self.arm,
                self.io,
                self.regs,
                runtime_state=self.runtime_state,
                robot_mode=self.robot_mode,
                protective_stopped=self.protective_stopped,
                execution_time_s=self.stats.last_tick_s,
                tcp_wrench=self.tcp_wrench(),
                protective_stop_force_n=self.protective_stop_force_n,
            )
        self.rtde.broadcast(snapshot, k)
        self.stats.last_step_s = time.perf_counter() - t_step

    def _check_safety(self, sample: ArmSample) -> None:
        now = time.monotonic()
        limit = self.protective_stop_force_n
        if sample.collision_force_n > limit and not self.protective_stopped:
            self._enter_protective_stop(
                f"contact force {sample.collision_force_n:.1f} N above the {limit:g} N limit"
                + (f" ({sample.collision_geoms})" if sample.collision_geoms else "")
            )
        # The UR's force limit is on the TCP, whatever it touches: pressing a part into the pile stops the arm too.
        tcp_force = self.tcp_force_n()
        self._force_recovery = self._force_recovery and tcp_force > limit
        if tcp_force > limit and not (self.protective_stopped or self._force_recovery):
            self._enter_protective_stop(f"TCP force {tcp_force:.1f} N above the {limit:g} N force limit")
        running = self.program is not None and self.runtime_state == RUNTIME_PLAYING
        if running and self._watchdog_hz and now - self._last_cmd_write > 1.0 / self._watchdog_hz:
            self.end_program(
                f"RTDE watchdog: no input_int_register_{self._cmd_register} update for "
                f"{now - self._last_cmd_write:.3f} s (minimum {self._watchdog_hz:g} Hz)",
                error=True,
            )
        if self._fault_hold is not None and self.runtime_state == RUNTIME_PAUSED:
            code, deadline = self._fault_hold
            if self.regs.input_int[self._cmd_register] != code or now > deadline:
                self._fault_hold = None
                self.runtime_state = RUNTIME_PLAYING

    def _tcp_wrench_of(self, sample: ArmSample) -> np.ndarray:
        if not np.any(sample.tool_wrench):
            return np.zeros(6)
        T_base_flange = forward_kinematics(sample.q)
        p_tcp = (T_base_flange @ self.arm.T_flange_tcp)[:3, 3]
        return wrench_about(sample.tool_wrench, T_base_flange[:3, 3], p_tcp)

    def _enter_protective_stop(self, reason: str) -> None:
        if self.protective_stopped:
            return
        log.warning("protective stop: %s", reason)
        self.protective_stopped = True
        self._protective_stop_time = time.monotonic()
        self.last_error = f"protective stop: {reason}"
        self.arm.hold_at(self._actual.q)
        if self.program is not None and self.runtime_state in (RUNTIME_PLAYING, RUNTIME_PAUSED):
            self.program.abort()
            self.runtime_state = self.protective_stop_runtime_state
            self._fault_hold = None


def _floats(values: object) -> tuple[float, ...]:
    return tuple(float(v) for v in values)  # type: ignore[attr-defined]
