"""``bench/compile_times.py``: one geocd command run in-process with numba's compile events counted per kernel.
No timing is asserted: that the command runs, its exit code passes through, and every compiled kernel is listed."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from geocd.geodesy import AOIGrid
from geocd.io.raster import write_cog
from tests.conftest import REPO


def _run(tmp_path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, str(REPO / "bench" / "compile_times.py"), *args],
        capture_output=True,
        text=True,
        cwd=REPO,
        timeout=600,
    )


@pytest.mark.slow
def test_a_cold_demdiff_lists_the_kernels_it_compiled(tmp_path):
    grid = AOIGrid.from_bounds(500000.0, 4000000.0, 500200.0, 4000200.0, 2.0, "EPSG:32631")
    yy, xx = np.mgrid[0 : grid.height, 0 : grid.width]
    rng = np.random.default_rng(0)
    a = 100.0 + 0.05 * xx + 0.02 * yy + rng.normal(0, 0.2, (grid.height, grid.width))
    b = a + rng.normal(0, 0.2, a.shape)
    b[40:50, 40:50] += 5.0
    write_cog(tmp_path / "a.tif", a.astype(np.float32), grid)
    write_cog(tmp_path / "b.tif", b.astype(np.float32), grid)
    out = tmp_path / "ct.json"
    r = _run(
        tmp_path,
        "--threads",
        "1",
        "--json",
        str(out),
        "--",
        "demdiff",
        str(tmp_path / "a.tif"),
        str(tmp_path / "b.tif"),
        "--out",
        str(tmp_path / "dd"),
    )
    assert r.returncode == 0, r.stderr[-3000:]
    assert "of it compiling" in r.stdout and "empty numba cache" in r.stdout, r.stdout
    rec = json.loads(out.read_text())
    assert rec["exit"] == 0 and rec["kernels"], rec
    assert all(name.startswith("geocd.") for name in rec["kernels"]), rec["kernels"]
    assert rec["compile_s"] == pytest.approx(sum(rec["kernels"].values()))
    assert (tmp_path / "dd").is_dir()


def test_a_failing_command_passes_its_exit_code_through(tmp_path):
    r = _run(tmp_path, "--warm", "--", "demdiff", str(tmp_path / "missing_a.tif"), str(tmp_path / "missing_b.tif"))
    assert r.returncode != 0
    assert "exit" in r.stdout
