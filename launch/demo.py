"""``sygrid demo``: the main job on built-in defaults, the picking demo in the simulated cell.

It is ``sygrid pick`` on ``launch/cells/sim.toml``: the UR controller emulator on loopback, a bin of 10 built-in
parts dropped with the seed, the shipped models (``models/sim_cell``) in the loop, ur_rtde driving the arm until
the bin is empty or nothing is safe to pick; it prints the success rate and cycle times and writes the run report
(JSON and PNG) to ``out/pick``. Every option of ``sygrid pick`` applies.
"""

from __future__ import annotations

import argparse

from launch import pick
from robot.pick_report import StopReason

add_arguments = pick.add_arguments


def run(args: argparse.Namespace) -> int:
    """As ``sygrid pick``, except that a run that stopped cleanly with parts left (exit code 1 there, so scripts
    can tell a cleared bin) is a completed demo: its report says what was left and why. A run ended by an error or
    a stop request (the emulator died) keeps its 1."""
    code, report = pick.run_with_report(args)
    return 0 if code == 1 and report.stop_reason not in (StopReason.ERROR, StopReason.INTERRUPTED) else code
