"""Model card sections that later commands rewrite in place (``perception.model_card``)."""

from __future__ import annotations

from pathlib import Path

from perception.model_card import replace_card_section


def test_a_card_section_is_replaced_not_repeated(tmp_path: Path):
    card = tmp_path / "pose.card.md"
    card.write_text("# Model card: pose\n\nkept text\n")
    replace_card_section(card, "### Pose strategies per part", ["### Pose strategies per part", "", "first run"])
    replace_card_section(card, "### Pose strategies per part", ["### Pose strategies per part", "", "second run"])
    text = card.read_text()
    assert text.count("### Pose strategies per part") == 1 and "second run" in text and "first run" not in text
    assert text.startswith("# Model card: pose\n\nkept text\n")
    replace_card_section(tmp_path / "new.card.md", "### A", ["### A", "x"])
    assert (tmp_path / "new.card.md").read_text() == "# Model card: new\n\n### A\nx\n"


def test_the_sections_after_a_replaced_one_stay_and_code_blocks_hold_no_headings(tmp_path: Path):
    card = tmp_path / "detector.card.md"
    card.write_text("# Model card: d\n\n## Held-out test set: x\n\nfigures\n\n### Where it fails\n\nold table\n"
                    "```\n# not a heading\n## nor this\n```\n\n## Transfer\n\nmatrix\n")  # fmt: skip
    replace_card_section(card, "### Where it fails", ["### Where it fails", "", "new table"])
    assert card.read_text() == ("# Model card: d\n\n## Held-out test set: x\n\nfigures\n\n### Where it fails\n\n"
                                "new table\n\n## Transfer\n\nmatrix\n")  # fmt: skip
    replace_card_section(card, "## Held-out test set: ", ["## Held-out test set: y", "", "all new"])
    assert card.read_text() == "# Model card: d\n\n## Held-out test set: y\n\nall new\n\n## Transfer\n\nmatrix\n"
