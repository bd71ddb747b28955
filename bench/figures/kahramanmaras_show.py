"""Figures and figures-of-merit of the Kahramanmaraş case (docs/kahramanmaras.md).

Reads a finished ``geocd run examples/kahramanmaras/scene.yaml --model ... --out RUN`` and writes

* true orthos of the first view of each epoch (through the corrected cameras, on each epoch's own DSM):
  ``RUN/orthos/<image>.tif`` (what the marked-point-process work reads);
* ``docs/kahramanmaras_quicklook.png``: pre | post | detected buildings (classes over the post ortho);
* ``bench/results/kahramanmaras_show.json``: orientation residuals, building classes, stable-ground false alarms.

Usage::

    .venv/bin/python bench/figures/kahramanmaras_show.py --run RUN [--out docs]
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


def quicklook(pre: np.ndarray, post: np.ndarray, damage, grid, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch

    from geocd.change.dsm_buildings import DAMAGE_CLASSES

    def stretch(a):
        v = a[np.isfinite(a)]
        lo, hi = np.percentile(v, [1, 99]) if v.size else (0, 1)
        return np.clip((a - lo) / max(hi - lo, 1e-9), 0, 1)

    l, b, r, t = grid.bounds
    ext = (0, r - l, 0, t - b)
    fig, ax = plt.subplots(1, 3, figsize=(18, 6.4))
    ax[0].imshow(stretch(pre), cmap="gray", extent=ext)
    ax[0].set_title("pre-event (pre_event_img1, ortho on the ground model)")
    ax[1].imshow(stretch(post), cmap="gray", extent=ext)
    ax[1].set_title("post-event 2023-04-15 (post_event_img1, ortho on the ground model)")
    ax[2].imshow(stretch(post), cmap="gray", extent=ext, alpha=0.55)
    for _, row in damage.iterrows():
        colour = DAMAGE_CLASSES[row["class"]][0]
        geoms = getattr(row.geometry, "geoms", [row.geometry])
        for g in geoms:
            x, y = g.exterior.xy
            x, y = np.asarray(x) - l, np.asarray(y) - b
            if row["class"] in ("unchanged", "unobserved"):
                ax[2].plot(x, y, color="#6a6a6a" if row["class"] == "unchanged" else "#ffffff", lw=0.6)
            else:
                ax[2].fill(x, y, color=colour, alpha=0.75, lw=1.0, ec="k")
    counts = damage["class"].value_counts().to_dict()
    ax[2].legend(
        handles=[
            Patch(color=DAMAGE_CLASSES[c][0], label=f"{c} ({counts.get(c, 0)})")
            for c in DAMAGE_CLASSES
            if c != "unobserved"
        ],
        loc="lower left",
        fontsize=8,
        framealpha=0.85,
    )
    ax[2].set_title("geocd: buildings from the pre-event DSM, damage at 99 %")
    for a in ax:
        a.set_xlabel("m")
    fig.tight_layout()
    fig.savefig(path, dpi=48)
    plt.close(fig)


def main(argv=None) -> int:
    from geocd.change.building_layer import read_building_layer
    import rasterio

    from geocd.geodesy import AOIGrid
    from geocd.io.manifest import load_manifest

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", default="/tmp/kahra")
    ap.add_argument("--manifest", default=str(REPO / "examples" / "kahramanmaras" / "scene.yaml"))
    ap.add_argument("--out", default=str(REPO / "docs"))
    args = ap.parse_args(argv)
    run, out = Path(args.run), Path(args.out)
    with rasterio.open(run / "sc_change.tif") as ds:
        grid = AOIGrid.from_raster(ds)
    ap_layer = run / "sc_changes.gpkg"
    damage = read_building_layer(ap_layer)
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
    o = orthos(run, m, grid, ground=ground.astype(np.float64), sub="orthos_ground")
    pre = o["pre_event_img1"].values[0].astype(float)
    post = o["post_event_img1"].values[0].astype(float)
    pre[~o["pre_event_img1"].observed] = np.nan
    post[~o["post_event_img1"].observed] = np.nan
    quicklook(pre, post, damage, grid, out / "kahramanmaras_quicklook.png")
    (REPO / "bench" / "results" / "kahramanmaras_show.json").write_text(json.dumps(res, indent=1, default=str))
    print(json.dumps(res, indent=1, default=str))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
