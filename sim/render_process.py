"""The emulated cell's camera rendered in a process of its own, off the emulator's 500 Hz tick.

Rendering a frame takes the CPU and Python's GIL for tens of milliseconds, which in the emulator's process would
delay the tick and its RTDE stream. So the emulator's process only hands out its world's state, and a render process
renders it:

- the emulator's child process runs ``serve_world_state`` in a thread on a pipe of its own: ``("state", version)``
  returns the joint positions ``qpos`` and the simulated time (microseconds of work under ``world.lock``), plus the
  model and the cell's layout when the world was recompiled since ``version`` (``add_parts``);
- the render process (``RenderProcess``, started by the ``ControllerProcess`` that owns the emulator) keeps a
  ``WorldMirror`` (the model, a ``MjData`` at the served ``qpos``) and renders it with ``sim.camera.SimCamera``:
  ``capture`` returns a frame's fields to the caller; ``start_load(rate_hz)`` renders at that rate by itself (the
  load of a perception client, for benchmarks) until ``stop_load``, which returns the frame times [s].

Frames are those ``SimCamera`` renders from the world itself: the same model, the state of one physics step.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing
import os
import threading
import time
from multiprocessing.connection import Connection
from typing import Any

import mujoco
import numpy as np

log = logging.getLogger(__name__)
NO_ANSWER = "render process did not answer"  # begins the error of a call that timed out (callers match it)
RENDER_NICENESS = 10  # added to the render process's niceness where the idle scheduling class is not available


class WorldMirror:
    """What ``SimCamera`` reads of a ``CellWorld`` (``model``, ``data``, ``lock``, ``config``, ``sync_kinematics``),
    held at a state served by the emulator (``set_state``)."""

    def __init__(self, model: mujoco.MjModel, config: Any) -> None:
        self.model, self.config = model, config
        self.data = mujoco.MjData(model)
        self.lock = threading.RLock()

    def set_state(self, qpos: np.ndarray, time_s: float) -> None:
        with self.lock:
            self.data.qpos[:] = qpos
            self.data.time = time_s

    def sync_kinematics(self) -> None:
        with self.lock:
            mujoco.mj_kinematics(self.model, self.data)
            mujoco.mj_camlight(self.model, self.data)


def serve_world_state(conn: Connection, world: Any) -> threading.Thread:
    """Answers a render process's ``("state", version)`` requests on ``conn`` from a daemon thread (see the module
    docstring); returns the thread. Ends when the pipe closes."""

    def serve() -> None:
        version, model = 0, None
        while True:
            try:
                _, known = conn.recv()
            except (EOFError, OSError):
                return
            with world.lock:
                if world.model is not model:
                    model, version = world.model, version + 1
                qpos, time_s = world.data.qpos.copy(), float(world.data.time)
            reply: dict[str, Any] = {"version": version, "qpos": qpos, "time_s": time_s}
            if known != version:
                reply.update(model=model, config=world.config)  # pickled outside the lock
            try:
                conn.send(reply)
            except (OSError, BrokenPipeError):
                return

    thread = threading.Thread(target=serve, name="world-state-server", daemon=True)
    thread.start()
    return thread


class _Renderer:
    """The render process's state: the mirror, one camera per set of camera arguments."""

    def __init__(self, state_conn: Connection) -> None:
        self.state_conn = state_conn
        self.version = 0
        self.mirror: WorldMirror | None = None
        self.cameras: dict[tuple, Any] = {}

    def frame(self, camera_kwargs: dict[str, Any]) -> dict[str, Any]:
        from sim.camera import SimCamera

        self.state_conn.send(("state", self.version))
        state = self.state_conn.recv()
        if "model" in state:
            for camera in self.cameras.values():
                camera.close()
            self.cameras.clear()
            self.mirror = WorldMirror(state["model"], state["config"])
            self.version = state["version"]
        assert self.mirror is not None
        self.mirror.set_state(state["qpos"], state["time_s"])
        key = tuple(sorted(camera_kwargs.items()))
        if key not in self.cameras:
            self.cameras[key] = SimCamera(self.mirror, **camera_kwargs)  # type: ignore[arg-type]
        frame = self.cameras[key].capture()
        return {
            "rgb": frame.rgb,
            "depth_m": frame.depth_m,
            "intrinsics": frame.intrinsics,
            "timestamp_s": frame.timestamp_s,
            "T_base_camera": frame.T_base_camera,
        }


def _lower_priority() -> None:
    """Where cores are short the tick runs first: a frame may wait, a late tick is a fault. Linux's idle
    scheduling class (``SCHED_IDLE``) runs this process only on a core nothing else wants and lets any other task
    take the core back at once, where a niceness only shrinks its share (its slices still delay a waking tick);
    elsewhere the niceness is raised by ``RENDER_NICENESS``."""
    try:
        os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
    except (AttributeError, OSError):  # not Linux, or refused
        os.nice(RENDER_NICENESS)


def _render_main(conn: Connection, state_conn: Connection) -> None:
    os.environ.setdefault("LP_NUM_THREADS", "1")  # a software rasteriser keeps to one core, beside the tick's
    _lower_priority()
    renderer = _Renderer(state_conn)
    load_period_s: float | None = None
    next_load_s = 0.0
    load_times: list[float] = []
    parent = os.getppid()
    while True:
        wait = 0.5 if load_period_s is None else max(0.0, next_load_s - time.monotonic())
        if not conn.poll(wait):
            if os.getppid() != parent:
                return
            if load_period_s is not None and time.monotonic() >= next_load_s:
                start = time.perf_counter()
                try:
                    renderer.frame({})
                except Exception:  # a load frame that fails is logged, the load goes on
                    log.exception("load frame failed")
                load_times.append(time.perf_counter() - start)
                next_load_s += load_period_s
            continue
        try:
            name, args = conn.recv()
        except EOFError:
            return
        try:
            if name == "stop":
                conn.send(("ok", None))
                return
            if name == "capture":
                conn.send(("ok", renderer.frame(args)))
            elif name == "start_load":
                load_period_s, next_load_s, load_times = 1.0 / float(args), time.monotonic(), []
                conn.send(("ok", None))
            elif name == "stop_load":
                load_period_s = None
                conn.send(("ok", list(load_times)))
            else:
                conn.send(("error", f"unknown render request {name!r}"))
        except Exception as exc:
            conn.send(("error", f"{type(exc).__name__}: {exc}"))


class RenderProcess:
    """The render process of one emulator; ``state_conn`` is its end of the pipe the emulator's
    ``serve_world_state`` answers on. Calls may come from several threads (one at a time)."""

    def __init__(self, state_conn: Connection, name: str = "renderer") -> None:
        ctx = multiprocessing.get_context("spawn")
        self._conn, child_conn = ctx.Pipe()
        self._lock = threading.Lock()
        self._proc = ctx.Process(target=_render_main, args=(child_conn, state_conn), daemon=True, name=name)
        self._proc.start()
        child_conn.close()

    def call(self, name: str, args: Any = None, timeout_s: float = 30.0) -> Any:
        with self._lock:
            self._conn.send((name, args))
            if not self._conn.poll(timeout_s):
                alive = "alive" if self._proc.is_alive() else f"dead (exit code {self._proc.exitcode})"
                raise RuntimeError(f"{NO_ANSWER} {name!r} within {timeout_s:g} s (the process is {alive})")
            status, value = self._conn.recv()
        if status != "ok":
            raise RuntimeError(f"render process: {name} failed: {value}")
        return value

    def capture(self, timeout_s: float = 30.0, **camera_kwargs: Any) -> dict[str, Any]:
        """One frame's fields (``rgb``, ``depth_m``, ``intrinsics``, ``timestamp_s``, ``T_base_camera``) rendered
        from the emulator's world as it is now; ``camera_kwargs`` go to ``SimCamera``."""
        return self.call("capture", camera_kwargs, timeout_s)

    def start_load(self, rate_hz: float) -> None:
        """Renders the overhead camera at ``rate_hz`` in the render process until ``stop_load``."""
        if not rate_hz > 0:
            raise ValueError(f"rate_hz must be > 0, got {rate_hz}")
        self.call("start_load", float(rate_hz))

    def stop_load(self) -> list[float]:
        """Ends the load; returns the time of each load frame [s]."""
        return self.call("stop_load")

    def close(self, timeout_s: float = 5.0) -> None:
        if self._proc.is_alive():
            with contextlib.suppress(RuntimeError, OSError, EOFError):
                self.call("stop", timeout_s=timeout_s)
            self._proc.join(timeout_s)
            if self._proc.is_alive():
                self._proc.terminate()
        self._conn.close()
