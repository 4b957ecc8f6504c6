"""Runs an ``ArmBackend`` for the controller tick: inline when stepping is cheap, or in its own thread when a step
can block (MuJoCo shares its lock with the camera renderer), so a slow step never delays the 500 Hz stream.

Threaded mode: the tick queues one ``(q, qd)`` target per 2 ms and reads the latest sample without waiting. The
stepper thread replays every queued target in order (each for one controller period of physics, ``CHUNK_TARGETS`` per
backend call), so simulated time stays tied to the commanded trajectory. The controller withholds new targets while
the stepper trails (``lag_targets``; ``sim.controller.controller``'s pacing), so on a machine too slow for real time
the simulation runs slower than the clock instead of falling behind it. Past ``max_lag_s`` (a caller that pushes
without pacing) the oldest targets are dropped (logged) as a last bound: the arm then jumps. Gripper commands go into
the same queue and run between the targets they came between: a gripper closed after the arm arrived (by the
controller's clock) closes after the simulated arm arrived too, however far the simulation trails.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from collections.abc import Callable

import numpy as np

from sim.controller.backend import ArmBackend, ArmSample

log = logging.getLogger(__name__)

CONTROLLER_PERIOD_S = 0.002
#: Targets the stepper simulates per backend call: the sample the tick reads is at most this many periods old when
#: the stepper keeps up, and a trailing stepper catches up in chunks instead of one long call.
CHUNK_TARGETS = 10


class BackendRunner:
    """Owns every call into the backend."""

    def __init__(self, backend: ArmBackend, threaded: bool | None = None, max_lag_s: float = 0.5) -> None:
        self.backend = backend
        self.threaded = backend.step_may_block if threaded is None else threaded
        self.steps_per_target = max(1, round(CONTROLLER_PERIOD_S / backend.dt_s))
        self._max_targets = max(1, int(max_lag_s / CONTROLLER_PERIOD_S))
        self._lock = threading.Lock()  # guards the queues and, inline, the backend itself
        # targets (q, qd) and ops (callables), in the order they were handed over
        self._queue: collections.deque[tuple[np.ndarray, np.ndarray] | Callable[[], None]] = collections.deque()
        self._n_targets = 0  # handed over and not yet simulated, the stepper's current chunk included
        self._in_flight = 0  # targets of the chunk the stepper is simulating
        self._ops: list[Callable[[], None]] = []  # inline mode: run before the next step
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._latest = backend.sample()
        self.dropped_targets = 0
        self.max_advance_s = 0.0
        self.advance_calls = 0

    def start(self) -> None:
        if self.threaded and self._thread is None:
            self._thread = threading.Thread(target=self._run, name="backend-stepper", daemon=True)
            self._thread.start()

    def stop(self, timeout_s: float = 2.0) -> None:
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout_s)
            if self._thread.is_alive():
                log.warning("backend stepper still busy after %.1f s; leaving it (daemon thread)", timeout_s)
            self._thread = None

    def latest(self) -> ArmSample:
        return self._latest

    @property
    def lag_targets(self) -> int:
        """Targets handed over and not yet simulated, the chunk being simulated included (each one 2 ms of simulated
        time): how far the simulated arm trails the controller."""
        return self._n_targets

    def push_target(self, q: np.ndarray, qd: np.ndarray) -> ArmSample:
        """Hands one tick's target to the backend; returns the newest sample available now."""
        if not self.threaded:
            with self._lock:
                ops, self._ops = self._ops, []
                for op in ops:
                    op()
                self._latest = self._timed_advance([(q, qd)])
            return self._latest
        with self._lock:
            self._queue.append((q, qd))
            self._n_targets += 1
            if self._n_targets > self._max_targets:
                self._drop_oldest_target()
                self.dropped_targets += 1
                if self.dropped_targets == 1 or self.dropped_targets % 500 == 0:
                    log.warning(
                        "backend is %.1f s behind the controller; dropped %d targets so far",
                        self._max_targets * CONTROLLER_PERIOD_S,
                        self.dropped_targets,
                    )
        self._wake.set()
        return self._latest

    def call(self, op: Callable[[], None]) -> None:
        """Runs ``op`` (e.g. a gripper command) on the backend after the targets handed over before it."""
        with self._lock:
            if self.threaded:
                self._queue.append(op)
            else:
                self._ops.append(op)
        self._wake.set()

    def _drop_oldest_target(self) -> None:
        for i, item in enumerate(self._queue):
            if isinstance(item, tuple):
                del self._queue[i]
                self._n_targets -= 1
                return

    def reset_arm(self, q: np.ndarray) -> None:
        def _reset() -> None:
            self.backend.reset_arm(q)

        if self.threaded:
            self.call(_reset)
        else:
            with self._lock:
                _reset()
                self._latest = self.backend.sample()

    def _timed_advance(self, targets: list[tuple[np.ndarray, np.ndarray]]) -> ArmSample:
        t0 = time.perf_counter()
        sample = self.backend.advance(targets, self.steps_per_target)
        self.max_advance_s = max(self.max_advance_s, time.perf_counter() - t0)
        self.advance_calls += 1
        return sample

    def _take(self) -> tuple[list[tuple[np.ndarray, np.ndarray]], Callable[[], None] | None]:
        """The next piece of work off the queue: up to ``CHUNK_TARGETS`` targets (stopping at an op), or the op at its
        head. Targets taken still count in ``lag_targets`` until they are simulated."""
        targets: list[tuple[np.ndarray, np.ndarray]] = []
        with self._lock:
            while self._queue and len(targets) < CHUNK_TARGETS:
                if not isinstance(self._queue[0], tuple):
                    if targets:
                        break
                    return targets, self._queue.popleft()  # type: ignore[return-value]
                targets.append(self._queue.popleft())  # type: ignore[arg-type]
            self._in_flight = len(targets)
        return targets, None

    def _run(self) -> None:
        while not self._stop.is_set():
            self._wake.wait(0.05)
            self._wake.clear()
            while not self._stop.is_set():
                targets, op = self._take()
                if not targets and op is None:
                    break
                try:
                    if op is not None:
                        op()
                        self._latest = self.backend.sample()
                    else:
                        self._latest = self._timed_advance(targets)
                except Exception:
                    log.exception("backend step failed; the arm state is frozen at the last good sample")
                    time.sleep(0.1)
                finally:
                    with self._lock:
                        self._n_targets -= self._in_flight
                        self._in_flight = 0
