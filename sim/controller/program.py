"""The uploaded ``rtde_control`` program, run natively: the script's main loop (protocol note section 1.6) as a
state machine stepped once per 2 ms controller cycle, with its commands implemented on ``ArmController``.

Per cycle: while a synchronous command (a blocking move or stop) runs, the loop waits for it and then writes
"done" (2). Otherwise it reads ``cmd`` from input_int_register_0 (+offset): realtime codes run every cycle and write
"ready" (1); 0 clears ``executing`` and writes ready; any other code runs once, then writes done. Code 255 ends the
program without done. All register indices are relative to the program's register offset (0 or 24).

Failure semantics:
- A motion the robot cannot execute (IK fails, target outside limits) halts the program (runtime_state STOPPED),
  as the URScript runtime error does on a real robot; the client's wait sees "script is not running" -> False.
- An unsupported non-realtime code writes zero results, withholds done and pauses the program until the client's
  clear arrives (at most ``fault_hold_s``); the client's wait sees the pause and returns False, and the next command
  works. Unsupported realtime codes cannot fail on the client side (it never waits for them): they are logged.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Protocol

import numpy as np

from sim.controller.arm import ArmController, Motion, within_joint_limits
from sim.controller.commands import REALTIME_CODES, STOP_SCRIPT, command_name
from sim.controller.contact_detection import ContactDetection, move_back_to, stop_at_contact
from sim.controller.errors import MotionError
from sim.controller.ik_query import solve_ik
from sim.controller.state import Registers
from sygrid.robots.kinematics import T_to_pose, forward_kinematics, pose_to_T

log = logging.getLogger(__name__)

READY, DONE = 1, 2
_PROGRESS_FINISHED = -1


class ProgramHost(Protocol):
    """What the program needs from the controller around it."""

    def actual_q(self) -> np.ndarray: ...
    def actual_torque(self) -> np.ndarray: ...
    def q_history(self, steps: int) -> np.ndarray: ...
    def tool_contact(self, direction: np.ndarray, max_steps: int | None = None) -> int: ...
    def trigger_protective_stop(self, reason: str) -> None: ...
    def set_watchdog(self, min_frequency_hz: float) -> None: ...
    def end_program(self, reason: str, error: bool) -> None: ...
    def fault_command(self, code: int) -> None: ...


class ControlProgram:
    """One run of the rtde_control script."""

    name = "rtde_control"

    def __init__(self, regs: Registers, arm: ArmController, host: ProgramHost, register_offset: int) -> None:
        self.regs, self.arm, self.host, self.offset = regs, arm, host, register_offset
        self.executing = False
        self.started = False
        self.aborted = False
        self._blocking: Callable[[], bool] | None = None  # returns True when the synchronous command is finished
        self._async_motion: Motion | None = None
        self._stop_thread_motion: Motion | None = None
        self._stop_type = 0  # 0 = stopj, 1 = stopl; global in the script, set to 1 by every async stop
        self._speed_type = 0  # 0 = speedl, 1 = speedj
        self._async_wr_count = 0
        self._async_op_id = 0
        self._unsupported_rt_logged: int | None = None
        self._contact = ContactDetection(arm, host)
        self._handlers: dict[int, Callable[[], bool | None]] = {
            1: self._movej,
            2: self._movej_ik,
            3: self._movel,
            4: self._movel_fk,
            6: self._force_mode,
            7: self._force_mode_stop,
            8: lambda: None,  # zeroFtSensor: there is no force sensor to zero
            9: self._speedj,
            10: self._speedl,
            11: self._servoj,
            15: self._speed_stop,
            16: self._servo_stop,
            17: self._set_payload,
            20: lambda: self.arm.set_force_damping(self.in_double(0)),
            21: lambda: self.arm.set_force_gain_scaling(self.in_double(0)),
            24: self._servol,
            25: self._tool_contact,
            26: self._get_step_time,
            27: self._q_history,
            28: self._target_waypoint,
            29: self._set_tcp,
            30: self._ik_args,
            31: self._protective_stop,
            33: self._stop,
            34: self._stop,
            35: self._set_watchdog,
            36: self._pose_within_limits,
            37: self._joints_within_limits,
            38: self._joint_torques,
            39: self._pose_trans,
            40: self._tcp_offset,
            43: self._fk_default,
            44: self._fk_args,
            46: self._ik_default,
            47: self._is_steady,
            51: self._move_until_contact,
            55: lambda: None,  # setExternalForceTorque: the wrench arrives as an RTDE input and is stored there
            58: self._flange_pose,
            59: lambda: None,  # setGravity: the kinematic and MuJoCo arms keep their own gravity
            60: self._ik_has_solution,
            61: self._ik_has_solution_args,
            62: lambda: self._contact.start(self.in_vector(0)),
            63: lambda: self._answer_contact(self._contact.stop),
            64: lambda: self._answer_contact(lambda: self._contact.step_back),
            65: self._set_target_payload,
        }

    # --- registers (relative to the offset) ----------------------------------------------------------------
    def in_int(self, i: int) -> int:
        return self.regs.input_int[i + self.offset]

    def in_double(self, i: int) -> float:
        return self.regs.input_double[i + self.offset]

    def in_vector(self, first: int, n: int = 6) -> np.ndarray:
        return np.array(self.regs.input_double[first + self.offset : first + self.offset + n])

    def out_int(self, i: int, value: int) -> None:
        self.regs.output_int[i + self.offset] = int(value)

    def out_vector(self, values: np.ndarray, first: int = 0) -> None:
        for k, v in enumerate(values):
            self.regs.output_double[first + k + self.offset] = float(v)

    # --- the main loop -------------------------------------------------------------------------------------
    def tick(self) -> None:
        if not self.started:
            self.started = True
            self._write_async_progress(_PROGRESS_FINISHED)
            self.out_int(0, READY)
        self._track_async()
        self._contact.step(self._stop_async_move)
        if self._blocking is not None:
            if not self._blocking():
                return
            self._blocking = None
            self.out_int(0, DONE)
        cmd = self.in_int(0)
        if cmd in REALTIME_CODES:
            self._run(cmd)
            self.out_int(0, READY)
        elif cmd == 0:
            self.executing = False
            self._unsupported_rt_logged = None
            self.out_int(0, READY)
        elif not self.executing:
            self.executing = True
            if cmd == STOP_SCRIPT:
                log.info("rtde_control: stopScript received; program ends")
                self.host.end_program("stopScript (code 255)", error=False)
                return
            if self._run(cmd) and self._blocking is None and not self.aborted:
                self.out_int(0, DONE)

    def abort(self) -> None:
        """The program is stopped or paused from outside: drop the synchronous command without signalling done."""
        self.aborted = True
        self._blocking = None
        self.arm.end_force_mode()
        self.arm.contact_watch = False
        self._contact.abort()
        if self._async_motion is not None or self._stop_thread_motion is not None:
            self._async_motion = self._stop_thread_motion = None
            self._write_async_progress(_PROGRESS_FINISHED)

    def _run(self, cmd: int) -> bool:
        """Runs one command; False when it failed (the host has been told)."""
        handler = self._handlers.get(cmd)
        if handler is None:
            self._unsupported(cmd)
            return False
        try:
            handler()
        except MotionError as exc:
            log.error("rtde_control: %s failed: %s; program halted (a URScript runtime error)", command_name(cmd), exc)
            self.host.end_program(f"{command_name(cmd)} failed: {exc}", error=True)
            return False
        return True

    def _unsupported(self, cmd: int) -> None:
        if cmd in REALTIME_CODES:
            if self._unsupported_rt_logged != cmd:
                self._unsupported_rt_logged = cmd
                log.error(
                    "rtde_control: command %d %s is not supported by the emulator; ignored (the client does "
                    "not wait for realtime commands, so it cannot see a failure)",
                    cmd,
                    command_name(cmd),
                )
            return
        log.error(
            "rtde_control: command %d %s is not supported by the emulator; the call fails", cmd, command_name(cmd)
        )
        self.out_int(1, 0)
        self.out_vector(np.zeros(6))
        self.host.fault_command(cmd)

    # --- async progress word (output_int_register_2) -------------------------------------------------------
    def _write_async_progress(self, value: int) -> None:
        self._async_wr_count = (self._async_wr_count + 1) % 128
        if value == 0:
            self._async_op_id = (self._async_op_id + 1) % 128
        word = self._async_wr_count * 65536 + self._async_op_id * 16777216
        if value >= 0:
            word += min(value, 32767) + 32768
        self.out_int(2, word)

    def _track_async(self) -> None:
        if self._async_motion is not None and self.arm.motion is not self._async_motion:
            self._async_motion = None
            self._write_async_progress(_PROGRESS_FINISHED)
        if self._stop_thread_motion is not None and self.arm.motion is None:
            self._stop_thread_motion = None
            self._write_async_progress(_PROGRESS_FINISHED)

    def _stop_async_move(self) -> None:
        if self._async_motion is not None:
            self._async_motion = None
            self._write_async_progress(_PROGRESS_FINISHED)

    # --- moves ---------------------------------------------------------------------------------------------
    def _start_move(self, start: Callable[[], Motion]) -> None:
        asynchronous = self.in_int(1) == 1
        self._stop_async_move()
        motion = start()
        if asynchronous:
            self._async_motion = motion
            self._write_async_progress(0)
        else:
            self._blocking = lambda: self.arm.motion is not motion

    def _ik(self, pose: np.ndarray, q_near: np.ndarray | None = None) -> np.ndarray:
        q = solve_ik(pose_to_T(pose), self.host.actual_q() if q_near is None else q_near, self.arm.T_flange_tcp)
        if q is None:
            raise MotionError(f"get_inverse_kin: no solution for pose {np.round(pose, 5).tolist()}")
        return q

    def _movej(self) -> None:
        q, v, a = self.in_vector(0), self.in_double(6), self.in_double(7)
        self._start_move(lambda: self.arm.movej(q, v, a))

    def _movej_ik(self) -> None:
        q, v, a = self._ik(self.in_vector(0)), self.in_double(6), self.in_double(7)
        self._start_move(lambda: self.arm.movej(q, v, a))

    def _movel(self) -> None:
        pose, v, a = self.in_vector(0), self.in_double(6), self.in_double(7)
        self._start_move(lambda: self.arm.movel(pose, v, a))

    def _movel_fk(self) -> None:
        pose = T_to_pose(forward_kinematics(self.in_vector(0), self.arm.T_flange_tcp))
        v, a = self.in_double(6), self.in_double(7)
        self._start_move(lambda: self.arm.movel(pose, v, a))

    # --- force-limited motion -------------------------------------------------------------------------------
    def _force_mode(self) -> None:
        """forceMode (6, realtime): d0-5 task frame, d6-11 wrench, d12-17 limits, i1 type, i2-7 selection."""
        selection = [self.in_int(k) for k in range(2, 8)]
        self.arm.force_mode(self.in_vector(0), selection, self.in_vector(6), self.in_int(1), self.in_vector(12))

    def _force_mode_stop(self) -> None:
        """forceModeStop (7): end_force_mode(), then stopl(10), waited for."""
        self.arm.end_force_mode()
        self.arm.stop(10.0, linear=True)
        self._blocking = lambda: self.arm.motion is None

    def _tool_contact(self) -> None:
        """toolContact (25, realtime): i1 the steps back to the contact's start (0: none), d0 the step time."""
        self.out_int(1, self.host.tool_contact(self.in_vector(0)))
        self.regs.output_double[self.offset] = 0.002

    def _move_until_contact(self) -> None:
        """moveUntilContact (51): d0-5 tool speed, d6-11 contact direction, d12 acceleration. As the script: speedl
        until tool_contact sees a contact, then stopl(3) and movel back to where the contact began; blocking."""
        xd, direction, accel = self.in_vector(0), self.in_vector(6), self.in_double(12)
        self._stop_async_move()
        state: dict[str, object] = {"phase": "moving", "ticks": 0}
        self.arm.contact_watch = True

        def step() -> bool:
            phase = state["phase"]
            if phase == "moving":
                # a contact found at once (the tool already touching) began no earlier than this command
                steps = self.host.tool_contact(direction, max_steps=state["ticks"])
                state["ticks"] = int(state["ticks"]) + 1
                if steps <= 0:
                    self.arm.speedl(xd, accel)
                    return False
                state["q"] = self.host.q_history(steps)
                stop_at_contact(self.arm)
                state["phase"] = "stopping"
            if state["phase"] == "stopping":
                if self.arm.motion is not None:
                    return False
                try:
                    move_back_to(self.arm, state["q"])
                except MotionError as exc:
                    self.host.end_program(f"moveUntilContact failed: {exc}", error=True)
                    return False
                state["phase"] = "returning"
                return False
            return self.arm.motion is None

        step()
        self._blocking = step

    def _answer_contact(self, answer: Callable[[], int]) -> None:
        """readContactDetection (64) / stopContactDetection (63): i1 the steps back to the contact's start (0:
        none); while a contact is being stopped and moved back from, the script's main loop answers afterwards."""

        def done() -> bool:
            if self._contact.handling:
                return False
            self.out_int(1, answer())
            return True

        if not done():
            self._blocking = done

    # --- stops ---------------------------------------------------------------------------------------------
    def _stop(self) -> None:
        """stopL (33) / stopJ (34), as exec_stopl_stopj: async stops run in a 'stop thread' and always use stopl."""
        decel, asynchronous = self.in_double(0), self.in_int(1) == 1
        log.info(
            "rtde_control: %s (decel %g) received %s", command_name(self.in_int(0)), decel,
            "during a motion" if self.arm.motion is not None else "at rest",
        )  # fmt: skip
        if self._stop_thread_motion is not None:
            self._stop_thread_motion = None
            self._write_async_progress(_PROGRESS_FINISHED)
        else:
            self._stop_async_move()
        if asynchronous:
            self._stop_type = 1
            self._write_async_progress(0)
            self._stop_thread_motion = self.arm.stop(decel, linear=True)
            if self._stop_thread_motion is None:
                self._write_async_progress(_PROGRESS_FINISHED)
        else:
            self.arm.stop(decel, linear=self._stop_type == 1)
            self._blocking = lambda: self.arm.motion is None

    def _speedj(self) -> None:
        self._speed_type = 1
        self.arm.speedj(self.in_vector(0), self.in_double(6))

    def _speedl(self) -> None:
        self._speed_type = 0
        self.arm.speedl(self.in_vector(0), self.in_double(6))

    def _servoj(self) -> None:
        self.arm.servo(self.in_vector(0), self.in_double(9))

    def _servol(self) -> None:
        self.arm.servo(self._ik(self.in_vector(0), self.arm.target_q), self.in_double(9))

    def _speed_stop(self) -> None:
        self.arm.stop(self.in_double(0), linear=self._speed_type == 0)
        self._blocking = lambda: self.arm.motion is None

    def _servo_stop(self) -> None:
        self.arm.stop(self.in_double(0), linear=True)
        self._blocking = lambda: self.arm.motion is None

    def _protective_stop(self) -> None:
        self.host.trigger_protective_stop("triggerProtectiveStop (command 31)")

    def _set_watchdog(self) -> None:
        self.host.set_watchdog(self.in_double(0))

    # --- settings and queries ------------------------------------------------------------------------------
    def _set_tcp(self) -> None:
        self.arm.set_tcp(self.in_vector(0))

    def _set_payload(self) -> None:
        cog = self.in_vector(1, 3)
        self.arm.set_payload(self.in_double(0), None if not np.any(cog) else cog)

    def _set_target_payload(self) -> None:
        cog = self.in_vector(1, 3)
        self.arm.set_payload(self.in_double(0), None if not np.any(cog) else cog, self.in_vector(4))

    def _tcp_offset(self) -> None:
        self.out_vector(self.arm.tcp_pose)

    def _fk_default(self) -> None:
        self.out_vector(T_to_pose(forward_kinematics(self.host.actual_q(), self.arm.T_flange_tcp)))

    def _fk_args(self) -> None:
        # The TCP comes from d6..d11 even when the client's recipe 6 did not write them (stale registers).
        q, tcp = self.in_vector(0), self.in_vector(6)
        self.out_vector(T_to_pose(forward_kinematics(q, pose_to_T(tcp))))

    def _ik_default(self) -> None:
        self.out_vector(self._ik(self.in_vector(0)))

    def _ik_with_qnear_and_tolerances(self) -> np.ndarray | None:
        """get_inverse_kin(x, qnear, maxPositionError, maxOrientationError): d0-5 x, d6-11 qnear, d12, d13."""
        x, q_near = pose_to_T(self.in_vector(0)), self.in_vector(6)
        return solve_ik(x, q_near, self.arm.T_flange_tcp, self.in_double(12), self.in_double(13))

    def _ik_args(self) -> None:
        q = self._ik_with_qnear_and_tolerances()
        if q is None:
            raise MotionError(
                f"get_inverse_kin: no solution for pose {np.round(self.in_vector(0), 5).tolist()} within "
                f"{self.in_double(12)} m / {self.in_double(13)} rad"
            )
        self.out_vector(q)

    def _ik_has_solution(self) -> None:
        q = solve_ik(pose_to_T(self.in_vector(0)), self.host.actual_q(), self.arm.T_flange_tcp)
        self.out_int(1, q is not None)

    def _ik_has_solution_args(self) -> None:
        self.out_int(1, self._ik_with_qnear_and_tolerances() is not None)

    def _is_steady(self) -> None:
        self.out_int(1, self.arm.is_steady)

    def _joint_torques(self) -> None:
        self.out_vector(self.host.actual_torque())

    def _flange_pose(self) -> None:
        self.out_vector(T_to_pose(forward_kinematics(self.host.actual_q())))

    def _get_step_time(self) -> None:
        self.regs.output_double[self.offset] = 0.002

    def _q_history(self) -> None:
        self.out_vector(self.host.q_history(self.in_int(1)))

    def _target_waypoint(self) -> None:
        self.out_vector(T_to_pose(forward_kinematics(self.arm.target_q, self.arm.T_flange_tcp)))

    def _pose_trans(self) -> None:
        self.out_vector(T_to_pose(pose_to_T(self.in_vector(0)) @ pose_to_T(self.in_vector(6))))

    def _pose_within_limits(self) -> None:
        q = solve_ik(pose_to_T(self.in_vector(0)), self.host.actual_q(), self.arm.T_flange_tcp)
        self.out_int(1, q is not None)

    def _joints_within_limits(self) -> None:
        self.out_int(1, within_joint_limits(self.in_vector(0)))
