"""The controller's shared state: RTDE registers, IO, safety and program status codes, and the immutable
per-tick snapshot every output variable is read from.

Registers and IO are global across all RTDE connections and persist for the controller's lifetime (as on a real
robot: a register keeps the last value any client wrote, see pitfall 1 in the protocol note).
"""

from __future__ import annotations

import dataclasses
import logging

from sim.controller.rtde_names import N_REGISTERS

log = logging.getLogger(__name__)

# runtime_state
RUNTIME_STOPPING, RUNTIME_STOPPED, RUNTIME_PLAYING, RUNTIME_PAUSING, RUNTIME_PAUSED, RUNTIME_RESUMING = range(6)
RUNTIME_NAMES = {0: "STOPPING", 1: "STOPPED", 2: "PLAYING", 3: "PAUSING", 4: "PAUSED", 5: "RESUMING"}
# robot_mode
ROBOT_MODE_POWER_OFF, ROBOT_MODE_IDLE, ROBOT_MODE_RUNNING = 3, 5, 7
ROBOT_MODE_NAMES = {3: "POWER_OFF", 4: "POWER_ON", 5: "IDLE", 6: "BACKDRIVE", 7: "RUNNING"}
# safety_mode
SAFETY_MODE_NORMAL, SAFETY_MODE_PROTECTIVE_STOP = 1, 3
SAFETY_MODE_NAMES = {1: "NORMAL", 2: "REDUCED", 3: "PROTECTIVE_STOP"}
# safety_status_bits
SAFETY_BIT_NORMAL = 1 << 0
SAFETY_BIT_PROTECTIVE_STOP = 1 << 2
SAFETY_BIT_EMERGENCY_STOP = 1 << 7
# robot_status_bits
ROBOT_STATUS_POWER_ON = 1 << 0
ROBOT_STATUS_PROGRAM_RUNNING = 1 << 1
JOINT_MODE_RUNNING = 253

_ZERO6 = (0.0,) * 6


@dataclasses.dataclass
class Registers:
    """RTDE general-purpose registers 0..47 (int, double) and bit registers 0..127, inputs and outputs."""

    input_int: list[int] = dataclasses.field(default_factory=lambda: [0] * N_REGISTERS)
    input_double: list[float] = dataclasses.field(default_factory=lambda: [0.0] * N_REGISTERS)
    input_bits: int = 0
    output_int: list[int] = dataclasses.field(default_factory=lambda: [0] * N_REGISTERS)
    output_double: list[float] = dataclasses.field(default_factory=lambda: [0.0] * N_REGISTERS)
    output_bits: int = 0


@dataclasses.dataclass
class IoState:
    """Controller IO as RTDE exposes it."""

    standard_do: int = 0  # 8 bits
    configurable_do: int = 0  # 8 bits
    tool_do: int = 0  # 2 bits
    analog_out: list[float] = dataclasses.field(default_factory=lambda: [0.0, 0.0])
    analog_out_voltage_mask: int = 0  # bit i set: analog output i is a voltage output (else current)
    speed_slider: float = 1.0
    external_force_torque: tuple[float, ...] = _ZERO6

    @property
    def digital_output_bits(self) -> int:
        """``actual_digital_output_bits``: standard 0-7, configurable 8-15, tool 16-17."""
        return self.standard_do | (self.configurable_do << 8) | (self.tool_do << 16)


def _masked(old: int, mask: int, value: int) -> int:
    return (old & ~mask) | (value & mask)


def apply_input_fields(regs: Registers, io: IoState, fields: dict[str, object]) -> None:
    """Applies one RTDE input package (name -> decoded value) the way the controller does: registers are
    overwritten, masked outputs change only the bits in their mask."""
    for name, value in fields.items():
        if name.startswith("input_int_register_"):
            regs.input_int[int(name[19:])] = int(value)  # type: ignore[call-overload]
        elif name.startswith("input_double_register_"):
            regs.input_double[int(name[22:])] = float(value)  # type: ignore[arg-type]
        elif name.startswith("input_bit_register_"):
            bit = 1 << int(name[19:])
            regs.input_bits = regs.input_bits | bit if value else regs.input_bits & ~bit
        elif name == "input_bit_registers0_to_31":
            regs.input_bits = (regs.input_bits & ~0xFFFFFFFF) | int(value)  # type: ignore[call-overload]
        elif name == "input_bit_registers32_to_63":
            regs.input_bits = (regs.input_bits & ~(0xFFFFFFFF << 32)) | (int(value) << 32)  # type: ignore[call-overload]
        elif name == "external_force_torque":
            io.external_force_torque = tuple(float(v) for v in value)  # type: ignore[attr-defined]
    if "standard_digital_output_mask" in fields:
        io.standard_do = _masked(
            io.standard_do, _int(fields, "standard_digital_output_mask"), _int(fields, "standard_digital_output")
        )
    if "configurable_digital_output_mask" in fields:
        io.configurable_do = _masked(
            io.configurable_do,
            _int(fields, "configurable_digital_output_mask"),
            _int(fields, "configurable_digital_output"),
        )
    if "tool_digital_output_mask" in fields:
        io.tool_do = (
            _masked(io.tool_do, _int(fields, "tool_digital_output_mask"), _int(fields, "tool_digital_output")) & 0x3
        )
    if "speed_slider_mask" in fields and _int(fields, "speed_slider_mask") & 1:
        fraction = float(fields.get("speed_slider_fraction", io.speed_slider))  # type: ignore[arg-type]
        io.speed_slider = min(max(fraction, 0.0), 1.0)
    if "standard_analog_output_mask" in fields:
        mask = _int(fields, "standard_analog_output_mask")
        io.analog_out_voltage_mask = _masked(
            io.analog_out_voltage_mask, mask, _int(fields, "standard_analog_output_type")
        )
        for i in (0, 1):
            key = f"standard_analog_output_{i}"
            if mask & (1 << i) and key in fields:
                io.analog_out[i] = min(max(float(fields[key]), 0.0), 1.0)  # type: ignore[arg-type]


def _int(fields: dict[str, object], name: str) -> int:
    return int(fields.get(name, 0))  # type: ignore[call-overload]


@dataclasses.dataclass(frozen=True)
class StateSnapshot:
    """Everything the RTDE outputs report for one controller tick. Vectors are tuples."""

    timestamp_s: float = 0.0
    target_q: tuple[float, ...] = _ZERO6
    target_qd: tuple[float, ...] = _ZERO6
    target_qdd: tuple[float, ...] = _ZERO6
    actual_q: tuple[float, ...] = _ZERO6
    actual_qd: tuple[float, ...] = _ZERO6
    actual_qdd: tuple[float, ...] = _ZERO6
    joint_torque: tuple[float, ...] = _ZERO6
    actual_tcp_pose: tuple[float, ...] = _ZERO6
    actual_tcp_speed: tuple[float, ...] = _ZERO6
    target_tcp_pose: tuple[float, ...] = _ZERO6
    target_tcp_speed: tuple[float, ...] = _ZERO6
    tcp_force: tuple[float, ...] = _ZERO6
    robot_mode: int = ROBOT_MODE_RUNNING
    safety_mode: int = SAFETY_MODE_NORMAL
    safety_status_bits: int = SAFETY_BIT_NORMAL
    robot_status_bits: int = ROBOT_STATUS_POWER_ON
    runtime_state: int = RUNTIME_STOPPED
    digital_output_bits: int = 0
    digital_input_bits: int = 0
    analog_out: tuple[float, float] = (0.0, 0.0)
    analog_io_types: int = 0
    speed_scaling: float = 1.0
    target_speed_fraction: float = 1.0
    payload_mass_kg: float = 0.0
    payload_cog_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    payload_inertia: tuple[float, ...] = _ZERO6
    input_int: tuple[int, ...] = (0,) * N_REGISTERS
    input_double: tuple[float, ...] = (0.0,) * N_REGISTERS
    input_bits: int = 0
    output_int: tuple[int, ...] = (0,) * N_REGISTERS
    output_double: tuple[float, ...] = (0.0,) * N_REGISTERS
    output_bits: int = 0
    execution_time_s: float = 0.0
    collision_ratio: float = 0.0
