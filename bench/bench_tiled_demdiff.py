"""Tiled DEM differencing at scale: wall time, cells/s, peak RSS of the whole process tree; SIGKILL + resume;
a dask.distributed scheduler with two workers on loopback.

    nice -n 10 .venv/bin/python bench/bench_tiled_demdiff.py run DIR_WITH_dem_a_dem_b OUT [--tile-size 1024]
        [--scheduler auto] [--workers 2] [--memory-limit 1.5GB] [--json result.json]
    nice -n 10 .venv/bin/python bench/bench_tiled_demdiff.py untiled DIR OUT            # the in-memory baseline
    nice -n 10 .venv/bin/python bench/bench_tiled_demdiff.py kill DIR OUT --at 0.5     # SIGKILL at 50 %, rerun
    nice -n 10 .venv/bin/python bench/bench_tiled_demdiff.py cluster DIR OUT           # dask scheduler + 2 workers
    .venv/bin/python bench/bench_tiled_demdiff.py same OUT1 OUT2                        # identical products?

Each run is ``geocd demdiff DIR/dem_a.tif DIR/dem_b.tif --out OUT --tiled ...`` in a child process
(``--progress json``); a thread samples the summed RSS of that process and every descendant (the
local cluster's nanny and worker processes, or the scheduler and workers the ``cluster`` mode
starts) with psutil every 0.2 s. Cells/s counts the grid's cells once per run (every tiled pass
touches them; see the report's ``passes``).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path


sys.path.insert(0, str(Path(__file__).resolve().parent))
from _memwatch import tree_rss  # noqa: E402

GEOCD = str(Path(sys.executable).with_name("geocd"))
RASTERS = ("dh", "significance", "change_mask")


class Watch:
    """Peak summed RSS of a set of process trees."""

    def __init__(self, pids):
        self.pids = list(pids)
        self.peak = 0
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._run, daemon=True)

    def _run(self):
        while not self._stop.is_set():
            self.peak = max(self.peak, sum(tree_rss(p) for p in self.pids))
            self._stop.wait(0.2)

    def __enter__(self):
        self._t.start()
        return self

    def __exit__(self, *a):
        self._stop.set()
        self._t.join()


def cmd(dem_dir: Path, out: Path, a, tiled: bool = True) -> list[str]:
    c = [
        GEOCD,
        "--progress",
        "json",
        "demdiff",
        str(dem_dir / "dem_a.tif"),
        str(dem_dir / "dem_b.tif"),
        "--json",
        "--out",
        str(out),
        "--no-plots",
    ]
    if getattr(a, "region_test", None):
        c += ["--region-test", a.region_test]
    if not tiled:
        return c + ["--untiled"]
    c += ["--tiled", "--tile-size", str(a.tile_size)]
    if a.scheduler:
        c += ["--scheduler", a.scheduler]
    if a.workers:
        c += ["--workers", str(a.workers)]
    if a.memory_limit:
        c += ["--memory-limit", a.memory_limit]
    return c


def run_once(c: list[str], kill_at: float | None = None, extra_pids=()) -> dict:
    """Run the CLI; optionally SIGKILL its process group when the progress passes ``kill_at``."""
    t0 = time.perf_counter()
    p = subprocess.Popen(c, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    last = {"fraction": 0.0}
    killed = False
    with Watch([p.pid, *extra_pids]) as w:
        for line in p.stderr:
            try:
                ev = json.loads(line)
            except ValueError:
                continue
            if ev.get("type") == "progress" and ev.get("fraction") is not None:
                last = ev
                if kill_at is not None and ev["fraction"] >= kill_at and not killed:
                    os.killpg(p.pid, signal.SIGKILL)
                    killed = True
                    break
        out, _ = p.communicate()
    wall = time.perf_counter() - t0
    res = {
        "wall_s": round(wall, 1),
        "peak_tree_rss_gb": round(w.peak / 1e9, 3),
        "returncode": p.returncode,
        "killed_at": last.get("fraction") if killed else None,
        "last_message": last.get("message"),
    }
    if not killed:
        try:
            res["result"] = json.loads(out)
        except ValueError:
            res["stdout_tail"] = out[-2000:]
    return res


def digest(out: Path) -> dict:
    """sha1 of every product raster's pixels and of the report (without wall times)."""
    import rasterio

    d = {}
    for n in RASTERS:
        with rasterio.open(out / f"demdiff_{n}.tif") as ds:
            d[n] = hashlib.sha1(ds.read().tobytes()).hexdigest()
    rep = json.loads((out / "demdiff_report.json").read_text())
    rep["summary"].pop("wall_s", None)
    d["report"] = hashlib.sha1(json.dumps(rep, sort_keys=True).encode()).hexdigest()
    return d


def visible_partials(out: Path) -> list[str]:
    """Product files visible under their own name that are not complete GeoTIFFs / GeoPackages."""
    import rasterio

    bad = []
    for f in sorted(out.glob("*.tif")):
        try:
            with rasterio.open(f) as ds:
                ds.read(1, window=((ds.height - 1, ds.height), (ds.width - 1, ds.width)))
        except Exception:  # noqa: BLE001
            bad.append(f.name)
    return bad


def grid_cells(dem_dir: Path) -> int:
    import rasterio

    with rasterio.open(dem_dir / "dem_a.tif") as ds:
        return ds.width * ds.height


def free_port() -> int:
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("mode", choices=["run", "untiled", "kill", "cluster", "same"])
    ap.add_argument("dem_dir")
    ap.add_argument("out")
    ap.add_argument("--tile-size", type=int, default=1024)
    ap.add_argument("--scheduler", default=None)
    ap.add_argument("--workers", type=int, default=None)
    ap.add_argument("--memory-limit", default=None)
    ap.add_argument("--at", type=float, default=0.5)
    ap.add_argument(
        "--region-test",
        default=None,
        choices=["noise", "off"],
        help="demdiff's region test (default: the CLI's, noise; off: the products of earlier runs)",
    )
    ap.add_argument("--json", default=None, help="also write the result here")
    a = ap.parse_args()
    dem_dir, out = Path(a.dem_dir), Path(a.out)
    if a.mode == "same":
        d1, d2 = digest(dem_dir), digest(out)
        rep = {"same": d1 == d2, "a": d1, "b": d2}
    elif a.mode == "run":
        n = grid_cells(dem_dir)
        r = run_once(cmd(dem_dir, out, a))
        rep = {"cells": n, **r, "cells_per_s": round(n / r["wall_s"])}
        if r["returncode"] == 0:
            rep["digest"] = digest(out)
    elif a.mode == "untiled":
        # the in-memory pipeline on the same pair: the baseline of the ratios
        n = grid_cells(dem_dir)
        r = run_once(cmd(dem_dir, out, a, tiled=False))
        rep = {"cells": n, **r, "cells_per_s": round(n / r["wall_s"])}
        if r["returncode"] == 0:
            rep["digest"] = digest(out)
    elif a.mode == "kill":
        n = grid_cells(dem_dir)
        r1 = run_once(cmd(dem_dir, out, a), kill_at=a.at)
        partial = visible_partials(out)
        work = out / ".geocd-work"
        journal = sum(1 for _ in work.rglob("*.done.pkl")) if work.exists() else 0
        r2 = run_once(cmd(dem_dir, out, a))
        res = r2.get("result", {})
        rep = {
            "cells": n,
            "killed": r1,
            "visible_partial_products_after_kill": partial,
            "finished_tile_results_journalled": journal,
            "rerun": r2,
            "tiles_resumed": (res.get("summary") or {}).get("tiles_resumed") if isinstance(res, dict) else None,
        }
        if r2["returncode"] == 0:
            rep["digest"] = digest(out)
    else:  # cluster
        n = grid_cells(dem_dir)
        port = free_port()
        addr = f"tcp://127.0.0.1:{port}"
        dask = str(Path(sys.executable).with_name("dask"))
        procs = [
            subprocess.Popen(
                [dask, "scheduler", "--host", "127.0.0.1", "--port", str(port), "--no-dashboard"],
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
            )
        ]
        time.sleep(3)
        for _ in range(2):
            procs.append(
                subprocess.Popen(
                    [
                        dask,
                        "worker",
                        addr,
                        "--nworkers",
                        "1",
                        "--nthreads",
                        "1",
                        "--memory-limit",
                        a.memory_limit or "2GB",
                        "--no-dashboard",
                        "--host",
                        "127.0.0.1",
                    ],
                    stdout=subprocess.DEVNULL,
                    stderr=subprocess.DEVNULL,
                )
            )
        time.sleep(5)
        try:
            a.scheduler = addr
            a.workers = None
            a.memory_limit = None
            r = run_once(cmd(dem_dir, out, a), extra_pids=[q.pid for q in procs])
        finally:
            for q in procs[::-1]:
                q.send_signal(signal.SIGTERM)
            for q in procs:
                try:
                    q.wait(20)
                except subprocess.TimeoutExpired:
                    q.kill()
        rep = {"cells": n, "scheduler": addr, **r, "cells_per_s": round(n / r["wall_s"])}
        if r["returncode"] == 0:
            rep["digest"] = digest(out)
    if "result" in rep and isinstance(rep["result"], dict):
        rep["result"] = {k: rep["result"].get(k) for k in ("summary", "status") if k in rep["result"]}
    txt = json.dumps(rep, indent=1, default=str)
    print(txt)
    if a.json:
        Path(a.json).write_text(txt)


if __name__ == "__main__":
    main()
