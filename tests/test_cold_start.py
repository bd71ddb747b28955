"""Cold start: a command compiles only the kernels it uses, and says so once when it compiles."""

from __future__ import annotations

import io
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_info_compiles_no_kernel(tmp_path):
    cache = tmp_path / "numba_cache"
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache))
    for image in ("A_sat1.tif", "A_air1.tif"):  # an RPC and a frame camera
        p = subprocess.run(
            [sys.executable, "-m", "geocd", "info", str(REPO / "sample_aoi" / "images" / image)],
            capture_output=True,
            text=True,
            env=env,
            timeout=300,
        )
        assert p.returncode == 0, p.stderr
        assert "footprint:" in p.stdout and "compiling" not in p.stderr
    assert not list(cache.rglob("*.nbi"))  # nothing was compiled (was: minutes of CPU)


def test_info_footprint_equals_the_kernel_footprint():
    from geocd.io.cameras import load_camera

    for image in ("A_sat1.tif", "A_air1.tif"):
        cam = load_camera(REPO / "sample_aoi" / "images" / image)
        a = cam.footprint(200.0, reference=True)
        b = cam.footprint(200.0)
        assert a.symmetric_difference(b).area < 1e-6 * b.area
        lon, lat = cam.localize([10.0, 300.0], [20.0, 400.0], [200.0, 200.0])
        dr = cam.dproj_dh_reference(lon, lat, [200.0, 200.0])
        dk = cam.dproj_dh(lon, lat, [200.0, 200.0])
        assert max(abs(float(x - y)) for u, v in zip(dr, dk) for x, y in zip(u, v)) < 1e-4


def test_compile_notice_is_said_once():
    numba = pytest.importorskip("numba")
    from geocd import _jit

    buf = io.StringIO()
    fresh = not _jit._state["installed"]
    if fresh:  # else an earlier CLI test of this session installed it (on its stderr)
        _jit.install_compile_notice(stream=buf)
    n0, s0 = _jit._state["kernels"], _jit.compile_seconds()

    @numba.njit
    def f(x):
        return x + 1

    f(1)
    f(2.0)
    assert _jit._state["kernels"] >= n0 + 2 and _jit.compile_seconds() > s0
    if fresh:
        assert buf.getvalue().count("compiling numerical kernels") == 1


_PARALLEL_PROBE = """
import json, sys
import numpy as np
from numba import prange
from geocd._jit import parallel_njit

@parallel_njit(error_model="numpy")
def row_sums(a):
    out = np.empty(a.shape[0])
    for i in prange(a.shape[0]):
        out[i] = a[i].sum()
    return out

a = np.arange(12.0).reshape(4, 3)
print(json.dumps({"sums": row_sums(a).tolist(), "parallel": bool(row_sums.targetoptions.get("parallel")),
                  "qualname": row_sums.py_func.__qualname__}))
"""


@pytest.mark.parametrize("threads", [1, 2])
def test_parallel_kernels_compile_serial_where_numba_runs_one_thread(tmp_path, threads):
    """One thread: the kernel is compiled serial (a third of the compile time) and cached under its own name;
    more threads: parallel=True. Both give the same answer."""
    import json

    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "cache"), NUMBA_NUM_THREADS=str(threads))
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), env.get("PYTHONPATH", "")])
    probe = tmp_path / "probe.py"  # numba caches kernels of files only
    probe.write_text(_PARALLEL_PROBE)
    p = subprocess.run([sys.executable, str(probe)], capture_output=True, text=True, env=env, timeout=300)
    assert p.returncode == 0, p.stderr
    got = json.loads(p.stdout.strip().splitlines()[-1])
    assert got["sums"] == [3.0, 12.0, 21.0, 30.0]
    assert got["parallel"] == (threads > 1)
    name = "row_sums" if threads > 1 else "row_sums__serial"
    assert got["qualname"] == name
    assert [f.name.split("-")[0] for f in (tmp_path / "cache").rglob("*.nbi")] == [f"probe.{name}"]
