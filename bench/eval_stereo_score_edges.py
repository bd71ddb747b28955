"""Where windows straddling a height step fall in the MDL score's deciles (docs/stereo.md, "Is the score informative?").

With the whole-window MDL they gathered in deciles 2–3 (the deciles' bump); with the score of a match taken as
its worst 3 × 3 sub-window they gather in decile 10.

Usage: ``geocd run sample_aoi --out /tmp/run3`` then ``.venv/bin/python bench/eval_stereo_score_edges.py [/tmp/run3]``.
For the satellite–satellite pair-DEMs of the run: per MDL-score decile, the fraction of matches with
|z − truth| > 1 m, the share of cells whose 7 × 7 matching window straddles a > 2 m height step of the truth DSM,
and the bad fraction off and on such steps.
"""

import sys
import glob

import numpy as np
from scipy import ndimage as ndi
from geocd.stereo import read_pair_dem
from geocd.io.raster import read_dem

RUN = sys.argv[1] if len(sys.argv) > 1 else "/tmp/run3"
S = []
E = []
B = []
T = []
for f in sorted(glob.glob(f"{RUN}/stereo/*/*sat*__*sat*.tif")):
    pd = read_pair_dem(f)
    ep = f.split("/")[-2]
    t = read_dem(f"sample_aoi/truth/dsm_{ep}.tif", grid=pd.grid).height_m
    rng = ndi.maximum_filter(t, 7) - ndi.minimum_filter(t, 7)  # height range in the 7x7 matching window
    v = pd.valid & np.isfinite(t)
    S.append(pd.score[v])
    E.append(np.abs(pd.z_m - t)[v] > 1)
    B.append(rng[v] > 2.0)
    T.append((1 - pd.ncc)[v])
S = np.concatenate(S)
E = np.concatenate(E)
B = np.concatenate(B)
T = np.concatenate(T)
edges = np.quantile(S, np.linspace(0, 1, 11))
idx = np.clip(np.searchsorted(edges, S, side="right") - 1, 0, 9)
print("decile: %bad | share of cells whose window straddles a >2 m step | %bad off steps | %bad on steps")
for k in range(10):
    m = idx == k
    print(
        k + 1,
        f"{100 * E[m].mean():.1f}",
        f"{100 * B[m].mean():.1f}",
        f"{100 * E[m & ~B].mean():.1f}",
        f"{100 * E[m & B].mean():.1f}",
    )
print("overall share straddling", B.mean(), "bad share among straddling", E[B].mean(), "off", E[~B].mean())
