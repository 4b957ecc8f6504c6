"""``sygrid calibrate hand-eye``: the ChArUco hand-eye calibration run through the stock ur_rtde client against the
emulator (127.0.0.92; no other test uses it), its file used by a cell, and the cell-file fields it reads."""

from __future__ import annotations

import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from robot.calibration import load_calibration
from robot.cell_setup import load_cell_setup
from robot.charuco import CharucoBoard
from sygrid.errors import ConfigError
from sygrid.transforms import make_T

ROOT = Path(__file__).resolve().parents[1]
SIM_HOST = "127.0.0.92"


def _cell(tmp_path: Path, source: str, calibration: str, name: str) -> Path:
    """``launch/cells/`` ``source`` in ``tmp_path`` with its ``[calibration]`` section replaced by ``calibration``."""
    text = (ROOT / "launch" / "cells" / source).read_text().replace('host = "127.0.0.50"', f'host = "{SIM_HOST}"')
    text, n = re.subn(r"^\[calibration\]\n(?:(?!\[).*\n)*", f"[calibration]\n{calibration}\n\n", text, flags=re.M)
    assert n == 1, f"{source}: no [calibration] section"
    path = tmp_path / name
    path.write_text(text)
    return path


@pytest.mark.slow  # the emulator in real time: 8 poses at 0.5 rad/s
def test_the_simulated_cell_calibrates_its_camera_through_ur_rtde_and_a_cell_uses_the_file(tmp_path, capsys):
    pytest.importorskip("rtde_control")
    from launch.calibrate_hand_eye import keep_previous, run_hand_eye
    from launch.cli import main
    from launch.pick import camera_pose
    from launch.sim_calibration import true_T_base_camera
    from sim.cell_config import CellConfig

    cell = _cell(tmp_path, "sim.toml", 'source = "file"\nfile = "T_base_camera.json"', "sim.toml")
    assert main(["calibrate", "hand-eye", "--config", str(cell), "--poses", "8", "--speed", "1.0"]) == 0
    printed = capsys.readouterr().out
    assert "8 poses used (0 skipped)" in printed and f"wrote {tmp_path / 'T_base_camera.json'}" in printed
    error_mm, error_deg = (float(v) for v in re.search(r"true pose: ([\d.]+) mm, ([\d.]+) deg", printed).groups())
    assert error_mm < 1.0 and error_deg < 0.1  # exact flange poses; the error is the board's detection
    calibration = load_calibration(tmp_path / "T_base_camera.json")
    assert calibration.n_poses == 8 and calibration.reprojection_rms_px < 0.5
    assert calibration.board == CharucoBoard()
    # The cell file that names it runs with it (as a hardware cell's does).
    T, info = camera_pose(load_cell_setup(cell))
    np.testing.assert_array_equal(T, calibration.T_base_camera)
    assert info == {"source": "file", "file": str(tmp_path / "T_base_camera.json")}
    assert np.linalg.norm(T[:3, 3] - true_T_base_camera(CellConfig())[:3, 3]) < 1e-3
    # A calibration the file held is kept beside it, with how far the new one moved the camera (unreadable: kept too).
    out = tmp_path / "T_base_camera.json"
    moved = replace(calibration, T_base_camera=calibration.T_base_camera @ make_T(t=(0.0, 0.002, 0.0)))
    backup, change = keep_previous(out, moved)
    assert backup == tmp_path / "T_base_camera.previous.json" and backup.read_bytes() == out.read_bytes()
    assert change == pytest.approx((2.0, 0.0), abs=1e-3)  # arccos near 1 has ~1e-6 degrees of rounding
    out.write_text("{not json")
    assert keep_previous(out, moved) == (backup, None) and backup.read_text() == "{not json"
    assert keep_previous(tmp_path / "none.json", moved) == (None, None)
    # Too few poses for a calibration is refused before anything starts.
    with pytest.raises(ConfigError, match=r"--poses >= 6"):
        run_hand_eye(load_cell_setup(cell), tmp_path / "x.json", 4, 0, 0.5)


def test_the_board_and_its_mount_come_from_the_cell_file_with_errors_naming_the_field(tmp_path):
    mount = "[[1, 0, 0, -0.105], [0, -1, 0, 0.075], [0, 0, -1, 0.17], [0, 0, 0, 1]]"
    cell = _cell(
        tmp_path, "ur5e_realsense.toml",
        'source = "file"\nfile = "cam.json"\n'
        'board = { squares_x = 9, squares_y = 6, square_m = 0.025, marker_m = 0.018, dictionary = "DICT_5X5_100" }\n'
        f"T_flange_board_guess = {mount}", "cell.toml",
    )  # fmt: skip
    setup = load_cell_setup(cell, load_gripper_calibration=False)
    assert setup.hand_eye_board() == CharucoBoard(9, 6, 0.025, 0.018, "DICT_5X5_100")
    np.testing.assert_array_equal(setup.flange_board_guess()[:3, 3], [-0.105, 0.075, 0.17])

    bare = load_cell_setup(_cell(tmp_path, "ur5e_realsense.toml", 'source = "file"\nfile = "cam.json"', "bare.toml"))
    assert bare.hand_eye_board() == CharucoBoard()  # the default board
    with pytest.raises(ConfigError, match=r"bare\.toml: \[calibration\] T_flange_board_guess is not set"):
        bare.flange_board_guess()
    scaled = mount.replace("[1, 0", "[2, 0")  # not a rotation
    skewed_section = f'source = "file"\nfile = "c.json"\nT_flange_board_guess = {scaled}'
    skewed = _cell(tmp_path, "ur5e_realsense.toml", skewed_section, "skewed.toml")
    with pytest.raises(ConfigError, match=r"skewed\.toml: \[calibration\] T_flange_board_guess: expected a rigid 4x4"):
        load_cell_setup(skewed).flange_board_guess()
    odd_board = 'source = "file"\nfile = "c.json"\nboard = { squares_x = "7" }'
    odd = _cell(tmp_path, "ur5e_realsense.toml", odd_board, "o.toml")
    with pytest.raises(ConfigError, match=r"o\.toml: \[calibration\] board"):
        load_cell_setup(odd).hand_eye_board()


def test_the_printable_board_is_the_cell_files_board_at_its_physical_size(tmp_path, capsys):
    import cv2

    from launch.cli import main
    from robot.charuco import BoardDetector
    from sygrid.camera import CameraIntrinsics

    board = "board = { squares_x = 6, squares_y = 4, square_m = 0.04, marker_m = 0.03 }"  # the default's dictionary
    section = f'source = "file"\nfile = "c.json"\n{board}'
    cell = _cell(tmp_path, "ur5e_oak.toml", section, "cell.toml")
    assert main(["calibrate", "board", "--config", str(cell), "--out", str(tmp_path / "board.png")]) == 0
    assert "6 x 4 squares of 40 mm" in capsys.readouterr().out
    image = cv2.imread(str(tmp_path / "board.png"))
    dpi = 300 / 0.0254  # pixels per metre
    assert image.shape[1] == pytest.approx(dpi * 0.04 * 7, abs=3)  # 6 squares and two half-square margins
    h, w = image.shape[:2]
    rgb = cv2.resize(image[:, :, ::-1], (w // 4, h // 4), interpolation=cv2.INTER_AREA)
    K = CameraIntrinsics(fx=600.0, fy=600.0, cx=rgb.shape[1] / 2, cy=rgb.shape[0] / 2, width=rgb.shape[1],
                         height=rgb.shape[0])  # fmt: skip
    observation, why = BoardDetector(CharucoBoard(6, 4, 0.04, 0.03)).detect(rgb, K)
    assert observation is not None, why
    assert len(observation.corner_ids) == 5 * 3  # every inner corner
    assert main(["calibrate", "board", "--config", str(cell), "--out", str(tmp_path / "board.jpg")]) == 2
    assert re.search(r"board\.jpg: the board is written as \.pdf or \.png", capsys.readouterr().err)
