"""``sygrid pick`` stopped by SIGINT and SIGTERM on the simulated cell (oracle perception, a subprocess): it exits
130 / 143, writes the report with the finished cycles and the interrupted one, says where it stopped, and the
emulator saw the arm's stop. Hosts 127.0.0.81 and 127.0.0.82 (no other test module uses them). Also, without a
cell: the exit codes and their ``--help`` text; the emulator's child process on 127.0.0.84, which outlives SIGINT
and SIGTERM (its parent stops it) and whose death is named by ``EmulatorWatch``."""

from __future__ import annotations

import json
import os
import queue
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from launch.pick_stops import EXIT_CODES, EmulatorWatch, exit_code
from robot.pick_report import RunReport
from sim.controller import ControllerProcess

REPO = Path(__file__).resolve().parents[1]
SEED = 6  # the drop leaves the parts pickable (tests/test_pick_sim.py's cell)
SCENE = {
    "name": "pick_five",
    "objects": [
        {"builtin": "hex_nut", "count": 2},
        {"builtin": "l_bracket", "count": 1},
        {"builtin": "pipe", "count": 1},
        {"builtin": "spur_gear", "count": 1},
    ],
}


def test_exit_codes_and_their_help():
    assert exit_code(RunReport([], "bin_empty"), None) == 0 and exit_code(RunReport([], "max_cycles"), None) == 0
    for reason in ("nothing_safe", "gave_up", "too_many_failures", "needs_operator", "interrupted", "error"):
        assert exit_code(RunReport([], reason), None) == 1
    assert exit_code(RunReport([], "bin_empty"), signal.SIGINT) == 130
    assert exit_code(None, signal.SIGTERM) == 143
    text = subprocess.run(
        [sys.executable, "-m", "launch.cli", "pick", "--help"], cwd=REPO, capture_output=True, text=True, timeout=60
    ).stdout
    assert " ".join(text.split()).endswith(" ".join(EXIT_CODES.split()))


def test_the_emulator_process_outlives_stop_signals_and_its_death_is_named():
    deaths: list[str] = []
    with ControllerProcess("127.0.0.84", backend="kinematic") as process, EmulatorWatch(process, deaths.append, 0.05):
        for signum in (signal.SIGINT, signal.SIGTERM):  # a Ctrl-C or a service stop reaching the process group
            os.kill(process.pid, signum)
        time.sleep(0.5)
        assert process.exitcode is None and process.state().runtime_state is not None and deaths == []
        os.kill(process.pid, signal.SIGKILL)
        deadline = time.monotonic() + 10.0
        while not deaths and time.monotonic() < deadline:
            time.sleep(0.05)
        pid = process.pid
    assert deaths == [f"the emulator process (pid {pid}, host 127.0.0.84) was killed by SIGKILL"]


def _cell_file(folder: Path, host: str) -> Path:
    """``launch/cells/sim.toml`` with the five-part scene, ``host`` and the seed, paths made absolute."""
    (folder / "scene.json").write_text(json.dumps(SCENE))
    cells = (REPO / "launch" / "cells").resolve()
    text = (cells / "sim.toml").read_text()
    text = re.sub(r'^models_dir = "(.*)"', lambda m: f'models_dir = "{(cells / m[1]).resolve()}"', text, flags=re.M)
    text = text.replace('host = "127.0.0.50"', f'host = "{host}"').replace("seed = 0", f"seed = {SEED}")
    text = re.sub(r"^scene = .*$", 'scene = "scene.json"', text, flags=re.MULTILINE)
    assert f'host = "{host}"' in text and 'scene = "scene.json"' in text
    (folder / "cell.toml").write_text(text)
    return folder / "cell.toml"


@pytest.mark.slow
@pytest.mark.timeout(400)
@pytest.mark.parametrize("signum, host", [(signal.SIGINT, "127.0.0.81"), (signal.SIGTERM, "127.0.0.82")])
def test_a_signal_stops_the_arm_and_keeps_the_report(tmp_path, signum, host):
    out = tmp_path / "out"
    proc = subprocess.Popen(
        [sys.executable, "-m", "launch.cli", "pick", "--config", str(_cell_file(tmp_path, host)),
         "--perception", "oracle", "--out", str(out)],
        cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    lines: queue.Queue[str | None] = queue.Queue()
    threading.Thread(target=lambda: [*map(lines.put, proc.stdout), lines.put(None)], daemon=True).start()
    text: list[str] = []
    try:
        deadline = time.monotonic() + 300.0
        while time.monotonic() < deadline:
            line = lines.get(timeout=max(deadline - time.monotonic(), 0.1))
            if line is None:
                break
            text.append(line)
            if "robot.picker: cycle 0: " in line:
                break
        assert any("robot.picker: cycle 0: " in t for t in text), "".join(text)
        time.sleep(1.5)  # into the next cycle: its look and plan, then the arm moves in
        proc.send_signal(signum)
        proc.wait(timeout=90.0)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    while (line := lines.get(timeout=10.0)) is not None:
        text.append(line)
    log = "".join(text)
    name = signal.Signals(signum).name
    assert proc.returncode == 128 + signum, log
    assert f"sygrid pick: interrupted by {name} (exit code {128 + signum})" in log
    assert f"stopped: interrupted (stop requested ({name}): stopped " in log  # where it stopped
    report = json.loads((out / "pick_report.json").read_text())
    assert report["stop_reason"] == "interrupted" and report["stop_detail"].startswith(f"stop requested ({name})")
    cycles = report["cycles"]
    assert len(cycles) >= 1 and cycles[0]["end"] not in (None, "interrupted")  # the finished cycle is kept
    assert all(c["end"] != "interrupted" for c in cycles[:-1]) and [c["index"] for c in cycles] == [*range(len(cycles))]
    assert report["n_attempts"] == sum(len(c["attempts"]) for c in cycles)
    if cycles[-1]["end"] == "interrupted":
        assert cycles[-1]["interrupted_in"]
    emulator_log = (out / "emulator.log").read_text()
    assert re.search(r"rtde_control: stop[LJ] \(decel [0-9.e+-]+\) received", emulator_log), emulator_log[-3000:]
    assert (out / "pick_report.png").stat().st_size > 0
