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
