"""Quick-look of a generated stereo scene and its change run: a crop of one view per epoch, the truth dh
and the change mask at 99 %.

    .venv/bin/python bench/plot_big_stereo_scene.py /work/big/st1250 /work/big/run1250 docs/bigstereo_quicklook.png
"""

from __future__ import annotations

import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import rasterio  # noqa: E402
from rasterio.windows import Window  # noqa: E402

from geocd.geodesy import to_lonlat  # noqa: E402
from geocd.io.rpc import load_rpc_for_image  # noqa: E402


def main(scene: str, run: str, png: str, side: int = 400) -> None:
    with rasterio.open(f"{scene}/truth/dh.tif") as ds:
        dh = ds.read(1)
        h, w = dh.shape
        tr, crs = ds.transform, ds.crs
    with rasterio.open(f"{scene}/truth/dsm_A.tif") as ds:
        z_mean = float(np.mean(ds.read(1)))
    with rasterio.open(f"{run}/sc_change_mask.tif") as ds:
        m = ds.read(1).astype(float)
    # the crop holding the most truth change
    best, rc = -1, (0, 0)
    for r in range(0, h - side + 1, side // 2):
        for c in range(0, w - side + 1, side // 2):
            s = np.count_nonzero(np.abs(dh[r : r + side, c : c + side]) > 1)
            if s > best:
                best, rc = s, (r, c)
    r, c = rc
    f, ax = plt.subplots(1, 4, figsize=(16, 4.4))
    for a, name in zip(ax[:2], ("A_sat1", "B_sat1")):
        rpc = load_rpc_for_image(f"{scene}/images/{name}.tif")
        x, y = tr * (c + side / 2, r + side / 2)
        lon, lat = to_lonlat(np.array([x]), np.array([y]), crs)
        ic, ir = rpc.project(lon, lat, np.array([z_mean]))
        with rasterio.open(f"{scene}/images/{name}.tif") as ds:
            img = ds.read(1, window=Window(int(ic[0]) - side // 2, int(ir[0]) - side // 2, side, side), boundless=True)
        a.imshow(img, cmap="gray", vmin=np.percentile(img, 1), vmax=np.percentile(img, 99))
        a.set_title(f"{name}: image (sensor geometry) around the crop centre", fontsize=9)
    ax[2].imshow(dh[r : r + side, c : c + side], cmap="RdBu", vmin=-15, vmax=15)
    ax[2].set_title("truth dh = DSM B − DSM A (m)")
    mm = m[r : r + side, c : c + side]
    mm[mm == -128] = np.nan
    ax[3].imshow(mm, cmap="RdBu", vmin=-1.5, vmax=1.5)
    ax[3].set_title("sc_change_mask at 99 % (white: unobserved)")
    for a in ax:
        a.set_xticks([])
        a.set_yticks([])
    f.tight_layout()
    f.savefig(png, dpi=60)


if __name__ == "__main__":
    main(*sys.argv[1:4])
