"""The QGIS plugin's plain-Python parts, without QGIS: the algorithm table against the CLI, command lines,
manifests written from layers, the child-process runner (real geocd runs, real cancel), executable discovery and
the plugin zip."""

from __future__ import annotations

import json
import os
import sys
import time
import zipfile
from pathlib import Path

import click
import pytest

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "qgis_plugin"))

from geocd_qgis import locate, runner, specs  # noqa: E402

GEOCD = [str(Path(sys.executable).parent / "geocd")]


def _command(*names: str) -> click.Command | None:
    """The click command of ``geocd NAME [SUBNAME...]`` (None when it does not exist)."""
    from geocd.cli import SUBCOMMANDS, main

    if names[0] not in SUBCOMMANDS:
        return None
    cmd = main
    for name in names:
        if not isinstance(cmd, click.Group):
            return None
        with click.Context(cmd) as ctx:
            cmd = cmd.get_command(ctx, name)
        if cmd is None:
            return None
    return cmd


# --- the table against the CLI -------------------------------------------------------------------------------------


@pytest.mark.parametrize("alg", specs.active(), ids=lambda a: a.name)
def test_spec_matches_cli(alg):
    cmd = _command(*alg.command)
    assert cmd is not None, f"geocd has no command {' '.join(alg.command)!r} but the plugin offers geocd:{alg.name}"
    opts = {o: prm for prm in cmd.params if isinstance(prm, click.Option) for o in prm.opts + prm.secondary_opts}
    args = [prm for prm in cmd.params if isinstance(prm, click.Argument)]
    positional = [
        p
        for p in alg.params
        if p.cli is None and not p.manifest and p.kind not in ("folder_destination", "file_destination")
    ]
    if alg.writes_manifest:
        assert len(args) == 1 and not positional, f"{alg.name}: the manifest must be the only positional argument"
    else:
        assert len(positional) <= len(args) or (args and args[-1].nargs == -1), (
            f"{alg.name}: {len(positional)} positional parameters for {len(args)} CLI arguments"
        )
    for p in alg.params:
        if p.cli is None:
            continue
        assert p.cli in opts, (
            f"geocd {' '.join(alg.command)} has no option {p.cli} (plugin parameter {alg.name}.{p.name})"
        )
        o = opts[p.cli]
        if p.kind == "enum" and isinstance(o.type, click.Choice):
            values = [v for _, v in p.options if v != ""]
            assert set(values) <= set(o.type.choices), f"{alg.name}.{p.name}: {values} vs {o.type.choices}"
        if p.kind == "bool":
            assert o.is_flag, f"{alg.name}.{p.name}: {p.cli} is not a flag"
        if p.kind in ("rasters", "numbers") or (p.kind == "string" and p.multiple):
            assert o.multiple, f"{alg.name}.{p.name}: {p.cli} must be repeatable"
        if p.kind in ("range", "pair"):
            assert o.nargs == 2, f"{alg.name}.{p.name}: {p.cli} must take two values"
        if p.cli_default and p.default is not None and p.kind != "bool":
            default = (p.options[p.default][1] or None) if p.kind == "enum" else p.default
            cli_default = o.get_default(click.Context(cmd))
            assert cli_default == default, (
                f"{alg.name}.{p.name}: plugin default {default!r} differs from the CLI's {cli_default!r}"
            )


def test_pending_algorithms_stay_pending_only_while_the_command_is_missing():
    landed = [a.name for a in specs.ALGORITHMS if a.pending and _command(*a.command) is not None]
    assert not landed, (
        f"geocd now has the command(s) of pending plugin algorithm(s) {landed}: check their "
        "parameters against `geocd CMD --help` and set pending=False in qgis_plugin/geocd_qgis/specs.py"
    )


def test_metadata_and_versions():
    from geocd import __version__
    from geocd.cli.plugin import read_metadata

    meta = read_metadata(REPO / "qgis_plugin" / "geocd_qgis")
    assert meta["version"] == __version__
    assert meta["hasProcessingProvider"] == "yes"
    assert meta["qgisMinimumVersion"] == "3.22"
    for key in ("name", "description", "about", "author", "email", "tracker", "repository", "changelog", "icon"):
        assert meta.get(key), key
    assert (REPO / "qgis_plugin" / "geocd_qgis" / meta["icon"]).is_file()


def test_plugin_imports_only_qgis_and_the_standard_library():
    """The plugin runs inside QGIS's Python: no numpy/rasterio/pyproj/geocd imports (they crash QGIS)."""
    import ast

    stdlib = set(sys.stdlib_module_names)
    for py in (REPO / "qgis_plugin" / "geocd_qgis").rglob("*.py"):
        tree = ast.parse(py.read_text(encoding="utf-8"))
        for node in ast.walk(tree):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0:
                names = [node.module]
            for n in names:
                top = n.split(".")[0]
                assert top in stdlib or top in ("qgis", "processing"), f"{py.name} imports {n}"


# --- command lines and manifests -----------------------------------------------------------------------------------


def test_build_args_stereo():
    alg = specs.spec("stereo")
    args = specs.build_args(
        alg,
        {
            "MANIFEST": "/d/-scene.yaml",
            "EPOCHS": "A, B",
            "OUTPUT": "/o",
            "POSTING": 0.5,
            "WINDOW": 7,
            "HEIGHT_RANGE": (10.0, 80.5),
            "SCORE": 1,
            "TILE_SIZE": None,
        },
    )
    assert args == [
        "stereo",
        "--epoch",
        "A",
        "--epoch",
        "B",
        "--out",
        "/o",
        "--posting",
        "0.5",
        "--window",
        "7",
        "--height-range",
        "10",
        "80.5",
        "--score",
        "ncc",
        "--",
        "/d/-scene.yaml",
    ]


def test_build_args_defaults_and_repeats():
    alg = specs.spec("change")
    args = specs.build_args(
        alg,
        {
            "EPOCH_A": ["/a1.tif", "/a2.tif"],
            "EPOCH_B": ["/b1.tif"],
            "DEM_DATUM": 0,
            "MODEL": "/m.json",
            "OUTPUT": "/o",
            "CONFIDENCES": "95;99.5",
            "REPORT_CONFIDENCE": 99.0,
            "COMBINE": 0,
        },
    )
    assert args == [
        "change",
        "--pair-dem-a",
        "/a1.tif",
        "--pair-dem-a",
        "/a2.tif",
        "--pair-dem-b",
        "/b1.tif",
        "--model",
        "/m.json",
        "--out",
        "/o",
        "--confidence",
        "95",
        "--confidence",
        "99.5",
    ]
    with pytest.raises(ValueError, match="numbers"):
        specs.build_args(alg, {"CONFIDENCES": "ninety"})
    upd = specs.build_args(
        specs.spec("volumeupdate"),
        {"MODEL": "/m", "IMAGES": ["/a.tif"], "PASSES": 5, "SUN": "135, 40.5", "NORMALIZE": 1, "FOOTPRINTS": True},
    )
    assert upd == [
        "volume",
        "update",
        "--image",
        "/a.tif",
        "--roofs-from-footprints",
        "--normalize",
        "percentile",
        "--sun",
        "135",
        "40.5",
        "--",
        "/m",
    ]
    with pytest.raises(ValueError, match="two numbers"):
        specs.build_args(specs.spec("volumedetect"), {"MODEL": "/m", "IMAGE": "/i.tif", "SUN": "135"})
    syn = specs.build_args(specs.spec("synth"), {"OUTPUT": "/s", "SEED": 3, "TINY": True, "SIZE_M": 300.0})
    assert syn == ["synth", "--out", "/s", "--seed", "3", "--tiny"]


def test_manifest_from_layers_loads_in_geocd(tmp_path):
    from geocd.io.manifest import load_manifest

    for name in ("a1.tif", "a2.tif", "b1.tif", "b2.tif", "dem.tif", "fp.gpkg"):
        (tmp_path / name).write_bytes(b"")
    alg = specs.spec("runlayers")
    vals = {
        "IMAGES_A": [str(tmp_path / "a1.tif"), str(tmp_path / "a2.tif")],
        "IMAGES_B": [str(tmp_path / "b1.tif"), str(tmp_path / "b2.tif")],
        "DEM": str(tmp_path / "dem.tif"),
        "DEM_DATUM": 2,
        "FOOTPRINTS": f"{tmp_path / 'fp.gpkg'}|layername=buildings",
        "AOI": (500000.0, 6000000.0, 500300.0, 6000300.0, "EPSG:32735"),
        "POSTING": 0.5,
        "SCENE_CLASS": "urban",
    }
    m = specs.build_manifest(alg, vals, output=str(tmp_path / "out"))
    path = tmp_path / "scene.json"
    path.write_text(json.dumps(m))
    man = load_manifest(path)
    assert [e.name for e in man.epochs] == ["A", "B"]
    assert [im.name for im in man.epochs[1].images] == ["b1", "b2"]
    assert man.dem.vertical_datum == "egm96" and man.footprints.layer == "buildings"
    assert man.aoi.bounds == (500000.0, 6000000.0, 500300.0, 6000300.0) and man.aoi.posting_m == 0.5
    assert man.scene_class == "urban"
    args = specs.build_args(alg, {**vals, "OUTPUT": "/o"}, manifest_path=str(path))
    assert args == ["run", "--out", "/o", "--", str(path)]
    # an image pair: one epoch
    pair = specs.build_manifest(
        specs.spec("stereopair"), {"IMAGE_A": str(tmp_path / "a1.tif"), "IMAGE_B": str(tmp_path / "a1.tif")}
    )
    assert [im["name"] for im in pair["epochs"][0]["images"]] == ["a1_1", "a1_2"]
    with pytest.raises(ValueError, match="at least one epoch"):
        specs.build_manifest(alg, {})


# --- the runner: real geocd child processes ------------------------------------------------------------------------


def test_runner_streams_and_reports_errors(tmp_path):
    bad = tmp_path / "scene.yaml"
    bad.write_text("epochs: [unclosed\n")
    events = []
    res = runner.run_geocd(
        [*GEOCD, "--progress", "json", "info", str(bad)], on_console=events.append, env=locate.child_env()
    )
    assert res.returncode != 0 and not res.ok
    assert "not valid YAML" in res.error and str(bad) in res.error
    assert res.failure_message() == res.error


@pytest.mark.slow
def test_runner_cancel_kills_child_and_cleanup_leaves_nothing(tmp_path):
    out = tmp_path / "scene"
    before = runner.snapshot(str(out))
    progress = []
    t_cancel = {}

    def cancelled():
        if any(f is not None and f > 0.05 for f, _, _ in progress):
            t_cancel.setdefault("t", time.monotonic())
            return True
        return False

    res = runner.run_geocd(
        [*GEOCD, "--progress", "json", "synth", "--tiny", "--supersample", "8", "--out", str(out)],
        on_progress=lambda f, m, s: progress.append((f, m, s)),
        is_cancelled=cancelled,
        env=locate.child_env(),
        grace_s=3.0,
    )
    stopped_s = time.monotonic() - t_cancel["t"]
    assert res.cancelled and res.returncode != 0 and "cancelled" in res.failure_message()
    assert stopped_s < 5.0
    with pytest.raises(ProcessLookupError):
        os.kill(res.pid, 0)
    runner.remove_new_files(str(out), before)
    assert not out.exists(), f"left behind: {list(out.rglob('*'))}"


def test_runner_resolves_relative_outputs(tmp_path):
    script = tmp_path / "fake.py"
    script.write_text(
        "import json,sys; sys.stderr.write(json.dumps({'type':'result','outputs':{'x':'a/b.tif'}})+'\\n')"
    )
    res = runner.run_geocd([sys.executable, str(script)], cwd=str(tmp_path))
    assert res.ok and res.outputs == {"x": str(tmp_path / "a" / "b.tif")}


# --- finding geocd, packaging --------------------------------------------------------------------------------------


def test_locate_prefers_setting_then_env(monkeypatch, tmp_path):
    monkeypatch.setenv(locate.ENV_VAR, GEOCD[0])
    argv, source = locate.find_geocd()
    assert argv == GEOCD and source == f"${locate.ENV_VAR}"
    argv, source = locate.find_geocd(configured=sys.executable)
    assert argv == [sys.executable, "-m", "geocd"] and source == "Processing settings"
    argv, msg = locate.check_geocd(configured=str(tmp_path / "nope" / "geocd"))
    assert argv is None and "does not exist" in msg and "pip install" in msg
    argv, msg = locate.check_geocd(configured=sys.executable)
    from geocd import __version__

    assert argv is not None and __version__ in msg
    env = locate.child_env({"PYTHONPATH": "/usr/share/qgis/python", "PROJ_LIB": "/x", "HOME": "/h"})
    assert "PYTHONPATH" not in env and "PROJ_LIB" not in env and env["HOME"] == "/h"


def test_plugin_zip(tmp_path):
    from click.testing import CliRunner

    from geocd.cli import main

    out = tmp_path / "geocd_qgis.zip"
    r = CliRunner().invoke(main, ["--progress", "json", "plugin-zip", "--out", str(out)])
    assert r.exit_code == 0, r.output
    with zipfile.ZipFile(out) as zf:
        names = zf.namelist()
        assert all(n.startswith("geocd_qgis/") for n in names)
        for need in (
            "__init__.py",
            "metadata.txt",
            "provider.py",
            "algorithm.py",
            "runner.py",
            "specs.py",
            "locate.py",
            "icons/geocd.svg",
            "environment.json",
        ):
            assert f"geocd_qgis/{need}" in names
        assert not [n for n in names if "__pycache__" in n or n.endswith(".pyc")]
        hint = json.loads(zf.read("geocd_qgis/environment.json"))
        assert Path(hint["python"]).exists()
    r = CliRunner().invoke(main, ["plugin-zip", "--out", str(tmp_path / "b.zip"), "--no-environment-hint"])
    with zipfile.ZipFile(tmp_path / "b.zip") as zf:
        assert "geocd_qgis/environment.json" not in zf.namelist()


def test_plugins_xml_names_the_zip_it_offers(tmp_path):
    """plugins.xml's file_name is the zip's own name, and QGIS reads the plugin's id (geocd_qgis) from it."""
    import xml.etree.ElementTree as ET

    from click.testing import CliRunner

    from geocd import __version__
    from geocd.cli import main

    repo = tmp_path / "dist"
    r = CliRunner().invoke(main, ["plugin-zip", "--out", f"{repo}/", "--no-environment-hint"])
    assert r.exit_code == 0, r.output
    zips = sorted(p.name for p in repo.glob("*.zip"))
    assert zips == [f"geocd_qgis.{__version__}.zip"]
    plugin = ET.parse(repo / "plugins.xml").getroot().find("pyqgis_plugin")
    file_name = plugin.findtext("file_name")
    assert file_name == zips[0]
    assert plugin.findtext("download_url").endswith("/" + zips[0])
    assert file_name.partition(".")[0] == plugin.get("plugin_id") == "geocd_qgis"  # QGIS's installer reads the id so
    # a zip the user named: download URL names it; file_name keeps an id QGIS installs under
    r = CliRunner().invoke(main, ["plugin-zip", "--out", str(tmp_path / "p.zip"), "--no-environment-hint"])
    assert r.exit_code == 0, r.output
    plugin = ET.parse(tmp_path / "plugins.xml").getroot().find("pyqgis_plugin")
    assert plugin.findtext("download_url").endswith("/p.zip")
    assert plugin.findtext("file_name").partition(".")[0] == "geocd_qgis"
