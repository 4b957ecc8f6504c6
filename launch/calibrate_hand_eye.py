"""``sygrid calibrate hand-eye --config CELL.toml``: the camera's pose in the robot's base frame by the ChArUco
procedure of ``robot.calibration``, run with the cell's own robot (ur_rtde) and camera.

Before it: the board is fixed to the flange (``[calibration] board``; ``T_flange_board_guess``: where it sits, to a
few centimetres and degrees) and the arm is jogged so that the board faces the camera near the middle of the image
(the start pose). Then:

1. a first frame: the board's pose in it, with the flange pose and the mount guess, gives the camera pose guess (no
   other input needed);
2. ``n_poses`` flange poses are drawn around it that show the whole board from varied angles
   (``robot.calibration.generate_pose_set``), each with an IK solution on the start pose's branch, the TCP inside
   the workspace box and the gripper and wrist clear of the bin's walls along the joint move from the start pose
   (``JointMoves``; ``URRobot`` checks every move again);
3. the arm visits them by joint moves at ``speed_rad_s``, and at each, once still, the board is detected; the
   pairs are solved (``robot.hand_eye``), the result written (``robot.calibration.save_calibration``; a calibration
   the file held is kept beside it, ``NAME.previous.json``, and how far the camera moved since is printed), and the
   arm goes back to the start pose. An error, SIGINT or SIGTERM stops the arm where it is (``URRobot.close``).

On a simulated cell the emulator is started (empty bin) with the board on a plate on the flange
(``launch.sim_calibration.board_plate_on_flange``, whose mount is known), the arm is first moved to hold the board
in front of the camera (``presenting_joints``, as an operator would jog it), and the result is compared with the
simulated camera's true pose: the procedure runs through the stock ur_rtde client against the emulator, as it would
against a controller.
"""

from __future__ import annotations

import contextlib
import logging
import shutil
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from perception.camera import Camera
from robot.calibration import calibrate, generate_pose_set, load_calibration, pose_error, save_calibration
from robot.cell_setup import CellSetup
from robot.charuco import BoardDetector, CharucoBoard
from robot.grasp_collision import CollisionChecker
from robot.hand_eye import CalibrationError, HandEyeCalibration
from robot.ur import URRobot
from robot.ur_errors import MotionRefusedError
from sygrid.camera import CameraIntrinsics
from sygrid.errors import ConfigError, SygridError
from sygrid.transforms import invert

log = logging.getLogger(__name__)

SETTLE_S = 0.5  # after a move: the arm rings down and the camera's next exposure starts after it


@dataclass(frozen=True, eq=False)
class HandEyeRun:
    """What ``run_hand_eye`` did: the calibration, where it was written, and (simulated cells) its error against
    the camera's true pose (mm, degrees)."""

    calibration: HandEyeCalibration
    path: Path
    error_mm: float | None = None
    error_deg: float | None = None
    backup: Path | None = None  # the calibration ``path`` held before, kept
    change: tuple[float, float] | None = None  # how far this result lies from that one (mm, degrees)


class JointMoves:
    """``robot.calibration.FlangeRobot`` over a ``URRobot``: a joint move to the flange pose's IK solution nearest
    ``q_seed`` (the start pose: every pose on its branch), then ``settle_s`` for the arm to come to rest.

    A pose is drawn only where its joints are reachable, the TCP stays in the workspace box and the gripper and the
    wrist links keep the planner's transit clearance from the bin's walls along the joint move from the start pose
    (``robot.grasp_collision``; the board sits past the fingers, away from the bin); a move between two poses whose
    straight joint line does not keep it goes back through the start pose."""

    def __init__(
        self,
        robot: URRobot,
        q_seed: np.ndarray,
        speed_rad_s: float,
        collision: CollisionChecker,
        settle_s: float = SETTLE_S,
    ) -> None:
        self.robot, self.q_seed = robot, np.asarray(q_seed, dtype=float)
        self.speed_rad_s, self.settle_s = speed_rad_s, settle_s
        self.collision = collision
        self._boxes = collision.config.gripper.boxes(0.0)  # the gripper closed (as it is while calibrating)

    def clear(self, q_from: np.ndarray, q_to: np.ndarray) -> bool:
        """Whether the joint move keeps the gripper and the wrist off the bin's walls and the elbow up."""
        gap = self.collision.transit_gap_m(q_from, q_to, self._boxes)
        return gap >= (self.collision.config.transit_clearance_m or 0.0) and self.collision.elbow_clear(q_from, q_to)

    def joints_for(self, T_base_flange: np.ndarray) -> np.ndarray | None:
        """The joints that put the flange at ``T_base_flange``; None where the class docstring's checks fail."""
        T_base_tcp = T_base_flange @ self.robot.T_flange_tcp
        q = self.robot.ik(T_base_tcp, self.q_seed)
        if q is None:
            return None
        try:
            self.robot.check_joint_path(self.q_seed, q)  # the path and where it ends
        except MotionRefusedError:  # outside the workspace box or the joint limits: not a pose to draw
            return None
        return q if self.clear(self.q_seed, q) else None

    def move_to(self, T_base_flange: np.ndarray) -> None:
        q = self.joints_for(T_base_flange)
        if q is None:
            raise CalibrationError(f"the flange pose {np.round(T_base_flange, 4).tolist()} became unreachable")
        if not self.clear(self.robot.q(), q):
            self._move(self.q_seed)
        self._move(q)
        time.sleep(self.settle_s)

    def _move(self, q: np.ndarray) -> None:
        if not self.robot.move_j(q, self.speed_rad_s).reached:
            raise CalibrationError(f"the joint move to {np.round(q, 3).tolist()} was stopped")

    def T_base_flange(self) -> np.ndarray:
        return self.robot.T_base_flange()


def camera_guess(
    robot: URRobot, frame_rgb: np.ndarray, intrinsics: CameraIntrinsics, board: CharucoBoard, T_flange_board: np.ndarray
) -> np.ndarray:
    """``T_base_camera`` from one view of the board at the current flange pose and the mount guess; a
    CalibrationError saying what to do when the camera does not see the board."""
    observation, why = BoardDetector(board).detect(frame_rgb, intrinsics)
    if observation is None:
        raise CalibrationError(
            f"the camera does not see the board at the start pose ({why}): jog the arm so that the board faces the "
            "camera near the middle of the image, and check [calibration] board against the printed one"
        )
    return robot.T_base_flange() @ T_flange_board @ invert(observation.T_camera_board)


def run_hand_eye(
    setup: CellSetup, out: Path, n_poses: int, seed: int, speed_rad_s: float, settle_s: float = SETTLE_S
) -> HandEyeRun:
    """The procedure of the module docstring on the cell ``setup``; writes ``out`` and returns what it did."""
    if speed_rad_s <= 0 or n_poses < 6:
        raise ConfigError(f"need --speed > 0 and --poses >= 6, got {speed_rad_s} and {n_poses}")
    board = setup.hand_eye_board()
    rng = np.random.default_rng(seed)
    with contextlib.ExitStack() as stack:
        T_true = None
        if setup.is_sim:
            camera, robot, T_flange_board, T_true = _open_sim_cell(stack, setup, board, seed, speed_rad_s)
        else:
            T_flange_board = setup.flange_board_guess()
            camera = stack.enter_context(setup.open_camera())
            robot = stack.enter_context(URRobot(setup.robot))
        q_start = robot.q()
        arm = JointMoves(robot, q_start, speed_rad_s, CollisionChecker(setup.planner_config()), settle_s)
        first = camera.capture()
        T_guess = camera_guess(robot, first.rgb, first.intrinsics, board, T_flange_board)
        poses = generate_pose_set(
            board, T_guess, first.intrinsics, T_flange_board, n_poses, rng,
            reachable=lambda T: arm.joints_for(T) is not None,
        )  # fmt: skip
        print(f"visiting {len(poses)} poses at {speed_rad_s} rad/s; keep clear of the arm ...")
        # an error or a stop signal leaves through the ExitStack: URRobot.close stops a motion in flight
        calibration = calibrate(arm, camera.capture, board, poses)
        robot.move_j(q_start, speed_rad_s)  # back where the operator left it
    backup, change = keep_previous(out, calibration)
    path = save_calibration(out, calibration)
    error = (None, None) if T_true is None else pose_error(calibration.T_base_camera, T_true)
    return HandEyeRun(calibration, path, *error, backup=backup, change=change)


def _open_sim_cell(
    stack: contextlib.ExitStack, setup: CellSetup, board: CharucoBoard, seed: int, speed_rad_s: float
) -> tuple[Camera, URRobot, np.ndarray, np.ndarray]:
    """The emulator (empty bin, the board's plate on the flange), its camera and the robot, with the arm holding the
    board in front of the camera; returns them with the board's mount and the camera's true pose."""
    from launch.sim_calibration import board_plate_on_flange, presenting_joints, true_T_base_camera
    from sim.cell_config import CellConfig
    from sim.controller import ControllerProcess
    from sim.emulator_camera import EmulatorCamera
    from sygrid.sensor import sensor_preset, sensor_rng

    if board != CharucoBoard():
        raise ConfigError(f"{setup.path}: [calibration] board: the simulated cell's plate carries the default board")
    plate, T_flange_board = board_plate_on_flange(board)
    cell = replace(CellConfig(), calibration_board=plate)
    T_true = true_T_base_camera(cell)
    print(f"starting the emulator on {setup.data.sim.host} (empty bin, the board on the flange) ...")
    process = stack.enter_context(
        ControllerProcess(setup.data.sim.host, backend="mujoco", backend_kwargs={"config": cell},
                          start_timeout_s=120.0, unlock_delay_s=setup.data.sim.unlock_delay_s)
    )  # fmt: skip
    # nothing here is time-critical: a loaded machine may take long for the first frame
    sensor = sensor_preset(setup.data.camera.sensor)
    camera = EmulatorCamera(process, timeout_s=60.0, sensor=sensor, rng=sensor_rng(seed, 7))
    robot = stack.enter_context(URRobot(setup.robot))
    robot.move_j(presenting_joints(T_true, T_flange_board, board), speed_rad_s)  # where an operator jogs it
    return camera, robot, T_flange_board, T_true


def keep_previous(out: Path, calibration: HandEyeCalibration) -> tuple[Path | None, tuple[float, float] | None]:
    """Before ``out`` is replaced: a copy of it beside it (``NAME.previous.json``) and how far the new camera pose
    lies from the one it held (mm, degrees; None when it does not load). (None, None) when there is no ``out``."""
    if not out.is_file():
        return None, None
    backup = out.with_name(f"{out.stem}.previous{out.suffix}")
    shutil.copy2(out, backup)
    try:
        previous = load_calibration(out)
    except SygridError as err:
        log.warning("%s: the previous calibration does not load (%s); kept as %s", out, err, backup)
        return backup, None
    return backup, pose_error(calibration.T_base_camera, previous.T_base_camera)


def write_board(board: CharucoBoard, out: Path, dpi: int = 300) -> tuple[Path, tuple[float, float]]:
    """The board to print at 100 % scale: a PDF or PNG (by ``out``'s suffix) whose page is the board with a white
    margin of half a square, at its physical size (the PNG carries ``dpi``). Returns the file and the page size
    (width, height) in metres. Written by matplotlib at the page size, so that a printer's "actual size" is right."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if out.suffix.lower() not in (".pdf", ".png"):
        raise ConfigError(f"{out}: the board is written as .pdf or .png")
    px_per_square = max(20, round(board.square_m / 0.0254 * dpi))
    image, size_m, _ = board.plate(px_per_square, margin_squares=0.5)
    fig = plt.figure(figsize=(size_m[0] / 0.0254, size_m[1] / 0.0254))
    ax = fig.add_axes((0.0, 0.0, 1.0, 1.0))
    ax.imshow(image, interpolation="nearest")
    ax.set_axis_off()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=dpi)
    plt.close(fig)
    return out, size_m


def summary(run: HandEyeRun) -> str:
    """The lines the command prints: residuals, the mount found, the file (and the error in a simulated cell)."""
    c = run.calibration
    t = c.T_base_camera[:3, 3]
    lines = [
        f"{c.n_poses} poses used ({len(c.skipped)} skipped), method {c.method}: corner reprojection RMS "
        f"{c.reprojection_rms_px:.3f} px, worst pose {max(c.per_pose_reprojection_rms_px):.3f} px; the mount per "
        f"pose within {max(c.flange_board_spread_mm):.2f} mm / {max(c.flange_board_spread_deg):.3f} deg",
        f"camera at ({t[0]:.4f}, {t[1]:.4f}, {t[2]:.4f}) m in the base frame",
    ]
    if run.error_mm is not None:
        lines.append(f"against the simulated camera's true pose: {run.error_mm:.2f} mm, {run.error_deg:.3f} deg")
    if run.backup is not None:
        moved = "" if run.change is None else f": the camera moved {run.change[0]:.2f} mm, {run.change[1]:.3f} deg"
        lines.append(f"the previous calibration is kept as {run.backup}{moved}")
    lines.append(f"wrote {run.path}")
    return "\n".join(lines)
