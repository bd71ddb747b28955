"""Figures and figures-of-merit of the Kahramanmaraş case (docs/kahramanmaras.md).

Reads a finished ``geocd run examples/kahramanmaras/scene.yaml --model ... --out RUN`` and writes

* true orthos of each view (through the corrected cameras, on each epoch's own DSM): ``RUN/orthos/<image>.tif``
  (what the marked-point-process work and the QGIS picture read), and orthos on the pre-event ground model
  (no holes, buildings lean): ``RUN/orthos_ground/<image>.tif``;
* ``bench/results/kahramanmaras_show.json``: orientation residuals, building classes, stable-ground false alarms.

The page's quick-look (``docs/kahramanmaras_quicklook.png``) is the run's own ``sc_quicklook.png``
(``python -m bench.figures --only kahramanmaras_run``). The building layer is ``buildings`` (the merged layer),
else ``building_damage``.

Usage::

    .venv/bin/python bench/figures/kahramanmaras_show.py --run RUN
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))


def stable_false_alarms(run: Path, damage, grid, buffer_m: float = 0.0) -> dict:
    """Flagged share of observed cells outside every changed building (see geocd.change.dsm_buildings)."""
    import rasterio

    from geocd.change.dsm_buildings import stable_false_alarms as sfa

    with rasterio.open(run / "sc_change.tif") as ds:
        conf = ds.read(4)
    return sfa(conf, np.isfinite(conf), damage, grid, buffer_m=buffer_m)


def orthos(run: Path, manifest, grid, ground=None, sub: str = "orthos"):
    """Orthos of each epoch's views (corrected cameras): true orthos on that epoch's own DSM, or on
    ``ground`` (a ground model: no holes, buildings lean as in a classic orthophoto)."""
    from geocd.io.cameras import load_camera
    from geocd.ortho import fill_dsm_holes
    from geocd.ortho.pipeline import ortho_image
    from geocd.orientation.pipeline import corrected_manifest
    from geocd.stereo import read_pair_dem

    rep_path = run / "orientation" / "orientation.json"
    m = manifest
    if rep_path.is_file():
        rep = json.loads(rep_path.read_text())
        if rep.get("applied"):
            m = corrected_manifest(manifest, rep)
    out = {}
    for e in m.epochs:
        pdem = sorted((run / "stereo" / e.name).glob("*.tif"))[0]
        pd = read_pair_dem(pdem)
        dsm = np.where(pd.valid, pd.z_m, np.nan)
        filled, was_filled = fill_dsm_holes(dsm) if ground is None else (ground, None)
        for im in e.images:
            cam = load_camera(im.path, im.camera)
            _, res = ortho_image(im.path, cam, grid, filled, run / sub / f"{im.name}.tif", dsm_filled=was_filled)
            out[im.name] = res
    return out


def main(argv=None) -> int:
    import rasterio

    from geocd.change.building_layer import read_building_layer
    from geocd.geodesy import AOIGrid
    from geocd.io.manifest import load_manifest

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", default="/tmp/kahra")
    ap.add_argument("--manifest", default=str(REPO / "examples" / "kahramanmaras" / "scene.yaml"))
    args = ap.parse_args(argv)
    run = Path(args.run)
    with rasterio.open(run / "sc_change.tif") as ds:
        grid = AOIGrid.from_raster(ds)
    damage = read_building_layer(run / "sc_changes.gpkg")
    summary = json.loads((run / "run_summary.json").read_text())
    from geocd.pipeline import run_orientation

    orientation = run_orientation(run, summary)
    res = {
        "orientation": orientation,
        "buildings": summary.get("buildings") if "building_damage" not in summary else summary["building_damage"],
        "changed_fraction": summary.get("changed_fraction"),
        "stable_false_alarms": stable_false_alarms(run, damage, grid),
        "stable_false_alarms_3m": stable_false_alarms(run, damage, grid, buffer_m=3.0),
    }
    cls = damage["class"]
    res["collapsed"] = {
        "collapsed": int((cls == "collapsed").sum()),
        "partly collapsed": int((cls == "partly collapsed").sum()),
        "by_confidence": damage[cls == "collapsed"]["confidence_pct"].value_counts().to_dict(),
    }
    from geocd.change.dsm_buildings import ground_model
    from geocd.stereo import read_pair_dem

    m = load_manifest(args.manifest)
    orthos(run, m, grid)  # true orthos (for later work on this case)
    pd = read_pair_dem(sorted((run / "stereo" / m.epochs[0].name).glob("*.tif"))[0])
    ground, _ = ground_model(np.where(pd.valid, pd.z_m, np.nan), grid.posting_m)
    orthos(run, m, grid, ground=ground.astype(np.float64), sub="orthos_ground")
    (REPO / "bench" / "results" / "kahramanmaras_show.json").write_text(json.dumps(res, indent=1, default=str))
    print(json.dumps(res, indent=1, default=str))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
