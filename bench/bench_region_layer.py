"""Memory and time of merging ~1 M change regions across tile seams and writing the ``changes`` layer.

``make DIR`` labels synthetic tiles (smoothed noise: ~12.6 cells per region, like the 20 000² demdiff scene)
and pickles their :class:`~geocd.tiling.regions.TileRegions`; ``write DIR OUT.gpkg --mode whole|batches``
loads them, merges, builds the layer (at once, or in batches) and writes it, printing the client's peak RSS
above the loaded tiles (bytes of the process, sampled every 0.05 s) and the wall time as JSON;
``same A.gpkg B.gpkg`` compares two layers (attributes and WKB, in order).

    python bench/bench_region_layer.py make /tmp/regions --tiles 7x6
    python bench/bench_region_layer.py write /tmp/regions whole.gpkg --mode whole
    python bench/bench_region_layer.py write /tmp/regions batches.gpkg --mode batches
    python bench/bench_region_layer.py same whole.gpkg batches.gpkg
"""

from __future__ import annotations

import argparse
import gc
import json
import pickle
import sys
import time
from pathlib import Path

import numpy as np
from affine import Affine
from scipy import ndimage

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _memwatch import TreeMemory, tree_rss  # noqa: E402

from geocd.geodesy import AOIGrid  # noqa: E402
from geocd.tiling import TileGrid  # noqa: E402
from geocd.tiling.regions import merge_regions, regions_layer, regions_layer_batches, tile_regions  # noqa: E402


def _grid(nr: int, nc: int, size: int) -> AOIGrid:
    return AOIGrid("EPSG:32631", Affine(1.0, 0, 500000.0, 0, -1.0, 4800000.0), nc * size, nr * size)


def make(d: Path, nr: int, nc: int, size: int) -> None:
    d.mkdir(parents=True, exist_ok=True)
    g = _grid(nr, nc, size)
    tg = TileGrid(g, (size, size), 0)
    parts = []
    rng = np.random.default_rng(0)
    f = ndimage.gaussian_filter(rng.normal(size=(g.height, g.width)).astype(np.float32), 1.2)
    f /= f.std()
    for t in tg:
        sl = t.core_slices
        ft = f[sl]
        sign = np.where(ft > 1.0, 1, np.where(ft < -1.0, -1, 0)).astype(np.int8)
        dz = (ft * 2.0).astype(np.float64)
        tr = tile_regions(sign, dz, t, g, sigma=np.full(sign.shape, 0.2), confidence=np.full(sign.shape, 99.5))
        tr.labels = None
        parts.append(tr)
    n = sum(st["n"].size for p in parts for st in p.stats.values())
    (d / "parts.pkl").write_bytes(pickle.dumps({"shape": (nr, nc, size), "parts": parts}, protocol=5))
    print(json.dumps({"tiles": len(parts), "tile_regions": int(n)}))


def write(d: Path, out: Path, mode: str) -> None:
    data = pickle.loads((d / "parts.pkl").read_bytes())
    nr, nc, size = data["shape"]
    g = _grid(nr, nc, size)
    tg = TileGrid(g, (size, size), 0)
    gc.collect()
    base = tree_rss()
    from geocd.io.vector import write_gpkg

    t0 = time.perf_counter()
    with TreeMemory(interval_s=0.05) as m:
        merged = merge_regions(data.pop("parts"), tg, 1)
        t1 = time.perf_counter()
        kw = dict(cell_area_m2=1.0, method="demdiff", epoch_a="A", epoch_b="B", volume_sigma=lambda k: 1.0)
        layer = (regions_layer if mode == "whole" else regions_layer_batches)(merged, g, **kw)
        write_gpkg(out, {"changes": layer})
    print(
        json.dumps(
            {
                "mode": mode,
                "regions": len(merged),
                "base_rss_mb": base >> 20,
                "peak_above_base_mb": (m.peak - base) >> 20,
                "merge_s": round(t1 - t0, 2),
                "wall_s": round(time.perf_counter() - t0, 2),
                "gpkg_mb": out.stat().st_size >> 20,
            }
        )
    )


def same(a: Path, b: Path) -> None:
    import pyogrio

    ia, ib = pyogrio.read_info(a, layer="changes"), pyogrio.read_info(b, layer="changes")
    ra = pyogrio.read_dataframe(a, layer="changes")
    rb = pyogrio.read_dataframe(b, layer="changes")
    ok = (
        ia["geometry_type"] == ib["geometry_type"]
        and ra.drop(columns="geometry").equals(rb.drop(columns="geometry"))
        and list(ra.geometry.to_wkb()) == list(rb.geometry.to_wkb())
    )
    print(json.dumps({"same": bool(ok), "rows": len(ra), "geometry_type": [ia["geometry_type"], ib["geometry_type"]]}))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("cmd", choices=("make", "write", "same"))
    ap.add_argument("a")
    ap.add_argument("b", nargs="?")
    ap.add_argument("--tiles", default="7x6")
    ap.add_argument("--size", type=int, default=1024)
    ap.add_argument("--mode", default="batches", choices=("whole", "batches"))
    a = ap.parse_args()
    if a.cmd == "make":
        nr, nc = (int(v) for v in a.tiles.split("x"))
        make(Path(a.a), nr, nc, a.size)
    elif a.cmd == "write":
        write(Path(a.a), Path(a.b), a.mode)
    else:
        same(Path(a.a), Path(a.b))


if __name__ == "__main__":
    main()
