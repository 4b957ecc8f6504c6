"""The RTDE variable tables: every output and input name a UR e-Series controller (PolyScope 5.15) knows, with
its wire type.

Types are the ones ur_rtde 1.6.5 decodes with (its own built-in table, not the server's reply): only
``actual_tool_accelerometer``, ``payload_cog``, ``elbow_position`` and ``elbow_velocity`` are 3-vectors; every
other double vector is 6 long. Names the client's table also knows but UR does not document (``actual_qdd``,
``actual_moment``) are served as well, so a user-chosen ``variables=`` list never desynchronises.
Unknown names answer ``NOT_FOUND`` (outputs) in the setup reply; nothing is ever ``IN_USE``.
"""

from __future__ import annotations

import struct

# wire type -> struct code (big-endian is added by the packer) and element count
TYPE_CODES: dict[str, str] = {
    "BOOL": "?",
    "UINT8": "B",
    "UINT32": "I",
    "UINT64": "Q",
    "INT32": "i",
    "DOUBLE": "d",
    "VECTOR3D": "3d",
    "VECTOR6D": "6d",
    "VECTOR6INT32": "6i",
    "VECTOR6UINT32": "6I",
}
NOT_FOUND = "NOT_FOUND"
N_REGISTERS = 48  # input/output int and double registers 0..47

_V6 = "VECTOR6D"


def _output_table() -> dict[str, str]:
    table = {
        "timestamp": "DOUBLE",
        "target_q": _V6,
        "target_qd": _V6,
        "target_qdd": _V6,
        "target_current": _V6,
        "target_moment": _V6,
        "actual_q": _V6,
        "actual_qd": _V6,
        "actual_qdd": _V6,  # in ur_rtde's table, not in UR's documentation
        "actual_current": _V6,
        "actual_current_window": _V6,
        "actual_current_as_torque": _V6,
        "actual_moment": _V6,  # in ur_rtde's table, not in UR's documentation
        "joint_control_output": _V6,
        "actual_TCP_pose": _V6,
        "actual_TCP_speed": _V6,
        "actual_TCP_force": _V6,
        "target_TCP_pose": _V6,
        "target_TCP_speed": _V6,
        "actual_digital_input_bits": "UINT64",
        "joint_temperatures": _V6,
        "actual_execution_time": "DOUBLE",
        "robot_mode": "INT32",
        "joint_mode": "VECTOR6INT32",
        "safety_mode": "INT32",
        "safety_status": "INT32",
        "actual_tool_accelerometer": "VECTOR3D",
        "speed_scaling": "DOUBLE",
        "target_speed_fraction": "DOUBLE",
        "actual_momentum": "DOUBLE",
        "actual_main_voltage": "DOUBLE",
        "actual_robot_voltage": "DOUBLE",
        "actual_robot_current": "DOUBLE",
        "actual_joint_voltage": _V6,
        "actual_digital_output_bits": "UINT64",
        "runtime_state": "UINT32",
        "elbow_position": "VECTOR3D",
        "elbow_velocity": "VECTOR3D",
        "robot_status_bits": "UINT32",
        "safety_status_bits": "UINT32",
        "analog_io_types": "UINT32",
        "standard_analog_input0": "DOUBLE",
        "standard_analog_input1": "DOUBLE",
        "standard_analog_output0": "DOUBLE",
        "standard_analog_output1": "DOUBLE",
        "io_current": "DOUBLE",
        "euromap67_input_bits": "UINT32",
        "euromap67_output_bits": "UINT32",
        "euromap67_24V_voltage": "DOUBLE",
        "euromap67_24V_current": "DOUBLE",
        "tool_mode": "UINT32",
        "tool_analog_input_types": "UINT32",
        "tool_analog_input0": "DOUBLE",
        "tool_analog_input1": "DOUBLE",
        "tool_output_voltage": "INT32",
        "tool_output_current": "DOUBLE",
        "tool_temperature": "DOUBLE",
        "tcp_force_scalar": "DOUBLE",
        "output_bit_registers0_to_31": "UINT32",
        "output_bit_registers32_to_63": "UINT32",
        "input_bit_registers0_to_31": "UINT32",
        "input_bit_registers32_to_63": "UINT32",
        "tool_output_mode": "UINT8",
        "tool_digital_output0_mode": "UINT8",
        "tool_digital_output1_mode": "UINT8",
        "payload": "DOUBLE",
        "payload_cog": "VECTOR3D",
        "payload_inertia": _V6,
        "script_control_line": "UINT32",
        "ft_raw_wrench": _V6,
        "joint_position_deviation_ratio": "DOUBLE",
        "collision_detection_ratio": "DOUBLE",
    }
    for i in range(64, 128):
        table[f"output_bit_register_{i}"] = "BOOL"
        table[f"input_bit_register_{i}"] = "BOOL"
    for i in range(N_REGISTERS):
        table[f"output_int_register_{i}"] = "INT32"
        table[f"output_double_register_{i}"] = "DOUBLE"
        table[f"input_int_register_{i}"] = "INT32"
        table[f"input_double_register_{i}"] = "DOUBLE"
    return table


def _input_table() -> dict[str, str]:
    table = {
        "speed_slider_mask": "UINT32",
        "speed_slider_fraction": "DOUBLE",
        "standard_digital_output_mask": "UINT8",
        "standard_digital_output": "UINT8",
        "configurable_digital_output_mask": "UINT8",
        "configurable_digital_output": "UINT8",
        "tool_digital_output_mask": "UINT8",
        "tool_digital_output": "UINT8",
        "standard_analog_output_mask": "UINT8",
        "standard_analog_output_type": "UINT8",
        "standard_analog_output_0": "DOUBLE",
        "standard_analog_output_1": "DOUBLE",
        "input_bit_registers0_to_31": "UINT32",
        "input_bit_registers32_to_63": "UINT32",
        "external_force_torque": _V6,
    }
    for i in range(64, 128):
        table[f"input_bit_register_{i}"] = "BOOL"
    for i in range(N_REGISTERS):
        table[f"input_int_register_{i}"] = "INT32"
        table[f"input_double_register_{i}"] = "DOUBLE"
    return table


OUTPUT_TYPES: dict[str, str] = _output_table()
INPUT_TYPES: dict[str, str] = _input_table()


def output_types(names: list[str]) -> list[str]:
    """Wire types for an output setup request, ``NOT_FOUND`` where the name is unknown."""
    return [OUTPUT_TYPES.get(name, NOT_FOUND) for name in names]


def input_types(names: list[str]) -> list[str]:
    """Wire types for an input setup request, ``NOT_FOUND`` where the name is unknown or read-only."""
    return [INPUT_TYPES.get(name, NOT_FOUND) for name in names]


def recipe_struct(types: list[str]) -> struct.Struct:
    """The big-endian ``struct.Struct`` packing one data package body of these types (no recipe id)."""
    return struct.Struct(">" + "".join(TYPE_CODES[t] for t in types))


def type_width(type_name: str) -> int:
    """How many scalars one field of this type holds (1, 3 or 6)."""
    code = TYPE_CODES[type_name]
    return int(code[0]) if code[0].isdigit() else 1
