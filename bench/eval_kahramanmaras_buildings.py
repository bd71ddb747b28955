"""Kahramanmaraş: the building layer against buildings marked by eye (cleared, new, unchanged).

No change truth exists for the city. ``bench/data/kahramanmaras_by_eye.csv`` holds one point per building
marked by eye (x, y in UTM 37N; class ``cleared`` — standing before, gone or a heap after —, ``new`` — ground,
a lawn or a building site before, a building after —, or ``unchanged``): on the pre- and post-event orthos of a
run with each epoch's height above the ground model beside them, the cleared and new candidates also taken from
where the two surfaces differ by more than 4 m and kept only when the orthos confirm them. So the marks share
the DSMs with the layer, not its objects or rules: they check that the step from the DSMs to building objects
keeps what the DSMs show. Scored as the issue that asked for it does:

* **layer**: the nearest object of the ``buildings`` layer within 8 m of the point (0 m when inside) — a
  cleared building is found when that object is ``collapsed``, ``partly collapsed`` or ``lowered``; a new one
  when it is ``new`` or ``raised``; an unchanged one is flagged when it is any changed class;
* **plain rule** on the same run's epoch surfaces (median of each epoch's pair-DEMs): the median Δz of the cells
  within 3 m of the point below −4 m (cleared found), above +4 m (new found), beyond ±4 m (unchanged flagged).

Usage::

    python bench/eval_kahramanmaras_buildings.py --run RUN [--layer RUN/sc_changes.gpkg] [--rebuild OUT] [--json J]
    python bench/eval_kahramanmaras_buildings.py --scene sample_aoi            # or --scene T1 --run R1

``RUN`` is the output folder of ``geocd run examples/kahramanmaras/scene.yaml --model
examples/kahramanmaras/marseille_urban_model.json --out RUN``. ``--rebuild OUT``: run everything after the
stereo again on RUN's pair-DEMs with the code as it is now (written to OUT), and score that layer.
``--scene``: a generated scene (``geocd synth``) instead, its truth buildings as the points (demolished and
lowered → cleared, new and raised → new), scoring the layer made from its DSMs without footprints.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

BY_EYE = REPO / "bench" / "data" / "kahramanmaras_by_eye.csv"
#: the layer classes that count as found, per by-eye class
FOUND = {
    "cleared": ("collapsed", "partly collapsed", "lowered"),
    "new": ("new", "raised"),
}
#: a generated scene's truth status → the by-eye classes (``--scene``)
TRUTH_CLASS = {"demolished": "cleared", "lowered": "cleared", "new": "new", "raised": "new", "unchanged": "unchanged"}
RADIUS_M = 8.0
DH_RADIUS_M = 3.0
DH_M = 4.0


def read_points(path: Path = BY_EYE):
    import geopandas as gpd
    import pandas as pd

    df = pd.read_csv(path, comment="#")
    return gpd.GeoDataFrame(df, geometry=gpd.points_from_xy(df["x"], df["y"]), crs="EPSG:32637")


def truth_points(scene: Path, crs):
    """One point per building of a generated scene (``truth/footprints_all.gpkg``; a point inside each), classed
    by its truth status as the by-eye points are (:data:`TRUTH_CLASS`)."""
    import geopandas as gpd

    fp = gpd.read_file(scene / "truth" / "footprints_all.gpkg").to_crs(crs)
    return gpd.GeoDataFrame(
        {"id": fp["building_id"].to_numpy(), "class": fp["status"].map(TRUTH_CLASS).to_numpy()},
        geometry=fp.geometry.representative_point().to_numpy(),
        crs=crs,
    )


def synth_layer(scene: Path, run: Path | None, cache: Path):
    """The DSM-derived building layer (no footprints) of a generated scene and the grid: everything after the
    stereo of ``geocd run`` with its defaults, on the pair-DEMs of ``run`` (a finished ``geocd run SCENE --out
    RUN``) or, for sample_aoi without one, of its default run computed once into ``cache`` as the tests do
    (:mod:`tests.sample_aoi_cache`)."""
    import tempfile

    from geocd.io.manifest import load_manifest
    from geocd.pipeline import RunConfig, run_building_layer, run_change
    from geocd.stereo import read_pair_dem

    if run is not None:
        m = load_manifest(scene)
        by: dict = {}
        for f in sorted((run / "stereo").rglob("*.tif")):
            p = read_pair_dem(f)
            by.setdefault(p.epoch, []).append(p)
        grid = next(iter(by.values()))[0].grid
    elif scene.resolve() == (REPO / "sample_aoi").resolve():
        from tests.sample_aoi_cache import sample_aoi_pairs

        m, by, grid = sample_aoi_pairs(cache)
    else:
        raise SystemExit("--scene other than sample_aoi: give the pair-DEMs of its geocd run with --run")
    with tempfile.TemporaryDirectory() as tmp:
        res = run_change(m, by, grid, out_dir=tmp, config=RunConfig())
    ea, eb = (e.name for e in m.epochs[:2])
    layer, _ = run_building_layer(None, res["result"], grid, by[ea], by[eb], res["model"], RunConfig(), ea, eb)
    return layer, grid


def score_layer(points, layer) -> dict:
    """Per by-eye class: points, found (or flagged for ``unchanged``), and the points' ids missed/flagged."""
    from geocd.change.building_layer import CHANGED

    layer = layer.to_crs(points.crs)
    sidx = layer.sindex
    out: dict = {}
    for cls, g in points.groupby("class"):
        hits, ids = 0, []
        for pid, p in zip(g["id"], g.geometry):
            cand = sidx.query(p.buffer(RADIUS_M), predicate="intersects")
            got = None
            if len(cand):
                d = layer.geometry.iloc[cand].distance(p).to_numpy()
                got = str(layer["class"].iloc[cand[int(np.argmin(d))]])
            if cls == "unchanged":
                hit = got in CHANGED
            else:
                hit = got in FOUND[cls]
            hits += hit
            if hit == (cls == "unchanged"):
                ids.append(f"{pid}:{got}")
        key = "flagged" if cls == "unchanged" else "found"
        out[cls] = {"points": int(len(g)), key: int(hits), ("flagged_ids" if cls == "unchanged" else "missed_ids"): ids}
    return out


def score_dh(points, dz, grid) -> dict:
    """The plain rule: the median Δz within 3 m of each point beyond ±4 m."""
    rows, cols = grid.shape
    r = int(np.ceil(DH_RADIUS_M / grid.posting_m))
    yy, xx = np.mgrid[-r : r + 1, -r : r + 1]
    disk = (yy**2 + xx**2) * grid.posting_m**2 <= DH_RADIUS_M**2
    inv = ~grid.transform
    out: dict = {}
    for cls, g in points.groupby("class"):
        hits = 0
        for p in g.geometry:
            c, rr = inv * (p.x, p.y)
            c, rr = int(np.floor(c)), int(np.floor(rr))
            win = np.full(disk.shape, np.nan)
            r0, r1, c0, c1 = max(rr - r, 0), min(rr + r + 1, rows), max(c - r, 0), min(c + r + 1, cols)
            if r0 < r1 and c0 < c1:
                win[r0 - (rr - r) : r1 - (rr - r), c0 - (c - r) : c1 - (c - r)] = dz[r0:r1, c0:c1]
            v = win[disk & np.isfinite(win)]
            med = float(np.median(v)) if v.size else 0.0
            hits += {"cleared": med < -DH_M, "new": med > DH_M}.get(cls, abs(med) > DH_M)
        out[cls] = {"points": int(len(g)), ("flagged" if cls == "unchanged" else "found"): int(hits)}
    return out


def epoch_dz(run: Path):
    """Δz = post − pre of the run's epoch surfaces (median of each epoch's pair-DEMs) and the grid."""
    from geocd.stereo import read_pair_dem
    from geocd.stereo.surface import epoch_surface

    recs = {
        ep: [read_pair_dem(p) for p in sorted((run / "stereo" / ep).glob("*.tif"))]
        for ep in ("pre_event", "post_event")
    }
    return epoch_surface(recs["post_event"]) - epoch_surface(recs["pre_event"]), recs["pre_event"][0].grid


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", type=Path, help="output folder of the example's geocd run (with --scene: of the scene's)")
    ap.add_argument(
        "--scene", type=Path, help="a generated scene with truth instead (sample_aoi): its DSM-derived layer"
    )
    ap.add_argument("--cache", type=Path, default=REPO / ".pytest_cache" / "d" / "geocd_sample_aoi_stereo")
    ap.add_argument("--layer", type=Path, help="a building layer (GeoPackage; default RUN/sc_changes.gpkg)")
    ap.add_argument("--rebuild", type=Path, help="rerun the steps after the stereo into this folder and score that")
    ap.add_argument("--model", type=Path, default=REPO / "examples" / "kahramanmaras" / "marseille_urban_model.json")
    ap.add_argument("--points", type=Path, default=BY_EYE)
    ap.add_argument("--json", type=Path)
    a = ap.parse_args(argv)
    from geocd.change.building_layer import read_building_layer

    if a.scene:
        layer, grid = synth_layer(a.scene, a.run, a.cache)
        res = {
            "scene": a.scene.name,
            "objects": int(len(layer)),
            "classes": {k: int(v) for k, v in layer["class"].value_counts().items()},
            "truth_points": score_layer(truth_points(a.scene, layer.crs), layer),
        }
        print(json.dumps(res, indent=2, default=str))
        return 0
    layer_path = a.layer or a.run / "sc_changes.gpkg"
    summary = None
    if a.rebuild:
        from bench.eval_kahramanmaras import rerun

        summary = rerun(a.run, a.rebuild, a.model)
        layer_path = a.rebuild / "sc_changes.gpkg"
    pts = read_points(a.points)
    layer = read_building_layer(layer_path)
    dz, grid = epoch_dz(a.run)
    res = {
        "layer": str(layer_path),
        "objects": int(len(layer)),
        "classes": {k: int(v) for k, v in layer["class"].value_counts().items()},
        "by_eye_layer": score_layer(pts, layer),
        "by_eye_plain_dh_rule": score_dh(pts, dz, grid),
    }
    if summary is not None:
        res["stable_false_alarms"] = summary.get("buildings", {}).get("stable_false_alarms")
    text = json.dumps(res, indent=2, default=str)
    print(text)
    if a.json:
        a.json.write_text(text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
