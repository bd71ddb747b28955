"""Speed of the 2-D screen, and what the tiered run (``geocd run --screen``) saves and loses.

1. ``features``: seconds per km² at 0.5 m for each grid feature (one core: BLAS/torch limited to one
   thread), on a 1024 × 1024 pair cut from the Kahramanmaraş Pléiades views (pre/post, grey) when
   ../shared is there, else a synthetic textured pair; the whole screen (features of both images,
   d_g, Felzenszwalb superpixels of both, exclusions), cold (first call) and warm (second call),
   wall and CPU seconds (one thread: CPU seconds are what a free core takes on a loaded machine).
   The ratio column compares with the patch feature measured in the same run.
2. ``tiered SCENE``: ``geocd run SCENE [--model M]`` and ``geocd run SCENE --screen`` in child processes;
   wall and CPU seconds of each, the speed-up, the fraction of the grid the stereo ran on, and the 3-D
   detections lost: regions of the full run's ``changes`` layer (99 %) that no region of the tiered run
   overlaps, and (when the scene has truth) building-level and cell-level figures of both.

Usage::

    nice -n 10 .venv/bin/python bench/bench_screen.py features --out bench/results/screen_bench.json
    nice -n 10 .venv/bin/python bench/bench_screen.py tiered sample_aoi --out bench/results/screen_bench.json
    nice -n 10 .venv/bin/python bench/bench_screen.py tiered examples/kahramanmaras/scene.yaml \\
        --model examples/kahramanmaras/marseille_urban_model.json --full-dir /tmp/kahra2 --out bench/results/screen_bench.json
    nice -n 10 .venv/bin/python bench/bench_screen.py stereo-overhead sample_aoi --epoch B --tiered-dir T
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
for v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(v, "1")
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

KAHRA = ROOT.parent / "shared" / "data" / "cnes_picanteo_kahramanmaras"


def _pair(size: int = 1024):
    """A real grey pair (pre/post Kahramanmaraş crops, not co-registered: the screen's speed only) or synthetic."""
    if (KAHRA / "pre_event_img1.tif").exists():
        from geocd.io.raster import read_image
        from rasterio.windows import Window

        a = read_image(KAHRA / "pre_event_img1.tif", window=Window(0, 0, size, size)).data.astype(np.float32)
        b = read_image(KAHRA / "post_event_img1.tif", window=Window(0, 0, size, size)).data.astype(np.float32)
        return a, b, f"Kahramanmaraş pre_event_img1 / post_event_img1, first {size} × {size} px"
    from tests.screen.scenes import pair

    a, b, _ = pair(size=size)
    return a, b, "synthetic textured pair"


def bench_features(size: int = 1024, only: list[str] | None = None) -> dict:
    from geocd.screen import FeatureSpec, ScreenParams, screen_pair
    from geocd.screen.cnn import random_state_dict, torch_available

    try:
        import torch

        torch.set_num_threads(1)
    except ImportError:
        pass
    a, b, what = _pair(size)
    km2 = a.shape[-1] * a.shape[-2] * 0.25 / 1e6
    wdir = Path("/tmp/geocd_bench_screen")
    wdir.mkdir(exist_ok=True)
    specs = [
        ("patch 16px", FeatureSpec("patch", 16)),
        ("randbank 16px", FeatureSpec("randbank", 16)),
        ("daisy 16px", FeatureSpec("daisy", 16)),
        ("daisy 32px", FeatureSpec("daisy", 32)),
    ]
    for bb, ly in (("vgg19", "pool4"), ("vgg19", "pool5"), ("resnet18", "layer3"), ("efficientnet_lite0", "stage5")):
        w = wdir / f"{bb}.npz"
        if not w.exists():
            np.savez(w, **random_state_dict(bb, 0))
        for eng in ["numpy", "torch"] if torch_available() else ["numpy"]:
            specs.append((f"{bb} {ly} ({eng})", FeatureSpec("cnn", backbone=bb, weights=str(w), layer=ly, engine=eng)))
    if only:
        specs = [s for s in specs if any(s[0].startswith(k) for k in only)]
    rows = []
    for label, spec in specs:
        feat = spec.build()
        times, cpu = [], []
        for _ in range(2):
            t0, c0 = time.perf_counter(), time.process_time()
            screen_pair(a, b, gsd_m=0.5, params=ScreenParams(feature=spec), feature=feat)
            times.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
        # CPU seconds of this one-threaded process are what one free core would take (wall depends on the load)
        rows.append(
            {
                "feature": label,
                "cold_s": round(times[0], 2),
                "warm_s": round(times[1], 2),
                "cold_cpu_s": round(cpu[0], 2),
                "warm_cpu_s": round(cpu[1], 2),
                "s_per_km2_warm": round(times[1] / km2, 1),
                "cpu_s_per_km2_warm": round(cpu[1] / km2, 1),
            }
        )
        print(json.dumps(rows[-1]), flush=True)
    if rows[0]["feature"].startswith("patch"):
        base = rows[0]["cpu_s_per_km2_warm"]
        for r in rows:
            r["cpu_ratio_to_patch"] = round(r["cpu_s_per_km2_warm"] / base, 2)
    return {"pair": what, "km2": round(km2, 4), "threads": 1, "load_average": os.getloadavg(), "rows": rows}


def _run(args: list[str], cold: bool = False) -> dict:
    """One geocd command as a child process; ``cold``: with an empty numba cache of its own (every kernel it
    uses compiles, as on a first run; the worktree's cache is left alone)."""
    import tempfile

    env = dict(os.environ)
    tmp = tempfile.TemporaryDirectory(prefix="geocd_numba_cold_") if cold else None
    if tmp is not None:
        env["NUMBA_CACHE_DIR"] = tmp.name
    load0 = os.getloadavg()[0]
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    p = subprocess.run(
        [str(ROOT / ".venv" / "bin" / "geocd"), "--progress", "none", *args], capture_output=True, text=True, env=env
    )
    if tmp is not None:
        tmp.cleanup()
    wall = time.perf_counter() - t0
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    if p.returncode:
        raise SystemExit(f"geocd {' '.join(args)} failed:\n{p.stderr[-3000:]}")
    return {
        "wall_s": round(wall, 1),
        "cpu_s": round((r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime), 1),
        "load_average_1min": [round(load0, 2), round(os.getloadavg()[0], 2)],
        "stdout": p.stdout[-2000:],
    }


def _parts(out: Path) -> dict:
    """Wall seconds of a run's parts, from its log's progress lines (1 s resolution): orientation, the 3-D
    stage (screen + stereo in a tiered run), the change test (model, comparisons, buildings) and the products."""
    import re

    marks: dict[str, float] = {}
    log = out / "geocd_run.log"
    if not log.exists():
        return {}
    day = 0.0
    last = None
    for line in log.read_text().splitlines():
        mm = re.match(r"(\d\d):(\d\d):(\d\d) PROGRESS run +(\d+)% (.*)", line)
        if not mm:
            continue
        t = int(mm[1]) * 3600 + int(mm[2]) * 60 + int(mm[3]) + day
        if last is not None and t < last:  # past midnight
            day += 86400.0
            t += 86400.0
        last = t
        pct, msg = int(mm[4]), mm[5]
        marks.setdefault("start", t)
        if pct >= 10:
            marks.setdefault("stereo", t)
        if msg.startswith(("learning", "cross-epoch change test")):
            marks.setdefault("change", t)
        if msg.startswith("writing products"):
            marks.setdefault("products", t)
        if msg.startswith("done"):
            marks.setdefault("done", t)
    keys = ["start", "stereo", "change", "products", "done"]
    if not all(k in marks for k in keys):
        return {}
    names = ["orientation_s", "stereo_s", "change_test_s", "products_s"]
    return {n: round(marks[b] - marks[a], 1) for n, a, b in zip(names, keys[:-1], keys[1:])}


def _regions(out: Path):
    import geopandas as gpd

    f = out / "sc_changes.gpkg"
    return gpd.read_file(f, layer="changes")


def _changed_and_lost(full: Path, tier: Path):
    """(full run's changed buildings, tiered run's changed buildings, full's changed buildings no tiered
    changed building overlaps), or None when the runs have no building layer."""
    import pyogrio

    from geocd.change.building_layer import read_building_layer

    names = [str(n) for n, _ in pyogrio.list_layers(full / "sc_changes.gpkg")]
    if "building_damage" not in names and "buildings" not in names:
        return None
    quiet = ("unchanged", "unobserved", "not examined")
    a = read_building_layer(full / "sc_changes.gpkg")
    b = read_building_layer(tier / "sc_changes.gpkg")
    a, b = a[~a["class"].isin(quiet)], b[~b["class"].isin(quiet)]
    return a, b, (a[~a.geometry.intersects(b.unary_union)] if len(b) else a)


def _damaged_buildings(full: Path, tier: Path, examined=None, grid=None) -> dict | None:
    """Buildings of the full run's building layer in a changed class (not unchanged/unobserved) that
    no changed building of the tiered run overlaps (the building outlines come from each run's own DSM), split
    into those wholly or partly outside the examined (flagged) tiles — the screen missed them — and those
    inside — the 3-D stage on the tiles gave another answer."""
    got = _changed_and_lost(full, tier)
    if got is None:
        return None
    a, b, lost = got
    res = {
        "changed_full": int(len(a)),
        "changed_tiered": int(len(b)),
        "full_changed_not_found": int(len(lost)),
        "lost_by_class": lost["class"].value_counts().to_dict(),
    }
    if examined is not None and len(lost):
        from geocd.pipeline import mark_not_examined

        fr = mark_not_examined(lost.assign(**{"class": "x"}), grid, examined)["frac_examined"].to_numpy()
        res["lost_outside_flagged_tiles"] = int((fr < 0.5).sum())
        res["lost_inside_flagged_tiles"] = int((fr >= 0.5).sum())
    return res


def _lost_vs_threshold_rule(full: Path, tier: Path, grid) -> dict | None:
    """Do the changed buildings the tiered run lost come from the screen's threshold rule?

    For each changed building of the full run that no changed tiered building overlaps: the screen's
    largest dissimilarity over its footprint (``screen_dissimilarity.tif``, band 1), against the threshold
    the products used (the no-change pair's 99 % quantile, then Otsu's split above it) and against the bare
    99 % quantile of the no-change pair (the first step of the rule alone). A diagnostic: no threshold is
    changed. ``above_null_below_split``: buildings the Otsu step cut; ``below_null``: buildings whose
    image change the feature does not see above the no-change pair's own 99 % level."""
    import rasterio
    from rasterio.features import rasterize
    from scipy import ndimage as ndi

    got = _changed_and_lost(full, tier)
    if got is None:
        return None
    a, b, lost = got
    summ = json.loads((tier / "screen" / "screen_summary.json").read_text())
    t = float(summ["threshold"])
    q99 = float(summ["null"]["quantiles"]["99"])
    with rasterio.open(tier / "screen" / "screen_dissimilarity.tif") as ds:
        d = ds.read(1)
    if not len(lost):
        return {"threshold": t, "null_q99": q99, "lost": 0}
    lab = rasterize(
        [(g, i + 1) for i, g in enumerate(lost.to_crs(grid.crs).geometry)],
        out_shape=grid.shape,
        transform=grid.transform,
        fill=0,
        dtype="int32",
    )
    idx = np.arange(1, len(lost) + 1)
    dmax = np.asarray(ndi.maximum(np.nan_to_num(d, nan=-1.0), lab, idx))
    return {
        "threshold": round(t, 4),
        "null_q99": round(q99, 4),
        "lost": int(len(lost)),
        "above_threshold": int((dmax > t).sum()),
        "above_null_below_split": int(((dmax > q99) & (dmax <= t)).sum()),
        "below_null": int((dmax <= q99).sum()),
        "max_d_quantiles": [round(float(v), 3) for v in np.quantile(dmax, [0.1, 0.5, 0.9])],
    }


def screen_losses(full: Path, screens: list[Path], tile_cells: int = 128, min_region_m2: float = 4.0) -> dict:
    """What each screen alone would lose: the full run's changed buildings (its building layer, changed
    classes) lying mostly (≥ 50 % of their cells) outside the tiles the screen flags, and how many of those
    the screen sees below its own no-change 99 % quantile. For comparing screens (e.g. the views on the
    terrain or on a DSM), independent of how the 3-D stage then covers the tiles."""
    import rasterio
    from rasterio.features import rasterize
    from scipy import ndimage as ndi

    from geocd.change.building_layer import read_building_layer
    from geocd.geodesy import AOIGrid
    from geocd.pipeline import mark_not_examined
    from geocd.screen.tiered import flag_tiles

    a = read_building_layer(full / "sc_changes.gpkg")
    a = a[~a["class"].isin(("unchanged", "unobserved", "not examined"))]
    out = {"full_dir": str(full), "changed_full": int(len(a)), "tile_cells": tile_cells, "screens": {}}
    for sd in screens:
        summ = json.loads((sd / "screen_summary.json").read_text())
        with rasterio.open(sd / "screen_change_mask.tif") as ds:
            ch = ds.read(1) == 1
            grid = AOIGrid.from_raster(ds)
        with rasterio.open(sd / "screen_dissimilarity.tif") as ds:
            d = ds.read(1)
        lab, n = ndi.label(ch, structure=np.ones((3, 3), bool))
        if n:
            keep = np.bincount(lab.ravel()) >= max(1, int(np.ceil(min_region_m2 / grid.cell_area_m2)))
            keep[0] = False
            ch = keep[lab]
        fl = flag_tiles(ch, tile_cells)
        ex = fl.examined(grid.shape)
        fr = mark_not_examined(a.assign(**{"class": "x"}), grid, ex)["frac_examined"].to_numpy()
        outside = a[fr < 0.5]
        q99 = float(summ["null"]["quantiles"]["99"]) if summ.get("null") else float("nan")
        below = 0
        if len(outside):
            lb = rasterize(
                [(g, i + 1) for i, g in enumerate(outside.to_crs(grid.crs).geometry)],
                out_shape=grid.shape,
                transform=grid.transform,
                fill=0,
                dtype="int32",
            )
            dmax = np.asarray(ndi.maximum(np.nan_to_num(d, nan=-1.0), lb, np.arange(1, len(outside) + 1)))
            below = int((dmax <= q99).sum())
        out["screens"][str(sd)] = {
            "threshold": round(float(summ["threshold"]), 4),
            "null": summ.get("null"),
            "flagged_tile_fraction": round(fl.tile_fraction, 4),
            "flagged_cell_fraction": round(fl.cell_fraction(grid.shape), 4),
            "lost_outside_flagged_tiles": int(len(outside)),
            "of_which_below_null_q99": below,
            "surface": summ.get("surface"),
        }
    return out


def calibration_fits(full: Path, tier: Path, model: str) -> dict:
    """The transfer calibration (scale, edge σ) fitted on several selections of one full run's pair-DEMs: every
    cell (the full run's fit), the screen's flagged tiles (the tiered run's old fit), the flagged tiles' cells
    the screen calls unchanged (the new rule), the same over the whole grid, and two diagnostics that use the
    full run's own 99 % change mask (the static scene of the grid and of the flagged tiles)."""
    import rasterio
    from scipy import ndimage

    from geocd.consistency import ChangeParams, SelfConsistencyModel
    from geocd.screen.tiered import Flagged, calibration_cells, fit_calibration_on
    from geocd.stereo import read_pair_dem

    mdl = SelfConsistencyModel.load(model)
    summ = json.loads((full / "run_summary.json").read_text())
    ea, eb = summ["epoch_a"], summ["epoch_b"]
    A = [read_pair_dem(p) for p in sorted((full / "stereo" / ea).glob("*.tif"))]
    B = [read_pair_dem(p) for p in sorted((full / "stereo" / eb).glob("*.tif"))]
    shape = A[0].z_m.shape
    scr = json.loads((tier / "run_summary.json").read_text())["screen"]
    t = scr["tile_cells"]
    sel = np.zeros((-(-shape[0] // t), -(-shape[1] // t)), bool)
    for i, j in scr["flagged"]:
        sel[i, j] = True
    flagged = Flagged(t, sel).examined(shape)
    with rasterio.open(tier / "screen" / "screen_change_mask.tif") as ds:
        ch = ds.read(1) == 1
    with rasterio.open(tier / "screen" / "screen_dissimilarity.tif") as ds:
        d = ds.read(1)
    ssum = json.loads((tier / "screen" / "screen_summary.json").read_text())
    q50 = float(ssum["null"]["quantiles"]["50"])
    cell = int(ssum["cell_px"])
    with rasterio.open(full / "sc_change_mask.tif") as ds:
        fm = ds.read(1)
    static = ~ndimage.binary_dilation((fm == 1) | (fm == -1), iterations=8)
    every = np.ones(shape, bool)
    rows = {
        "all cells (the full run's fit)": every,
        "flagged tiles, every cell (the old tiered fit)": flagged,
        "flagged tiles, screen-unchanged (the new rule)": calibration_cells(d, q50, ch, flagged, cell),
        "whole grid, screen-unchanged": calibration_cells(d, q50, ch, every, cell),
        "diagnostic: whole grid without the full run's 99 % changes (8-cell buffer)": static,
        "diagnostic: flagged tiles without the full run's 99 % changes (8-cell buffer)": flagged & static,
    }
    out = {"full_dir": str(full), "tiered_dir": str(tier), "model": model, "fits": {}}
    for name, cells in rows.items():
        cal, _ = fit_calibration_on(A, B, mdl, ChangeParams(), cells)
        out["fits"][name] = {"selected_cells": int(cells.sum()), **(cal.to_dict() if cal is not None else {})}
    return out


def _curve_diff(a, b) -> tuple[float, float]:
    """|99 % curve of b − of a| / of a over the score bins a populates: (weighted by a's counts, max)."""
    sc = a.score_centres
    ta, tb = a.threshold(sc, 99.0), b.threshold(sc, 99.0)
    ok = np.isfinite(ta) & np.isfinite(tb) & (a.bin_counts > 0)
    if not ok.any():
        return float("nan"), float("nan")
    w = a.bin_counts[ok].astype(float)
    rel = np.abs(tb[ok] - ta[ok]) / np.maximum(np.abs(ta[ok]), 1e-9)
    return round(float(np.sum(w * rel) / w.sum()), 4), round(float(rel.max()), 4)


def _models(full: Path, tier: Path) -> dict | None:
    """The learned self-consistency model of the two runs (the whole-scene statistic a tiered run learns on
    its flagged tiles only). Splits the difference of the 99 % curves into the **subset** effect (the full
    run's pair-DEMs cut to the flagged tiles' cells, model learned again) and the **tiled stereo** effect
    (that model vs the tiered run's). Curves compared as ``_curve_diff`` (weighted mean and max relative)."""
    import rasterio

    from geocd.consistency import ConsistencyParams, SelfConsistencyModel, learn_self_consistency
    from geocd.stereo import read_pair_dem

    fa, fb = full / "self_consistency_model.json", tier / "self_consistency_model.json"
    if not (fa.exists() and fb.exists()):
        return None
    ma, mb = SelfConsistencyModel.load(fa), SelfConsistencyModel.load(fb)
    res = {
        "match_pairs_full": int(ma.bin_counts.sum()),
        "match_pairs_tiered": int(mb.bin_counts.sum()),
        "curve99_full_vs_tiered": _curve_diff(ma, mb),
    }
    learned = json.loads((tier / "run_summary.json").read_text())["model"]["learned_here"]
    if not learned:
        res["note"] = "a given scene-class model (--model): the same in both runs"
        return res
    with rasterio.open(tier / "sc_change_mask.tif") as ds:
        ex = ds.read(1) != -127
    by: dict = {}
    for f in sorted((full / "stereo").rglob("*.tif")):
        p = read_pair_dem(f)
        p.valid = p.valid & ex
        p.z_m = np.where(ex, p.z_m, np.nan).astype(np.float32)
        by.setdefault(p.epoch, []).append(p)
    cfg = json.loads((full / "run_config.json").read_text())["consistency"]
    cfg = {k: tuple(v) if isinstance(v, list) else v for k, v in cfg.items()}
    mr = learn_self_consistency([g for g in by.values() if len(g) >= 2], ConsistencyParams(**cfg))
    res["match_pairs_full_cut_to_flagged"] = int(mr.bin_counts.sum())
    res["curve99_subset_effect"] = _curve_diff(ma, mr)
    res["curve99_tiled_stereo_effect"] = _curve_diff(mr, mb)
    return res


def _cells(full: Path, tier: Path) -> dict:
    """Changed cells (99 % mask) of the full run that the tiered run does not call changed, split by where they are."""
    import rasterio

    with rasterio.open(full / "sc_change_mask.tif") as ds:
        mf = ds.read(1)
    with rasterio.open(tier / "sc_change_mask.tif") as ds:
        mt = ds.read(1)
    from geocd.consistency import NOT_EXAMINED

    chf, cht = np.isin(mf, (-1, 1)), np.isin(mt, (-1, 1))
    ex = mt != NOT_EXAMINED
    both = chf & cht & ex
    same_sign = both & (mf == mt)
    return {
        "changed_full": int(chf.sum()),
        "changed_tiered": int(cht.sum()),
        "full_changed_outside_flagged": int((chf & ~ex).sum()),
        "full_changed_inside_not_found": int((chf & ex & ~cht).sum()),
        "tiered_changed_not_in_full": int((cht & ~chf).sum()),
        "jaccard_inside_flagged": round(float(both.sum() / max(((chf | cht) & ex).sum(), 1)), 4),
        "same_sign_inside": round(float(same_sign.sum() / max(both.sum(), 1)), 4),
        "examined_fraction": round(float(ex.mean()), 4),
        "observed_full_inside": round(float((mf[ex] != -128).mean()), 4),
        "observed_tiered_inside": round(float((mt[ex] != -128).mean()), 4),
    }


def _truth_buildings(out: Path, scene: Path, hit_share: float = 0.3) -> dict:
    """A generated scene's truth buildings (``truth/buildings.gpkg``, status demolished / new / unchanged) found
    by a run's 99 % change mask: a building is found when ≥ ``hit_share`` of its observed footprint cells
    are raised or lowered (the rule of ``bench_big_stereo_change.py evaluate``). Cells not examined (−127,
    screened out) count as observed and unchanged — a changed building there is a loss of the tiered run —
    and the changed buildings mostly (≥ 50 %) outside the examined cells are counted apart."""
    import geopandas as gpd
    import rasterio
    from rasterio.features import rasterize

    from geocd.consistency import CHANGE_NODATA, NOT_EXAMINED

    with rasterio.open(out / "sc_change_mask.tif") as ds:
        m = ds.read(1)
        tr, shape = ds.transform, ds.shape
    b = gpd.read_file(scene / "truth" / "buildings.gpkg")
    lab = rasterize(
        ((g, i + 1) for i, g in enumerate(b.geometry)), out_shape=shape, transform=tr, fill=0, dtype="int32"
    )
    n = len(b) + 1
    obs, det, ex = m != CHANGE_NODATA, (m == 1) | (m == -1), m != NOT_EXAMINED
    n_all = np.bincount(lab.ravel(), minlength=n)[1:]
    n_obs = np.bincount(lab[obs].ravel(), minlength=n)[1:]
    n_det = np.bincount(lab[det].ravel(), minlength=n)[1:]
    n_ex = np.bincount(lab[ex].ravel(), minlength=n)[1:]
    share = np.where(n_obs > 0, n_det / np.maximum(n_obs, 1), np.nan)
    found = np.nan_to_num(share) >= hit_share
    outside = n_ex < 0.5 * np.maximum(n_all, 1)
    st = b["status"].to_numpy()
    res: dict = {"hit_share": hit_share}
    for s in ("demolished", "new", "unchanged"):
        k = st == s
        res[s] = {
            "buildings": int(k.sum()),
            "observed": int((k & np.isfinite(share)).sum()),
            "flagged": int((k & found).sum()),
            "mostly_not_examined": int((k & outside).sum()),
        }
    chg = st != "unchanged"
    res["changed_found"] = int((chg & found).sum())
    res["changed_observed"] = int((chg & np.isfinite(share)).sum())
    res["changed_mostly_not_examined"] = int((chg & outside).sum())
    res["found_ids"] = sorted(int(v) for v in b["building_id"].to_numpy()[chg & found])
    return res


def _truth_scores(out: Path, scene: Path) -> dict | None:
    t = scene / "truth" / "change_mask.tif"
    if not t.exists():
        return None
    import rasterio

    from geocd.geodesy import AOIGrid
    from geocd.io.raster import read_on_grid
    from geocd.screen.threshold import f1_scores

    with rasterio.open(out / "sc_change_mask.tif") as ds:
        m = ds.read(1)
        g = AOIGrid.from_raster(ds)
    truth = np.nan_to_num(read_on_grid(t, g)) > 0
    s = json.loads((out / "run_summary.json").read_text())
    det = (m == 1) | (m == -1)  # raised/lowered (0 unchanged, -128 not observed, -127 not examined)
    res = {"cells_99": f1_scores(det, truth), "buildings": s.get("buildings")}
    if (scene / "truth" / "buildings.gpkg").exists():
        res["truth_buildings"] = _truth_buildings(out, scene)
    if (m == -127).any():
        ex = m != -127
        res["cells_99_in_flagged_tiles"] = f1_scores(det[ex], truth[ex])
        res["truth_cells_outside_flagged_tiles"] = int((truth & ~ex).sum())
    return res


def bench_tiered(scene: str, model: str | None, work: Path, reference: Path | None = None, cold: bool = False) -> dict:
    """Full then tiered run, back to back (same machine state), whole processes; ``reference``: another full
    run's folder to compare the tiered run's detections with as well."""
    import shutil

    extra = ["--model", model] if model else []
    full, tier = work / "full", work / "tiered"
    for d in (full, tier):  # no resumed tiles, no earlier products: every run starts from nothing
        shutil.rmtree(d, ignore_errors=True)
    r_full = _run(["run", scene, "--out", str(full), *extra], cold)
    r_tier = _run(["run", scene, "--out", str(tier), "--screen", *extra], cold)
    res = compare(scene, model, full, tier, r_full, r_tier)
    if reference is not None:
        ref = compare(scene, model, reference, tier, {"wall_s": float("nan"), "cpu_s": float("nan")}, r_tier)
        res["vs_reference"] = {
            k: ref[k]
            for k in (
                "full_dir",
                "regions_full",
                "regions_lost",
                "area_lost_m2",
                "area_full_m2",
                "cells",
                "buildings",
                "lost_buildings_vs_threshold_rule",
            )
            if k in ref
        }
    return res


def compare(scene: str, model: str | None, full: Path, tier: Path, r_full: dict, r_tier: dict) -> dict:
    """Speed-up and detections lost between a full and a tiered run's output folders."""
    import rasterio

    from geocd.consistency import NOT_EXAMINED
    from geocd.geodesy import AOIGrid

    sc = Path(scene)
    a, b = _regions(full), _regions(tier)
    lost = a[~a.geometry.intersects(b.unary_union)] if len(b) else a
    s = json.loads((tier / "run_summary.json").read_text())["screen"]
    with rasterio.open(tier / "sc_change_mask.tif") as ds:
        examined = ds.read(1) != NOT_EXAMINED
        grid = AOIGrid.from_raster(ds)
    res = {
        "scene": scene,
        "model": model,
        "full_dir": str(full),
        "tiered_dir": str(tier),
        "full": {k: v for k, v in r_full.items() if k != "stdout"},
        "tiered": {k: v for k, v in r_tier.items() if k != "stdout"},
        "screen": s,
        "speedup_wall": round(r_full["wall_s"] / r_tier["wall_s"], 2),
        "speedup_cpu": round(r_full["cpu_s"] / r_tier["cpu_s"], 2),
        "parts_wall_s": {"full": _parts(full), "tiered": _parts(tier)},
        "regions_full": int(len(a)),
        "regions_tiered": int(len(b)),
        "regions_lost": int(len(lost)),
        "area_lost_m2": round(float(lost.area.sum()), 1),
        "area_full_m2": round(float(a.area.sum()), 1),
        "cells": _cells(full, tier),
        "models": _models(full, tier),
    }
    bd = _damaged_buildings(full, tier, examined, grid)
    if bd is not None:
        res["buildings"] = bd
        res["lost_buildings_vs_threshold_rule"] = _lost_vs_threshold_rule(full, tier, grid)
    root = sc if sc.is_dir() else sc.parent
    tf, tt = _truth_scores(full, root), _truth_scores(tier, root)
    if tf is not None:
        res["truth_full"], res["truth_tiered"] = tf, tt
        if "truth_buildings" in tf:
            a_ids, b_ids = set(tf["truth_buildings"]["found_ids"]), set(tt["truth_buildings"]["found_ids"])
            res["truth_buildings_found"] = {
                "full": len(a_ids),
                "tiered": len(b_ids),
                "both": len(a_ids & b_ids),
                "lost_by_tiered": len(a_ids - b_ids),
                "gained_by_tiered": len(b_ids - a_ids),
            }
    return res


def tile_sizes(full: Path, tier: Path, sizes=(64, 128, 256), min_region_m2: float = 4.0) -> list[dict]:
    """What other ``--screen-tile`` sizes would have done with the same screen: the fraction of tiles flagged
    (= of the grid the stereo runs on), and the full run's changed cells (99 %) outside every flagged tile
    (lost to the 3-D test)."""
    import rasterio
    from scipy import ndimage

    from geocd.screen.tiered import flag_tiles

    with rasterio.open(tier / "screen" / "screen_change_mask.tif") as ds:
        ch = ds.read(1) == 1
    with rasterio.open(full / "sc_change_mask.tif") as ds:
        m = ds.read(1)
        cell_m2 = abs(ds.transform.a * ds.transform.e)
    det = (m == 1) | (m == -1)
    lab, n = ndimage.label(ch, structure=np.ones((3, 3), bool))
    if n:
        keep = np.bincount(lab.ravel()) >= max(1, int(np.ceil(min_region_m2 / cell_m2)))
        keep[0] = False
        ch = keep[lab]
    dl, nd = ndimage.label(det, structure=np.ones((3, 3), bool))
    rows = []
    for t in sizes:
        fl = flag_tiles(ch, t)
        win = fl.examined(ch.shape)
        hit = np.unique(dl[win & det])
        rows.append(
            {
                "tile_cells": t,
                "flagged_tile_fraction": round(fl.tile_fraction, 3),
                "stereo_cell_fraction": round(float(win.mean()), 3),
                "full_changed_cells_outside": int((det & ~win).sum()),
                "full_changed_cells": int(det.sum()),
                "full_regions_missed": int(nd - np.count_nonzero(hit[hit > 0])),
                "full_regions": int(nd),
            }
        )
    return rows


def flag_rules(tier: Path, scene: Path, tile_cells: int = 128, min_region_m2: float = 4.0) -> dict:
    """Tile-flag rules on a tiered run's stored screen (no stereo): flagged tile fraction and the truth changed
    buildings lying ≥ 50 % in flagged tiles (``truth/buildings.gpkg`` of a generated scene), for thresholds
    (the old rule: the no-change pair's 99 % then Otsu's split; the no-change 99 %; the screened pair's own
    99 %, with and without Otsu's split) × tile rules (any region of ``min_region_m2``; the chance count with
    and without the reach). The screen's dissimilarity does not depend on the rule, so one run serves all."""
    import geopandas as gpd
    import rasterio
    from rasterio.features import rasterize
    from scipy import ndimage

    from geocd.screen.threshold import split_above
    from geocd.screen.tiered import Flagged, flag_tiles, flag_tiles_by_chance

    summ = json.loads((tier / "screen" / "screen_summary.json").read_text())
    q_null = float(summ["null"]["quantiles"]["99"])
    cell = int(summ["cell_px"])
    with rasterio.open(tier / "screen" / "screen_dissimilarity.tif") as ds:
        d = ds.read(1)
        tr = ds.transform
        area = abs(tr.a * tr.e)
    ok = np.isfinite(d)
    q_own = float(np.quantile(d[ok], 0.99))
    b = gpd.read_file(scene / "truth" / "buildings.gpkg")
    lab = rasterize(
        ((g, i + 1) for i, g in enumerate(b.geometry)), out_shape=d.shape, transform=tr, fill=0, dtype="int32"
    )
    n_all = np.bincount(lab.ravel(), minlength=len(b) + 1)[1:]
    chg = (b["status"] != "unchanged").to_numpy()

    def regions(t):
        c = ok & (d > t)
        lb, n = ndimage.label(c, structure=np.ones((3, 3), bool))
        if n:
            keep = np.bincount(lb.ravel()) >= max(1, int(np.ceil(min_region_m2 / area)))
            keep[0] = False
            c = keep[lb]
        return c

    def score(fl):
        ex = fl.examined(d.shape)
        n_ex = np.bincount(lab[ex].ravel(), minlength=len(b) + 1)[1:]
        inside = n_ex >= 0.5 * np.maximum(n_all, 1)
        return {
            "tile_fraction": round(fl.tile_fraction, 4),
            "changed_buildings_in_flagged": int((chg & inside).sum()),
            "unchanged_buildings_in_flagged": int((~chg & inside).sum()),
        }

    rows = {}
    for name, t in (
        ("no-change 99 % + Otsu (old)", split_above(d, q_null)),
        ("no-change 99 %", q_null),
        ("own 99 %", q_own),
        ("own 99 % + Otsu", split_above(d, q_own)),
    ):
        c = regions(t)
        rows[f"{name}, any region"] = {"threshold": round(float(t), 4), **score(flag_tiles(c, tile_cells))}
        for reach in (True, False):
            fl = (
                flag_tiles_by_chance(c, ok, tile_cells, cell, 0.01)[0]
                if reach
                else Flagged(tile_cells, _chance_only(c, ok, tile_cells, cell))
            )
            rows[f"{name}, chance count" + ("" if reach else ", no reach")] = {
                "threshold": round(float(t), 4),
                **score(fl),
            }
    return {"changed_buildings": int(chg.sum()), "null_q99": round(q_null, 4), "own_q99": round(q_own, 4), "rows": rows}


def _chance_only(changed, valid, tile_cells, unit, rate=0.01):
    """The chance count's tiles without the reach (for the comparison in :func:`flag_rules`)."""
    from geocd.screen.tiered import chance_cells

    H, W = changed.shape
    nr, nc = -(-H // tile_cells), -(-W // tile_cells)

    def per_tile(m):
        pad = np.zeros((nr * tile_cells, nc * tile_cells))
        pad[:H, :W] = m
        return pad.reshape(nr, tile_cells, nc, tile_cells).sum(axis=(1, 3))

    n = per_tile(valid) / unit**2
    return per_tile(changed) / unit**2 > chance_cells(n, rate, rate)


def stereo_overhead(scene: str, tier: Path, epoch: str, work: Path) -> dict:
    """Where the tiered stereo's time goes: one epoch's pairs matched untiled (``run_stereo``, as the full run),
    tiled on the tiered run's flagged tiles, and tiled on every tile (same tile size and declared margins),
    in this process (CPU seconds of all threads), plus the pairs' central-window probes."""
    import shutil

    from geocd.tiling.params import TilingParams
    from geocd.io.manifest import load_manifest
    from geocd.pipeline import RunConfig
    from geocd.stereo import read_pair_dem
    from geocd.stereo.pipeline import run_stereo
    from geocd.stereo.scene import load_epoch_images
    from geocd.stereo.tiled import _pair_job, run_stereo_tiled

    m = load_manifest(scene)
    cfg = RunConfig()
    summ = json.loads((tier / "run_summary.json").read_text())
    grid = read_pair_dem(next(v for k, v in summ["outputs"].items() if k.startswith("stereo:"))).grid
    t = summ["screen"]["tile_cells"]
    sel = np.zeros((-(-grid.height // t), -(-grid.width // t)), bool)
    for i, j in summ["screen"]["flagged"]:
        sel[i, j] = True
    shutil.rmtree(work, ignore_errors=True)
    res = {"scene": scene, "epoch": epoch, "tile_cells": t, "flagged_tiles": int(sel.sum()), "tiles": int(sel.size)}

    def timed(name, fn):
        c0, w0 = time.process_time(), time.perf_counter()
        fn()
        res[f"{name}_cpu_s"] = round(time.process_time() - c0, 1)
        res[f"{name}_wall_s"] = round(time.perf_counter() - w0, 1)

    timed(
        "untiled",
        lambda: run_stereo(
            m, epochs=[epoch], out_dir=work / "u", params=cfg.stereo, grid=grid, pairs=cfg.pairs, orient=False
        ),
    )
    ims = load_epoch_images(m, m.epoch(epoch))
    datum = m.dem.vertical_datum if m.dem is not None else None

    def probes():
        import itertools

        for a, b in itertools.combinations(ims, 2):
            if cfg.pairs == "all" or a.camera.kind == b.camera.kind:
                _pair_job(epoch, a, b, cfg.stereo, datum, grid, TilingParams(tile_size=t), None)

    timed("probes", probes)
    for name, s in (("tiled_flagged", sel), ("tiled_all", np.ones_like(sel))):
        timed(
            name,
            lambda s=s, name=name: run_stereo_tiled(
                m,
                out_dir=work / name,
                epochs=[epoch],
                params=cfg.stereo,
                grid=grid,
                pairs=cfg.pairs,
                tiling=TilingParams(tile_size=t, scheduler="sync"),
                tiles=s,
            ),
        )
    res["load_average_1min"] = round(os.getloadavg()[0], 2)
    return res


def _key(scene: str) -> str:
    p = Path(scene)
    return p.parent.name if p.suffix else p.name


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument(
        "what",
        choices=[
            "features",
            "tiered",
            "compare",
            "tiles",
            "stereo-overhead",
            "screen-losses",
            "calibration",
            "flag-rules",
        ],
    )
    ap.add_argument(
        "--screen-dir", type=Path, action="append", default=[], help="screen-losses: a screen's output folder (repeat)"
    )
    ap.add_argument("--epoch", default="B", help="stereo-overhead: the epoch whose pairs are matched")
    ap.add_argument(
        "--full-dir",
        type=Path,
        help="compare: the full run's output folder; tiered: a reference "
        "full run to compare the detections with as well",
    )
    ap.add_argument("--tiered-dir", type=Path, help="compare: the tiered run's output folder")
    ap.add_argument("--full-time", nargs=2, type=float, metavar=("WALL", "CPU"), help="compare: seconds")
    ap.add_argument("--tiered-time", nargs=2, type=float, metavar=("WALL", "CPU"), help="compare: seconds")
    ap.add_argument("scene", nargs="?", default="sample_aoi")
    ap.add_argument("--model", default=None)
    ap.add_argument("--cold", action="store_true", help="tiered: each run with an empty numba cache of its own")
    ap.add_argument("--size", type=int, default=1024, help="features: side of the benchmark pair (px)")
    ap.add_argument("--features", default=None, help="features: comma-separated label prefixes (default all)")
    ap.add_argument("--work", type=Path, default=Path("/tmp/geocd_bench_screen"))
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "screen_bench.json")
    a = ap.parse_args(argv)
    doc = json.loads(a.out.read_text()) if a.out.exists() else {}
    if a.what == "features":
        res = bench_features(a.size, a.features.split(",") if a.features else None)
        doc.setdefault("features", {})[f"{a.size}px" + (f" {a.features}" if a.features else "")] = res
    elif a.what == "compare":  # two runs made by hand (e.g. in parallel on a loaded machine) with their timings
        doc.setdefault("tiered", {})[_key(a.scene)] = compare(
            a.scene,
            a.model,
            a.full_dir,
            a.tiered_dir,
            {"wall_s": a.full_time[0], "cpu_s": a.full_time[1]},
            {"wall_s": a.tiered_time[0], "cpu_s": a.tiered_time[1]},
        )
    elif a.what == "stereo-overhead":  # untiled vs tiled stereo of one epoch, on the tiered run's flags
        doc.setdefault("stereo_overhead", {})[_key(a.scene)] = stereo_overhead(
            a.scene, a.tiered_dir, a.epoch, a.work / "overhead"
        )
    elif a.what == "screen-losses":  # what screens alone would lose (no stereo): --full-dir and --screen-dir ...
        doc.setdefault("screen_losses", {})[_key(a.scene)] = screen_losses(a.full_dir, a.screen_dir)
    elif a.what == "calibration":  # the transfer calibration fitted on several selections of a full run's cells
        doc.setdefault("calibration", {})[_key(a.scene)] = calibration_fits(a.full_dir, a.tiered_dir, a.model)
    elif a.what == "flag-rules":  # tile-flag rules on a tiered run's stored screen, scored on the truth buildings
        doc.setdefault("flag_rules", {})[_key(a.scene)] = flag_rules(
            a.tiered_dir, Path(a.scene).parent if Path(a.scene).is_file() else Path(a.scene)
        )
    elif a.what == "tiles":  # other --screen-tile sizes with the screen of a tiered run (no stereo re-run)
        doc.setdefault("tiles", {})[_key(a.scene)] = tile_sizes(a.full_dir, a.tiered_dir)
    else:
        w = a.work / _key(a.scene)
        doc.setdefault("tiered", {})[_key(a.scene) + (" cold" if a.cold else "")] = bench_tiered(
            a.scene, a.model, w, a.full_dir, a.cold
        )
    a.out.write_text(json.dumps(doc, indent=1, default=str))
    print(json.dumps(doc, indent=1, default=str)[-3000:])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
