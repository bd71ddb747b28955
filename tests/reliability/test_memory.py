"""Out of memory is said as such, whatever library ran out: never "a corrupt file" or "internal error"."""

from __future__ import annotations

import errno
import resource
import subprocess
import sys

import pytest
from rasterio.errors import RasterioIOError

from geocd.errors import ResourceError
from geocd.faults import translate

from .scenes import error_lines, write_dem_pair


@pytest.mark.parametrize("exc", [
    MemoryError(),
    ImportError("libfoo.so: failed to map segment from shared object"),
    OSError(errno.ENOMEM, "Cannot allocate memory"),
    RasterioIOError("Out of memory allocating 1048576000 bytes"),
    RuntimeError("std::bad_alloc"),
])
def test_every_failed_allocation_is_a_resource_error(exc):
    err = translate(exc)
    assert isinstance(err, ResourceError), err
    assert str(err).startswith("out of memory") and "--posting" in str(err)


def test_a_corrupt_file_is_still_a_corrupt_file():
    err = translate(RasterioIOError("not recognized as a supported file format"))
    assert not isinstance(err, ResourceError) and "corrupt" in str(err)


def test_a_run_under_a_memory_limit_says_out_of_memory(tmp_path):
    """`ulimit -v` 400 MB: the imports cannot map their libraries; the message names memory and the limit."""
    a, b = write_dem_pair(tmp_path / "d")

    def limit():
        resource.setrlimit(resource.RLIMIT_AS, (400 * 2**20, 400 * 2**20))

    r = subprocess.run([sys.executable, "-m", "geocd", "--progress", "none", "demdiff", str(a), str(b), "--out",
                        str(tmp_path / "o")], capture_output=True, text=True, preexec_fn=limit, timeout=300)
    assert r.returncode == 2, r.stderr[-2000:]
    errs = error_lines(r.stderr)
    assert len(errs) == 1, r.stderr[-2000:]
    assert "out of memory" in errs[0] and "ulimit -v" in errs[0], errs[0]
    assert "corrupt" not in errs[0] and "internal error" not in errs[0], errs[0]
