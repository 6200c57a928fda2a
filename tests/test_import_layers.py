"""Imports run one way: comms <- policy <- agent <- groundstation and tools; firmware sits
beside agent. Every import counts, also one inside a function or under TYPE_CHECKING."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent

MAY_IMPORT: dict[str, frozenset[str]] = {
    "comms": frozenset({"comms"}),
    "policy": frozenset({"comms", "policy"}),
    "agent": frozenset({"comms", "policy", "agent"}),
    "firmware": frozenset({"comms", "policy", "firmware"}),
    "groundstation": frozenset({"comms", "policy", "groundstation"}),
    "tools": frozenset({"comms", "policy", "agent", "groundstation", "tools"}),
}
"""Which of covey's own top-level packages each package may import."""
OURS = frozenset(MAY_IMPORT) | {"bench", "covey_cli"}


def imported_modules(source: str, module: str) -> list[tuple[int, str]]:
    """(line, absolute module name) of every import in `source`, at any depth. `module` is the
    dotted name of the file's own module (for relative imports)."""
    out = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            out += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = module.split(".")[: -node.level]
                name = ".".join(base + ([node.module] if node.module else []))
            else:
                name = node.module or ""
            out.append((node.lineno, name))
    return out


def violations(package: str) -> list[str]:
    allowed = MAY_IMPORT[package]
    found = []
    for path in sorted((REPO / package).rglob("*.py")):
        rel = path.relative_to(REPO)
        module = ".".join(rel.with_suffix("").parts)
        for line, name in imported_modules(path.read_text(), module):
            top = name.split(".")[0]
            if top in OURS and top not in allowed:
                found.append(f"{rel}:{line} imports {name}")
    return found


@pytest.mark.parametrize("package", sorted(MAY_IMPORT))
def test_imports_run_downward(package: str) -> None:
    bad = violations(package)
    assert not bad, f"{package}/ may import only {sorted(MAY_IMPORT[package])}:\n" + "\n".join(bad)


def test_imports_inside_functions_and_relative_ones_are_seen() -> None:
    source = (
        "import comms.schema\n"
        "def f():\n"
        "    from firmware.sitl import emulator\n"
        "if TYPE_CHECKING:\n"
        "    import agent.app as a\n"
        "from . import keys\n"
        "from ..policy import runtime\n"
    )
    got = sorted(imported_modules(source, "comms.sub.mod"))
    assert got == [
        (1, "comms.schema"),
        (3, "firmware.sitl"),
        (5, "agent.app"),
        (6, "comms.sub"),
        (7, "comms.policy"),
    ]
