"""Are the cells a pair-DEM marks valid right? Valid-but-wrong, completeness and NMAD on real pairs.

For each real pair, ``match_pair`` with default parameters and *no* prior DEM (the cameras' height range, as
``geocd stereo a.tif b.tif`` runs), compared with a reference surface on the same grid:

* Réunion pair and the three Marseille triplet pairs (``../shared/data/s2p_pleiades``) against s2p's DSMs;
* Mont Ventoux (``cnes_pleiades_ventoux``, OSSIM ``.geom`` cameras, strong relief) against SRTM (a 90 m, 2000
  surface of a forested slope: only gross errors can be told there, so its threshold is 30 m, not 5 m).

Reported per pair: completeness on the reference's cells, median |dz| and NMAD of valid cells after the median
offset, the share of valid cells wrong by more than the threshold (the issue's "valid-but-wrong", goal
≤ 0.1 %) and of those wrong by more than it against every reference height within ±1 m (a blunder, not an edge
placed a cell or two off), with the flags of the cells the validity rule removed; the same for the ``z`` band as
written (valid + filled cells). ``--cars``: CARS 1.3 (its own venv) on the same pairs, its final DSM scored the
same way on the same grid.

Usage::

    python bench/eval_stereo_validity.py [--only reunion marseille ventoux] [--json bench/results/stereo_validity.json]
    python bench/eval_stereo_validity.py --save DIR   # also the per-cell bands (npz), to study the rule offline
    python bench/eval_stereo_validity.py --without --json bench/results/stereo_validity.json   # the docs' table
    python bench/eval_stereo_validity.py --set isolation_min_cells=1   # any StereoParams fields (JSON values)
    python bench/eval_stereo_validity.py --only reunion marseille --cars ~/.cache/geocd/peers/cars-1.3/bin/cars
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
from scipy import ndimage

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.figures.stereo_show import DATA, nmad, s2p_scene  # noqa: E402
from geocd.geodesy import AOIGrid, to_lonlat  # noqa: E402
from geocd.stereo import StereoParams, match_pair  # noqa: E402
from geocd.stereo.products import FLAGS  # noqa: E402

CARS_WORK = Path("geocd_out/validity_cars")
CARS_REUSE = False


def score_pair(pd, ref: np.ndarray, inside: np.ndarray, wrong_m: float) -> dict:
    """Figures of one pair-DEM against a reference on the same grid (``inside``: the cells to count)."""
    have = np.isfinite(ref) & inside
    both = pd.valid & have
    d = (pd.z_m - ref)[both].astype(np.float64)
    off = float(np.median(d)) if d.size else float("nan")
    e = d - off
    wrong = np.abs(e) > wrong_m
    # wrong even allowing a 1 m horizontal shift: beyond the reference's heights within ±1 m by the threshold
    # (an edge placed one or two cells off at a 20 m wall is not a blunder)
    k = 2 * max(1, int(round(1.0 / pd.grid.posting_m))) + 1
    rf = np.where(np.isfinite(ref), ref, np.nanmedian(ref))
    z_off = np.asarray(pd.z_m, np.float64) - off
    beyond = (z_off > ndimage.maximum_filter(rf, k) + wrong_m) | (z_off < ndimage.minimum_filter(rf, k) - wrong_m)
    blunder = beyond[both]
    raw = np.asarray(pd.z_raw_m if pd.z_raw_m is not None else pd.z_m, np.float64) - ref - off
    removed = have & ~pd.valid & np.isfinite(raw)
    flag_counts = {k: int(((pd.flags & v) > 0)[have].sum()) for k, v in FLAGS.items()} if pd.flags is not None else {}
    # the z band as written: valid heights and those interpolated in narrow holes (flag `filled`), what compares
    # with a peer's filled DSM
    bf = np.isfinite(pd.z_m) & have
    ef = np.asarray(pd.z_m, np.float64)[bf] - ref[bf] - off
    with_filled = {
        "completeness_on_ref": float(bf.sum() / max(have.sum(), 1)),
        "nmad_m": nmad(ef) if ef.size else float("nan"),
        "wrong_share": float(np.mean(np.abs(ef) > wrong_m)) if ef.size else float("nan"),
        "blunder_share": float(beyond[bf].mean()) if ef.size else float("nan"),
    }
    return {
        "offset_m": off,
        "completeness_on_ref": float(both.sum() / max(have.sum(), 1)),
        "median_abs_m": float(np.median(np.abs(e))) if e.size else float("nan"),
        "nmad_m": nmad(e) if e.size else float("nan"),
        "wrong_threshold_m": wrong_m,
        "valid_wrong_cells": int(wrong.sum()),
        "valid_wrong_share": float(wrong.mean()) if e.size else float("nan"),
        "valid_blunder_cells": int(blunder.sum()),
        "valid_blunder_share": float(blunder.mean()) if e.size else float("nan"),
        "cells_valid": int(both.sum()),
        "cells_ref": int(have.sum()),
        # of the raw matches the rule removed, how many were wrong: what the rule is worth
        "removed_cells": int(removed.sum()),
        "removed_wrong_share": float(np.mean(np.abs(raw[removed]) > wrong_m)) if removed.any() else float("nan"),
        "flags_on_ref": flag_counts,
        "with_filled": with_filled,
    }


class _PeerDSM:
    """A peer's DSM on the reference grid as :func:`score_pair` reads a pair-DEM (valid = has a height)."""

    def __init__(self, z: np.ndarray, grid: AOIGrid):
        self.z_m, self.grid, self.valid = z, grid, np.isfinite(z)
        self.z_raw_m = self.flags = None


def cars_pair(
    cars: str, work: Path, images: tuple[Path, Path], ref: np.ndarray, grid: AOIGrid, reuse: bool = False
) -> dict:
    """CARS's whole process on one pair (its own venv; config as ``bench/bench_stereo.py``'s: a flat initial
    elevation at the reference's median height, the reference's posting and CRS, ellipsoidal heights, 2
    workers), its final ``dsm/dsm.tif`` resampled (nearest) onto the reference's grid and scored like geocd's."""
    import rasterio

    from bench._memwatch import run_process
    from bench.bench_stereo import cars_config
    from geocd.io.raster import reproject_array

    work.mkdir(parents=True, exist_ok=True)
    lon, lat = to_lonlat(*grid.xy(np.array([grid.height // 2]), np.array([grid.width // 2])), grid.crs)
    config = cars_config(
        work,
        float(np.nanmedian(ref)),
        images,
        (float(lon[0]) - 0.1, float(lat[0]) + 0.1),
        int(grid.crs.to_epsg()),
        grid.posting_m,
    )
    final = work / "out" / "dsm" / "dsm.tif"
    record = work / "cars_run.json"
    if reuse and final.is_file() and record.is_file():  # a finished CARS run of the same config: score it again
        r = json.loads(record.read_text())
    else:
        r = run_process([cars, str(config)], cwd=work)
        record.write_text(json.dumps({k: r[k] for k in ("wall_s", "cpu_s", "peak_rss_mb", "returncode") if k in r}))
    out = {k: r[k] for k in ("wall_s", "cpu_s", "peak_rss_mb", "returncode") if k in r}
    if r.get("returncode") != 0 or not final.is_file():
        out["error"] = r.get("error_tail", f"no {final}")
        return out
    with rasterio.open(final) as ds:
        g = AOIGrid.from_raster(ds)
        a = ds.read(1, masked=True).astype(np.float32).filled(np.nan)
    z = reproject_array(a, g, grid, "nearest").astype(np.float64)
    out.update(score_pair(_PeerDSM(z, grid), ref, np.ones(grid.shape, bool), 5.0))
    return out


def s2p_pairs(params: StereoParams, save: Path | None, only: set[str], cars: str | None = None) -> dict:

    out = {}
    sets = {
        "reunion": ("pair", "input_pair", [("img_01", "img_02")]),
        "marseille": ("triplet", "input_triplet", [("img_01", "img_02"), ("img_01", "img_03"), ("img_02", "img_03")]),
    }
    for label, (key, folder, pairs) in sets.items():
        if label not in only:
            continue
        grid, ref, cams, chips = s2p_scene(key, folder, sorted({i for p in pairs for i in p}))
        for a, b in pairs:
            t = time.perf_counter()
            pd = match_pair(chips[a], chips[b], cams[a], cams[b], grid, params=params)
            r = score_pair(pd, ref, np.ones(grid.shape, bool), 5.0)
            r["wall_s"] = time.perf_counter() - t
            r["reference"] = f"s2p expected_output/{key}/dsm.tif"
            out[f"{label}:{a}__{b}"] = r
            _print(f"{label}:{a}__{b}", r)
            if save:
                _save(save / f"{label}_{a}__{b}.npz", pd, ref)
            if cars:
                images = tuple(DATA / "s2p_pleiades" / folder / f"{n}.tif" for n in (a, b))
                t = time.perf_counter()
                c = cars_pair(cars, CARS_WORK / f"{label}_{a}__{b}", images, ref, grid, CARS_REUSE)
                c.setdefault("wall_s", time.perf_counter() - t)
                out[f"CARS {label}:{a}__{b}"] = c
                if "error" in c:
                    print(f"CARS {label}:{a}__{b} failed: {c['error'][-300:]}", flush=True)
                else:
                    _print(f"CARS {label}:{a}__{b}", c)
    return out


def ventoux(params: StereoParams, save: Path | None) -> dict:
    from shapely import contains_xy
    from shapely.geometry import Polygon

    from geocd.geodesy import from_lonlat, geoid_undulation, utm_crs_for
    from geocd.io.cameras import load_camera
    from geocd.io.raster import read_dem
    from geocd.stereo.scene import read_chip

    root = DATA / "cnes_pleiades_ventoux"
    cams = {n: load_camera(root / f"{n}.tif") for n in ("left_image", "right_image")}
    crs = utm_crs_for(5.195, 44.206)
    h_ell = 540.0 + float(geoid_undulation(5.195, 44.206, "egm96"))
    fps = []
    for c in cams.values():
        lon, lat = np.asarray(c.footprint(h_ell).exterior.coords).T
        fps.append(Polygon(np.column_stack(from_lonlat(lon, lat, crs))))
    inter = fps[0].intersection(fps[1])
    grid = AOIGrid.from_bounds(*inter.bounds, 0.5, crs)
    ref = read_dem(root / "srtm" / "N44E005.hgt", grid=grid, vertical_datum="egm96").to_ellipsoidal().height_m
    inside = contains_xy(inter, *grid.xy())
    chips = {
        n: read_chip(root / f"{n}.tif", c, grid, h_ell - 400, h_ell + 400, name=n, margin_px=40)
        for n, c in cams.items()
    }
    t = time.perf_counter()
    pd = match_pair(
        chips["left_image"], chips["right_image"], cams["left_image"], cams["right_image"], grid, params=params
    )
    r = score_pair(pd, np.asarray(ref, np.float64), inside, 30.0)
    r["wall_s"] = time.perf_counter() - t
    r["reference"] = "SRTM N44E005 (EGM96 → ellipsoidal), inside the two footprints' overlap"
    _print("ventoux", r)
    if save:
        _save(save / "ventoux.npz", pd, np.where(inside, ref, np.nan))
    return {"ventoux:left__right": r}


def _save(path: Path, pd, ref: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(
        path,
        z=pd.z_m,
        z_raw=pd.z_raw_m,
        valid=pd.valid,
        flags=pd.flags,
        score=pd.score,
        mdl_window=pd.mdl_window,
        ncc=pd.ncc,
        g=pd.g_px_per_m,
        ref=ref.astype(np.float32),
    )


def _print(name: str, r: dict) -> None:
    r.setdefault("removed_cells", 0)
    r.setdefault("removed_wrong_share", float("nan"))
    print(
        f"{name:28s} complete {r['completeness_on_ref']:.1%}  median|dz| {r['median_abs_m']:.2f} m  "
        f"NMAD {r['nmad_m']:.2f} m  valid wrong >{r['wrong_threshold_m']:g} m: {r['valid_wrong_cells']} "
        f"({r['valid_wrong_share']:.3%}; beyond ±1 m: {r['valid_blunder_share']:.3%})  removed {r['removed_cells']} ({r['removed_wrong_share']:.1%} wrong)  "
        f"{r['wall_s']:.1f} s"
        + (
            f"\n{'':28s} z as written (valid + filled): complete {r['with_filled']['completeness_on_ref']:.1%}  "
            f"NMAD {r['with_filled']['nmad_m']:.2f} m  wrong {r['with_filled']['wrong_share']:.3%}; "
            f"beyond ±1 m: {r['with_filled']['blunder_share']:.3%}"
            if "with_filled" in r
            else ""
        ),
        flush=True,
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", nargs="+", default=["reunion", "marseille", "ventoux"])
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--save", type=Path, default=None, help="folder for the per-cell bands (npz)")
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="StereoParams fields (JSON values)")
    ap.add_argument("--without", action="store_true", help="also without the neighbour-agreement test")
    ap.add_argument("--cars", default=None, help="CARS's executable (its own venv): run it on each s2p pair too")
    ap.add_argument("--cars-work", type=Path, default=Path("geocd_out/validity_cars"), help="CARS's work folder")
    ap.add_argument("--cars-reuse", action="store_true", help="score CARS DSMs already in --cars-work again")
    a = ap.parse_args(argv)
    global CARS_WORK, CARS_REUSE
    CARS_WORK = a.cars_work.resolve()
    CARS_REUSE = a.cars_reuse
    given = {k: json.loads(v) for k, v in (x.split("=", 1) for x in a.set)}
    runs = {"default": given}
    if a.without:
        runs["without neighbour agreement"] = {**given, "isolation_min_cells": 1}
    res = {}
    for label, d in runs.items():
        print(f"--- {label}", flush=True)
        params = StereoParams.from_dict(d)
        r = {"params": params.to_dict()}
        cars = a.cars if label == "default" else None
        r.update(s2p_pairs(params, a.save if label == "default" else None, set(a.only), cars))
        if "ventoux" in a.only:
            r.update(ventoux(params, a.save if label == "default" else None))
        res[label] = r
    if a.json:
        a.json.write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
