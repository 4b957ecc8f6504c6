"""``sygrid bench sim``: the simulated cell's real-time figures, one variant after another in one run.

- RTDE state stream seen by a raw client (rate, p50/p99/max gap between packages) for three loads: the kinematic
  backend; the MuJoCo cell with 20 dropped parts; the same while the overhead camera renders at 5 Hz (in the
  emulator's render process, ``sim.render_process``, from the world state the emulator hands out).
- The same stream while something misbehaves, the emulator in this process (as ``tests/test_controller_protocol.py``
  runs it): a backend whose step blocks 100 ms every 20 calls; a second client that stops reading (its packages are
  dropped). The tests check that every tick's package arrives in order; the rates are measured here.
- Command round trip: ``getForwardKinematics()`` through the stock ur_rtde client, p50/p99, per backend.
- MuJoCo camera frame time at 640x480 (RGB + depth) on the 20-part cell.
- The stream (kinematic backend, the emulator in its own process) while a client sends one 64 MiB line to the
  dashboard port, and the emulator process's RSS before and after.

Targets on a 2-core machine: 500 Hz with p99 gap <= 3 ms and longest gap <= 10 ms (the camera rendering too, and
beside a 64 MiB dashboard line), round trip p50 <= 6 ms, camera frame <= 40 ms.
The emulator runs in a child process, as it must beside a ur_rtde client (see ``sim.controller.process``).
``--scenarios`` runs some of them (``camera``, ``controller``, ``faults``, ``long-line``); a partial run writes
``sim-<scenarios>.json``, not ``sim.json``.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import socket
import struct
import threading
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from sim.camera import SimCamera
from sim.cell import build_cell_world
from sim.controller import rtde_wire as wire
from sim.controller.backend import KinematicBackend, StallingBackend
from sim.controller.controller import EmulatedController
from sim.controller.process import ControllerProcess
from sim.controller.rtde_probe import RtdeProbe
from sygrid.bench.common import DEFAULT_RESULTS_DIR, percentile, save_results

log = logging.getLogger(__name__)

HOST = "127.0.0.61"
HOST_FAULTS = "127.0.0.62"
TARGETS = {"rate_hz": 500.0, "gap_p99_ms": 3.0, "gap_max_ms": 10.0, "fk_p50_ms": 6.0, "camera_frame_ms": 40.0,
           "long_line_gap_p99_ms": 3.0, "long_line_gap_max_ms": 10.0}  # fmt: skip
SCENARIOS = ("camera", "controller", "faults", "long-line")
LONG_LINE_BYTES = 64 * 1024 * 1024
# (label, backend, backend kwargs, camera frames per second)
VARIANTS = (
    ("kinematic", "kinematic", {}, 0.0),
    ("mujoco, 20 parts", "mujoco", {"parts_seed": 0}, 0.0),
    ("mujoco, 20 parts, camera 5 Hz", "mujoco", {"parts_seed": 0}, 5.0),
)


def measure_camera(frames: int, seed: int = 0) -> dict:
    world = build_cell_world(seed=seed)
    camera = SimCamera(world)
    camera.capture()  # renderer set-up
    times = []
    for _ in range(frames):
        start = time.perf_counter()
        frame = camera.capture()
        times.append((time.perf_counter() - start) * 1e3)
    h, w = frame.rgb.shape[:2]
    return {"resolution": f"{w}x{h}", "frames": frames, "frame_p50_ms": percentile(times, 50),
            "frame_p90_ms": percentile(times, 90), "frame_max_ms": max(times), "frame_ms": times}  # fmt: skip


def measure_controller(
    backend: str, backend_kwargs: dict, stream_s: float, round_trips: int, camera_hz: float = 0.0
) -> dict:
    import rtde_control  # the stock client, imported late: it is only needed here

    with ControllerProcess(HOST, backend=backend, backend_kwargs=backend_kwargs, start_timeout_s=120.0) as cell:
        frame_s: list[float] = []
        if camera_hz > 0:
            cell.capture()  # the render process's set-up (GL context, model upload): not part of the load
            cell.start_camera_load(camera_hz)
        with RtdeProbe(HOST) as probe:
            probe.negotiate()
            probe.setup_outputs(["timestamp", "actual_q", "actual_TCP_pose", "runtime_state"], 500.0)
            probe.start()
            stream = probe.stream_timing(stream_s)
            probe.pause()
        if camera_hz > 0:
            frame_s = cell.stop_camera_load()
        control = rtde_control.RTDEControlInterface(HOST)
        try:
            rt_ms = []
            for _ in range(round_trips):
                start = time.perf_counter()
                control.getForwardKinematics()
                rt_ms.append((time.perf_counter() - start) * 1e3)
        finally:
            control.stopScript()
            control.disconnect()
        tick = cell.state().tick
    return {**stream, "fk_p50_ms": percentile(rt_ms, 50), "fk_p99_ms": percentile(rt_ms, 99), "fk_ms": rt_ms,
            "late_ticks": tick.late_ticks, "ticks": tick.ticks, "camera_frames": len(frame_s)}  # fmt: skip


def _stalled_reader(host: str) -> socket.socket:
    """A client that asks for large packages at 500 Hz and never reads them."""
    sock = socket.create_connection((host, 30004), timeout=2.0)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    sock.sendall(wire.frame(wire.REQUEST_PROTOCOL_VERSION, struct.pack(">H", 2)))
    fields = ["actual_q", "actual_qd", "target_q", "target_qd", "actual_TCP_pose", "target_TCP_pose"] * 30
    sock.sendall(wire.frame(wire.SETUP_OUTPUTS, struct.pack(">d", 500.0) + ",".join(fields).encode()))
    sock.sendall(wire.frame(wire.START))
    return sock


def _stream_in_process(ctl: EmulatedController, stream_s: float) -> dict:
    with RtdeProbe(ctl.host) as probe:
        probe.negotiate()
        probe.setup_outputs(["timestamp", "actual_q", "target_q"], 500.0)
        probe.start()
        stream = probe.stream_timing(stream_s)
        probe.pause()
    return {**stream, "late_ticks": ctl.stats.late_ticks, "ticks": ctl.stats.ticks, "resyncs": ctl.stats.resyncs}


def measure_stream_faults(stream_s: float) -> dict:
    """The raw client's stream (``RtdeProbe.stream_timing``) beside a stalling backend and beside a client that
    stopped reading; the emulator runs in this process."""
    results = {}
    with EmulatedController(StallingBackend(stall_s=0.1, every=20), host=HOST_FAULTS) as ctl:
        results["backend stalling 100 ms every 20 steps"] = _stream_in_process(ctl, stream_s)
    with EmulatedController(KinematicBackend(), host=HOST_FAULTS) as ctl, _stalled_reader(HOST_FAULTS):
        end = time.monotonic() + 10.0
        while time.monotonic() < end and not any(c.dropped_messages for c in list(ctl.rtde.service.connections)):
            time.sleep(0.01)
        stream = _stream_in_process(ctl, stream_s)
        dropped = sum(c.dropped_messages for c in list(ctl.rtde.service.connections))
        results["beside a client that stopped reading"] = {**stream, "stalled_client_dropped": dropped}
    return results


def _rss_mb(pid: int) -> float:
    """Resident set size of process ``pid`` in MB (``/proc``; NaN elsewhere)."""
    try:
        with open(f"/proc/{pid}/status") as f:
            kb = next(int(line.split()[1]) for line in f if line.startswith("VmRSS:"))
    except (OSError, StopIteration, ValueError):
        return float("nan")
    return kb / 1024.0


def _send_long_line(host: str, port: int, payload: bytes) -> dict:
    """Sends ``payload`` (one long line) to the dashboard at ``host:port`` from a thread while reading the reply until
    the server ends its side; returns the reply, the seconds to it, how much of the line went out and the seconds
    until the sending stopped (all sent, or the connection closed)."""
    with socket.create_connection((host, port), timeout=30.0) as sock:
        sock.recv(100)  # the greeting
        sent, send_s = [0], [float("nan")]

        def send() -> None:
            view = memoryview(payload)
            with contextlib.suppress(OSError):  # the server answers and closes before the line ends
                while sent[0] < len(payload):
                    sent[0] += sock.send(view[sent[0] : sent[0] + 1024 * 1024])
            send_s[0] = time.perf_counter() - start

        start = time.perf_counter()
        sender = threading.Thread(target=send, daemon=True)
        sender.start()
        reply = b""
        with contextlib.suppress(OSError):
            while chunk := sock.recv(4096):
                reply += chunk
        reply_s = time.perf_counter() - start
        sender.join(60.0)
    return {"reply": reply.decode(errors="replace").strip(), "reply_after_s": reply_s, "line_sent_bytes": sent[0],
            "sending_ended_after_s": send_s[0]}  # fmt: skip


def measure_long_line(stream_s: float, line_bytes: int = LONG_LINE_BYTES, delay_s: float = 1.0) -> dict:
    """The raw client's stream (``RtdeProbe.stream_timing``) from the emulator in its own process (kinematic
    backend) while another client sends one ``line_bytes`` line to the dashboard port, ``delay_s`` into the stream;
    with the same stream just before (``baseline``: the machine's own noise) and the emulator process's RSS before
    and after."""
    payload = b"x" * line_bytes + b"\n"  # made before the stream starts: this process reads the stream too
    with ControllerProcess(HOST, backend="kinematic") as cell:
        rss_before = _rss_mb(cell.pid)
        sent: dict = {}

        def send_later() -> None:
            time.sleep(delay_s)
            sent.update(_send_long_line(HOST, 29999, payload))

        with RtdeProbe(HOST) as probe:
            probe.negotiate()
            probe.setup_outputs(["timestamp", "actual_q", "target_q"], 500.0)
            probe.start()
            baseline = probe.stream_timing(stream_s)
            sender = threading.Thread(target=send_later, daemon=True)
            sender.start()
            stream = probe.stream_timing(stream_s)
            probe.pause()
            sender.join(60.0)
        rss_after = _rss_mb(cell.pid)
        tick = cell.state().tick
    return {**stream, **sent, "line_bytes": line_bytes, "rss_before_mb": rss_before, "rss_after_mb": rss_after,
            "late_ticks": tick.late_ticks, "ticks": tick.ticks, "baseline": baseline}  # fmt: skip


def chart(results: dict):
    """One panel per scenario measured: stream gaps per backend, the FK round trip, camera frame times, and the
    stream beside a 64 MiB dashboard line."""
    panels = [p for p, key in ((_stream_panel, "controller"), (_fk_panel, "controller"), (_camera_panel, "camera"),
                               (_long_line_panel, "long_line")) if key in results]  # fmt: skip
    fig, axes = plt.subplots(1, max(len(panels), 1), figsize=(5.4 * max(len(panels), 1), 4.2), squeeze=False)
    for panel, ax in zip(panels, axes[0], strict=False):
        panel(results, ax)
        ax.grid(alpha=0.3)
    fig.suptitle("sygrid bench sim: UR controller emulator and sim camera")
    return fig


def _stream_panel(results: dict, ax) -> None:
    labels = list(results["controller"])
    stream = [results["controller"][k] for k in labels]
    x = np.arange(len(labels))
    ax.bar(x - 0.2, [s["gap_p99_ms"] for s in stream], 0.4, label="gap p99")
    ax.bar(x + 0.2, [s["gap_max_ms"] for s in stream], 0.4, label="gap max")
    ax.axhline(TARGETS["gap_p99_ms"], color="grey", ls=":", lw=1, label="p99 target")
    for i, s in enumerate(stream):
        ax.annotate(f"{s['rate_hz']:.0f} Hz", (i, 0.3), ha="center", fontsize=8, color="white")
    wrapped = [label.replace(", ", "\n") for label in labels]
    ax.set(xticks=x, xticklabels=wrapped, ylabel="ms", title="RTDE state stream (raw client)")
    ax.legend(fontsize=7)


def _fk_panel(results: dict, ax) -> None:
    for label, s in results["controller"].items():
        ax.hist(s["fk_ms"], bins=40, histtype="step", label=label)
    ax.axvline(TARGETS["fk_p50_ms"], color="grey", ls=":", lw=1)
    ax.set(xlabel="getForwardKinematics round trip [ms]", ylabel="calls", title="Command round trip (ur_rtde)")
    ax.legend(fontsize=7)


def _camera_panel(results: dict, ax) -> None:
    cam = results["camera"]
    ax.hist(cam["frame_ms"], bins=30)
    ax.axvline(TARGETS["camera_frame_ms"], color="grey", ls=":", lw=1)
    ax.set(xlabel="frame time [ms]", ylabel="frames", title=f"MuJoCo camera {cam['resolution']} RGB + depth")


def _long_line_panel(results: dict, ax) -> None:
    r = results["long_line"]
    b = r["baseline"]
    ax.bar([-0.2, 0.8], [b["gap_p99_ms"], b["gap_max_ms"]], 0.4, color="grey", label="without the line")
    ax.bar([0.2, 1.2], [r["gap_p99_ms"], r["gap_max_ms"]], 0.4, color=["C0", "C1"])
    ax.axhline(TARGETS["long_line_gap_p99_ms"], color="C0", ls=":", lw=1, label="p99 target")
    ax.axhline(TARGETS["long_line_gap_max_ms"], color="C1", ls=":", lw=1, label="max target")
    ax.set_yscale("log")
    ax.set(xticks=[0, 1], xticklabels=["gap p99", "gap max"], ylabel="ms (log)",
           title=f"stream beside a {r['line_bytes'] >> 20} MiB dashboard line ({r['rate_hz']:.0f} Hz)")  # fmt: skip
    ax.legend(fontsize=7)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--stream-seconds", type=float, default=10.0)
    parser.add_argument("--round-trips", type=int, default=500)
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument(
        "--scenarios", type=_scenarios, default=SCENARIOS,
        help=f"comma-separated, of: {', '.join(SCENARIOS)} (default: all; a partial run writes sim-<scenarios>.json)",
    )  # fmt: skip


def _scenarios(text: str) -> tuple[str, ...]:
    names = tuple(n.strip() for n in text.split(",") if n.strip())
    unknown = [n for n in names if n not in SCENARIOS]
    if unknown or not names:
        raise argparse.ArgumentTypeError(f"unknown scenario(s) {unknown or [text]}; choose from {', '.join(SCENARIOS)}")
    return tuple(n for n in SCENARIOS if n in names)


def run(args: argparse.Namespace, out_dir: Path = DEFAULT_RESULTS_DIR) -> int:
    scenarios = getattr(args, "scenarios", SCENARIOS)
    results: dict = {"targets": TARGETS}
    if "camera" in scenarios:
        results["camera"] = measure_camera(args.frames)
    if "controller" in scenarios:
        results["controller"] = {}
        for label, backend, kwargs, camera_hz in VARIANTS:
            print(f"measuring: {label} ...", flush=True)
            results["controller"][label] = measure_controller(
                backend, kwargs, args.stream_seconds, args.round_trips, camera_hz
            )
    if "faults" in scenarios:
        print("measuring: the stream beside a stalling backend and a stalled client ...", flush=True)
        results["stream_faults"] = measure_stream_faults(args.stream_seconds)
    if "long-line" in scenarios:
        print(f"measuring: the stream beside a {LONG_LINE_BYTES >> 20} MiB dashboard line ...", flush=True)
        results["long_line"] = measure_long_line(args.stream_seconds)
    _print_results(results)
    name = "sim" if scenarios == SCENARIOS else "sim-" + "-".join(scenarios)
    json_path, png_path = save_results(name, results, chart(results), out_dir)
    print(f"wrote {json_path} and {png_path}")
    return 0


def _print_results(results: dict) -> None:
    if "controller" in results:
        print(f"{'variant':<32}{'rate Hz':>9}{'gap p50':>9}{'gap p99':>9}{'gap max':>9}{'FK p50':>8}{'FK p99':>8}"
              f"{'late ticks':>12}")  # fmt: skip
        for label, r in results["controller"].items():
            print(f"{label:<32}{r['rate_hz']:>9.1f}{r['gap_p50_ms']:>9.2f}{r['gap_p99_ms']:>9.2f}{r['gap_max_ms']:>9.2f}"
                  f"{r['fk_p50_ms']:>8.2f}{r['fk_p99_ms']:>8.2f}{r['late_ticks']:>7}/{r['ticks']}")  # fmt: skip
    if "stream_faults" in results:
        print(f"{'in-process emulator, kinematic':<42}{'rate Hz':>9}{'gap p99':>9}{'gap max':>9}{'skipped ticks':>15}")
        for label, r in results["stream_faults"].items():
            print(f"{label:<42}{r['rate_hz']:>9.1f}{r['gap_p99_ms']:>9.2f}{r['gap_max_ms']:>9.2f}"
                  f"{r['skipped_ticks']:>15.0f}")  # fmt: skip
    if "long_line" in results:
        r = results["long_line"]
        print(
            f"beside a {r['line_bytes'] >> 20} MiB dashboard line: {r['rate_hz']:.1f} Hz, gap p50 "
            f"{r['gap_p50_ms']:.2f} ms, p99 {r['gap_p99_ms']:.2f} ms, max {r['gap_max_ms']:.2f} ms, skipped ticks "
            f"{r['skipped_ticks']:.0f}; "
            f"reply {r.get('reply', '')!r} after {r.get('reply_after_s', float('nan')):.3f} s, "
            f"{r.get('line_sent_bytes', 0) / 2**20:.1f} MiB sent in {r.get('sending_ended_after_s', float('nan')):.3f} "
            "s; "
            f"emulator RSS {r['rss_before_mb']:.0f} -> "
            f"{r['rss_after_mb']:.0f} MB"
        )
        b = r["baseline"]
        print(f"  the same stream just before, without the line: {b['rate_hz']:.1f} Hz, gap p99 {b['gap_p99_ms']:.2f} "
              f"ms, max {b['gap_max_ms']:.2f} ms")  # fmt: skip
    if "camera" in results:
        cam = results["camera"]
        print(f"camera {cam['resolution']} RGB+depth: p50 {cam['frame_p50_ms']:.1f} ms, "
              f"p90 {cam['frame_p90_ms']:.1f} ms")  # fmt: skip
