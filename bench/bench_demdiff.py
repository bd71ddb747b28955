"""Benchmark: geocd demdiff vs xDEM 0.2.3 on Mount St Helens 26→27 and 2→27 (same inputs, same masks).

Run from the repository root::

    .venv/bin/python bench/bench_demdiff.py [--xdem-python PEERS/xdem/bin/python] [--repeat 3]

xDEM runs in its own virtual environment (never a geocd dependency), by default the one ``python -m bench.peers
--install --no-measure`` makes under ``~/.cache/geocd/peers`` (``$GEOCD_PEERS``)::

    python3 -m venv PEERS/xdem && PEERS/xdem/bin/pip install xdem scikit-gstat

Both tools get, per case, the same two DEMs restricted to the survey area both epochs
share (cells where each GeoTIFF differs from the 2000 base grid ``raw_e00/1_msh00_83.e00``),
the same stable-terrain mask and the same "changed cells" mask:

* 26→27: stable = geocd's automatic stable terrain; changed = geocd's significant cells
  (95 %, regions of ≥ 4 cells).
* 2→27: almost everything changed; stable = the common-area cells with |dh| < 5 m
  (what a user might try), changed = the other common-area cells.

xDEM chain (timed inside its process, imports excluded): NuthKaab fit/apply, dh,
slope + maximum curvature, ``infer_heteroscedasticity_from_stable``,
``infer_spatial_correlation_from_stable`` (Gaussian + Spherical),
``spatial_error_propagation`` over the changed cells (as polygons). geocd chain
(warm: numba compiled, best of ``--repeat``): :func:`geocd.demdiff.dem_difference`
with the stable mask (co-registration, error model, variogram, significance,
regions, volume σ) + the volume σ over the same changed cells.

Prints wall times, their ratio (goal: geocd ≥ 5× faster), and the shift, stable
NMAD, changed area, volume ± σ of both tools side by side. Both ratios are printed: in
process (warm, imports excluded, the stable mask given) and whole process against whole
process — ``geocd demdiff A.tif B.tif --base BASE`` as a user runs it (its own stable terrain; cold:
an empty numba cache, then warm) against xDEM's whole worker process (imports included). Without the xDEM venv it
says "xdem not available" and prints geocd's figures only.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench._memwatch import geocd_command, geocd_env, run_process  # noqa: E402
from bench.peers.install import PEERS, executable, peers_dir  # noqa: E402

DATA = Path(os.environ.get("GEOCD_SHARED_DATA", REPO.parent / "shared" / "data")) / "usgs_msh_dome_dems"

XDEM_WORKER = r"""
import json, sys, time, warnings
import numpy as np
warnings.filterwarnings("ignore")
t_imp = time.perf_counter()
import geopandas as gpd
import rasterio.features
import xdem
from affine import Affine
from rasterio.crs import CRS
from shapely.geometry import shape
t_imp = time.perf_counter() - t_imp
d = np.load(sys.argv[1])
meta = json.loads(str(d["meta"]))
tr = Affine(*meta["transform"])
crs = CRS.from_wkt(meta["crs"])
A, B = d["a"], d["b"]
stable, changed = d["stable"].astype(bool), d["changed"].astype(bool)
out = {"import_s": t_imp, "xdem_version": xdem.__version__}
t0, c0 = time.perf_counter(), time.process_time()
ref = xdem.DEM.from_array(np.where(np.isfinite(A), A, -9999.0).astype("float32"), tr, crs, nodata=-9999.0)
tba = xdem.DEM.from_array(np.where(np.isfinite(B), B, -9999.0).astype("float32"), tr, crs, nodata=-9999.0)
nk = xdem.coreg.NuthKaab()
nk.fit(ref, tba, inlier_mask=stable)
aff = nk.meta["outputs"]["affine"]
out["shift_m"] = [float(aff["shift_x"]), float(aff["shift_y"]), float(aff["shift_z"])]
out["n_fit"] = int(nk.meta["outputs"].get("random", {}).get("subsample_final", -1))
aligned = nk.apply(tba, resample=True)
t1 = time.perf_counter()
dh = aligned - ref
dha = dh.data.filled(np.nan).astype(float)
out["stable_nmad_m"] = float(xdem.spatialstats.nmad(dha[stable & np.isfinite(dha)]))
slope, maxc = xdem.terrain.get_terrain_attribute(ref, attribute=["slope", "max_curvature"])
out["failed"] = []
try:
    errors, df_bin, err_fun = xdem.spatialstats.infer_heteroscedasticity_from_stable(
        dvalues=dh, list_var=[slope, maxc], list_var_names=["slope", "maxc"], stable_mask=stable)
except Exception as exc:  # too few stable cells: fall back to a constant error (the stable NMAD)
    out["failed"].append(f"heteroscedasticity: {exc}")
    errors = dh.copy(new_array=np.full(dha.shape, out["stable_nmad_m"], dtype="float32"))
t2 = time.perf_counter()
z = dh / errors
params = None
try:
    emp, params, corr = xdem.spatialstats.infer_spatial_correlation_from_stable(
        dvalues=z, list_models=["Gaussian", "Spherical"], stable_mask=stable, random_state=42)
except Exception as exc:
    out["failed"].append(f"variogram: {exc}")
t3 = time.perf_counter()
ch = changed & np.isfinite(dha)
se = float("nan")
if params is not None:
    polys = [shape(g) for g, v in rasterio.features.shapes(ch.astype("uint8"), mask=ch, transform=tr) if v == 1]
    gdf = gpd.GeoDataFrame(geometry=polys, crs=crs)
    try:
        se = xdem.spatialstats.spatial_error_propagation(areas=[gdf], errors=errors, params_variogram_model=params)[0]
    except Exception as exc:
        out["failed"].append(f"propagation: {exc}")
t4, c4 = time.perf_counter(), time.process_time()
cell = abs(tr.a * tr.e)
n = int(ch.sum())
out.update(n_changed=n, changed_area_m2=n * cell, volume_m3=float(np.nansum(dha[ch]) * cell),
           volume_sigma_m3=float(se * n * cell), mean_sigma_m=float(se),
           variogram=params[["model", "range", "psill"]].to_dict("list") if params is not None else None,
           wall_s={"coreg": t1 - t0, "heteroscedasticity": t2 - t1, "variogram": t3 - t2, "propagation": t4 - t3,
                   "total": t4 - t0}, cpu_s=c4 - c0)
print(json.dumps(out))
"""


def load_case(a: int, b: int):
    from geocd.io.e00 import read_e00_dem
    from geocd.io.raster import read_dem
    from geocd.demdiff import survey_footprint

    base = read_e00_dem(DATA / "raw_e00" / "1_msh00_83.e00")
    da = read_dem(DATA / "geotiff_utm10n" / f"{a}.tif")
    db = read_dem(DATA / "geotiff_utm10n" / f"{b}.tif")
    obs = survey_footprint(da.height_m, base.height_m) & survey_footprint(db.height_m, base.height_m)
    return da, db, obs


def masks_for(case: str, da, db, obs):
    from geocd.demdiff import dem_difference

    if case == "26-27":
        r = dem_difference(da, db, observed=obs, epoch_a="26", epoch_b="27")
        return r.stable, r.changed
    dh = db.height_m.astype(float) - da.height_m
    stable = obs & (np.abs(dh) < 5.0)
    return stable, obs & ~stable


def run_geocd(da, db, obs, stable, changed, repeat: int):
    from geocd.demdiff import dem_difference
    from geocd.io.raster import DEM

    B = DEM(np.where(obs, db.height_m, np.nan).astype(np.float32), db.grid, db.vertical_datum)
    A = DEM(np.where(obs, da.height_m, np.nan).astype(np.float32), da.grid, da.vertical_datum)
    best = best_cpu = np.inf
    r = None
    for _ in range(repeat):
        t, c = time.perf_counter(), time.process_time()
        r = dem_difference(A, B, stable_mask=stable, epoch_a="a", epoch_b="b")
        cell = r.posting_xy_m[0] * r.posting_xy_m[1]
        same = changed & np.isfinite(r.dh_m)
        vs = r.uncertainty.volume_sigma_m3(same, cell) if r.uncertainty is not None else float("nan")
        vs_random = r.uncertainty.volume_sigma_m3(same, cell, include_bias=False) if r.uncertainty else float("nan")
        best, best_cpu = min(best, time.perf_counter() - t), min(best_cpu, time.process_time() - c)
    s = r.summary
    out = {
        "shift_m": s["shift_applied_m"],
        "fitted_shift_m": s["shift_fitted_m"],
        "shift_sigma_m": s["shift_sigma_m"],
        "coreg": f"{r.coreg.status}/{r.coreg.applied}",
        "reasons": list(r.coreg.reasons),
        "n_fit": r.coreg.n_fit,
        "stable_nmad_m": s["stable_nmad_m"],
        "n_changed": int(same.sum()),
        "changed_area_m2": float(same.sum() * cell),
        "volume_m3": float(np.nansum(r.dh_m[same]) * cell),
        "volume_sigma_m3": vs,
        "volume_sigma_random_m3": vs_random,
        "own_changed_area_m2": s["changed_area_m2"],
        "own_volume_m3": s["volume_changed_m3"],
        "own_volume_sigma_m3": s["volume_changed_sigma_m3"],
        "wall_s": best,
        "cpu_s": best_cpu,
        "notes": list(r.notes),
        "variogram": {
            "nugget": r.uncertainty.variogram.nugget,
            "ranges_m": r.uncertainty.variogram.ranges_m,
            "sills": r.uncertainty.variogram.sills,
        }
        if r.uncertainty
        else None,
    }
    # what applying the fitted shift (as xDEM does) does to the same volume
    if r.coreg.applied != "horizontal+vertical" and any(r.coreg.fitted_shift_m[:2]):
        from geocd.demdiff import apply_shift

        Bf = apply_shift(B.height_m, r.coreg.fitted_shift_m, r.posting_xy_m)
        vf = float(np.nansum((Bf - A.height_m)[same]) * cell)
        out["volume_if_fitted_shift_applied_m3"] = vf
    return out


def xdem_inputs(npz: Path, da, db, obs, stable, changed) -> Path:
    """The xDEM worker's input file: both DEMs restricted to the common survey area, the masks, the grid."""
    meta = {"transform": list(da.grid.transform)[:6], "crs": da.grid.crs.to_wkt()}
    np.savez(
        npz,
        a=np.where(obs, da.height_m, np.nan),
        b=np.where(obs, db.height_m, np.nan),
        stable=stable,
        changed=changed,
        meta=json.dumps(meta),
    )
    return npz


def xdem_process(python: str, npz: Path) -> dict:
    """One xDEM worker process on ``npz``: its figures, or ``error`` (why it failed).

    ``process_s`` / ``process_cpu_s`` / ``peak_rss_mb``: the whole process (imports included); ``wall_s`` and
    ``cpu_s``: its chain in process (imports excluded).
    """
    worker = npz.with_name("xdem_worker.py")
    worker.write_text(XDEM_WORKER)
    p = run_process([python, str(worker), str(npz)])
    if p["returncode"] != 0:
        tail = p.get("error_tail", "").strip().splitlines()
        return {"error": tail[-1] if tail else f"exit {p['returncode']}", "command": [python, str(worker), str(npz)]}
    out = json.loads(p["stdout_tail"].strip().splitlines()[-1])
    out.update(
        process_s=p["wall_s"],
        process_cpu_s=p["cpu_s"],
        peak_rss_mb=p["peak_rss_mb"],
        command=[python, "xdem_worker.py", "in.npz"],
    )
    return out


def run_xdem(python: str, da, db, obs, stable, changed) -> dict | None:
    """xDEM's chain on the case in its own process (None: no xDEM venv or it failed)."""
    if not python or not Path(python).exists():
        return None
    with tempfile.TemporaryDirectory() as td:
        out = xdem_process(python, xdem_inputs(Path(td) / "in.npz", da, db, obs, stable, changed))
    if "error" in out:
        print(f"  xdem failed: {out['error']}")
        return None
    return out


def demdiff_command(a: int, b: int, out: Path) -> list[str]:
    """``geocd demdiff A.tif B.tif --base BASE --out OUT`` on two MSH epochs.

    ``--base``: both GeoTIFFs are the 2000 DEM with each survey pasted over its footprint; without the base geocd
    finds the shared cells as stable terrain of zero noise and calls its answer not credible.
    """
    return [
        *geocd_command(),
        "demdiff",
        str(DATA / "geotiff_utm10n" / f"{a}.tif"),
        str(DATA / "geotiff_utm10n" / f"{b}.tif"),
        "--base",
        str(DATA / "raw_e00" / "1_msh00_83.e00"),
        "--out",
        str(out),
    ]


def geocd_process(a: int, b: int) -> dict:
    """``geocd demdiff A.tif B.tif --base BASE`` as a user runs it, whole process: cold (empty numba cache), then
    warm."""
    res = {}
    with tempfile.TemporaryDirectory() as td:
        env = geocd_env(Path(td) / "numba_cache")
        for label in ("cold", "warm"):
            res[label] = run_process(demdiff_command(a, b, Path(td) / label), env=env)
    return res


def fmt_shift(s) -> str:
    return "(" + ", ".join(f"{v:+.2f}" for v in s) + ") m"


def warm_up() -> None:
    """Compile the numba kernels on a tiny problem (compile time never counts)."""
    from geocd.demdiff import dem_difference
    from geocd.geodesy import AOIGrid
    from geocd.io.raster import DEM
    from affine import Affine

    g = AOIGrid("EPSG:32610", Affine(10, 0, 0, 0, -10, 1000), 60, 60)
    rr, cc = np.mgrid[0:60, 0:60]
    a = 100 + 5 * np.sin(rr / 5.0) * np.cos(cc / 7.0) + np.random.default_rng(0).normal(scale=0.1, size=rr.shape)
    dem_difference(DEM(a.astype(np.float32), g), DEM((a + 0.2).astype(np.float32), g))


#: published figures (cited in docs/demdiff.md): Schilling et al. 2008, USGS PP 1750 ch. 8 abstract
#: (https://pubs.usgs.gov/publication/pp17508): welt of 10×10⁶ m³ before lava appeared on 2004-10-11,
#: "more than 73×10⁶ m³" by 2005-12-15 (vs 1986/2003 reference surfaces); Schilling et al. 2006, USGS SIM 2928:
#: "about 80 million cubic meters of dacite lava" erupted between October 2004 and February 2006.
PUBLISHED = [
    ("2004-10-11", 10e6, "welt before lava appeared (PP 1750-8)"),
    ("2005-12-15", 73e6, "> 73 Mm³ by 2005-12-15 (PP 1750-8)"),
    ("2006-02-09", 80e6, "≈ 80 Mm³ lava Oct 2004–Feb 2006 (SIM 2928)"),
]


def figures(out: Path) -> None:
    """Figures and tables of docs/demdiff.md (MSH pairs, MSH series, demcompare, error model)."""
    import datetime as dt

    from geocd.change.plots import plot_dh_map, plot_volume_series, _plt, _save
    from geocd.demdiff import Epoch, dem_difference, dem_time_series
    from geocd.demdiff.products import series_for_plot
    from geocd.io.e00 import read_e00_dem
    from geocd.io.raster import read_dem

    out.mkdir(parents=True, exist_ok=True)
    for a, b in ((26, 27), (2, 27)):
        da, db, obs = load_case(a, b)
        t = time.perf_counter()
        r = dem_difference(da, db, observed=obs, epoch_a=str(a), epoch_b=str(b))
        wall = time.perf_counter() - t
        s = r.summary
        note = f"stable NMAD {s['stable_nmad_m']:.2f} m; co-registration {r.coreg.status} ({r.coreg.applied})"
        if np.isfinite(s["volume_changed_sigma_m3"]):
            note += (
                f"\nchanged {s['changed_area_m2'] / 1e6:.3f} km², {s['volume_changed_m3'] / 1e6:+.3f} ± "
                f"{s['volume_changed_sigma_m3'] / 1e6:.3f} Mm³ (1σ)"
            )
        else:
            note += (
                f"\nno stable terrain: σ unknown; net {s['volume_net_observed_m3'] / 1e6:+.2f} Mm³ over the common area"
            )
        p = plot_dh_map(
            np.where(obs, r.dh_m, np.nan),
            r.grid,
            out / f"msh_{a}_{b}_dh.png",
            sign=r.sign,
            backdrop_m=da.height_m,
            backdrop_posting_xy_m=r.posting_xy_m,
            title=f"Mount St Helens {a} → {b}: Δh over the common survey area",
            note=note,
            vmax=20 if a == 26 else 200,
        )
        print(f"{p}: {r.coreg.summary()} | {note.replace(chr(10), ' | ')} | {wall:.2f} s")
        if a == 26:
            plt = _plt()
            fig, ax = plt.subplots(1, 2, figsize=(11, 4))
            u = r.uncertainty
            tb = u.error_model.table
            xs = [0.5 * (t_["slope_lo_deg"] + t_["slope_hi_deg"]) for t_ in tb]
            ax[0].scatter(
                xs,
                [t_["nmad_m"] for t_ in tb],
                s=[4 + t_["n"] / 40 for t_ in tb],
                c="k",
                label="stable-terrain bins (NMAD)",
            )
            ss = np.linspace(0, 60, 61)
            for qv, ls in ((0.0, "-"), (float(np.nanmedian([t_["q_hi"] for t_ in tb])), "--")):
                ax[0].plot(
                    ss,
                    u.error_model.sigma(np.radians(ss), np.full(ss.shape, qv)),
                    ls,
                    label=f"model σ(slope, curvature={qv:.1f})",
                )
            ax[0].set_xlabel("slope (°)")
            ax[0].set_ylabel("σ of dh (m)")
            ax[0].legend(fontsize=8)
            ax[0].set_title("26 → 27: heteroscedasticity on stable terrain", fontsize=9)
            vg = u.variogram
            lags = np.asarray(vg.lags_m)
            gam = np.asarray(vg.gamma)
            ax[1].semilogx(lags, gam, "ko", ms=3, label="empirical (all stable pairs, FFT)")
            ll = np.geomspace(max(lags.min(), 1), lags.max(), 200)
            ax[1].semilogx(
                ll,
                vg.semivariance(ll),
                "r-",
                label=f"nugget {vg.nugget:.2f} + sph {vg.ranges_m[0]:.0f} m ({vg.sills[0]:.2f})"
                + (f" + sph {vg.ranges_m[1]:.0f} m ({vg.sills[1]:.2f})" if len(vg.ranges_m) > 1 else ""),
            )
            ax[1].set_xlabel("lag (m)")
            ax[1].set_ylabel("semivariance of z")
            ax[1].legend(fontsize=8)
            ax[1].set_title("26 → 27: variogram of standardized stable residuals", fontsize=9)
            print(_save(fig, out / "demdiff_error_model.png"))
    # demcompare control
    ref = read_dem(DATA.parent / "cnes_demcompare_srtm" / "srtm_ref.tif")
    sec = read_dem(DATA.parent / "cnes_demcompare_srtm" / "srtm_blurred_and_shifted.tif")
    t = time.perf_counter()
    r = dem_difference(ref, sec, epoch_a="srtm_ref", epoch_b="blurred_and_shifted")
    wall = time.perf_counter() - t
    px = r.coreg.shift_px
    print(
        f"demcompare: shift {px[0]:+.3f}, {px[1]:+.3f} px (E, N) ± {r.coreg.shift_sigma_m[0] / r.posting_xy_m[0]:.3f}, "
        f"{r.coreg.shift_sigma_m[1] / r.posting_xy_m[1]:.3f} px; NMAD {r.coreg.nmad_before_m:.2f} → "
        f"{r.summary['stable_nmad_m']:.2f} m; changed {r.summary['changed_area_m2'] / 1e6:.2f} km² "
        f"({100 * r.changed.sum() / r.observed.sum():.2f} % of cells); {wall:.1f} s"
    )
    plot_dh_map(
        r.dh_m,
        r.grid,
        out / "demdiff_demcompare_dh.png",
        sign=r.sign,
        backdrop_m=r.height_a_m,
        backdrop_posting_xy_m=r.posting_xy_m,
        vmax=20,
        title=f"demcompare SRTM vs blurred copy shifted (3, 5) px: found ({px[0]:+.2f}, {-px[1]:+.2f}) px",
        note=f"Δh after co-registration; stable NMAD {r.summary['stable_nmad_m']:.2f} m; outlines: "
        f"'changed' at 95 % = the blur on ridges and valleys",
    )
    # the series
    meta = json.loads((DATA / "dem.json").read_text())
    dates = {int(m["filename"].split("_")[0]): dt.date.fromisoformat(m["date"].replace("_", "-")) for m in meta}
    eps = [Epoch(str(n), dates[n], read_dem(DATA / "geotiff_utm10n" / f"{n}.tif")) for n in range(2, 28)]
    base = Epoch("2000", dates[1], read_e00_dem(DATA / "raw_e00" / "1_msh00_83.e00"))
    t = time.perf_counter()
    ts = dem_time_series(eps, base=base)
    wall = time.perf_counter() - t
    series, bars = series_for_plot(ts)
    ref_pts = [
        {
            "label": "published (Schilling et al. 2006, 2008; vs 1986/2003 surfaces)",
            "dates": [dt.date.fromisoformat(d) for d, _, _ in PUBLISHED],
            "values": [v for _, v, _ in PUBLISHED],
        }
    ]
    print(
        plot_volume_series(
            series,
            out / "msh_timeseries.png",
            reference=ref_pts,
            bars=bars,
            title="Mount St Helens dome 2004–2007: volume change (1σ error bars)",
        )
    )
    print(f"series: {len(ts.table)} comparisons in {wall:.1f} s")
    print("| interval | dates | common area km² | coreg | stable NMAD m | net volume Mm³ | cumulative Mm³ |")
    print("|---|---|---|---|---|---|---|")
    for row in ts.table:
        if row["kind"] != "interval":
            continue
        print(
            f"| {row['epoch_a']}→{row['epoch_b']} | {row['date_a']} → {row['date_b']} | "
            f"{row['observed_area_m2'] / 1e6:.2f} | {row['coreg_applied']} | {row['stable_nmad_m']:.2f} | "
            f"{row['volume_net_m3'] / 1e6:+.2f} ± {row['volume_net_sigma_m3'] / 1e6:.2f} | "
            f"{row['cumulative_net_m3'] / 1e6:.1f} ± {row['cumulative_net_sigma_m3'] / 1e6:.1f} |"
        )
    print("| base → epoch | date | survey area km² | stable cells | net volume vs 2000 Mm³ |")
    print("|---|---|---|---|---|")
    for row in ts.table:
        if row["kind"] != "vs_base":
            continue
        sg = row.get("volume_net_sigma_m3", float("nan"))
        sgs = f" ± {sg / 1e6:.1f}" if sg is not None and np.isfinite(sg) else " (σ unknown: no stable terrain)"
        print(
            f"| 2000→{row['epoch_b']} | {row['date_b']} | {row['observed_area_m2'] / 1e6:.2f} | {row['n_stable']} | "
            f"{row['volume_net_m3'] / 1e6:.1f}{sgs} |"
        )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--xdem-python", default=str(executable(PEERS["xdem"], peers_dir())))
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument(
        "--figures",
        type=Path,
        default=None,
        metavar="DIR",
        help="instead of the benchmark, draw the figures of docs/demdiff.md into DIR and print its tables",
    )
    args = ap.parse_args()
    if not DATA.is_dir():
        sys.exit(f"data not found: {DATA}")
    warm_up()
    if args.figures is not None:
        figures(args.figures)
        return
    have_xdem = Path(args.xdem_python).exists()
    if not have_xdem:
        print(f"xdem not available ({args.xdem_python} missing): printing geocd's figures only")
    ratios = []
    for case, (a, b) in {"26-27": (26, 27), "2-27": (2, 27)}.items():
        da, db, obs = load_case(a, b)
        stable, changed = masks_for(case, da, db, obs)
        g = run_geocd(da, db, obs, stable, changed, args.repeat)
        x = run_xdem(args.xdem_python, da, db, obs, stable, changed) if have_xdem else None
        print(
            f"\n=== MSH {a} → {b}: common survey area {int(obs.sum())} cells, stable mask {int(stable.sum())} cells, "
            f"changed mask {int(changed.sum())} cells ==="
        )
        rows = [("", "geocd", "xDEM 0.2.3" if x else "xdem not available")]
        rows.append(("shift applied (E, N, Z)", fmt_shift(g["shift_m"]), fmt_shift(x["shift_m"]) if x else "-"))
        rows.append(("shift fitted ± 1σ", fmt_shift(g["fitted_shift_m"]) + " ± " + fmt_shift(g["shift_sigma_m"]), "-"))
        rows.append(
            ("co-registration", f"{g['coreg']} on {g['n_fit']} cells", f"applied on {x['n_fit']} cells" if x else "-")
        )
        rows.append(("stable NMAD", f"{g['stable_nmad_m']:.2f} m", f"{x['stable_nmad_m']:.2f} m" if x else "-"))
        rows.append(
            (
                "changed area (same cells)",
                f"{g['changed_area_m2'] / 1e6:.3f} km²",
                f"{x['changed_area_m2'] / 1e6:.3f} km²" if x else "-",
            )
        )
        rows.append(
            (
                "volume ± 1σ (same cells)",
                f"{g['volume_m3'] / 1e6:+.3f} ± {g['volume_sigma_m3'] / 1e6:.3f} Mm³ "
                f"(random part {g['volume_sigma_random_m3'] / 1e6:.3f})",
                f"{x['volume_m3'] / 1e6:+.3f} ± {x['volume_sigma_m3'] / 1e6:.3f} Mm³" if x else "-",
            )
        )
        if "volume_if_fitted_shift_applied_m3" in g:
            rows.append(
                (
                    "geocd volume if its fitted shift were applied",
                    f"{g['volume_if_fitted_shift_applied_m3'] / 1e6:+.3f} Mm³",
                    "",
                )
            )
        rows.append(
            (
                "geocd own significant change (95 %)",
                f"{g['own_changed_area_m2'] / 1e6:.3f} km², {g['own_volume_m3'] / 1e6:+.3f} ± "
                f"{g['own_volume_sigma_m3'] / 1e6:.3f} Mm³",
                "",
            )
        )
        if x:
            vg = x["variogram"]
            rows.append(
                (
                    "variogram ranges",
                    ", ".join(f"{v:.0f}" for v in g["variogram"]["ranges_m"]) + " m" if g["variogram"] else "-",
                    ", ".join(f"{v:.0f}" for v in vg["range"]) + " m" if vg else "-",
                )
            )
            dv = g["volume_m3"] - x["volume_m3"]
            sv = float(np.hypot(g["volume_sigma_m3"], x["volume_sigma_m3"]))
            rows.append(
                (
                    "volume difference geocd − xDEM",
                    f"{dv / 1e6:+.3f} Mm³ = {dv / sv:+.1f} σ (combined)",
                    f"= {dv / x['volume_sigma_m3']:+.1f} xDEM σ",
                )
            )
            rows.append(
                (
                    "wall time (warm, imports excluded)",
                    f"{g['wall_s']:.3f} s",
                    f"{x['wall_s']['total']:.2f} s (coreg {x['wall_s']['coreg']:.2f}, hetero "
                    f"{x['wall_s']['heteroscedasticity']:.2f}, variogram {x['wall_s']['variogram']:.2f}, "
                    f"propagation {x['wall_s']['propagation']:.2f})",
                )
            )
            ratio = x["wall_s"]["total"] / g["wall_s"]
            ratios.append(ratio)
            rows.append(("speed ratio xDEM / geocd (in process, warm, stable mask given)", f"{ratio:.1f}×", ""))
            gp = geocd_process(a, b)
            for lab in ("cold", "warm"):
                c = gp[lab]
                rows.append(
                    (
                        f"whole process, geocd {lab} (`geocd demdiff A.tif B.tif --base BASE`, own stable terrain)",
                        f"{c['wall_s']:.2f} s wall, {c['cpu_s']:.2f} s CPU"
                        + ("" if c["returncode"] == 0 else f" FAILED {c.get('error_tail', '')[-200:]}"),
                        f"xDEM process {x['process_s']:.2f} s wall, {x['process_cpu_s']:.2f} s CPU → "
                        f"×{x['process_s'] / c['wall_s']:.1f} wall, ×{x['process_cpu_s'] / max(c['cpu_s'], 1e-9):.1f} CPU",
                    )
                )
        else:
            rows.append(("wall time (warm)", f"{g['wall_s']:.3f} s", "-"))
        w = max(len(r[0]) for r in rows)
        w1 = max(len(r[1]) for r in rows)
        for r in rows:
            print(f"  {r[0]:<{w}}  {r[1]:<{w1}}  {r[2]}")
        if g["reasons"]:
            print("  geocd co-registration not trusted: " + "; ".join(g["reasons"]))
        if g.get("notes"):
            print("  geocd notes: " + " | ".join(g["notes"]))
        if x and x.get("failed"):
            print("  xDEM steps that failed (fallbacks used): " + " | ".join(x["failed"]))
        if x and g["coreg"].split("/")[1] != "horizontal+vertical":
            sx = x["volume_sigma_m3"] if np.isfinite(x["volume_sigma_m3"]) else g["volume_sigma_m3"]
            print(
                f"  xDEM applied its shift; its volume differs from geocd's (shift not applied) by "
                f"{(x['volume_m3'] - g['volume_m3']) / 1e6:+.3f} Mm³ = {(x['volume_m3'] - g['volume_m3']) / sx:+.1f} σ"
            )
    if ratios:
        print(
            f"\nspeed ratio (xDEM wall / geocd wall): {', '.join(f'{r:.1f}×' for r in ratios)}; goal ≥ 5×: "
            f"{'met' if min(ratios) >= 5 else 'NOT met'}"
        )


if __name__ == "__main__":  # pragma: no cover
    main()
