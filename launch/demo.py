"""``sygrid demo``: the main job on built-in defaults, the picking demo in the simulated cell.

It is ``sygrid pick`` on ``launch/cells/sim.toml``: the UR controller emulator on loopback, a bin of 10 built-in
parts dropped with the seed, the shipped models (``models/builtin``) in the loop, ur_rtde driving the arm until
the bin is empty; it prints the success rate and cycle times and writes the run report (JSON and PNG) to
``out/pick``. Every option of ``sygrid pick`` applies.
"""

from launch.pick import add_arguments, run

__all__ = ["add_arguments", "run"]
