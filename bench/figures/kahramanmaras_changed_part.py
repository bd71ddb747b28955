"""The buildings the changed-part option moves on Kahramanmaraş (docs/kahramanmaras.md, "The changed-part rule").

For every building whose class differs between two damage layers of ``bench/eval_kahramanmaras.py`` (the
default, and ``--changed-part on``): the pre- and post-event orthos around it with its outline, and the cells
the change test flags at 99 % (blue raised, red lowered). What an analyst would look at to judge the parts.

Usage::

    .venv/bin/python bench/figures/kahramanmaras_changed_part.py --run RUN --default A.gpkg --option B.gpkg \
        [--out docs/kahramanmaras_changed_part.png]

``RUN``: a folder with ``sc_change.tif`` and ``orthos_ground/{pre,post}_event_img1.tif`` (the ``--rerun`` folder
of ``eval_kahramanmaras.py`` after ``bench/figures/kahramanmaras_show.py``).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]


def main(argv=None) -> int:
    import geopandas as gpd
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import rasterio
    from PIL import Image
    from rasterio.windows import from_bounds

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", required=True)
    ap.add_argument("--default", required=True, help="damage layer without the option")
    ap.add_argument("--option", required=True, help="damage layer with --changed-part on")
    ap.add_argument("--out", default=str(REPO / "docs" / "kahramanmaras_changed_part.png"))
    a = ap.parse_args(argv)
    run = Path(a.run)
    off, on = gpd.read_file(a.default), gpd.read_file(a.option)
    moved = on[on["class"] != off["class"]]
    print(moved[["building_id", "class", "frac_changed", "area_m2", "rule"]].to_string())
    n = len(moved)
    fig, ax = plt.subplots(n, 3, figsize=(7.5, 2.5 * n), squeeze=False)
    with rasterio.open(run / "sc_change.tif") as ch:
        for k, (_, b) in enumerate(moved.iterrows()):
            l, bt, r, t = b.geometry.buffer(8).bounds
            g = b.geometry if b.geometry.geom_type == "Polygon" else b.geometry.convex_hull
            x, y = g.exterior.xy
            for j, ep in enumerate(("pre_event", "post_event")):
                with rasterio.open(run / "orthos_ground" / f"{ep}_img1.tif") as ds:
                    im = ds.read(1, window=from_bounds(l, bt, r, t, ds.transform), boundless=True, fill_value=0).astype(
                        float
                    )
                lo, hi = np.percentile(im[im > 0], [2, 98]) if (im > 0).any() else (0.0, 1.0)
                ax[k, j].imshow(im, cmap="gray", vmin=lo, vmax=hi, extent=(l, r, bt, t))
                ax[k, j].plot(x, y, "y-", lw=0.8)
            w = from_bounds(l, bt, r, t, ch.transform)
            conf = ch.read(4, window=w, boundless=True, fill_value=np.nan)
            dz = ch.read(1, window=w, boundless=True, fill_value=np.nan)
            ax[k, 2].imshow(
                np.where(conf >= 99, np.sign(dz), np.nan), cmap="bwr_r", vmin=-1, vmax=1, extent=(l, r, bt, t)
            )
            ax[k, 2].plot(x, y, "k-", lw=0.8)
            ax[k, 0].set_ylabel(
                f"#{b.building_id} {b['class']}\n{b.height_before_m:.0f}→{b.height_after_m:.0f} m", fontsize=7
            )
            for c in ax[k]:
                c.set_xticks([])
                c.set_yticks([])
    ax[0, 0].set_title("pre", fontsize=8)
    ax[0, 1].set_title("post", fontsize=8)
    ax[0, 2].set_title("99 %: blue raised / red lowered", fontsize=8)
    fig.tight_layout()
    fig.savefig(a.out, dpi=60)
    Image.open(a.out).convert("RGB").quantize(64).save(a.out, optimize=True)  # a third of the size
    print(a.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
