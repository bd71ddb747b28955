"""Object-space stereo throughput on the s2p Pléiades pair, against baselines measured in the same run.

1. Kernel level, on the same crop of the s2p DSM grid (``--crop`` cells square, ``--planes``
   height planes, 7×7 windows, both images warped per plane):

   * geocd: :class:`geocd.stereo.PlaneSweep` + the fused running-sum kernel ``sweep_step``
     (O(cells × planes), numba, all threads);
   * numpy box filters (``scipy.ndimage.uniform_filter`` of the five products, also
     O(cells × planes), single thread);
   * numpy direct windows (``sliding_window_view`` sums, O(cells × planes × window²)),
     the textbook implementation.

   Reported: cell-plane evaluations per second and the ratios.

2. The whole pair: :func:`geocd.stereo.match_pair` on s2p's DSM grid (721 × 739 cells at
   0.5 m) from the RPCs' own height range (coarse-to-fine, pointing correction): best-of-``--repeat`` wall
   time, CPU time, cell-height evaluations and evaluations per second.

3. Time against area (in process, warm): the pair on ¼, ½ and all of the whole overlap of the
   two images (centred sub-grids of the CLI's default AOI): wall, CPU and cell-height
   evaluations per cell — the work per cell should not grow with the AOI.

4. Whole process against whole process (``--whole``): ``geocd info`` on an image, ``geocd stereo``
   on a manifest of the pair (default AOI: the whole overlap) and ``geocd run sample_aoi``, each
   **cold** (an empty numba cache: ``NUMBA_CACHE_DIR`` pointed at a new folder, so every kernel
   the command uses is compiled) and then **warm** (same folder), as a user runs them; wall and
   CPU of the process tree. With ``--cars PATH/TO/cars`` (CARS in its own venv, never in geocd's;
   flat initial elevation at the site's height, 0.5 m, no geoid, 2 workers as in peers.md), CARS's
   whole process on the same pair in the same run, and both final products — geocd's pair-DEM
   and CARS's ``dsm/dsm.tif`` (not an intermediate under ``intermediate_data/``) — against s2p's
   DSM on s2p's grid: NMAD after the median offset, fraction within 1 m, completeness on s2p's
   valid cells.

Sections 1–3 warm numba before timing; section 4 measures the cold start on purpose. The
machine is shared: the load average is printed with the figures (compare CPU seconds and
ratios within a run), and in-process figures are the best of ``--repeat`` runs.

Usage (``PEERS``: the peers' folder of ``python -m bench.peers --install``, ``~/.cache/geocd/peers``)::

    .venv/bin/python bench/bench_stereo.py [--crop 160] [--planes 48] [--repeat 3] [--whole]
        [--cars PEERS/cars-1.3/bin/cars] [--json bench/results/stereo_bench.json]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("GEOCD_SHARED_DATA", REPO.parent / "shared" / "data")) / "s2p_pleiades"
sys.path.insert(0, str(REPO))

import geocd  # noqa: E402,F401  (first: sets OMP_WAIT_POLICY before numba starts its threads)
import rasterio  # noqa: E402
from geocd.geodesy import AOIGrid  # noqa: E402
from geocd.stereo import FLAGS, read_pair_dem  # noqa: E402

from bench._memwatch import geocd_command, geocd_env, run_process  # noqa: E402


def load_s2p_dsm() -> tuple[np.ndarray, AOIGrid]:
    """s2p's DSM of the pair (NaN where it has no height) and its grid."""
    with rasterio.open(DATA / "expected_output" / "pair" / "dsm.tif") as ds:
        return ds.read(1, masked=True).astype(np.float64).filled(np.nan), AOIGrid.from_raster(ds)


def load_pair():
    from geocd.io.cameras import load_camera
    from geocd.stereo.scene import read_chip

    ref, grid = load_s2p_dsm()
    cams, chips = [], []
    for n in ("img_01", "img_02"):
        p = DATA / "input_pair" / f"{n}.tif"
        cam = load_camera(p)
        cams.append(cam)
        chips.append(
            read_chip(p, cam, grid, float(np.nanmin(ref)) - 300, float(np.nanmax(ref)) + 300, name=n, margin_px=40)
        )
    return grid, ref, cams, chips


def numpy_box(stack_fn, K, r, eps, min_n):
    """Best 1 − NCC over planes with scipy box filters (O(cells × planes))."""
    from scipy import ndimage

    from geocd.stereo._kernels import ncc_cost_ref

    best = None
    for k in range(K):
        a, b = stack_fn(k)
        ok = np.isfinite(a) & np.isfinite(b)
        A = np.where(ok, a, 0.0).astype(np.float64)
        B = np.where(ok, b, 0.0).astype(np.float64)
        w = 2 * r + 1
        f = lambda x: ndimage.uniform_filter(x, w, mode="constant") * (w * w)  # noqa: E731
        mom = (f(ok.astype(np.float64)), f(A), f(B), f(A * A), f(B * B), f(A * B))  # indexable like (6, h, w)
        c = ncc_cost_ref(mom, min_n, eps)[0]
        best = c if best is None else np.minimum(best, c)
    return best


def numpy_direct(stack_fn, K, r, eps, min_n):
    """Best 1 − NCC over planes with explicit windows (O(cells × planes × window²))."""
    from numpy.lib.stride_tricks import sliding_window_view

    from geocd.stereo._kernels import ncc_cost_ref

    best = None
    w = 2 * r + 1
    for k in range(K):
        a, b = stack_fn(k)
        ok = np.isfinite(a) & np.isfinite(b)
        A = np.pad(np.where(ok, a, 0.0).astype(np.float64), r)
        B = np.pad(np.where(ok, b, 0.0).astype(np.float64), r)
        O = np.pad(ok.astype(np.float64), r)
        wa, wb, wo = (sliding_window_view(x, (w, w)) for x in (A, B, O))
        mom = tuple(x.sum(axis=(2, 3)) for x in (wo, wa, wb, wa * wa, wb * wb, wa * wb))
        c = ncc_cost_ref(mom, min_n, eps)[0]
        best = c if best is None else np.minimum(best, c)
    return best


def kernel_bench(grid, ref, cams, chips, crop: int, planes: int, repeat: int) -> dict:
    from geocd.stereo import HeightSearch, PlaneSweep
    from geocd.stereo import _kernels as K

    r, eps, min_n = 3, 9.0, 37.0
    H, W = grid.shape
    r0, c0 = (H - crop) // 2, (W - crop) // 2
    sub = grid.subgrid(r0, c0, crop, crop)
    h0 = float(np.nanmedian(ref[r0 : r0 + crop, c0 : c0 + crop])) - planes * 0.8
    search = HeightSearch.uniform(sub.shape, h0, h0 + (planes - 1) * 1.6, 1.6)
    sweep = PlaneSweep(sub, chips, cams, search, tile_size=max(crop, 32), margin=r)
    tile = sweep.tiles()[0]
    # the warped stacks, for the numpy baselines (warping is not what they are compared on)
    stacks = [sl.stack.copy() for sl in sweep.slices(tile)]

    def geocd_run():
        st = K.new_state(tile.outer_shape)
        work = np.empty((6, *tile.outer_shape))
        kmin, kmax = sweep.kmin(tile), sweep.kmax(tile)
        for sl in sweep.slices(tile):
            K.sweep_step(sl.stack[0], sl.stack[1], r, sl.k, kmin, kmax, min_n, eps, 1.0, st, work)
        K.sweep_finish(planes, 1.0, st)
        return st

    def geocd_kernel_only():
        st = K.new_state(tile.outer_shape)
        work = np.empty((6, *tile.outer_shape))
        kmin, kmax = sweep.kmin(tile), sweep.kmax(tile)
        for k, s in enumerate(stacks):
            K.sweep_step(s[0], s[1], r, k, kmin, kmax, min_n, eps, 1.0, st, work)
        K.sweep_finish(planes, 1.0, st)
        return st

    fn = lambda k: (stacks[k][0], stacks[k][1])  # noqa: E731
    geocd_run()  # warm-up (numba)
    n_eval = tile.outer_shape[0] * tile.outer_shape[1] * planes
    best = {
        "geocd sweep (warp + windows + update)": np.inf,
        "geocd windows + update only": np.inf,
        "numpy box filters": np.inf,
        "numpy direct windows": np.inf,
    }
    results = {}
    for _ in range(repeat):
        for name, f in (
            ("geocd sweep (warp + windows + update)", geocd_run),
            ("geocd windows + update only", geocd_kernel_only),
            ("numpy box filters", lambda: numpy_box(fn, planes, r, eps, min_n)),
            ("numpy direct windows", lambda: numpy_direct(fn, planes, r, eps, min_n)),
        ):
            t = time.perf_counter()
            out = f()
            best[name] = min(best[name], time.perf_counter() - t)
            results[name] = out
    # the kernels and the baselines agree on the best cost
    st = results["geocd windows + update only"]
    bc = np.where(np.isfinite(st[K.BEST_C]), st[K.BEST_C], np.nan)
    nb = results["numpy box filters"]
    nd = results["numpy direct windows"]
    inner = (slice(r, -r), slice(r, -r))
    agree = {
        "max |geocd − numpy box| (best 1−NCC)": float(
            np.nanmax(np.abs(bc[inner] - np.where(np.isfinite(nb), nb, np.nan)[inner]))
        ),
        "max |numpy box − direct|": float(
            np.nanmax(
                np.abs(np.where(np.isfinite(nb), nb, np.nan)[inner] - np.where(np.isfinite(nd), nd, np.nan)[inner])
            )
        ),
    }
    return {
        "crop_cells": f"{tile.outer_shape[1]}x{tile.outer_shape[0]}",
        "planes": planes,
        "window": 2 * r + 1,
        "evaluations": n_eval,
        "seconds": best,
        "evals_per_s": {k: n_eval / v for k, v in best.items()},
        "agreement": agree,
    }


def best_of(fn, repeat: int):
    """``(result, best wall s, best CPU s)`` of ``repeat`` calls: the machine is shared."""
    wall = cpu = np.inf
    out = None
    for _ in range(max(1, repeat)):
        t, c = time.perf_counter(), time.process_time()
        out = fn()
        wall, cpu = min(wall, time.perf_counter() - t), min(cpu, time.process_time() - c)
    return out, wall, cpu


def pair_bench(grid, ref, cams, chips, repeat: int = 1) -> dict:
    from geocd.stereo import StereoParams, match_pair

    small = grid.subgrid(0, 0, 128, 128)
    match_pair(chips[0], chips[1], cams[0], cams[1], small, params=StereoParams(height_range_m=(2250.0, 2400.0)))
    pd, wall, cpu = best_of(lambda: match_pair(chips[0], chips[1], cams[0], cams[1], grid), repeat)
    both = pd.valid & np.isfinite(ref)
    d = (pd.z_m - ref)[both]
    d = d - np.median(d)
    return {
        "grid": f"{grid.width}x{grid.height} at {grid.posting_m} m",
        "wall_s": wall,
        "cpu_s": cpu,
        "repeat": repeat,
        "evaluations": pd.meta["evaluations"],
        "evals_per_s_wall": pd.meta["evaluations"] / wall,
        "levels": pd.meta["levels"],
        "completeness": float(pd.valid[np.isfinite(ref)].mean()),
        "median_abs_dz_vs_s2p_m": float(np.median(np.abs(d))),
        "nmad_vs_s2p_m": float(1.4826 * np.median(np.abs(d - np.median(d)))),
    }


def _overlap_images():
    from geocd.io.manifest import parse_manifest
    from geocd.stereo.scene import load_epoch_images

    m = parse_manifest(
        {
            "epochs": [
                {
                    "name": "pair",
                    "images": [str(DATA / "input_pair" / "img_01.tif"), str(DATA / "input_pair" / "img_02.tif")],
                }
            ]
        },
        DATA / "input_pair",
    )
    return m, load_epoch_images(m, m.epochs[0])


def area_bench(repeat: int = 1, fractions=(0.25, 0.5, 1.0)) -> dict:
    """The pair on centred sub-grids of the whole overlap (the CLI's default AOI): work per cell vs area."""
    from geocd.stereo import match_pair
    from geocd.stereo.scene import default_aoi_grid, read_chip

    m, ims = _overlap_images()
    t = time.perf_counter()
    full = default_aoi_grid(m, {"pair": ims})
    t_aoi = time.perf_counter() - t
    H, W = full.shape
    out = {"aoi_s": t_aoi, "full_grid": f"{W}x{H} at {full.posting_m} m", "areas": []}
    for frac in fractions:
        h, w = int(round(H * np.sqrt(frac))), int(round(W * np.sqrt(frac)))
        g = full.subgrid((H - h) // 2, (W - w) // 2, h, w)
        chips = [read_chip(im.path, im.camera, g, 2200.0, 2450.0, name=im.name, margin_px=40) for im in ims]
        pd, wall, cpu = best_of(lambda: match_pair(chips[0], chips[1], ims[0].camera, ims[1].camera, g), repeat)
        cells = g.width * g.height
        out["areas"].append(
            {
                "fraction": frac,
                "grid": f"{g.width}x{g.height}",
                "cells": cells,
                "wall_s": wall,
                "cpu_s": cpu,
                "evaluations": pd.meta["evaluations"],
                "evaluations_per_cell": pd.meta["evaluations"] / cells,
                "wall_us_per_cell": 1e6 * wall / cells,
                "cpu_us_per_cell": 1e6 * cpu / cells,
                "valid": float(pd.valid.mean()),
                "levels": pd.meta["levels"],
                "coarse_interval_m": pd.meta.get("coarse_interval_m"),
            }
        )
    return out


def cold_warm(cmd: list[str], cache: Path, cwd: Path | None = None, prepare=None) -> dict:
    """The command with an empty numba cache (cold), then again with the cache it filled (warm)."""
    env = geocd_env(cache)
    res = {}
    for label in ("cold", "warm"):
        if prepare is not None:
            prepare()
        res[label] = run_process(cmd, env=env, cwd=cwd)
    res["cold_over_warm_wall"] = res["cold"]["wall_s"] / res["warm"]["wall_s"]
    res["cold_over_warm_cpu"] = res["cold"]["cpu_s"] / max(res["warm"]["cpu_s"], 1e-9)
    return res


def compare_to_s2p(z: np.ndarray, z_grid, ref: np.ndarray, ref_grid) -> dict:
    """A DSM (NaN = no height) against s2p's DSM on s2p's grid (nearest neighbour: no filling)."""
    from geocd.io.raster import reproject_array

    zz = reproject_array(np.asarray(z, np.float32), z_grid, ref_grid, "nearest").astype(np.float64)
    have = np.isfinite(ref)
    both = have & np.isfinite(zz)
    d = (zz - ref)[both]
    off = float(np.median(d))
    e = d - off
    return {
        "offset_m": off,
        "nmad_m": float(1.4826 * np.median(np.abs(e - np.median(e)))),
        "median_abs_m": float(np.median(np.abs(e))),
        "within_1m": float(np.mean(np.abs(e) < 1.0)),
        "completeness_on_s2p": float(both.sum() / have.sum()),
        "cells_compared": int(both.sum()),
    }


def cars_config(
    work: Path,
    h: float,
    images: tuple[Path, Path] | None = None,
    corner_lonlat: tuple[float, float] = (55.6, -21.2),
    epsg: int = 32740,
    resolution_m: float = 0.5,
) -> Path:
    """CARS's config for one pair in ``work`` (default: the Réunion pair): a flat initial elevation ``h`` (m) on a
    0.2° square whose north-west corner is ``corner_lonlat`` (CARS needs a DEM and has none here), the output
    posting and CRS, ellipsoidal heights (``geoid: false``), multiprocessing with 2 workers."""
    import rasterio
    from rasterio.transform import from_origin

    images = images or tuple(DATA / p for p in PAIR_IMAGES)
    dem = work / "flat_dem.tif"
    with rasterio.open(
        dem,
        "w",
        driver="GTiff",
        width=40,
        height=40,
        count=1,
        dtype="float32",
        crs="EPSG:4326",
        transform=from_origin(*corner_lonlat, 0.005, 0.005),
    ) as ds:
        ds.write(np.full((1, 40, 40), h, np.float32))
    cfg = {
        "input": {
            "sensors": {n: {"image": str(p), "geomodel": str(p)} for n, p in zip(("left", "right"), images)},
            "pairing": [["left", "right"]],
            "initial_elevation": {"dem": str(dem)},
        },
        "output": {"directory": str(work / "out"), "resolution": resolution_m, "epsg": epsg, "geoid": False},
        "orchestrator": {"mode": "multiprocessing", "nb_workers": 2},
    }
    (work / "config.json").write_text(json.dumps(cfg, indent=1))
    return work / "config.json"


PAIR_IMAGES = ("input_pair/img_01.tif", "input_pair/img_02.tif")


def pair_manifest(work: Path) -> Path:
    """A manifest of the Réunion pair (one epoch, both images; default AOI: the whole overlap) under ``work``."""
    man = work / "pair.yaml"
    man.write_text(
        json.dumps(
            {
                "geocd_manifest": 1,
                "name": "reunion_pair",
                "epochs": [{"name": "pair", "images": [str(DATA / p) for p in PAIR_IMAGES]}],
            }
        )
    )
    return man


def stereo_command(man: Path, out: Path) -> list[str]:
    """``geocd stereo MANIFEST --out OUT``."""
    return [*geocd_command(), "stereo", str(man), "--out", str(out)]


def stereo_accuracy(out: Path, ref: np.ndarray, ref_grid) -> dict:
    """geocd's pair-DEM under ``out`` against s2p's DSM: valid cells, and the z band as written (valid + filled)."""
    pd = read_pair_dem(out / "stereo" / "pair" / "img_01__img_02.tif")
    return {
        "grid": f"{pd.grid.width}x{pd.grid.height} at {pd.grid.posting_m} m",
        "vs_s2p": compare_to_s2p(np.where(pd.valid, pd.z_m, np.nan), pd.grid, ref, ref_grid),
        # the z band as written: valid heights + those interpolated in narrow holes (flag `filled`), what
        # compares with CARS's filled dsm/dsm.tif
        "vs_s2p_with_filled": compare_to_s2p(pd.z_m, pd.grid, ref, ref_grid),
        "filled_cells": int(np.count_nonzero(pd.flags & FLAGS["filled"])),
    }


def run_cars(cars: str, cw: Path, ref: np.ndarray, ref_grid) -> dict:
    """CARS's whole process on the pair in the new folder ``cw`` and its final ``dsm/dsm.tif`` against s2p's."""
    cw.mkdir(parents=True)
    cfg = cars_config(cw, float(np.nanmedian(ref)))
    c = run_process([cars, str(cfg)], cwd=cw)
    c["command"] = [cars, str(cfg)]
    final = cw / "out" / "dsm" / "dsm.tif"
    c["dsm"] = "out/dsm/dsm.tif"
    if c["returncode"] == 0 and final.is_file():
        with rasterio.open(final) as ds:
            g = AOIGrid.from_raster(ds)
            a = ds.read(1, masked=True).astype(np.float64).filled(np.nan)
        c["dsm_grid"] = f"{g.width}x{g.height} at {g.posting_m:g} m"
        c["vs_s2p"] = compare_to_s2p(a, g, ref, ref_grid)
    else:
        c["error_tail"] = c.get("error_tail", "") or f"no {final}"
    return c


def whole_process_bench(ref: np.ndarray, ref_grid, cars: str | None, skip_run: bool = False) -> dict:
    """geocd's CLI (cold and warm) and CARS, each a whole process, and their final DSMs vs s2p's."""
    work = Path(tempfile.mkdtemp(prefix="geocd_bench_"))
    res: dict = {}
    try:
        res["info"] = cold_warm([*geocd_command(), "info", str(DATA / PAIR_IMAGES[0])], work / "cache_info")
        out = work / "st"
        res["stereo"] = cold_warm(stereo_command(pair_manifest(work), out), work / "cache_stereo")
        res["stereo"].update(stereo_accuracy(out, ref, ref_grid))
        if not skip_run:
            res["run_sample_aoi"] = cold_warm(
                [*geocd_command(), "run", str(REPO / "sample_aoi"), "--out", str(work / "run")],
                work / "cache_run",
                prepare=lambda: shutil.rmtree(work / "run", ignore_errors=True),
            )
        if cars:
            res["cars"] = run_cars(cars, work / "cars", ref, ref_grid)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return res


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--crop", type=int, default=160)
    ap.add_argument("--planes", type=int, default=48)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--cars", default=None, help="path of a `cars` executable (its own venv); needs --whole")
    ap.add_argument("--whole", action="store_true", help="also the whole-process cold/warm comparisons")
    ap.add_argument("--skip-run", action="store_true", help="with --whole: leave out geocd run sample_aoi")
    ap.add_argument("--json", type=Path, default=None, help="also write the figures here")
    args = ap.parse_args(argv)
    if not DATA.is_dir():
        print(f"{DATA} not found (needs ../shared/data)", file=sys.stderr)
        return 2
    import numba

    res: dict = {
        "numba_threads": numba.get_num_threads(),
        "cpu_count": os.cpu_count(),
        "loadavg_start": os.getloadavg(),
    }
    grid, ref, cams, chips = load_pair()
    k = kernel_bench(grid, ref, cams, chips, args.crop, args.planes, args.repeat)
    res["kernel"] = k
    print(f"kernel: {k['crop_cells']} cells x {k['planes']} planes, window {k['window']}")
    base = k["seconds"]["numpy box filters"]
    for name, s in k["seconds"].items():
        print(
            f"  {name:40s} {s * 1e3:9.1f} ms  {k['evals_per_s'][name] / 1e6:8.2f} M evals/s  "
            f"x{base / s:6.2f} vs numpy box filters"
        )
    print(f"  agreement: {k['agreement']}")
    p = pair_bench(grid, ref, cams, chips, args.repeat)
    res["pair"] = p
    print(
        f"pair (s2p img_01/img_02, {p['grid']}, RPC height range, {p['levels']} levels; in process, warm): wall {p['wall_s']:.1f} s "
        f"(best of {args.repeat}), "
        f"cpu {p['cpu_s']:.1f} s, {p['evaluations'] / 1e6:.1f} M evaluations, "
        f"{p['evals_per_s_wall'] / 1e6:.2f} M evals/s; completeness {p['completeness']:.1%}, "
        f"median |dz| vs s2p {p['median_abs_dz_vs_s2p_m']:.2f} m, NMAD {p['nmad_vs_s2p_m']:.3f} m"
    )
    ab = area_bench(repeat=args.repeat)
    res["area"] = ab
    print(
        f"time vs area (whole overlap {ab['full_grid']}, centred sub-grids, in process, warm, best of {args.repeat}):"
    )
    for r in ab["areas"]:
        print(
            f"  {r['fraction']:>5.2f} of it: {r['grid']:>9s} cells  wall {r['wall_s']:6.1f} s  cpu {r['cpu_s']:6.1f} s  "
            f"{r['evaluations'] / 1e6:7.1f} M evals = {r['evaluations_per_cell']:5.0f} per cell, "
            f"{r['cpu_us_per_cell']:5.1f} µs CPU per cell, {r['valid']:.1%} valid"
        )
    if args.whole:
        w = whole_process_bench(ref, grid, args.cars, skip_run=args.skip_run)
        res["whole_process"] = w
        for key, label in (
            ("info", "geocd info img_01.tif"),
            ("stereo", "geocd stereo (Réunion pair, whole overlap)"),
            ("run_sample_aoi", "geocd run sample_aoi"),
        ):
            if key not in w:
                continue
            c, h = w[key]["cold"], w[key]["warm"]
            print(
                f"{label}: cold {c['wall_s']:.1f} s wall / {c['cpu_s']:.1f} s CPU, warm {h['wall_s']:.1f} s wall / "
                f"{h['cpu_s']:.1f} s CPU (cold/warm x{w[key]['cold_over_warm_wall']:.2f} wall, "
                f"x{w[key]['cold_over_warm_cpu']:.2f} CPU)"
                + (
                    ""
                    if c["returncode"] == 0 and h["returncode"] == 0
                    else f"  FAILED: {c.get('error_tail', h.get('error_tail'))}"
                )
            )
        v = w["stereo"]["vs_s2p"]
        print(
            f"  geocd pair-DEM vs s2p on s2p's grid, valid cells: NMAD {v['nmad_m']:.3f} m, within 1 m "
            f"{v['within_1m']:.1%}, completeness {v['completeness_on_s2p']:.1%}"
        )
        v = w["stereo"]["vs_s2p_with_filled"]
        print(
            f"  ... valid + filled cells (z band as written; {w['stereo']['filled_cells']} filled): NMAD "
            f"{v['nmad_m']:.3f} m, within 1 m {v['within_1m']:.1%}, completeness {v['completeness_on_s2p']:.1%}"
        )
        if "cars" in w:
            c = w["cars"]
            if "vs_s2p" in c:
                v = c["vs_s2p"]
                st = w["stereo"]
                print(
                    f"CARS (whole process, same run): wall {c['wall_s']:.1f} s, CPU {c['cpu_s']:.1f} s; final "
                    f"{c['dsm']} ({c['dsm_grid']}) vs s2p: NMAD {v['nmad_m']:.3f} m, within 1 m {v['within_1m']:.1%}, "
                    f"completeness {v['completeness_on_s2p']:.1%}"
                )
                for lab in ("cold", "warm"):
                    print(
                        f"  CARS / geocd stereo {lab}: x{c['wall_s'] / st[lab]['wall_s']:.1f} wall, "
                        f"x{c['cpu_s'] / st[lab]['cpu_s']:.1f} CPU"
                    )
            else:
                print(f"CARS failed (rc {c['returncode']}): {c.get('error_tail', '')[-600:]}")
    res["loadavg_end"] = os.getloadavg()
    print(f"load average start {res['loadavg_start']}, end {res['loadavg_end']} (2 cores shared)")
    if args.json:
        args.json.write_text(json.dumps(res, indent=1, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
