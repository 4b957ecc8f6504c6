"""``sygrid sim``: serves on the requested loopback address, prints a summary, and shuts down cleanly on SIGINT and
SIGTERM."""

from __future__ import annotations

import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.timeout(60)


@pytest.mark.parametrize("signum, host", [(signal.SIGINT, "127.0.0.27"), (signal.SIGTERM, "127.0.0.28")])
def test_sim_command_serves_and_stops_on_signal(signum, host):
    proc = subprocess.Popen(
        [sys.executable, "-m", "launch.cli", "sim", "--host", host, "--backend", "kinematic"],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        lines = []
        deadline = time.monotonic() + 30.0
        while time.monotonic() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            lines.append(line)
            if line.startswith("Ctrl-C"):
                break
        text = "".join(lines)
        assert f"UR controller emulator on {host} (backend: kinematic)" in text
        assert "RTDE 30004, dashboard 29999, script 30001, 30002, 30003, gripper 63352" in text
        with socket.create_connection((host, 29999), timeout=2.0) as dash:
            assert dash.recv(100).startswith(b"Connected: Universal Robots Dashboard Server")
        proc.send_signal(signum)
        out, _ = proc.communicate(timeout=15.0)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, out
    assert "stopped." in out and "robot RUNNING" in out


def test_sim_command_reports_a_taken_port():
    with socket.socket() as blocker:
        blocker.bind(("127.0.0.26", 29999))
        blocker.listen(1)
        result = subprocess.run(
            [sys.executable, "-m", "launch.cli", "sim", "--host", "127.0.0.26"],
            cwd=REPO,
            capture_output=True,
            text=True,
            timeout=30,
        )
    assert result.returncode == 2
    assert "sygrid sim: error: " in result.stderr and "cannot listen on 127.0.0.26:29999" in result.stderr
