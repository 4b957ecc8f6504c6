"""Is a UR controller answering? Connection checks bounded by a timeout at every step, for use before ur_rtde's
constructors, which wait for the controller without one (holding the GIL).

``probe_rtde`` does the RTDE protocol-version handshake; ``probe_tcp`` only connects. Both raise
``RobotConnectionError`` naming the host and the port.
"""

from __future__ import annotations

import socket
import struct

from robot.ur_errors import RobotConnectionError

__all__ = ["DASHBOARD_PORT", "RTDE_PORT", "probe_rtde", "probe_tcp"]

RTDE_PORT = 30004
DASHBOARD_PORT = 29999


def probe_rtde(host: str, port: int = RTDE_PORT, timeout_s: float = 2.0) -> None:
    """Connects to the RTDE port and asks for protocol version 2, bounded by ``timeout_s`` at every step.

    Written by hand because ur_rtde's constructors have no timeout here: they block (holding the GIL) until the
    controller streams. Raises ``RobotConnectionError`` naming the host and port."""
    try:
        sock = socket.create_connection((host, port), timeout=timeout_s)
    except OSError as exc:
        raise RobotConnectionError(
            f"UR controller {host}: nothing answers on port {port} (RTDE) within {timeout_s:g} s ({exc}); "
            "check the address, the network and that the controller is on"
        ) from exc
    with sock:
        try:
            sock.settimeout(timeout_s)
            sock.sendall(struct.pack(">HBH", 5, ord("V"), 2))  # size (with header), 'V', protocol version 2
            header = _recv_exact(sock, 3)
            size, kind = struct.unpack(">HB", header)
            if kind != ord("V") or size < 4:
                raise RobotConnectionError(
                    f"UR controller {host}:{port} answered the RTDE version request with message type {kind} "
                    "(expected 'V'); is this a UR controller?"
                )
            accepted = _recv_exact(sock, size - 3)[0]
        except TimeoutError as exc:
            raise RobotConnectionError(
                f"UR controller {host}:{port} (RTDE) accepted a connection but did not answer the protocol "
                f"version request within {timeout_s:g} s"
            ) from exc
        except OSError as exc:
            raise RobotConnectionError(f"UR controller {host}:{port} (RTDE): {exc}") from exc
    if not accepted:
        raise RobotConnectionError(f"UR controller {host}:{port} refused RTDE protocol version 2 (software < 3.5?)")


def _recv_exact(sock: socket.socket, n: int) -> bytes:
    data = b""
    while len(data) < n:
        chunk = sock.recv(n - len(data))
        if not chunk:
            raise ConnectionResetError("the controller closed the connection")
        data += chunk
    return data


def probe_tcp(host: str, port: int, what: str, timeout_s: float) -> None:
    """Connects to ``port`` (``what`` names it in the error) and closes again, within ``timeout_s``."""
    try:
        with socket.create_connection((host, port), timeout=timeout_s):
            pass
    except OSError as exc:
        raise RobotConnectionError(
            f"UR controller {host}: nothing answers on port {port} ({what}) within {timeout_s:g} s ({exc})"
        ) from exc
