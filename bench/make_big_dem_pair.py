"""Make a large synthetic DEM pair with known changes (geocd.synth.bigdem) and report time and memory.

    nice -n 10 .venv/bin/python bench/make_big_dem_pair.py /path/to/out --size 20000 [--scheduler auto]

Prints wall time, cells/s and the peak RSS of the whole process tree (this process and
every dask worker), sampled with psutil every 0.2 s.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _memwatch import TreeMemory  # noqa: E402

from geocd.synth.bigdem import DEMPairParams, make_dem_pair  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out")
    ap.add_argument("--size", type=int, default=20000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--tile-size", type=int, default=2048)
    ap.add_argument("--scheduler", default="auto")
    a = ap.parse_args()
    p = DEMPairParams(size=a.size, seed=a.seed)
    with TreeMemory() as mem:
        t0 = time.perf_counter()
        paths = make_dem_pair(a.out, p, tile_size=a.tile_size, scheduler=a.scheduler)
        wall = time.perf_counter() - t0
    cells = a.size * a.size
    rep = {
        "size": a.size,
        "cells": cells,
        "wall_s": round(wall, 1),
        "cells_per_s": round(cells / wall),
        "peak_tree_rss_gb": round(mem.peak / 1e9, 3),
        "scheduler": a.scheduler,
        "outputs": {k: str(v) for k, v in paths.items()},
    }
    print(json.dumps(rep, indent=1))


if __name__ == "__main__":
    main()
