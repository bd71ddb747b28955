"""A tiled run killed with SIGKILL half way: no partial product visible; the same command resumes and
gives the same product."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest
import rasterio

SCRIPT = textwrap.dedent("""
    import os, sys, time
    import numpy as np
    from affine import Affine
    from geocd.geodesy import AOIGrid
    from geocd.tiling import ArraySource, RasterProduct, run_tiled

    def slow_tile(arrays, ctx):
        time.sleep(float(os.environ.get("SLOW_TILE_S", "0")))
        a = arrays["x"]
        return {"y": (a * 2.0 + 1.0).astype(np.float32)}

    out = sys.argv[1]
    g = AOIGrid("EPSG:32631", Affine(1.0, 0, 500000.0, 0, -1.0, 4800000.0), 160, 200)
    x = np.arange(g.height * g.width, dtype=np.float32).reshape(g.shape)
    run = run_tiled(slow_tile, g, {"x": ArraySource(x)}, tile_size=40, out=out, stage="slow",
              products={"y": RasterProduct(out + "/y.tif", ("y",))}, scheduler="sync")
    print("resumed", run.n_resumed)
""")


@pytest.mark.slow
def test_sigkill_then_resume(tmp_path):
    script = tmp_path / "job.py"
    script.write_text(SCRIPT)
    out = tmp_path / "out"
    env = dict(os.environ)
    # 20 tiles of 0.3 s: killed once 8 are journalled
    p = subprocess.Popen(
        [sys.executable, str(script), str(out)], env=dict(env, SLOW_TILE_S="0.3"), start_new_session=True
    )
    work = out / ".geocd-work"
    t0 = time.time()
    while time.time() - t0 < 120:
        n = len(list(work.rglob("*.done.pkl"))) if work.exists() else 0
        if n >= 8:
            break
        time.sleep(0.05)
    os.killpg(p.pid, signal.SIGKILL)
    p.wait()
    done = len(list(work.rglob("*.done.pkl")))
    assert 8 <= done < 20
    # nothing visible under the product's name
    assert not (out / "y.tif").exists()
    assert [f.name for f in out.iterdir() if not f.name.startswith(".")] == []
    # the same command resumes: only the unfinished tiles run
    r = subprocess.run([sys.executable, str(script), str(out)], env=env, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert f"resumed {done}" in r.stdout
    with rasterio.open(out / "y.tif") as ds:
        y = ds.read(1)
    x = np.arange(200 * 160, dtype=np.float32).reshape(200, 160)
    np.testing.assert_array_equal(y, x * 2.0 + 1.0)
