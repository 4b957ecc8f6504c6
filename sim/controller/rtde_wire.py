"""RTDE framing: a 3-byte header (``uint16`` size including the header, ``uint8`` type) then the payload, all
big-endian. Pure byte functions shared by the server and the small probe client.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator

HEADER = struct.Struct(">HB")
MAX_MESSAGE_BYTES = 0xFFFF

# message types (ASCII letters)
REQUEST_PROTOCOL_VERSION = ord("V")
GET_URCONTROL_VERSION = ord("v")
TEXT_MESSAGE = ord("M")
DATA_PACKAGE = ord("U")
SETUP_OUTPUTS = ord("O")
SETUP_INPUTS = ord("I")
START = ord("S")
PAUSE = ord("P")

PROTOCOL_VERSION = 2


def frame(msg_type: int, payload: bytes = b"") -> bytes:
    """One framed message."""
    size = HEADER.size + len(payload)
    if size > MAX_MESSAGE_BYTES:
        raise ValueError(f"RTDE message of {size} bytes exceeds the {MAX_MESSAGE_BYTES}-byte limit")
    return HEADER.pack(size, msg_type) + payload


class FrameReader:
    """Splits a byte stream into ``(type, payload)`` messages; feed it whatever ``recv`` returned."""

    def __init__(self) -> None:
        self._buffer = bytearray()

    def feed(self, data: bytes) -> Iterator[tuple[int, bytes]]:
        self._buffer += data
        while len(self._buffer) >= HEADER.size:
            size, msg_type = HEADER.unpack_from(self._buffer)
            if size < HEADER.size:
                raise ValueError(f"RTDE header announces {size} bytes, less than the 3-byte header itself")
            if len(self._buffer) < size:
                return
            payload = bytes(self._buffer[HEADER.size : size])
            del self._buffer[:size]
            yield msg_type, payload


def parse_names(payload: bytes) -> list[str]:
    """Comma-separated variable names (the client sends a trailing comma)."""
    return [n.strip() for n in payload.decode("ascii", errors="replace").split(",") if n.strip()]


def parse_output_setup(payload: bytes) -> tuple[float, list[str]]:
    """``O`` payload (protocol 2): ``double`` frequency, then the names."""
    if len(payload) < 8:
        raise ValueError(f"output setup payload of {len(payload)} bytes is shorter than its 8-byte frequency")
    (frequency_hz,) = struct.unpack_from(">d", payload)
    return frequency_hz, parse_names(payload[8:])


def setup_reply(msg_type: int, recipe_id: int, types: list[str]) -> bytes:
    """``O``/``I`` reply: recipe id then the comma-joined type names."""
    return frame(msg_type, bytes([recipe_id & 0xFF]) + ",".join(types).encode("ascii"))


def version_reply(major: int, minor: int, bugfix: int, build: int) -> bytes:
    return frame(GET_URCONTROL_VERSION, struct.pack(">IIII", major, minor, bugfix, build))


def text_message(message: str, source: str = "emulator", level: int = 1) -> bytes:
    """``M`` from the controller (protocol 2): ``uint8`` length and the message, ``uint8`` length and the source,
    ``uint8`` warning level (0 exception, 1 error, 2 warning, 3 info). Texts are cut to 255 bytes."""
    text, src = message.encode("ascii", errors="replace")[:255], source.encode("ascii", errors="replace")[:255]
    return frame(TEXT_MESSAGE, bytes([len(text)]) + text + bytes([len(src)]) + src + bytes([level]))


def success_reply(msg_type: int, ok: bool = True) -> bytes:
    """``V``, ``S`` and ``P`` replies: one ``uint8`` accepted flag."""
    return frame(msg_type, bytes([1 if ok else 0]))
