"""Kahramanmaraş: the change test and the building damage re-evaluated from a run's pair-DEMs.

Reads ``RUN/stereo/<epoch>/*.tif`` of ``geocd run examples/kahramanmaras/scene.yaml --model M --out RUN``,
re-runs the cross-epoch test with the scene-class model (both significance modes: region, the default, and
the SRI per-cell test), derives the buildings from the pre-event DSM and reports, for each mode,

* the flagged share of observed cells at 90/95/99 %;
* stable-ground false alarms: flagged share of observed cells outside every changed building (and outside a
  3 m band around them — the edges of changed buildings are changed too);
* the building classes, and the collapsed buildings with their confidence.

Usage::

    .venv/bin/python bench/eval_kahramanmaras.py --run /tmp/kahra --model examples/kahramanmaras/marseille_urban_model.json \
        [--json docs/kahramanmaras_eval.json]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def evaluate(run: Path, model_path: Path, significance: str) -> tuple[dict, object]:
    from geocd.consistency import ChangeParams, SelfConsistencyModel, change_test
    from geocd.change.dsm_buildings import stable_false_alarms
    from geocd.pipeline import _building_damage
    from geocd.stereo import read_pair_dem

    recs = {ep: [read_pair_dem(p) for p in sorted((run / "stereo" / ep).glob("*.tif"))]
            for ep in ("pre_event", "post_event")}
    model = SelfConsistencyModel.load(model_path)
    res = change_test(recs["pre_event"], recs["post_event"], model, ChangeParams(significance=significance))
    grid = recs["pre_event"][0].grid
    damage, _ = _building_damage(None, res, grid, recs["pre_event"], recs["post_event"], model, 99.0,
                                 "pre_event", "post_event")
    obs = res.observed
    cls = damage["class"]
    out = {"significance": significance,
           "flagged_of_observed": {f"{c:g}": round(float((res.changed_at(c) != 0)[obs].mean()), 5)
                                   for c in res.confidences},
           "observed_fraction": round(float(obs.mean()), 4),
           "stable_false_alarms": stable_false_alarms(res.confidence, obs, damage, grid),
           "stable_false_alarms_3m": stable_false_alarms(res.confidence, obs, damage, grid, buffer_m=3.0),
           "buildings": int(len(damage)), "classes": cls.value_counts().to_dict(),
           "collapsed": damage[cls == "collapsed"][["building_id", "confidence_pct", "height_before_m",
                                                      "height_after_m", "volume_lost_m3", "volume_sigma_m3",
                                                      "area_m2"]].to_dict(orient="records"),
           "volume_lost_collapsed_m3": round(float(damage[cls == "collapsed"]["volume_lost_m3"].sum()), 1)}
    return out, damage


def probchange_figures(pc_dir: Path, damage_gpkg: Path, layer: str = "building_damage") -> dict:
    """probchange (p > 0.5) on the same grid: flagged share, outside changed buildings, per building class."""
    import geopandas as gpd
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
    dmg = gpd.read_file(damage_gpkg, layer=layer)
    conf = np.where(flagged, 99.0, 0.0)
    fa = stable_false_alarms(conf, observed, dmg, grid, levels=(99.0,))
    lab = rasterize([(g, i + 1) for i, g in enumerate(dmg.geometry)], out_shape=grid.shape, transform=grid.transform,
                    fill=0, dtype="int32")
    idx = np.arange(1, len(dmg) + 1)
    frac = np.asarray(ndi.sum(flagged, lab, idx)) / np.maximum(np.asarray(ndi.sum(observed, lab, idx)), 1)
    by_class = {c: round(float(np.mean(frac[(dmg["class"] == c).to_numpy()])), 3) for c in dmg["class"].unique()}
    return {"observed_fraction": round(float(observed.mean()), 4),
            "flagged_of_observed": round(float(flagged[observed].mean()), 4),
            "outside_changed_buildings": fa["99"],
            "mean_flagged_share_by_geocd_class": by_class,
            "geocd_collapsed_with_15pct_flagged": int(np.sum((frac >= 0.15) & (dmg["class"] == "collapsed").to_numpy())),
            "geocd_unchanged_with_15pct_flagged": int(np.sum((frac >= 0.15) & (dmg["class"] == "unchanged").to_numpy()))}


def volume_figures(prob_ortho: Path, damage_gpkg: Path, layer: str = "building_damage") -> dict:
    """Octree-model change probability (orthorectified) against geocd's building classes on the same cells."""
    import geopandas as gpd
    import rasterio
    from rasterio.features import rasterize

    from geocd.change.metrics import roc_curve

    with rasterio.open(prob_ortho) as ds:
        p = ds.read(1).astype(float)
        tr, shape = ds.transform, (ds.height, ds.width)
    dmg = gpd.read_file(damage_gpkg, layer=layer).to_crs(ds.crs)
    cls_code = {"collapsed": 1, "partly collapsed": 2, "unchanged": 3}
    lab = rasterize([(g, cls_code[c]) for g, c in zip(dmg.geometry, dmg["class"]) if c in cls_code],
                    out_shape=shape, transform=tr, fill=0, dtype="uint8")
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
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", default="/tmp/kahra")
    ap.add_argument("--model", default=str(REPO / "examples" / "kahramanmaras" / "marseille_urban_model.json"))
    ap.add_argument("--json", default=None)
    ap.add_argument("--modes", default="region,cell")
    ap.add_argument("--probchange", default=None, help="output folder of geocd probchange on the same AOI")
    ap.add_argument("--volume", default=None, help="orthorectified change probability of geocd volume detect")
    args = ap.parse_args(argv)
    results = {}
    if args.volume:
        results["volume"] = volume_figures(Path(args.volume), Path(args.run) / "sc_changes.gpkg")
        print(json.dumps(results["volume"], indent=1))
    if args.probchange:
        results["probchange"] = probchange_figures(Path(args.probchange), Path(args.run) / "sc_changes.gpkg")
        print(json.dumps(results["probchange"], indent=1))
    for mode in [m for m in args.modes.split(",") if m]:
        r, dmg = evaluate(Path(args.run), Path(args.model), mode)
        results[mode] = r
        print(json.dumps({k: v for k, v in r.items() if k != "collapsed"}, indent=1))
        dmg.to_file(Path(args.run) / f"eval_building_damage_{mode}.gpkg", driver="GPKG")
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1, default=str))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
