"""Imports run one way, floor by floor, and never in a circle:

    kit <- comms <- trust <- cli <- policy <- firmware <- agent <- groundstation <- recording <- tools

`kit` (helpers that import nothing of covey) is the ground floor and `comms` (the wire) the
first; a package imports only from the floors below it, and not even all of those
(`policy` never needs `trust`, `groundstation` never imports `agent` or `firmware`; `agent`
imports `firmware` for its C guidance core alone). Every import counts,
also one inside a function or under TYPE_CHECKING. docs/architecture.md draws the imports seen
here (tests/test_architecture_doc.py checks it)."""

from __future__ import annotations

import ast
from collections.abc import Iterable
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent

MAY_IMPORT: dict[str, frozenset[str]] = {
    "kit": frozenset({"kit"}),
    "comms": frozenset({"kit", "comms"}),
    "trust": frozenset({"kit", "comms", "trust"}),
    "cli": frozenset({"kit", "comms", "trust", "cli"}),
    "policy": frozenset({"kit", "comms", "cli", "policy"}),
    "firmware": frozenset({"kit", "comms", "cli", "policy", "firmware"}),
    "agent": frozenset({"kit", "comms", "trust", "cli", "policy", "firmware", "agent"}),
    "groundstation": frozenset({"kit", "comms", "trust", "cli", "policy", "groundstation"}),
    "recording": frozenset({"kit", "comms", "trust", "cli", "groundstation", "recording"}),
    "tools": frozenset(
        {"kit", "comms", "trust", "cli", "policy", "agent", "groundstation", "recording", "tools"}
    ),
}
"""Which of covey's own top-level packages each package may import."""
OURS = frozenset(MAY_IMPORT) | {"bench", "covey_cli"}

# Circles allowed for now (none): an entry here must name a circle that still exists
# (test_no_import_circles fails while it names one that is gone).
KNOWN_CIRCLES: frozenset[frozenset[str]] = frozenset()
"""Module circles that exist today and are being removed; nothing may join them."""


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


def imported_names(source: str, module: str) -> list[str]:
    """Like `imported_modules`, plus `X.y` for every `from X import y` (y may be a module)."""
    out = [name for _, name in imported_modules(source, module)]
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.ImportFrom):
            base = module.split(".")[: -node.level] if node.level else []
            name = ".".join(base + ([node.module] if node.module else []))
            out += [f"{name}.{alias.name}" for alias in node.names]
    return out


def our_files(packages: Iterable[str] = sorted(OURS)) -> dict[str, Path]:
    """Dotted module name -> file, for every module of covey's own packages."""
    out = {}
    for package in packages:
        single = REPO / f"{package}.py"
        paths = [single] if single.exists() else sorted((REPO / package).rglob("*.py"))
        for path in paths:
            parts = path.relative_to(REPO).with_suffix("").parts
            if "build" in parts:
                continue
            out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
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


def package_imports() -> dict[str, set[str]]:
    """Package -> the other packages of MAY_IMPORT that its modules import (what is drawn in
    docs/architecture.md)."""
    seen: dict[str, set[str]] = {p: set() for p in MAY_IMPORT}
    for package in MAY_IMPORT:
        for path in sorted((REPO / package).rglob("*.py")):
            module = ".".join(path.relative_to(REPO).with_suffix("").parts)
            for _, name in imported_modules(path.read_text(), module):
                top = name.split(".")[0]
                if top in MAY_IMPORT and top != package:
                    seen[package].add(top)
    return seen


def module_graph() -> dict[str, set[str]]:
    """Module -> the modules of ours it imports, lazy imports included."""
    files = our_files()
    graph: dict[str, set[str]] = {}
    for module, path in files.items():
        own = module + ".__init__" if path.name == "__init__.py" else module
        deps = set()
        for name in imported_names(path.read_text(), own):
            while name and name not in files:
                name = name.rpartition(".")[0]
            if name and name != module and not module.startswith(name + "."):
                deps.add(name)
        graph[module] = deps
    return graph


def circles(graph: dict[str, set[str]]) -> list[frozenset[str]]:
    """The strongly connected components of more than one node (Tarjan, iteratively)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found = []
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph.get(child, ())))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                comp = set()
                while True:
                    top = stack.pop()
                    on_stack.discard(top)
                    comp.add(top)
                    if top == node:
                        break
                if len(comp) > 1:
                    found.append(frozenset(comp))
    return found


@pytest.mark.parametrize("package", sorted(MAY_IMPORT))
def test_imports_run_downward(package: str) -> None:
    bad = violations(package)
    assert not bad, f"{package}/ may import only {sorted(MAY_IMPORT[package])}:\n" + "\n".join(bad)


def test_floors_have_no_circle() -> None:
    graph = {p: set(allowed) - {p} for p, allowed in MAY_IMPORT.items()}
    assert circles(graph) == []
    assert all((REPO / p / "__init__.py").exists() for p in MAY_IMPORT)


def test_no_import_circles() -> None:
    found = set(circles(module_graph()))
    new = [sorted(c) for c in found - KNOWN_CIRCLES]
    assert not new, f"import circles: {new}"
    gone = [sorted(c) for c in KNOWN_CIRCLES - found]
    assert not gone, f"no longer circles, remove them from KNOWN_CIRCLES: {gone}"


def test_circles_are_found() -> None:
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a", "e"}, "e": {"d"}, "f": set()}
    assert sorted(sorted(c) for c in circles(graph)) == [["a", "b", "c"], ["d", "e"]]
    assert circles({"a": {"b"}, "b": set()}) == []


def test_every_package_is_installed() -> None:
    """pyproject's package list names every package here, so a wheel holds them all."""
    text = (REPO / "pyproject.toml").read_text()
    missing = [p for p in MAY_IMPORT if f'"{p}*"' not in text]
    assert not missing, f"pyproject.toml [tool.setuptools.packages.find] lacks {missing}"


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
    assert "firmware.sitl.emulator" in imported_names(source, "comms.sub.mod")
