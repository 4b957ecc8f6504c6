"""The on-disk cache of grasp candidates: where it lives, and one entry per file, read back only under its key.

An entry is an ``.npz`` of named arrays plus the key it was written under (the caller's hash of everything the
arrays depend on); it is written atomically. An entry that is missing, unreadable or written under another key reads
as None (a warning for the last two), so a broken cache costs a rebuild, never the result; a folder that cannot be
written costs the next rebuild.
"""

from __future__ import annotations

import io
import logging
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import TypeVar

import numpy as np

from sygrid.fileio import cache_dir_for, write_bytes_atomic

log = logging.getLogger(__name__)


T = TypeVar("T")


def resolve_cache_dir(cache_dir: Path | str | None = None) -> Path:
    """The grasp cache folder (``sygrid.fileio.cache_dir_for("grasps", cache_dir)``)."""
    return cache_dir_for("grasps", cache_dir)


def save_entry(path: Path, key: str, arrays: Mapping[str, np.ndarray]) -> None:
    """Writes ``arrays`` (names as given, plus ``key``) to ``path`` atomically; a failed write is logged, not
    raised."""
    buffer = io.BytesIO()
    np.savez(buffer, key=np.array(key), **arrays)
    try:
        write_bytes_atomic(path, buffer.getvalue())
    except OSError as exc:  # a read-only or full cache folder costs a rebuild next time, not the result
        log.warning("could not write the grasp cache entry %s: %s", path, exc)
        return
    log.debug("wrote grasp cache entry %s", path)


def load_entry(path: Path, key: str, build: Callable[[Mapping[str, np.ndarray]], T]) -> T | None:
    """``build`` applied to the arrays stored at ``path`` under ``key``; None when there is no such file, or when it
    cannot be read, was stored under another key, or ``build`` raises ``KeyError`` or ``ValueError`` on it."""
    if not path.exists():
        return None
    try:
        with np.load(path, allow_pickle=False) as npz:
            if str(npz["key"]) != key:
                raise ValueError("the key stored in the file does not match its name")
            return build(npz)
    except (OSError, ValueError, KeyError) as exc:
        log.warning("ignoring the unreadable grasp cache entry %s (%s); rebuilding it", path, exc)
        return None
