"""``sygrid bench sim``: the simulated cell's real-time figures, one variant after another in one run.

- RTDE state stream seen by a raw client (rate, p50/p99/max gap between packages) for three loads: the kinematic
  backend; the MuJoCo cell with 20 dropped parts; the same while the overhead camera renders at 5 Hz (in the
  emulator's render process, ``sim.render_process``, from the world state the emulator hands out).
- The same stream while something misbehaves, the emulator in this process (as ``tests/test_controller_protocol.py``
  runs it): a backend whose step blocks 100 ms every 20 calls; a second client that stops reading (its packages are
  dropped). The tests check that every tick's package arrives in order; the rates are measured here.
- Command round trip: ``getForwardKinematics()`` through the stock ur_rtde client, p50/p99, per backend.
- MuJoCo camera frame time at 640x480 (RGB + depth) on the 20-part cell.

Targets on a 2-core machine: 500 Hz with p99 gap <= 3 ms and longest gap <= 10 ms (the camera rendering too),
round trip p50 <= 6 ms, camera frame <= 40 ms.
The emulator runs in a child process, as it must beside a ur_rtde client (see ``sim.controller.process``).
"""

from __future__ import annotations

import argparse
import logging
import socket
import struct
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
TARGETS = {"rate_hz": 500.0, "gap_p99_ms": 3.0, "gap_max_ms": 10.0, "fk_p50_ms": 6.0, "camera_frame_ms": 40.0}
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


def chart(results: dict):
    fig, axes = plt.subplots(1, 3, figsize=(16, 4.2))
    labels = list(results["controller"])
    stream = [results["controller"][k] for k in labels]
    x = np.arange(len(labels))
    axes[0].bar(x - 0.2, [s["gap_p99_ms"] for s in stream], 0.4, label="gap p99")
    axes[0].bar(x + 0.2, [s["gap_max_ms"] for s in stream], 0.4, label="gap max")
    axes[0].axhline(TARGETS["gap_p99_ms"], color="grey", ls=":", lw=1, label="p99 target")
    for i, s in enumerate(stream):
        axes[0].annotate(f"{s['rate_hz']:.0f} Hz", (i, 0.3), ha="center", fontsize=8, color="white")
    wrapped = [label.replace(", ", "\n") for label in labels]
    axes[0].set(xticks=x, xticklabels=wrapped, ylabel="ms", title="RTDE state stream (raw client)")
    for s, label in zip(stream, labels, strict=True):
        axes[1].hist(s["fk_ms"], bins=40, histtype="step", label=label)
    axes[1].axvline(TARGETS["fk_p50_ms"], color="grey", ls=":", lw=1)
    axes[1].set(xlabel="getForwardKinematics round trip [ms]", ylabel="calls", title="Command round trip (ur_rtde)")
    cam = results["camera"]
    axes[2].hist(cam["frame_ms"], bins=30)
    axes[2].axvline(TARGETS["camera_frame_ms"], color="grey", ls=":", lw=1)
    axes[2].set(xlabel="frame time [ms]", ylabel="frames", title=f"MuJoCo camera {cam['resolution']} RGB + depth")
    for ax in axes:
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    axes[1].legend(fontsize=7)
    fig.suptitle("sygrid bench sim: UR controller emulator and sim camera")
    return fig


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--stream-seconds", type=float, default=10.0)
    parser.add_argument("--round-trips", type=int, default=500)
    parser.add_argument("--frames", type=int, default=60)


def run(args: argparse.Namespace, out_dir: Path = DEFAULT_RESULTS_DIR) -> int:
    results: dict = {"targets": TARGETS, "controller": {}}
    results["camera"] = measure_camera(args.frames)
    for label, backend, kwargs, camera_hz in VARIANTS:
        print(f"measuring: {label} ...", flush=True)
        results["controller"][label] = measure_controller(
            backend, kwargs, args.stream_seconds, args.round_trips, camera_hz
        )
    print("measuring: the stream beside a stalling backend and a stalled client ...", flush=True)
    results["stream_faults"] = measure_stream_faults(args.stream_seconds)
    print(f"{'variant':<32}{'rate Hz':>9}{'gap p50':>9}{'gap p99':>9}{'gap max':>9}{'FK p50':>8}{'FK p99':>8}"
          f"{'late ticks':>12}")  # fmt: skip
    for label, r in results["controller"].items():
        print(f"{label:<32}{r['rate_hz']:>9.1f}{r['gap_p50_ms']:>9.2f}{r['gap_p99_ms']:>9.2f}{r['gap_max_ms']:>9.2f}"
              f"{r['fk_p50_ms']:>8.2f}{r['fk_p99_ms']:>8.2f}{r['late_ticks']:>7}/{r['ticks']}")  # fmt: skip
    print(f"{'in-process emulator, kinematic':<42}{'rate Hz':>9}{'gap p99':>9}{'gap max':>9}{'skipped ticks':>15}")
    for label, r in results["stream_faults"].items():
        print(
            f"{label:<42}{r['rate_hz']:>9.1f}{r['gap_p99_ms']:>9.2f}{r['gap_max_ms']:>9.2f}{r['skipped_ticks']:>15.0f}"
        )
    cam = results["camera"]
    print(f"camera {cam['resolution']} RGB+depth: p50 {cam['frame_p50_ms']:.1f} ms, p90 {cam['frame_p90_ms']:.1f} ms")
    json_path, png_path = save_results("sim", results, chart(results), out_dir)
    print(f"wrote {json_path} and {png_path}")
    return 0
