"""One error path: every exception the CLI or the QGIS plugin can meet becomes one line naming the fix."""

from __future__ import annotations

import errno
import json
import subprocess
import sys
from pathlib import Path

import pytest
from click.testing import CliRunner

import geocd.errors as E
from geocd.cli import main
from geocd.faults import translate
from geocd.io.outputs import check_prefix, check_resources

from .scenes import error_lines

REPO = Path(__file__).resolve().parents[2]


def _rasterio_error():
    from rasterio.errors import RasterioIOError

    return RasterioIOError("TIFFReadEncodedTile() failed")


def _rasterio_free_space_error():
    from rasterio.errors import RasterioIOError

    return RasterioIOError(
        "demdiff_significance.assemble.part.tif: Free disk space available is 4683780096 bytes, "
        "whereas 4908122112 are at least necessary. You can disable this check by defining the "
        "CHECK_DISK_FREE_SPACE configuration option to FALSE."
    )


def _pyogrio_error():
    from pyogrio.errors import DataSourceError

    return DataSourceError("Failed to commit transaction")


@pytest.mark.parametrize(
    "make, cls, needle",
    [
        (lambda: MemoryError(), E.ResourceError, "coarser posting"),
        (
            lambda: OSError(errno.ENOSPC, "No space left on device", "/data/out/x.tif"),
            E.DiskFullError,
            "no space left on device",
        ),
        (lambda: OSError(errno.EFBIG, "File too large", "/data/out/x.tif"), E.DiskFullError, "file size limit"),
        (lambda: OSError(errno.EROFS, "Read-only file system", "/mnt/ro"), E.OutputError, "read-only file system"),
        (lambda: PermissionError(errno.EACCES, "Permission denied", "/root/x"), E.OutputError, "permission denied"),
        (lambda: FileExistsError(errno.EEXIST, "File exists", "/data/out"), E.OutputError, "already exists"),
        (
            lambda: FileNotFoundError(errno.ENOENT, "No such file", "/data/in.tif"),
            E.InputFileNotFoundError,
            "does not exist",
        ),
        (lambda: b"\xff\xfe\x00".decode("utf-8"), E.UnsupportedFormatError, "binary or not UTF-8"),
        (_rasterio_error, E.UnsupportedFormatError, "GDAL (rasterio)"),
        (_rasterio_free_space_error, E.DiskFullError, "about 4,908 MB needed, 4,684 MB free"),
        (_pyogrio_error, E.UnsupportedFormatError, "OGR (pyogrio)"),
        (lambda: ValueError("operands could not be broadcast"), E.InternalError, "this is a bug in geocd"),
        (lambda: KeyError("x"), E.InternalError, "rerun with --debug"),
    ],
)
def test_translate(make, cls, needle):
    try:
        exc = make()
        if isinstance(exc, BaseException):
            raise exc
    except Exception as caught:  # noqa: BLE001
        err = translate(caught)
    assert type(err) is cls, (type(err), err)
    assert needle in str(err) and "\n" not in str(err)
    assert err.__cause__ is not None
    assert isinstance(err, E.GeoCDError)


def test_a_geocd_error_is_kept():
    e = E.ManifestError("x")
    assert translate(e) is e


@pytest.mark.parametrize(
    "exc, cls",
    [
        (ValueError("boom"), "InternalError"),
        (MemoryError(), "ResourceError"),
        (OSError(errno.ENOSPC, "No space left on device"), "DiskFullError"),
    ],
)
def test_cli_turns_any_exception_into_one_line(monkeypatch, tmp_path, exc, cls):
    import geocd.info

    def describe(path):
        raise exc

    monkeypatch.setattr(geocd.info, "describe", describe)
    r = CliRunner().invoke(main, ["info", str(tmp_path)])
    assert r.exit_code == 2
    errs = error_lines(r.stderr)
    assert len(errs) == 1 and "Traceback" not in r.output, r.output
    r = CliRunner().invoke(main, ["--progress", "json", "info", str(tmp_path)])
    events = [json.loads(ln) for ln in r.stderr.splitlines() if ln.startswith("{")]
    assert events and events[-1]["type"] == "error" and events[-1]["error"] == cls
    r = CliRunner().invoke(main, ["--debug", "info", str(tmp_path)])
    assert r.exception is exc  # --debug: the original exception and its traceback


def test_ctrl_c_exits_130_without_traceback(monkeypatch, tmp_path):
    import geocd.info

    def describe(path):
        raise KeyboardInterrupt

    monkeypatch.setattr(geocd.info, "describe", describe)
    r = CliRunner().invoke(main, ["info", str(tmp_path)])
    assert r.exit_code == 130 and "interrupted (Ctrl-C)" in error_lines(r.stderr)[0]


def test_internal_error_in_a_real_process(tmp_path):
    """A bug (here: a command that divides by zero) still reaches the user as one line, exit 2."""
    code = (
        "import click\nimport geocd.cli as c\n"
        "@click.command('boom')\ndef boom():\n    1 / 0\n"
        "c.SUBCOMMANDS['boom'] = '__main__:boom'\nc.main(['boom'])\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2
    assert error_lines(r.stderr) == [
        "geocd: error: internal error (ZeroDivisionError: division by zero); this is a "
        "bug in geocd: rerun with --debug and report the traceback"
    ]
    assert "Traceback" not in r.stderr


# --------------------------------------------------------------------------------------------------------------
# resources and names
# --------------------------------------------------------------------------------------------------------------
def test_memory_estimate_refuses_before_work(monkeypatch):
    monkeypatch.setenv("GEOCD_MEMORY_LIMIT_MB", "100")
    with pytest.raises(E.ResourceError, match=r"needs about 1\.9 GiB of memory, 95 MiB is available; use less"):
        check_resources("a job", memory_bytes=2 * 10**9, fix="use less")
    check_resources("a small job", memory_bytes=10**6)


def test_disk_estimate(monkeypatch, tmp_path):
    import geocd.faults

    monkeypatch.setattr(geocd.faults, "free_bytes", lambda p: 10**6)
    with pytest.raises(E.DiskFullError, match=r"about 25 MB needed \(compressed; 100 MB uncompressed\), 1 MB free"):
        check_resources("stereo", disk_bytes=10**8, out=tmp_path)
    with pytest.warns(UserWarning, match="may need up to 3 MB"):
        check_resources("stereo", disk_bytes=3 * 10**6, out=tmp_path)


def test_stereo_estimate_names_a_posting_that_fits(monkeypatch):
    from geocd.geodesy import AOIGrid
    from geocd.stereo.pipeline import check_stereo_resources

    monkeypatch.setenv("GEOCD_MEMORY_LIMIT_MB", "8000")
    g = AOIGrid.from_bounds(0, 0, 100_000, 100_000, 0.5, "EPSG:32631")
    with pytest.raises(E.ResourceError) as ei:
        check_stereo_resources(g, 6, None, keep_arrays=True)
    msg = str(ei.value)
    assert "200000 x 200000 grid at 0.5 m (6 pair(s)) needs about" in msg and "--posting" in msg
    posting = float(msg.split("about --posting ")[1].split(" ")[0])
    g2 = AOIGrid.from_bounds(0, 0, 100_000, 100_000, posting, "EPSG:32631")
    check_stereo_resources(g2, 6, None, keep_arrays=True)  # the suggested posting fits


@pytest.mark.parametrize("prefix", ["../x", "a/b", "..", ".hidden", "", "c:evil", "a\\b", "x\x00"])
def test_prefix_must_be_a_plain_name(prefix):
    with pytest.raises(E.ConfigError, match="not a plain file-name prefix"):
        check_prefix(prefix)


@pytest.mark.parametrize("prefix", ["demdiff", "site_1", "2024-05-01", "é"])
def test_plain_prefixes_pass(prefix):
    assert check_prefix(prefix) == prefix


def test_writes_outside_the_session_are_refused(tmp_path):
    from geocd.io.atomic import write_text_atomic
    from geocd.io.outputs import open_outputs

    with open_outputs(tmp_path / "O", command="test"):
        write_text_atomic(tmp_path / "O" / "ok.txt", "x")
        with pytest.raises(E.OutputError, match="outside this run's output"):
            write_text_atomic(tmp_path / "elsewhere.txt", "x")
    assert not (tmp_path / "elsewhere.txt").exists()


# --------------------------------------------------------------------------------------------------------------
# the QGIS plugin never shows a traceback
# --------------------------------------------------------------------------------------------------------------
@pytest.fixture
def runner_mod():
    sys.path.insert(0, str(REPO / "qgis_plugin"))
    from geocd_qgis import runner

    return runner


def test_plugin_summarises_a_crashed_child(runner_mod, tmp_path):
    """A child that dies with a Python traceback (a broken installation): one paragraph, no traceback."""
    res = runner_mod.run_geocd([sys.executable, "-c", "import json\nraise ValueError('boom')"])
    assert res.returncode == 1
    msg = res.failure_message()
    assert "ValueError: boom" in msg and "Traceback" not in msg and "--debug" in msg


def test_plugin_carries_geocds_one_line(runner_mod, tmp_path):
    res = runner_mod.run_geocd(
        [
            sys.executable,
            "-m",
            "geocd",
            "--progress",
            "json",
            "demdiff",
            str(tmp_path / "a.tif"),
            str(tmp_path / "b.tif"),
            "--out",
            str(tmp_path / "O"),
        ]
    )
    assert res.returncode == 2 and res.error_type == "InputFileNotFoundError"
    msg = res.failure_message()
    assert "a.tif does not exist; check the" in msg and "\n" not in msg


def test_plugin_describes_its_own_failures(runner_mod):
    msg = runner_mod.describe_exception(OSError(errno.EROFS, "Read-only file system", "/mnt/x"))
    assert msg.startswith("read-only file system: /mnt/x")
    assert "bug" in runner_mod.describe_exception(KeyError("x")) and "Traceback" not in msg


@pytest.mark.qgis
@pytest.mark.slow
def test_qgis_unwritable_output_folder_is_a_message(tmp_path):
    from tests.qgis.qgis_env import QGIS, require_qgis
    from tests.reliability.scenes import write_dem_pair

    require_qgis()
    a, b = write_dem_pair(tmp_path / "dems")
    qgis = QGIS(tmp_path / "profile")
    rep = qgis.pyqgis("error", "geocd:demdiff", f"DEM_A={a}", f"DEM_B={b}", "OUTPUT=/sys/geocd_qgis_test/out")
    assert rep.get("exception") == "QgsProcessingException", rep
    assert "Traceback" not in rep["message"] and "/sys/geocd_qgis_test" in rep["message"], rep
