"""A ur_rtde client's recovery from a protective stop, as the emulator tests drive it by hand."""

from __future__ import annotations

import socket
import time
from typing import Any


def unlock_and_restart(host: str, control: Any) -> None:
    """Dashboard ``unlock protective stop`` on ``host`` (its reply checked), then the control script uploaded again
    through ``control`` (an ``RTDEControlInterface``) and awaited for up to 2 s."""
    with socket.create_connection((host, 29999), timeout=2.0) as dash:
        dash.recv(100)
        dash.sendall(b"unlock protective stop\n")
        assert dash.recv(100) == b"Protective stop releasing\n"
    assert control.reuploadScript()
    end = time.monotonic() + 2.0
    while not control.isProgramRunning() and time.monotonic() < end:
        time.sleep(0.005)
