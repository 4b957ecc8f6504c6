"""What the controller emulator needs from a simulated arm: the ``ArmBackend`` protocol, and ``KinematicBackend``,
a perfect-tracking arm (actual = commanded) for fast protocol tests, optionally above a stiff horizontal surface
that the flange can press on (contact and force-mode tests); ``StallingBackend`` is one whose step sometimes blocks
(load for tests and benchmarks).

The MuJoCo cell implements the same protocol in ``sim.controller.world_backend``; ``sim.controller.backend_by_name``
chooses one by name.
"""

from __future__ import annotations

import dataclasses
import threading
import time
from collections.abc import Sequence
from typing import Protocol

import numpy as np

from sygrid.robots import gripper_2f85, ur5e
from sygrid.robots.kinematics import forward_kinematics

GRIPPER_STROKE_M = gripper_2f85.STROKE_M  # fully open


@dataclasses.dataclass(frozen=True)
class ArmSample:
    """The arm and gripper as the backend last saw them. Arrays are (6,) float64, SI units."""

    time_s: float
    q: np.ndarray
    qd: np.ndarray
    torque: np.ndarray
    collision_force_n: float = 0.0
    collision_geoms: str = ""  # the two geoms of the largest collision contact, for the protective-stop message
    gripper_width_m: float = GRIPPER_STROKE_M
    gripper_target_m: float = GRIPPER_STROKE_M  # the last width commanded through set_gripper
    gripper_moving: bool = False
    gripper_object_detected: bool = False
    #: the external contact wrench on the tool, base frame: force [N], torque [N m] about the flange origin
    tool_wrench: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(6))


class ArmBackend(Protocol):
    """A simulated UR5e the controller drives at its 500 Hz tick."""

    dt_s: float
    """Physics step in [s]; the controller steps ``round(0.002 / dt_s)`` times per tick."""

    step_may_block: bool
    """True when ``advance`` can take longer than a tick (a shared lock, a slow model): the controller then steps
    the backend in its own thread and keeps streaming the latest sample meanwhile."""

    def reset_arm(self, q: np.ndarray) -> None:
        """Puts the arm at rest at ``q``."""

    def advance(self, targets: Sequence[tuple[np.ndarray, np.ndarray]], steps_per_target: int) -> ArmSample:
        """Tracks each ``(q, qd)`` target for ``steps_per_target`` physics steps, in order; returns the new state."""

    def sample(self) -> ArmSample:
        """The current state, without stepping."""

    def set_gripper(self, width_m: float, speed_m_s: float, force_n: float) -> None:
        """Commands the gripper to an opening width."""


class KinematicBackend:
    """Perfect tracking: actual q and qd equal the last target; starts at ``ur5e.HOME_Q`` unless told otherwise.
    The gripper moves at the commanded speed and, when ``object_width_m`` is set, stops on an object of that width
    while closing (``object_detected``). With ``surface_z_m`` the flange origin meets a horizontal surface at that
    base height: below it the tool feels ``surface_stiffness_n_m`` times the depth, upwards (the arm still goes
    where it is told)."""

    step_may_block = False

    def __init__(
        self,
        initial_q: np.ndarray | None = None,
        dt_s: float = 0.002,
        object_width_m: float | None = None,
        surface_z_m: float | None = None,
        surface_stiffness_n_m: float = 2e4,
    ) -> None:
        if dt_s <= 0:
            raise ValueError(f"dt_s must be positive, got {dt_s}")
        self.dt_s = dt_s
        self.object_width_m = object_width_m
        self.surface_z_m, self.surface_stiffness_n_m = surface_z_m, float(surface_stiffness_n_m)
        self._lock = threading.Lock()
        self._time_s = 0.0
        self._q = np.array(ur5e.HOME_Q if initial_q is None else initial_q, dtype=float)
        if self._q.shape != (6,):
            raise ValueError(f"initial_q must have 6 joint angles, got shape {self._q.shape}")
        self._qd = np.zeros(6)
        self._collision_force_n = 0.0
        self._width_m = GRIPPER_STROKE_M
        self._width_target_m = GRIPPER_STROKE_M
        self._gripper_speed_m_s = 0.1
        self._object_detected = False

    def inject_collision_force(self, force_n: float) -> None:
        """Test hook: the contact force this backend reports until set back to 0."""
        with self._lock:
            self._collision_force_n = float(force_n)

    def reset_arm(self, q: np.ndarray) -> None:
        with self._lock:
            self._q = np.array(q, dtype=float)
            self._qd = np.zeros(6)

    def set_gripper(self, width_m: float, speed_m_s: float, force_n: float) -> None:
        with self._lock:
            self._width_target_m = float(np.clip(width_m, 0.0, GRIPPER_STROKE_M))
            self._gripper_speed_m_s = max(float(speed_m_s), 1e-3)
            self._object_detected = False

    def advance(self, targets: Sequence[tuple[np.ndarray, np.ndarray]], steps_per_target: int) -> ArmSample:
        with self._lock:
            for q, qd in targets:
                self._q = np.array(q, dtype=float)
                self._qd = np.array(qd, dtype=float)
                for _ in range(steps_per_target):
                    self._step_gripper()
                    self._time_s += self.dt_s
            return self._sample_locked()

    def sample(self) -> ArmSample:
        with self._lock:
            return self._sample_locked()

    def _step_gripper(self) -> None:
        error = self._width_target_m - self._width_m
        if error == 0.0 or self._object_detected:
            return
        step = float(np.clip(error, -self._gripper_speed_m_s * self.dt_s, self._gripper_speed_m_s * self.dt_s))
        new_width = self._width_m + step
        if self.object_width_m is not None and step < 0 and new_width <= self.object_width_m <= self._width_m:
            new_width, self._object_detected = self.object_width_m, True
        self._width_m = new_width

    def _sample_locked(self) -> ArmSample:
        moving = self._width_m != self._width_target_m and not self._object_detected
        return ArmSample(
            time_s=self._time_s,
            q=self._q.copy(),
            qd=self._qd.copy(),
            torque=np.zeros(6),
            collision_force_n=self._collision_force_n,
            gripper_width_m=self._width_m,
            gripper_target_m=self._width_target_m,
            gripper_moving=moving,
            gripper_object_detected=self._object_detected,
            tool_wrench=self._surface_wrench(),
        )

    def _surface_wrench(self) -> np.ndarray:
        wrench = np.zeros(6)
        if self.surface_z_m is not None:
            depth = self.surface_z_m - float(forward_kinematics(self._q)[2, 3])
            wrench[2] = self.surface_stiffness_n_m * max(depth, 0.0)
        return wrench


class StallingBackend(KinematicBackend):
    """A ``KinematicBackend`` whose ``advance`` blocks for ``stall_s`` on every ``every``-th call, like a world whose
    lock a renderer holds; declares ``step_may_block`` so the controller steps it in its own thread."""

    step_may_block = True

    def __init__(self, stall_s: float, every: int, **kwargs: object) -> None:
        if stall_s < 0 or every < 1:
            raise ValueError(f"StallingBackend needs stall_s >= 0 and every >= 1, got {stall_s}, {every}")
        super().__init__(**kwargs)  # type: ignore[arg-type]
        self.stall_s, self.every, self.calls = stall_s, every, 0

    def advance(self, targets: Sequence[tuple[np.ndarray, np.ndarray]], steps_per_target: int) -> ArmSample:
        self.calls += 1
        if self.calls % self.every == 0:
            time.sleep(self.stall_s)
        return super().advance(targets, steps_per_target)
