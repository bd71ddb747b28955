"""Figures and tables of docs/stereo.md (issue 4's Show list).

Usage (from the repository root)::

    .venv/bin/python bench/figures/stereo_show.py s2p        # Réunion pair + Marseille triplet vs s2p's DSMs
    .venv/bin/python bench/figures/stereo_show.py ventoux    # Pléiades Ventoux pair vs SRTM
    .venv/bin/python bench/figures/stereo_show.py sample     # sample_aoi pairs vs the truth DSM
    .venv/bin/python bench/figures/stereo_show.py all

Each writes ``bench/results/stereo_<name>.json`` (numbers) and ``docs/stereo_<name>*.png``.
Real data are read in place from ../shared/data.
"""

from __future__ import annotations

import itertools
import json
import sys
import time
import warnings
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
DATA = REPO.parent / "shared" / "data"
DOCS = REPO / "docs"
sys.path.insert(0, str(REPO))

from geocd.geodesy import AOIGrid  # noqa: E402
from geocd.stereo import StereoParams, match_pair  # noqa: E402
from geocd.stereo.scene import read_chip  # noqa: E402


def nmad(x: np.ndarray) -> float:
    return float(1.4826 * np.median(np.abs(x - np.median(x))))


def compare(pd, ref: np.ndarray) -> dict:
    """Heights vs a reference DSM on the same grid, after removing the median offset."""
    both = pd.valid & np.isfinite(ref)
    d = (pd.z_m - ref)[both].astype(np.float64)
    off = float(np.median(d))
    e = d - off
    # the z band as written: valid heights + those interpolated in narrow holes (flag `filled`, not valid)
    have = np.isfinite(ref)
    bf = np.isfinite(pd.z_m) & have
    ef = (pd.z_m - ref)[bf].astype(np.float64)
    ef = ef - np.median(ef)
    return {
        "offset_m": off,
        "median_abs_m": float(np.median(np.abs(e))),
        "nmad_m": nmad(e),
        "within_1m": float(np.mean(np.abs(e) < 1.0)),
        "p95_abs_m": float(np.percentile(np.abs(e), 95)),
        "completeness_on_ref": float(pd.valid[have].mean()),
        "completeness_all": float(pd.valid.mean()),
        "cells_compared": int(both.sum()),
        "with_filled": {
            "nmad_m": nmad(ef),
            "within_1m": float(np.mean(np.abs(ef) < 1.0)),
            "completeness_on_ref": float(bf.sum() / have.sum()),
        },
    }


def decile_table(score: np.ndarray, bad: np.ndarray, n_bins: int = 10) -> dict:
    """Per score bin (equal counts; finite scores only), the fraction of ``bad`` matches, and the score's AUC
    as a detector of bad matches (higher score = worse)."""
    from scipy.stats import mannwhitneyu

    ok = np.isfinite(score)
    v, b = np.asarray(score, np.float64)[ok], np.asarray(bad, bool)[ok]
    edges = np.quantile(v, np.linspace(0, 1, n_bins + 1))
    idx = np.clip(np.searchsorted(edges, v, side="right") - 1, 0, n_bins - 1)
    frac = [float(b[idx == i].mean()) for i in range(n_bins)]
    auc = (
        float(mannwhitneyu(v[b], v[~b]).statistic / (b.sum() * (~b).sum())) if b.any() and (~b).any() else float("nan")
    )
    rises = int(sum(1 for x, y in zip(frac, frac[1:]) if y >= x))
    return {
        "edges": [float(e) for e in edges],
        "frac_bad": frac,
        "count": [int((idx == i).sum()) for i in range(n_bins)],
        "auc": auc,
        "non_decreasing_steps": f"{rises}/{n_bins - 1}",
    }


def score_table(pd, ref: np.ndarray, offset: float, n_bins: int = 10, thresh_m: float = 1.0) -> dict:
    """Per score bin (equal counts), the fraction of valid matches with |Δz| > thresh_m, for mdl/ncc/ssd."""
    both = pd.valid & np.isfinite(ref)
    bad = (np.abs(pd.z_m - ref - offset) > thresh_m)[both]
    scores = {
        "mdl": pd.score if pd.meta.get("score_kind") == "mdl" else None,
        "mdl (whole window)": pd.mdl_window,
        "1-ncc": 1.0 - pd.ncc,
        "ssd": pd.ssd,
    }
    return {name: decile_table(s[both], bad, n_bins) for name, s in scores.items() if s is not None}


def load_rpc_chip(path: Path, grid: AOIGrid, lo: float, hi: float, name: str):
    from geocd.io.cameras import load_camera

    cam = load_camera(path)
    return cam, read_chip(path, cam, grid, lo, hi, name=name, margin_px=40)


def quicklook(path: Path, panels: list[tuple[str, np.ndarray, dict]], title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(panels), figsize=(4.6 * len(panels), 4.6))
    for ax, (t, a, kw) in zip(np.atleast_1d(axes), panels):
        im = ax.imshow(a, interpolation="nearest", **kw)
        ax.set_title(t, fontsize=10)
        ax.set_xticks([])
        ax.set_yticks([])
        fig.colorbar(im, ax=ax, fraction=0.046, pad=0.03)
    fig.suptitle(title, fontsize=11)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def s2p_scene(key: str, folder: str, names) -> tuple:
    """s2p's DSM ``expected_output/<key>/dsm.tif`` (its grid, heights with NaN) and the RPC cameras and chips of
    the images ``<folder>/<name>.tif`` on that grid."""
    import rasterio

    with rasterio.open(DATA / "s2p_pleiades" / "expected_output" / key / "dsm.tif") as ds:
        grid = AOIGrid.from_raster(ds)
        ref = ds.read(1, masked=True).astype(np.float64).filled(np.nan)
    lo, hi = np.nanmin(ref) - 300, np.nanmax(ref) + 300  # only to size the image windows
    cams, chips = {}, {}
    for n in names:
        cams[n], chips[n] = load_rpc_chip(DATA / "s2p_pleiades" / folder / f"{n}.tif", grid, lo, hi, n)
    return grid, ref, cams, chips


def s2p(params: StereoParams = StereoParams()) -> dict:

    res: dict = {"params": params.to_dict()}
    sets = {
        "pair": ("input_pair", [("img_01", "img_02")]),
        "triplet": ("input_triplet", [("img_01", "img_02"), ("img_01", "img_03"), ("img_02", "img_03")]),
    }
    for key, (folder, pairs) in sets.items():
        grid, ref, cams, chips = s2p_scene(key, folder, sorted({i for p in pairs for i in p}))
        for a, b in pairs:
            t = time.perf_counter()
            pd = match_pair(chips[a], chips[b], cams[a], cams[b], grid, params=params)
            wall = time.perf_counter() - t
            c = compare(pd, ref)
            c.update(
                wall_s=wall,
                evaluations=pd.meta["evaluations"],
                levels=pd.meta["levels"],
                base_height=pd.meta["base_height_median"],
                g_median_px_per_m=pd.meta["g_median_px_per_m"],
                step_m=pd.meta["step_m"],
                flags=pd.flag_counts(),
                grid=f"{grid.width}x{grid.height}",
                height_source=pd.meta["height_source"],
            )
            c["scores"] = score_table(pd, ref, c["offset_m"])
            res[f"{key}:{a}__{b}"] = c
            print(
                key,
                a,
                b,
                {k: (round(v, 3) if isinstance(v, float) else v) for k, v in c.items() if k != "scores"},
                flush=True,
            )
            d = pd.z_m - ref - c["offset_m"]
            lo_v, hi_v = np.nanpercentile(ref, [2, 98])
            quicklook(
                DOCS / f"stereo_s2p_{key}_{a}__{b}.png",
                [
                    ("s2p DSM (m, ellipsoidal)", ref, {"vmin": lo_v, "vmax": hi_v, "cmap": "terrain"}),
                    ("geocd z (valid cells)", pd.z_m, {"vmin": lo_v, "vmax": hi_v, "cmap": "terrain"}),
                    ("geocd − s2p − offset (m)", d, {"vmin": -2, "vmax": 2, "cmap": "RdBu_r"}),
                    ("MDL score (bits/px)", pd.score, {"vmin": -3, "vmax": 0, "cmap": "viridis_r"}),
                ],
                f"s2p {key} {a}/{b}: median |dz| {c['median_abs_m']:.2f} m, completeness {c['completeness_on_ref']:.1%}",
            )
    (REPO / "bench" / "results" / "stereo_s2p.json").write_text(json.dumps(res, indent=1))
    return res


def ventoux(params: StereoParams = StereoParams()) -> dict:
    from geocd.io.cameras import load_camera
    from geocd.io.raster import read_dem
    from geocd.geodesy import from_lonlat, utm_crs_for

    root = DATA / "cnes_pleiades_ventoux"
    cams = {n: load_camera(root / f"{n}.tif") for n in ("left_image", "right_image")}
    crs = utm_crs_for(5.195, 44.206)
    # AOI: the two images' common footprint at the SRTM height of the spot
    h0 = 540.0
    from geocd.geodesy import geoid_undulation

    h_ell = h0 + float(geoid_undulation(5.195, 44.206, "egm96"))
    fps = []
    for c in cams.values():
        fp = c.footprint(h_ell)
        lon, lat = np.asarray(fp.exterior.coords).T
        x, y = from_lonlat(lon, lat, crs)
        from shapely.geometry import Polygon

        fps.append(Polygon(np.column_stack([x, y])))
    inter = fps[0].intersection(fps[1])
    l, b, r, t = inter.bounds
    grid = AOIGrid.from_bounds(l, b, r, t, 0.5, crs)
    srtm = read_dem(root / "srtm" / "N44E005.hgt", grid=grid, vertical_datum="egm96").to_ellipsoidal()
    ref = srtm.height_m.astype(np.float64)
    inside = np.zeros(grid.shape, bool)
    gx, gy = grid.xy()
    from shapely import contains_xy

    inside = contains_xy(inter, gx, gy)
    res: dict = {
        "grid": f"{grid.width}x{grid.height} at 0.5 m, {crs.to_string()}",
        "srtm": "N44E005.hgt (EGM96 → ellipsoidal)",
        "overlap_area_m2": float(inter.area),
    }
    chips = {
        n: read_chip(root / f"{n}.tif", c, grid, h_ell - 400, h_ell + 400, name=n, margin_px=40)
        for n, c in cams.items()
    }
    for label, dem in (("no prior (RPC height range, coarse-to-fine)", None), ("SRTM prior ± 30 m", srtm)):
        t0 = time.perf_counter()
        pd = match_pair(
            chips["left_image"],
            chips["right_image"],
            cams["left_image"],
            cams["right_image"],
            grid,
            dem=dem,
            params=params,
        )
        wall = time.perf_counter() - t0
        v = pd.valid & inside & np.isfinite(ref)
        d = (pd.z_m - ref)[v].astype(np.float64)
        # also at SRTM's own scale: 3-arc-second cells (~65 m × 93 m) averaged
        r_ = {
            "median_dz_m": float(np.median(d)),
            "nmad_m": nmad(d),
            "mean_dz_m": float(np.mean(d)),
            "completeness_overlap": float(pd.valid[inside].mean()),
            "completeness_overlap_with_filled": float(np.isfinite(pd.z_m)[inside].mean()),
            "cells": int(v.sum()),
            "wall_s": wall,
            "levels": pd.meta["levels"],
            "base_height": pd.meta["base_height_median"],
            "g_median_px_per_m": pd.meta["g_median_px_per_m"],
            "flags": pd.flag_counts(),
        }
        res[label] = r_
        print(label, {k: (round(x, 3) if isinstance(x, float) else x) for k, x in r_.items()}, flush=True)
        if dem is None:
            lo_v, hi_v = np.nanpercentile(ref[inside], [1, 99])
            lo_v, hi_v = lo_v - 15, hi_v + 15
            quicklook(
                DOCS / "stereo_ventoux.png",
                [
                    (
                        "SRTM 2000 (m, ellipsoidal, bilinear)",
                        np.where(inside, ref, np.nan),
                        {"vmin": lo_v, "vmax": hi_v, "cmap": "terrain"},
                    ),
                    (
                        "geocd z 2013 (valid cells)",
                        np.where(inside, pd.z_m, np.nan),
                        {"vmin": lo_v, "vmax": hi_v, "cmap": "terrain"},
                    ),
                    (
                        "geocd − SRTM (m)",
                        np.where(inside, pd.z_m - ref, np.nan),
                        {"vmin": -20, "vmax": 20, "cmap": "RdBu_r"},
                    ),
                ],
                f"Ventoux: median dz {r_['median_dz_m']:.1f} m, NMAD {r_['nmad_m']:.1f} m (SRTM is 90 m, 2000)",
            )
    (REPO / "bench" / "results" / "stereo_ventoux.json").write_text(json.dumps(res, indent=1))
    return res


def visibility(cam, grid: AOIGrid, dsm: np.ndarray, tol_m: float = 0.3, step_m: float = 0.25) -> np.ndarray:
    """Cells of ``grid`` whose surface point (``dsm``) the camera sees: inside the image and not occluded.

    Marches each cell's line of sight towards the camera (``X − A·t`` at height ``z + t``, with
    ``A = (∂u/∂(x,y))⁻¹ ∂u/∂z`` the local relief displacement) and checks that the DSM stays
    below it.
    """
    from scipy import ndimage

    x, y = grid.xy()
    z = np.where(np.isfinite(dsm), dsm, np.nanmin(dsm)).astype(np.float64)
    pr = cam.ground_projector(x, y, grid.crs)
    c, r = pr.project(z)
    inside = (c >= 0) & (r >= 0) & (c < cam.width) & (r < cam.height)
    cx, rx = cam.ground_projector(x + 1.0, y, grid.crs).project(z)
    cy, ry = cam.ground_projector(x, y + 1.0, grid.crs).project(z)
    dc, dr = pr.dproj_dh(z)
    a11, a12, a21, a22 = cx - c, cy - c, rx - r, ry - r
    det = a11 * a22 - a12 * a21
    Ax = (a22 * dc - a12 * dr) / det
    Ay = (-a21 * dc + a11 * dr) / det
    seen = inside.copy()
    top = float(np.nanmax(dsm))
    for t in np.arange(step_m, top - float(np.nanmin(z)) + 2 * step_m, step_m):
        active = seen & (z + t <= top + step_m)
        if not active.any():
            break
        rr, cc = grid.rowcol(x[active] - Ax[active] * t, y[active] - Ay[active] * t)
        h = ndimage.map_coordinates(dsm, [rr - 0.5, cc - 0.5], order=1, mode="nearest")
        blocked = h > z[active] + t + tol_m
        idx = np.flatnonzero(active)
        seen.flat[idx[blocked]] = False
    return seen


def sample(params: StereoParams = StereoParams()) -> dict:
    """sample_aoi: every pair of every epoch vs the truth DSM of its epoch."""
    from geocd.io.manifest import load_manifest
    from geocd.io.raster import read_dem
    from geocd.stereo.scene import default_aoi_grid, load_epoch_images

    m = load_manifest(REPO / "sample_aoi" / "scene.yaml")
    images = {e.name: load_epoch_images(m, e) for e in m.epochs}
    grid = default_aoi_grid(m, images)
    dem = read_dem(m.dem.path, grid=grid, vertical_datum=m.dem.vertical_datum).to_ellipsoidal().height_m
    sats = set(m.truth.get("satellite_images", []))
    res: dict = {"grid": f"{grid.width}x{grid.height} at {grid.posting_m} m", "params": params.to_dict(), "pairs": {}}
    pooled = []
    for e in m.epochs:
        truth = read_dem(m.truth_path(f"dsm_{e.name}"), grid=grid).height_m.astype(np.float64)
        vis = {im.name: visibility(im.camera, grid, truth) for im in images[e.name]}
        chips = {
            im.name: read_chip(
                im.path,
                im.camera,
                grid,
                float(np.nanmin(dem)) - 35,
                float(np.nanmax(dem)) + 35,
                name=im.name,
                margin_px=40,
            )
            for im in images[e.name]
        }
        for a, b in itertools.combinations(images[e.name], 2):
            kind = {2: "satellite-satellite", 0: "aerial-aerial", 1: "satellite-aerial"}[
                (a.name in sats) + (b.name in sats)
            ]
            t0 = time.perf_counter()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                pd = match_pair(
                    chips[a.name], chips[b.name], a.camera, b.camera, grid, dem=dem, params=params, epoch=e.name
                )
            wall = time.perf_counter() - t0
            both_vis = vis[a.name] & vis[b.name]
            d = (pd.z_m - truth)[pd.valid]
            r_ = {
                "kind": kind,
                "median_abs_m": float(np.median(np.abs(d))),
                "median_dz_m": float(np.median(d)),
                "nmad_m": nmad(d),
                "frac_abs_gt_1m": float(np.mean(np.abs(d) > 1.0)),
                "completeness_visible_both": float(pd.valid[both_vis].mean()),
                "visible_both_fraction": float(both_vis.mean()),
                "completeness_all": float(pd.valid.mean()),
                "base_height": pd.meta["base_height_median"],
                "g_median_px_per_m": pd.meta["g_median_px_per_m"],
                "pointing_px": pd.meta.get("pointing", {}).get("total_shift_px"),
                "wall_s": wall,
                "evaluations": pd.meta["evaluations"],
                "flags": pd.flag_counts(),
            }
            res["pairs"][f"{e.name}/{a.name}__{b.name}"] = r_
            print(
                f"{e.name}/{a.name}__{b.name}",
                {k: (round(x, 3) if isinstance(x, float) else x) for k, x in r_.items() if k != "flags"},
                flush=True,
            )
            v = pd.valid & np.isfinite(truth)
            pooled.append(
                np.stack(
                    [
                        pd.score[v],
                        pd.mdl_window[v],
                        1.0 - pd.ncc[v],
                        pd.ssd[v],
                        np.abs(pd.z_m - truth)[v],
                        (np.abs(pd.z_m - truth) * pd.g_px_per_m)[v],
                        np.full(
                            int(v.sum()), {"satellite-satellite": 0, "satellite-aerial": 1, "aerial-aerial": 2}[kind]
                        ),
                    ]
                )
            )
            if (e.name, a.name, b.name) in (
                ("A", "A_sat2", "A_sat3"),
                ("A", "A_air1", "A_air2"),
                ("A", "A_sat1", "A_air2"),
            ):
                lo_v, hi_v = np.nanpercentile(truth, [1, 99])
                quicklook(
                    DOCS / f"stereo_sample_{a.name}__{b.name}.png",
                    [
                        ("truth DSM A (m)", truth, {"vmin": lo_v, "vmax": hi_v, "cmap": "terrain"}),
                        ("geocd z (valid)", pd.z_m, {"vmin": lo_v, "vmax": hi_v, "cmap": "terrain"}),
                        ("z − truth (m)", pd.z_m - truth, {"vmin": -2, "vmax": 2, "cmap": "RdBu_r"}),
                        ("MDL score (bits/px)", pd.score, {"vmin": -3, "vmax": 0, "cmap": "viridis_r"}),
                    ],
                    f"sample_aoi {kind} {a.name}/{b.name}: median |dz| {r_['median_abs_m']:.2f} m, "
                    f"completeness (visible in both) {r_['completeness_visible_both']:.1%}",
                )
    # summaries per kind
    summ = {}
    for kind in ("satellite-satellite", "aerial-aerial", "satellite-aerial"):
        rs = [r for r in res["pairs"].values() if r["kind"] == kind]
        if rs:
            summ[kind] = {
                "pairs": len(rs),
                "median_abs_m (median over pairs)": float(np.median([r["median_abs_m"] for r in rs])),
                "worst median_abs_m": float(max(r["median_abs_m"] for r in rs)),
                "completeness_visible_both (median)": float(np.median([r["completeness_visible_both"] for r in rs])),
                "worst completeness_visible_both": float(min(r["completeness_visible_both"] for r in rs)),
            }
    res["summary"] = summ
    # score informativeness, pooled over every pair: fraction of valid matches with |Δz| > 1 m per score decile
    # (and, the paper's unit, with |Δz|·g > 1 px of disparity; and per pair kind)
    P = np.concatenate(pooled, axis=1)
    table = {}
    names = ("mdl (worst 3x3 sub-window, the score)", "mdl (whole 7x7 window)", "1-ncc", "ssd")
    kinds = {"all pairs": None, "satellite-satellite": 0, "satellite-aerial": 1, "aerial-aerial": 2}
    for i, name in enumerate(names):
        table[name] = {}
        for kname, kcode in kinds.items():
            sel = np.ones(P.shape[1], bool) if kcode is None else P[6] == kcode
            table[name][kname] = {
                "abs_dz_gt_1m": decile_table(P[i][sel], P[4][sel] > 1.0),
                "disparity_gt_1px": decile_table(P[i][sel], P[5][sel] > 1.0),
            }
            t = table[name][kname]["abs_dz_gt_1m"]
            print(
                f"{name} [{kname}] AUC {t['auc']:.3f} {t['non_decreasing_steps']} frac>1m by decile",
                [round(100 * f, 2) for f in t["frac_bad"]],
            )
    res["score_informativeness"] = table
    res["pooled_matches"] = int(P.shape[1])
    _score_plot(table, DOCS / "stereo_sample_scores.png")
    (REPO / "bench" / "results" / "stereo_sample.json").write_text(json.dumps(res, indent=1))
    return res


def _score_plot(table: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import NullFormatter, ScalarFormatter

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    for ax, (crit, label) in zip(
        axes, (("abs_dz_gt_1m", "|z − truth| > 1 m"), ("disparity_gt_1px", "|z − truth|·g > 1 px of disparity"))
    ):
        for name, t in table.items():
            t = t["all pairs"][crit]
            ax.plot(
                np.arange(1, 11),
                100 * np.array(t["frac_bad"]),
                "o-",
                label=f"{name} (AUC {t['auc']:.2f}, {t['non_decreasing_steps']} steps rise)",
            )
        ax.set_xlabel("score decile (1 = best scores)")
        ax.set_ylabel(f"% of valid matches with {label}")
        ax.set_yscale("log")
        ax.yaxis.set_major_formatter(ScalarFormatter())
        ax.yaxis.set_minor_formatter(NullFormatter())
        ax.set_title(f"sample_aoi, all 24 pairs pooled: {label}", fontsize=10)
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


if __name__ == "__main__":
    what = sys.argv[1] if len(sys.argv) > 1 else "all"
    if what in ("s2p", "all"):
        s2p()
    if what in ("ventoux", "all"):
        ventoux()
    if what in ("sample", "all"):
        sample()
    if what == "score-plot":  # redraw the score figure from bench/results/stereo_sample.json
        _score_plot(
            json.loads((REPO / "bench" / "results" / "stereo_sample.json").read_text())["score_informativeness"],
            DOCS / "stereo_sample_scores.png",
        )
