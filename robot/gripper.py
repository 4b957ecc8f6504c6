"""Parallel grippers behind one interface: a Robotiq 2F-85 on the URCap socket, or one driven by a digital output.

API (lengths m, speeds m/s, forces N, times s)::

    gripper = make_gripper(config, io=robot)     # RobotiqGripperConfig or DigitalOutputGripperConfig
    with gripper:                                # connect() ... disconnect()
        gripper.activate()
        gripper.open(width_m=None)               # fully open, or to a width (socket gripper only)
        held = gripper.close(force_n=None, speed_m_s=None)   # True / False / None (no sensor)
        gripper.width_m()                        # None when the gripper has no position feedback
        gripper.object_detected()                # True / False / None (no sensor)

``close()`` returns whether the fingers stopped on an object. ``None`` means the gripper cannot tell (a
digital-output gripper without a sensor input): the caller must verify the grasp another way (a look after lifting).
``can_set_width`` says whether ``open(width_m=...)`` is possible.

**Robotiq socket** (``RobotiqSocketGripper``): the ASCII protocol of the Robotiq URCap's gripper server (port 63352 on
the robot): ``SET VAR n [VAR n ...]`` answers ``ack``, ``GET VAR`` answers ``VAR n``. Variables used: ``ACT``
(activate), ``GTO`` (go to the requested position), ``POS`` (requested on SET, measured on GET; 0 = open, 255 =
closed), ``SPE``/``FOR`` (speed and force, 0-255), ``STA`` (3 = activated), ``PRE`` (the position request echo),
``OBJ`` (0 moving, 1 stopped on an object while opening, 2 while closing, 3 at the requested position) and ``FLT``
(fault code). ``open()``/``close()`` request 0/255; widths map onto positions through the calibrated readings
``pos_open``/``pos_closed`` (``RobotiqGripperConfig``). A move sends ``SET SPE s FOR f POS p``, waits until ``PRE``
echoes ``p`` (the request has reached the gripper), then until ``OBJ`` is non-zero. Every read has a timeout; a
timeout or a fault raises ``GripperError`` naming the host, the port and the command.

**Digital output** (``DigitalOutputGripper``): one output (standard, configurable or tool, through rtde_io) closes
the gripper at ``close_level`` and opens it at the other level; it waits ``actuation_time_s`` after switching.
Object detection comes from an optional digital input (e.g. a pressure switch or a finger sensor), or none.
The robot side is the ``DigitalIO`` protocol, which ``robot.ur.URRobot`` implements.
"""

from __future__ import annotations

import abc
import logging
import math
import socket
import threading
import time
from collections.abc import Mapping
from dataclasses import dataclass, fields
from typing import Any, Protocol

from sygrid.errors import ConfigError, SygridError
from sygrid.robots import gripper_2f85

log = logging.getLogger(__name__)

__all__ = [
    "DigitalIO",
    "DigitalOutputGripper",
    "DigitalOutputGripperConfig",
    "Gripper",
    "GripperError",
    "RobotiqGripperConfig",
    "RobotiqSocketGripper",
    "gripper_config_from_dict",
    "make_gripper",
]

ROBOTIQ_PORT = 63352
# OBJ values of the Robotiq register map.
OBJ_MOVING, OBJ_STOPPED_OPENING, OBJ_STOPPED_CLOSING, OBJ_AT_POSITION = 0, 1, 2, 3
#: Position requests for full opening and full closing: the register's ends.
POS_FULLY_OPEN, POS_FULLY_CLOSED = 0, 255
_STA_ACTIVE = 3
_POLL_S = 0.01
_DIGITAL_KINDS = ("standard", "configurable", "tool")


class GripperError(SygridError, RuntimeError):
    """The gripper did not answer, reported a fault, or could not do what was asked."""


class DigitalIO(Protocol):
    """What a digital-output gripper needs of the robot (``robot.ur.URRobot`` has it)."""

    def set_digital_out(self, index: int, value: bool, kind: str = "standard") -> None: ...

    def digital_in(self, index: int, kind: str = "standard") -> bool: ...


# ---------------------------------------------------------------------------------------------- configuration


@dataclass(frozen=True)
class RobotiqGripperConfig:
    """A Robotiq 2F-85 (or 2F-140 with ``stroke_m=0.14``) on the URCap socket of ``host``.

    ``pos_open``/``pos_closed``: the position register's readings with the fingers fully open (``stroke_m``) and
    closed on nothing (0 m); the width is linear between them. 0 and 255 uncalibrated; a real 2F-85's fingers meet
    short of 255, so ``sygrid calibrate gripper`` measures both (``robot.gripper_calibration``). Full opening and
    closing request the register's ends (0, 255) whatever the calibration. Speed and force map linearly onto 0-255
    over the gripper's ranges; requests outside them raise ``GripperError``."""

    host: str
    port: int = ROBOTIQ_PORT
    #: Bound on connecting and on each reply.
    timeout_s: float = 2.0
    activation_timeout_s: float = 5.0
    #: Extra time allowed beyond a full stroke at the commanded speed.
    move_margin_s: float = 2.0
    stroke_m: float = gripper_2f85.STROKE_M
    pos_open: int = 0
    pos_closed: int = 255
    speed_range_m_s: tuple[float, float] = gripper_2f85.SPEED_RANGE_M_S
    force_range_n: tuple[float, float] = gripper_2f85.FORCE_RANGE_N
    speed_m_s: float = 0.1
    force_n: float = 100.0

    def __post_init__(self) -> None:
        if not isinstance(self.host, str) or not self.host:
            raise ConfigError(f"RobotiqGripperConfig.host must be a non-empty address, got {self.host!r}")
        if not (isinstance(self.port, int) and 0 < self.port < 65536):
            raise ConfigError(f"RobotiqGripperConfig.port must be 1..65535, got {self.port!r}")
        for name in ("timeout_s", "activation_timeout_s", "stroke_m"):
            _check_positive(self, name)
        if not (isinstance(self.move_margin_s, int | float) and self.move_margin_s >= 0):
            raise ConfigError(f"RobotiqGripperConfig.move_margin_s must be >= 0, got {self.move_margin_s!r}")
        if not (0 <= self.pos_open <= 255 and 0 <= self.pos_closed <= 255 and self.pos_open < self.pos_closed):
            raise ConfigError(
                f"RobotiqGripperConfig needs 0 <= pos_open < pos_closed <= 255, got {self.pos_open}, {self.pos_closed}"
            )
        for name in ("speed_range_m_s", "force_range_n"):
            lo, hi = getattr(self, name)
            if not 0 < lo < hi:
                raise ConfigError(f"RobotiqGripperConfig.{name} must be (low, high) with 0 < low < high, got {lo, hi}")
        _check_in_range(self.speed_m_s, self.speed_range_m_s, "RobotiqGripperConfig.speed_m_s", ConfigError)
        _check_in_range(self.force_n, self.force_range_n, "RobotiqGripperConfig.force_n", ConfigError)


@dataclass(frozen=True)
class DigitalOutputGripperConfig:
    """A gripper switched by one digital output (a pneumatic valve, an electric gripper's IO mode).

    ``output``/``output_kind``: the pin (standard 0-7, configurable 0-7, tool 0-1); ``close_level``: the level that
    closes. ``object_input``/``object_input_kind``/``object_present_level``: an optional sensor input that reads
    ``object_present_level`` while an object is held; None: no sensor."""

    output: int
    output_kind: str = "tool"
    close_level: bool = True
    actuation_time_s: float = 0.3
    object_input: int | None = None
    object_input_kind: str = "tool"
    object_present_level: bool = True

    def __post_init__(self) -> None:
        for kind_name in ("output_kind", "object_input_kind"):
            if getattr(self, kind_name) not in _DIGITAL_KINDS:
                raise ConfigError(
                    f"DigitalOutputGripperConfig.{kind_name} must be one of {list(_DIGITAL_KINDS)}, "
                    f"got {getattr(self, kind_name)!r}"
                )
        _check_pin(self.output, self.output_kind, "output")
        if self.object_input is not None:
            _check_pin(self.object_input, self.object_input_kind, "object_input")
        if not (isinstance(self.actuation_time_s, int | float) and self.actuation_time_s >= 0):
            raise ConfigError(f"DigitalOutputGripperConfig.actuation_time_s must be >= 0, got {self.actuation_time_s}")


def _check_positive(config: object, name: str) -> None:
    value = getattr(config, name)
    if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
        raise ConfigError(f"{type(config).__name__}.{name} must be a positive number, got {value!r}")


def _check_in_range(value: object, bounds: tuple[float, float], name: str, error: type[Exception]) -> float:
    lo, hi = bounds
    if not (isinstance(value, int | float) and lo <= value <= hi):
        raise error(f"{name} must be within [{lo:g}, {hi:g}], got {value!r}")
    return float(value)


def _check_pin(index: object, kind: str, name: str) -> None:
    count = 2 if kind == "tool" else 8
    if not (isinstance(index, int) and not isinstance(index, bool) and 0 <= index < count):
        raise ConfigError(f"DigitalOutputGripperConfig.{name} must be a {kind} pin 0..{count - 1}, got {index!r}")


GripperConfig = RobotiqGripperConfig | DigitalOutputGripperConfig
_KINDS: dict[str, type] = {"robotiq_socket": RobotiqGripperConfig, "digital_output": DigitalOutputGripperConfig}


def gripper_config_from_dict(
    data: Mapping[str, Any], where: str = "gripper config", default_host: str | None = None
) -> GripperConfig:
    """From a TOML/JSON table with ``kind = "robotiq_socket" | "digital_output"`` and the fields of that config.
    A socket gripper's ``host`` defaults to ``default_host`` (the robot's address). ``where`` names the file and
    section in error messages."""
    if not isinstance(data, Mapping):
        raise ConfigError(f"{where}: expected a table of gripper settings, got {type(data).__name__}")
    kind = data.get("kind")
    if kind not in _KINDS:
        raise ConfigError(f"{where}: kind must be one of {sorted(_KINDS)}, got {kind!r}")
    cls = _KINDS[kind]
    known = {f.name for f in fields(cls)}
    kwargs = {k: v for k, v in data.items() if k != "kind"}
    unknown = sorted(set(kwargs) - known)
    if unknown:
        raise ConfigError(f"{where}: unknown keys {unknown} for kind {kind!r}; valid keys: {sorted(known)}")
    if cls is RobotiqGripperConfig:
        kwargs.setdefault("host", default_host)
        for key in ("speed_range_m_s", "force_range_n"):
            if key in kwargs:
                kwargs[key] = tuple(kwargs[key])
    try:
        return cls(**kwargs)
    except (ConfigError, TypeError, ValueError) as exc:
        raise ConfigError(f"{where}: {exc}") from None


# ---------------------------------------------------------------------------------------------- interface


class Gripper(abc.ABC):
    """A parallel gripper; see the module docstring. A context manager (connect/disconnect)."""

    #: Whether ``open(width_m=...)`` can go to a given width.
    can_set_width: bool = False

    @property
    def stroke_m(self) -> float | None:
        """The fingers' fully open width (m), None where it is not known."""
        return None

    def __enter__(self) -> Gripper:
        self.connect()
        return self

    def __exit__(self, *exc: object) -> None:
        self.disconnect()

    def connect(self) -> None:  # noqa: B027 - grippers without a link of their own need nothing here
        """Opens the gripper's own link, if it has one."""

    def disconnect(self) -> None:  # noqa: B027
        """Closes the gripper's own link, if it has one."""

    @abc.abstractmethod
    def activate(self) -> None:
        """Makes the gripper ready to move (Robotiq: reset and activate; digital output: open)."""

    @abc.abstractmethod
    def open(self, width_m: float | None = None, speed_m_s: float | None = None) -> None:
        """Opens fully, or to ``width_m`` where ``can_set_width``; returns when the fingers stopped."""

    @abc.abstractmethod
    def close(self, force_n: float | None = None, speed_m_s: float | None = None) -> bool | None:
        """Closes with ``force_n``; returns whether an object stopped the fingers (None: cannot tell)."""

    @abc.abstractmethod
    def width_m(self) -> float | None:
        """The measured opening (m), or None without position feedback."""

    @abc.abstractmethod
    def object_detected(self) -> bool | None:
        """Whether an object is held (None: cannot tell)."""


# ---------------------------------------------------------------------------------------------- Robotiq socket


class RobotiqSocketGripper(Gripper):
    """A Robotiq 2F gripper through the URCap's socket server; see the module docstring."""

    can_set_width = True

    def __init__(self, config: RobotiqGripperConfig) -> None:
        self.config = config
        self._sock: socket.socket | None = None
        self._buffer = b""
        self._lock = threading.Lock()

    @property
    def stroke_m(self) -> float:
        return self.config.stroke_m

    @property
    def _where(self) -> str:
        return f"gripper at {self.config.host}:{self.config.port}"

    def connect(self) -> None:
        """Opens the socket (bounded by ``timeout_s``); ``GripperError`` naming host and port when nothing answers."""
        if self._sock is not None:
            return
        cfg = self.config
        try:
            sock = socket.create_connection((cfg.host, cfg.port), timeout=cfg.timeout_s)
        except OSError as exc:
            raise GripperError(
                f"{self._where}: cannot connect within {cfg.timeout_s:g} s ({exc}); is the Robotiq URCap installed "
                "and the gripper plugged in?"
            ) from exc
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._sock, self._buffer = sock, b""

    def disconnect(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    def activate(self) -> None:
        """Resets and activates the gripper unless it is already active, then enables motion (``GTO 1``)."""
        if self.get("STA") != _STA_ACTIVE or self.get("ACT") != 1:
            self.set(ACT=0, ATR=0)  # a reset clears faults; activation needs it after power-up
            self._wait(lambda: self.get("STA") == 0, self.config.timeout_s, "the reset (STA 0)")
            self.set(ACT=1)
            self._wait(lambda: self.get("STA") == _STA_ACTIVE, self.config.activation_timeout_s, "activation (STA 3)")
        self.set(GTO=1)
        self._raise_on_fault("activation")

    def open(self, width_m: float | None = None, speed_m_s: float | None = None) -> None:
        pos = POS_FULLY_OPEN if width_m is None else self._width_to_pos(width_m)
        obj = self.move_to_position(pos, speed_m_s, None)
        if obj == OBJ_STOPPED_OPENING:
            log.warning("%s: the fingers stopped on something while opening", self._where)

    def close(self, force_n: float | None = None, speed_m_s: float | None = None) -> bool:
        return self.move_to_position(POS_FULLY_CLOSED, speed_m_s, force_n) == OBJ_STOPPED_CLOSING

    def width_m(self) -> float:
        cfg = self.config
        fraction = (self.get("POS") - cfg.pos_open) / (cfg.pos_closed - cfg.pos_open)
        return cfg.stroke_m * (1.0 - min(max(fraction, 0.0), 1.0))

    def object_detected(self) -> bool:
        return self.get("OBJ") in (OBJ_STOPPED_OPENING, OBJ_STOPPED_CLOSING)

    def move_to_position(self, pos: int, speed_m_s: float | None = None, force_n: float | None = None) -> int:
        """Sends a position request (0-255) and waits until the fingers stop; returns the final ``OBJ``."""
        cfg = self.config
        speed = _check_in_range(
            cfg.speed_m_s if speed_m_s is None else speed_m_s, cfg.speed_range_m_s, "speed_m_s", GripperError
        )
        force = _check_in_range(cfg.force_n if force_n is None else force_n, cfg.force_range_n, "force_n", GripperError)
        spe = round(255 * (speed - cfg.speed_range_m_s[0]) / (cfg.speed_range_m_s[1] - cfg.speed_range_m_s[0]))
        fr = round(255 * (force - cfg.force_range_n[0]) / (cfg.force_range_n[1] - cfg.force_range_n[0]))
        if self.get("STA") != _STA_ACTIVE:
            raise GripperError(f"{self._where} is not activated (STA {self.get('STA')}); call activate() first")
        # POS last, so the request that starts the motion carries the new speed and force.
        self.set(SPE=spe, FOR=fr, POS=pos)
        self._wait(lambda: self.get("PRE") == pos, cfg.timeout_s, f"the position request echo (PRE {pos})")
        timeout = cfg.stroke_m / speed + cfg.move_margin_s
        obj = OBJ_MOVING
        end = time.monotonic() + timeout
        while (obj := self.get("OBJ")) == OBJ_MOVING:
            if time.monotonic() > end:
                self._raise_on_fault(f"the move to POS {pos}")
                raise GripperError(f"{self._where}: the fingers did not stop within {timeout:.1f} s (POS {pos})")
            time.sleep(_POLL_S)
        self._raise_on_fault(f"the move to POS {pos}")
        return obj

    # --- protocol --------------------------------------------------------------------------------------------
    def set(self, **values: int) -> None:
        """``SET NAME value ...`` (values 0-255); ``GripperError`` unless the gripper acknowledges."""
        for name, value in values.items():
            if not (isinstance(value, int) and 0 <= value <= 255):
                raise GripperError(f"{self._where}: SET {name} needs an integer 0..255, got {value!r}")
        line = "SET " + " ".join(f"{name} {value}" for name, value in values.items())
        reply = self._exchange(line, b"ack")
        if reply != "ack":
            raise GripperError(f"{self._where}: {line!r} answered {reply!r} (expected 'ack')")

    def get(self, name: str) -> int:
        """``GET NAME``; the integer value."""
        line = f"GET {name}"
        reply = self._exchange(line, b"\n")
        words = reply.split()
        if len(words) != 2 or words[0] != name or not words[1].lstrip("-").isdigit():
            raise GripperError(f"{self._where}: {line!r} answered {reply!r} (expected '{name} <number>')")
        return int(words[1])

    def _exchange(self, line: str, terminator: bytes) -> str:
        """Sends one line and reads one reply: up to a newline for GET, the bare ``ack`` (no newline, as the URCap
        sends it) or an error mark for SET."""
        with self._lock:
            self.connect()
            sock = self._sock
            assert sock is not None
            try:
                sock.sendall((line + "\n").encode("ascii"))
                while True:
                    reply = self._take_reply(terminator)
                    if reply is not None:
                        return reply
                    chunk = sock.recv(1024)
                    if not chunk:
                        raise ConnectionResetError("the gripper closed the connection")
                    self._buffer += chunk
            except TimeoutError as exc:
                self.disconnect()  # a late reply would pair with the next request
                raise GripperError(f"{self._where}: no reply to {line!r} within {self.config.timeout_s:g} s") from exc
            except OSError as exc:
                self.disconnect()
                raise GripperError(f"{self._where}: {line!r} failed: {exc}") from exc

    def _take_reply(self, terminator: bytes) -> str | None:
        buf = self._buffer
        if terminator == b"\n":
            end = buf.find(b"\n")
            if end < 0:
                return None
            self._buffer = buf[end + 1 :]
            return buf[:end].decode("ascii", "replace").strip()
        # SET: "ack" without a newline; an error reply ("?" or a line) also ends the wait.
        stripped = buf.lstrip()
        if stripped.startswith(b"ack"):
            self._buffer = stripped[3:].lstrip(b"\r\n")
            return "ack"
        if stripped[:1] == b"?" or b"\n" in stripped:
            self._buffer = b""
            return stripped.decode("ascii", "replace").strip()
        return None

    def _wait(self, predicate: Any, timeout_s: float, what: str) -> None:
        end = time.monotonic() + timeout_s
        while not predicate():
            if time.monotonic() > end:
                self._raise_on_fault(what)
                raise GripperError(f"{self._where}: timed out after {timeout_s:g} s waiting for {what}")
            time.sleep(_POLL_S)

    def _raise_on_fault(self, during: str) -> None:
        fault = self.get("FLT")
        if fault:
            raise GripperError(f"{self._where}: fault {fault:#04x} during {during} (Robotiq FLT register)")

    def _width_to_pos(self, width_m: float) -> int:
        cfg = self.config
        if not (isinstance(width_m, int | float) and 0.0 <= width_m <= cfg.stroke_m):
            raise GripperError(f"width_m must be within [0, {cfg.stroke_m:g}] m, got {width_m!r}")
        return round(cfg.pos_open + (cfg.pos_closed - cfg.pos_open) * (1.0 - width_m / cfg.stroke_m))


# ---------------------------------------------------------------------------------------------- digital output


class DigitalOutputGripper(Gripper):
    """A gripper switched by one digital output of the robot; see the module docstring."""

    can_set_width = False

    def __init__(self, config: DigitalOutputGripperConfig, io: DigitalIO) -> None:
        self.config = config
        self.io = io

    def activate(self) -> None:
        self.open()

    def open(self, width_m: float | None = None, speed_m_s: float | None = None) -> None:
        if width_m is not None:
            raise GripperError(
                "a digital-output gripper only opens fully (can_set_width is False); call open() without width_m"
            )
        self._switch(not self.config.close_level)

    def close(self, force_n: float | None = None, speed_m_s: float | None = None) -> bool | None:
        """Switches the output to closed and waits ``actuation_time_s``. Force and speed are set by the hardware
        (air pressure, flow valves): passing them is an error rather than silently ignored."""
        if force_n is not None or speed_m_s is not None:
            raise GripperError("a digital-output gripper has no force or speed setting; call close() without them")
        self._switch(self.config.close_level)
        return self.object_detected()

    def width_m(self) -> None:
        return None

    def object_detected(self) -> bool | None:
        cfg = self.config
        if cfg.object_input is None:
            return None
        return self.io.digital_in(cfg.object_input, cfg.object_input_kind) == cfg.object_present_level

    def _switch(self, level: bool) -> None:
        cfg = self.config
        self.io.set_digital_out(cfg.output, level, cfg.output_kind)
        time.sleep(cfg.actuation_time_s)


# ---------------------------------------------------------------------------------------------- factory


def make_gripper(config: GripperConfig | Mapping[str, Any], io: DigitalIO | None = None) -> Gripper:
    """The gripper for ``config`` (a config object, or a table for ``gripper_config_from_dict``). A digital-output
    gripper needs ``io`` (the ``URRobot``). The socket gripper connects on first use (or ``connect()``/``with``)."""
    if isinstance(config, Mapping):
        config = gripper_config_from_dict(config)
    if isinstance(config, RobotiqGripperConfig):
        return RobotiqSocketGripper(config)
    if isinstance(config, DigitalOutputGripperConfig):
        if io is None:
            raise ConfigError("a digital-output gripper needs the robot's digital IO: make_gripper(config, io=robot)")
        return DigitalOutputGripper(config, io)
    raise ConfigError(
        f"make_gripper: unknown gripper config {type(config).__name__}; expected RobotiqGripperConfig or "
        "DigitalOutputGripperConfig"
    )
