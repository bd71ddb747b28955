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


def stable_false_alarms(conf: np.ndarray, observed: np.ndarray, damage, grid, buffer_m: float = 0.0,
                        levels=(90.0, 95.0, 99.0)) -> dict:
    from rasterio.features import rasterize

    from geocd.change.dsm_buildings import CHANGED

    changed = damage[damage["class"].isin(CHANGED)]
    geoms = [g.buffer(buffer_m) if buffer_m else g for g in changed.geometry]
    inside = (rasterize([(g, 1) for g in geoms], out_shape=grid.shape, transform=grid.transform, fill=0,
                        dtype="uint8").astype(bool) if geoms else np.zeros(grid.shape, bool))
    stable = observed & ~inside
    out = {f"{c:g}": round(float((np.nan_to_num(conf[stable]) >= c).mean()), 5) for c in levels}
    out.update(stable_cells=int(stable.sum()), buffer_m=buffer_m)
    return out


def evaluate(run: Path, model_path: Path, significance: str) -> tuple[dict, object]:
    from geocd.consistency import ChangeParams, SelfConsistencyModel, change_test
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
           "stable_false_alarms_3m": stable_false_alarms(res.confidence, obs, damage, grid, 3.0),
           "buildings": int(len(damage)), "classes": cls.value_counts().to_dict(),
           "collapsed": damage[cls == "collapsed"][["building_id", "confidence_pct", "height_before_m",
                                                      "height_after_m", "volume_lost_m3", "volume_sigma_m3",
                                                      "area_m2"]].to_dict(orient="records"),
           "volume_lost_collapsed_m3": round(float(damage[cls == "collapsed"]["volume_lost_m3"].sum()), 1)}
    return out, damage


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", default="/tmp/kahra")
    ap.add_argument("--model", default=str(REPO / "examples" / "kahramanmaras" / "marseille_urban_model.json"))
    ap.add_argument("--json", default=None)
    ap.add_argument("--modes", default="region,cell")
    args = ap.parse_args(argv)
    results = {}
    for mode in args.modes.split(","):
        r, dmg = evaluate(Path(args.run), Path(args.model), mode)
        results[mode] = r
        print(json.dumps({k: v for k, v in r.items() if k != "collapsed"}, indent=1))
        dmg.to_file(Path(args.run) / f"eval_building_damage_{mode}.gpkg", driver="GPKG")
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1, default=str))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
