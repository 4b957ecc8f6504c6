"""Gripper calibration: the position register's readings with the fingers fully open and closed on nothing, the
width mapping between them and the hold threshold, measured on the gripper and kept per cell in a JSON file.

Why: a Robotiq 2F-85's position register runs from 0 (open) to 255 (the full-close request), but its fingers meet
short of 255, at a reading that differs from unit to unit. Uncalibrated (``pos_closed = 255``) an empty close then
reads a few millimetres apart, which the picker takes for a hold (``PickerConfig.min_held_width_m``).

Routine (``calibrate_gripper``; nothing between the fingers): activate, then ``repeats`` times open fully (request 0)
and read the position, close fully (request 255) and read the position. Every empty close must end "at the
requested position" (``OBJ`` 3; a stop on an object means something is between the fingers). Result:

- ``pos_open``: the largest open reading; ``pos_closed``: the median closed reading (``RobotiqGripperConfig``'s
  fields): widths map linearly, ``width = stroke_m * (pos_closed - pos) / (pos_closed - pos_open)``, clipped to
  ``[0, stroke_m]``, so ``metres_per_count = stroke_m / (pos_closed - pos_open)``.
- ``hold_threshold_counts``: how far below ``pos_closed`` an empty close has read (the lowest closed reading) plus
  ``HOLD_MARGIN_COUNTS`` for the register's noise; ``hold_threshold_m`` is that in metres: the smallest finger
  opening that counts as a hold. The cell raises ``PickerConfig.min_held_width_m`` to it (``robot.cell_setup``).

Checks: the fingers must travel at least ``MIN_TRAVEL_COUNTS`` between open and closed (less: something blocks
them), the closed readings may spread by at most ``MAX_SPREAD_COUNTS``, and a final empty close read through the new
mapping must come out below the hold threshold. Failures raise ``GripperError`` saying what was read.

File (``save_gripper_calibration``/``load_gripper_calibration``): ``format``, ``version``, the gripper it was made
on (``gripper``: host:port) and its ``stroke_m``, the fields above and the raw ``readings``. A hardware cell refuses
to start without it (``robot.cell_setup.CellSetup.require_gripper_calibration``).
"""

from __future__ import annotations

import dataclasses
import datetime
import logging
import statistics
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from robot.gripper import (
    OBJ_AT_POSITION,
    OBJ_STOPPED_CLOSING,
    POS_FULLY_CLOSED,
    POS_FULLY_OPEN,
    GripperError,
    RobotiqGripperConfig,
    RobotiqSocketGripper,
)
from sygrid.errors import ConfigError
from sygrid.fileio import read_json, write_json_atomic

log = logging.getLogger(__name__)

FILE_FORMAT = "sygrid.gripper_calibration"
FILE_VERSION = 1
#: Register counts added to the empty closes' spread for the hold threshold (the register reads within a count).
HOLD_MARGIN_COUNTS = 2
#: The fewest counts between the open and the closed reading of a working gripper (a 2F-85 travels about 230).
MIN_TRAVEL_COUNTS = 100
#: The most the empty-closed readings may spread.
MAX_SPREAD_COUNTS = 4
#: Speed and force of the calibration moves: slow and gentle.
CALIBRATION_SPEED_M_S = 0.05
CALIBRATION_FORCE_N = 40.0


@dataclass(frozen=True)
class GripperCalibration:
    """A measured calibration; see the module docstring. Lengths in metres, positions in register counts."""

    gripper: str
    stroke_m: float
    pos_open: int
    pos_closed: int
    hold_threshold_counts: int
    open_readings: tuple[int, ...]
    closed_readings: tuple[int, ...]
    created: str = ""

    def __post_init__(self) -> None:
        if not 0 <= self.pos_open < self.pos_closed <= 255:
            raise ConfigError(
                f"GripperCalibration needs 0 <= pos_open < pos_closed <= 255, got {self.pos_open}, {self.pos_closed}"
            )
        if not self.stroke_m > 0:
            raise ConfigError(f"GripperCalibration.stroke_m must be > 0, got {self.stroke_m}")
        if not 1 <= self.hold_threshold_counts <= self.pos_closed - self.pos_open:
            raise ConfigError(
                f"GripperCalibration.hold_threshold_counts must be in [1, {self.pos_closed - self.pos_open}], got "
                f"{self.hold_threshold_counts}"
            )

    @property
    def metres_per_count(self) -> float:
        return self.stroke_m / (self.pos_closed - self.pos_open)

    @property
    def hold_threshold_m(self) -> float:
        """The smallest finger opening that counts as a hold."""
        return self.hold_threshold_counts * self.metres_per_count

    def width_m(self, pos: int) -> float:
        """The finger opening for a position reading."""
        fraction = (self.pos_closed - pos) / (self.pos_closed - self.pos_open)
        return self.stroke_m * min(max(fraction, 0.0), 1.0)

    def apply(self, config: RobotiqGripperConfig, where: str = "gripper calibration") -> RobotiqGripperConfig:
        """``config`` with the calibrated ``pos_open``/``pos_closed``. ConfigError (naming ``where``) when the
        calibration was made on another gripper (address or stroke)."""
        here = f"{config.host}:{config.port}"
        if self.gripper != here or abs(self.stroke_m - config.stroke_m) > 1e-9:
            raise ConfigError(
                f"{where}: made on the gripper at {self.gripper} with a {self.stroke_m:g} m stroke, but the cell's "
                f"gripper is at {here} with {config.stroke_m:g} m; recalibrate it"
            )
        return dataclasses.replace(config, pos_open=self.pos_open, pos_closed=self.pos_closed)


def calibrate_gripper(gripper: RobotiqSocketGripper, repeats: int = 3) -> GripperCalibration:
    """Runs the routine of the module docstring on a connected gripper with nothing between its fingers; leaves the
    fingers open. ``GripperError`` when a check fails."""
    if repeats < 1:
        raise ValueError(f"repeats must be >= 1, got {repeats}")
    cfg = gripper.config
    where = f"gripper at {cfg.host}:{cfg.port}"
    gripper.activate()
    open_readings, closed_readings = [], []
    for k in range(repeats):
        _move(gripper, POS_FULLY_OPEN, f"opening (run {k + 1})")
        open_readings.append(gripper.get("POS"))
        obj = _move(gripper, POS_FULLY_CLOSED, f"the empty close (run {k + 1})")
        closed_readings.append(gripper.get("POS"))
        if obj == OBJ_STOPPED_CLOSING:
            _move(gripper, POS_FULLY_OPEN, "opening")
            raise GripperError(
                f"{where}: the fingers stopped on an object at position {closed_readings[-1]} while closing; take "
                "whatever is between them away and calibrate again"
            )
    _move(gripper, POS_FULLY_OPEN, "opening")
    pos_open, pos_closed = max(open_readings), round(statistics.median(closed_readings))
    spread = max(closed_readings) - min(closed_readings)
    readings = f"open readings {open_readings}, closed readings {closed_readings}"
    if pos_closed - pos_open < MIN_TRAVEL_COUNTS:
        raise GripperError(
            f"{where}: the fingers travelled only {pos_closed - pos_open} counts ({readings}; at least "
            f"{MIN_TRAVEL_COUNTS} expected): is something blocking them?"
        )
    if spread > MAX_SPREAD_COUNTS:
        raise GripperError(
            f"{where}: the empty closes disagree by {spread} counts ({readings}; at most {MAX_SPREAD_COUNTS})"
        )
    calibration = GripperCalibration(
        gripper=f"{cfg.host}:{cfg.port}",
        stroke_m=cfg.stroke_m,
        pos_open=pos_open,
        pos_closed=pos_closed,
        hold_threshold_counts=pos_closed - min(closed_readings) + HOLD_MARGIN_COUNTS,
        open_readings=tuple(open_readings),
        closed_readings=tuple(closed_readings),
        created=datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
    )
    _verify(gripper, calibration, where)
    log.info("%s calibrated: %s", where, readings)
    return calibration


def _move(gripper: RobotiqSocketGripper, pos: int, what: str) -> int:
    obj = gripper.move_to_position(pos, CALIBRATION_SPEED_M_S, CALIBRATION_FORCE_N)
    if obj not in (OBJ_AT_POSITION, OBJ_STOPPED_CLOSING):
        raise GripperError(f"gripper: {what} ended with OBJ {obj} (expected 3, at the requested position)")
    return obj


def _verify(gripper: RobotiqSocketGripper, calibration: GripperCalibration, where: str) -> None:
    """One more empty close read through the new mapping: below the hold threshold. Leaves the fingers open."""
    _move(gripper, POS_FULLY_CLOSED, "the check close")
    width = calibration.width_m(gripper.get("POS"))
    _move(gripper, POS_FULLY_OPEN, "opening")
    if width >= calibration.hold_threshold_m:
        raise GripperError(
            f"{where}: an empty close still reads {1e3 * width:.2f} mm with the new calibration (hold threshold "
            f"{1e3 * calibration.hold_threshold_m:.2f} mm); the closed position drifts: calibrate again"
        )


# ---------------------------------------------------------------------------------------------- file


def save_gripper_calibration(path: str | Path, calibration: GripperCalibration) -> Path:
    """Writes the calibration JSON atomically."""
    c = calibration
    return write_json_atomic(
        path,
        {
            "format": FILE_FORMAT,
            "version": FILE_VERSION,
            "gripper": c.gripper,
            "created": c.created,
            "stroke_m": c.stroke_m,
            "pos_open": c.pos_open,
            "pos_closed": c.pos_closed,
            "metres_per_count": c.metres_per_count,
            "hold_threshold_counts": c.hold_threshold_counts,
            "hold_threshold_m": c.hold_threshold_m,
            "readings": {"open": list(c.open_readings), "closed": list(c.closed_readings)},
        },
    )


def load_gripper_calibration(path: str | Path) -> GripperCalibration:
    """Reads ``save_gripper_calibration``'s JSON; a missing, corrupt or inconsistent file raises ConfigError naming
    the file and the field."""
    path = Path(path)
    data = read_json(path, "gripper calibration")
    where = str(path)
    if not isinstance(data, dict) or data.get("format") != FILE_FORMAT:
        raise ConfigError(f'{where}: not a gripper calibration file (expected "format": "{FILE_FORMAT}")')
    if data.get("version") != FILE_VERSION:
        raise ConfigError(f"{where}: version {data.get('version')!r} is not supported (expected {FILE_VERSION})")
    readings = data.get("readings")
    if not isinstance(readings, dict):
        raise ConfigError(f"{where}: readings must be an object with open and closed lists")
    try:
        return GripperCalibration(
            gripper=_field(data, "gripper", str, where),
            stroke_m=float(_field(data, "stroke_m", (int, float), where)),
            pos_open=_field(data, "pos_open", int, where),
            pos_closed=_field(data, "pos_closed", int, where),
            hold_threshold_counts=_field(data, "hold_threshold_counts", int, where),
            open_readings=tuple(_counts(readings, "open", where)),
            closed_readings=tuple(_counts(readings, "closed", where)),
            created=str(data.get("created", "")),
        )
    except ConfigError as exc:
        raise ConfigError(f"{where}: {exc}") from None


def _field(data: dict[str, Any], name: str, kind: type | tuple[type, ...], where: str) -> Any:
    value = data.get(name)
    if not isinstance(value, kind) or isinstance(value, bool):
        raise ConfigError(f"{where}: {name} is missing or not a {getattr(kind, '__name__', 'number')}: {value!r}")
    return value


def _counts(readings: dict[str, Any], name: str, where: str) -> list[int]:
    values = readings.get(name)
    if not isinstance(values, list) or not values or not all(isinstance(v, int) and 0 <= v <= 255 for v in values):
        raise ConfigError(f"{where}: readings.{name} must be a non-empty list of positions 0..255, got {values!r}")
    return values
