"""A quick-look per building class on Kahramanmaraş (docs/kahramanmaras.md): pre | post | the object.

For each class of the run's building layer (``buildings`` of ``sc_changes.gpkg``) the largest buildings of that
class: the pre- and post-event orthos around each with its outline, and the post-event ortho with every object
of the layer nearby in its class colour (the layer's own style). What an analyst sees when checking a class.

Usage::

    .venv/bin/python bench/figures/kahramanmaras_classes.py --run RUN [--per-class 3] \
        [--out docs/kahramanmaras_classes.png]

``RUN``: a ``geocd run examples/kahramanmaras/scene.yaml`` folder with ``orthos/{pre,post}_event_img1.tif``
(``bench/figures/kahramanmaras_show.py --run RUN`` writes them).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))

#: the classes shown, in this order, and their colours (as the layer's QGIS style and the run's quick-look)
ORDER = ("collapsed", "partly collapsed", "lowered", "new", "raised", "unchanged")


def main(argv=None) -> int:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import rasterio
    from PIL import Image
    from rasterio.windows import from_bounds

    from geocd.change.building_layer import read_building_layer
    from geocd.change.plots import QUICKLOOK_CLASSES

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", required=True, type=Path)
    ap.add_argument("--layer", type=Path, help="building layer (default RUN/sc_changes.gpkg)")
    ap.add_argument("--per-class", type=int, default=3)
    ap.add_argument("--out", default=str(REPO / "docs" / "kahramanmaras_classes.png"))
    a = ap.parse_args(argv)
    layer = read_building_layer(a.layer or a.run / "sc_changes.gpkg")
    rows = []
    for cls in ORDER:
        g = layer[layer["class"] == cls].sort_values("area_m2", ascending=False)
        rows += [(cls, b) for _, b in g.head(a.per_class).iterrows()]
    fig, ax = plt.subplots(len(rows), 3, figsize=(7.5, 2.5 * len(rows)), squeeze=False)
    for k, (cls, b) in enumerate(rows):
        l, bt, r, t = b.geometry.buffer(10).bounds
        side = max(r - l, t - bt)
        cx, cy = (l + r) / 2, (bt + t) / 2
        l, r, bt, t = cx - side / 2, cx + side / 2, cy - side / 2, cy + side / 2
        for j, ep in enumerate(("pre_event", "post_event", "post_event")):
            with rasterio.open(a.run / "orthos" / f"{ep}_img1.tif") as ds:
                im = ds.read(1, window=from_bounds(l, bt, r, t, ds.transform), boundless=True, fill_value=0)
            im = im.astype(float)
            lo, hi = np.percentile(im[im > 0], [2, 98]) if (im > 0).any() else (0.0, 1.0)
            ax[k, j].imshow(im, cmap="gray", vmin=lo, vmax=hi, extent=(l, r, bt, t))
            shown = [(b.geometry, QUICKLOOK_CLASSES.get(cls, ("yellow",))[0])]
            if j == 2:  # every object of the layer in view, in its class colour
                near = layer[layer.intersects(b.geometry.buffer(side))]
                shown = [(g, QUICKLOOK_CLASSES.get(c, ("white",))[0]) for g, c in zip(near.geometry, near["class"])]
            for geom, colour in shown:
                for poly in getattr(geom, "geoms", [geom]):
                    x, y = poly.exterior.xy
                    ax[k, j].plot(x, y, "-", color=colour, lw=1.6)
            ax[k, j].set_xlim(l, r)
            ax[k, j].set_ylim(bt, t)
            ax[k, j].set_xticks([])
            ax[k, j].set_yticks([])
        ax[k, 0].set_ylabel(
            f"{cls}\n{b.area_m2:.0f} m², {b.height_before_m:.0f} → {b.height_after_m:.0f} m", fontsize=7
        )
    ax[0, 0].set_title("pre-event", fontsize=8)
    ax[0, 1].set_title("post-event", fontsize=8)
    ax[0, 2].set_title("post-event, every object by class", fontsize=8)
    fig.tight_layout()
    fig.savefig(a.out, dpi=80)
    Image.open(a.out).convert("RGB").quantize(64).save(a.out, optimize=True)
    print(a.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
