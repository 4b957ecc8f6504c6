"""``sygrid calibrate gripper --config CELL.toml``: the gripper calibration of a cell (``robot.gripper_calibration``).

Connects to the cell's socket gripper (on a simulated cell: starts the emulator on the file's loopback address with
an empty bin, so its MuJoCo gripper runs the same routine), opens and closes it empty a few times, and writes the
calibration to the file named by the cell's ``[gripper] calibration`` (or ``--out``). Nothing may be between the
fingers; the arm does not move. A hardware cell with a socket gripper does not start without this file.
"""

from __future__ import annotations

import argparse
import contextlib
from pathlib import Path

from robot.cell_setup import load_cell_setup
from sygrid.errors import ConfigError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("what", choices=("gripper",), help="what to calibrate")
    parser.add_argument("--config", type=Path, required=True, help="cell file (TOML)")
    parser.add_argument("--out", type=Path, default=None, help="calibration file (default: the cell file's)")
    parser.add_argument("--repeats", type=int, default=3, help="empty open/close runs")


def run(args: argparse.Namespace) -> int:
    from robot.gripper import RobotiqGripperConfig, RobotiqSocketGripper
    from robot.gripper_calibration import calibrate_gripper, save_gripper_calibration

    setup = load_cell_setup(args.config, load_gripper_calibration=False)
    if not isinstance(setup.gripper, RobotiqGripperConfig):
        raise ConfigError(
            f"{args.config}: the gripper (kind 'digital_output') has no position feedback: nothing to calibrate"
        )
    out = args.out or setup.gripper_calibration_path
    if out is None:
        raise ConfigError(f'{args.config}: set [gripper] calibration = "..." (where to keep it) or pass --out')
    if args.repeats < 1:
        raise ConfigError(f"--repeats must be >= 1, got {args.repeats}")
    with contextlib.ExitStack() as stack:
        if setup.is_sim:
            from sim.controller import ControllerProcess

            print(f"starting the emulator on {setup.data.sim.host} (empty bin) ...")
            stack.enter_context(ControllerProcess(setup.data.sim.host, backend="mujoco", start_timeout_s=120.0))
        print(f"calibrating the gripper at {setup.gripper.host}:{setup.gripper.port}: keep the fingers clear ...")
        gripper = stack.enter_context(RobotiqSocketGripper(setup.gripper))
        calibration = calibrate_gripper(gripper, repeats=args.repeats)
    path = save_gripper_calibration(out, calibration)
    c = calibration
    print(
        f"open at {c.pos_open}, closed (empty) at {c.pos_closed} counts: {1e3 * c.metres_per_count:.3f} mm per count; "
        f"a hold is {c.hold_threshold_counts} counts ({1e3 * c.hold_threshold_m:.2f} mm) or more apart\n"
        f"wrote {path}"
    )
    return 0
