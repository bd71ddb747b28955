"""Make a large two-epoch RPC stereo scene with known changes (geocd.synth.bigstereo); report time and memory.

    nice -n 10 .venv/bin/python bench/make_big_stereo_scene.py OUT --cells 2500 [--seed 0] [--views-a 2]

Prints wall time, cells/s, image pixels/s and the peak RSS of the whole process tree (sampled every 0.2 s).
``--views-a 3`` gives epoch A three views (three pairs): a scene to learn a self-consistency model on.
``--event-radius-m R [--event-centre-m E N]``: a local event — buildings change only within R m of the AOI
centre (+ E, N m); ``--demolished-fraction`` / ``--new-fraction`` (default 0.04 each) apply inside it.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _memwatch import TreeMemory  # noqa: E402

from geocd.synth.bigstereo import StereoSceneParams, make_stereo_scene  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out")
    ap.add_argument("--cells", type=int, default=2500)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--views-a", type=int, default=2, choices=(2, 3))
    ap.add_argument("--workers", type=int, default=None)
    ap.add_argument("--block", type=int, default=512)
    ap.add_argument(
        "--event-radius-m",
        type=float,
        default=None,
        help="buildings change only within this distance of the event centre (default: anywhere)",
    )
    ap.add_argument(
        "--event-centre-m",
        type=float,
        nargs=2,
        default=(0.0, 0.0),
        metavar=("EAST", "NORTH"),
        help="the event centre, metres from the AOI centre (default 0 0)",
    )
    ap.add_argument("--demolished-fraction", type=float, default=StereoSceneParams.demolished_fraction)
    ap.add_argument("--new-fraction", type=float, default=StereoSceneParams.new_fraction)
    a = ap.parse_args()
    kw = {
        "event_radius_m": a.event_radius_m,
        "event_centre_m": tuple(a.event_centre_m),
        "demolished_fraction": a.demolished_fraction,
        "new_fraction": a.new_fraction,
    }
    if a.views_a == 3:
        kw["views_a"] = ((-12.0, 2.0), (0.0, 2.0), (12.0, 2.0))
    p = StereoSceneParams(cells=a.cells, seed=a.seed, **kw)
    with TreeMemory() as mem:
        t0 = time.perf_counter()
        r = make_stereo_scene(a.out, p, block=a.block, workers=a.workers)
        wall = time.perf_counter() - t0
    px = sum(v["width"] * v["height"] for v in r["report"]["views"])
    rep = {
        "cells": a.cells,
        "wall_s": round(wall, 1),
        "cells_per_s": round(a.cells**2 / wall),
        "image_pixels": px,
        "pixels_per_s": round(px / wall),
        "peak_tree_rss_gb": round(mem.peak / 1e9, 3),
        "buildings": r["report"]["buildings"],
        "event": r["report"].get("event"),
        "views": r["report"]["views"],
        "timings": r["report"]["timings"],
        "manifest": str(r["manifest"]),
    }
    print(json.dumps(rep, indent=1))


if __name__ == "__main__":
    main()
