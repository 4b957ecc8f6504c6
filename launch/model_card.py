"""Model cards (``*.card.md`` in a model folder): sections that later commands rewrite in place."""

from __future__ import annotations

from pathlib import Path

from sygrid.fileio import write_bytes_atomic


def replace_card_section(card_path: Path, heading: str, lines: list[str]) -> None:
    """Puts ``lines`` (a section starting with its ``heading`` line) at the end of the model card, replacing that
    section and everything after it from an earlier run; a missing card is started with a title."""
    card = card_path.read_text() if card_path.is_file() else f"# Model card: {card_path.name.split('.')[0]}\n"
    card = card.split(heading)[0].rstrip("\n") + "\n\n"
    write_bytes_atomic(card_path, ("\n".join([card.rstrip("\n"), "", *lines]) + "\n").encode())
