"""``sygrid calibrate gripper|hand-eye|board --config CELL.toml``: a cell's gripper calibration
(``robot.gripper_calibration``), its camera's hand-eye calibration (``launch.calibrate_hand_eye``), or the ChArUco
board that calibration uses, to print.

Gripper: connects to the cell's socket gripper (on a simulated cell: starts the emulator on the file's loopback
address with an empty bin, so its MuJoCo gripper runs the same routine), opens and closes it empty a few times, and
writes the calibration to the file named by the cell's ``[gripper] calibration`` (or ``--out``). Nothing may be
between the fingers; the arm does not move. A hardware cell with a socket gripper does not start without this file.
"""

from __future__ import annotations

import argparse
import contextlib
from pathlib import Path

from robot.cell_setup import load_cell_setup
from sygrid.errors import ConfigError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "what", choices=("gripper", "hand-eye", "board"),
        help="gripper: empty open/close; hand-eye: the camera's pose from a ChArUco board on the flange; board: "
        "that board as a PDF or PNG to print at 100 %%",
    )  # fmt: skip
    parser.add_argument("--config", type=Path, required=True, help="cell file (TOML)")
    parser.add_argument("--out", type=Path, default=None, help="calibration file (default: the cell file's)")
    parser.add_argument("--repeats", type=int, default=3, help="gripper: empty open/close runs")
    parser.add_argument("--poses", type=int, default=12, help="hand-eye: board poses to visit (%(default)s)")
    parser.add_argument("--seed", type=int, default=0, help="hand-eye: draws the poses (%(default)s)")
    parser.add_argument(
        "--speed", type=float, default=0.5, help="hand-eye: joint speed between poses, rad/s (%(default)s)"
    )


def run(args: argparse.Namespace) -> int:
    if args.what == "hand-eye":
        return _hand_eye(args)
    if args.what == "board":
        return _board(args)
    return _gripper(args)


def _board(args: argparse.Namespace) -> int:
    from launch.calibrate_hand_eye import write_board

    board = load_cell_setup(args.config, load_gripper_calibration=False).hand_eye_board()
    path, (w, h) = write_board(board, args.out or Path("charuco_board.pdf"))
    print(
        f"wrote {path}: {board.squares_x} x {board.squares_y} squares of {1e3 * board.square_m:g} mm, markers of "
        f"{1e3 * board.marker_m:g} mm ({board.dictionary}), on a page of {1e3 * w:.0f} x {1e3 * h:.0f} mm. Print it "
        "at 100 % (actual size), check that a square measures its size, and fix it flat to a rigid plate"
    )
    return 0


def _hand_eye(args: argparse.Namespace) -> int:
    from launch.calibrate_hand_eye import run_hand_eye, summary
    from launch.pick_stops import StopSignals

    setup = load_cell_setup(args.config, load_gripper_calibration=False)
    out = args.out or setup.resolve(setup.data.calibration.file)
    if out is None:
        raise ConfigError(f'{args.config}: set [calibration] file = "..." (where to keep it) or pass --out')
    with StopSignals():  # SIGINT / SIGTERM raise, and the robot's context stops the arm
        run = run_hand_eye(setup, out, args.poses, args.seed, args.speed)
    print(summary(run))
    return 0


def _gripper(args: argparse.Namespace) -> int:
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
