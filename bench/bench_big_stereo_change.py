"""Whole-scene stereo → change → products on a generated RPC stereo scene (bench/make_big_stereo_scene.py).

    # a self-consistency model learned on another scene of the generator (3 views in epoch A, other seed)
    nice -n 10 .venv/bin/python bench/bench_big_stereo_change.py model /work/big/calib1k OUT_MODEL
    # the run: tiled stereo of both epochs (one pair each) + tiled change test + products
    nice -n 10 .venv/bin/python bench/bench_big_stereo_change.py run /work/big/st2500 OUT --model OUT_MODEL/model.json
    .venv/bin/python bench/bench_big_stereo_change.py table run.*.json        # the figures side by side
    .venv/bin/python bench/bench_big_stereo_change.py same RUN_A RUN_B        # products bit for bit
    bash bench/stereo_change_cluster_kill.sh SCENE MODEL OUT                   # LocalCluster / address / SIGKILL

``run`` is the path ``geocd stereo --tile-size`` + ``geocd change --tiled`` take
(:func:`geocd.stereo.tiled.run_stereo_tiled`, then :func:`geocd.change.tiled.change_test_tiled` on the
pair-DEMs). It prints, per stage and in all: wall, CPU seconds of the process tree (this process and its
reaped children: the LocalCluster's nanny and worker processes), peak RSS of the whole process tree
(psutil, every 0.2 s), cells/s and seconds per million cells; then the change result against the
generator's truth (read after the timed part): changed buildings (demolished or new) found at 99 %
(≥ ``--hit-share`` of the footprint's observed cells changed), unchanged buildings flagged, changed
cells outside the truth changes (grown by 2 m), and the load average over the run.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from _memwatch import TreeMemory  # noqa: E402


def _cpu() -> float:
    s = resource.getrusage(resource.RUSAGE_SELF)
    c = resource.getrusage(resource.RUSAGE_CHILDREN)
    return s.ru_utime + s.ru_stime + c.ru_utime + c.ru_stime


class _Load:
    """Load average sampled every 10 s."""

    def __init__(self):
        import threading

        self.samples: list[float] = []
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._run, daemon=True)

    def _run(self):
        while not self._stop.wait(10.0):
            self.samples.append(os.getloadavg()[0])

    def __enter__(self):
        self.samples.append(os.getloadavg()[0])
        self._t.start()
        return self

    def __exit__(self, *a):
        self._stop.set()
        self.samples.append(os.getloadavg()[0])

    def summary(self) -> dict:
        s = np.array(self.samples)
        return {
            "min": round(float(s.min()), 2),
            "median": round(float(np.median(s)), 2),
            "max": round(float(s.max()), 2),
        }


def cmd_model(a) -> None:
    from geocd.consistency import ConsistencyParams, learn_self_consistency
    from geocd.tiling.params import TilingParams
    from geocd.stereo.products import read_pair_dem
    from geocd.stereo.tiled import run_stereo_tiled

    out = Path(a.out)
    t0 = time.perf_counter()
    r = run_stereo_tiled(
        Path(a.scene) / "scene.yaml",
        epochs=["A"],
        out_dir=out,
        tiling=TilingParams(tile_size=a.tile_size, scheduler=a.scheduler),
    )
    pairs = [read_pair_dem(p) for p in r["outputs"].values()]
    model = learn_self_consistency(
        [pairs],
        ConsistencyParams(),
        provenance={"scene": str(a.scene), "scene_class": "synthetic-blocks", "gsd_m": pairs[0].grid.posting_m},
    )
    path = model.save(out / "model.json")
    print(
        json.dumps(
            {
                "model": str(path),
                "pairs": list(r["outputs"]),
                "completeness": r["completeness"],
                "wall_s": round(time.perf_counter() - t0, 1),
            },
            indent=1,
        )
    )


def evaluate(scene: Path, mask_path: Path, hit_share: float) -> dict:
    """Changed buildings found, unchanged ones flagged, changed cells outside the truth changes."""
    import geopandas as gpd
    import rasterio
    from rasterio.features import rasterize
    from scipy.ndimage import binary_dilation

    from geocd.consistency import CHANGE_NODATA

    with rasterio.open(mask_path) as ds:
        m = ds.read(1)
        tr, shape, post = ds.transform, ds.shape, ds.res[0]
    with rasterio.open(scene / "truth" / "change_mask.tif") as ds:
        truth = ds.read(1) > 0
    b = gpd.read_file(scene / "truth" / "buildings.gpkg")
    obs = m != CHANGE_NODATA
    changed = obs & (m != 0)
    lab = rasterize(
        ((g, i + 1) for i, g in enumerate(b.geometry)), out_shape=shape, transform=tr, fill=0, dtype="int32"
    )
    n = len(b) + 1
    n_obs = np.bincount(lab[obs].ravel(), minlength=n)
    n_chg = np.bincount(lab[changed].ravel(), minlength=n)
    share = np.where(n_obs > 0, n_chg / np.maximum(n_obs, 1), np.nan)[1:]
    st = b["status"].to_numpy()
    out = {}
    for s in ("demolished", "new", "unchanged"):
        k = st == s
        seen = k & np.isfinite(share)
        hit = seen & (np.nan_to_num(share) >= hit_share)
        out[s] = {"buildings": int(k.sum()), "observed": int(seen.sum()), "flagged": int(hit.sum())}
    ch = out["demolished"]["observed"] + out["new"]["observed"]
    out["changed_recall"] = round((out["demolished"]["flagged"] + out["new"]["flagged"]) / max(ch, 1), 4)
    out["unchanged_flagged_share"] = round(out["unchanged"]["flagged"] / max(out["unchanged"]["observed"], 1), 4)
    grow = max(int(round(2.0 / post)), 1)
    near = binary_dilation(truth, iterations=grow)
    out["changed_cells"] = int(changed.sum())
    out["false_alarm_cells"] = int((changed & ~near).sum())
    out["false_alarm_cell_share"] = round(float((changed & ~near).sum() / max((obs & ~near).sum(), 1)), 6)
    out["truth_changed_cells_detected"] = round(float((changed & truth).sum() / max((obs & truth).sum(), 1)), 4)
    out["observed_fraction"] = round(float(obs.mean()), 4)
    out["hit_share"] = hit_share
    return out


def cmd_run(a) -> None:
    from geocd.change.tiled import change_test_tiled
    from geocd.consistency import ChangeParams, SelfConsistencyModel
    from geocd.tiling.params import TilingParams
    from geocd.stereo.tiled import run_stereo_tiled

    scene = Path(a.scene)
    out = Path(a.out)
    tiling = TilingParams(tile_size=a.tile_size, scheduler=a.scheduler)
    model = SelfConsistencyModel.load(a.model)
    stages = {}
    with _Load() as load, TreeMemory() as mem:
        t0, c0 = time.perf_counter(), _cpu()
        st = run_stereo_tiled(scene / "scene.yaml", epochs=["A", "B"], out_dir=out, tiling=tiling)
        t1, c1, p1 = time.perf_counter(), _cpu(), mem.peak
        A = [str(v) for k, v in st["outputs"].items() if k.startswith("A/")]
        B = [str(v) for k, v in st["outputs"].items() if k.startswith("B/")]
        res = change_test_tiled(
            A, B, model, out, params=ChangeParams(confidences=(90.0, 95.0, 99.0)), tiling=tiling, region_confidence=99.0
        )
        t2, c2 = time.perf_counter(), _cpu()
    cells = st["grid"].width * st["grid"].height
    stages["stereo"] = {
        "wall_s": round(t1 - t0, 1),
        "cpu_s": round(c1 - c0, 1),
        "peak_tree_rss_gb": round(p1 / 1e9, 3),
        "completeness": {k: round(v, 4) for k, v in st["completeness"].items()},
        "margins": st["margins"],
        "pair_cells_per_s": round(len(st["outputs"]) * cells / (t1 - t0)),
    }
    stages["change"] = {
        "wall_s": round(t2 - t1, 1),
        "cpu_s": round(c2 - c1, 1),
        "passes": res.passes,
        "exact": res.exact,
    }
    wall = t2 - t0
    rep = {
        "scene": str(scene),
        "cells": cells,
        "grid": [st["grid"].width, st["grid"].height],
        "tile_size": a.tile_size,
        "scheduler": a.scheduler,
        "pairs": list(st["outputs"]),
        "wall_s": round(wall, 1),
        "cpu_s": round(c2 - c0, 1),
        "cells_per_s": round(cells / wall),
        "s_per_mcell": round(wall / cells * 1e6, 2),
        "peak_tree_rss_gb": round(mem.peak / 1e9, 3),
        "load_average": load.summary(),
        "stages": stages,
        "outputs": {k: str(v) for k, v in res.outputs.items()},
    }
    rep["truth"] = evaluate(scene, Path(res.outputs["change_mask"]), a.hit_share)
    print(json.dumps(rep, indent=1))
    if a.json:
        Path(a.json).write_text(json.dumps(rep, indent=1))


def cmd_table(a) -> None:
    rows = [json.loads(Path(p).read_text()) for p in a.files]
    rows.sort(key=lambda r: r["cells"])
    print(
        "| cells | wall | CPU | cells/s | s per M cells | peak tree RSS | load (median) | changed buildings found "
        "| unchanged flagged | false-alarm cells |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        t = r["truth"]
        print(
            f"| {r['grid'][0]}² | {r['wall_s']} s | {r['cpu_s']} s | {r['cells_per_s']:,} | {r['s_per_mcell']} | "
            f"{r['peak_tree_rss_gb']} GB | {r['load_average']['median']} | {t['changed_recall']:.1%} of "
            f"{t['demolished']['observed'] + t['new']['observed']} | {t['unchanged_flagged_share']:.2%} | "
            f"{t['false_alarm_cell_share']:.4%} |"
        )
    for r0, r1 in zip(rows, rows[1:]):
        print(
            f"{r0['grid'][0]}² → {r1['grid'][0]}²: ×{r1['cells'] / r0['cells']:.2f} cells, "
            f"×{r1['wall_s'] / r0['wall_s']:.2f} wall"
        )


def cmd_same(a) -> None:
    """Compare two run folders' products: every GeoTIFF's arrays bit for bit (NaN = NaN), every
    GeoPackage layer's attributes and geometries (WKB), except the styles' update timestamps."""
    import pyogrio
    import rasterio

    ref, other = Path(a.a), Path(a.b)
    rows, ok = [], True
    for f in sorted(ref.rglob("*.tif")):
        if ".geocd-work" in f.parts:
            continue
        g = other / f.relative_to(ref)
        if not g.exists():
            rows.append({"file": str(f.relative_to(ref)), "same": False, "why": "missing"})
            ok = False
            continue
        with rasterio.open(f) as x, rasterio.open(g) as y:
            A, B = x.read(), y.read()
        same = A.shape == B.shape and np.array_equal(A, B, equal_nan=bool(np.issubdtype(A.dtype, np.floating)))
        rows.append({"file": str(f.relative_to(ref)), "shape": list(A.shape), "same": bool(same)})
        ok &= same
    for f in sorted(ref.rglob("*.gpkg")):
        if ".geocd-work" in f.parts:
            continue
        g = other / f.relative_to(ref)
        for lyr, _ in pyogrio.list_layers(f):
            x = pyogrio.read_dataframe(f, layer=lyr)
            y = pyogrio.read_dataframe(g, layer=lyr)
            if lyr == "layer_styles":
                x, y = (d.drop(columns=[c for c in ("update_time",) if c in d.columns]) for d in (x, y))
            if "geometry" in x.columns:
                same = x.drop(columns="geometry").equals(y.drop(columns="geometry")) and list(
                    x.geometry.to_wkb()
                ) == list(y.geometry.to_wkb())
            else:
                same = x.equals(y)
            rows.append({"file": f"{f.relative_to(ref)}:{lyr}", "rows": len(x), "same": bool(same)})
            ok &= same
    rep = {"same": bool(ok), "a": str(ref), "b": str(other), "products": rows}
    print(json.dumps(rep, indent=1))
    if a.json:
        Path(a.json).write_text(json.dumps(rep, indent=1))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    m = sub.add_parser("model")
    m.add_argument("scene")
    m.add_argument("out")
    r = sub.add_parser("run")
    r.add_argument("scene")
    r.add_argument("out")
    r.add_argument("--model", required=True)
    r.add_argument("--hit-share", type=float, default=0.3)
    r.add_argument("--json", default=None)
    for p in (m, r):
        p.add_argument("--tile-size", type=int, default=1024)
        p.add_argument("--scheduler", default="auto")
    c = sub.add_parser("same")
    c.add_argument("a")
    c.add_argument("b")
    c.add_argument("--json", default=None)
    t = sub.add_parser("table")
    t.add_argument("files", nargs="+")
    a = ap.parse_args()
    {"model": cmd_model, "run": cmd_run, "same": cmd_same, "table": cmd_table}[a.cmd](a)


if __name__ == "__main__":
    main()
