"""RPC projection and localization throughput: geocd's numba kernels vs GDAL's RPC transformer.

Measured in the same run, on the same 1e6 points drawn uniformly in the validity box
(lon, lat, ellipsoidal height) of the s2p Pléiades ``img_01`` RPC:

* projection (ground → image): :meth:`RPCModel.project` vs rasterio
  ``RPCTransformer.rowcol(..., op=np.positive)`` (float output, no rounding);
* localization (image + height → ground): :meth:`RPCModel.localize` (tol 1e-9 px) vs rasterio
  ``RPCTransformer.xy(..., offset="ul")`` with GDAL's default options and with
  ``RPC_PIXEL_ERROR_THRESHOLD=1e-6`` (GDAL's default threshold is 0.1 px);
  accuracy = image distance between the input pixel and the projection of the result.

numba is warmed up (compiled / loaded from cache) before any timing; each figure is the
best of ``--repeat`` runs, the contenders taking turns within each repeat (other processes'
load then hits them alike). geocd is timed with 1 thread and with all threads
(``numba.set_num_threads``); GDAL's transformer is single-threaded.

The first localization of a process (``--first geocd|gdal --points IN.npz --out OUT.npz``): one process that
imports its tool, reads the image's RPC and localizes the points of ``IN.npz`` (``col``, ``row``, ``h``, from
:func:`sample_points`) once, writing ``lon``, ``lat`` to ``OUT.npz`` and its own timings as one JSON line.
``python -m bench.peers`` runs it with an empty numba cache (cold) and a filled one (warm), GDAL beside.

Usage::

    .venv/bin/python bench/bench_rpc.py [--n 1000000] [--repeat 5] [--image PATH]
    .venv/bin/python bench/bench_rpc.py --first geocd --points IN.npz --out OUT.npz [--image PATH]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
DEFAULT_IMAGE = (
    Path(os.environ.get("GEOCD_SHARED_DATA", REPO.parent / "shared" / "data"))
    / "s2p_pleiades"
    / "input_pair"
    / "img_01.tif"
)


def sample_points(model, n: int, seed: int = 0) -> tuple[np.ndarray, ...]:
    """``n`` points drawn uniformly in the RPC's validity box: ``lon, lat, h`` and their pixel ``col, row``."""
    box = model.validity_box()
    rng = np.random.default_rng(seed)
    lon = rng.uniform(*box["lon"], n)
    lat = rng.uniform(*box["lat"], n)
    h = rng.uniform(*box["h"], n)
    col, row = model.project(lon, lat, h)
    return lon, lat, h, col, row


def first_localization(tool: str, image: Path, points: Path, out: Path) -> dict:
    """Import ``tool`` (``geocd`` or ``gdal``: rasterio's RPC transformer, default options), read the image's RPC
    and localize the points once (the process's first localization); ``lon``, ``lat`` go to ``out``.

    Returns
    -------
    dict
        ``import_s``, ``load_s``, ``localize_s`` (wall) and ``localize_cpu_s``, ``tool_version``, ``n``.
    """
    d = np.load(points)
    col, row, h = d["col"], d["row"], d["h"]
    t0 = time.perf_counter()
    if tool == "geocd":
        import geocd
        from geocd.io.rpc import load_rpc_for_image

        t1 = time.perf_counter()
        model = load_rpc_for_image(image)
        t2, c2 = time.perf_counter(), time.process_time()
        x, y = model.localize(col, row, h)
        version = geocd.__version__
    else:
        import rasterio
        from rasterio.transform import RPCTransformer

        t1 = time.perf_counter()
        with rasterio.open(image) as ds:
            rpcs = ds.rpcs
        t2, c2 = time.perf_counter(), time.process_time()
        with RPCTransformer(rpcs) as tr:
            x, y = tr.xy(row, col, h, offset="ul")
        version = f"rasterio {rasterio.__version__}, GDAL {rasterio.__gdal_version__}"
    t3, c3 = time.perf_counter(), time.process_time()
    np.savez(out, lon=np.asarray(x, np.float64), lat=np.asarray(y, np.float64))
    return {
        "tool": tool,
        "tool_version": version,
        "n": int(col.size),
        "import_s": t1 - t0,
        "load_s": t2 - t1,
        "localize_s": t3 - t2,
        "localize_cpu_s": c3 - c2,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=1_000_000, help="number of points (default 1e6)")
    ap.add_argument("--repeat", type=int, default=5, help="timings per figure; the best is kept")
    ap.add_argument("--image", type=Path, default=DEFAULT_IMAGE, help="image with RPC (default s2p img_01)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--first", choices=("geocd", "gdal"), default=None, help="one first localization (see above)")
    ap.add_argument("--points", type=Path, default=None, help="with --first: the points (.npz: col, row, h)")
    ap.add_argument("--out", type=Path, default=None, help="with --first: where lon, lat go (.npz)")
    args = ap.parse_args(argv)
    if args.first:
        print(json.dumps(first_localization(args.first, args.image, args.points, args.out)))
        return 0

    import numba
    import rasterio
    from rasterio.transform import RPCTransformer

    from geocd.io.rpc import load_rpc_for_image

    if not args.image.is_file():
        print(f"image {args.image} not found (needs ../shared/data)", file=sys.stderr)
        return 2
    model = load_rpc_for_image(args.image)
    rpc = model.to_rasterio()
    n = args.n
    # warm-up: numba kernels compiled or loaded from cache, cubic Newton start fitted
    lon, lat, h, col, row = sample_points(model, 1000, args.seed)
    model.localize(col, row, h)
    model.dproj_dh(lon[:10], lat[:10], h[:10])
    lon, lat, h, col, row = sample_points(model, n, args.seed)

    max_threads = numba.config.NUMBA_NUM_THREADS
    print(f"# geocd RPC benchmark: {n:.0e} points in the validity box of {args.image.name}")
    print(f"# {model!r}")
    print(
        f"# rasterio {rasterio.__version__}, GDAL {rasterio.__gdal_version__}, numba {numba.__version__}, "
        f"{os.cpu_count()} CPUs, numba threads available {max_threads}, best of {args.repeat}"
    )

    rows = []

    def report(task: str, who: str, seconds: float, base: float | None, extra: str = "") -> None:
        rate = n / seconds
        ratio = "" if base is None else f"{base / seconds:7.1f}x"
        rows.append((task, who, rate, ratio, extra))
        print(f"{task:13s} {who:42s} {rate / 1e6:9.2f} M points/s {ratio:>9s}  {extra}", flush=True)

    # Each repeat times every contender once, in turn, so that load from other processes
    # hits all of them alike; the best time of each is kept.
    thread_counts = sorted({1, max_threads})

    def timed(fn) -> float:
        t0 = time.perf_counter()
        fn()
        return time.perf_counter() - t0

    # ---- projection ------------------------------------------------------------------
    best: dict[str, float] = {}
    with RPCTransformer(rpc) as tr:
        g_row, g_col = tr.rowcol(lon, lat, h, op=np.positive)
        for _ in range(args.repeat):
            best["gdal"] = min(best.get("gdal", np.inf), timed(lambda: tr.rowcol(lon, lat, h, op=np.positive)))
            for threads in thread_counts:
                numba.set_num_threads(threads)
                best[threads] = min(best.get(threads, np.inf), timed(lambda: model.project(lon, lat, h)))
    diff = float(np.max(np.hypot(np.asarray(g_col) - col, np.asarray(g_row) - row)))
    report("projection", "GDAL RPCTransformer.rowcol (1 thread)", best["gdal"], None)
    for threads in thread_counts:
        report(
            "projection",
            f"geocd RPCModel.project ({threads} thread{'s' * (threads > 1)})",
            best[threads],
            best["gdal"],
            f"max |geocd - GDAL| = {diff:.1e} px",
        )

    # ---- localization --------------------------------------------------------------------
    def accuracy(x, y) -> str:
        x = np.asarray(x, float)
        y = np.asarray(y, float)
        ok = np.isfinite(x) & np.isfinite(y)
        c2, r2 = model.project(x[ok], y[ok], h[ok])
        err = np.hypot(c2 - col[ok], r2 - row[ok])
        return f"error max {err.max():.1e} px, p99 {np.percentile(err, 99):.1e} px, converged {100.0 * ok.mean():.2f}%"

    gdal_opts = {"default (0.1 px)": {}, "RPC_PIXEL_ERROR_THRESHOLD=1e-6": {"RPC_PIXEL_ERROR_THRESHOLD": 1e-6}}
    best = {}
    results = {}
    transformers = {k: RPCTransformer(rpc, **o) for k, o in gdal_opts.items()}
    try:
        for k, tr in transformers.items():
            results[k] = tr.xy(row, col, h, offset="ul")
        for _ in range(args.repeat):
            for k, tr in transformers.items():
                best[k] = min(best.get(k, np.inf), timed(lambda: tr.xy(row, col, h, offset="ul")))
            for threads in thread_counts:
                numba.set_num_threads(threads)
                best[threads] = min(best.get(threads, np.inf), timed(lambda: model.localize(col, row, h)))
    finally:
        for tr in transformers.values():
            tr.close()
    for k in gdal_opts:
        report("localization", f"GDAL RPCTransformer.xy, {k}", best[k], None, accuracy(*results[k]))
    x, y, its = model.localize(col, row, h, return_iterations=True)
    ok = its >= 0
    hist = np.bincount(its[ok])
    for threads in thread_counts:
        report(
            "localization",
            f"geocd RPCModel.localize ({threads} thread{'s' * (threads > 1)})",
            best[threads],
            best["RPC_PIXEL_ERROR_THRESHOLD=1e-6"],
            accuracy(x, y) + f", iterations max {its[ok].max()} mean {its[ok].mean():.2f} "
            f"(histogram {hist.tolist()}); vs GDAL default {best['default (0.1 px)'] / best[threads]:.1f}x",
        )
    print(
        "# ratios: geocd rate / GDAL rate (localization: against GDAL at 1e-6 px; "
        "the ratio against GDAL's default is at the end of the line)"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
