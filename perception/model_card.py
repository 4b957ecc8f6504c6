"""Model cards (``*.card.md`` in a model folder): sections that later commands rewrite in place."""

from __future__ import annotations

import shlex
import sys
from pathlib import Path

from sygrid.fileio import write_bytes_atomic


def invoked_command(fallback: str) -> str:
    """The ``sygrid`` command line this process was started with, for a card or a report to name; ``fallback``
    where it was called without arguments (from Python)."""
    return "sygrid " + shlex.join(sys.argv[1:]) if sys.argv[1:] else fallback


def replace_card_section(card_path: Path, heading: str, lines: list[str]) -> None:
    """Puts ``lines`` (a section starting with its ``heading`` line) into the model card: in place of the section
    whose heading line starts with ``heading`` (up to the next heading of the same or a higher level outside code
    blocks, so that later sections stay), else at the end; a missing card is started with a title."""
    text = card_path.read_text() if card_path.is_file() else f"# Model card: {card_path.name.split('.')[0]}\n"
    old = text.rstrip("\n").split("\n")
    levels = _heading_levels(old)
    start = next((i for i, line in enumerate(old) if levels[i] and line.startswith(heading)), None)
    if start is None:
        new = [*old, "", *lines]
    else:
        end = next((j for j in range(start + 1, len(old)) if 0 < levels[j] <= levels[start]), len(old))
        before = old[:start]
        while before and not before[-1]:
            before.pop()
        new = [*before, "", *lines, *([""] if end < len(old) else []), *old[end:]]
    write_bytes_atomic(card_path, ("\n".join(new) + "\n").encode())


def _heading_levels(lines: list[str]) -> list[int]:
    """Per line its markdown heading level (``## x``: 2), 0 for other lines and for lines inside fenced code."""
    levels, fenced = [], False
    for line in lines:
        if line.startswith("```"):
            fenced = not fenced
        hashes = len(line) - len(line.lstrip("#"))
        levels.append(hashes if not fenced and hashes and line[hashes : hashes + 1] == " " else 0)
    return levels
