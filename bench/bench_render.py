"""Rendering speed of the scene simulator (geocd.synth): pixels per second for one view.

Scene: the sample_aoi town (``SynthParams()``: seed 0, 300 m × 300 m, 0.5 m GSD), one
satellite view (``--view``, default ``A_sat2``, about 740 × 750 pixels) and one aerial frame.
Per view, in the same run:

* **render**: :func:`geocd.synth.render.render_view` — k × k rays per pixel (``--supersample``,
  default 2 as in sample_aoi), each with a shadow ray, textures and shading, plus the ray
  generation from the camera (physical pushbroom / frame camera);
* **trace**: the geometry-only kernel (first hit) on the same primary rays;
* **baseline**: the pure-numpy reference (:func:`geocd.synth._kernels.first_hit_ref`, brute force over
  every object, terrain sampled every 1 cm) on a subset of the same rays; the ratio
  trace / baseline is the speed-up of the numba ray caster over the obvious numpy code.

numba is warmed up first (compile / cache load never counts); each figure is the best of
``--repeat`` runs. numba uses all threads unless ``--threads`` is given.

Usage::

    .venv/bin/python bench/bench_render.py [--view A_sat2] [--supersample 2] [--repeat 3] [--threads N]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def best_time(fn, repeat: int) -> tuple[float, object]:
    best, out = float("inf"), None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--view", default="A_sat2")
    ap.add_argument("--supersample", type=int, default=2)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--baseline-rays", type=int, default=3000)
    a = ap.parse_args()

    import numba

    from geocd.synth import _kernels as K
    from geocd.synth.generate import SynthParams, _sun, make_aerial_cameras, make_satellite_cameras
    from geocd.synth.render import RenderParams, camera_rays, pack_scene, render_view, scene_z_band
    from geocd.synth.scene import build_town

    if a.threads:
        numba.set_num_threads(a.threads)
    p = SynthParams()
    town = build_town(p.town_params())
    S = pack_scene(town, "A")
    sun = _sun(p, town)["A"].direction_enu()
    cams = {**make_satellite_cameras(p, town), **make_aerial_cameras(p, town)}
    rp = RenderParams(supersample=a.supersample)
    print(
        f"geocd.synth render benchmark: numba {numba.__version__}, {numba.get_num_threads()} threads, "
        f"{S.kind.shape[0]} objects, supersample {a.supersample}x{a.supersample}"
    )
    print(
        f"{'view':8s} {'size':>10s} {'render px/s':>12s} {'rays/s':>11s} {'trace rays/s':>13s} "
        f"{'numpy rays/s':>13s} {'trace/numpy':>12s}"
    )
    for name in (a.view, "A_air2"):
        cam = cams[name]
        render_view(town, "A", cam, sun, rp, scene=S, window=(0, 0, 8, 8))  # warm-up (compile / cache load)
        t_render, _ = best_time(lambda: render_view(town, "A", cam, sun, rp, scene=S), a.repeat)
        npx = cam.width * cam.height
        nrays = npx * a.supersample**2
        # geometry only, same primary rays
        k = a.supersample
        off = (np.arange(k) + 0.5) / k - 0.5
        R, C = np.meshgrid(np.arange(cam.height) + 0.5, np.arange(cam.width) + 0.5, indexing="ij")
        R = (R[..., None, None] + off[None, None, :, None]).ravel()
        C = (C[..., None, None] + off[None, None, None, :]).ravel()
        C, R = np.broadcast_arrays(C, R)
        o, d, tm = camera_rays(town, cam, C, R, scene_z_band(S))
        t = np.empty(len(tm))
        ob = np.empty(len(tm), np.int64)
        fc = np.empty(len(tm), np.int64)
        K.trace_first_hit(o[:16], d[:16], tm[:16], S, t[:16], ob[:16], fc[:16])
        t_trace, _ = best_time(lambda: K.trace_first_hit(o, d, tm, S, t, ob, fc), a.repeat)
        sel = np.random.default_rng(0).choice(len(tm), size=min(a.baseline_rays, len(tm)), replace=False)
        t_ref, (tr, obr) = best_time(lambda: K.first_hit_ref(S, o[sel], d[sel], tm[sel]), 1)
        agree = float(np.mean(obr == ob[sel]))
        r_trace = len(tm) / t_trace
        r_ref = len(sel) / t_ref
        print(
            f"{name:8s} {cam.width:>4d}x{cam.height:<5d} {npx / t_render:12.0f} {nrays / t_render:11.0f} "
            f"{r_trace:13.0f} {r_ref:13.0f} {r_trace / r_ref:11.0f}x   (render {t_render:.2f} s; "
            f"first hits agree with numpy on {100 * agree:.1f}% of the baseline rays)"
        )


if __name__ == "__main__":
    main()
