"""The errors of ``robot.ur``: what a caller (the picker's state machine) can tell apart and act on.

- ``MotionRefusedError`` (a ``ValueError``): checked and **nothing was sent**; try another candidate.
- ``MotionFailedError``: sent, not completed; ``recoverable`` ones need ``URRobot.recover()`` and a re-plan.
- ``RobotConnectionError``: connecting failed; ``RecoveryError``: ``recover()`` failed.
"""

from __future__ import annotations

import numpy as np

from sygrid.errors import SygridError

__all__ = [
    "ConnectionLostError",
    "EmergencyStopError",
    "MotionFailedError",
    "MotionRefusedError",
    "NoContactError",
    "OutsideWorkspaceError",
    "ProtectiveStopError",
    "RecoveryError",
    "RobotConnectionError",
    "RobotError",
    "UnreachableError",
]


class RobotError(SygridError):
    """Base of the errors this module raises."""


class RobotConnectionError(RobotError, ConnectionError):
    """Could not connect to the controller (the message names the host and the port)."""


class MotionRefusedError(RobotError, ValueError):
    """A motion failed its checks; nothing was sent to the controller."""


class OutsideWorkspaceError(MotionRefusedError):
    """The target, or the path to it, leaves the workspace box."""


class UnreachableError(MotionRefusedError):
    """No inverse-kinematics solution within the joint limits."""


class MotionFailedError(RobotError, RuntimeError):
    """A motion was sent but did not complete. ``q``/``T_base_tcp``: where the arm was when it was seen (or None).
    ``recoverable``: ``URRobot.recover()`` can bring the robot back (then re-plan from the current pose)."""

    recoverable = True

    def __init__(self, message: str, q: np.ndarray | None = None, T_base_tcp: np.ndarray | None = None) -> None:
        super().__init__(message)
        self.q = q
        self.T_base_tcp = T_base_tcp


class ProtectiveStopError(MotionFailedError):
    """The controller is in a protective stop (a collision, a safety limit, or a stop command)."""


class EmergencyStopError(MotionFailedError):
    """The controller is emergency-stopped: a person must release the button; software cannot recover it."""

    recoverable = False


class ConnectionLostError(MotionFailedError):
    """The link to the controller dropped (or went silent) before or during a motion."""


class NoContactError(MotionFailedError):
    """A move until contact went its whole travel without meeting anything; the program was stopped (recover)."""


class RecoveryError(RobotError, RuntimeError):
    """``recover()`` could not bring the robot back to a running control program."""
