"""Gripper calibration: the routine against a register model of a real 2F-85 (fingers that meet short of 255), the
file round trip, the cell file's calibration (loaded, applied, required before a hardware run), and the same routine
run by ``sygrid calibrate gripper`` against the emulator's MuJoCo gripper (127.0.0.91; no other test uses it)."""

from __future__ import annotations

import itertools
import json
import re
from pathlib import Path

import pytest

from robot.cell_setup import load_cell_setup
from robot.gripper import (
    OBJ_AT_POSITION,
    OBJ_STOPPED_CLOSING,
    GripperError,
    RobotiqGripperConfig,
    RobotiqSocketGripper,
)
from robot.gripper_calibration import (
    HOLD_MARGIN_COUNTS,
    GripperCalibration,
    calibrate_gripper,
    load_gripper_calibration,
    save_gripper_calibration,
)
from robot.pick_config import PickerConfig
from sygrid.errors import ConfigError

ROOT = Path(__file__).resolve().parents[1]
SIM_HOST = "127.0.0.91"
STROKE_M = 0.085


class Real2F85(RobotiqSocketGripper):
    """The register map of a real 2F-85 behind the socket protocol (``get``/``set``; no socket): the fingers meet at
    the readings ``meet`` (in turn, short of 255), fully open reads ``open_at`` (in turn); between, the opening is
    ``STROKE_M * (meet - POS) / meet``. An object ``object_width_m`` wide stops a close (OBJ 2); a full close on
    nothing ends "at the requested position" (OBJ 3), as the real gripper reports it."""

    def __init__(self, config: RobotiqGripperConfig, meet=(227,), open_at=(0,), object_width_m=None) -> None:
        super().__init__(config)
        self.regs = {"ACT": 0, "GTO": 0, "ATR": 0, "STA": 0, "PRE": 0, "POS": 0, "OBJ": 0, "FLT": 0, "SPE": 0, "FOR": 0}
        self._meet, self._open_at = itertools.cycle(meet), itertools.cycle(open_at)
        self._current_meet = meet[0]
        self.object_width_m = object_width_m

    def connect(self) -> None:
        pass

    def get(self, name: str) -> int:
        return self.regs[name]

    def set(self, **values: int) -> None:
        self.regs.update({k: v for k, v in values.items() if k != "POS"})  # POS reads the fingers, not the request
        if "ACT" in values:
            self.regs["STA"] = 3 if values["ACT"] else 0
        if "POS" in values and self.regs["GTO"]:
            self._move(values["POS"])

    def _move(self, request: int) -> None:
        if request > self.regs["POS"]:  # a close: where the fingers meet this time
            self._current_meet = next(self._meet)
        meet = self._current_meet
        self.regs["PRE"] = request
        stop = meet
        if self.object_width_m is not None:
            stop = round(meet * (1.0 - self.object_width_m / STROKE_M))
        if request >= stop and stop < meet:
            self.regs.update(POS=stop, OBJ=OBJ_STOPPED_CLOSING)
        else:
            pos = min(request, meet)
            self.regs.update(POS=next(self._open_at) if pos == 0 else pos, OBJ=OBJ_AT_POSITION)


def _calibrated(meet=(227,), **kwargs) -> GripperCalibration:
    return calibrate_gripper(Real2F85(RobotiqGripperConfig("robot.test"), meet=meet, **kwargs))


def test_calibration_makes_an_empty_close_read_zero_and_widths_true() -> None:
    min_held = PickerConfig().min_held_width_m
    raw = Real2F85(RobotiqGripperConfig("robot.test"))
    raw.activate()
    assert raw.close() is False  # nothing held, as the gripper says, but the width reads 9 mm: a hold to the picker
    assert raw.width_m() == pytest.approx(STROKE_M * (1 - 227 / 255)) and raw.width_m() >= min_held

    calibration = _calibrated(meet=(227, 228, 227), open_at=(0, 1, 0))
    assert (calibration.pos_open, calibration.pos_closed) == (1, 227)
    assert calibration.closed_readings == (227, 228, 227) and calibration.open_readings == (0, 1, 0)
    assert calibration.hold_threshold_counts == HOLD_MARGIN_COUNTS  # no empty close read below 227
    assert calibration.metres_per_count == pytest.approx(STROKE_M / 226)

    config = calibration.apply(RobotiqGripperConfig("robot.test"))
    assert (config.pos_open, config.pos_closed) == (1, 227)
    gripper = Real2F85(config)
    gripper.activate()
    assert gripper.close() is False and gripper.width_m() == 0.0 < calibration.hold_threshold_m
    assert gripper.get("PRE") == 255  # a full close still requests the register's end
    holding = Real2F85(config, object_width_m=0.030)
    holding.activate()
    assert holding.close() is True
    assert holding.width_m() == pytest.approx(0.030, abs=calibration.metres_per_count)
    gripper.open(width_m=0.050)
    assert gripper.width_m() == pytest.approx(0.050, abs=calibration.metres_per_count)
    gripper.open()
    assert gripper.get("PRE") == 0


def test_calibration_refuses_what_it_cannot_trust() -> None:
    with pytest.raises(GripperError, match=r"stopped on an object at position 147 while closing"):
        _calibrated(object_width_m=0.030)
    with pytest.raises(GripperError, match=r"travelled only 80 counts.*is something blocking them"):
        _calibrated(meet=(80,))
    with pytest.raises(GripperError, match=r"the empty closes disagree by 6 counts"):
        _calibrated(meet=(225, 231, 228))
    spread = _calibrated(meet=(226, 229, 228))
    assert spread.pos_closed == 228 and spread.hold_threshold_counts == 2 + HOLD_MARGIN_COUNTS


def test_the_calibration_file_round_trip_and_its_errors(tmp_path: Path) -> None:
    calibration = _calibrated(meet=(227, 228, 227))
    path = save_gripper_calibration(tmp_path / "cal" / "gripper.json", calibration)
    assert load_gripper_calibration(path) == calibration
    data = json.loads(path.read_text())
    assert data["gripper"] == "robot.test:63352" and data["hold_threshold_m"] == pytest.approx(
        calibration.hold_threshold_m
    )
    for edit, match in (
        (lambda d: d.update(format="other"), "not a gripper calibration file"),
        (lambda d: d.update(pos_closed="227"), "pos_closed is missing or not a int"),
        (lambda d: d.update(pos_open=230), r"0 <= pos_open < pos_closed"),
        (lambda d: d["readings"].update(closed=[]), r"readings\.closed must be a non-empty list"),
    ):
        broken = json.loads(path.read_text())
        edit(broken)
        bad = tmp_path / "bad.json"
        bad.write_text(json.dumps(broken))
        with pytest.raises(ConfigError, match=rf"bad\.json: .*{match}"):
            load_gripper_calibration(bad)
    bad.write_text("{")
    with pytest.raises(ConfigError, match=r"bad\.json: not valid JSON"):
        load_gripper_calibration(bad)
    with pytest.raises(ConfigError, match=r"made on the gripper at robot\.test:63352 .* recalibrate"):
        calibration.apply(RobotiqGripperConfig("robot.other"))
    with pytest.raises(ConfigError, match=r"0\.14 m; recalibrate"):
        calibration.apply(RobotiqGripperConfig("robot.test", stroke_m=0.14))


def _hardware_cell(tmp_path: Path, calibration: str | None = "gripper.json", name: str = "cell.toml") -> Path:
    """``launch/cells/ur5e_realsense.toml`` in ``tmp_path``, its gripper calibration in the same folder (or none)."""
    text = (ROOT / "launch" / "cells" / "ur5e_realsense.toml").read_text()
    line = "" if calibration is None else f'calibration = "{calibration}"'
    text, n = re.subn(r"^calibration = .*$", line, text, flags=re.MULTILINE)
    assert n == 1, "the cell file's [gripper] calibration line was not found"
    path = tmp_path / name
    path.write_text(text)
    return path


def test_a_hardware_cell_needs_its_gripper_calibration_to_start(tmp_path: Path) -> None:
    from launch.pick import open_cell

    cell = _hardware_cell(tmp_path)
    setup = load_cell_setup(cell)  # loads without it: `sygrid calibrate gripper` reads the same file
    assert setup.gripper_calibration is None and setup.gripper_calibration_path == tmp_path / "gripper.json"
    command = re.escape(f"sygrid calibrate gripper --config {cell}")
    with pytest.raises(ConfigError, match=rf"no gripper calibration at .*gripper\.json: run `{command}`"):
        setup.require_gripper_calibration()
    with pytest.raises(ConfigError, match=command), open_cell(setup):  # before anything is connected
        pass
    unset = load_cell_setup(_hardware_cell(tmp_path, calibration=None, name="unset.toml"))
    with pytest.raises(ConfigError, match=r"needs a gripper calibration: set \[gripper\] calibration"):
        unset.require_gripper_calibration()

    calibration = GripperCalibration("192.168.1.10:63352", STROKE_M, 0, 227, 4, (0, 0), (225, 227))
    save_gripper_calibration(tmp_path / "gripper.json", calibration)
    setup = load_cell_setup(cell)
    setup.require_gripper_calibration()
    assert setup.gripper_calibration == calibration
    assert (setup.gripper.pos_open, setup.gripper.pos_closed) == (0, 227)
    assert setup.picker.min_held_width_m == pytest.approx(4 * STROKE_M / 227)  # raised to the threshold
    assert load_cell_setup(cell, load_gripper_calibration=False).gripper.pos_closed == 255

    other = GripperCalibration("192.168.1.11:63352", STROKE_M, 0, 227, 4, (0,), (227,))
    save_gripper_calibration(tmp_path / "gripper.json", other)
    with pytest.raises(ConfigError, match=r"cell\.toml: gripper\.calibration .*made on the gripper at 192\.168\.1\.11"):
        load_cell_setup(cell)


def test_the_realsense_cell_file_loads_its_camera(tmp_path: Path) -> None:
    from perception.oak import OakConfig
    from perception.realsense import RealSenseConfig

    setup = load_cell_setup(ROOT / "launch" / "cells" / "ur5e_realsense.toml")
    assert not setup.is_sim and setup.data.camera.kind == "realsense"
    assert setup.camera == RealSenseConfig(rgb_size=(1280, 720), depth_size=(848, 480), fps=15, emitter_enabled=True)
    assert isinstance(load_cell_setup(ROOT / "launch" / "cells" / "ur5e_oak.toml").camera, OakConfig)
    assert load_cell_setup(ROOT / "launch" / "cells" / "sim.toml").camera is None
    text = _hardware_cell(tmp_path).read_text()
    bad = tmp_path / "bad.toml"
    for old, new, match in (
        ('visual_preset = "default"', 'visual_preset = "sharp"', r"\[camera\]: .*visual_preset 'sharp'"),
        ("fps = 15", "fps = 14.5", r"\[camera\]: RealSenseConfig\.fps must be a whole number"),
        ("fps = 15", "fps = 25", r"\[camera\]: RealSenseConfig\.fps must be one of"),
        ('kind = "realsense"', 'kind = "oak"', r"\[camera\]: \['depth_size', 'emitter_enabled', 'visual_preset'\] are"),
        ("emitter_enabled = true", 'emitter_enabled = "on"', r"bad\.toml.*camera\.emitter_enabled"),
    ):
        bad.write_text(text.replace(old, new, 1))
        with pytest.raises(ConfigError, match=rf"bad\.toml.*{match}" if "bad" not in match else match):
            load_cell_setup(bad)


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_the_simulated_gripper_runs_the_same_routine(tmp_path: Path) -> None:
    pytest.importorskip("rtde_control")
    from launch.cli import main

    text = (ROOT / "launch" / "cells" / "sim.toml").read_text().replace('host = "127.0.0.50"', f'host = "{SIM_HOST}"')
    text = text.replace("[gripper]\n", '[gripper]\ncalibration = "gripper.json"\n', 1)
    cell = tmp_path / "sim.toml"
    cell.write_text(text)
    assert main(["calibrate", "gripper", "--config", str(cell), "--repeats", "2"]) == 0
    setup = load_cell_setup(cell)
    calibration = setup.gripper_calibration
    assert calibration is not None and calibration.gripper == f"{SIM_HOST}:63352"
    # The simulated fingers open to the full stroke and meet at the register's end.
    assert calibration.open_readings == (0, 0) and calibration.closed_readings == (255, 255)
    assert (setup.gripper.pos_open, setup.gripper.pos_closed) == (0, 255)
    assert calibration.hold_threshold_counts == HOLD_MARGIN_COUNTS
    # raised from the uncalibrated default to the calibration's 2 counts (0.67 mm)
    assert setup.picker.min_held_width_m == pytest.approx(calibration.hold_threshold_m)
    assert calibration.hold_threshold_m > PickerConfig().min_held_width_m
