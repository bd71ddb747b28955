"""The package's layers: the doors (``geocd.cli``, ``geocd.pipeline``) sit above every method; no method imports them.

A method that imports a door drags the command line (or the whole run) into every use of it, and makes import
cycles through the doors possible. Imports are read from the source (function-local ones included).
"""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "geocd"
DOORS = ("geocd.cli", "geocd.pipeline", "geocd.__main__")


def _module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imported(path: Path) -> set[str]:
    """Absolute names of the modules ``path`` imports (``from . import x`` gives the package and ``package.x``)."""
    name = _module_name(path)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            out.add(mod)
            out.update(f"{mod}.{a.name}" for a in node.names)
    return out


def _is_door(module: str) -> bool:
    return any(module == d or module.startswith(d + ".") for d in DOORS)


def test_no_method_imports_a_door():
    offenders = []
    for path in sorted(PACKAGE.rglob("*.py")):
        if _is_door(_module_name(path)):
            continue
        bad = sorted(m for m in _imported(path) if _is_door(m))
        if bad:
            offenders.append(f"{path.relative_to(PACKAGE.parent)}: {', '.join(bad)}")
    assert not offenders, "methods import a door:\n" + "\n".join(offenders)


def test_the_check_sees_relative_and_local_imports():
    """geocd/mpp/pipeline.py's ``from ..io.manifest import pick_epochs`` (inside a function) and ``from ..errors
    import ConfigError`` (at the top) resolve to geocd's absolute names."""
    names = _imported(PACKAGE / "mpp" / "pipeline.py")
    assert {"geocd.io.manifest.pick_epochs", "geocd.errors.ConfigError"} <= names
    assert _is_door("geocd.pipeline") and _is_door("geocd.cli.common") and not _is_door("geocd.pipelines")


def _import_graph() -> dict[str, set[str]]:
    """geocd's modules and the geocd modules each imports (function-local imports included; a name imported from
    a module counts as that module)."""
    mods = {_module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}
    graph: dict[str, set[str]] = {}
    for m, p in mods.items():
        graph[m] = set()
        for name in _imported(p):
            while name and name not in mods:
                name = name.rpartition(".")[0]
            if name and name != m and not m.startswith(name + "."):  # a module's own packages: imported first anyway
                graph[m].add(name)
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_no_import_cycles():
    """No two geocd modules import each other, directly or through others, even inside functions: a cycle makes
    the import order matter and hides which layer a module belongs to."""
    assert _cycles(_import_graph()) == []


def test_the_cycle_check_finds_a_cycle():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []
