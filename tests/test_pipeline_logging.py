"""geocd.pipeline.run from Python: stage lines on the "geocd" logger and geocd_run.log in the output folder.

The heavy steps are replaced by a stand-in (``_run``) that reports stages as the real one does.
"""

from __future__ import annotations

import logging
import warnings

import pytest
from click.testing import CliRunner

import geocd.pipeline as pipeline
from geocd.errors import ConfigError

STAGES = (
    "relative orientation",
    "stereo",
    "learning the self-consistency distribution",
    "cross-epoch change test",
    "writing products",
)


def _fake_run(fail: bool = False):
    def fake(m, out, config, prog, footprints):
        out.mkdir(parents=True, exist_ok=True)
        prog(0.0, "relative orientation")
        prog(0.1, "stereo")
        prog(0.2, "stereo: pair 1/2")
        prog(0.4, "stereo: pair 2/2")
        warnings.warn("a stand-in warning", UserWarning)
        prog(0.78, "learning the self-consistency distribution")
        if fail:
            raise ConfigError("a stand-in failure")
        prog(0.85, "cross-epoch change test")
        prog(0.95, "writing products")
        prog(1.0, "done")
        (out / "sc_change.tif").write_bytes(b"")
        return {
            "outputs": {"change": out / "sc_change.tif"},
            "summary": {
                "epoch_a": "a",
                "epoch_b": "b",
                "grid": {"width": 2, "height": 2},
                "observed_fraction": 1.0,
                "changed_fraction": {},
            },
        }

    return fake


def test_python_run_logs_stages_and_writes_the_log_file(sample_aoi, tmp_path, monkeypatch, caplog):
    monkeypatch.setattr(pipeline, "_run", _fake_run())
    out = tmp_path / "out"
    with caplog.at_level(logging.INFO, logger="geocd"), warnings.catch_warnings():
        warnings.simplefilter("always")
        res = pipeline.run(sample_aoi, out_dir=out)
    assert res["outputs"]["change"].name == "sc_change.tif"
    msgs = [r.getMessage() for r in caplog.records if r.name == "geocd" and r.levelno == logging.INFO]
    for stage in STAGES:
        assert any(stage in msg for msg in msgs), (stage, msgs)
    assert any("run done in" in msg for msg in msgs), msgs
    log = (out / "geocd_run.log").read_text(encoding="utf-8")
    assert log.count("==== geocd ") == 1 and "parameters:" in log and "cwd:" in log
    for stage in STAGES:
        assert f"% {stage}" in log, stage
    assert "WARNING UserWarning: a stand-in warning" in log
    assert "OUTPUT change:" in log and "done in" in log


def test_python_run_that_fails_logs_the_error(sample_aoi, tmp_path, monkeypatch, caplog):
    monkeypatch.setattr(pipeline, "_run", _fake_run(fail=True))
    out = tmp_path / "out"
    with caplog.at_level(logging.INFO, logger="geocd"), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with pytest.raises(ConfigError):
            pipeline.run(sample_aoi, out_dir=out)
    log = (out / "geocd_run.log").read_text(encoding="utf-8")
    assert "ERROR ConfigError: a stand-in failure" in log and "failed after" in log
    assert any("run failed" in r.getMessage() for r in caplog.records)


def test_python_run_without_log_file(sample_aoi, tmp_path, monkeypatch):
    monkeypatch.setattr(pipeline, "_run", _fake_run())
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        pipeline.run(sample_aoi, out_dir=tmp_path / "out", log_file=False)
    assert not (tmp_path / "out" / "geocd_run.log").exists()


def test_cli_run_writes_one_log(sample_aoi, tmp_path, monkeypatch):
    """`geocd run` writes geocd_run.log itself: one header per run, the pipeline's progress in it."""
    from geocd.cli import main

    monkeypatch.setattr(pipeline, "_run", _fake_run())
    out = tmp_path / "out"
    r = CliRunner().invoke(main, ["run", str(sample_aoi), "--out", str(out), "--progress", "lines"])
    assert r.exit_code == 0, r.output
    log = (out / "geocd_run.log").read_text(encoding="utf-8")
    assert log.count("==== geocd ") == 1, log
    assert "PROGRESS run" in log and "% stereo" in log


def test_cli_run_prints_building_counts_per_class(sample_aoi, tmp_path, monkeypatch):
    """The summary on stdout names the building layer's source and its counts per class, on every run that has
    one, and says why when a run has none (no footprints, derivation off)."""
    from geocd.cli import main

    fake = _fake_run()
    entry = {}

    def with_buildings(m, out, config, prog, footprints):
        res = fake(m, out, config, prog, footprints)
        res["summary"]["buildings"] = entry
        return res

    monkeypatch.setattr(pipeline, "_run", with_buildings)
    entry.update(
        source="footprints + change map",
        classes={"collapsed": 3, "new": 2, "unchanged": 41},
        volume_lost_m3=1234.5,
    )
    r = CliRunner().invoke(main, ["run", str(sample_aoi), "--out", str(tmp_path / "out"), "--progress", "none"])
    assert r.exit_code == 0, r.output
    assert "buildings (footprints + change map): 3 collapsed, 2 new, 41 unchanged; 1,234 m³ lost" in r.stdout
    assert "building damage" not in r.stdout
    entry.clear()
    entry.update(source="A DSM", classes={}, volume_lost_m3=0.0)
    r = CliRunner().invoke(main, ["run", str(sample_aoi), "--out", str(tmp_path / "out2"), "--progress", "none"])
    assert "buildings (A DSM): none found" in r.stdout
    entry.clear()
    entry.update(source=None, classes={}, volume_lost_m3=None, reason="no footprints and derive_buildings is off")
    r = CliRunner().invoke(main, ["run", str(sample_aoi), "--out", str(tmp_path / "out3"), "--progress", "none"])
    assert "buildings: no building layer (no footprints and derive_buildings is off)" in r.stdout
