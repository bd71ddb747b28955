"""Stereo matching tile by tile on the AOI grid (:mod:`geocd.tiling`): whole scenes with bounded memory.

:func:`run_stereo_tiled` does what :func:`geocd.stereo.pipeline.run_stereo` does — every image pair
of each epoch matched in object space, one pair-DEM per pair — but :func:`~geocd.stereo.match.match_pair`
runs on AOI windows: each tile reads the image windows its cells can project to (between the
lowest and highest searched height) and matches its window grown by a **margin** that covers
what a cell's result depends on beyond its own column:

* the matching window at the coarsest level of the coarse-to-fine search
  (``radius × 2^levels`` cells: a coarse cell averages ``2^levels`` fine ones);
* the occlusion check's reach: a surface up to the height range ``hi − lo`` above a cell hides
  cells up to ``(hi − lo) × tan(view angle)`` away (from the cameras' image motion per metre of
  height and their ground sampling).

Each tile keeps its core; the writer assembles the pair-DEM COG (the bands and tags of
:func:`~geocd.stereo.products.write_pair_dem`). What differs from an untiled match, by design:
the pointing correction and the noise level are estimated on each tile's window (a whole-scene
pair can drift along its length, so this follows it), and the coarse levels' cell blocks start at
the tile's corner. docs/tiling.md measures the difference on sample_aoi.
"""

from __future__ import annotations

import itertools
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from ..errors import ConfigError
from ..geodesy import AOIGrid
from ..progress import Progress, ensure_progress, sub_progress
from ..tiling import RasterProduct, RasterSource, TileGrid, TileOutput, open_engine, remove_work, run_tiled
from ..tiling.writer import write_product
from .params import StereoParams


@dataclass(frozen=True)
class _PairJob:
    epoch: str
    a: Any          # EpochImage
    b: Any
    params: StereoParams
    dem_datum: str | None

    def cache_key(self) -> dict:
        import os

        def ident(p):
            st = os.stat(p)
            return [str(p), st.st_size, st.st_mtime_ns]

        return {"epoch": self.epoch, "a": [self.a.name, ident(self.a.path), repr(self.a.camera)],
                "b": [self.b.name, ident(self.b.path), repr(self.b.camera)], "params": self.params.to_dict(),
                "datum": self.dem_datum}


def stereo_margin_cells(grid: AOIGrid, cams: Sequence, lo_m: float, hi_m: float, params: StereoParams) -> int:
    """The overlap a stereo tile needs (see module docstring), in cells of ``grid``."""
    from .sweep import image_sampling_px_per_m

    rows = np.array([grid.height // 2])
    cols = np.array([grid.width // 2])
    mid = 0.5 * (lo_m + hi_m)
    x, y = grid.xy(rows, cols)
    reach = 0.0
    jmax = 0.0
    for cam in cams:
        pr = cam.ground_projector(np.array([x[0], x[0]]), np.array([y[0], y[0]]), grid.crs)
        c, r = pr.project(np.array([lo_m, hi_m]))
        px_per_m_height = math.hypot(c[1] - c[0], r[1] - r[0]) / max(hi_m - lo_m, 1e-6)
        px_per_m_ground = float(image_sampling_px_per_m(cam, grid, rows, cols, mid)[0])
        if np.isfinite(px_per_m_height) and px_per_m_ground > 0:
            reach = max(reach, (hi_m - lo_m) * px_per_m_height / px_per_m_ground)
            jmax = max(jmax, px_per_m_height)
    # levels of the coarse-to-fine search (as match_pair chooses them); the coarsest averages 2^L cells
    k0 = (hi_m - lo_m) * jmax / max(params.max_step_px, 1e-9)
    levels = int(math.ceil(math.log2(k0 / params.max_heights))) if k0 > params.max_heights else 0
    if params.pointing_correction:
        levels = max(levels, 2)
    return int(math.ceil(reach / grid.posting_m)) + int(params.radius * 2 ** levels) + 2


def _t_pair(arrays, ctx):
    """Match one pair on a tile's window; keep the core."""
    from ..io.raster import DEM
    from .match import height_bounds, match_pair
    from .pipeline import read_chip

    J: _PairJob = ctx.params
    p = J.params
    sub = ctx.read_grid
    dem = None
    if "dem" in arrays:
        dem = DEM(arrays["dem"], sub, J.dem_datum).to_ellipsoidal().height_m.astype(np.float32)
        if not np.isfinite(dem).any():
            dem = None
    cams = [J.a.camera, J.b.camera]
    lo, hi, _ = height_bounds(sub, cams, dem, p)
    lo_m, hi_m = float(np.min(lo)), float(np.max(hi))
    chips = [read_chip(im.path, im.camera, sub, lo_m, hi_m, name=im.name, margin_px=16 + 2 * p.window,
                       block_px=p.norm_block_px) for im in (J.a, J.b)]
    pd = match_pair(chips[0], chips[1], cams[0], cams[1], sub, dem=dem, params=p, epoch=J.epoch,
                    name=f"{J.a.name}__{J.b.name}")
    f32 = np.float32
    arr = {"z": pd.z_m.astype(f32), "score": pd.score.astype(f32), "g": pd.g_px_per_m.astype(f32),
           "valid": np.asarray(pd.valid, f32), "ncc": pd.ncc.astype(f32), "ssd": pd.ssd.astype(f32),
           "flags": np.asarray(pd.flags, f32)}
    core = ctx.core
    return TileOutput(arrays=arr, small={"meta": pd.meta, "valid": int(np.count_nonzero(pd.valid[core])),
                                         "cells": int(pd.valid[core].size)})


def run_stereo_tiled(manifest, *, out_dir, epochs: Sequence[str] | None = None, params: StereoParams = StereoParams(),
                     grid: AOIGrid | None = None, posting_m: float | None = None, pairs: str = "all", tiling=None,
                     progress: Progress | None = None) -> dict[str, Any]:
    """:func:`geocd.stereo.pipeline.run_stereo` tile by tile (see module docstring).

    Returns dict with ``outputs`` ({"<epoch>/<a>__<b>": path}), ``grid``, ``margins`` (cells per pair)
    and ``completeness`` per pair.
    """
    from ..demdiff.tiled import TilingParams
    from ..io.manifest import Manifest, load_manifest
    from ..io.raster import read_dem
    from .match import height_bounds
    from .pipeline import default_aoi_grid, load_epoch_images, pair_path
    from .products import BANDS, SCORE_DEFINITION, FLAGS

    tiling = tiling or TilingParams()
    prog = ensure_progress(progress)
    m = manifest if isinstance(manifest, Manifest) else load_manifest(manifest)
    selected = [m.epoch(e) for e in epochs] if epochs else [e for e in m.epochs if len(e.images) >= 2]
    if not selected:
        raise ConfigError("no epoch of the manifest has two images or more, so there is no stereo pair to match")
    out = Path(out_dir)
    images = {e.name: load_epoch_images(m, e) for e in selected}
    dem_median = None
    if grid is None and m.dem is not None:
        d0 = read_dem(m.dem.path, vertical_datum=m.dem.vertical_datum).to_ellipsoidal()
        dem_median = float(np.nanmedian(d0.height_m))
    if grid is None:
        grid = default_aoi_grid(m, images, posting_m=posting_m, dem_median=dem_median, params=params)
    todo = [(e, a, b) for e in selected for a, b in itertools.combinations(images[e.name], 2)
            if pairs == "all" or a.camera.kind == b.camera.kind]
    if not todo:
        raise ConfigError("no image pair left to match")
    inputs = {}
    datum = None
    if m.dem is not None:
        inputs["dem"] = RasterSource(str(m.dem.path), dem=True, resampling="bilinear")
        datum = m.dem.vertical_datum
    outputs: dict[str, Path] = {}
    margins: dict[str, int] = {}
    complete: dict[str, float] = {}
    units = {"z": "m (WGS84 ellipsoidal)", "score": f"{params.score} (lower = better)", "g": "px/m",
             "valid": "1 valid, 0 invalid", "ncc": "1", "ssd": "DN^2 (normalized 8-bit)", "flags": json.dumps(FLAGS)}
    with open_engine(tiling.scheduler, n_workers=tiling.n_workers, memory_limit=tiling.memory_limit) as eng:
        for i, (e, a, b) in enumerate(todo):
            key = f"{e.name}/{a.name}__{b.name}"
            lo, hi, _ = height_bounds(grid.subgrid(0, 0, min(grid.height, 64), min(grid.width, 64)),
                                      [a.camera, b.camera], None, params) if m.dem is None else (None, None, None)
            if lo is None:
                d = read_dem(m.dem.path, vertical_datum=m.dem.vertical_datum).to_ellipsoidal().height_m
                lo_m = float(np.nanmin(d)) - params.dem_margin_m
                hi_m = float(np.nanmax(d)) + params.dem_margin_m
            else:
                lo_m, hi_m = float(np.min(lo)), float(np.max(hi))
            ov = min(stereo_margin_cells(grid, [a.camera, b.camera], lo_m, hi_m, params), tiling.tile_size // 2)
            margins[key] = ov
            job = _PairJob(e.name, a, b, params, datum)
            tg = TileGrid(grid, (tiling.tile_size, tiling.tile_size), ov)
            r = run_tiled(_t_pair, tg, inputs, params=job, out=out, stage=f"stereo-{e.name}-{a.name}__{b.name}",
                          scheduler=eng, progress=sub_progress(prog, i / len(todo), (i + 1) / len(todo),
                                                                f"pair {i + 1}/{len(todo)} "))
            smalls = [s for _, s in r.smalls()]
            meta = dict(smalls[0]["meta"]) if smalls else {}
            meta["tiled"] = {"tile_size": tiling.tile_size, "margin_cells": ov, "tiles": len(smalls),
                             "pointing_per_tile": [s["meta"].get("pointing", {}).get("total_shift_px")
                                                   for s in smalls]}
            complete[key] = sum(s["valid"] for s in smalls) / max(sum(s["cells"] for s in smalls), 1)
            tags = {"geocd_product": "stereo_pair", "pair": f"{a.name}__{b.name}",
                    "cameras": json.dumps([a.name, b.name]), "epoch": e.name, "score_definition": SCORE_DEFINITION,
                    "vertical_datum": "ellipsoid", "meta": json.dumps(meta, default=_json_default),
                    "images": json.dumps([str(a.path), str(b.path)]), "manifest": str(m.path or "")}
            prod = RasterProduct(str(pair_path(out, e.name, a.name, b.name)), tuple(BANDS), tags=tags,
                                 band_tags=[{"units": units[bn]} for bn in BANDS])
            outputs[key] = write_product(r.store, prod, grid, tg)
    if not tiling.keep_work:
        remove_work(out)
    prog(1.0, "stereo done")
    return {"outputs": outputs, "grid": grid, "margins": margins, "completeness": complete}


def _json_default(o: Any):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    return str(o)
