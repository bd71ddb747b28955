"""Throughput of the volume model: ray-cell segments per second per core, images per minute for a 600×600 view.

Usage::

    OMP_NUM_THREADS=1 .venv/bin/python bench/bench_volume.py [--scene sample_aoi] [--model DIR]

With ``--model`` (e.g. the one ``python -m geocd.volume.evaluate`` saves), the
measurements use that trained model; otherwise a model is trained here on the
epoch-A satellite views (2 passes). The view is a 600×600 crop of a satellite
image (its RPC cropped accordingly). Numba kernels are serial (one core) and
are compiled and warmed up before any timing. The baseline measured in the same
run is the pure-numpy reference of each kernel on a subset of the same rays.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scene", default="sample_aoi")
    ap.add_argument("--model", default=None)
    ap.add_argument("--view", default="A_sat2")
    ap.add_argument("--size", type=int, default=600)
    ap.add_argument("--repeat", type=int, default=2)
    a = ap.parse_args()

    from geocd.io.manifest import load_manifest
    from geocd.io.raster import read_dem
    from geocd.volume import VolumeModel, VolumeParams, detect_change, load_model, update_model
    from geocd.volume import _kernels as K
    from geocd.volume.io import geometry_from_manifest, read_view
    from geocd.volume.prior import seed_from_dem
    from geocd.volume.rays import image_rays
    from geocd.volume.update import RayScratch

    man = load_manifest(a.scene)
    spec = next(im for e in man.epochs for im in e.images if im.name == a.view)
    v = read_view(spec.path, spec.camera, name=spec.name)
    rows, cols = v.intensity.shape
    n = a.size
    r0, c0 = (rows - n) // 2, (cols - n) // 2
    cam = v.camera.cropped(c0, r0, n, n)
    img = np.ascontiguousarray(v.intensity[r0 : r0 + n, c0 : c0 + n])

    if a.model:
        model = load_model(a.model)
        how = f"model {a.model}"
    else:
        geom, grid = geometry_from_manifest(man)
        model = VolumeModel.create(geom, VolumeParams(), init_depth=1)
        dem = read_dem(man.dem.path, grid=grid).height_m
        seed_from_dem(model, dem, grid)
        sats = [read_view(im.path, im.camera, name=im.name) for im in man.epoch("A").images if "sat" in im.name]
        for _ in range(2):
            for s in sats:
                update_model(model, s.intensity, s.camera, sun=s.sun, name=s.name)
        how = "model trained here (4 satellite views × 2 passes)"
    print(f"{how}: {model.n_leaves:,} leaves, {model.nbytes() / 2**20:.0f} MiB; view {a.view} crop {n}×{n}")

    # --- warm-up (compilation never counts) ---------------------------------------------------
    m_small = model.copy()
    h = n // 2
    update_model(m_small, img[h : h + 32, h : h + 32], cam.cropped(h, h, 32, 32), sun=v.sun)
    detect_change(model, img[h : h + 32, h : h + 32], cam.cropped(h, h, 32, 32), sun=v.sun)
    del m_small

    # --- kernel throughput on this view's rays --------------------------------------------------
    g = model.geometry
    geo = g.geo_array()
    sc = RayScratch(geo)
    o, d, rr, cc = image_rays(cam, g, 0, n, n, 1)
    obs = img[rr, cc]
    nn = model.n_nodes
    acc = np.zeros((4, nn))
    best = {}
    for _ in range(a.repeat):
        acc[:] = 0
        t = time.perf_counter()
        segs = K.seglen_rays(
            o,
            d,
            obs,
            g.box_lo,
            g.box_hi,
            geo,
            model.block_root,
            model.child,
            acc[0],
            acc[2],
            sc.seg_cell,
            sc.seg_len,
            sc.seg_t,
        )
        best["trace+accumulate (pass 1)"] = min(best.get("trace+accumulate (pass 1)", 1e9), time.perf_counter() - t)
        cell_obs = np.where(acc[0] > 0, acc[2] / np.maximum(acc[0], 1e-30), np.nan)
        acc[:] = 0
        t = time.perf_counter()
        K.update_rays(
            o,
            d,
            obs,
            cell_obs,
            g.box_lo,
            g.box_hi,
            geo,
            model.block_root,
            model.child,
            model.alpha,
            model.app,
            0,
            1.0,
            1.0,
            acc[0],
            acc[1],
            acc[2],
            acc[3],
            sc.seg_cell,
            sc.seg_len,
            sc.seg_t,
            sc.a,
            sc.b,
            sc.c,
            sc.d,
        )
        best["update ray pass (eqs. 20-25)"] = min(
            best.get("update ray pass (eqs. 20-25)", 1e9), time.perf_counter() - t
        )
        out = np.empty((4, o.shape[0]))
        t = time.perf_counter()
        K.render_rays(
            o,
            d,
            obs,
            g.box_lo,
            g.box_hi,
            geo,
            model.block_root,
            model.child,
            model.alpha,
            model.app,
            0,
            1.0,
            0.5,
            1.0,
            np.zeros(0),
            np.zeros(0),
            np.zeros(0),
            out[0],
            out[1],
            out[2],
            out[3],
            sc.seg_cell,
            sc.seg_len,
            sc.seg_t,
        )
        best["detect/render pass (eq. 27)"] = min(best.get("detect/render pass (eq. 27)", 1e9), time.perf_counter() - t)
    print(f"\nrays {o.shape[0]:,}, ray-cell segments per ray {segs / o.shape[0]:.1f} (total {segs:,})")
    print(f"{'kernel (1 core)':34s} {'s':>7s} {'M segments/s':>13s}")
    for k, s in best.items():
        print(f"{k:34s} {s:7.3f} {segs / s / 1e6:13.2f}")

    # numpy reference on a subset of the same rays (the baseline measured in this run)
    sub = slice(0, 300)
    t = time.perf_counter()
    K.update_rays_ref(
        o[sub],
        d[sub],
        obs[sub],
        cell_obs,
        g.box_lo,
        g.box_hi,
        geo,
        model.block_root,
        model.child,
        model.alpha,
        model.app,
        0,
        1.0,
        1.0,
        nn,
    )
    t_ref = (time.perf_counter() - t) / 300
    t_nb = best["update ray pass (eqs. 20-25)"] / o.shape[0]
    print(
        f"\nupdate pass per ray: numba {t_nb * 1e6:.2f} µs, numpy reference {t_ref * 1e6:.0f} µs "
        f"→ {t_ref / t_nb:.0f}× faster"
    )

    # --- whole operations on the 600×600 view (ray generation, both passes, finalize, refinement) ---
    m2 = model.copy()
    t = time.perf_counter()
    st = update_model(m2, img, cam, sun=v.sun, name="bench")
    t_upd = time.perf_counter() - t
    t = time.perf_counter()
    detect_change(model, img, cam, sun=v.sun)
    t_det = time.perf_counter() - t
    t = time.perf_counter()
    res = detect_change(model, img, cam, sun=(v.sun[0] + 25.0, v.sun[1] - 15.0) if v.sun else None)
    t_rel = time.perf_counter() - t
    print(
        f"\nwhole update of a {n}×{n} view: {t_upd:.2f} s → {60 / t_upd:.1f} images/minute "
        f"({st.segments / t_upd / 1e6:.2f} M segments/s end to end)"
    )
    print(f"whole change detection of a {n}×{n} view: {t_det:.2f} s → {60 / t_det:.1f} images/minute")
    if res.relight is not None:
        print(
            f"whole change detection with relighting (sun 29° away from the trained bin): {t_rel:.2f} s → "
            f"{60 / t_rel:.1f} images/minute"
        )
    print(
        f"(threads: NUMBA_NUM_THREADS={os.environ.get('NUMBA_NUM_THREADS', 'default')}, "
        f"OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', 'default')}; kernels are serial)"
    )


if __name__ == "__main__":
    main()
