"""The terrain under a DSM when none is given, on several places: how much of each DSM stands above it.

``geocd mpp`` without ``--ground`` takes the progressive morphological filter of :mod:`geocd.terrain`, and refuses
before the annealing when more than ``RAISED_MAX`` of the cells stand ``min_height_m`` above it on both dates
(:mod:`geocd.mpp.detect`). Both were chosen on Kahramanmaraş. This script reports, per DSM, the share of its
valid cells more than ``min_height_m`` (2.5 m) above

* the terrain filter (the default now), and
* one grey opening wider than the largest building, smoothed (the former default),

on real DSMs of other places and sensors' runs (s2p's Réunion and Marseille DSMs; any DSM given with ``--dsm``)
and on generated towns (their truth DSMs, ``--town``).

Usage::

    python bench/eval_mpp_ground.py [--dsm NAME=PATH ...] [--town NAME=SCENE ...] [--json OUT]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
SHARED = REPO.parent / "shared" / "data"

#: real DSMs of places the defaults were not chosen on (s2p's own products)
REAL = {
    "reunion_s2p_pair": SHARED / "s2p_pleiades" / "expected_output" / "pair" / "dsm.tif",
    "marseille_s2p_triplet": SHARED / "s2p_pleiades" / "expected_output" / "triplet" / "dsm.tif",
}


def opening_ground(dsm: np.ndarray, width_cells: int) -> np.ndarray:
    """The former default: one grey opening wider than the largest building, then smoothed."""
    from scipy import ndimage

    ok = np.isfinite(dsm)
    fill = np.where(ok, dsm, np.nanmedian(dsm) if ok.any() else 0.0)
    w = int(width_cells) | 1
    return ndimage.uniform_filter(ndimage.grey_opening(fill, size=(w, w), mode="nearest"), size=w, mode="nearest")


def raised_shares(dsm: np.ndarray, posting_m: float) -> dict:
    from geocd.mpp.detect import RAISED_MAX
    from geocd.mpp.features import dsm_ground
    from geocd.mpp.params import MPPParams

    p = MPPParams()
    ok = np.isfinite(dsm)
    out = {"cells": int(ok.sum()), "raised_max": RAISED_MAX}
    for name, g in (
        ("terrain_filter", dsm_ground(dsm, posting_m)),
        ("one_opening", opening_ground(dsm, 2 * int(math.ceil(p.side_max_m / posting_m)) + 1)),
    ):
        out[name] = round(float(np.mean((dsm - g)[ok] > p.min_height_m)), 3)
    return out


def read(path: Path) -> tuple[np.ndarray, float]:
    import rasterio

    with rasterio.open(path) as ds:
        z = ds.read(1, masked=True).astype(np.float64).filled(np.nan)
        return z, float(ds.res[0])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dsm", action="append", default=[], help="NAME=PATH, a DSM GeoTIFF (metres)")
    ap.add_argument("--town", action="append", default=[], help="NAME=SCENE, a geocd synth folder (truth DSMs)")
    ap.add_argument("--json", type=Path)
    a = ap.parse_args(argv)
    dsms = {k: v for k, v in REAL.items() if v.is_file()}
    for spec in a.dsm:
        k, v = spec.split("=", 1)
        dsms[k] = Path(v)
    for spec in a.town:
        k, v = spec.split("=", 1)
        for ep in ("A", "B"):
            dsms[f"{k}_{ep}"] = Path(v) / "truth" / f"dsm_{ep}.tif"
    res = {}
    for name, path in dsms.items():
        z, posting = read(path)
        res[name] = raised_shares(z, posting)
        print(name, res[name], flush=True)
    if a.json:
        a.json.write_text(json.dumps(res, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
