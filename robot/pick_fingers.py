"""``Fingers``: what the pick cycle commands of the gripper and reads back from it: open to a width and wait until
the fingers are there, let go at the place pose, hold the fingers where they are, and tell a held part from one that
slipped out. Widths in metres; the settings are ``PickerConfig``'s."""

from __future__ import annotations

import logging
import time

import numpy as np

from robot.gripper import GripperError
from robot.pick_config import PickerConfig
from robot.pick_protocols import GraspLike, GripperLike

log = logging.getLogger(__name__)

_WIDTH_STEADY_M = 0.0005  # fingers that move less than this ...
_WIDTH_STEADY_S = 0.15  # ... for this long rest on what they hold


class Fingers:
    """The gripper as the pick cycle uses it (``gripper``: any ``GripperLike``)."""

    def __init__(self, gripper: GripperLike, config: PickerConfig) -> None:
        self.gripper = gripper
        self.config = config

    def stroke(self) -> float:
        """The fully open width (inf where the gripper does not know it)."""
        stroke = self.gripper.stroke_m
        return float(np.inf) if stroke is None else float(stroke)

    def grasp_opening(self, grasp: GraspLike) -> float | None:
        """The opening a grasp's approach was checked with, as the gripper is commanded to it (None: a gripper that
        can only open fully)."""
        return min(grasp.opening_width_m, self.stroke()) if self.gripper.can_set_width else None

    def open_to(self, width_m: float | None) -> bool:
        """Opens to ``width_m`` (None: fully) and waits until the fingers are there (within ``open_tolerance_m``,
        for up to ``open_timeout_s``): a gripper can report "stopped on something" while a squeezed part still
        holds its fingers. False if they did not get there; True also for a gripper that cannot tell its width."""
        cfg = self.config
        if width_m is None:
            self.gripper.open()
        else:
            self.gripper.open(width_m=width_m)
        target = self.stroke() if width_m is None else width_m
        deadline = time.monotonic() + cfg.open_timeout_s
        while True:
            width = self.gripper.width_m()
            if width is None or not np.isfinite(target) or width >= target - cfg.open_tolerance_m:
                return True
            if time.monotonic() > deadline:
                return False
            time.sleep(0.02)

    def release(self, width_m: float | None) -> bool:
        """Lets go at the place pose: opens (up to ``release_tries`` times) until the fingers are open."""
        for k in range(self.config.release_tries):
            if self.open_to(width_m):
                return True
            log.warning("the fingers did not open at the place pose (at %s, try %d)", self.width_text(), k + 1)
        return False

    def hold(self) -> None:
        """Stops the fingers where they are (commanded to their own width), so they no longer push on anything."""
        try:
            width = self.gripper.width_m() if self.gripper.can_set_width else None
            if width is not None:
                self.gripper.open(width_m=width)
        except GripperError as exc:
            log.warning("could not hold the fingers before recovering (%s)", exc)

    def apart(self) -> bool:
        """The fingers stopped at least ``min_held_width_m`` apart: something thin is between them."""
        width = self.gripper.width_m()
        return width is not None and width >= self.config.min_held_width_m

    def width_text(self) -> str:
        width = self.gripper.width_m()
        return "an unknown width" if width is None else f"{1e3 * width:.1f} mm"

    def slip_reason(self, grasp: GraspLike) -> tuple[str, float | None]:
        """Why the part is not in the gripper after lifting ("" when it is), and the fingers' last width.

        Fingers closed below the narrowest width the part can be held at (``PickerConfig.hold_any_width``), less
        ``slip_width_tolerance_m`` and never below ``min_held_width_m``, say so at once. Otherwise the part is held
        when the gripper reports an object, or when the fingers rest where they are (no change over
        ``_WIDTH_STEADY_S``): a gripper may read "moving" (no object) while its pads hold a part, from the jitter of
        the finger speed. Neither within ``slip_settle_s``: the object is lost."""
        cfg = self.config
        narrowest = min(grasp.min_hold_width_m, grasp.grasp_width_m) if cfg.hold_any_width else grasp.grasp_width_m
        lowest = max(narrowest - cfg.slip_width_tolerance_m, cfg.min_held_width_m)
        deadline = time.monotonic() + cfg.slip_settle_s
        steady_since, last_width = time.monotonic(), None
        while True:
            detected = self.gripper.object_detected()
            width = self.gripper.width_m()
            now = time.monotonic()
            if width is not None and width < lowest:
                why = f"the fingers closed to {1e3 * width:.1f} mm, the part is {1e3 * grasp.grasp_width_m:.1f} mm wide"
                if narrowest < grasp.grasp_width_m:
                    why += f" ({1e3 * narrowest:.1f} mm at its narrowest hold)"
                return why, width
            if detected is not False:
                return "", width
            if width is not None and last_width is not None and abs(width - last_width) > _WIDTH_STEADY_M:
                steady_since = now
            last_width = width
            if width is not None and now - steady_since >= _WIDTH_STEADY_S:
                return "", width
            if now > deadline:
                return "the gripper no longer reports an object after lifting", width
            time.sleep(0.02)
