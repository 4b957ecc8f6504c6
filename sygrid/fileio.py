"""File I/O at the edges: crash-safe writes (a reader sees the old file or the new one, never half of one) and JSON
reading with errors that name the file."""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any

from sygrid.errors import ConfigError

CACHE_ENV = "SYGRID_CACHE_DIR"  # the root shared by the project's on-disk caches


def cache_dir_for(kind: str, cache_dir: str | Path | None = None) -> Path:
    """The cache folder of ``kind`` (e.g. "collision", "grasps"): ``cache_dir`` when given, else
    ``$SYGRID_CACHE_DIR/<kind>``, else ``~/.cache/sygrid/<kind>``. The environment is read at each call, never at
    import."""
    if cache_dir is not None:
        return Path(cache_dir).expanduser()
    root = os.environ.get(CACHE_ENV)
    if root:
        return Path(root).expanduser() / kind
    return Path.home() / ".cache" / "sygrid" / kind


def current_umask() -> int:
    """The process's file mode creation mask, read without changing it (``/proc/self/status`` on Linux; elsewhere
    set and restored at once, which is not atomic against other threads creating files)."""
    try:
        with open("/proc/self/status", encoding="ascii") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def write_bytes_atomic(path: str | Path, payload: bytes) -> Path:
    """Bytes to ``path`` through a temporary file in the same folder, fsync, and an atomic rename. The file gets
    the mode an ordinary ``open(path, "w")`` would give it (``0o666`` less the process's umask), not the
    temporary file's ``0o600``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            os.fchmod(f.fileno(), 0o666 & ~current_umask())
            f.write(payload)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def remove_stale_temporaries(root: str | Path) -> list[Path]:
    """Removes the temporary files (``.NAME.XXXXXXXX.tmp``) that ``write_bytes_atomic`` leaves when its process is
    killed between creating one and renaming it; returns them. Only for a folder no other process is writing to."""
    stale = [p for p in Path(root).rglob(".*.tmp") if p.is_file()]
    for path in stale:
        path.unlink(missing_ok=True)
    return stale


def write_json_atomic(path: str | Path, data: object, indent: int | None = 1) -> Path:
    return write_bytes_atomic(path, json.dumps(data, indent=indent).encode())


def read_json(path: str | Path, what: str) -> Any:
    """Parses a JSON file; unreadable files and syntax errors raise ConfigError naming the file and the position."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the {what} ({exc.strerror})") from None
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise ConfigError(f"{path}: not valid JSON at line {exc.lineno} column {exc.colno}: {exc.msg}") from None
