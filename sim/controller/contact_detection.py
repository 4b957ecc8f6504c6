"""The ``rtde_control`` script's contact detection (ur_rtde's ``startContactDetection`` / ``readContactDetection``
/ ``stopContactDetection``, commands 62-64), stepped once per controller cycle.

As the script's ``contact_thread``: once started (a direction in input_double_register 0-5; a null one means the
tool's own motion), it first waits until the tool is not in contact, then for a contact against the direction
(URScript ``tool_contact``, the wrench history's onset, ``sim.controller.force``). On a contact it does what the
script's internal command 254 does: ends the async move, stops the arm (stopl at 3 m/s2) and moves back to where the
contact began (``movel`` with URScript's defaults), and keeps the steps back to the contact's start, which both
reading and stopping the detection answer (output_int_register_1; 0: no contact). The controller reacts on the
tick the contact shows, not after a client's round trip, which is why a cell uses it for an unexpected contact.
A null direction is taken as "any direction" (the force's magnitude) here, not as the target TCP speed's.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Protocol

import numpy as np

from sim.controller.arm import ArmController
from sim.controller.errors import MotionError
from sygrid.robots.kinematics import T_to_pose, forward_kinematics

log = logging.getLogger(__name__)

#: URScript's stopl deceleration in the script's contact handling [m/s^2], and movel's defaults [m/s, m/s^2].
STOP_DECEL_M_S2 = 3.0
RETURN_SPEED_M_S, RETURN_ACCEL_M_S2 = 0.25, 1.2


def stop_at_contact(arm: ArmController) -> None:
    """The script's reaction to a contact (moveUntilContact and contact detection alike): stopl(3)."""
    arm.stop(STOP_DECEL_M_S2, linear=True)
    arm.contact_watch = False


def move_back_to(arm: ArmController, q_contact: np.ndarray) -> None:
    """Once stopped: ``movel`` with URScript's defaults back to where the contact began (``MotionError`` when the
    arm cannot)."""
    arm.movel(T_to_pose(forward_kinematics(q_contact, arm.T_flange_tcp)), RETURN_SPEED_M_S, RETURN_ACCEL_M_S2)


class ContactHost(Protocol):
    def tool_contact(self, direction: np.ndarray, max_steps: int | None = None) -> int: ...
    def q_history(self, steps: int) -> np.ndarray: ...
    def end_program(self, reason: str, error: bool) -> None: ...


class ContactDetection:
    """One detection at a time; ``step`` once per cycle; ``step_back`` is what commands 63/64 answer."""

    def __init__(self, arm: ArmController, host: ContactHost) -> None:
        self.arm, self.host = arm, host
        self.phase: str | None = None  # None (off), "clear", "watch", "stopping", "returning"
        self.step_back = 0
        self._direction = np.zeros(6)
        self._q_contact: np.ndarray | None = None

    @property
    def handling(self) -> bool:
        """The contact is being handled (stop and move back): the script's main loop is busy with it."""
        return self.phase in ("stopping", "returning")

    def start(self, direction: np.ndarray) -> None:
        """Command 62: a running detection is replaced; the last contact's steps back are kept until one is seen."""
        self._direction = np.asarray(direction, dtype=float)
        self.phase = "clear"
        self.arm.contact_watch = True

    def stop(self) -> int:
        """Command 63: ends the detection (a contact being handled still finishes); the steps back (0: none)."""
        if not self.handling:
            self.phase = None
            self.arm.contact_watch = False
        return self.step_back

    def abort(self) -> None:
        self.phase = None
        self.arm.contact_watch = False

    def step(self, on_contact: Callable[[], None]) -> None:
        """One cycle; ``on_contact()`` ends the program's async move when a contact is seen."""
        if self.phase in ("clear", "watch"):
            steps = self.host.tool_contact(self._direction)
            if self.phase == "clear":
                if steps == 0:
                    self.phase, self.step_back = "watch", 0
                return
            if steps > 0:
                self.step_back = steps
                self._q_contact = self.host.q_history(steps)
                log.info("rtde_control: contact detected (%d steps back); stopping and moving back", steps)
                on_contact()
                stop_at_contact(self.arm)
                self.phase = "stopping"
            return
        if self.phase == "stopping" and self.arm.motion is None:
            try:
                move_back_to(self.arm, self._q_contact)
            except MotionError as exc:
                self.phase = None
                self.host.end_program(f"contact detection failed: {exc}", error=True)
                return
            self.phase = "returning"
        elif self.phase == "returning" and self.arm.motion is None:
            self.phase = None
