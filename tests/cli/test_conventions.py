"""What every geocd command shares (geocd/cli/common.py): options after the command, confidence in percent,
stdout = result / stderr = progress, a log file in the output folder, defaults in the current directory, inputs
checked before heavy imports, two images into `geocd stereo`."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import click
import numpy as np
import pytest
from click.testing import CliRunner

from geocd.cli import SUBCOMMANDS, main

REPO = Path(__file__).resolve().parents[2]


def _commands():
    """(path, click command) of every leaf command, as the group loads them (common options applied)."""
    out = []
    for name in sorted(SUBCOMMANDS):
        with click.Context(main) as ctx:
            cmd = main.get_command(ctx, name)
        if isinstance(cmd, click.Group):
            out += [((name, sub), c) for sub, c in sorted(cmd.commands.items())]
        else:
            out.append(((name,), cmd))
    return out


COMMANDS = _commands()


def _confidence_options():
    found = []
    for path, cmd in COMMANDS:
        for p in cmd.params:
            if isinstance(p, click.Option) and "confidence" in (p.name or ""):
                found.append((path, next(o for o in p.opts if o.startswith("--"))))
    return found


CONFIDENCE_OPTIONS = _confidence_options()


@pytest.mark.parametrize("path", [p for p, _ in COMMANDS], ids=lambda p: " ".join(p))
def test_every_command_takes_progress_and_json_after_its_name(path):
    r = CliRunner().invoke(main, [*path, "--help"])
    assert r.exit_code == 0, r.output
    assert "--progress [auto|bar|lines|json|none]" in r.output and "--json" in r.output


def test_confidence_options_exist_where_expected():
    got = {(" ".join(p), o) for p, o in CONFIDENCE_OPTIONS}
    for need in [
        ("run", "--confidence"),
        ("run", "--report-confidence"),
        ("change", "--confidence"),
        ("change", "--report-confidence"),
        ("consistency", "--confidence"),
        ("demdiff", "--confidence"),
    ]:
        assert need in got, sorted(got)


@pytest.mark.parametrize("path,opt", CONFIDENCE_OPTIONS, ids=lambda x: " ".join(x) if isinstance(x, tuple) else x)
def test_cli_rejects_the_0_to_1_convention(path, opt):
    """Confidence is a percentage: `--confidence 0.95` is refused with a hint, before any work."""
    r = CliRunner().invoke(main, [*path, opt, "0.95", "no_such_input"])
    assert r.exit_code == 2, r.output
    assert f"geocd: error: {opt} is a percentage: did you mean 95?" in r.output
    assert "Traceback" not in r.output
    r = CliRunner().invoke(main, [*path, opt, "120", "no_such_input"])
    assert r.exit_code == 2 and "outside [50, 100)" in r.output, r.output


def test_docs_table_lists_every_confidence_option():
    """docs/cli.md's table of confidence-carrying options and fields covers every CLI option (all in percent)."""
    text = (REPO / "docs" / "cli.md").read_text(encoding="utf-8")
    section = text[text.index("## Confidence is a percentage") :]
    section = section[: section.index("\n## ", 5)] if "\n## " in section[5:] else section
    for path, opt in CONFIDENCE_OPTIONS:
        assert re.search(rf"`geocd {' '.join(path)}[^`]*{re.escape(opt)}", section), f"geocd {' '.join(path)} {opt}"
    for field in (
        "sc_change.tif",
        "demdiff_significance.tif",
        "buildings",
        "changes",
        "CONFIDENCE",
        "REPORT_CONFIDENCE",
        "CONFIDENCES",
    ):
        assert field in section, field


def test_missing_input_fails_before_heavy_imports(tmp_path):
    """`geocd run nonexistent` says so without importing numba, rasterio or the pipeline."""
    code = (
        "import sys\nfrom geocd.cli import main\n"
        "try:\n    main(['run', 'nonexistent_scene'], standalone_mode=True)\nexcept SystemExit as e:\n    code = e.code\n"
        "heavy = [m for m in ('numba', 'rasterio', 'geocd.pipeline', 'geocd.stereo') if m in sys.modules]\n"
        "print('EXIT', code, 'HEAVY', heavy)\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path, timeout=120)
    assert "EXIT 2 HEAVY []" in r.stdout, r.stdout + r.stderr
    assert "geocd: error: nonexistent_scene does not exist" in r.stderr


def _dems(tmp_path: Path) -> tuple[Path, Path]:
    from geocd.io.raster import write_cog
    from tests.demdiff.synthetic import grid, pair

    g = grid(60, 70)
    a, b, _ = pair((0.0, 0.0, 0.0), noise_m=0.4, bump_m=8.0, g=g, seed=3)
    pa = write_cog(tmp_path / "a.tif", a.height_m.astype(np.float32), a.grid)
    pb = write_cog(tmp_path / "b.tif", b.height_m.astype(np.float32), b.grid)
    return pa, pb


def _geocd(*args, cwd: Path, env: dict | None = None) -> subprocess.CompletedProcess:
    exe = Path(sys.executable).parent / "geocd"
    argv = [str(exe)] if exe.is_file() else [sys.executable, "-m", "geocd"]
    return subprocess.run(
        [*argv, *args],
        capture_output=True,
        text=True,
        cwd=cwd,
        timeout=600,
        env={**os.environ, **(env or {})},
        stdin=subprocess.DEVNULL,
    )


@pytest.mark.slow
def test_streams_log_file_and_default_output_folder(tmp_path):
    """Redirected like `geocd demdiff a.tif b.tif > log.txt 2> err.txt`: the products and summary on stdout,
    plain progress lines on stderr, a log file in the default output folder ./geocd_out/a__b."""
    pa, pb = _dems(tmp_path)
    r = _geocd("demdiff", pa.name, pb.name, "--no-plots", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    out = tmp_path / "geocd_out" / "a__b"
    assert (out / "demdiff_dh.tif").is_file()
    # stdout: summary, products, log path, nothing else
    assert "stable NMAD" in r.stdout and "products:" in r.stdout
    assert re.search(r"^  dh: .*geocd_out/a__b/demdiff_dh\.tif$", r.stdout, re.M), r.stdout
    assert "log: " in r.stdout and "%" not in r.stdout.split("products:")[1].split("log:")[0]
    # stderr: plain progress lines (not a terminal), no product list, nothing glued to a bar
    lines = r.stderr.splitlines()
    assert sum(1 for l in lines if l.startswith("geocd: [")) >= 3, r.stderr
    assert "\r" not in r.stderr and "products:" not in r.stderr and "demdiff_dh.tif" not in r.stderr
    # no message twice
    msgs = [l for l in lines if l.startswith(("geocd: note:", "geocd: warning:"))]
    assert len(msgs) == len(set(msgs)), msgs
    # the log file: command line, parameters, progress, products, end
    log = (out / "geocd_demdiff.log").read_text(encoding="utf-8")
    for need in ("geocd ", "argv:", "parameters:", "PROGRESS demdiff", "OUTPUT dh:", "done in"):
        assert need in log, need
    # --json: one document on stdout; the same run appends to the log
    r = _geocd("demdiff", pa.name, pb.name, "--no-plots", "--json", "--progress", "none", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    doc = json.loads(r.stdout)
    assert doc["status"] == "ok" and doc["command"] == "demdiff"
    assert Path(doc["outputs"]["dh"]).name == "demdiff_dh.tif" and doc["log"].endswith("geocd_demdiff.log")
    assert doc["summary"]["stable_nmad_m"] > 0.3 and "geocd: [" not in r.stderr
    assert (out / "geocd_demdiff.log").read_text(encoding="utf-8").count("==== geocd") == 2


@pytest.mark.slow
def test_json_progress_after_the_command(tmp_path):
    pa, pb = _dems(tmp_path)
    r = _geocd("demdiff", str(pa), str(pb), "--out", "o", "--no-plots", "--progress", "json", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    events = [json.loads(l) for l in r.stderr.splitlines() if l.startswith("{")]
    assert events and all(e["type"] in ("progress", "info", "warning", "result") for e in events)
    assert events[-1]["type"] == "result" and events[-1]["log"].endswith("geocd_demdiff.log")


@pytest.mark.slow
def test_degenerate_stable_terrain_warns(tmp_path):
    """Two DEMs identical off the change (as if pasted on a common base): NMAD 0 is flagged, not reported as fact."""
    from geocd.io.raster import write_cog
    from tests.demdiff.synthetic import grid, pair

    g = grid(60, 70)
    a, b, info = pair((0.0, 0.0, 0.0), noise_m=0.0, bump_m=8.0, g=g, seed=3)
    pa = write_cog(tmp_path / "a.tif", a.height_m.astype(np.float32), a.grid)
    zb = np.where(info["bump"], b.height_m, a.height_m).astype(np.float32)
    pb = write_cog(tmp_path / "b.tif", zb, a.grid)
    r = _geocd("demdiff", str(pa), str(pb), "--out", "o", "--no-plots", "--json", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    doc = json.loads(r.stdout)
    assert doc["summary"]["status"] == "degenerate_stable_terrain"
    assert doc["summary"]["stable_identical_fraction"] > 0.8
    assert any("--base" in w and "not an error estimate" in w for w in doc["warnings"]), doc["warnings"]
    assert "geocd: warning: degenerate stable terrain" in r.stderr
    rep = json.loads((tmp_path / "o" / "demdiff_report.json").read_text())
    assert rep["status"] == "degenerate_stable_terrain" and rep["warnings"]
    # independent noise on both DEMs: no warning
    a2, b2, _ = pair((0.0, 0.0, 0.0), noise_m=0.3, bump_m=8.0, g=g, seed=4)
    write_cog(tmp_path / "a2.tif", a2.height_m.astype(np.float32), a2.grid)
    write_cog(tmp_path / "b2.tif", b2.height_m.astype(np.float32), b2.grid)
    r = _geocd("demdiff", "a2.tif", "b2.tif", "--out", "o2", "--no-plots", "--json", cwd=tmp_path)
    doc = json.loads(r.stdout)
    assert doc["summary"]["status"] != "degenerate_stable_terrain" and not any(
        "degenerate" in w for w in doc["warnings"]
    ), doc


def test_unwritable_default_output_folder_says_give_out(tmp_path):
    if os.geteuid() == 0:
        pytest.skip("root can write into a read-only folder")
    pa, pb = _dems(tmp_path)
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    try:
        r = _geocd("demdiff", str(pa), str(pb), cwd=ro)
    finally:
        ro.chmod(0o755)
    assert r.returncode != 0 and "give --out" in r.stderr


def test_unwritable_default_output_folder_message(tmp_path, monkeypatch):
    """The message for an output folder that cannot be created names the fix (works as root too)."""
    from geocd.cli.common import resolve_out_dir
    from geocd.errors import OutputError

    blocker = tmp_path / "file"
    blocker.write_text("x")
    monkeypatch.chdir(blocker.parent)
    with pytest.raises(OutputError, match="give another --out"):
        resolve_out_dir(blocker, "x")
    monkeypatch.setattr(Path, "cwd", classmethod(lambda cls: blocker))
    with pytest.raises(OutputError, match="give --out DIR"):
        resolve_out_dir(None, "scene")


def test_stereo_inputs(tmp_path):
    """`geocd stereo a.tif b.tif` makes a one-epoch scene of the images; one image gets a clear message."""
    from geocd.cli.stereo import scene_from_inputs
    from geocd.errors import ConfigError

    for n in ("a.tif", "b.tif"):
        (tmp_path / n).write_bytes(b"II*\x00")
    m = scene_from_inputs((str(tmp_path / "a.tif"), str(tmp_path / "b.tif")))
    assert [e.name for e in m.epochs] == ["pair"] and [i.name for i in m.epochs[0].images] == ["a", "b"]
    assert m.name == "a__b" and m.output is None
    r = CliRunner().invoke(main, ["stereo", str(tmp_path / "a.tif")])
    assert r.exit_code == 2 and "is one image; stereo needs two or more" in r.output and "YAML" not in r.output
    r = CliRunner().invoke(main, ["stereo", str(tmp_path / "a.tif"), str(tmp_path)])
    assert r.exit_code == 2 and "is not an image" in r.output
    with pytest.raises(ConfigError):
        scene_from_inputs((str(tmp_path / "a.tif"), str(tmp_path / "notes.txt")))
