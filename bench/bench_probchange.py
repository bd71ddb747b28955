"""Time per key frame of the probabilistic change detector (issue 8), with baselines from the same run.

Setting of the thesis's experiments: a 640 × 480 key frame, n = 128 hypotheses,
4 images per epoch (3 pairs per epoch). The images are synthetic (affine RPC
views of a textured plane at 0.5 m GSD: the content does not change the work);
the key-frame variant, the object-space variant on a 640 × 480-cell AOI grid and,
as the "reconstruct, then subtract" baseline, geocd.stereo.match_pair (one pair,
then × 6 for 3 pairs per epoch) are timed on the same images.

Numba compile time never counts: everything runs once on a small crop first.

Usage::

    .venv/bin/python bench/bench_probchange.py [--repeat 2] [--bins 128]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "probchange"))

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def make_images(width: int, height: int, seed: int = 0):
    """4 + 4 affine RPC views of a textured plane (heights 200 m) and their cameras."""
    from scene import Texture, affine_rpc, local_xy

    tex = Texture(seed, extent_m=400.0, step_m=0.25)
    rng = np.random.default_rng(seed)
    par = {
        "A": [(0.0, 0.02), (0.55, 0.05), (-0.5, 0.03), (0.3, -0.45)],
        "B": [(0.05, -0.1), (-0.45, 0.02), (0.5, 0.1), (-0.2, 0.4)],
    }
    out = {}
    for e in ("A", "B"):
        out[e] = []
        for k, p in enumerate(par[e]):
            cam = affine_rpc(0.5, p, width + 60, height + 60)
            cc, rr = np.meshgrid(np.arange(width + 60) + 0.5, np.arange(height + 60) + 0.5)
            lon, lat = cam.localize(cc, rr, np.full(cc.shape, 200.0))
            img = np.clip(900 + 150 * tex(*local_xy(lon, lat)) + 3 * rng.normal(size=cc.shape), 0, 2047)
            out[e].append((img.astype(np.uint16), cam, f"{e}{k + 1}"))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--bins", type=int, default=128)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    a = ap.parse_args()

    import numba

    from geocd.geodesy import AOIGrid, from_lonlat, utm_crs_for
    from geocd.probchange import ProbChangeParams, detect_keyframe, detect_objectspace, make_view
    from geocd.stereo import StereoParams, match_pair, prepare_chip
    from scene import LAT0, LON0

    W, H = a.width, a.height
    ims = make_images(W, H)
    views = {e: [make_view(img, cam, name=n) for img, cam, n in ims[e]] for e in ("A", "B")}
    # the key window: the central W x H pixels of A1
    key_full = views["A"][0]
    key = key_full.__class__(
        key_full.name,
        tuple(
            c.__class__(np.ascontiguousarray(c.data[30 : 30 + H, 30 : 30 + W]), 30, 30, c.name, c.noise_sigma)
            for c in key_full.chips
        ),
        key_full.camera,
    )
    crs = utm_crs_for(LON0, LAT0)
    x0, y0 = from_lonlat(LON0, LAT0, crs)
    grid = AOIGrid.from_bounds(
        float(x0) - W * 0.25, float(y0) - H * 0.25, float(x0) + W * 0.25, float(y0) + H * 0.25, 0.5, crs
    )
    rng_m = (195.0, 235.0)
    p = ProbChangeParams(n_bins=a.bins, height_range_m=rng_m)
    pr = ProbChangeParams.robust(n_bins=a.bins, height_range_m=rng_m)
    sp = StereoParams(height_range_m=rng_m, pointing_correction=False)

    # warm-up on small problems (numba compilation)
    small = grid.subgrid(0, 0, 64, 64)
    kc = key.chips[0]
    key_small = key.__class__(
        key.name, (kc.__class__(np.ascontiguousarray(kc.data[:64, :64]), 30, 30, kc.name),), key.camera
    )
    detect_keyframe(key_small, views["A"][1:], views["B"], params=p.replace(n_bins=16))
    detect_keyframe(key_small, views["A"][1:], views["B"], params=pr.replace(n_bins=16))
    detect_objectspace(views["A"], views["B"], small, params=p.replace(n_bins=16))
    chips = [prepare_chip(img, name=n) for img, _, n in ims["A"][:2]]
    match_pair(chips[0], chips[1], ims["A"][0][1], ims["A"][1][1], small, params=sp)

    def best(fn) -> float:
        ts = []
        for _ in range(a.repeat):
            t = time.perf_counter()
            fn()
            ts.append(time.perf_counter() - t)
        return min(ts)

    t_key = best(lambda: detect_keyframe(key, views["A"][1:], views["B"], params=p))
    t_key_r = best(lambda: detect_keyframe(key, views["A"][1:], views["B"], params=pr))
    t_obj = best(lambda: detect_objectspace(views["A"], views["B"], grid, params=p))
    t_pair = best(lambda: match_pair(chips[0], chips[1], ims["A"][0][1], ims["A"][1][1], grid, params=sp))
    t_mvs = 6 * t_pair
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"machine: {os.cpu_count()} CPUs, numba threads {numba.get_num_threads()}, load average {load:.1f}")
    print(f"key frame {W}x{H}, n={a.bins}, 4 images per epoch (3 pairs each), best of {a.repeat}")
    print(f"{'what':48s} {'seconds':>8s} {'vs MVS':>8s}")
    rows = [
        ("probchange key frame, thesis model", t_key),
        ("probchange key frame, robust model", t_key_r),
        (f"probchange object space, {grid.width}x{grid.height} grid", t_obj),
        ("stereo match_pair, one pair (same grid)", t_pair),
        ("MVS baseline: 3 pairs per epoch x 2 epochs", t_mvs),
    ]
    for name, t in rows:
        print(f"{name:48s} {t:8.2f} {t / t_mvs:8.2f}")
    print(f"hypothesis evaluations per second (key frame, thesis): {W * H * a.bins / t_key / 1e6:.1f} M")


if __name__ == "__main__":
    main()
