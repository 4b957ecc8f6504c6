"""What ``EmulatedController.state()`` reports: a picklable snapshot of the controller for tests and the CLI."""

from __future__ import annotations

import dataclasses


@dataclasses.dataclass
class TickStats:
    """Timing of the 500 Hz tick thread, in seconds."""

    ticks: int = 0
    late_ticks: int = 0  # started more than 1 ms after their deadline
    max_lateness_s: float = 0.0
    max_tick_s: float = 0.0  # longest tick body (step + program + snapshot + streaming)
    last_tick_s: float = 0.0
    last_step_s: float = 0.0
    resyncs: int = 0  # ticks so late that the deadline grid was reset
    paced_ticks: int = 0  # ticks that held the motion for a trailing backend: simulated time behind the clock

    def record(self, started_s: float, duration_s: float, deadline_s: float) -> None:
        self.ticks += 1
        lateness = started_s - deadline_s
        if lateness > 1e-3:
            self.late_ticks += 1
        self.max_lateness_s = max(self.max_lateness_s, lateness)
        self.max_tick_s = max(self.max_tick_s, duration_s)
        self.last_tick_s = duration_s


@dataclasses.dataclass(frozen=True)
class ControllerStatus:
    """The emulated controller at one instant. Poses are ``[x, y, z, rx, ry, rz]`` in the controller base frame."""

    host: str
    runtime_state: int
    runtime_name: str
    robot_mode: int
    protective_stopped: bool
    program: str
    register_offset: int
    actual_q: tuple[float, ...]
    target_q: tuple[float, ...]
    actual_tcp_pose: tuple[float, ...]
    tcp_offset: tuple[float, ...]
    payload_kg: float
    digital_output_bits: int
    speed_slider: float
    gripper_width_m: float
    gripper_object_detected: bool
    watchdog_hz: float
    last_error: str
    rtde_connections: int
    rtde_packages_sent: int
    backend_lag_ticks: int
    backend_dropped_targets: int  # targets the backend fell too far behind to play (the world lost real time)
    tick: TickStats
