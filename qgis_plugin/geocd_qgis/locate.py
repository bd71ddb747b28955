"""Find the user's geocd environment (plain Python: no ``qgis`` import).

geocd runs out of process, from its own Python environment: pip wheels of
rasterio/pyproj carry their own GDAL and PROJ, which crash when loaded into the
QGIS process beside QGIS's builds. The plugin therefore only needs to know how
to start ``geocd``. In order, it uses:

1. the path configured in Processing ▸ Options ▸ Providers ▸ geocd ▸ "geocd executable";
2. the ``GEOCD_EXECUTABLE`` environment variable;
3. ``environment.json`` written into the plugin by ``geocd plugin-zip`` (the environment that built the zip);
4. ``geocd`` on ``PATH``;
5. known virtual environments: the ``.venv`` of the geocd checkout the plugin sits in, ``~/.venvs/geocd``,
   ``~/geocd/.venv``, ``~/.local/bin`` and conda environments named ``geocd``.

A configured path may be the ``geocd`` script or the environment's Python
interpreter (then ``python -m geocd`` is run).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Optional

PLUGIN_DIR = Path(__file__).resolve().parent
ENV_VAR = "GEOCD_EXECUTABLE"
HINT_FILE = PLUGIN_DIR / "environment.json"

INSTALL_HELP = (
    "Install geocd into a Python environment of its own, e.g.\n"
    "    python3 -m venv ~/.venvs/geocd && ~/.venvs/geocd/bin/pip install geocd\n"
    "(or `pip install -e .` in a geocd checkout), then either put its `geocd` on PATH, set the environment "
    'variable GEOCD_EXECUTABLE, or set Processing ▸ Options ▸ Providers ▸ geocd ▸ "geocd executable" to the '
    "path of `geocd` (or of that environment's python)."
)

_IS_WIN = sys.platform.startswith("win")


def _bin(venv: Path, name: str) -> Path:
    return venv / ("Scripts" if _IS_WIN else "bin") / (name + (".exe" if _IS_WIN else ""))


def command_for(path: str | os.PathLike) -> list[str]:
    """argv prefix that starts geocd from ``path`` (the geocd script, or a Python interpreter)."""
    p = Path(path)
    if p.name.lower().startswith("python"):
        return [str(p), "-m", "geocd"]
    return [str(p)]


def _usable(path: Path) -> bool:
    return path.is_file() and os.access(path, os.X_OK)


def candidates(configured: Optional[str] = None) -> list[tuple[str, Path]]:
    """(source, path) of every place geocd may be, in order of preference (not yet checked)."""
    out: list[tuple[str, Path]] = []
    if configured and str(configured).strip():
        out.append(("Processing settings", Path(str(configured).strip()).expanduser()))
    env = os.environ.get(ENV_VAR, "").strip()
    if env:
        out.append((f"${ENV_VAR}", Path(env).expanduser()))
    if HINT_FILE.is_file():
        try:
            hint = json.loads(HINT_FILE.read_text(encoding="utf-8"))
            for key in ("geocd", "python"):
                if hint.get(key):
                    out.append((f"{HINT_FILE.name} ({key})", Path(hint[key])))
        except (OSError, ValueError):
            pass
    which = shutil.which("geocd")
    if which:
        out.append(("PATH", Path(which)))
    home = Path.home()
    # the plugin inside a geocd checkout: <repo>/qgis_plugin/geocd_qgis
    repo = PLUGIN_DIR.parent.parent
    venvs = [
        repo / ".venv",
        repo / "venv",
        home / ".venvs" / "geocd",
        home / "geocd" / ".venv",
        home / "venvs" / "geocd",
    ]
    for conda in ("miniconda3", "miniforge3", "mambaforge", "anaconda3", ".conda"):
        venvs.append(home / conda / "envs" / "geocd")
    for v in venvs:
        out.append((f"venv {v}", _bin(v, "geocd")))
    out.append(("~/.local/bin", home / ".local" / "bin" / "geocd"))
    return out


def find_geocd(configured: Optional[str] = None) -> Optional[tuple[list[str], str]]:
    """(argv prefix, source) of the first usable geocd, or None."""
    for source, path in candidates(configured):
        if _usable(path):
            return command_for(path), source
        if source == "Processing settings" or source.startswith("$"):
            # an explicit setting that does not work is an error worth reporting, not skipping silently
            return None
    return None


def child_env(base: Optional[dict] = None) -> dict:
    """Environment for the geocd child: the host's, minus what belongs to QGIS's own Python, GDAL and PROJ.

    QGIS may set PYTHONPATH/PYTHONHOME (its Python), GDAL_DATA/PROJ_LIB/PROJ_DATA (its GDAL and PROJ
    builds); geocd's wheels bring their own data, and a different version's proj.db breaks them.
    """
    env = dict(os.environ if base is None else base)
    for k in (
        "PYTHONPATH",
        "PYTHONHOME",
        "PYTHONSTARTUP",
        "PYTHONEXECUTABLE",
        "PYTHONNOUSERSITE",
        "GDAL_DATA",
        "GDAL_DRIVER_PATH",
        "PROJ_LIB",
        "PROJ_DATA",
        "QGIS_PREFIX_PATH",
    ):
        env.pop(k, None)
    env["PYTHONUNBUFFERED"] = "1"
    env["PYTHONIOENCODING"] = "utf-8"
    return env


_VERSION_CACHE: dict[tuple, Optional[str]] = {}


def geocd_version(argv: list[str], timeout_s: float = 60.0) -> Optional[str]:
    """``geocd --version`` (cached per argv), e.g. ``"0.1.0"``; None when it does not run."""
    key = tuple(argv)
    if key not in _VERSION_CACHE:
        try:
            r = subprocess.run(
                [*argv, "--version"],
                capture_output=True,
                text=True,
                timeout=timeout_s,
                env=child_env(),
                stdin=subprocess.DEVNULL,
            )
            text = (r.stdout or r.stderr).strip()
            _VERSION_CACHE[key] = text.split()[-1] if r.returncode == 0 and text else None
        except (OSError, subprocess.SubprocessError):
            _VERSION_CACHE[key] = None
    return _VERSION_CACHE[key]


def cached_version() -> Optional[str]:
    """The geocd version found by the last successful check (no child process started), else None."""
    for v in _VERSION_CACHE.values():
        if v:
            return v
    return None


def check_geocd(configured: Optional[str] = None) -> tuple[Optional[list[str]], str]:
    """(argv prefix or None, message): a runnable geocd, or why there is none and how to install it."""
    found = find_geocd(configured)
    if found is None:
        explicit = [(s, p) for s, p in candidates(configured)[:2] if s == "Processing settings" or s.startswith("$")]
        if explicit:
            s, p = explicit[0]
            return None, (
                f"the geocd executable set in {s} ({p}) does not exist or is not executable; "
                f"fix the path, or clear it to let the plugin search. " + INSTALL_HELP
            )
        return None, "geocd was not found. " + INSTALL_HELP
    argv, source = found
    version = geocd_version(argv)
    if version is None:
        return None, (
            f"{' '.join(argv)} (found via {source}) does not run (`--version` failed); "
            f"check that environment. " + INSTALL_HELP
        )
    return argv, f"geocd {version} ({' '.join(argv)}, via {source})"
