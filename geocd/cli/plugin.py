"""``geocd plugin-zip``: build the installable QGIS plugin zip (Plugins ▸ Manage and Install ▸ Install from ZIP)."""

from __future__ import annotations

import json
import sys
import zipfile
from pathlib import Path

import click

PLUGIN_NAME = "geocd_qgis"
_SKIP_DIRS = {"__pycache__", ".pytest_cache", ".mypy_cache"}
_SKIP_SUFFIXES = {".pyc", ".pyo", ".orig", ".rej", ".swp"}
_REQUIRED_METADATA = ("name", "qgisMinimumVersion", "description", "about", "version", "author", "email",
                      "repository")


def plugin_source_dir() -> Path:
    """``qgis_plugin/geocd_qgis`` of the geocd checkout this package runs from."""
    from ..errors import InputFileNotFoundError

    here = Path(__file__).resolve()
    for root in here.parents:
        cand = root / "qgis_plugin" / PLUGIN_NAME
        if (cand / "metadata.txt").is_file():
            return cand
    raise InputFileNotFoundError(
        "the QGIS plugin sources (qgis_plugin/geocd_qgis) are not beside this geocd installation; "
        "run `geocd plugin-zip` from a geocd source checkout installed with `pip install -e .`")


def read_metadata(plugin_dir: Path) -> dict[str, str]:
    import configparser

    cp = configparser.ConfigParser(interpolation=None)
    cp.optionxform = str  # keep the keys' case (qgisMinimumVersion)
    cp.read(plugin_dir / "metadata.txt", encoding="utf-8")
    return dict(cp["general"]) if cp.has_section("general") else {}


def _geocd_executable() -> str | None:
    """The ``geocd`` script of the running environment (beside its python), if present."""
    exe = Path(sys.executable)
    for cand in (exe.parent / "geocd", exe.parent / "geocd.exe", exe.parent / "Scripts" / "geocd.exe"):
        if cand.is_file():
            return str(cand)
    return None


def build_plugin_zip(out: str | Path | None = None, *, environment_hint: bool = True) -> Path:
    """Write the plugin zip (one top folder ``geocd_qgis/``) atomically; return its path.

    With ``environment_hint``, ``geocd_qgis/environment.json`` records this environment's ``geocd`` and python,
    so the installed plugin finds geocd without configuration on this machine.
    """
    from .. import __version__
    from ..errors import ConfigError
    from ..io.atomic import atomic_path

    src = plugin_source_dir()
    meta = read_metadata(src)
    missing = [k for k in _REQUIRED_METADATA if not meta.get(k)]
    if missing:
        raise ConfigError(f"{src / 'metadata.txt'} lacks {', '.join(missing)}; add them to its [general] section")
    if meta.get("hasProcessingProvider", "").lower() != "yes":
        raise ConfigError(f"{src / 'metadata.txt'} must say hasProcessingProvider=yes")
    version = meta["version"]
    if version != __version__:
        raise ConfigError(f"plugin version {version} (metadata.txt) differs from geocd {__version__}; "
                          "bump both together")
    out_path = Path(out) if out else Path("dist") / f"{PLUGIN_NAME}-{version}.zip"
    if out_path.suffix.lower() != ".zip":
        out_path = out_path / f"{PLUGIN_NAME}-{version}.zip" if out_path.is_dir() else out_path.with_suffix(".zip")
    files = sorted(p for p in src.rglob("*")
                   if p.is_file() and not (set(p.relative_to(src).parts) & _SKIP_DIRS)
                   and p.suffix not in _SKIP_SUFFIXES and p.name != "environment.json")
    with atomic_path(out_path) as tmp:
        with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_DEFLATED) as zf:
            for p in files:
                zf.write(p, f"{PLUGIN_NAME}/{p.relative_to(src).as_posix()}")
            if environment_hint:
                hint = {"geocd": _geocd_executable(), "python": sys.executable, "version": __version__}
                zf.writestr(f"{PLUGIN_NAME}/environment.json", json.dumps(hint, indent=2) + "\n")
    return out_path


@click.command("plugin-zip")
@click.option("--out", "out", type=click.Path(path_type=str), default=None,
              help="Zip file to write (default: dist/geocd_qgis-VERSION.zip).")
@click.option("--no-environment-hint", is_flag=True,
              help="Do not record this environment's geocd in the zip (for zips shared with other machines).")
@click.pass_context
def plugin_zip(ctx: click.Context, out: str | None, no_environment_hint: bool) -> None:
    """Build the QGIS plugin zip: install it with Plugins ▸ Manage and Install Plugins ▸ Install from ZIP.

    The plugin (Processing provider "geocd") runs this geocd installation as a child process; the zip records
    where it is unless --no-environment-hint is given.
    """
    from ..io.outputs import open_outputs
    from . import emit_result

    open_outputs(None, files=[out or "dist"])
    path = build_plugin_zip(out, environment_hint=not no_environment_hint)
    emit_result(ctx, {"plugin_zip": path})
