"""docs/architecture.md draws the imports between covey's packages that the code really has:
its arrow list (`a -> b, c`) equals what tests/test_import_layers.py sees, both ways."""

from __future__ import annotations

import re

from test_import_layers import MAY_IMPORT, REPO, package_imports

DOC = REPO / "docs" / "architecture.md"
ARROW = re.compile(r"^(\w+) -> (\w+(?:, \w+)*)$")


def drawn_arrows(text: str) -> dict[str, set[str]]:
    """Package -> the packages its `a -> b, c` lines name, from the fenced blocks of `text`."""
    out: dict[str, set[str]] = {}
    blocks = re.findall(r"^```[^\n]*\n(.*?)^```", text, re.S | re.M)
    for line in "\n".join(blocks).splitlines():
        m = ARROW.match(line.strip())
        if m:
            out.setdefault(m[1], set()).update(m[2].split(", "))
    return out


def test_the_arrows_are_parsed() -> None:
    text = "x\n```\ncomms -> kit\n  agent -> comms, kit\nnot -> an arrow!\n```\nfoo -> bar\n"
    assert drawn_arrows(text) == {"comms": {"kit"}, "agent": {"comms", "kit"}}


def test_the_doc_draws_the_imports_the_code_has() -> None:
    drawn = drawn_arrows(DOC.read_text())
    real = {p: deps for p, deps in package_imports().items() if deps}
    named = set(drawn) | {d for deps in drawn.values() for d in deps}
    unknown = sorted(named - set(MAY_IMPORT))
    assert not unknown, f"docs/architecture.md names packages that are not covey's: {unknown}"
    missing = sorted(f"{p} -> {d}" for p, deps in real.items() for d in deps - drawn.get(p, set()))
    invented = sorted(f"{p} -> {d}" for p, deps in drawn.items() for d in deps - real.get(p, set()))
    assert not missing, f"imports that docs/architecture.md does not draw: {missing}"
    assert not invented, f"arrows in docs/architecture.md that no import makes: {invented}"
