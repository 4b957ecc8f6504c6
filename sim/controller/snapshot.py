"""Turns the controller's state after one tick into the immutable ``StateSnapshot`` every RTDE output reads.

TCP poses come from the shared forward kinematics with the active TCP; TCP speeds are finite differences over one
tick (zero when the joints are at rest). ``actual_TCP_force`` is the backend's measured external wrench on the tool
(base frame, torque about the TCP). ``pose_from_T`` is the 500 Hz version of the shared ``T_to_pose``.
"""

from __future__ import annotations

import math

import numpy as np

from sim.controller.arm import ArmController
from sim.controller.backend import ArmSample
from sim.controller.state import (
    ROBOT_MODE_POWER_OFF,
    ROBOT_STATUS_POWER_ON,
    ROBOT_STATUS_PROGRAM_RUNNING,
    RUNTIME_PLAYING,
    SAFETY_BIT_NORMAL,
    SAFETY_BIT_PROTECTIVE_STOP,
    SAFETY_MODE_NORMAL,
    SAFETY_MODE_PROTECTIVE_STOP,
    IoState,
    Registers,
    StateSnapshot,
)
from sygrid.robots.kinematics import forward_kinematics

TICK_S = 0.002
_ZERO_TWIST = (0.0,) * 6


class SnapshotBuilder:
    """Keeps last tick's TCP poses for the speed finite differences."""

    def __init__(self, q0: np.ndarray) -> None:
        T0 = forward_kinematics(q0)
        self._prev_T = (T0, T0)

    def build(
        self,
        k: int,
        a: ArmSample,
        arm: ArmController,
        io: IoState,
        regs: Registers,
        *,
        runtime_state: int,
        robot_mode: int,
        protective_stopped: bool,
        execution_time_s: float,
        protective_stop_force_n: float,
        tcp_wrench: np.ndarray | None = None,
    ) -> StateSnapshot:
        """The snapshot of tick ``k`` (timestamp ``k * 2 ms``) from the backend sample ``a`` and the controller."""
        tcp = arm.T_flange_tcp
        T_target = forward_kinematics(arm.target_q, tcp)
        same = np.array_equal(a.q, arm.target_q)
        T_actual = T_target if same else forward_kinematics(a.q, tcp)
        target_speed = _twist(self._prev_T[1], T_target) if np.any(arm.target_qd) else _ZERO_TWIST
        actual_speed = target_speed if same else (_twist(self._prev_T[0], T_actual) if np.any(a.qd) else _ZERO_TWIST)
        self._prev_T = (T_actual, T_target)
        target_pose = pose_from_T(T_target)
        running = runtime_state == RUNTIME_PLAYING
        return StateSnapshot(
            timestamp_s=k * TICK_S,
            target_q=tuple(arm.target_q.tolist()),
            target_qd=tuple(arm.target_qd.tolist()),
            target_qdd=tuple(arm.target_qdd.tolist()),
            actual_q=tuple(a.q.tolist()),
            actual_qd=tuple(a.qd.tolist()),
            joint_torque=tuple(a.torque.tolist()),
            actual_tcp_pose=target_pose if same else pose_from_T(T_actual),
            actual_tcp_speed=actual_speed,
            target_tcp_pose=target_pose,
            target_tcp_speed=target_speed,
            tcp_force=_ZERO_TWIST if tcp_wrench is None else tuple(tcp_wrench.tolist()),
            robot_mode=robot_mode,
            safety_mode=SAFETY_MODE_PROTECTIVE_STOP if protective_stopped else SAFETY_MODE_NORMAL,
            safety_status_bits=SAFETY_BIT_PROTECTIVE_STOP if protective_stopped else SAFETY_BIT_NORMAL,
            robot_status_bits=(ROBOT_STATUS_POWER_ON if robot_mode != ROBOT_MODE_POWER_OFF else 0)
            | (ROBOT_STATUS_PROGRAM_RUNNING if running else 0),
            runtime_state=runtime_state,
            digital_output_bits=io.digital_output_bits,
            analog_out=(io.analog_out[0], io.analog_out[1]),
            analog_io_types=io.analog_out_voltage_mask << 2,
            speed_scaling=io.speed_slider,
            target_speed_fraction=io.speed_slider,
            payload_mass_kg=arm.payload_mass_kg,
            payload_cog_m=tuple(arm.payload_cog_m.tolist()),
            payload_inertia=tuple(arm.payload_inertia.tolist()),
            input_int=tuple(regs.input_int),
            input_double=tuple(regs.input_double),
            input_bits=regs.input_bits,
            output_int=tuple(regs.output_int),
            output_double=tuple(regs.output_double),
            output_bits=regs.output_bits,
            execution_time_s=execution_time_s,
            collision_ratio=a.collision_force_n / protective_stop_force_n,
        )


def pose_from_T(T: np.ndarray) -> tuple[float, ...]:
    """``sygrid.robots.kinematics.T_to_pose`` for the 500 Hz snapshot: scipy's algorithm (Shepperd quaternion,
    w >= 0) and the shared canonical sign at pi, in plain floats; 30x faster for one matrix."""
    m = T[:3, :3].tolist()
    trace = m[0][0] + m[1][1] + m[2][2]
    decision = (m[0][0], m[1][1], m[2][2], trace)
    choice = max(range(4), key=decision.__getitem__)
    q = [0.0, 0.0, 0.0, 0.0]
    if choice != 3:
        i, j, k = choice, (choice + 1) % 3, (choice + 2) % 3
        q[i] = 1.0 - trace + 2.0 * m[i][i]
        q[j] = m[j][i] + m[i][j]
        q[k] = m[k][i] + m[i][k]
        q[3] = m[k][j] - m[j][k]
    else:
        q = [m[2][1] - m[1][2], m[0][2] - m[2][0], m[1][0] - m[0][1], 1.0 + trace]
    norm = math.sqrt(sum(c * c for c in q))
    if q[3] < 0:
        norm = -norm
    x, y, z, w = (c / norm for c in q)
    sin_half = math.sqrt(x * x + y * y + z * z)
    angle = 2.0 * math.atan2(sin_half, w)
    scale = 2.0 + angle**2 / 12.0 + 7.0 * angle**4 / 2880.0 if angle <= 1e-3 else angle / math.sin(angle / 2.0)
    r = [scale * x, scale * y, scale * z]
    if angle > math.pi - 1e-9:  # r and -r are the same rotation: the shared T_to_pose's canonical sign
        first = next((c for c in r if abs(c) > 1e-9 * max(angle, 1.0)), 0.0)
        if first < 0:
            r = [-c for c in r]
    return (float(T[0, 3]), float(T[1, 3]), float(T[2, 3]), r[0], r[1], r[2])


def _twist(T_prev: np.ndarray, T: np.ndarray) -> tuple[float, ...]:
    """Finite-difference TCP speed ``[vx, vy, vz, wx, wy, wz]`` over one tick, base frame."""
    v = (T[:3, 3] - T_prev[:3, 3]) / TICK_S
    R = T[:3, :3] @ T_prev[:3, :3].T
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / (2.0 * TICK_S)  # small-angle
    return (*v.tolist(), *w.tolist())
