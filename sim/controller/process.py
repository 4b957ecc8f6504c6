"""Runs an ``EmulatedController`` in a child process and forwards its test hooks over a pipe.

Needed whenever the ur_rtde client lives in the same Python program: the client's constructors hold the GIL while
they wait for the controller's first state package (with no timeout), which would freeze an in-process emulator.
The child's log records are kept in a ring buffer (``log_messages``) and WARNING and above also go to stderr.
The child ignores SIGINT and SIGTERM (a Ctrl-C, or a service manager's stop, reaches the whole process group, and the
parent must stop the arm before the emulator goes): it exits when the parent tells it to or is gone, and ``stop``
kills it when it does not; ``exitcode`` says whether it is still running.

With the MuJoCo backend the overhead camera is rendered in a third process (``sim.render_process``), from the
world state the child hands out, so frames never take the emulator's CPU time or GIL (``capture``,
``start_camera_load``).
The child is started with the ``spawn`` method, so a script that uses this class needs the usual
``if __name__ == "__main__":`` guard. The child also shortens the interpreter's GIL switch interval (its process is
the emulator's alone), which keeps the tick within a fraction of a millisecond of its deadline.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import logging
import multiprocessing
import os
import signal
import sys
import threading
import time
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import numpy as np

from sim.controller.errors import EmulatorError
from sim.controller.status import ControllerStatus

log = logging.getLogger(__name__)

# The tick thread waking from its sleep waits for the GIL up to the switch interval (5 ms by default) while a socket
# thread runs Python; 0.2 ms keeps tick lateness well under a tick. Set only in processes the emulator owns.
SWITCH_INTERVAL_S = 0.0002


# The emulator stands in for a controller with a computer of its own: where it shares a small machine with the
# perception of the program it serves, its real-time physics must come first (a late step is lost real time, a late
# frame only a slower cycle). The niceness it asks for, where the process is allowed to (root, CAP_SYS_NICE or an
# RLIMIT_NICE that permits it).
EMULATOR_NICENESS = -10


def tune_emulator_process() -> None:
    """Settings for a process that the emulator owns: short GIL slices, a single-threaded software renderer
    (Mesa llvmpipe) for the sim camera, whose worker threads otherwise take both cores of a small machine from the
    500 Hz tick (``sygrid bench sim`` measures the stream's gaps), and a higher priority (``EMULATOR_NICENESS``) than
    the program it serves."""
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    os.environ.setdefault("LP_NUM_THREADS", "1")  # read by Mesa when the first GL context is made
    raise_priority(EMULATOR_NICENESS)


def raise_priority(niceness: int) -> bool:
    """Sets the niceness of every thread of this process to ``niceness`` where it is lower than the calling thread's
    and the process may lower it; else leaves it and logs why at WARNING (the emulator then shares the cores evenly,
    and on a small machine its physics trails real time more often: ``TickStats.paced_ticks`` counts the held ticks).
    Threads started later take their creator's niceness. True if set."""
    now = os.getpriority(os.PRIO_PROCESS, 0)
    if now <= niceness:
        return True
    # Linux keeps a niceness per thread, and imports start threads (a BLAS pool) before this runs: each one is set
    tasks = Path("/proc/self/task")
    tids = [int(t.name) for t in tasks.iterdir()] if tasks.is_dir() else [0]
    try:
        for tid in tids:
            os.setpriority(os.PRIO_PROCESS, tid, niceness)
    except OSError as exc:  # PermissionError without the privilege
        log.warning("the emulator runs at niceness %d, not %d (%s): where it shares few cores with perception "
                    "its physics may trail real time, and the arm then moves slower",
                    now, niceness, exc.strerror)  # fmt: skip
        return False
    return True


_HOOKS = (
    "state", "trigger_protective_stop", "inject_collision_force", "log_messages", "unlock_protective_stop",
    "part_poses", "part_names", "set_part_poses", "park_parts", "contacts", "place_parts", "drop_connections",
    "thrown_parts",
)  # fmt: skip

# Where parked ("removed") parts wait: high above the cell (behind the camera), spread out, held against gravity.
_PARK_ORIGIN_M = np.array([5.0, 5.0, 3.0])
_PARK_SPACING_M = 0.5


class _RingHandler(logging.Handler):
    def __init__(self, size: int = 5000) -> None:
        super().__init__()
        self.lines: collections.deque[str] = collections.deque(maxlen=size)

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append(f"{record.levelname} {record.name}: {record.getMessage()}")


def _child_main(
    conn: Connection,
    state_conn: Connection | None,
    host: str,
    backend: str,
    backend_kwargs: dict,
    controller_kwargs: dict,
) -> None:
    from sim.controller.backend_by_name import make_backend
    from sim.controller.controller import EmulatedController

    for sig in (signal.SIGINT, signal.SIGTERM):  # the parent stops the arm first, then this process
        signal.signal(sig, signal.SIG_IGN)
    ring = _RingHandler()
    stderr = logging.StreamHandler(sys.stderr)
    stderr.setLevel(logging.WARNING)
    stderr.setFormatter(logging.Formatter(f"[emulator {host}] %(levelname)s %(name)s: %(message)s"))
    logging.basicConfig(level=logging.INFO, handlers=[ring, stderr], force=True)
    tune_emulator_process()
    parent = os.getppid()
    try:
        arm = make_backend(backend, **backend_kwargs)
        ctl = EmulatedController(arm, host=host, **controller_kwargs)
        ctl.start()
    except Exception as exc:
        conn.send(("error", f"{type(exc).__name__}: {exc}"))
        return
    if state_conn is not None and hasattr(arm, "world"):
        from sim.render_process import serve_world_state

        serve_world_state(state_conn, arm.world)
    conn.send(("ok", None))
    hooks = {
        "state": ctl.state,
        "trigger_protective_stop": ctl.trigger_protective_stop,
        "unlock_protective_stop": ctl.unlock_protective_stop,
        "inject_collision_force": getattr(arm, "inject_collision_force", None),
        "log_messages": lambda: list(ring.lines),
        # The MuJoCo backend's parts, T_world_obj (n, 4, 4): ground truth for sim-in-the-loop tests.
        "part_poses": (lambda: arm.world.part_poses()) if hasattr(arm, "world") else None,
        "part_names": (lambda: arm.world.part_names()) if hasattr(arm, "world") else None,
        "set_part_poses": (lambda T: arm.world.set_part_poses(T)) if hasattr(arm, "world") else None,
        "park_parts": (lambda idx: _park_parts(arm.world, idx)) if hasattr(arm, "world") else None,
        "contacts": (lambda: _contacts(arm.world)) if hasattr(arm, "world") else None,
        "place_parts": (lambda T, held=(): _place_parts(arm.world, T, held)) if hasattr(arm, "world") else None,
        "drop_connections": lambda down_s=2.0: _drop_connections(ctl, down_s),
        "thrown_parts": (lambda: [dataclasses.asdict(t) for t in arm.world.throws]) if hasattr(arm, "world") else None,
    }
    try:
        while True:
            if not conn.poll(0.5):
                if os.getppid() != parent:
                    break  # the parent died without stopping us
                continue
            try:
                name, args, kwargs = conn.recv()
            except EOFError:
                break
            if name == "stop":
                break
            hook = hooks.get(name)
            try:
                if hook is None:
                    raise EmulatorError(f"hook {name!r} is not available here; available: {sorted(_HOOKS)}")
                conn.send(("ok", hook(*args, **kwargs)))
            except Exception as exc:
                conn.send(("error", f"{type(exc).__name__}: {exc}"))
    finally:
        ctl.stop()
        with contextlib.suppress(OSError):
            conn.send(("ok", "stopped"))


def _park_parts(world: Any, indices: list[int]) -> None:
    """Moves parts ``indices`` out of the cell (high above it, at rest, held against gravity): "removes" them
    without recompiling the world (tests: an empty bin, a part taken away before the gripper closes)."""
    import mujoco

    with world.lock:
        T = world.part_poses()
        for i in indices:
            if not 0 <= i < len(T):
                raise ValueError(f"part index {i} out of range: the cell has {len(T)} parts")
            T[i] = np.eye(4)
            T[i, :3, 3] = _PARK_ORIGIN_M + np.array([_PARK_SPACING_M * i, 0.0, 0.0])
            body = mujoco.mj_name2id(world.model, mujoco.mjtObj.mjOBJ_BODY, world.part_names()[i])
            # An applied force that cancels gravity (body_gravcomp cannot be switched on after compiling).
            world.data.xfrc_applied[body, :3] = -world.model.body_subtreemass[body] * world.model.opt.gravity
        world.set_part_poses(T)


def _place_parts(world: Any, T_world_obj: np.ndarray, held: Any = ()) -> None:
    """Teleports every part to ``T_world_obj`` (n, 4, 4) at rest; the parts in ``held`` stay there against gravity
    (floating: an unreachable part in view), every other part is free again (an earlier hold or park released)."""
    import mujoco

    with world.lock:
        names = world.part_names()
        for i, name in enumerate(names):
            body = mujoco.mj_name2id(world.model, mujoco.mjtObj.mjOBJ_BODY, name)
            hold = i in set(int(k) for k in held)
            world.data.xfrc_applied[body, :3] = (
                -world.model.body_subtreemass[body] * world.model.opt.gravity if hold else 0.0
            )
        world.set_part_poses(T_world_obj)


def _drop_connections(ctl: Any, down_s: float) -> int:
    """A network link that goes down for ``down_s`` seconds: closes the robot's interfaces (RTDE, dashboard, script
    ports: listeners and client connections) and opens them again afterwards, in a thread; the controller, its
    program and the world keep running. Returns how many client connections were closed.

    The listeners go down too: closing only the connections lets ur_rtde 1.6.5's own background reconnect race
    with the client's next call, which can crash the client process (segmentation fault)."""
    from sim.controller.tcp_service import TcpService, start_all

    services = [ctl.rtde.service, ctl.dashboard.service, *ctl.script.services]
    closed = sum(len(service.connections) for service in services)
    for service in services:
        service.stop()
    log.warning("link down for %.1f s: %d client connection(s) closed (test hook)", down_s, closed)

    def restore() -> None:
        time.sleep(down_s)
        fresh = [TcpService(s.name, s.host, s.port, s._handler) for s in services]
        start_all(fresh)
        ctl.rtde.service, ctl.dashboard.service, ctl.script.services = fresh[0], fresh[1], fresh[2:]
        log.warning("link up again (test hook)")

    threading.Thread(target=restore, name="link-restore", daemon=True).start()
    return closed


def _contacts(world: Any) -> list[dict]:
    """The world's contacts of the last step, by body and geom name, with their normal force (N) and distance (m,
    < 0: penetration): which link touched what when a protective stop fired, whether a part is in the fingers."""
    import mujoco

    out = []
    with world.lock:
        m, d = world.model, world.data
        force = np.zeros(6)
        for i in range(d.ncon):
            g1, g2 = int(d.contact.geom1[i]), int(d.contact.geom2[i])
            mujoco.mj_contactForce(m, d, i, force)
            out.append(
                {
                    "geom1": mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, g1) or f"geom{g1}",
                    "geom2": mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, g2) or f"geom{g2}",
                    "body1": mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, int(m.geom_bodyid[g1])) or "",
                    "body2": mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, int(m.geom_bodyid[g2])) or "",
                    "dist_m": float(d.contact.dist[i]),
                    "force_n": float(force[0]),
                }
            )
    return out


class ControllerProcess:
    """``EmulatedController`` in a child process; a context manager. Keyword arguments go to the controller."""

    def __init__(
        self,
        host: str = "127.0.0.1",
        backend: str = "kinematic",
        backend_kwargs: dict[str, Any] | None = None,
        start_timeout_s: float = 30.0,
        **controller_kwargs: Any,
    ) -> None:
        self.host = host
        self._args = (host, backend, backend_kwargs or {}, controller_kwargs)
        self._start_timeout_s = start_timeout_s
        self._conn: Connection | None = None
        self._proc: multiprocessing.process.BaseProcess | None = None
        self._call_lock = threading.Lock()
        self._state_conn: Connection | None = None  # the render process's end of the world-state pipe
        self._renderer: Any = None  # a sim.render_process.RenderProcess, started on the first frame

    def __enter__(self) -> ControllerProcess:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def start(self) -> None:
        ctx = multiprocessing.get_context("spawn")
        parent_conn, child_conn = ctx.Pipe()
        renderer_end, state_end = ctx.Pipe() if self._args[1] == "mujoco" else (None, None)
        self._proc = ctx.Process(
            target=_child_main, args=(child_conn, state_end, *self._args), daemon=True, name=f"emulator-{self.host}"
        )
        self._proc.start()
        if state_end is not None:
            state_end.close()
        self._conn, self._state_conn = parent_conn, renderer_end
        try:
            self._receive(self._start_timeout_s, "start")
        except BaseException:  # a failed start, or an interrupt while waiting: leave no child behind
            self.stop()
            raise

    @property
    def pid(self) -> int | None:
        """The child's process id (None before ``start``)."""
        return None if self._proc is None else self._proc.pid

    @property
    def exitcode(self) -> int | None:
        """None while the child runs (or before ``start``); its exit code once it has ended (``-N``: killed by
        signal N)."""
        return None if self._proc is None else self._proc.exitcode

    def describe_exit(self) -> str | None:
        """A sentence naming the child and how it ended once it has ended, else None."""
        code = self.exitcode
        if code is None:
            return None
        if code >= 0:
            how = f"exited with code {code}"
        else:
            try:
                how = f"was killed by {signal.Signals(-code).name}"
            except ValueError:
                how = f"was killed by signal {-code}"
        return f"the emulator process (pid {self.pid}, host {self.host}) {how}"

    def _receive(self, timeout_s: float, what: str) -> Any:
        assert self._conn is not None and self._proc is not None
        waited = 0.0
        while not self._conn.poll(0.05):
            waited += 0.05
            if not self._proc.is_alive():
                raise EmulatorError(
                    f"emulator process on {self.host} died (exit code {self._proc.exitcode}) "
                    f"before answering {what!r}; see its stderr"
                )
            if waited >= timeout_s:
                raise EmulatorError(f"emulator on {self.host} did not answer {what!r} within {timeout_s:g} s")
        status, value = self._conn.recv()
        if status != "ok":
            raise EmulatorError(f"emulator on {self.host}: {what} failed: {value}")
        return value

    def call(self, hook: str, *args: Any, timeout_s: float = 10.0, **kwargs: Any) -> Any:
        """Calls one of the child's hooks (``state``, ``trigger_protective_stop``, ...) and returns its result."""
        if self._conn is None:
            raise EmulatorError(f"emulator on {self.host} is not running; call start() first")
        with self._call_lock:
            self._conn.send((hook, args, kwargs))
            return self._receive(timeout_s, hook)

    def state(self) -> ControllerStatus:
        return self.call("state")

    def trigger_protective_stop(self, reason: str = "test hook") -> None:
        self.call("trigger_protective_stop", reason)

    def inject_collision_force(self, force_n: float) -> None:
        """Kinematic backend only: the contact force it reports until set back to 0."""
        self.call("inject_collision_force", force_n)

    def part_poses(self) -> np.ndarray:
        """MuJoCo backend only: ``T_world_obj`` (n, 4, 4) of the cell's parts, for tests."""
        return self.call("part_poses")

    def capture(self, timeout_s: float = 10.0) -> dict:
        """MuJoCo backend only: one overhead-camera frame of the child's world (``sim.camera.SimCamera`` in the
        render process), as the fields of a ``perception.camera.Frame`` (``sim.emulator_camera.EmulatorCamera`` is
        the ``Camera``)."""
        return self._render_process().capture(timeout_s)

    def start_camera_load(self, rate_hz: float) -> None:
        """MuJoCo backend only: the render process renders the overhead camera at ``rate_hz`` by itself (the load
        of a perception client) until ``stop_camera_load``."""
        self._render_process().start_load(rate_hz)

    def stop_camera_load(self) -> list[float]:
        """Ends ``start_camera_load``; returns each load frame's render time [s]."""
        return self._render_process().stop_load()

    def _render_process(self) -> Any:
        if self._state_conn is None:
            raise EmulatorError(f"emulator on {self.host}: frames need the 'mujoco' backend (and a started emulator)")
        if self._renderer is None:
            from sim.render_process import RenderProcess

            self._renderer = RenderProcess(self._state_conn, name=f"renderer-{self.host}")
        return self._renderer

    def part_names(self) -> list[str]:
        """MuJoCo backend only: the parts' body names (``part<k>_<model name>``), in ``part_poses`` order."""
        return self.call("part_names")

    def set_part_poses(self, T_world_obj: np.ndarray) -> None:
        """MuJoCo backend only: teleports every part to ``T_world_obj`` (n, 4, 4), at rest."""
        self.call("set_part_poses", np.asarray(T_world_obj, dtype=float))

    def park_parts(self, indices: list[int]) -> None:
        """MuJoCo backend only: takes parts out of the cell (parked high above it, at rest)."""
        self.call("park_parts", [int(i) for i in indices])

    def place_parts(self, T_world_obj: np.ndarray, held: list[int] | None = None) -> None:
        """MuJoCo backend only: teleports every part to ``T_world_obj`` (n, 4, 4) at rest; parts ``held`` float
        there against gravity, the others are free (undoes ``park_parts``)."""
        self.call("place_parts", np.asarray(T_world_obj, dtype=float), [int(i) for i in (held or [])])

    def drop_connections(self, down_s: float = 2.0) -> int:
        """The robot's network link goes down for ``down_s`` seconds: every RTDE, dashboard and script connection
        is closed and none accepted until then; the controller and the world keep running. Returns how many client
        connections were closed."""
        return self.call("drop_connections", float(down_s))

    def contacts(self) -> list[dict]:
        """MuJoCo backend only: the contacts of the last physics step, one dict each: ``geom1``, ``geom2``,
        ``body1``, ``body2`` (names), ``dist_m`` (< 0: penetration) and ``force_n`` (normal force)."""
        return self.call("contacts")

    def thrown_parts(self) -> list[dict]:
        """MuJoCo backend only: the parts the physics threw so far (``sim.throw_watch.Throw`` as dicts: part, time,
        speed, and the deepest penetration before the throw with what it penetrated)."""
        return self.call("thrown_parts")

    def log_messages(self) -> list[str]:
        return self.call("log_messages")

    def stop(self, timeout_s: float = 5.0) -> None:
        """Stops the render process, the controller and the child (terminating them if they do not exit in time)."""
        if self._renderer is not None:
            self._renderer.close(timeout_s)
            self._renderer = None
        if self._state_conn is not None:
            self._state_conn.close()
            self._state_conn = None
        if self._conn is not None:
            try:
                self._conn.send(("stop", (), {}))
                self._conn.poll(timeout_s)
            except (OSError, BrokenPipeError):
                pass
            self._conn.close()
            self._conn = None
        if self._proc is not None:
            self._proc.join(timeout_s)
            if self._proc.is_alive():
                log.warning("emulator process on %s did not exit; killing it", self.host)
                self._proc.kill()  # it ignores SIGTERM
                self._proc.join(timeout_s)
            self._proc = None
