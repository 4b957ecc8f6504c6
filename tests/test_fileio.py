"""``sygrid.fileio``'s atomic writers give their files the mode an ordinary write would (``0o666`` less the umask),
not the temporary file's ``0o600``: datasets, poses and reports are readable by the group and others by default."""

from __future__ import annotations

import os
import stat
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from sygrid.fileio import current_umask, write_bytes_atomic, write_json_atomic


@pytest.fixture
def umask():
    """Sets the process's umask for a test (``umask(value)``) and restores it."""
    previous = os.umask(0o022)
    os.umask(previous)
    yield os.umask
    os.umask(previous)


def _mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


@pytest.mark.parametrize("mask, mode", [(0o022, 0o644), (0o002, 0o664), (0o077, 0o600), (0o000, 0o666)])
def test_atomic_writes_follow_the_umask(tmp_path, umask, mask, mode):
    umask(mask)
    assert current_umask() == mask
    assert _mode(write_bytes_atomic(tmp_path / "a.bin", b"x")) == mode
    assert _mode(write_json_atomic(tmp_path / "sub" / "b.json", {"k": 1})) == mode
    path = tmp_path / "a.bin"
    os.chmod(path, 0o600)
    assert _mode(write_bytes_atomic(path, b"y")) == mode and path.read_bytes() == b"y"  # a rewrite too
    assert not list(tmp_path.rglob("*.tmp"))


def test_the_pick_report_is_0644_under_the_default_umask(tmp_path, umask):
    from launch.pick import SceneShot, write_report
    from robot.pick_report import RunReport

    umask(0o022)
    setup = SimpleNamespace(path=tmp_path / "cell.toml")
    json_path, png_path = write_report(RunReport([], "bin_empty"), tmp_path, SceneShot(), np.eye(4), setup, "x", {})
    assert _mode(json_path) == 0o644 and _mode(png_path) == 0o644
