"""Kahramanmaraş side by side: CARS DSM per epoch + picanteo's 3-D rule, against geocd, on the same AOI.

Peers run in their own venv (``/work/peers/cars-venv``: CARS 1.3 and Bulldozer, as ../shared/notes/peers.md
describes); nothing of theirs is imported here. Two stages:

``cars``   runs CARS on each epoch's pair (flat initial elevation at the site's geoid height, ellipsoidal
           output, 0.5 m, UTM 37N, ambiguity auxiliary band), then Bulldozer for a DTM per epoch; measures
           wall time and the peak memory of the whole process tree (RSS summed, sampled every 0.2 s).
``compare`` puts CARS's DSMs on geocd's AOI grid and compares them with geocd's pair-DEMs (median |dz|
           after the median offset, NMAD, completeness), applies picanteo's rule (DHM_post − DHM_pre ≤ −4 m,
           CARS confidence from ambiguity (1 − ambiguity) ≥ 0.5 in both epochs, regions ≥ 12 m²; no NDVI filter: these are
           panchromatic images) and scores both change maps on the same building objects.

Usage::

    .venv/bin/python bench/bench_kahramanmaras_cars.py cars --work /tmp/kahra_cars
    .venv/bin/python bench/bench_kahramanmaras_cars.py compare --work /tmp/kahra_cars --run /tmp/kahra --json bench/results/kahramanmaras_bench.json
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
DATA = (REPO.parent / "shared" / "data" / "cnes_picanteo_kahramanmaras").resolve()
CARS_VENV = Path(os.environ.get("CARS_VENV", "/work/peers/cars-venv"))
EPOCHS = {"pre_event": ("pre_event_img1", "pre_event_img2"), "post_event": ("post_event_img1", "post_event_img2")}
GEOID_HEIGHT_M = 680.0  # rough terrain height above the geoid (geocd's ellipsoidal ground ~705 m, N ≈ 25 m)


def _tree_rss(pid: int) -> int:
    """Resident memory (bytes) of a process and all its descendants."""
    total = 0
    kids = {pid}
    try:
        procs = [p for p in os.listdir("/proc") if p.isdigit()]
    except OSError:
        return 0
    parent = {}
    for p in procs:
        try:
            with open(f"/proc/{p}/stat") as f:
                parts = f.read().rsplit(")", 1)[1].split()
            parent[int(p)] = int(parts[1])
        except (OSError, IndexError, ValueError):
            continue
    changed = True
    while changed:
        changed = False
        for c, pp in parent.items():
            if pp in kids and c not in kids:
                kids.add(c)
                changed = True
    for k in kids:
        try:
            with open(f"/proc/{k}/statm") as f:
                total += int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
        except (OSError, IndexError, ValueError):
            continue
    return total


def run_measured(cmd: list[str], cwd: Path, log: Path) -> dict:
    """Run a command; wall time, CPU time of the children and peak RSS of the process tree."""
    t0 = time.perf_counter()
    r0 = os.times()
    with open(log, "w") as lf:
        p = subprocess.Popen(cmd, cwd=cwd, stdout=lf, stderr=subprocess.STDOUT)
        peak = [0]

        def sample():
            while p.poll() is None:
                peak[0] = max(peak[0], _tree_rss(p.pid))
                time.sleep(0.2)

        th = threading.Thread(target=sample, daemon=True)
        th.start()
        rc = p.wait()
        th.join()
    r1 = os.times()
    return {
        "cmd": " ".join(cmd),
        "returncode": rc,
        "wall_s": round(time.perf_counter() - t0, 1),
        "cpu_s": round((r1.children_user - r0.children_user) + (r1.children_system - r0.children_system), 1),
        "peak_rss_mb": round(peak[0] / 2**20, 0),
    }


def stage_cars(work: Path) -> dict:
    import rasterio
    from rasterio.transform import from_origin

    work.mkdir(parents=True, exist_ok=True)
    dem = work / "flat_dem.tif"
    with rasterio.open(
        dem,
        "w",
        driver="GTiff",
        width=40,
        height=40,
        count=1,
        dtype="float32",
        crs="EPSG:4326",
        transform=from_origin(36.85, 37.64, 0.004, 0.004),
    ) as ds:
        ds.write(np.full((1, 40, 40), GEOID_HEIGHT_M, np.float32))
    res = {}
    for ep, (a, b) in EPOCHS.items():
        d = work / ep
        d.mkdir(exist_ok=True)
        cfg = {
            "input": {
                "sensors": {n: {"image": str(DATA / f"{n}.tif"), "geomodel": str(DATA / f"{n}.geom")} for n in (a, b)},
                "pairing": [[a, b]],
                "initial_elevation": {"dem": str(dem)},
            },
            "output": {
                "directory": str(d / "out"),
                "resolution": 0.5,
                "epsg": 32637,
                "geoid": False,
                "auxiliary": {"ambiguity": True},
            },
            "orchestrator": {"mode": "multiprocessing", "nb_workers": 2},
        }
        (d / "config.json").write_text(json.dumps(cfg, indent=1))
        r = run_measured([str(CARS_VENV / "bin" / "cars"), str(d / "config.json")], d, d / "cars.log")
        dsm = d / "out" / "dsm" / "dsm.tif"
        r["dsm"] = str(dsm) if dsm.exists() else None
        amb = sorted((d / "out").rglob("*ambiguity*.tif"))
        r["ambiguity"] = str(amb[0]) if amb else None
        if dsm.exists():
            bcfg = d / "bulldozer.yaml"
            bcfg.write_text(f"dsm_path: {dsm}\noutput_dir: {d / 'bulldozer'}\ngenerate_dhm: True\nnb_max_workers: 2\n")
            r["bulldozer"] = run_measured([str(CARS_VENV / "bin" / "bulldozer"), str(bcfg)], d, d / "bulldozer.log")
            dhm = d / "bulldozer" / "dhm.tif"
            dtm = d / "bulldozer" / "dtm.tif"
            r["dhm"] = str(dhm) if dhm.exists() else None
            r["dtm"] = str(dtm) if dtm.exists() else None
        res[ep] = r
        print(ep, json.dumps(r), flush=True)
        with open(work / "cars_stdout.log", "a") as f:
            f.write(f"{ep} {json.dumps(r)}\n")
    (work / "cars_stage.json").write_text(json.dumps(res, indent=1))
    return res


def _to_grid(path: str, grid, resampling="bilinear") -> np.ndarray:
    import rasterio
    from rasterio.enums import Resampling
    from rasterio.warp import reproject

    out = np.full(grid.shape, np.nan, np.float32)
    with rasterio.open(path) as ds:
        src = ds.read(1).astype(np.float32)
        if ds.nodata is not None:
            src[src == ds.nodata] = np.nan
        reproject(
            src,
            out,
            src_transform=ds.transform,
            src_crs=ds.crs,
            dst_transform=grid.transform,
            dst_crs=grid.crs,
            src_nodata=np.nan,
            dst_nodata=np.nan,
            resampling=getattr(Resampling, resampling),
        )
    return out


def _dsm_stats(a: np.ndarray, ref: np.ndarray) -> dict:
    both = np.isfinite(a) & np.isfinite(ref)
    d = (a - ref)[both]
    off = float(np.median(d))
    r = d - off
    return {
        "offset_m": round(off, 2),
        "median_abs_dz_m": round(float(np.median(np.abs(r))), 3),
        "nmad_m": round(float(1.4826 * np.median(np.abs(r - np.median(r)))), 3),
        "within_1m": round(float(np.mean(np.abs(r) < 1.0)), 4),
        "completeness_geocd": round(float(np.isfinite(a).mean()), 4),
        "completeness_cars": round(float(np.isfinite(ref).mean()), 4),
    }


def stage_compare(work: Path, run_dir: Path) -> dict:
    from geocd.change.building_layer import read_building_layer
    from scipy import ndimage as ndi

    from geocd.stereo import read_pair_dem

    if (work / "cars_stage.json").is_file():
        cars = json.loads((work / "cars_stage.json").read_text())
    else:  # the cars stage still running: the epochs it finished (its stdout lines "epoch {json}")
        cars = {}
        log = work / "cars_stdout.log"
        for line in log.read_text().splitlines() if log.is_file() else []:
            ep, _, js = line.partition(" ")
            if ep in EPOCHS and js.startswith("{"):
                cars[ep] = json.loads(js)
        for ep in EPOCHS:
            cars.setdefault(ep, {})
    summary = json.loads((run_dir / "run_summary.json").read_text())
    out: dict = {
        "geocd_run": {k: summary.get(k) for k in ("orientation", "buildings", "building_damage", "changed_fraction")}
    }
    from geocd.pipeline import run_orientation

    out["geocd_run"]["orientation"] = run_orientation(run_dir, summary)
    geocd_dsm, cars_dsm = {}, {}
    grid = None
    for ep, (a, b) in EPOCHS.items():
        pd = read_pair_dem(run_dir / "stereo" / ep / f"{a}__{b}.tif")
        grid = pd.grid
        geocd_dsm[ep] = np.where(pd.valid, pd.z_m, np.nan)
        if cars[ep].get("dsm"):
            cars_dsm[ep] = _to_grid(cars[ep]["dsm"], grid)
            out[f"dsm_{ep}"] = _dsm_stats(geocd_dsm[ep], cars_dsm[ep])
            out[f"cars_{ep}"] = {k: cars[ep][k] for k in ("wall_s", "cpu_s", "peak_rss_mb", "returncode")}
            if cars[ep].get("bulldozer"):
                out[f"bulldozer_{ep}"] = {k: cars[ep]["bulldozer"][k] for k in ("wall_s", "cpu_s", "peak_rss_mb")}

    # picanteo's 3-D rule on CARS's products
    def dhm(ep):  # Bulldozer's DHM, or DSM − Bulldozer's DTM when it wrote none
        if cars[ep].get("dhm"):
            return _to_grid(cars[ep]["dhm"], grid)
        return cars_dsm[ep] - _to_grid(cars[ep]["dtm"], grid)

    if all(cars[ep].get("dhm") or cars[ep].get("dtm") for ep in EPOCHS) and len(cars_dsm) == 2:
        dhm_pre, dhm_post = dhm("pre_event"), dhm("post_event")
        diff = dhm_post - dhm_pre
        flag = np.nan_to_num(diff, nan=0.0) <= -4.0
        amb_ok = np.ones(grid.shape, bool)
        for ep in EPOCHS:
            if cars[ep].get("ambiguity"):
                # CARS 1.3 writes the ambiguity (median 0.28 here); picanteo's filter reads CARS's
                # "confidence_from_ambiguity", its complement 1 − ambiguity, and keeps confidence ≥ 0.5
                amb = _to_grid(cars[ep]["ambiguity"], grid, "nearest")
                amb_ok &= (1.0 - np.nan_to_num(amb, nan=1.0)) >= 0.5
        flag &= amb_ok
        lab, n = ndi.label(flag)
        sizes = np.bincount(lab.ravel()) * grid.cell_area_m2
        small = sizes < 12.0
        small[0] = False
        flag[small[lab]] = False
        observed = np.isfinite(diff)
        out["picanteo_rule"] = {
            "flagged_fraction_of_observed": round(float(flag[observed].mean()), 4),
            "observed_fraction": round(float(observed.mean()), 4),
        }
        # both change maps on the same building objects (geocd's damage layer geometry)
        dmg = read_building_layer(run_dir / "sc_changes.gpkg")
        from rasterio.features import rasterize

        lab = rasterize(
            [(g, i + 1) for i, g in enumerate(dmg.geometry)],
            out_shape=grid.shape,
            transform=grid.transform,
            fill=0,
            dtype="int32",
        )
        idx = np.arange(1, len(dmg) + 1)
        frac_pic = np.asarray(ndi.sum(flag, lab, idx)) / np.maximum(np.asarray(ndi.sum(observed, lab, idx)), 1)
        pic_changed = frac_pic >= 0.15
        geocd_lowered = dmg["class"].isin(["collapsed", "partly collapsed", "lowered"]).to_numpy()
        out["buildings"] = {
            "n": int(len(dmg)),
            "geocd_lowered_classes": int(geocd_lowered.sum()),
            "picanteo_rule_changed": int(pic_changed.sum()),
            "both": int((pic_changed & geocd_lowered).sum()),
            "geocd_only": int((geocd_lowered & ~pic_changed).sum()),
            "picanteo_only": int((pic_changed & ~geocd_lowered).sum()),
            "geocd_classes": dmg["class"].value_counts().to_dict(),
        }
        dmg = dmg.assign(picanteo_frac=frac_pic.round(3), picanteo_changed=pic_changed)
        out["per_building"] = dmg.drop(columns="geometry").to_dict(orient="records")
        np.save(work / "picanteo_flag.npy", flag)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("stage", choices=["cars", "compare"])
    ap.add_argument("--work", default="/tmp/kahra_cars")
    ap.add_argument("--run", default="/tmp/kahra")
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    work = Path(args.work)
    if args.stage == "cars":
        stage_cars(work)
        return 0
    sys.path.insert(0, str(REPO))
    res = stage_compare(work, Path(args.run))
    text = json.dumps(res, indent=1, default=str)
    if args.json:
        Path(args.json).write_text(text)
    print(json.dumps({k: v for k, v in res.items() if k != "per_building"}, indent=1, default=str))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
