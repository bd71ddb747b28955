"""Kahramanmaraş: the change test and the building damage re-evaluated from a run's pair-DEMs.

Reads ``RUN/stereo/<epoch>/*.tif`` of ``geocd run examples/kahramanmaras/scene.yaml --model M --out RUN``,
re-runs the cross-epoch test with the scene-class model (both significance modes: region, the default, and
the SRI per-cell test; with the model calibrated to the pair, what ``geocd run`` does with a transferred
model, and as learned in Marseille), derives the buildings from the pre-event DSM and reports, for each,

* the flagged share of observed cells at 90/95/99 %;
* stable-ground false alarms: flagged share of observed cells outside every changed building (and outside a
  3 m band around them — the edges of changed buildings are changed too), and where they are;
* the transfer diagnostics: the model's predicted disagreement against this pair's on stable ground;
* the building classes, and the collapsed buildings with their confidence;
* with ``--cars-work`` (``bench_kahramanmaras_cars.py cars --work DIR``): the same false alarms on the cells an
  independent reconstruction calls stable — CARS's two DSMs (another matcher, its own pipeline) agree there
  within a tolerance —, and how many of geocd's "stable" false alarms CARS sees changed too. "Outside every
  changed building" counts as stable whatever else changed (trees felled or in leaf, new buildings the layer
  misses, objects moved); CARS's difference is a witness that does not depend on geocd's building layer.

Usage::

    .venv/bin/python bench/eval_kahramanmaras.py --run /tmp/kahra --model examples/kahramanmaras/marseille_urban_model.json \
        [--json bench/results/kahramanmaras_eval.json] [--out DIR] [--picanteo-flag /tmp/kahra_cars/picanteo_flag.npy]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def _recs(run: Path) -> dict:
    from geocd.stereo import read_pair_dem

    return {
        ep: [read_pair_dem(p) for p in sorted((run / "stereo" / ep).glob("*.tif"))]
        for ep in ("pre_event", "post_event")
    }


def _surface(recs) -> np.ndarray:
    """An epoch's surface as ``geocd run``'s building extraction sees it: the median of its pair-DEMs' valid
    heights (a pair-DEM may hold heights at cells it marks invalid)."""
    from geocd.stereo.surface import epoch_surface

    return epoch_surface(recs)


def _mask(geoms, grid) -> np.ndarray:
    from rasterio.features import rasterize

    geoms = list(geoms)
    if not geoms:
        return np.zeros(grid.shape, bool)
    return rasterize(
        [(g, 1) for g in geoms], out_shape=grid.shape, transform=grid.transform, fill=0, dtype="uint8"
    ).astype(bool)


def _nmad(x: np.ndarray) -> float:
    x = x[np.isfinite(x)]
    return float(1.4826 * np.median(np.abs(x - np.median(x)))) if x.size else float("nan")


def where_false_alarms(
    res, damage, grid, recs, dtm, level: float = 99.0, orthos: Path | None = None, cars: tuple | None = None
) -> dict:
    """Where the flagged cells outside every changed building are (shares of them; rate = flagged share there).

    Categories (cells outside changed buildings, observed): inside a building object that is not changed;
    within 2 m of any building outline (edges); not in a building and low in both epochs (< 3 m above the
    ground model: ground); not in a building, above ground in one epoch only (objects removed / added:
    trees felled or in leaf, debris, cleared plots); above ground in both; "tree objects": not in a building,
    in an object of either epoch's DSM that the building extraction drops as a tree (the default tree rule,
    applied to the objects of each epoch's DSM over its own ground model, as ``geocd run`` extracts them);
    other non-building objects above ground in either epoch; dark (the darkest 15 % of either epoch's ortho
    when given: shadows). With ``cars`` (CARS's two DSMs on the grid): per category, the share of its flagged
    cells where CARS's DSMs differ by more than 3 × NMAD as well (CARS-missing cells count as not seen), and
    the flagged cells that are neither seen by CARS nor in a non-building object.
    """
    from scipy import ndimage as ndi

    from geocd.change.dsm_buildings import DSMBuildingParams

    bp = DSMBuildingParams()
    m = false_alarm_masks(res, damage, grid, recs, dtm, level)
    stable, flag, allb, trees, up_a, up_b = (m[k] for k in ("stable", "flag", "in_building", "trees", "up_a", "up_b"))
    post = grid.posting_m
    edge = allb ^ ndi.binary_erosion(allb)
    d_edge = ndi.distance_transform_edt(~edge) * post
    cats = {
        "in unchanged building objects": allb,
        "within 2 m of a building outline": d_edge <= 2.0,
        "ground (not building, low in both)": ~allb & ~up_a & ~up_b,
        "not building, above ground before only": ~allb & up_a & ~up_b,
        "not building, above ground after only": ~allb & ~up_a & up_b,
        "not building, above ground in both": ~allb & up_a & up_b,
        f"tree objects (not building; the {bp.tree_rule} tree rule's trees, either epoch)": ~allb & trees,
        "other non-building objects (above ground in either epoch, not tree objects)": ~allb & ~trees & (up_a | up_b),
    }
    if orthos is not None and (orthos / "pre_event_img1.tif").is_file():
        import rasterio

        dark = np.zeros(grid.shape, bool)
        for name in ("pre_event_img1", "post_event_img1"):
            with rasterio.open(orthos / f"{name}.tif") as ds:
                img = ds.read(1).astype(float)
            if img.shape == grid.shape:
                dark |= img < np.nanpercentile(img[stable], 15)
        cats["dark (darkest 15 % of either epoch's ortho: shadows)"] = dark
    n_s, n_f = int(stable.sum()), int(flag.sum())
    out = {
        "stable_cells": n_s,
        "flagged": n_f,
        "tree_rule": bp.tree_rule,
        "raised_share_of_flagged": round(float((res.dz_m[flag] > 0).mean()), 3) if n_f else None,
    }
    seen = None
    if cars is not None:
        dc, nm = _cars_dz(res, stable, *cars)
        seen = np.abs(np.nan_to_num(dc, nan=0.0)) > 3 * nm
        nonbld = ~allb & (trees | up_a | up_b)
        out["cars_sees_gt_3nmad_share_of_flagged"] = round(float((seen & flag).sum() / max(n_f, 1)), 3)
        out["neither_cars_seen_nor_non_building_object_share_of_flagged"] = round(
            float((flag & ~seen & ~nonbld).sum() / max(n_f, 1)), 3
        )
    for k, m in cats.items():
        out[k] = {
            "share_of_stable": round(float((m & stable).sum() / max(n_s, 1)), 3),
            "share_of_flagged": round(float((m & flag).sum() / max(n_f, 1)), 3),
            "rate": round(float((m & flag).sum() / max((m & stable).sum(), 1)), 4),
        }
        if seen is not None:
            out[k]["cars_sees_gt_3nmad"] = round(float((m & flag & seen).sum() / max((m & flag).sum(), 1)), 3)
    return out


def false_alarm_masks(res, damage, grid, recs, dtm, level: float = 99.0) -> dict:
    """The masks (rows, cols) behind :func:`where_false_alarms`: ``stable`` (observed, outside every changed
    building), ``flag`` (stable and flagged at ``level``), ``in_building`` (inside any building of the layer),
    ``trees`` (:func:`tree_object_mask` of both epochs), ``up_a`` / ``up_b`` (≥ ``min_height_m`` above ``dtm``)."""
    from geocd.change.dsm_buildings import CHANGED, DSMBuildingParams

    bp = DSMBuildingParams()
    stable = res.observed & ~_mask(damage[damage["class"].isin(CHANGED)].geometry, grid)
    za, zb = _surface(recs["pre_event"]), _surface(recs["post_event"])
    return {
        "stable": stable,
        "flag": stable & (np.nan_to_num(res.confidence) >= level),
        "in_building": _mask(damage.geometry, grid),
        "trees": tree_object_mask((za, zb), grid.posting_m),
        "up_a": za - dtm >= bp.min_height_m,
        "up_b": zb - dtm >= bp.min_height_m,
    }


def tree_object_mask(dsms, posting_m: float) -> np.ndarray:
    """Cells of the objects the default tree rule drops as trees in any of ``dsms`` (each DSM's objects over
    its own ground model, as ``geocd run`` extracts them: :func:`geocd.change.dsm_buildings.tree_cells`)."""
    from geocd.change.dsm_buildings import tree_cells

    trees = np.zeros(dsms[0].shape, bool)
    for z in dsms:
        trees |= tree_cells(z, posting_m)
    return trees


def _cars_dz(res, stable: np.ndarray, cars_a: np.ndarray, cars_b: np.ndarray) -> tuple[np.ndarray, float]:
    """CARS's post − pre heights less their median on the stable cells, and its NMAD there (m)."""
    both = np.isfinite(cars_a) & np.isfinite(cars_b)
    dc = cars_b - cars_a
    dc = dc - np.nanmedian(dc[stable & both])
    return dc, _nmad(dc[stable & both])


def transfer_figures(res, damage, grid, recs, model) -> dict:
    """How the transferred model's predicted disagreement compares with this pair's on stable ground."""
    from geocd.change.dsm_buildings import CHANGED
    from geocd.consistency import align_reconstructions, local_slope, match_pairs

    stable = res.observed & ~_mask(damage[damage["class"].isin(CHANGED)].geometry, grid)
    al, _ = align_reconstructions(recs["pre_event"] + recs["post_event"])
    p, q = al[0], al[len(recs["pre_event"])]
    dt, sc, dz, both = match_pairs(p, q)
    s = stable & both
    m50 = model.threshold(sc, 50.0)
    slope = np.fmax(local_slope(p.z_m, grid.posting_m), local_slope(q.z_m, grid.posting_m))
    sb = np.clip(np.searchsorted(model.score_edges, sc, side="right") - 1, 0, len(model.score_edges) - 2)
    per_bin = []
    for b in range(len(model.score_edges) - 1):
        sel = s & (sb == b)
        if sel.sum() >= 200:
            per_bin.append((int(sel.sum()), float(np.median(np.abs(dt[sel]))), float(np.median(m50[sel]))))
    ratios = np.array([a / m for _, a, m in per_bin])
    slope_rows = {}
    for lo, hi in ((0, 0.2), (0.2, 0.5), (0.5, 1), (1, 2), (2, 5), (5, np.inf)):
        sel = s & (slope >= lo) & (slope < hi)
        slope_rows[f"{lo:g}-{hi:g}"] = {
            "cells": int(sel.sum()),
            "nmad_dz_m": round(_nmad(dz[sel]), 3),
            "model_sigma_m": round(float(np.nanmedian(res.dz_sigma_m[sel])), 3),
        }
    return {
        "stable_cells": int(s.sum()),
        "nmad_dz_stable_m": round(_nmad(dz[s]), 3),
        "model_sigma_m_median": round(float(np.nanmedian(res.dz_sigma_m[s])), 3),
        "median_abs_dtilde_pair_over_model_by_score_bin": {
            "min": round(float(ratios.min()), 2),
            "median": round(float(np.median(ratios)), 2),
            "max": round(float(ratios.max()), 2),
        },
        "stable_share_beyond_model_99": round(float((np.abs(dt[s]) > model.threshold(sc[s], 99.0)).mean()), 4),
        "abs_dz_above_m": {f"{e}": round(float((np.abs(dz[s]) > e).mean()), 4) for e in (2, 5, 10, 20)},
        "by_slope": slope_rows,
    }


def evaluate(
    run: Path,
    model_path: Path,
    significance: str,
    calibration: str = "auto",
    recs: dict | None = None,
    cars: tuple | None = None,
    tree_rule: str | None = None,
    changed_part: bool = False,
    split_changed: bool = True,
) -> tuple[dict, object, object, np.ndarray]:
    from geocd.consistency import ChangeParams, SelfConsistencyModel, change_test
    from geocd.change.dsm_buildings import DSMBuildingParams, stable_false_alarms
    from geocd.pipeline import _building_layer

    recs = recs or _recs(run)
    model = SelfConsistencyModel.load(model_path)
    res = change_test(
        recs["pre_event"], recs["post_event"], model, ChangeParams(significance=significance, calibration=calibration)
    )
    grid = recs["pre_event"][0].grid
    bp = DSMBuildingParams(
        tree_rule=tree_rule or DSMBuildingParams().tree_rule, changed_part=changed_part, split_changed=split_changed
    )
    damage, dtm = _building_layer(
        None, res, grid, recs["pre_event"], recs["post_event"], model, 99.0, "pre_event", "post_event", bp
    )
    obs = res.observed
    cls = damage["class"]
    out = {
        "significance": significance,
        "calibration": calibration,
        "tree_rule": bp.tree_rule,
        "changed_part": bp.changed_part,
        "calibration_fit": res.calibration.to_dict() if res.calibration is not None else None,
        "flagged_of_observed": {
            f"{c:g}": round(float((res.changed_at(c) != 0)[obs].mean()), 5) for c in res.confidences
        },
        "observed_fraction": round(float(obs.mean()), 4),
        "stable_false_alarms": stable_false_alarms(res.confidence, obs, damage, grid),
        "stable_false_alarms_3m": stable_false_alarms(res.confidence, obs, damage, grid, buffer_m=3.0),
        "lowered_only_stable_false_alarms_99": stable_false_alarms(
            np.where(res.dz_m < 0, res.confidence, 0.0), obs, damage, grid, levels=(99.0,)
        )["99"],
        "where_false_alarms_99": where_false_alarms(
            res, damage, grid, recs, dtm, orthos=run / "orthos_ground", cars=cars
        ),
        "buildings": int(len(damage)),
        "classes": cls.value_counts().to_dict(),
        "collapsed": damage[cls == "collapsed"][
            [
                "building_id",
                "confidence_pct",
                "height_before_m",
                "height_after_m",
                "volume_lost_m3",
                "volume_sigma_m3",
                "area_m2",
            ]
        ].to_dict(orient="records"),
        "volume_lost_collapsed_m3": round(float(damage[cls == "collapsed"]["volume_lost_m3"].sum()), 1),
    }
    if cars is not None:
        out["independent_reference_cars"] = independent_reference(res, damage, grid, *cars, recs=recs)
    return out, damage, res, dtm


def rerun(run: Path, out: Path, model_path: Path, calibration: str = "auto") -> dict:
    """Everything of ``geocd run`` after the stereo, on RUN's pair-DEMs and oriented manifest, written to OUT."""
    import dataclasses

    from geocd.consistency import ChangeParams
    from geocd.io.manifest import load_manifest
    from geocd.pipeline import RunConfig, run_change

    if out.resolve() == run.resolve():
        raise SystemExit("--rerun must name another folder than --run (the run is read, never written)")
    recs = _recs(run)
    m = load_manifest(run / "orientation" / "scene.oriented.yaml")
    cfg = dataclasses.replace(RunConfig(model_path=str(model_path)), change=ChangeParams(calibration=calibration))
    res = run_change(
        m,
        recs,
        recs["pre_event"][0].grid,
        out_dir=out,
        config=cfg,
        stereo_outputs={f"{ep}/{p.name}": run / "stereo" / ep / f"{p.name}.tif" for ep, ps in recs.items() for p in ps},
    )
    return res["summary"]


def cars_dsms(work: Path, grid) -> tuple[np.ndarray, np.ndarray]:
    """CARS's pre- and post-event DSMs (``WORK/<epoch>/out/dsm/dsm.tif``) resampled onto geocd's grid."""
    from bench_kahramanmaras_cars import _to_grid

    return tuple(_to_grid(str(work / ep / "out" / "dsm" / "dsm.tif"), grid) for ep in ("pre_event", "post_event"))


def independent_reference(
    res, damage, grid, cars_a: np.ndarray, cars_b: np.ndarray, level: float = 99.0, recs: dict | None = None
) -> dict:
    """geocd's false alarms on the cells CARS's own two DSMs call stable, and CARS's view of geocd's false alarms.

    Stable by the witness: observed by geocd, outside geocd's changed buildings (as the headline figure) and
    |Δz_CARS − median| ≤ T, with T = 3 × NMAD of Δz_CARS over those cells (the witness's own noise; 1, 2, 3
    and 5 m also reported). The reference shares the images with geocd, so a failure both matchers make alike
    hides in it; what it does not share is geocd's matcher, its test or its building layer.
    """
    from geocd.change.dsm_buildings import CHANGED

    inside = _mask(damage[damage["class"].isin(CHANGED)].geometry, grid)
    stable = res.observed & ~inside
    flag = stable & (np.nan_to_num(res.confidence) >= level)
    both = np.isfinite(cars_a) & np.isfinite(cars_b)
    dc, nm = _cars_dz(res, stable, cars_a, cars_b)
    out = {
        "cars_dz_nmad_stable_m": round(nm, 3),
        "stable_cells_with_cars_both": round(float((stable & both).sum() / max(stable.sum(), 1)), 4),
        "flagged_stable_cars_differs_gt_3m": round(float((np.abs(dc[flag & both]) > 3).mean()), 4)
        if (flag & both).any()
        else None,
        "flagged_stable_cars_differs_gt_3nmad": round(float((np.abs(dc[flag & both]) > 3 * nm).mean()), 4)
        if (flag & both).any()
        else None,
    }
    # do geocd's own DSMs agree with CARS's at those cells (both epochs within 3 m)? then the change is in the
    # images, not in one matcher's failure
    za = _surface(recs["pre_event"]) if recs else None
    if za is not None:
        zb = _surface(recs["post_event"])
        ea = za - cars_a
        eb = zb - cars_b
        ea -= np.nanmedian(ea)
        eb -= np.nanmedian(eb)
        sel = flag & both & np.isfinite(ea) & np.isfinite(eb)
        out["flagged_stable_geocd_dsms_match_cars_within_3m"] = round(
            float(((np.abs(ea[sel]) <= 3) & (np.abs(eb[sel]) <= 3)).mean()), 4
        )
    for name, t in (("3nmad", 3 * nm), ("1m", 1.0), ("2m", 2.0), ("3m", 3.0), ("5m", 5.0)):
        s = stable & both & (np.abs(dc) <= t)
        out[f"false_alarms_cars_stable_{name}"] = {
            "tolerance_m": round(float(t), 3),
            "share_of_stable": round(float(s.sum() / max(stable.sum(), 1)), 4),
            "rate": round(float((s & flag).sum() / max(s.sum(), 1)), 5),
            "lowered_only_rate": round(float((s & flag & (res.dz_m < 0)).sum() / max(s.sum(), 1)), 5),
        }
    return out


def picanteo_figures(flag_path: Path, res, damage, grid) -> dict:
    """picanteo's rule map (bench_kahramanmaras_cars.py compare) on the same stable-ground definition."""
    from geocd.change.dsm_buildings import stable_false_alarms

    from scipy import ndimage as ndi
    from rasterio.features import rasterize

    flag = np.load(flag_path)
    out = {
        "stable_false_alarms_99": stable_false_alarms(
            np.where(flag, 99.0, 0.0), res.observed, damage, grid, levels=(99.0,)
        )["99"]
    }
    lab = rasterize(
        [(g, i + 1) for i, g in enumerate(damage.geometry)],
        out_shape=grid.shape,
        transform=grid.transform,
        fill=0,
        dtype="int32",
    )
    idx = np.arange(1, len(damage) + 1)
    frac = np.asarray(ndi.sum(flag & res.observed, lab, idx)) / np.maximum(
        np.asarray(ndi.sum(res.observed, lab, idx)), 1
    )
    pic = frac >= 0.15
    cls = damage["class"].to_numpy()
    low = np.isin(cls, ["collapsed", "partly collapsed", "lowered"])
    out["buildings"] = {
        "picanteo_changed": int(pic.sum()),
        "geocd_lowered_classes": int(low.sum()),
        "both": int((pic & low).sum()),
        "geocd_only": int((low & ~pic).sum()),
        "picanteo_only": int((pic & ~low).sum()),
        "geocd_collapsed_also_picanteo": int((pic & (cls == "collapsed")).sum()),
        "picanteo_in_geocd_unchanged": int((pic & (cls == "unchanged")).sum()),
    }
    return out


def probchange_figures(pc_dir: Path, damage_gpkg: Path, layer: str | None = None) -> dict:
    """probchange (p > 0.5) on the same grid: flagged share, outside changed buildings, per building class."""
    from geocd.change.building_layer import read_building_layer
    import rasterio
    from rasterio.features import rasterize
    from scipy import ndimage as ndi

    from geocd.change.dsm_buildings import stable_false_alarms
    from geocd.geodesy import AOIGrid

    with rasterio.open(pc_dir / "probchange_change_mask.tif") as ds:
        mask = ds.read(1)
        nod = ds.nodata
        grid = AOIGrid.from_raster(ds)
    observed = mask != nod if nod is not None else np.isfinite(mask)
    flagged = observed & (mask > 0)
    dmg = read_building_layer(damage_gpkg, layer)
    conf = np.where(flagged, 99.0, 0.0)
    fa = stable_false_alarms(conf, observed, dmg, grid, levels=(99.0,))
    lab = rasterize(
        [(g, i + 1) for i, g in enumerate(dmg.geometry)],
        out_shape=grid.shape,
        transform=grid.transform,
        fill=0,
        dtype="int32",
    )
    idx = np.arange(1, len(dmg) + 1)
    frac = np.asarray(ndi.sum(flagged, lab, idx)) / np.maximum(np.asarray(ndi.sum(observed, lab, idx)), 1)
    by_class = {c: round(float(np.mean(frac[(dmg["class"] == c).to_numpy()])), 3) for c in dmg["class"].unique()}
    return {
        "observed_fraction": round(float(observed.mean()), 4),
        "flagged_of_observed": round(float(flagged[observed].mean()), 4),
        "outside_changed_buildings": fa["99"],
        "mean_flagged_share_by_geocd_class": by_class,
        "geocd_collapsed_with_15pct_flagged": int(np.sum((frac >= 0.15) & (dmg["class"] == "collapsed").to_numpy())),
        "geocd_unchanged_with_15pct_flagged": int(np.sum((frac >= 0.15) & (dmg["class"] == "unchanged").to_numpy())),
    }


def volume_figures(prob_ortho: Path, damage_gpkg: Path, layer: str | None = None) -> dict:
    """Octree-model change probability (orthorectified) against geocd's building classes on the same cells."""
    from geocd.change.building_layer import read_building_layer
    import rasterio
    from rasterio.features import rasterize

    from geocd.change.metrics import roc_curve

    with rasterio.open(prob_ortho) as ds:
        p = ds.read(1).astype(float)
        tr, shape = ds.transform, (ds.height, ds.width)
    dmg = read_building_layer(damage_gpkg, layer).to_crs(ds.crs)
    cls_code = {"collapsed": 1, "partly collapsed": 2, "unchanged": 3}
    lab = rasterize(
        [(g, cls_code[c]) for g, c in zip(dmg.geometry, dmg["class"]) if c in cls_code],
        out_shape=shape,
        transform=tr,
        fill=0,
        dtype="uint8",
    )
    ok = np.isfinite(p)
    out = {"known_fraction": round(float(ok.mean()), 4), "mean_p_known": round(float(np.mean(p[ok])), 3)}
    for name, code in cls_code.items():
        sel = ok & (lab == code)
        out[f"mean_p_{name}"] = round(float(np.mean(p[sel])), 3) if sel.any() else None
        out[f"cells_{name}"] = int(sel.sum())
    pos, neg = ok & (lab == 1), ok & (lab == 3)
    if pos.any() and neg.any():
        y = np.concatenate([np.ones(pos.sum()), np.zeros(neg.sum())])
        out["auc_collapsed_vs_unchanged_cells"] = round(roc_curve(np.concatenate([p[pos], p[neg]]), y)[3], 3)
    return out


def main(argv=None) -> int:
    from geocd.change.dsm_buildings import DSMBuildingParams

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", default="/tmp/kahra")
    ap.add_argument("--model", default=str(REPO / "examples" / "kahramanmaras" / "marseille_urban_model.json"))
    ap.add_argument("--json", default=None)
    ap.add_argument("--out", default=None, help="folder for the evaluated damage layers (default: the run folder)")
    ap.add_argument("--modes", default="region,cell")
    ap.add_argument(
        "--calibrations",
        default="auto,none",
        help="transfer calibrations to evaluate (auto = what geocd run does with a transferred model: pair)",
    )
    ap.add_argument("--probchange", default=None, help="output folder of geocd probchange on the same AOI")
    ap.add_argument("--volume", default=None, help="orthorectified change probability of geocd volume detect")
    ap.add_argument(
        "--picanteo-flag",
        default=None,
        help="picanteo's change map on the same grid (picanteo_flag.npy of bench_kahramanmaras_cars.py)",
    )
    ap.add_argument(
        "--cars-work",
        default=None,
        help="work folder of bench_kahramanmaras_cars.py cars (its DSMs: the independent stability witness)",
    )
    ap.add_argument(
        "--tree-rule",
        default=DSMBuildingParams().tree_rule,
        help="how the building extraction tells trees from buildings (DSMBuildingParams.tree_rule)",
    )
    ap.add_argument(
        "--changed-part",
        choices=["on", "off"],
        default="off",
        help="a building holding a changed part of the map's mapping unit is changed "
        "(DSMBuildingParams.changed_part; off: the changed fraction alone)",
    )
    ap.add_argument(
        "--rerun",
        default=None,
        help="write every layer of geocd run (after the stereo) for RUN's pair-DEMs into this folder",
    )
    args = ap.parse_args(argv)
    results = {}
    if args.rerun:
        s = rerun(Path(args.run), Path(args.rerun), Path(args.model))
        print(json.dumps({k: s[k] for k in ("changed_fraction", "model", "buildings") if k in s}, indent=1))
    if args.volume:
        results["volume"] = volume_figures(Path(args.volume), Path(args.run) / "sc_changes.gpkg")
        print(json.dumps(results["volume"], indent=1))
    if args.probchange:
        results["probchange"] = probchange_figures(Path(args.probchange), Path(args.run) / "sc_changes.gpkg")
        print(json.dumps(results["probchange"], indent=1))
    recs = _recs(Path(args.run))
    cars = cars_dsms(Path(args.cars_work), recs["pre_event"][0].grid) if args.cars_work else None
    for cal in [c for c in args.calibrations.split(",") if c]:
        for mode in [m for m in args.modes.split(",") if m]:
            r, dmg, res, _ = evaluate(
                Path(args.run),
                Path(args.model),
                mode,
                cal,
                recs=recs,
                cars=cars,
                tree_rule=args.tree_rule,
                changed_part=args.changed_part == "on",
            )
            key = mode if cal == "auto" else f"{mode}_{cal}"
            if mode == "region" and cal == "none":
                from geocd.consistency import SelfConsistencyModel

                r["transfer"] = transfer_figures(
                    res, dmg, recs["pre_event"][0].grid, recs, SelfConsistencyModel.load(args.model)
                )
            if args.picanteo_flag:
                r["picanteo"] = picanteo_figures(Path(args.picanteo_flag), res, dmg, recs["pre_event"][0].grid)
            results[key] = r
            print(key, json.dumps({k: v for k, v in r.items() if k != "collapsed"}, indent=1))
            out = Path(args.out or args.run)
            out.mkdir(parents=True, exist_ok=True)
            dmg.to_file(out / f"eval_buildings_{key}.gpkg", driver="GPKG")
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1, default=str))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
