"""Maps every RTDE output name to its value in a ``StateSnapshot``, and packs output recipes.

Values with no physical counterpart in the emulator are constants chosen to look like a healthy idle UR5e
(48 V supply, 30 degC joints, joint mode RUNNING); they are listed in ``_CONSTANTS``.
"""

from __future__ import annotations

import struct
from collections.abc import Callable

from sim.controller.rtde_names import N_REGISTERS, OUTPUT_TYPES, recipe_struct, type_width
from sim.controller.state import JOINT_MODE_RUNNING, StateSnapshot

Getter = Callable[[StateSnapshot], object]

_CONSTANTS: dict[str, object] = {
    "target_current": (0.0,) * 6,
    "actual_current": (0.0,) * 6,
    "actual_current_window": (0.0,) * 6,
    "joint_control_output": (0.0,) * 6,
    "joint_temperatures": (30.0,) * 6,
    "joint_mode": (JOINT_MODE_RUNNING,) * 6,
    "actual_tool_accelerometer": (0.0, 0.0, -9.81),
    "actual_momentum": 0.0,
    "actual_main_voltage": 48.0,
    "actual_robot_voltage": 48.0,
    "actual_robot_current": 0.5,
    "actual_joint_voltage": (48.0,) * 6,
    "elbow_position": (0.0, 0.0, 0.0),
    "elbow_velocity": (0.0, 0.0, 0.0),
    "standard_analog_input0": 0.0,
    "standard_analog_input1": 0.0,
    "io_current": 0.0,
    "euromap67_input_bits": 0,
    "euromap67_output_bits": 0,
    "euromap67_24V_voltage": 0.0,
    "euromap67_24V_current": 0.0,
    "tool_mode": 0,
    "tool_analog_input_types": 0,
    "tool_analog_input0": 0.0,
    "tool_analog_input1": 0.0,
    "tool_output_voltage": 24,
    "tool_output_current": 0.0,
    "tool_temperature": 35.0,
    "tool_output_mode": 0,
    "tool_digital_output0_mode": 0,
    "tool_digital_output1_mode": 0,
    "script_control_line": 0,
    "ft_raw_wrench": (0.0,) * 6,
    "joint_position_deviation_ratio": 0.0,
}


def _constant(value: object) -> Getter:
    return lambda s: value


def _build_getters() -> dict[str, Getter]:
    g: dict[str, Getter] = {name: _constant(value) for name, value in _CONSTANTS.items()}
    g.update(
        {
            "timestamp": lambda s: s.timestamp_s,
            "target_q": lambda s: s.target_q,
            "target_qd": lambda s: s.target_qd,
            "target_qdd": lambda s: s.target_qdd,
            "target_moment": lambda s: s.joint_torque,
            "actual_q": lambda s: s.actual_q,
            "actual_qd": lambda s: s.actual_qd,
            "actual_qdd": lambda s: s.actual_qdd,
            "actual_moment": lambda s: s.joint_torque,
            "actual_current_as_torque": lambda s: s.joint_torque,
            "actual_TCP_pose": lambda s: s.actual_tcp_pose,
            "actual_TCP_speed": lambda s: s.actual_tcp_speed,
            "actual_TCP_force": lambda s: s.tcp_force,
            "target_TCP_pose": lambda s: s.target_tcp_pose,
            "target_TCP_speed": lambda s: s.target_tcp_speed,
            "actual_digital_input_bits": lambda s: s.digital_input_bits,
            "actual_execution_time": lambda s: s.execution_time_s * 1e3,  # UR reports milliseconds
            "robot_mode": lambda s: s.robot_mode,
            "safety_mode": lambda s: s.safety_mode,
            "safety_status": lambda s: s.safety_mode,
            "speed_scaling": lambda s: s.speed_scaling,
            "target_speed_fraction": lambda s: s.target_speed_fraction,
            "actual_digital_output_bits": lambda s: s.digital_output_bits,
            "runtime_state": lambda s: s.runtime_state,
            "robot_status_bits": lambda s: s.robot_status_bits,
            "safety_status_bits": lambda s: s.safety_status_bits,
            "analog_io_types": lambda s: s.analog_io_types,
            "standard_analog_output0": lambda s: s.analog_out[0],
            "standard_analog_output1": lambda s: s.analog_out[1],
            "tcp_force_scalar": lambda s: sum(f * f for f in s.tcp_force[:3]) ** 0.5,
            "output_bit_registers0_to_31": lambda s: s.output_bits & 0xFFFFFFFF,
            "output_bit_registers32_to_63": lambda s: (s.output_bits >> 32) & 0xFFFFFFFF,
            "input_bit_registers0_to_31": lambda s: s.input_bits & 0xFFFFFFFF,
            "input_bit_registers32_to_63": lambda s: (s.input_bits >> 32) & 0xFFFFFFFF,
            "payload": lambda s: s.payload_mass_kg,
            "payload_cog": lambda s: s.payload_cog_m,
            "payload_inertia": lambda s: s.payload_inertia,
            "collision_detection_ratio": lambda s: s.collision_ratio,
        }
    )
    for i in range(N_REGISTERS):
        g[f"output_int_register_{i}"] = lambda s, i=i: s.output_int[i]
        g[f"output_double_register_{i}"] = lambda s, i=i: s.output_double[i]
        g[f"input_int_register_{i}"] = lambda s, i=i: s.input_int[i]
        g[f"input_double_register_{i}"] = lambda s, i=i: s.input_double[i]
    for i in range(64, 128):
        g[f"output_bit_register_{i}"] = lambda s, i=i: bool((s.output_bits >> i) & 1)
        g[f"input_bit_register_{i}"] = lambda s, i=i: bool((s.input_bits >> i) & 1)
    missing = set(OUTPUT_TYPES) - set(g)
    if missing:
        raise RuntimeError(f"RTDE outputs without a value getter: {sorted(missing)}")
    return g


OUTPUT_GETTERS: dict[str, Getter] = _build_getters()


class OutputRecipe:
    """A validated output recipe: packs a snapshot into one ``U`` payload (recipe id first)."""

    def __init__(self, recipe_id: int, names: list[str], frequency_hz: float) -> None:
        unknown = [n for n in names if n not in OUTPUT_TYPES]
        if unknown:
            raise ValueError(f"unknown RTDE output variables {unknown}")
        self.recipe_id = recipe_id
        self.names = names
        self.frequency_hz = frequency_hz
        types = [OUTPUT_TYPES[n] for n in names]
        self._struct = recipe_struct(types)
        self._id_prefix = struct.pack(">B", recipe_id)
        self._fields = [(OUTPUT_GETTERS[n], type_width(t)) for n, t in zip(names, types, strict=True)]

    def pack(self, snapshot: StateSnapshot) -> bytes:
        values: list[object] = []
        for getter, width in self._fields:
            value = getter(snapshot)
            if width == 1:
                values.append(value)
            else:
                values.extend(value)  # type: ignore[call-overload]
        return self._id_prefix + self._struct.pack(*values)
