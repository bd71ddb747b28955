"""Where the Kahramanmaraş "stable-ground false alarms" are, and whether an independent reconstruction sees them.

Reads the layers of a run (``RUN/sc_change.tif``, ``RUN/sc_changes.gpkg`` layer ``buildings``,
``RUN/orthos/post_event_img1.tif``, the pair-DEMs ``RUN/stereo/<epoch>/*.tif``) and CARS's two DSMs (``bench_kahramanmaras_cars.py cars --work WORK``) and
draws, over the post-event ortho, the cells flagged at 99 % outside every changed building (the issue's
"stable" cells): in colour where CARS's own two DSMs differ there by more than 3 × their NMAD too (a change
both matchers see: raised blue, lowered red), in yellow where CARS's DSMs agree (a false alarm by that
witness), the changed buildings' outlines (magenta) and the outlines of the objects the default tree rule
drops as trees in either epoch's DSM (green: felled, planted or standing trees, which count as "stable").

Usage::

    .venv/bin/python bench/figures/kahramanmaras_false_alarms.py --run /tmp/kahra4/run --cars-work /tmp/kahra_cars \
        [--png docs/kahramanmaras_false_alarms.png]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))


def main(argv=None) -> int:
    from geocd.change.building_layer import read_building_layer
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import rasterio
    from rasterio.features import rasterize
    from scipy import ndimage as ndi

    from bench_kahramanmaras_cars import _to_grid
    from eval_kahramanmaras import _recs, _surface, tree_object_mask
    from geocd.change.dsm_buildings import CHANGED
    from geocd.geodesy import AOIGrid

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", required=True)
    ap.add_argument("--cars-work", required=True)
    ap.add_argument("--png", default=str(REPO / "docs" / "kahramanmaras_false_alarms.png"))
    args = ap.parse_args(argv)
    run, work = Path(args.run), Path(args.cars_work)
    with rasterio.open(run / "sc_change.tif") as ds:
        dz, conf = ds.read(1), ds.read(4)
        grid = AOIGrid.from_raster(ds)
    with rasterio.open(run / "orthos" / "post_event_img1.tif") as ds:
        img = ds.read(1).astype(float)
    dmg = read_building_layer(run / "sc_changes.gpkg").to_crs(grid.crs)
    ch = dmg[dmg["class"].isin(CHANGED)]
    inside = (
        rasterize(
            [(g, 1) for g in ch.geometry], out_shape=grid.shape, transform=grid.transform, fill=0, dtype="uint8"
        ).astype(bool)
        if len(ch)
        else np.zeros(grid.shape, bool)
    )
    observed = np.isfinite(conf)
    stable = observed & ~inside
    flag = stable & (np.nan_to_num(conf) >= 99.0)
    ca, cb = (_to_grid(str(work / ep / "out" / "dsm" / "dsm.tif"), grid) for ep in ("pre_event", "post_event"))
    dc = cb - ca
    both = np.isfinite(dc)
    dc = dc - np.nanmedian(dc[stable & both])
    x = dc[stable & both]
    nmad = 1.4826 * np.median(np.abs(x - np.median(x)))
    seen = both & (np.abs(dc) > 3 * nmad)
    ov = np.zeros(grid.shape + (4,))
    ov[flag & seen & (dz > 0)] = [0.1, 0.45, 1.0, 0.85]
    ov[flag & seen & (dz <= 0)] = [1.0, 0.1, 0.1, 0.85]
    ov[flag & ~seen] = [1.0, 0.95, 0.0, 1.0]
    recs = _recs(run)
    trees = tree_object_mask(tuple(_surface(recs[ep]) for ep in ("pre_event", "post_event")), grid.posting_m)
    ov[trees ^ ndi.binary_erosion(trees)] = [0.0, 0.85, 0.0, 1.0]
    ov[inside ^ ndi.binary_erosion(inside)] = [1.0, 0.0, 1.0, 1.0]
    fig, ax = plt.subplots(figsize=(9, 8.8))
    v = img[np.isfinite(img)]
    ax.imshow(img, cmap="gray", vmin=np.percentile(v, 2), vmax=np.percentile(v, 98))
    ax.imshow(ov, interpolation="nearest")
    n_f = int(flag.sum())
    share = float((flag & seen).sum() / max((flag & both).sum(), 1))
    ax.set_title(
        f"flagged at 99 % outside changed buildings: {100 * n_f / stable.sum():.1f} % of the stable cells;\n"
        f"CARS's DSMs differ > {3 * nmad:.1f} m at {100 * share:.0f} % of those it observes (blue raised, red lowered);\n"
        f"yellow: CARS sees no change; magenta: changed buildings; green: tree objects",
        fontsize=9,
    )
    ax.set_xticks([])
    ax.set_yticks([])
    fig.tight_layout()
    fig.savefig(args.png, dpi=60)
    from PIL import Image

    Image.open(args.png).convert("RGB").quantize(128).save(args.png, optimize=True)  # a small PNG for docs/
    print(f"{args.png}: {n_f} flagged stable cells, {share:.3f} seen by CARS, NMAD {nmad:.2f} m")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
