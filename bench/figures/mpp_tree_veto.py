"""Would the damage layer's plane tree rule, read on each ``geocd mpp`` rectangle, remove its false objects?

An offline check (docs/mpp.md, "The plane tree rule as a veto"): for each rectangle of a finished run, the
median best-of-nine plane residual of its cells on the DSM of each date it is present on, against the rule's
threshold on that DSM (``geocd.change.dsm_buildings.plane_rule``: 7.5 cm, or the ground's 75th percentile when
higher). Two vetoes — drop a rectangle that reads a tree on every date it is present on, or on any — are then
scored with Table 2 against the run itself (the same rectangles, rasterised; no veto reproduces the run's row).

Usage::

    .venv/bin/python bench/figures/mpp_tree_veto.py NAME=SCENE=WORK [...] [--json bench/results/mpp_tree_veto.json]

``WORK``: the output folder of ``bench/figures/mpp_show.py scoring`` for that scene (``mpp/mpp_buildings.gpkg`` and
``ortho/{A,B}/dsm_*.tif``).
"""

import json
import sys
from pathlib import Path

import geopandas as gpd
import numpy as np
import rasterio
from rasterio.features import rasterize

from geocd.change.dsm_buildings import DSMBuildingParams, ground_model, plane_rule
from geocd.geodesy import AOIGrid
from geocd.mpp.evaluate import sample_truth, table2

P = DSMBuildingParams()
res = {}
args = sys.argv[1:]
out_json = None
if "--json" in args:
    k = args.index("--json")
    out_json = args[k + 1]
    args = args[:k] + args[k + 2 :]
for spec in args:
    name, scene, work = spec.split("=")
    scene, work = Path(scene), Path(work)
    rect = gpd.read_file(work / "mpp" / "mpp_buildings.gpkg", layer="rectangles")
    figs = {}
    for d in ("A", "B"):
        f = next((work / "ortho" / d).glob("dsm_*.tif"))
        with rasterio.open(f) as ds:
            z = ds.read(1, masked=True).astype(float).filled(np.nan)
            tr, crs, shape, bounds = ds.transform, ds.crs, z.shape, ds.bounds
        posting = abs(tr.a)
        dtm, ground = ground_model(z, posting, P)
        best, thr = plane_rule(z, dtm, posting, P, ground)
        figs[d] = (best, thr)
    grid = AOIGrid.from_bounds(*bounds, posting, crs)
    rect = rect.to_crs(crs)
    cells = [
        rasterize([(g, 1)], out_shape=shape, transform=tr, fill=0, dtype="uint8").astype(bool) for g in rect.geometry
    ]  # each rectangle's cells, once
    med = {"A": [], "B": []}
    for m in cells:
        for d in ("A", "B"):
            v = figs[d][0][m]
            v = v[np.isfinite(v)]
            med[d].append(float(np.median(v)) if v.size else np.nan)
    rect["medA"], rect["medB"] = med["A"], med["B"]
    treeA, treeB = rect["medA"] > figs["A"][1], rect["medB"] > figs["B"][1]
    pa, pb = rect["present_A"].astype(bool), rect["present_B"].astype(bool)
    fp = gpd.read_file(scene / "truth" / "footprints_all.gpkg")
    objs, t1, t2 = sample_truth(fp, grid, cut_buildings="masks")
    tany = t1 | t2
    # is each rect on a truth building (≥ half its cells)?
    onb = [float((m & tany).sum() / max(m.sum(), 1)) >= 0.5 for m in cells]
    rect["on_building"] = onb

    def masks(sel):
        out = {k: np.zeros(shape, bool) for k in ("date1", "date2", "new", "demolished", "any")}
        for k in np.nonzero(np.asarray(sel))[0]:
            r, m = rect.iloc[k], cells[k]
            out["any"] |= m
            if r.present_A:
                out["date1"] |= m
            if r.present_B:
                out["date2"] |= m
            if r.xi == "2":
                out["new"] |= m
            if r.xi == "1":
                out["demolished"] |= m
        return out

    rules = {
        "none": np.zeros(len(rect), bool),
        "all present dates tree": ((~pa | treeA) & (~pb | treeB)).to_numpy(),
        "any present date tree": ((pa & treeA) | (pb & treeB)).to_numpy(),
    }
    row = {"thr": {d: round(figs[d][1], 4) for d in figs}}
    for k, veto in rules.items():
        t = table2(masks(~veto), objs, t1, t2)
        row[k] = {x: t[x] for x in ("HO", "FO", "HV", "FV", "DP", "DP_precision", "DP_recall")}
        row[k]["vetoed_on_building"] = int((veto & rect["on_building"]).sum())
        row[k]["vetoed_off_building"] = int((veto & ~rect["on_building"]).sum())
    res[name] = row
    print(name, json.dumps(row), flush=True)
if out_json:
    Path(out_json).write_text(
        json.dumps({"command": "bench/figures/mpp_tree_veto.py " + " ".join(sys.argv[1:]), "scenes": res}, indent=1)
    )
