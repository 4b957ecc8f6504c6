"""The UR controller emulator: RTDE (30004), script intake (30001-30003), dashboard (29999) and a Robotiq-style
gripper socket (63352) on a loopback address, driving a simulated arm so that the stock ur_rtde client works.

    from sim.controller import EmulatedController, KinematicBackend
    with EmulatedController(KinematicBackend(), host="127.0.0.2") as ctl:
        ...  # rtde_control.RTDEControlInterface("127.0.0.2") from another process

The ur_rtde constructors hold the Python GIL while they wait for the emulator, so the client and the emulator must
live in different processes: ``ControllerProcess`` runs one in a child process and forwards the test hooks.
"""

from sim.controller.backend import ArmBackend, ArmSample, KinematicBackend
from sim.controller.backend_by_name import make_backend
from sim.controller.controller import ControllerPorts, EmulatedController
from sim.controller.errors import BackendUnavailableError, EmulatorError, MotionError
from sim.controller.process import ControllerProcess
from sim.controller.status import ControllerStatus, TickStats
from sim.controller.world_backend import WorldBackend

__all__ = [
    "ArmBackend",
    "ArmSample",
    "BackendUnavailableError",
    "ControllerPorts",
    "ControllerProcess",
    "ControllerStatus",
    "EmulatedController",
    "EmulatorError",
    "KinematicBackend",
    "MotionError",
    "TickStats",
    "WorldBackend",
    "make_backend",
]
