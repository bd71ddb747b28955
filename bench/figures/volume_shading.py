"""Slope shading in the octree's relighting, measured: a Lambertian ratio on the lit → lit pixels.

Runs ``bench/figures/volume_categories.py`` (the 3×3 detection with a DSM's shadows, and Carlotto's baseline, split by
pixel category) with the relighting's lit → lit pixels scaled by the ratio of each surface point's direct
irradiance under the image's sun to that under the trained sun, from the normals of the shadow DSM::

    r = (max(n·s_to, 0) + k) / (max(n·s_from, 0) + k),   k = sky · (0.6 + 0.4 n_up)

(``--sky 0``: the bare cosine ratio, both cosines floored at 0.1). Normals (``--normals``):

* ``cell``: the DSM's central differences (1 m baseline at 0.5 m);
* ``window``: a least-squares plane over the stereo matching window (``StereoParams().window`` cells), the
  finest slope a stereo DSM holds;
* ``window-ground``: as ``window`` on raised cells, and the slope of the DSM's own ground model
  (:func:`geocd.change.dsm_buildings.ground_model`) on cells less than ``min_height_m`` above it.

Not an option of geocd: no form of it was a gain on most scenes (docs/volume.md, "Slope shading in the
relighting").

Usage::

    .venv/bin/python bench/figures/volume_shading.py --normals window-ground [--sky 0] [--on-surface M] [--damp fit] SCENE WORK DSM OUT.json
"""

import argparse
import runpy
import sys
from pathlib import Path

import numpy as np
from scipy import ndimage as ndi

import geocd.volume.relight as R
from geocd.change.dsm_buildings import DSMBuildingParams, ground_model
from geocd.stereo.params import StereoParams

ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
ap.add_argument("--normals", choices=("cell", "window", "window-ground"), required=True)
ap.add_argument("--sky", type=float, default=0.0, help="sky irradiance / direct sun irradiance (0: bare cosines)")
ap.add_argument(
    "--on-surface",
    type=float,
    default=None,
    metavar="M",
    help="scale only pixels whose surface point lies within M metres of the DSM's height there (not walls)",
)
ap.add_argument(
    "--damp",
    choices=("off", "fit"),
    default="off",
    help="fit: raise the ratio to the power γ that the image itself gives (least squares of log(I/E) on "
    "log r over the pixels whose ratio departs from the median by > 10 %%)",
)
ap.add_argument("rest", nargs=4, metavar="SCENE WORK DSM OUT.json")
args = ap.parse_args()


def slopes(dsm: np.ndarray, posting_m: float, mode: str) -> tuple[np.ndarray, np.ndarray]:
    """dz/d(column), dz/d(row) in m/m."""
    z = np.where(np.isfinite(dsm), dsm, np.nanmedian(dsm))
    if mode == "cell":
        g_row, g_col = np.gradient(z, posting_m)
        return g_col, g_row
    w = StereoParams().window
    x = np.arange(w) - (w - 1) / 2
    k = x / (x * x).sum() / posting_m
    g_col = ndi.uniform_filter1d(ndi.correlate1d(z, k, axis=1, mode="nearest"), w, axis=0, mode="nearest")
    g_row = ndi.uniform_filter1d(ndi.correlate1d(z, k, axis=0, mode="nearest"), w, axis=1, mode="nearest")
    if mode == "window-ground":
        dtm = ground_model(dsm, posting_m)[0].astype(np.float64)
        t_row, t_col = np.gradient(dtm, posting_m)
        low = z - dtm < DSMBuildingParams().min_height_m
        g_col, g_row = np.where(low, t_col, g_col), np.where(low, t_row, g_row)
    return g_col, g_row


def ratio_map(dsm, posting_m, sun_from, sun_to) -> np.ndarray:
    g_col, g_row = slopes(dsm, posting_m, args.normals)
    n = np.stack([-g_col, g_row, np.ones_like(g_col)], -1)  # east, north, up (rows run south)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    c_to, c_from = n @ R.sun_vector_enu(sun_to), n @ R.sun_vector_enu(sun_from)
    if args.sky > 0:
        sky = args.sky * (0.6 + 0.4 * n[..., 2])
        return (np.maximum(c_to, 0) + sky) / (np.maximum(c_from, 0) + sky)
    return np.maximum(c_to, 0.1) / np.maximum(c_from, 0.1)


plain = R.relight_mapping


def shaded(model, intensity, camera, b, sun_from, sun_to, **kw):
    dsm, grid = R.check_shadow_dsm(model, kw["shadow_dsm"])
    r = ratio_map(dsm, grid.posting_m, sun_from, sun_to)

    def scale(depth):
        (rs, zs), h = R.surface_dsm_sample(model, camera, depth, [r, dsm], grid)
        if args.on_surface is not None:
            rs = np.where(np.abs(h - zs) <= args.on_surface, rs, np.nan)
        return rs

    gamma = 1.0
    if args.damp == "fit":
        from geocd.volume.render import render_image

        base = render_image(model, camera, intensity.shape, app_bin=b, name="damping pass")
        rs = scale(base.depth_m)
        ok = np.isfinite(rs) & np.isfinite(intensity) & (base.expected > 0.05) & (intensity > 0.05)
        lr, li = np.log(rs[ok]), np.log(intensity[ok] / base.expected[ok])
        dev = np.abs(lr - np.median(lr)) > 0.1
        if dev.sum() > 100:
            x, y = lr[dev] - lr[dev].mean(), li[dev] - li[dev].mean()
            gamma = float(np.clip((x * y).sum() / (x * x).sum(), 0.0, 1.0))
    kw["lit_scale"] = (lambda depth: scale(depth) ** gamma) if gamma != 1.0 else scale
    mapping, info = plain(model, intensity, camera, b, sun_from, sun_to, **kw)
    info["shading"] = {"normals": args.normals, "sky": args.sky, "on_surface_m": args.on_surface, "gamma": gamma}
    print(f"shading gamma {gamma:.3f}", flush=True)
    return mapping, info


R.relight_mapping = shaded
sys.argv = [str(Path(__file__).with_name("volume_categories.py"))] + args.rest
runpy.run_path(sys.argv[0], run_name="__main__")
