"""Quick-look of the 2-D screen on sample_aoi: the two views, the dissimilarity, the change mask against truth.

.venv/bin/geocd screen sample_aoi --out /tmp/scr
.venv/bin/python bench/figures/screen_show.py /tmp/scr            # → docs/screen_sample_aoi.png
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import rasterio  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from geocd.geodesy import AOIGrid  # noqa: E402
from geocd.io.raster import read_on_grid  # noqa: E402


def main(out_dir: str) -> None:
    d = Path(out_dir)
    s = json.loads((d / "screen_summary.json").read_text())
    pa, pb = s["pair"]
    with rasterio.open(d / "screen_dissimilarity.tif") as ds:
        dis = ds.read(1)
        g = AOIGrid.from_raster(ds)
    with rasterio.open(d / "screen_change_mask.tif") as ds:
        m = ds.read(1) == 1
    t3 = np.nan_to_num(read_on_grid(ROOT / "sample_aoi/truth/change_mask.tif", g)) > 0
    n3 = np.nan_to_num(read_on_grid(ROOT / "sample_aoi/truth/non3d_mask.tif", g))
    truth = t3 | (n3 == 1)

    def view(epoch, name):
        with rasterio.open(d / "views" / f"{epoch}_{name}.tif") as ds:
            v = ds.read(1).astype(float)
        lo, hi = np.nanpercentile(v[v > 0], (2, 98))
        return np.clip((v - lo) / (hi - lo), 0, 1)

    fig, ax = plt.subplots(1, 4, figsize=(16, 4.4))
    ax[0].imshow(view(s["epoch_a"], pa), cmap="gray")
    ax[0].set_title(f"{s['epoch_a']}: {pa} on the terrain DEM")
    ax[1].imshow(view(s["epoch_b"], pb), cmap="gray")
    ax[1].set_title(f"{s['epoch_b']}: {pb}")
    im = ax[2].imshow(dis, cmap="magma", vmin=0, vmax=max(float(np.nanmax(dis)), 1e-6))
    ax[2].set_title(f"dissimilarity ({s['method']}), t = {s['threshold']:.2f}")
    fig.colorbar(im, ax=ax[2], fraction=0.046)
    rgb = np.ones((*m.shape, 3))
    rgb[m & truth] = (0.1, 0.6, 0.1)
    rgb[m & ~truth] = (0.9, 0.3, 0.1)
    rgb[~m & truth] = (0.2, 0.4, 0.9)
    tp, fp, fn = (m & truth).sum(), (m & ~truth).sum(), (~m & truth).sum()
    ax[3].imshow(rgb)
    ax[3].set_title(
        f"changed vs truth: F1 {2 * tp / (2 * tp + fp + fn):.3f}\ngreen hit, orange false, blue missed", fontsize=10
    )
    for a in ax:
        a.set_axis_off()
    fig.tight_layout()
    out = ROOT / "docs" / "screen_sample_aoi.png"
    fig.savefig(out, dpi=60)
    from PIL import Image

    Image.open(out).convert("RGB").quantize(64).save(out, optimize=True)  # a small PNG for the repository
    print(out)


if __name__ == "__main__":
    main(sys.argv[1])
