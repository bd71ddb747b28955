"""``--out FILE`` (ortho, consistency, plugin-zip): geocd replaces its own earlier product, never a user's file
unless --overwrite says so."""

from __future__ import annotations

import json
import zipfile
from pathlib import Path

import pytest
from click.testing import CliRunner

from geocd.cli import main
from geocd.errors import OutputError
from geocd.io.outputs import is_qgis_style, refuse_foreign_files
from tests.reliability.scenes import error_lines, make_scene


def _cli(*args):
    return CliRunner().invoke(main, ["--progress", "none", *map(str, args)])


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return make_scene(tmp_path_factory.mktemp("outfiles") / "scene")


def test_refuse_foreign_files(tmp_path):
    mine, theirs = tmp_path / "mine.txt", tmp_path / "theirs.txt"
    mine.write_text("geocd")
    theirs.write_text("user")
    ours = lambda p: p.read_text() == "geocd"  # noqa: E731
    refuse_foreign_files([mine, None, tmp_path / "missing.txt", tmp_path], ours, what="x")
    with pytest.raises(OutputError, match="theirs.txt exists and geocd did not write it .it is not x.*--overwrite"):
        refuse_foreign_files([mine, theirs], ours, what="x")
    refuse_foreign_files([theirs], ours, what="x", force=True)

    def broken(p):
        raise ValueError("unreadable")

    with pytest.raises(OutputError):
        refuse_foreign_files([mine], broken, what="x")  # a file we cannot recognise is not ours


def test_qgis_style_recogniser(tmp_path):
    (tmp_path / "a.qml").write_text("<!DOCTYPE qgis PUBLIC 'http://mrcc.com/qgis.dtd' 'SYSTEM'>\n<qgis version='3'/>")
    (tmp_path / "b.qml").write_text("notes")
    assert is_qgis_style(tmp_path / "a.qml") and not is_qgis_style(tmp_path / "b.qml")


def test_consistency_model_recogniser(tmp_path):
    from geocd.cli.change import _is_consistency_model

    (tmp_path / "m.json").write_text(json.dumps({"geocd_self_consistency_model": 1, "hist": []}))
    (tmp_path / "o.json").write_text(json.dumps({"name": "other"}))
    (tmp_path / "t.json").write_text("plain text")
    assert _is_consistency_model(tmp_path / "m.json")
    assert not _is_consistency_model(tmp_path / "o.json") and not _is_consistency_model(tmp_path / "t.json")


def test_ortho_replaces_its_own_output_and_a_foreign_one_only_with_overwrite(scene, tmp_path):
    img, dem = scene.root / "images" / "A_0.tif", scene.root / "dem.tif"
    out = tmp_path / "x.tif"
    assert _cli("ortho", img, "--dsm", dem, "--out", out).exit_code == 0
    assert _cli("ortho", img, "--dsm", dem, "--out", out).exit_code == 0  # its own product: replaced
    foreign = tmp_path / "y.tif"
    foreign.write_text("mine")
    r = _cli("ortho", img, "--dsm", dem, "--out", foreign)
    assert r.exit_code == 2 and foreign.read_text() == "mine"
    assert "did not write it" in error_lines(r.stderr)[0]
    assert not (tmp_path / "y_status.tif").exists()
    r = _cli("ortho", img, "--dsm", dem, "--out", foreign, "--overwrite")
    assert r.exit_code == 0, r.output
    assert foreign.read_bytes()[:2] in (b"II", b"MM")
    r = _cli("ortho", img, "--dsm", dem, "--out", out, "--overwrite", "--no-overwrite")
    assert r.exit_code == 2 and "contradict" in r.stderr


def test_plugin_zip_replaces_its_own_zip(tmp_path):
    out = tmp_path / "p.zip"
    assert _cli("plugin-zip", "--out", out, "--no-environment-hint").exit_code == 0
    first = zipfile.ZipFile(out).namelist()
    r = _cli("plugin-zip", "--out", out, "--no-environment-hint")
    assert r.exit_code == 0, r.output
    assert zipfile.ZipFile(out).namelist() == first
    other = tmp_path / "o"
    other.mkdir()
    with zipfile.ZipFile(other / "p.zip", "w") as zf:
        zf.writestr("x.txt", "x")
    before = (other / "p.zip").read_bytes()
    assert _cli("plugin-zip", "--out", other / "p.zip").exit_code == 2
    assert (other / "p.zip").read_bytes() == before and not (other / "plugins.xml").exists()
    assert _cli("plugin-zip", "--out", other / "p.zip", "--overwrite").exit_code == 0
    assert Path(other / "plugins.xml").exists()
