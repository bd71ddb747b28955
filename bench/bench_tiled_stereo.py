"""Stereo tiled vs untiled: sample_aoi's epoch-B pairs (vs the truth DSM) and the Pléiades Réunion pair
(s2p's input, vs s2p's DSM), cut into tiles artificially.

    nice -n 10 .venv/bin/python bench/bench_tiled_stereo.py OUT [--tile-size 256] [--which sample,pleiades]

For each pair: completeness, median |dz| to the reference (after the median offset for Pléiades, whose
RPCs carry a vertical bias), share of errors > 1 m, for the untiled and the tiled pair-DEM; and cell by
cell: the share of commonly valid cells whose heights agree within 0.1 m, and the flags that agree.
Wall times are reported but the machine is shared: compare them only within one run.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import yaml

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data"
sys.path.insert(0, str(REPO))


def pleiades_manifest(out: Path) -> Path:
    import rasterio

    with rasterio.open(DATA / "s2p_pleiades" / "expected_output" / "pair" / "dsm.tif") as ds:
        b = ds.bounds
        crs = ds.crs.to_string()
        post = ds.res[0]
    m = {
        "geocd_manifest": 1,
        "name": "pleiades_reunion_pair",
        "aoi": {"crs": crs, "bounds": [b.left, b.bottom, b.right, b.top], "posting_m": post},
        "epochs": [
            {
                "name": "E",
                "images": [
                    {"path": str(DATA / "s2p_pleiades" / "input_pair" / f"{n}.tif"), "name": n}
                    for n in ("img_01", "img_02")
                ],
            }
        ],
    }
    p = out / "pleiades.yaml"
    p.write_text(yaml.safe_dump(m))
    return p


def compare(u_path: Path, t_path: Path, ref_path: Path, offset: bool) -> dict:
    from geocd.io.raster import read_dem
    from geocd.stereo.products import read_pair_dem

    a, b = read_pair_dem(u_path), read_pair_dem(t_path)
    ref = read_dem(ref_path, grid=a.grid).height_m
    out = {}
    for k, p in (("untiled", a), ("tiled", b)):
        d = (p.z_m - ref)[p.valid & np.isfinite(ref)].astype(np.float64)
        if offset:
            d = d - np.median(d)
        out[k] = {
            "completeness": round(float(p.valid.mean()), 4),
            "median_abs_m": round(float(np.median(np.abs(d))), 3),
            "over_1m": round(float(np.mean(np.abs(d) > 1.0)), 4),
        }
    both = a.valid & b.valid
    dz = np.abs(a.z_m - b.z_m)[both]
    out["cells"] = {
        "within_0.1m": round(float(np.mean(dz < 0.1)), 4),
        "p99_m": round(float(np.percentile(dz, 99)), 3),
        "flags_agree": round(float(np.mean(a.flags == b.flags)), 4),
    }
    out["margin_cells"] = (
        json.loads(b.meta.get("tiled", "{}")) if isinstance(b.meta.get("tiled"), str) else (b.meta.get("tiled") or {})
    )
    return out


def main() -> None:
    from geocd.tiling.params import TilingParams
    from geocd.stereo.pipeline import run_stereo
    from geocd.stereo.tiled import run_stereo_tiled

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out")
    ap.add_argument("--tile-size", type=int, default=256)
    ap.add_argument("--which", default="sample,pleiades")
    ap.add_argument("--json", default=None)
    a = ap.parse_args()
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    rep = {"tile_size": a.tile_size}
    cases = []
    if "sample" in a.which:
        cases.append(
            (
                "sample_aoi",
                REPO / "sample_aoi" / "scene.yaml",
                ["B"],
                REPO / "sample_aoi" / "truth" / "dsm_B.tif",
                False,
            )
        )
    if "pleiades" in a.which:
        cases.append(
            (
                "pleiades",
                pleiades_manifest(out),
                None,
                DATA / "s2p_pleiades" / "expected_output" / "pair" / "dsm.tif",
                True,
            )
        )
    for name, man, epochs, ref, offset in cases:
        t = time.perf_counter()
        u = run_stereo(man, epochs=epochs, out_dir=out / name / "untiled")["outputs"]
        tu = time.perf_counter() - t
        t = time.perf_counter()
        r = run_stereo_tiled(
            man,
            epochs=epochs,
            out_dir=out / name / "tiled",
            tiling=TilingParams(tile_size=a.tile_size, scheduler="sync"),
        )
        tt = time.perf_counter() - t
        rep[name] = {
            "wall_untiled_s": round(tu, 1),
            "wall_tiled_s": round(tt, 1),
            "margins": r["margins"],
            "pairs": {k: compare(u[k], r["outputs"][k], ref, offset) for k in u},
        }
        print(json.dumps({name: rep[name]}, indent=1), flush=True)
    if a.json:
        Path(a.json).write_text(json.dumps(rep, indent=1))


if __name__ == "__main__":
    main()
