"""Out of memory is said as such, whatever library ran out: never "a corrupt file" or "internal error"."""

from __future__ import annotations

import errno

import pytest
from rasterio.errors import RasterioIOError

from geocd.errors import ResourceError
from geocd.faults import translate

from .scenes import error_lines, write_dem_pair


@pytest.mark.parametrize(
    "exc",
    [
        MemoryError(),
        ImportError("libfoo.so: failed to map segment from shared object"),
        OSError(errno.ENOMEM, "Cannot allocate memory"),
        RasterioIOError("Out of memory allocating 1048576000 bytes"),
        RuntimeError("std::bad_alloc"),
    ],
)
def test_every_failed_allocation_is_a_resource_error(exc):
    err = translate(exc)
    assert isinstance(err, ResourceError), err
    assert str(err).startswith("out of memory") and "--posting" in str(err)


def test_a_corrupt_file_is_still_a_corrupt_file():
    err = translate(RasterioIOError("not recognized as a supported file format"))
    assert not isinstance(err, ResourceError) and "corrupt" in str(err)


def test_a_command_that_runs_out_of_memory_says_so(tmp_path, monkeypatch):
    """Under `ulimit -v` an import fails to map its shared library (ImportError): the command says "out of
    memory", never "internal error" or "corrupt file". In-process: the real limit's outcome depends on which
    allocation fails first (OpenBLAS aborts the process itself when its buffers do not fit)."""
    from click.testing import CliRunner

    import geocd.demdiff as D
    from geocd.cli import main

    a, b = write_dem_pair(tmp_path / "d")

    def fail(*args, **kwargs):
        raise ImportError("libsparsetools.so: failed to map segment from shared object")

    monkeypatch.setattr(D, "dem_difference", fail)
    r = CliRunner().invoke(main, ["--progress", "none", "demdiff", str(a), str(b), "--out", str(tmp_path / "o")])
    assert r.exit_code == 2, r.output
    errs = error_lines(r.stderr)
    assert len(errs) == 1, r.stderr
    assert errs[0].startswith("geocd: error: out of memory") and "free on the machine" in errs[0], errs[0]
    assert "corrupt" not in errs[0] and "internal error" not in errs[0], errs[0]
