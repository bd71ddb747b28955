"""``geocd plugin-zip`` and ``geocd plugin-install``: the QGIS plugin as a zip, a plugin repository, a headless install.

``geocd plugin-zip`` writes ``dist/geocd_qgis.VERSION.zip`` (QGIS's own naming) and, beside it, ``plugins.xml``: a QGIS plugin
repository file, so Plugins ▸ Manage and Install Plugins ▸ Settings ▸ Add… (URL ``file:///…/dist/plugins.xml``,
or ``http://host/…/plugins.xml`` when the folder is served) lists and installs geocd like any plugin.
``geocd plugin-install`` does that headless in one command, with QGIS's own installer code
(:mod:`geocd.cli.qgis_install`, run by the Python that has PyQGIS).
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import subprocess
import sys
import zipfile
from pathlib import Path
from xml.sax.saxutils import escape

import click

PLUGIN_NAME = "geocd_qgis"
_SKIP_DIRS = {"__pycache__", ".pytest_cache", ".mypy_cache"}
_SKIP_SUFFIXES = {".pyc", ".pyo", ".orig", ".rej", ".swp"}
_REQUIRED_METADATA = ("name", "qgisMinimumVersion", "description", "about", "version", "author", "email", "repository")


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
        "run `geocd plugin-zip` from a geocd source checkout installed with `pip install -e .`"
    )


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


def zip_name(version: str) -> str:
    """``geocd_qgis.VERSION.zip``: QGIS's naming of a plugin zip, the name plugins.xml gives it.

    QGIS's installer takes the plugin's id from the ``file_name`` of plugins.xml, up to its first dot, and installs
    the zip's top folder under that id: ``geocd_qgis-0.1.0.zip`` would make it ``geocd_qgis-0``.
    """
    return f"{PLUGIN_NAME}.{version}.zip"


def repository_file_name(zip_path: Path, version: str) -> str:
    """The ``file_name`` plugins.xml gives the zip: its own name when QGIS reads the plugin's id from it (the
    default ``geocd_qgis.VERSION.zip``, or ``geocd_qgis.zip``), else :func:`zip_name` (``--out p.zip``: the
    download URL still names p.zip)."""
    name = Path(zip_path).name
    return name if name.partition(".")[0] == PLUGIN_NAME else zip_name(version)


def zip_path(out: str | Path | None, version: str) -> Path:
    """Where ``geocd plugin-zip --out OUT`` writes the zip (OUT: a .zip file, or a folder; default dist/)."""
    out_path = Path(out) if out else Path("dist") / zip_name(version)
    if out_path.suffix.lower() != ".zip":
        is_dir = out_path.is_dir() or str(out).endswith(("/", os.sep)) or not out_path.suffix
        out_path = out_path / zip_name(version) if is_dir else out_path.with_suffix(".zip")
    return out_path


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
        raise ConfigError(
            f"plugin version {version} (metadata.txt) differs from geocd {__version__}; bump both together"
        )
    out_path = zip_path(out, version)
    files = sorted(
        p
        for p in src.rglob("*")
        if p.is_file()
        and not (set(p.relative_to(src).parts) & _SKIP_DIRS)
        and p.suffix not in _SKIP_SUFFIXES
        and p.name != "environment.json"
    )
    with atomic_path(out_path) as tmp:
        with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_DEFLATED) as zf:
            for p in files:
                zf.write(p, f"{PLUGIN_NAME}/{p.relative_to(src).as_posix()}")
            if environment_hint:
                hint = {"geocd": _geocd_executable(), "python": sys.executable, "version": __version__}
                zf.writestr(f"{PLUGIN_NAME}/environment.json", json.dumps(hint, indent=2) + "\n")
    return out_path


REPOSITORY_FILE = "plugins.xml"


def repository_xml(zip_path: Path, meta: dict[str, str], download_url: str) -> str:
    """A QGIS plugin repository document (``<plugins><pyqgis_plugin …>``) offering the plugin in ``zip_path``.

    ``file_name`` is the zip's own name (:func:`repository_file_name`): QGIS takes the plugin's id from the part
    before its first dot, and it must be the zip's top folder.
    """
    version = meta["version"]
    today = _dt.date.today().isoformat()
    fields = {
        "description": meta.get("description", ""),
        "about": meta.get("about", ""),
        "version": version,
        "qgis_minimum_version": meta.get("qgisMinimumVersion", "3.22"),
        "qgis_maximum_version": meta.get("qgisMaximumVersion", "3.99"),
        "homepage": meta.get("homepage", ""),
        "file_name": repository_file_name(zip_path, version),
        "icon": "",
        "author_name": meta.get("author", ""),
        "download_url": download_url,
        "uploaded_by": meta.get("author", ""),
        "create_date": today,
        "update_date": today,
        "experimental": meta.get("experimental", "False"),
        "deprecated": meta.get("deprecated", "False"),
        "tracker": meta.get("tracker", ""),
        "repository": meta.get("repository", ""),
        "tags": meta.get("tags", ""),
        "downloads": "0",
        "average_vote": "0",
        "rating_votes": "0",
        "external_dependencies": "",
        "server": meta.get("server", "False"),
    }
    body = "\n".join(f"    <{k}>{escape(' '.join(str(v).split()))}</{k}>" for k, v in fields.items())
    return (
        '<?xml version="1.0" encoding="UTF-8"?>\n<plugins>\n'
        f'  <pyqgis_plugin name="{escape(meta.get("name", PLUGIN_NAME))}" version="{escape(version)}" '
        f'plugin_id="{PLUGIN_NAME}">\n{body}\n  </pyqgis_plugin>\n</plugins>\n'
    )


def write_repository(zip_path: Path, url: str | None = None) -> Path:
    """Write ``plugins.xml`` beside ``zip_path`` (atomically); ``url`` = where the folder is served (else file://)."""
    from ..io.atomic import write_text_atomic

    zip_path = Path(zip_path).resolve()
    meta = read_metadata(plugin_source_dir())
    download = (url.rstrip("/") + "/" + zip_path.name) if url else zip_path.as_uri()
    return write_text_atomic(zip_path.parent / REPOSITORY_FILE, repository_xml(zip_path, meta, download))


def _is_plugin_zip(p: Path) -> bool:
    """Whether ``p`` is a plugin zip geocd wrote: a zip whose every entry lies in the plugin's top folder."""
    with zipfile.ZipFile(p) as zf:
        names = zf.namelist()
    return bool(names) and all(n.startswith(f"{PLUGIN_NAME}/") for n in names)


def _is_plugin_repository(p: Path) -> bool:
    """Whether ``p`` is a plugins.xml geocd wrote (a QGIS plugin repository offering this plugin)."""
    with open(p, "rb") as fh:
        head = fh.read(65536)
    return b"<plugins" in head and f'plugin_id="{PLUGIN_NAME}"'.encode() in head


@click.command("plugin-zip")
@click.option(
    "--out",
    "out",
    type=click.Path(path_type=str),
    default=None,
    help="Zip file or folder to write (default: dist/geocd_qgis.VERSION.zip).",
)
@click.option(
    "--url",
    default=None,
    help="URL the zip's folder will be served from (e.g. https://example.org/qgis/): the download URL in "
    "plugins.xml (default: the zip's file:// URL, for a repository on this machine or a shared disk).",
)
@click.option(
    "--no-environment-hint",
    is_flag=True,
    help="Do not record this environment's geocd in the zip (for zips shared with other machines).",
)
@click.option(
    "--overwrite", is_flag=True, help="Replace an existing zip or plugins.xml even when geocd did not write it."
)
@click.pass_context
def plugin_zip(
    ctx: click.Context, out: str | None, url: str | None, no_environment_hint: bool, overwrite: bool
) -> None:
    """Build the QGIS plugin zip and a plugin repository file (plugins.xml) beside it.

    Install from ZIP: Plugins ▸ Manage and Install Plugins ▸ Install from ZIP. Install from repository: add
    file:///…/plugins.xml (or its http URL) under Plugins ▸ Manage and Install Plugins ▸ Settings, then install
    "geocd" from the list; headless: `geocd plugin-install`. The plugin (Processing provider "geocd") runs this
    geocd installation as a child process; the zip records where it is unless --no-environment-hint is given.
    """
    from ..io.outputs import open_outputs, refuse_foreign_files
    from . import emit_result
    from .common import session

    sess = session(ctx)
    sess.log_enabled = False  # the folder is what a web server publishes: no log file there
    zp = zip_path(out, read_metadata(plugin_source_dir()).get("version", ""))
    open_outputs(None, files=[zp, zp.parent / REPOSITORY_FILE])
    refuse_foreign_files([zp], _is_plugin_zip, what=f"a {PLUGIN_NAME} plugin zip", force=overwrite)
    refuse_foreign_files(
        [zp.parent / REPOSITORY_FILE],
        _is_plugin_repository,
        what=f"a plugin repository offering {PLUGIN_NAME}",
        force=overwrite,
    )
    path = build_plugin_zip(out, environment_hint=not no_environment_hint)
    repo = write_repository(path, url)
    where = repo.resolve().as_uri() if not url else url.rstrip("/") + "/" + REPOSITORY_FILE
    sess.say(
        f"QGIS plugin {PLUGIN_NAME} {read_metadata(plugin_source_dir())['version']}: install from ZIP, or add the "
        f"repository {where} in QGIS (or run `geocd plugin-install`)"
    )
    emit_result(ctx, {"plugin_zip": path, "repository": repo})


def _repository_url(repository: str | None, built: Path | None) -> str:
    if repository is None:
        return (built.parent / REPOSITORY_FILE).resolve().as_uri()
    if "://" in repository:
        return repository
    p = Path(repository)
    if p.is_dir():
        p = p / REPOSITORY_FILE
    from ..errors import InputFileNotFoundError

    if not p.is_file():
        raise InputFileNotFoundError(
            f"{p} does not exist; give a plugins.xml written by `geocd plugin-zip`, its folder, or a URL"
        )
    return p.resolve().as_uri()


def _system_python() -> str:
    for cand in (os.environ.get("GEOCD_QGIS_PYTHON"), "/usr/bin/python3"):
        if cand and Path(cand).is_file():
            return cand
    return "python3"


@click.command("plugin-install")
@click.argument("repository", required=False, type=str)
@click.option(
    "--profile",
    type=click.Path(file_okay=False, path_type=str),
    default=None,
    help="QGIS configuration folder to install into (as QGIS_CUSTOM_CONFIG_PATH; default: QGIS's default "
    "profile, e.g. ~/.local/share/QGIS/QGIS3/profiles/default).",
)
@click.option(
    "--qgis-python",
    default=None,
    help="Python interpreter that has PyQGIS (default: $GEOCD_QGIS_PYTHON, else /usr/bin/python3).",
)
@click.option(
    "--timeout", "timeout_s", type=float, default=300.0, show_default=True, help="Give up after this many seconds."
)
@click.pass_context
def plugin_install(
    ctx: click.Context, repository: str | None, profile: str | None, qgis_python: str | None, timeout_s: float
) -> None:
    """Install the geocd QGIS plugin headless from a plugin repository (QGIS's own installer), and enable it.

    REPOSITORY: a plugins.xml (or its folder, or its URL) written by `geocd plugin-zip`; default: build the zip
    and plugins.xml into dist/ first. One command from a checkout: `geocd plugin-install`.
    """
    from . import emit_result
    from ..errors import ProcessingError
    from .common import session

    sess = session(ctx)
    sess.log_enabled = False
    built = None
    if repository is None:
        from ..io.outputs import open_outputs

        zp = zip_path(None, read_metadata(plugin_source_dir()).get("version", ""))
        open_outputs(None, files=[zp, zp.parent / REPOSITORY_FILE])
        built = build_plugin_zip(None)
        write_repository(built)
    url = _repository_url(repository, built)
    script = Path(__file__).with_name("qgis_install.py")
    py = qgis_python or _system_python()
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV")}
    env.setdefault("QT_QPA_PLATFORM", "offscreen")
    if profile:
        Path(profile).mkdir(parents=True, exist_ok=True)
        env["QGIS_CUSTOM_CONFIG_PATH"] = str(Path(profile).resolve())
    sess.log(f"running {py} {script} {url} {PLUGIN_NAME}")
    try:
        r = subprocess.run(
            [py, str(script), url, PLUGIN_NAME],
            env=env,
            capture_output=True,
            text=True,
            timeout=timeout_s,
            stdin=subprocess.DEVNULL,
        )
    except FileNotFoundError:
        raise ProcessingError(f"{py} not found: give the Python that has PyQGIS with --qgis-python") from None
    except subprocess.TimeoutExpired:
        raise ProcessingError(f"the QGIS installer did not finish in {timeout_s:g} s") from None
    sess.log(r.stderr)
    lines = [l for l in r.stdout.splitlines() if l.startswith("{")]
    try:
        rep = json.loads(lines[-1]) if lines else {}
    except ValueError:
        rep = {}
    if not rep.get("ok"):
        msg = rep.get("error") or f"the QGIS installer exited with status {r.returncode}: {r.stderr.strip()[-800:]}"
        raise ProcessingError(msg)
    sess.say(
        f"installed QGIS plugin {rep['plugin']} {rep['version']} from {url} into {rep['path']} and enabled it; "
        "restart QGIS, or check with: qgis_process plugins"
    )
    sess.data(**rep)
    emit_result(ctx, {"plugin": rep["path"]})
