"""Marked point process speed: seconds per megapixel of image pair on one core, and the energy kernel
against its numpy reference.

1. The energy kernel ``rect_features`` (all object features of a rectangle on one image) against
   ``rect_features_ref`` (numpy) on the same rectangles of a LEVIR-CD image: µs per rectangle, ratio; the
   same for the height-step kernel ``rect_steps`` on a synthetic height map of that size, and for the
   sub-cell edge fit ``fit_sides`` (that image and height map).
2. Whole runs (``geocd.mpp.detect``, joint model) on each LEVIR-CD pair (256 × 256 cells = 0.066 Mpx per
   image, 0.131 Mpx per pair) and, with ``--town DIR ORTHO_DIR``, on a generated town's orthos (600 × 600):
   wall and CPU seconds, seconds per megapixel of image pair, annealing iterations, births, µs per birth;
   on the town, the joint model alone, with the height term, and with the height term less the step term.

numba runs on one thread (``NUMBA_NUM_THREADS=1`` is set before numba loads). **Cold** is measured in a
child process with an empty numba cache (``NUMBA_CACHE_DIR`` a fresh temporary folder): the first
``detect`` on a LEVIR-CD pair (every kernel it uses compiled) and then the same call again in that process
(warm); "compile" is their difference. The kernel and whole-run figures that follow are warm (kernels loaded
from the worktree's cache). The machine is shared: CPU seconds and the load average are printed with the
wall times.

Usage::

    .venv/bin/python bench/bench_mpp.py [--repeat 3] [--no-cold] [--pairs 5] [--town sample_aoi /tmp/ortho_run]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
import warnings
from pathlib import Path

os.environ.setdefault("NUMBA_NUM_THREADS", "1")

import numpy as np  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data" / "levircd_building_change_samples"
sys.path.insert(0, str(REPO))


def _png(path):
    import rasterio
    from rasterio.errors import NotGeoreferencedWarning

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NotGeoreferencedWarning)
        with rasterio.open(path) as ds:
            return ds.read()


def kernel_bench(repeat: int) -> dict:
    from geocd.mpp import _kernels as K
    from geocd.mpp.features import image_features
    from geocd.mpp.model import EnergyModel, random_rectangles
    from geocd.mpp.params import MPPParams

    a = _png(sorted((DATA / "A").glob("*.png"))[0])
    p = MPPParams()
    f = image_features(a, 0.5, p)
    m = EnergyModel([f], 0.5, p)
    rects = random_rectangles(f, 400, m.smin, m.smax, 5.0, np.random.default_rng(0))
    e8 = f.colour_mask if f.colour_mask is not None else np.zeros((0, 0), np.uint8)
    s8 = f.shadow_mask if f.shadow_mask is not None else np.zeros((0, 0), np.uint8)
    sd = f.shadow_dir or (0.0, 0.0)
    args = (
        f.grey,
        f.valid,
        f.grad_mag,
        f.grad_ori,
        e8,
        s8,
        float(sd[0]),
        float(sd[1]),
        np.zeros((0, 0), np.float32),
        2.5,
        float(m.edge_w),
        float(m.ring_w),
        float(m.shadow_w),
        3.0 * f.noise_sigma,
        2.0,
    )
    out = np.empty((len(rects), K.N_FEATURES))
    t0 = time.perf_counter()
    K.rect_features(rects[:2], *args, -np.inf, float(m.edge_w), 0.0, out[:2])
    cold = time.perf_counter() - t0
    tk, tr = [], []
    for _ in range(repeat):
        t0 = time.perf_counter()
        K.rect_features(rects, *args, -np.inf, float(m.edge_w), 0.0, out)
        tk.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        ref = K.rect_features_ref(rects[:40], *args)
        tr.append((time.perf_counter() - t0) * len(rects) / 40)
    agree = bool(np.allclose(out[:40], ref, rtol=1e-6, atol=1e-9, equal_nan=True))
    res = {
        "rectangles": len(rects),
        "kernel_us_per_rect": round(min(tk) / len(rects) * 1e6, 1),
        "numpy_us_per_rect": round(min(tr) / len(rects) * 1e6, 1),
        "ratio": round(min(tr) / min(tk), 1),
        "first_call_s": round(cold, 2),
        "agree": agree,
    }
    # the height-step kernel on a height map of the same size: noise and raised blocks 8–30 m across
    rng = np.random.default_rng(1)
    h = rng.normal(0.0, 0.2, f.grey.shape).astype(np.float32)
    for _ in range(40):
        i, j, a_, b_ = rng.integers(0, 256, 2).tolist() + rng.integers(16, 60, 2).tolist()
        h[i : i + a_, j : j + b_] += rng.uniform(3, 15)
    sargs = (h, 0.85, 0.5, float(m.edge_w), float(m.ring_w), float(m.ring_w))
    st = np.empty(len(rects))
    t0 = time.perf_counter()
    K.rect_steps(rects[:2], *sargs, st[:2])
    cold = time.perf_counter() - t0
    tk, tr = [], []
    for _ in range(repeat):
        t0 = time.perf_counter()
        K.rect_steps(rects, *sargs, st)
        tk.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        ref = K.rect_steps_ref(rects[:40], *sargs)
        tr.append((time.perf_counter() - t0) * len(rects) / 40)
    res["step_kernel"] = {
        "kernel_us_per_rect": round(min(tk) / len(rects) * 1e6, 1),
        "numpy_us_per_rect": round(min(tr) / len(rects) * 1e6, 1),
        "ratio": round(min(tr) / min(tk), 1),
        "first_call_s": round(cold, 2),
        "agree": bool(np.allclose(st[:40], ref, atol=1e-12)),
    }
    # the sub-cell edge fit on the same image and height map (one date, DSM gate on)
    fargs = (
        np.ones((len(rects), 1), bool),
        f.grad_mag[None],
        f.grad_ori[None],
        h[None],
        True,
        2.5,
        float(m.ring_w),
        0.25,
        float(m.edge_w),
        float(m.edge_w + m.ring_w),
        float(m.smin),
        float(m.smax),
    )
    t0 = time.perf_counter()
    K.fit_sides(rects[:2].copy(), *fargs)
    cold = time.perf_counter() - t0
    tk, tr = [], []
    for _ in range(repeat):
        fit = rects.copy()
        t0 = time.perf_counter()
        K.fit_sides(fit, *fargs)
        tk.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        ref = K.fit_sides_ref(rects[:40], fargs[0][:40], *fargs[1:])
        tr.append((time.perf_counter() - t0) * len(rects) / 40)
    res["edge_fit_kernel"] = {
        "kernel_us_per_rect": round(min(tk) / len(rects) * 1e6, 1),
        "numpy_us_per_rect": round(min(tr) / len(rects) * 1e6, 1),
        "ratio": round(min(tr) / min(tk), 1),
        "first_call_s": round(cold, 2),
        "agree": bool(np.allclose(fit[:40], ref, atol=1e-9)),
    }
    return res


def cold_child() -> dict:
    """First and second ``detect`` in this process (run with an empty NUMBA_CACHE_DIR)."""
    t0 = time.perf_counter()
    from geocd.mpp.detect import detect
    from geocd.mpp.params import MPPParams

    t_import = time.perf_counter() - t0
    f = sorted((DATA / "A").glob("*.png"))[0]
    a, b = _png(f), _png(DATA / "B" / f.name)
    out = {"pair": f.stem, "import_s": round(t_import, 2)}
    for key in ("cold_s", "warm_s"):
        t0, c0 = time.perf_counter(), time.process_time()
        detect(a, b, 0.5, MPPParams())
        out[key] = round(time.perf_counter() - t0, 2)
        out[key.replace("_s", "_cpu_s")] = round(time.process_time() - c0, 2)
    out["compile_s"] = round(out["cold_s"] - out["warm_s"], 2)
    return out


def cold_bench() -> dict:
    import subprocess
    import tempfile

    with tempfile.TemporaryDirectory(prefix="geocd_numba_cold_") as cache:
        env = dict(os.environ, NUMBA_CACHE_DIR=cache, NUMBA_NUM_THREADS="1")
        r = subprocess.run(
            [sys.executable, __file__, "--cold-child"], env=env, capture_output=True, text=True, check=True
        )
    return json.loads(r.stdout.strip().splitlines()[-1])


def run_bench(image_a, image_b, posting, repeat, **kw) -> dict:
    from geocd.mpp.detect import detect
    from geocd.mpp.params import MPPParams

    p = MPPParams(**kw.pop("params", {}))
    best = None
    for _ in range(repeat):
        t0, c0 = time.perf_counter(), time.process_time()
        det = detect(image_a, image_b, posting, p, **kw)
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        if best is None or wall < best[0]:
            best = (wall, cpu, det)
    wall, cpu, det = best
    mpx = 2 * image_a.shape[-1] * image_a.shape[-2] / 1e6
    r = det.result
    return {
        "cells": list(image_a.shape[-2:]),
        "wall_s": round(wall, 2),
        "cpu_s": round(cpu, 2),
        "s_per_mpx_pair": round(wall / mpx, 1),
        "cpu_s_per_mpx_pair": round(cpu / mpx, 1),
        "iterations": r.iterations,
        "converged": r.converged,
        "births": r.births,
        "us_per_birth": round(wall / max(r.births, 1) * 1e6, 1),
        "rectangles": len(r),
    }


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--town", nargs=2, default=None, metavar=("TOWN", "ORTHO_DIR"))
    ap.add_argument("--no-cold", action="store_true", help="skip the cold (empty numba cache) run")
    ap.add_argument("--pairs", type=int, default=5, help="how many LEVIR-CD pairs to run (of 5)")
    ap.add_argument("--cold-child", action="store_true", help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.cold_child:
        print(json.dumps(cold_child()))
        return
    res = {"load_average": os.getloadavg(), "numba_threads": os.environ.get("NUMBA_NUM_THREADS")}
    if not a.no_cold:
        res["cold"] = cold_bench()
        print("cold (empty numba cache):", res["cold"], flush=True)
    res["kernel"] = kernel_bench(a.repeat)
    print("energy kernel:", res["kernel"], flush=True)
    runs = {}
    for f in sorted((DATA / "A").glob("*.png"))[: a.pairs]:
        runs[f.stem] = run_bench(_png(f), _png(DATA / "B" / f.name), 0.5, max(1, a.repeat - 2))
        print(f.stem, runs[f.stem], flush=True)
    res["levir"] = runs
    if a.town:
        sys.path.insert(0, str(REPO / "bench" / "figures"))
        from mpp_show import _town_inputs  # noqa: E402

        inp = _town_inputs(Path(a.town[0]), Path(a.town[1]))
        dsms = {"dsm_a": inp["dsm_a"], "dsm_b": inp["dsm_b"], "ground_m": inp["ground"]}
        for label, kw in (
            ("joint", {}),
            ("joint + height", {"params": {"height": "and"}, **dsms}),
            ("joint + height, no step term", {"params": {"height": "and", "step": "off"}, **dsms}),
        ):
            res[f"town {label}"] = run_bench(
                inp["image_a"],
                inp["image_b"],
                inp["grid"].posting_m,
                1,
                valid_a=inp["valid_a"],
                valid_b=inp["valid_b"],
                **kw,
            )
            print("town", label, res[f"town {label}"], flush=True)
    res["load_average_end"] = os.getloadavg()
    print(json.dumps(res, indent=2))


if __name__ == "__main__":
    main()
