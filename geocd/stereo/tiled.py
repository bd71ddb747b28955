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
:func:`~geocd.stereo.products.write_pair_dem`). Once a pair's DEM is written its tiles are deleted (unless
``keep_work``) and the pair is journalled in the work folder; a resumed run finds the DEM carrying the
pair's key (:data:`RESUME_TAG`) and does not match that pair again, so the scratch disk holds one pair's
tiles at a time. The pair's relative pointing correction and image
noise level are whole-scene choices: they are estimated once per pair on a central window (at most
one tile) and given to every tile. What differs from an untiled match: the image normalisation
blocks and the coarse levels' cell blocks start at the tile's corner, and a pair whose pointing
drifts along a long scene gets one correction. docs/tiling.md measures the difference on sample_aoi.
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
from ..tiling import (
    WORK_DIR,
    RasterProduct,
    RasterSource,
    TileGrid,
    TileOutput,
    make_key,
    open_engine,
    remove_work,
    run_tiled,
)
from ..tiling.writer import check_assembly_room, write_product
from .params import StereoParams


@dataclass(frozen=True)
class _PairJob:
    epoch: str
    a: Any  # EpochImage
    b: Any
    params: StereoParams
    dem_datum: str | None
    pointing_px: tuple[float, float] = (0.0, 0.0)  # the pair's relative pointing correction (image b)

    def cache_key(self) -> dict:
        import os

        def ident(p):
            st = os.stat(p)
            return [str(p), st.st_size, st.st_mtime_ns]

        return {
            "epoch": self.epoch,
            "a": [self.a.name, ident(self.a.path), repr(self.a.camera)],
            "b": [self.b.name, ident(self.b.path), repr(self.b.camera)],
            "params": self.params.to_dict(),
            "datum": self.dem_datum,
            "pointing": list(self.pointing_px),
        }


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
    levels = _coarse_levels(jmax, lo_m, hi_m, params)
    return int(math.ceil(reach / grid.posting_m)) + int(params.radius * 2**levels) + 2


def _coarse_levels(jmax_px_per_m: float, lo_m: float, hi_m: float, params: StereoParams) -> int:
    """Coarser levels of the coarse-to-fine search a large enough window gets (as match_pair chooses them)."""
    k0 = (hi_m - lo_m) * jmax_px_per_m / max(params.max_step_px, 1e-9)
    levels = int(math.ceil(math.log2(k0 / params.max_heights))) if k0 > params.max_heights else 0
    if params.pointing_correction:
        levels = max(levels, 2)
    return levels


def stereo_window_needs(manifest, grid: AOIGrid, a, b, params: StereoParams) -> tuple[int, int]:
    """(margin cells, smallest window side in cells that keeps every coarse level) for one pair on ``grid``.

    match_pair adds a coarser level only while the window's shorter side holds ``4 · window`` cells at
    that level, so a window narrower than ``4 · window · 2^L`` (L: the levels the height range asks for)
    searches its coarsest level over more heights at a finer posting. Measured on Kahramanmaraş
    (pre-event pair, 128-cell tiles): its refined levels then searched 3–4× more heights per cell (66–93
    against 21 on the whole grid) and its sweep took 3.4× the untiled one on 95 % of the cells. A tiered
    run sizes its windows from this side.
    """
    lo_m, hi_m = _pair_height_range(manifest, grid, a, b, params)
    margin = stereo_margin_cells(grid, [a.camera, b.camera], lo_m, hi_m, params)
    x, y = grid.xy(np.array([grid.height // 2]), np.array([grid.width // 2]))
    jmax = 0.0
    for cam in (a.camera, b.camera):
        pr = cam.ground_projector(np.array([x[0], x[0]]), np.array([y[0], y[0]]), grid.crs)
        c, r = pr.project(np.array([lo_m, hi_m]))
        v = math.hypot(c[1] - c[0], r[1] - r[0]) / max(hi_m - lo_m, 1e-6)
        if np.isfinite(v):
            jmax = max(jmax, v)
    return margin, int(4 * params.window * 2 ** _coarse_levels(jmax, lo_m, hi_m, params))


def _pair_height_range(m, grid: AOIGrid, a, b, params: StereoParams) -> tuple[float, float]:
    """The searched height range of a pair (m): the manifest DEM's ± the DEM margin, else the cameras' bounds."""
    from ..io.raster import read_dem
    from .match import height_bounds

    if m.dem is not None:
        d = read_dem(m.dem.path, vertical_datum=m.dem.vertical_datum).to_ellipsoidal().height_m
        return float(np.nanmin(d)) - params.dem_margin_m, float(np.nanmax(d)) + params.dem_margin_m
    lo, hi, _ = height_bounds(
        grid.subgrid(0, 0, min(grid.height, 64), min(grid.width, 64)), [a.camera, b.camera], None, params
    )
    return float(np.min(lo)), float(np.max(hi))


def _t_pair(arrays, ctx):
    """Match one pair on a tile's window; keep the core. A window one image does not see: every cell
    invalid, flagged ``out_of_image`` (as the untiled match flags the cells outside an image)."""
    from ..errors import NoOverlapError
    from .products import FLAGS

    J: _PairJob = ctx.params
    f32 = np.float32
    try:
        pd = _match_window(J, ctx.read_grid, arrays.get("dem"))
    except NoOverlapError:
        shape = ctx.read_grid.shape
        nan = np.full(shape, np.nan, f32)
        arr = {
            "z": nan,
            "score": nan,
            "g": nan,
            "valid": np.zeros(shape, f32),
            "ncc": nan,
            "ssd": nan,
            "flags": np.full(shape, FLAGS["out_of_image"], f32),
        }
        return TileOutput(arrays=arr, small={"meta": None, "valid": 0, "cells": int(nan[ctx.core].size)})
    arr = {
        "z": pd.z_m.astype(f32),
        "score": pd.score.astype(f32),
        "g": pd.g_px_per_m.astype(f32),
        "valid": np.asarray(pd.valid, f32),
        "ncc": pd.ncc.astype(f32),
        "ssd": pd.ssd.astype(f32),
        "flags": np.asarray(pd.flags, f32),
    }
    core = ctx.core
    return TileOutput(
        arrays=arr,
        small={"meta": pd.meta, "valid": int(np.count_nonzero(pd.valid[core])), "cells": int(pd.valid[core].size)},
    )


def _match_window(J: "_PairJob", sub: AOIGrid, dem_window: np.ndarray | None):
    """match_pair on a window of the AOI grid, with the pair's pointing correction given (not re-estimated)."""
    from ..io.raster import DEM
    from .match import height_bounds, match_pair
    from .pipeline import read_chip

    p = J.params
    dem = None
    arrays = {} if dem_window is None else {"dem": dem_window}
    if "dem" in arrays:
        dem = DEM(arrays["dem"], sub, J.dem_datum).to_ellipsoidal().height_m.astype(np.float32)
        if not np.isfinite(dem).any():
            dem = None
    cams = [J.a.camera, J.b.camera]
    lo, hi, _ = height_bounds(sub, cams, dem, p)
    lo_m, hi_m = float(np.min(lo)), float(np.max(hi))
    chips = [
        read_chip(
            im.path, im.camera, sub, lo_m, hi_m, name=im.name, margin_px=16 + 2 * p.window, block_px=p.norm_block_px
        )
        for im in (J.a, J.b)
    ]
    if J.pointing_px != (0.0, 0.0):
        chips[1] = chips[1].shifted(*J.pointing_px)
    return match_pair(
        chips[0], chips[1], cams[0], cams[1], sub, dem=dem, params=p, epoch=J.epoch, name=f"{J.a.name}__{J.b.name}"
    )


def _pair_job(epoch: str, a, b, params: StereoParams, datum, grid: AOIGrid, tiling, dem_src) -> _PairJob:
    """The pair's whole-scene choices, made once on a central window (at most a tile) and given to every
    tile: the relative pointing correction and the image noise level. Tiles estimate neither (a small
    window's pointing estimate is noisy: on sample_aoi 256-cell tiles applied 0.34 px where the whole
    scene's estimate is below the 0.25 px floor)."""
    import dataclasses

    side = min(tiling.tile_size, grid.height, grid.width)
    r0 = (grid.height - min(side, grid.height)) // 2
    c0 = (grid.width - min(side, grid.width)) // 2
    h, w = min(side, grid.height), min(side, grid.width)
    sub = grid.subgrid(r0, c0, h, w)
    dem_w = dem_src.read(grid, (r0, c0, h, w)) if dem_src is not None else None
    from ..errors import NoOverlapError

    try:
        probe = _match_window(_PairJob(epoch, a, b, params, datum), sub, dem_w)
    except NoOverlapError:  # an image that does not see the centre: no pointing correction, noise per tile
        return _PairJob(epoch, a, b, dataclasses.replace(params, min_pointing_px=1e9), datum, (0.0, 0.0))
    pt = probe.meta.get("pointing") or {}
    shift = tuple(float(v) for v in pt.get("total_shift_px", (0.0, 0.0))) if pt.get("applied") else (0.0, 0.0)
    # the tiles match with that shift and that noise level, and estimate no pointing of their own
    p = dataclasses.replace(
        params, noise_sigma=params.noise_sigma or float(probe.meta["noise_sigma"]), min_pointing_px=1e9
    )
    return _PairJob(epoch, a, b, p, datum, shift)


def run_stereo_tiled(
    manifest,
    *,
    out_dir,
    epochs: Sequence[str] | None = None,
    params: StereoParams = StereoParams(),
    grid: AOIGrid | None = None,
    posting_m: float | None = None,
    pairs: str = "all",
    tiling=None,
    tiles: np.ndarray | None = None,
    progress: Progress | None = None,
) -> dict[str, Any]:
    """:func:`geocd.stereo.pipeline.run_stereo` tile by tile (see module docstring).

    ``tiles`` (bool (tile rows, tile cols) of the ``tiling.tile_size`` tiling, optional) matches only
    those tiles (the tiered run's flagged tiles), each with the same declared margin and the pair's
    whole-scene pointing correction and noise level; neighbouring selected tiles of a tile row are
    matched as one window (their shared edges need no margin); the cells of the other tiles are
    written as not matched (z NaN, valid 0, flags :data:`~geocd.stereo.products.FLAGS_NOT_EXAMINED` = 255).

    Returns dict with ``outputs`` ({"<epoch>/<a>__<b>": path}), ``grid``, ``margins`` (cells per pair)
    and ``completeness`` per pair (over the matched tiles).
    """
    from ..tiling.params import TilingParams
    from ..io.manifest import Manifest, load_manifest
    from ..io.raster import read_dem
    from .pipeline import default_aoi_grid, load_epoch_images, pair_path
    from .products import BANDS, FLAGS, FLAGS_NOT_EXAMINED, SCORE_DEFINITION

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
    todo = [
        (e, a, b)
        for e in selected
        for a, b in itertools.combinations(images[e.name], 2)
        if pairs == "all" or a.camera.kind == b.camera.kind
    ]
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
    units = {
        "z": "m (WGS84 ellipsoidal)",
        "score": f"{params.score} (lower = better)",
        "g": "px/m",
        "valid": "1 valid, 0 invalid",
        "ncc": "1",
        "ssd": "DN^2 (normalized 8-bit)",
        "flags": json.dumps(FLAGS),
    }
    with open_engine(tiling.scheduler, n_workers=tiling.n_workers, memory_limit=tiling.memory_limit) as eng:
        for i, (e, a, b) in enumerate(todo):
            key = f"{e.name}/{a.name}__{b.name}"
            lo_m, hi_m = _pair_height_range(m, grid, a, b, params)
            ov = min(stereo_margin_cells(grid, [a.camera, b.camera], lo_m, hi_m, params), tiling.tile_size // 2)
            margins[key] = ov
            target = pair_path(out, e.name, a.name, b.name)
            pair_key = make_key(
                "stereo-pair",
                _PairJob(e.name, a, b, params, datum),
                grid.to_dict(),
                tiling.tile_size,
                ov,
                None if tiles is None else np.asarray(tiles, bool),
                {k: s.identity() for k, s in inputs.items()},
            )
            done = _finished_pair(out, target, pair_key)
            if done is not None:  # a resumed run: this pair's DEM was written and its tiles removed
                outputs[key], complete[key] = target, done
                prog((i + 1) / len(todo), f"pair {i + 1}/{len(todo)} resumed: {target.name} is written")
                continue
            # its DEM is assembled after its tiles: refuse now, not after an hour of matching
            check_assembly_room(RasterProduct(str(target), tuple(BANDS)), grid.shape, out / WORK_DIR, target)
            job = _pair_job(e.name, a, b, params, datum, grid, tiling, inputs.get("dem"))
            # a selection: runs of neighbouring selected tiles along a tile row are matched as one window
            tg = TileGrid(grid, (tiling.tile_size, tiling.tile_size), ov, tiles, merge_runs=tiles is not None)
            r = run_tiled(
                _t_pair,
                tg,
                inputs,
                params=job,
                out=out,
                stage=f"stereo-{e.name}-{a.name}__{b.name}",
                scheduler=eng,
                progress=sub_progress(prog, i / len(todo), (i + 1) / len(todo), f"pair {i + 1}/{len(todo)} "),
            )
            smalls = [s for _, s in r.smalls()]
            metas = [s["meta"] for s in smalls if s["meta"] is not None]
            meta = dict(metas[0]) if metas else {}
            meta["pointing"] = {
                "applied": job.pointing_px != (0.0, 0.0),
                "total_shift_px": list(job.pointing_px),
                "estimated_on": "central window",
            }
            meta["noise_sigma"] = job.params.noise_sigma
            meta["tiled"] = {
                "tile_size": tiling.tile_size,
                "margin_cells": ov,
                "units": len(smalls),
                "tiles": int(tg.selection_mask().sum()),
                "tiles_in_grid": len(list(tg.all_tiles())),
            }
            complete[key] = sum(s["valid"] for s in smalls) / max(sum(s["cells"] for s in smalls), 1)
            tags = {
                "geocd_product": "stereo_pair",
                "pair": f"{a.name}__{b.name}",
                "cameras": json.dumps([a.name, b.name]),
                "epoch": e.name,
                "score_definition": SCORE_DEFINITION,
                "vertical_datum": "ellipsoid",
                "meta": json.dumps(meta, default=_json_default),
                "images": json.dumps([str(a.path), str(b.path)]),
                "manifest": str(m.path or ""),
                RESUME_TAG: json.dumps({"key": pair_key, "completeness": complete[key]}),
            }
            prod = RasterProduct(
                str(target),
                tuple(BANDS),
                tags=tags,
                band_tags=[{"units": units[bn]} for bn in BANDS],
                fill={"valid": 0.0, "flags": float(FLAGS_NOT_EXAMINED)},
            )
            outputs[key] = write_product(r.store, prod, grid, tg)
            if not tiling.keep_work:
                # the pair's DEM holds everything later stages read: its tiles go now, not at the stage's end
                # (at 20 000² cells one pair's tiles are ~11 GB); the journal says the pair is finished
                _journal_pair(out, pair_key)
                r.store.remove()
    if not tiling.keep_work:
        remove_work(out)
    prog(1.0, "stereo done")
    return {"outputs": outputs, "grid": grid, "margins": margins, "completeness": complete}


RESUME_TAG = "geocd_resume"
"""The pair-DEM's tag naming the pair's resume key (and its completeness): a resumed run that finds the DEM
with this key, and the key journalled in the work folder, does not match the pair again."""


def _pairs_journal(out: Path) -> Path:
    return Path(out) / WORK_DIR / "stereo-pairs"


def _journal_pair(out: Path, pair_key: str) -> None:
    d = _pairs_journal(out)
    d.mkdir(parents=True, exist_ok=True)
    tmp = d / f"{pair_key[:32]}.part"
    tmp.write_text(pair_key)
    tmp.replace(d / f"{pair_key[:32]}.done")


def _finished_pair(out: Path, target: Path, pair_key: str) -> float | None:
    """The completeness of a pair this run already wrote (journalled in the work folder, and the DEM carries
    the same key), else None. A finished run has no work folder: running its command again matches anew."""
    import rasterio

    if not (_pairs_journal(out) / f"{pair_key[:32]}.done").exists() or not target.exists():
        return None
    try:
        with rasterio.open(target) as ds:
            tag = json.loads(ds.tags().get(RESUME_TAG, "{}"))
    except (rasterio.errors.RasterioError, ValueError):
        return None
    return float(tag["completeness"]) if tag.get("key") == pair_key else None


def _json_default(o: Any):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    return str(o)
