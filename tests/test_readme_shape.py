"""README.md stays a page for users: short, no histories or issue numbers, table cells of a
sentence at most, and every number it quotes is one the benchmarks or docs/ record."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"
MAX_LINES = 200
MAX_CELL_CHARS = 160  # about one sentence
NUMBER = re.compile(r"(?<![\w.])\d[\d,]*(?:\.\d+)?")


def prose(text: str) -> str:
    """The README without its code, fenced or inline (commands and inputs, not claims)."""
    return re.sub(r"`[^`\n]*`", "", re.sub(r"```.*?```", "", text, flags=re.S))


def recorded_numbers_text() -> str:
    parts = [(ROOT / "bench" / "results" / "SUMMARY.md").read_text(encoding="utf-8")]
    parts += [p.read_text(encoding="utf-8") for p in sorted((ROOT / "docs").glob("*.md"))]
    parts.append((ROOT / "firmware" / "README.md").read_text(encoding="utf-8"))
    return "\n".join(parts)


def unrecorded(readme: str, recorded: str) -> list[str]:
    """Numbers in the README's prose that appear nowhere in SUMMARY.md, docs/ or firmware/."""
    found = set(NUMBER.findall(prose(readme)))
    return sorted(n for n in found if not re.search(rf"(?<![\w.]){re.escape(n)}(?![\d])", recorded))


def test_readme_is_at_most_200_lines():
    assert len(README.read_text(encoding="utf-8").splitlines()) <= MAX_LINES


def test_readme_names_no_issue_numbers():
    hits = re.findall(r"\bissues? \d+", README.read_text(encoding="utf-8"), flags=re.I)
    assert hits == []


def test_readme_table_cells_are_short():
    long_cells = [
        cell.strip()
        for line in README.read_text(encoding="utf-8").splitlines()
        if line.startswith("|")
        for cell in line.strip("|").split("|")
        if len(cell.strip()) > MAX_CELL_CHARS
    ]
    assert long_cells == []


def test_every_number_in_the_readme_is_recorded():
    assert unrecorded(README.read_text(encoding="utf-8"), recorded_numbers_text()) == []


def test_the_number_check_can_fail():
    assert unrecorded("took 123,457.5 ms", "took 123,456.5 ms") == ["123,457.5"]
    assert unrecorded("took 4.5 ms to `goto 7`\n```\nrun 99\n```", "4.5") == []
