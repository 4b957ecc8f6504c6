"""``sygrid sim``: serve a simulated UR5e cell (RTDE, script, dashboard and gripper ports) on a loopback address
until Ctrl-C or SIGTERM. Drive it with the stock ur_rtde client from another process."""

from __future__ import annotations

import argparse
import logging
import signal
import threading
import time

from sim.controller.backend_by_name import BACKENDS, make_backend
from sim.controller.controller import PROTECTIVE_STOP_FORCE_N, ControllerPorts, EmulatedController
from sim.controller.errors import EmulatorError
from sim.controller.process import tune_emulator_process
from sim.controller.state import ROBOT_MODE_NAMES, SAFETY_MODE_NAMES

log = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--host",
        default="127.0.0.1",
        help="address to listen on; use distinct 127.0.0.x to run several cells (default 127.0.0.1)",
    )
    parser.add_argument(
        "--backend",
        choices=BACKENDS,
        default="kinematic",
        help="kinematic: perfect tracking, no physics; mujoco: the MuJoCo cell (default kinematic)",
    )
    parser.add_argument(
        "--parts-seed",
        type=int,
        default=None,
        metavar="S",
        help="mujoco backend: fill the bin with the parts of --scene dropped with this seed (default: an empty bin)",
    )
    parser.add_argument(
        "--scene",
        default=None,
        metavar="SCENE.json",
        help="mujoco backend: the scene whose parts fill the bin (default: 20 built-in parts); implies --parts-seed 0",
    )
    parser.add_argument("--rtde-port", type=int, default=30004)
    parser.add_argument("--dashboard-port", type=int, default=29999)
    parser.add_argument("--script-ports", type=int, nargs="+", default=[30001, 30002, 30003])
    parser.add_argument("--gripper-port", type=int, default=63352)
    parser.add_argument(
        "--protective-stop-force",
        type=float,
        default=PROTECTIVE_STOP_FORCE_N,
        metavar="N",
        help=f"contact force that triggers a protective stop (default {PROTECTIVE_STOP_FORCE_N:g} N)",
    )
    parser.add_argument(
        "--status-interval",
        type=float,
        default=0.0,
        metavar="S",
        help="print the robot state every S seconds (default: only at start and end)",
    )


def _summary(ctl: EmulatedController, backend: str) -> str:
    s = ctl.state()
    ports = ctl.ports
    return (
        f"UR controller emulator on {ctl.host} (backend: {backend})\n"
        f"  RTDE {ports.rtde}, dashboard {ports.dashboard}, script {', '.join(map(str, ports.script))}, "
        f"gripper {ports.gripper}\n"
        f"  robot {ROBOT_MODE_NAMES.get(s.robot_mode, s.robot_mode)}, safety "
        f"{SAFETY_MODE_NAMES[3 if s.protective_stopped else 1]}, program {s.program or '-'} {s.runtime_name}\n"
        f"  q [rad] {[round(v, 4) for v in s.actual_q]}\n"
        f"  TCP [m, rotvec] {[round(v, 4) for v in s.actual_tcp_pose]}\n"
        f"  ticks {s.tick.ticks}, late (>1 ms) {s.tick.late_ticks}, RTDE packages sent {s.rtde_packages_sent}"
    )


def run(args: argparse.Namespace) -> int:
    tune_emulator_process()  # this process is the emulator's
    backend_kwargs = {}
    if args.scene is not None or args.parts_seed is not None:
        if args.backend != "mujoco":
            raise EmulatorError("--scene and --parts-seed need --backend mujoco (the kinematic backend has no parts)")
        backend_kwargs = {"parts_scene": args.scene, "parts_seed": args.parts_seed or 0}
    backend = make_backend(args.backend, **backend_kwargs)
    ports = ControllerPorts(args.rtde_port, args.dashboard_port, tuple(args.script_ports), args.gripper_port)
    done = threading.Event()

    def _on_signal(signum: int, frame: object) -> None:
        log.info("received %s; shutting down", signal.Signals(signum).name)
        done.set()

    ctl = EmulatedController(backend, host=args.host, ports=ports, protective_stop_force_n=args.protective_stop_force)
    try:
        ctl.start()
    except OSError as exc:
        raise EmulatorError(str(exc)) from exc
    previous = {sig: signal.signal(sig, _on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        with ctl:
            time.sleep(0.05)  # let the first ticks run so the summary shows a live state
            print(_summary(ctl, args.backend), flush=True)
            print("Ctrl-C or SIGTERM stops it.", flush=True)
            while not done.wait(args.status_interval or 0.5):
                if args.status_interval:
                    print(_summary(ctl, args.backend), flush=True)
            final = _summary(ctl, args.backend)
        print("stopped.\n" + final, flush=True)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return 0
