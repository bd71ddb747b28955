"""DEM differencing tile by tile: whole scenes with bounded memory, resumable, on Dask.

:func:`dem_difference_tiled` runs :func:`~geocd.demdiff.pipeline.dem_difference`'s method
(same steps, same code for every whole-scene decision) on :mod:`geocd.tiling`: the DEMs
are read by window, every per-cell step runs on tiles with the context it declares, and
every whole-scene step runs on a reduction over tiles.

**Per-cell steps** (exact on every tile, whatever the tiling): alignment of B onto A's
grid (window reads; a GDAL warped VRT when B is on another grid), terrain attributes
(1 cell of context), B moved by the co-registration (:func:`~geocd.demdiff._kernels.shift_window`:
the whole grid's arithmetic, context ``ceil(|shift|) + 2``), the automatic stable terrain
of a given median and threshold (coherent groups of ≥ k cells: k − 1 + dilation cells of
context, :func:`~geocd.demdiff.stable.stable_overlap`), σ, z, confidence, the change sign
and the removal of regions smaller than ``min_region_cells`` (k − 1 cells of context).

**Whole-scene steps** run the pipeline's own code on *cell tables* gathered from the
tiles (values of the cells a statistic needs, in row-major order): the Nuth–Kääb fit
(:func:`~geocd.demdiff.coreg.coregister_cells`; B at the fit cells is interpolated from
small patches gathered around them, bit-identical to shifting the whole grid), the
stable-terrain iteration (:func:`~geocd.demdiff.stable.select_stable`; one pass per
iteration), the error model, the median and |z| distribution of the significance test,
the variogram (on the same grids :func:`~geocd.demdiff.uncertainty.empirical_variogram`
uses: the stable box, or its decimation and a central window — bounded at any size).

**Exactness.** Whole-scene statistics use every cell when the grid has at most
``TilingParams.sample_cells`` cells (8 million by default); beyond, a fixed
pseudo-random subsample of that many cells (a hash of each cell's index: independent
of the tiling and of the scheduler). Correlated sums (the K field of the stable-mean
cross term, volume σ of large cell sets) are computed on the whole grid when it has at
most ``exact_grid_cells`` cells (4 million); beyond, on a coarse grid of block sums with
the block-averaged covariance (:func:`block_covariance`); changed regions then come from
a merge of per-tile regions across seams (:mod:`geocd.tiling.regions`). Up to those sizes
every product is bit-identical to :func:`~geocd.demdiff.pipeline.dem_difference` +
:func:`~geocd.demdiff.products.write_demdiff_products` (tests/demdiff/test_tiled.py);
beyond them the tests state the tolerances.

Not tiled (yet): time series, arbitrary ``observed`` masks (``base`` survey footprints are), and
the stable terrain's hysteresis growth (``StableParams.grow_factor``).
"""

from __future__ import annotations

import hashlib
import math
import time
from dataclasses import dataclass, field, replace
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ConfigError, EmptyDataError, ProcessingError
from ..geodesy import AOIGrid, ELLIPSOID, normalize_datum_name, vertical_datum_of
from ..params import ParamsMixin
from ..progress import Progress, ensure_progress, sub_progress
from ..tiling import (RasterProduct, RasterSource, TileGrid, TileOutput, open_engine, remove_work, run_tiled,
                      work_root)
from ._kernels import shift_margin, shift_points, shift_window, terrain_attributes
from .coreg import CoregPlan, CoregResult, StableCells, coregister_cells
from .pipeline import CHANGE_NODATA, DEMDiffParams
from .significance import SignificanceModel
from .stable import (REJECTED, StableInfo, StableParams, buffered, nmad, select_stable, stable_overlap,
                     stable_state_mask)
from .uncertainty import (ErrorModel, Uncertainty, VariogramModel, VariogramPlan, _k_field, fit_error_model,
                          fit_variogram, variogram_from_plan, variogram_plan)


# ------------------------------------------------------------------------------------------
# parameters
# ------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class TilingParams(ParamsMixin):
    """How a scene is tiled and scheduled (see :mod:`geocd.tiling` and the module docstring).

    Attributes
    ----------
    tile_size : cells per tile side
    scheduler : sync | threads | processes | auto | a dask.distributed scheduler address
    n_workers, memory_limit : of the local cluster (default: one worker per core, 80 % of
        the machine's memory shared out)
    sample_cells : whole-scene statistics use every cell of grids up to this size, a fixed
        subsample of this many cells beyond
    exact_grid_cells : correlated sums on the whole grid up to this size, on a coarse grid beyond
    coarse_cells : size of that coarse grid
    patch_radius : cells around each co-registration fit cell gathered for its interpolation
    keep_work : keep the work folder (per-tile results) after a successful run
    """

    _kind = "tiling"

    tile_size: int = 1024
    scheduler: str = "auto"
    n_workers: int | None = None
    memory_limit: str | None = None
    sample_cells: int = 8_000_000
    exact_grid_cells: int = 4_000_000
    coarse_cells: int = 1_000_000
    patch_radius: int = 4
    keep_work: bool = False

    def __post_init__(self) -> None:
        if self.tile_size < 64:
            raise ConfigError(f"tile_size must be at least 64 cells, got {self.tile_size}")
        if self.sample_cells < 10_000 or self.coarse_cells < 1_000:
            raise ConfigError("sample_cells ≥ 10 000 and coarse_cells ≥ 1 000 are required")
        if self.patch_radius < 2:
            raise ConfigError("patch_radius must be ≥ 2")


# ------------------------------------------------------------------------------------------
# deterministic subsample
# ------------------------------------------------------------------------------------------
def keep_cells(rows: np.ndarray, cols: np.ndarray, width: int, fraction: float) -> np.ndarray:
    """bool: the cells a whole-scene statistic keeps at ``fraction`` (a hash of the cell index:
    the same cells whatever the tiling, scheduler or order)."""
    if fraction >= 1.0:
        return np.ones(np.shape(rows), bool)
    with np.errstate(over="ignore"):
        z = (np.asarray(rows, np.uint64) * np.uint64(width) + np.asarray(cols, np.uint64)
             + np.uint64(0x9E3779B97F4A7C15))
        z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        z = z ^ (z >> np.uint64(31))
    return (z >> np.uint64(11)).astype(np.float64) * (1.0 / 9007199254740992.0) < fraction


# ------------------------------------------------------------------------------------------
# what every tile knows
# ------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class _Setup:
    grid: AOIGrid
    posting: tuple[float, float]
    a: RasterSource
    b: RasterSource
    datum_a: str | None
    datum_b: str | None
    params: DEMDiffParams
    footprints: Any
    user_mask: Any
    mask_is: str
    fraction: float
    ident: str
    base: Any = None

    def cache_key(self) -> dict:
        return {"ident": self.ident}

    @property
    def shape(self) -> tuple[int, int]:
        return self.grid.shape


@dataclass(frozen=True)
class _StableDef:
    """How a tile computes a stable mask: ``valid`` (± footprints), ``user`` mask, or ``auto``
    (a :func:`select_stable` state) on dh = B (moved by ``plan``) − A."""

    kind: str
    plan: CoregPlan | None = None
    state: Any = None
    params: StableParams | None = None
    exclude: bool = True


class _Win:
    """A tile's read window: A, B (float64 from the aligned float32), terrain, masks."""

    def __init__(self, arrays: dict, ctx, S: _Setup):
        self.S = S
        self.ctx = ctx
        a32 = arrays["a"]
        b32 = arrays["b"]
        if S.datum_a is not None or S.datum_b is not None:
            from ..io.raster import DEM

            g = ctx.read_grid
            if S.datum_a is not None:
                a32 = DEM(a32, g, S.datum_a).to_ellipsoidal().height_m.astype(np.float32)
            if S.datum_b is not None:
                b32 = DEM(b32, g, S.datum_b).to_ellipsoidal().height_m.astype(np.float32)
        self.b32_raw = b32
        self.valid = np.isfinite(a32) & np.isfinite(b32)
        if "base" in arrays:
            from .timeseries import survey_footprint

            base = arrays["base"]
            self.valid &= survey_footprint(a32, base) & survey_footprint(b32, base)
            # the pipeline co-registers B masked to the compared cells
            b32 = np.where(self.valid, b32, np.float32(np.nan)).astype(np.float32)
        self.a32 = a32
        self.b32 = b32
        self.A = a32.astype(np.float64)
        self.B = b32.astype(np.float64)
        self._b = {}

    @cached_property
    def terrain(self) -> dict:
        return terrain_attributes(self.A, self.S.posting)

    @property
    def slope(self) -> np.ndarray:
        return self.terrain["slope_rad"]

    @property
    def q(self) -> np.ndarray | None:
        pr = self.S.params.error.predictor
        return self.terrain.get(pr) if pr != "none" else None

    @cached_property
    def footprint(self) -> np.ndarray | None:
        fp = self.S.footprints
        if fp is None:
            return None
        from ..io.vector import polygons_to_mask

        return polygons_to_mask(fp, self.ctx.read_grid).astype(bool)

    @cached_property
    def exclude(self) -> np.ndarray | None:
        if self.footprint is None:
            return None
        return buffered(self.footprint, self.S.params.stable.footprint_buffer_cells)

    @cached_property
    def user(self) -> np.ndarray | None:
        um = self.S.user_mask
        if um is None:
            return None
        if isinstance(um, RasterSource):
            m = um.read(self.ctx.grid, self.ctx.tile.read)
            inside = np.isfinite(m) & (m != 0)
        else:
            from ..io.vector import polygons_to_mask

            inside = polygons_to_mask(um, self.ctx.read_grid).astype(bool)
        return inside if self.S.mask_is == "stable" else ~inside

    def b_moved(self, plan: CoregPlan | None) -> np.ndarray:
        """B co-registered by ``plan`` (float64 from the pipeline's float32), B itself for None."""
        if plan is None:
            return self.B
        key = id(plan)
        if key not in self._b:
            self._b[key] = plan.apply(self.B, self.S.posting, self.ctx.origin, self.S.shape).astype(np.float64)
        return self._b[key]

    def dh(self, plan: CoregPlan | None) -> np.ndarray:
        return np.where(self.valid, self.b_moved(plan) - self.A, np.nan)

    def base(self, dh: np.ndarray, ok: np.ndarray, sp: StableParams) -> np.ndarray:
        """Candidate stable cells of the automatic selection (as :func:`auto_stable_mask`)."""
        s = self.slope
        base = ok & np.isfinite(s) & (s <= np.radians(sp.max_slope_deg))
        if self.exclude is not None:
            base &= ~self.exclude
        return base

    def stable(self, sd: _StableDef) -> np.ndarray:
        """The stable mask ``sd`` stands for (exact on the core given the pass's overlap)."""
        if sd.kind == "valid":
            m = self.valid & np.isfinite(self.dh(None))
            return m & ~self.exclude if (sd.exclude and self.exclude is not None) else m
        dh = self.dh(sd.plan)
        ok = self.valid & np.isfinite(dh)
        if sd.kind == "user":
            m = self.user & ok
            return m & ~self.exclude if self.exclude is not None else m
        if sd.kind == "auto":
            return stable_state_mask(dh, ok, self.base(dh, ok, sd.params), sd.state, sd.params)
        raise ProcessingError(f"unknown stable definition {sd.kind!r}")


def _core_cells(mask: np.ndarray, ctx, S: _Setup, sample: bool = True):
    """(global linear index, local rows, local cols) of the mask's core cells (sampled)."""
    core = ctx.core
    rr, cc = np.nonzero(mask[core])
    rr = rr + core[0].start
    cc = cc + core[1].start
    R0, C0 = ctx.origin
    if sample and S.fraction < 1.0:
        k = keep_cells(rr + R0, cc + C0, S.grid.width, S.fraction)
        rr, cc = rr[k], cc[k]
    idx = (rr + R0).astype(np.int64) * S.grid.width + (cc + C0)
    return idx, rr, cc


def _count_core(mask: np.ndarray, ctx) -> int:
    return int(np.count_nonzero(mask[ctx.core]))


def _positions_in_core(idx_all: np.ndarray, ctx, width: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Positions in the sorted ``idx_all`` of its cells inside the tile's core, with local rows/cols."""
    r0, c0, h, w = ctx.tile.core
    lo = np.searchsorted(idx_all, np.arange(r0, r0 + h, dtype=np.int64) * width + c0)
    hi = np.searchsorted(idx_all, np.arange(r0, r0 + h, dtype=np.int64) * width + c0 + w)
    n = hi - lo
    if n.sum() == 0:
        e = np.zeros(0, np.int64)
        return e, e, e
    pos = np.concatenate([np.arange(a, b) for a, b in zip(lo, hi) if b > a])
    g = idx_all[pos]
    R0, C0 = ctx.origin
    return pos, g // width - R0, g % width - C0


# ------------------------------------------------------------------------------------------
# tile functions (module level: they travel to dask workers)
# ------------------------------------------------------------------------------------------
def _t_table(arrays, ctx):
    """Cell table of a stable definition (for co-registration): idx, A, B, slope, aspect."""
    S, sd = ctx.params
    w = _Win(arrays, ctx, S)
    st = w.stable(sd) & np.isfinite(w.A) & np.isfinite(w.B)
    idx, rr, cc = _core_cells(st, ctx, S)
    return TileOutput(small={"n": _count_core(st, ctx), "idx": idx, "a": w.a32[rr, cc], "b": w.b32[rr, cc],
                             "slope": w.terrain["slope_rad"][rr, cc], "aspect": w.terrain["aspect_rad"][rr, cc]})


def _t_patches(arrays, ctx):
    """B on (2M+1)² patches around requested cells, centred at an integer offset."""
    S, idx_all, (orow, ocol), M = ctx.params
    w = _Win(arrays, ctx, S)
    pos, rr, cc = _positions_in_core(idx_all, ctx, S.grid.width)
    P = 2 * M + 1
    Q = M + max(abs(orow), abs(ocol)) + 1
    pad = np.full((w.B.shape[0] + 2 * Q, w.B.shape[1] + 2 * Q), np.nan, np.float32)
    pad[Q:-Q, Q:-Q] = w.b32
    pr = rr + orow - M
    pc = cc + ocol - M
    if pos.size:
        from numpy.lib.stride_tricks import sliding_window_view

        patches = np.ascontiguousarray(sliding_window_view(pad, (P, P))[pr + Q, pc + Q])
    else:
        patches = np.zeros((0, P, P), np.float32)
    R0, C0 = ctx.origin
    return TileOutput(small={"pos": pos, "patches": patches, "pr": pr + R0, "pc": pc + C0})


def _t_shifted(arrays, ctx):
    """B shifted by (dcol, drow) px at requested cells."""
    S, idx_all, dcol, drow = ctx.params
    w = _Win(arrays, ctx, S)
    pos, rr, cc = _positions_in_core(idx_all, ctx, S.grid.width)
    bh = shift_window(w.B, ctx.origin, S.shape, dcol, drow, S.params.coreg.resampling)
    return TileOutput(small={"pos": pos, "v": bh[rr, cc]})


def _t_stable(arrays, ctx):
    """One step of the automatic stable terrain: values of dh on the new mask and the counts."""
    S, plan, sp, prev, new, initial = ctx.params
    w = _Win(arrays, ctx, S)
    dh = w.dh(plan)
    ok = w.valid & np.isfinite(dh)
    base = w.base(dh, ok, sp)
    if initial:
        idx, rr, cc = _core_cells(base, ctx, S)
        return TileOutput(small={"v": dh[rr, cc], "n": _count_core(base, ctx)})
    m_prev = stable_state_mask(dh, ok, base, prev, sp)
    m_new = stable_state_mask(dh, ok, base, new, sp)
    idx, rr, cc = _core_cells(m_new, ctx, S)
    core = ctx.core
    return TileOutput(small={"v": dh[rr, cc], "n": _count_core(m_new, ctx),
                             "excluded": int(np.count_nonzero((base & ~m_new)[core])),
                             "toggled": int(np.count_nonzero((m_new != m_prev)[core]))})


def _t_errtable(arrays, ctx):
    """The final stable cells: dh, slope, q (sampled), their count, bounding box and 16-px blocks."""
    S, plan, sd = ctx.params
    w = _Win(arrays, ctx, S)
    dh = w.dh(plan)
    st = w.stable(sd) & np.isfinite(dh)
    idx, rr, cc = _core_cells(st, ctx, S)
    q = w.q
    # exact (not sampled): count, bounding box, blocks
    r_all, c_all = np.nonzero(st[ctx.core])
    R0 = ctx.tile.core[0]
    C0 = ctx.tile.core[1]
    bp = S.params.coreg.block_px
    ncb = S.grid.width // bp + 1
    blocks = np.unique(((r_all + R0) // bp) * ncb + (c_all + C0) // bp) if r_all.size else np.zeros(0, np.int64)
    bbox = ((int(r_all.min() + R0), int(c_all.min() + C0), int(r_all.max() + R0), int(c_all.max() + C0))
            if r_all.size else None)
    return TileOutput(small={"n": int(r_all.size), "idx": idx, "dh": dh[rr, cc], "slope": w.slope[rr, cc],
                             "q": q[rr, cc] if q is not None else None, "blocks": blocks, "bbox": bbox,
                             "fp_n": _count_core(w.footprint, ctx) if w.footprint is not None else 0})


def _sigma_window(w: _Win, em: ErrorModel, dh: np.ndarray) -> np.ndarray:
    """Per-cell σ as :func:`estimate_uncertainty` makes it (model, filled with its c0 where slope is NaN)."""
    sigma = em.sigma(w.slope, w.q if em.predictor != "none" else None)
    fill = float(math.sqrt(em.coef[0]) * em.scale)
    return np.where(np.isfinite(sigma), sigma, np.where(np.isfinite(dh), fill, np.nan)).astype(np.float32)


def _t_zgrids(arrays, ctx):
    """Standardized residuals z on the variogram plan's grids (box, or decimated box + window)."""
    S, plan, sd, em, med, vplan, clip = ctx.params
    w = _Win(arrays, ctx, S)
    dh = w.dh(plan)
    st = w.stable(sd) & np.isfinite(dh)
    sigma = _sigma_window(w, em, dh)
    m = st & np.isfinite(sigma) & (sigma > 0)
    z = np.full(dh.shape, np.nan)
    z[m] = (dh[m] - med) / sigma[m].astype(np.float64)
    z = np.clip(z, -clip, clip)
    r0, c0, h, wd = ctx.tile.core
    R0, C0 = ctx.origin
    out = {}
    fin = np.isfinite(z[ctx.core])
    rr, cc = np.nonzero(fin)
    out["bbox"] = ((int(rr.min() + r0), int(cc.min() + c0), int(rr.max() + r0), int(cc.max() + c0))
                   if rr.size else None)

    def piece(win):  # intersection of the core with a window (row0, col0, h, w) of the grid
        a0, b0, ah, aw = win
        i0, j0 = max(a0, r0), max(b0, c0)
        i1, j1 = min(a0 + ah, r0 + h), min(b0 + aw, c0 + wd)
        if i1 <= i0 or j1 <= j0:
            return None
        return (i0 - a0, j0 - b0, z[i0 - R0:i1 - R0, j0 - C0:j1 - C0].copy())

    if vplan.step == 1:
        out["box"] = piece(vplan.bbox)
    else:
        st_ = vplan.step
        a0, b0, ah, aw = vplan.bbox
        # decimated cells of the box inside this core
        i_first = a0 + ((max(r0, a0) - a0 + st_ - 1) // st_) * st_
        j_first = b0 + ((max(c0, b0) - b0 + st_ - 1) // st_) * st_
        i_last = min(r0 + h, a0 + ah) - 1
        j_last = min(c0 + wd, b0 + aw) - 1
        if i_first <= i_last and j_first <= j_last:
            blk = z[i_first - R0:i_last - R0 + 1:st_, j_first - C0:j_last - C0 + 1:st_]
            out["sub"] = ((i_first - a0) // st_, (j_first - b0) // st_, blk.copy())
        else:
            out["sub"] = None
        out["window"] = piece(vplan.window)
    return TileOutput(small=out)


def _t_grids(arrays, ctx):
    """Whole-grid arrays for the exact path (small grids): everything the untiled pipeline holds."""
    S, plan, sd, em, raw_plan = ctx.params
    w = _Win(arrays, ctx, S)
    dh = w.dh(plan)
    st = w.stable(sd) & np.isfinite(dh)
    sigma = _sigma_window(w, em, dh) if em is not None else np.full(dh.shape, np.nan, np.float32)
    bc = w.b_moved(plan).astype(np.float32) if plan is not None else w.b32_raw
    return TileOutput(arrays={"dh64": dh, "stable": st, "sigma_u": sigma, "a32": w.a32, "b32": w.b32_raw,
                              "valid": w.valid,
                              "bc32": bc, "slope": w.slope})


def _t_products(arrays, ctx):
    """Per-cell products and the tile's partial sums (large grids)."""
    S, plan, sd, em, sig, level, center, block, fitted_plan = ctx.params
    p = S.params
    w = _Win(arrays, ctx, S)
    dh = w.dh(plan)
    obs = w.valid & np.isfinite(dh)
    st = w.stable(sd) & np.isfinite(dh) if sd is not None else np.zeros(dh.shape, bool)
    if em is not None:
        sigma_u = _sigma_window(w, em, dh)
        sigma = np.where(obs, sigma_u, np.nan).astype(np.float32)
    else:
        sigma = np.full(dh.shape, np.nan, np.float32)
    from .significance import change_sign, significance_map

    if sig is not None:
        z, conf = significance_map(dh, sigma, sig)
        raw = change_sign(dh, conf, level, center)
    else:
        z = np.full(dh.shape, np.nan, np.float32)
        conf = np.full(dh.shape, np.nan, np.float32)
        if p.fallback_threshold_m is not None:
            raw = np.where(np.abs(np.nan_to_num(dh)) > p.fallback_threshold_m, np.sign(np.nan_to_num(dh)),
                           0).astype(np.int8)
        else:
            raw = np.zeros(dh.shape, np.int8)
    raw = np.where(obs, raw, 0).astype(np.int8)
    from .pipeline import _sign_in_regions

    sign = np.where(obs, _sign_in_regions(raw, p.min_region_cells), CHANGE_NODATA).astype(np.int8)
    conf_pct = np.where(np.isfinite(conf), 100.0 * conf, np.nan).astype(np.float32)
    dh32 = dh.astype(np.float32)
    core = ctx.core
    dhc = dh32[core].astype(np.float64)
    sc = sign[core]
    obc = obs[core]
    stc = st[core]
    ch = (sc == 1) | (sc == -1)
    small: dict[str, Any] = {
        "n_obs": int(obc.sum()), "n_stable": int(stc.sum()), "n_changed": int(ch.sum()),
        "n_raised": int((sc == 1).sum()), "n_lowered": int((sc == -1).sum()),
        "sum_changed": float(np.nansum(dhc[ch])), "sum_raised": float(np.nansum(dhc[sc == 1])),
        "sum_lowered": float(np.nansum(dhc[sc == -1])), "sum_obs": float(np.nansum(dhc[obc])),
    }
    idx, rr, cc = _core_cells(st, ctx, S)
    small["stable_dh"] = dh32[rr, cc]
    fin = np.isfinite(dh32)
    idx, rr, cc = _core_cells(fin, ctx, S)
    small["abs_dh"] = np.abs(dh32[rr, cc])
    if fitted_plan is not None and ch.any():
        bf = fitted_plan.apply(w.B, S.posting, ctx.origin, S.shape).astype(np.float64)
        d = np.where(obs, bf - w.A, np.nan)[core]
        small["sum_changed_fitted"] = float(np.nansum(d[ch]))
    # block sums of σ for correlated sums on the coarse grid
    if block is not None and em is not None:
        sg = np.where(np.isfinite(sigma), sigma, 0.0)[core].astype(np.float64)
        small["blocks"] = _block_sums(ctx, block, {"obs": np.where(obc, sg, 0.0), "changed": np.where(ch, sg, 0.0)})
    # changed regions of this tile, to be merged across seams
    from ..tiling.regions import tile_regions

    small["regions"] = tile_regions(sign[core], dh[core], ctx.tile, S.grid, sigma=sigma[core],
                                    confidence=conf[core])
    return TileOutput(arrays={"dh_m": dh32, "confidence_pct": conf_pct, "sigma_m": sigma, "z": z.astype(np.float32),
                              "sign": sign}, small=small)


def _t_blocks(arrays, ctx):
    """Block sums of the stable σ (coarse grid for the K field and the stable-mean σ)."""
    S, plan, sd, em, block = ctx.params
    w = _Win(arrays, ctx, S)
    dh = w.dh(plan)
    st = w.stable(sd) & np.isfinite(dh)
    sigma = _sigma_window(w, em, dh)
    m = st & np.isfinite(sigma) & (sigma > 0)
    ws = np.where(m, sigma, 0.0)[ctx.core].astype(np.float64)
    return TileOutput(small={"blocks": _block_sums(ctx, block, {"w": ws}), "n": _count_core(m, ctx)})


def _block_sums(ctx, block: int, fields: dict[str, np.ndarray]) -> dict:
    """Sums of each field over the ``block``-cell blocks of the whole grid that the core touches."""
    r0, c0, h, w = ctx.tile.core
    br = (np.arange(r0, r0 + h) // block)
    bc = (np.arange(c0, c0 + w) // block)
    ur, ir = np.unique(br, return_inverse=True)
    uc, ic = np.unique(bc, return_inverse=True)
    out = {"rows": ur, "cols": uc}
    for k, a in fields.items():
        s = np.zeros((ur.size, uc.size))
        np.add.at(s, (ir[:, None], ic[None, :]), a)
        out[k] = s
    return out


# ------------------------------------------------------------------------------------------
# coarse correlated sums (large grids)
# ------------------------------------------------------------------------------------------
def block_covariance(model: VariogramModel, block: int, posting_xy_m: tuple[float, float], shape: tuple[int, int],
                     near: int = 3) -> np.ndarray:
    """Average covariance between the cells of two ``block``² blocks, for every block lag.

    Returns the (2H−1, 2W−1) kernel over block lags (H, W = ``shape`` in blocks), centred.
    Lags within ``near`` blocks average C over the cell pairs (a triangle-weighted sum
    over the within-block offsets: exact for uniform σ in a block); farther lags use C
    at the blocks' centre distance (C is smooth there).
    """
    from .uncertainty import _lag_distance

    H, W = shape
    pxb, pyb = posting_xy_m[0] * block, posting_xy_m[1] * block
    cov = model.covariance(_lag_distance((2 * H - 1, 2 * W - 1), (pxb, pyb)))
    d = np.arange(-(block - 1), block)
    t = (block - np.abs(d)) / float(block * block)
    tw = t[:, None] * t[None, :]
    for i in range(-near, near + 1):
        for j in range(-near, near + 1):
            if abs(i) >= H or abs(j) >= W:
                continue
            dy = (i * block + d)[:, None] * posting_xy_m[1]
            dx = (j * block + d)[None, :] * posting_xy_m[0]
            cov[H - 1 + i, W - 1 + j] = float(np.sum(tw * model.covariance(np.hypot(dy, dx))))
    return cov


def _coarse_conv(a: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    from scipy.signal import fftconvolve

    return fftconvolve(a, kernel, mode="same")


# ------------------------------------------------------------------------------------------
# the run
# ------------------------------------------------------------------------------------------
@dataclass
class TiledDEMDiffResult:
    """What :func:`dem_difference_tiled` made: the products' paths and the whole-scene figures.

    Attributes
    ----------
    outputs : product name → path (the same names as :func:`write_demdiff_products`)
    summary : the headline figures (the same keys as ``DEMDiffResult.summary``)
    coreg, stable_info, uncertainty model, significance : as in DEMDiffResult (the uncertainty
        without per-cell grids)
    exact : True when every whole-scene statistic used every cell (bit-identical to the untiled run)
    timings : seconds per step; ``passes``: tiled passes run
    """

    outputs: dict[str, Path]
    summary: dict[str, Any]
    coreg: CoregResult
    stable_info: StableInfo
    status: str
    notes: list[str]
    error_model: ErrorModel | None = None
    variogram: VariogramModel | None = None
    significance: SignificanceModel | None = None
    exact: bool = True
    grid: AOIGrid | None = None
    timings: dict[str, float] = field(default_factory=dict)
    passes: int = 0
    tiles_resumed: int = 0


class _Runner:
    """Runs the passes of one tiled DEM difference (client side)."""

    def __init__(self, S: _Setup, out: Path, tiling: TilingParams, engine, progress: Progress):
        self.S = S
        self.out = out
        self.tiling = tiling
        self.eng = engine
        self.prog = progress
        self.tg = TileGrid(S.grid, (tiling.tile_size, tiling.tile_size), 0)
        self.sources = {"a": S.a, "b": S.b}
        if S.base is not None:
            self.sources["base"] = S.base
        self.passes = 0
        self.resumed = 0
        self.t0 = time.perf_counter()
        self.t_frac = 0.0
        self.est_passes = 18

    def overlap(self, plan: CoregPlan | None = None, cc: int = 0) -> int:
        S = self.S
        m = 1
        if plan is not None and plan.shift_px is not None:
            m = max(m, shift_margin(plan.shift_px[0], plan.shift_px[1], plan.resampling))
        if S.footprints is not None:
            m = max(m, S.params.stable.footprint_buffer_cells + 1)
        return m + cc

    def run(self, func, stage: str, params, overlap: int, products=None):
        self.passes += 1
        f0 = min(self.passes - 1, self.est_passes - 1) / self.est_passes
        f1 = min(self.passes, self.est_passes) / self.est_passes
        r = run_tiled(func, self.tg.with_overlap(overlap), self.sources, params=params, out=self.out,
                      stage=f"demdiff-{self.passes:02d}-{stage}", key=self.S.ident, products=products,
                      scheduler=self.eng, progress=sub_progress(self.prog, 0.02 + 0.9 * f0, 0.02 + 0.9 * f1,
                                                                f"{stage}: "))
        self.resumed += r.n_resumed
        return r

    # --- gathering -----------------------------------------------------------------------
    def table(self, sd: _StableDef, plan_for_overlap: CoregPlan | None, cc: int, stage: str) -> StableCells:
        r = self.run(_t_table, stage, (self.S, sd), self.overlap(plan_for_overlap, cc))
        parts = [s for _, s in r.smalls()]
        idx = np.concatenate([s["idx"] for s in parts])
        order = np.argsort(idx, kind="stable")
        W = self.S.grid.width
        idx = idx[order]

        def cat(k, dt):
            return np.concatenate([s[k] for s in parts])[order].astype(dt)

        return StableCells(idx // W, idx % W, cat("a", np.float64), cat("b", np.float64), cat("slope", np.float64),
                           cat("aspect", np.float64), self.S.shape, int(sum(s["n"] for s in parts)))


class _TiledCoregData:
    """:func:`coregister_cells`' access to tiles: B at the fit cells from gathered patches."""

    def __init__(self, runner: _Runner, cells: StableCells, stage: str):
        self.runner = runner
        self.cells = cells
        self.stage = stage
        self._patch = None   # (idx positions, centre offset, patches, pr, pc)

    def _gather_patches(self, idx: np.ndarray, orow: int, ocol: int) -> None:
        R = self.runner
        M = R.tiling.patch_radius
        W = R.S.grid.width
        lin = self.cells.rows[idx] * W + self.cells.cols[idx]
        r = R.run(_t_patches, f"{self.stage}-patches", (R.S, lin, (orow, ocol), M),
                  M + max(abs(orow), abs(ocol)) + 1)
        n = lin.size
        P = 2 * M + 1
        patches = np.full((n, P, P), np.nan, np.float32)
        pr = np.zeros(n, np.int64)
        pc = np.zeros(n, np.int64)
        for _, s in r.smalls():
            patches[s["pos"]] = s["patches"]
            pr[s["pos"]] = s["pr"]
            pc[s["pos"]] = s["pc"]
        self._patch = (idx, (orow, ocol), patches, pr, pc)

    def sample_b(self, idx: np.ndarray, dcol: float, drow: float) -> np.ndarray:
        rows, cols = self.cells.rows[idx], self.cells.cols[idx]
        method = self.runner.S.params.coreg.resampling
        centre = (int(round(-drow)), int(round(-dcol)))
        if self._patch is None or not np.array_equal(self._patch[0], idx):
            self._gather_patches(idx, *centre)
        v, ok = shift_points(self._patch[2], self._patch[3], self._patch[4], rows, cols, self.cells.shape, dcol, drow,
                             method)
        if not ok:
            self._gather_patches(idx, *centre)
            v, ok = shift_points(self._patch[2], self._patch[3], self._patch[4], rows, cols, self.cells.shape, dcol,
                                 drow, method)
            if not ok:
                raise ProcessingError("co-registration: patches too small for the shift (raise patch_radius)")
        return v

    def shifted_b(self, dcol: float, drow: float) -> np.ndarray:
        R = self.runner
        W = R.S.grid.width
        lin = self.cells.rows * W + self.cells.cols
        r = R.run(_t_shifted, f"{self.stage}-shifted", (R.S, lin, dcol, drow),
                  shift_margin(dcol, drow, R.S.params.coreg.resampling))
        v = np.full(lin.size, np.nan)
        for _, s in r.smalls():
            v[s["pos"]] = s["v"]
        return v


class _TiledStable:
    """:func:`select_stable`'s access to tiles: one pass per iteration."""

    def __init__(self, runner: _Runner, plan: CoregPlan | None, params: StableParams, stage: str):
        self.R = runner
        self.plan = plan
        self.params = params
        self.stage = stage
        self.prev = None
        self.n_base = 0
        self.k = 0

    def _ov(self) -> int:
        return self.R.overlap(self.plan, stable_overlap(self.params))

    def initial(self):
        r = self.R.run(_t_stable, f"{self.stage}-0", (self.R.S, self.plan, self.params, None, None, True), self._ov())
        parts = [s for _, s in r.smalls()]
        self.n_base = int(sum(s["n"] for s in parts))
        return np.concatenate([s["v"] for s in parts]), self.n_base

    def step(self, state):
        self.k += 1
        r = self.R.run(_t_stable, f"{self.stage}-{self.k}", (self.R.S, self.plan, self.params, self.prev, state, False),
                       self._ov())
        self.prev = state
        parts = [s for _, s in r.smalls()]
        return (np.concatenate([s["v"] for s in parts]), int(sum(s["n"] for s in parts)),
                int(sum(s["excluded"] for s in parts)), int(sum(s["toggled"] for s in parts)))


def _source_identity(src: RasterSource) -> dict:
    return src.identity()


def _gdf_key(gdf) -> str | None:
    if gdf is None:
        return None
    if isinstance(gdf, RasterSource):
        return str(gdf.identity())
    h = hashlib.sha1()
    for gm in gdf.geometry:
        h.update(gm.wkb)
    h.update(str(gdf.crs).encode())
    return h.hexdigest()


def _setup(path_a, path_b, *, datum_a, datum_b, params: DEMDiffParams, stable_mask, mask_is, footprints,
           tiling: TilingParams, base=None) -> tuple[_Setup, list[str]]:
    from ..errors import VerticalDatumError
    from ..io.raster import _open
    from .align import crop_to_overlap, metric_posting

    notes: list[str] = []
    with _open(path_a) as da, _open(path_b) as db:
        from ..errors import CRSError

        for p_, d_ in ((path_a, da), (path_b, db)):
            if d_.crs is None:
                raise CRSError(f"DEM {p_} has no CRS; assign one (gdal_edit.py -a_srs EPSG:...) before using it")
        ga = AOIGrid.from_raster(da)
        gb = AOIGrid.from_raster(db)
        va = normalize_datum_name(datum_a) or vertical_datum_of(da.crs)
        vb = normalize_datum_name(datum_b) or vertical_datum_of(db.crs)
    if (va is None) != (vb is None):
        which = "B" if va is not None else "A"
        raise VerticalDatumError(
            f"DEM A's vertical datum is {va or 'unknown'} and DEM B's is {vb or 'unknown'}: geocd will not guess. "
            f"Declare DEM {which}'s vertical datum (--datum-{which.lower()} ellipsoid|egm96|egm2008, or "
            f"vertical_datum= in Python); if both are in the same datum, declare it for both")
    # with a base DEM the comparison keeps A's whole grid (the survey footprints decide what is compared)
    target = crop_to_overlap(ga, gb) if base is None else ga
    conv_a = conv_b = None
    if va != vb:
        notes.append(f"vertical datums differ ({va} vs {vb}): both converted to ellipsoidal heights")
        conv_a = va if va != ELLIPSOID else None
        conv_b = vb if vb != ELLIPSOID else None
    if not gb.same_as(target):
        notes.append(f"B resampled onto the reference grid ({params.resampling})")
    if params.stable.grow_factor is not None:
        stable_overlap(params.stable)  # raises: not tileable
    src_a = RasterSource(str(path_a), dem=True, resampling=params.resampling)
    src_b = RasterSource(str(path_b), dem=True, resampling=params.resampling)
    fp = None
    if footprints is not None:
        from ..io.vector import read_footprints

        fp = footprints if hasattr(footprints, "geometry") else read_footprints(footprints, crs=target.crs)
        fp = fp.to_crs(target.crs) if fp.crs is not None else fp
    um = None
    if stable_mask is not None:
        if isinstance(stable_mask, np.ndarray):
            raise ConfigError("a tiled run takes the stable mask as a file (raster or polygons), not an array")
        if hasattr(stable_mask, "geometry"):
            um = stable_mask.to_crs(target.crs) if stable_mask.crs is not None else stable_mask
        else:
            p = Path(stable_mask)
            from ..errors import InputFileNotFoundError

            if not p.exists():
                raise InputFileNotFoundError(f"mask file {p} does not exist; check the path")
            if p.suffix.lower() in (".gpkg", ".geojson", ".json", ".shp", ".fgb", ".kml", ".gml"):
                from ..io.vector import read_footprints

                um = read_footprints(p, crs=target.crs)
            else:
                um = RasterSource(str(p), resampling="nearest")
    base_src = None
    if base is not None:
        base_src = _base_source(base, target, va)
    frac = min(1.0, tiling.sample_cells / float(target.width * target.height))
    ident = {"a": src_a.identity(), "b": src_b.identity(), "datums": [conv_a, conv_b], "params": params,
             "grid": target.to_dict(), "fp": _gdf_key(fp), "mask": _gdf_key(um), "mask_is": mask_is,
             "frac": frac, "patch": tiling.patch_radius, "exact": tiling.exact_grid_cells,
             "coarse": tiling.coarse_cells, "base": base_src.identity() if base_src is not None else None}
    from ..tiling import make_key

    S = _Setup(target, metric_posting(target), src_a, src_b, conv_a, conv_b, params, fp, um, mask_is, frac,
               make_key(ident), base_src)
    return S, notes


def _base_source(base, grid: AOIGrid, datum_a: str | None):
    """The base DEM on the grid: a window source for GDAL rasters, an in-memory array for .e00 grids."""
    from ..errors import VerticalDatumError
    from ..io.raster import DEM, read_dem
    from ..tiling import ArraySource
    from .align import _resample

    if isinstance(base, DEM) or Path(str(base)).suffix.lower() == ".e00":
        if not isinstance(base, DEM):
            from ..io.e00 import read_e00_dem

            base = read_e00_dem(base, vertical_datum=datum_a)
        if normalize_datum_name(base.vertical_datum) != datum_a:
            raise VerticalDatumError(f"the base DEM's vertical datum ({base.vertical_datum}) is not DEM A's "
                                     f"({datum_a}); declare it or convert the base first")
        return ArraySource(_resample(base, grid, "bilinear").astype(np.float32))
    with rasterio_open(base) as ds:
        vb = vertical_datum_of(ds.crs)
    if vb is not None and datum_a is not None and normalize_datum_name(vb) != datum_a:
        raise VerticalDatumError(f"the base DEM's vertical datum ({vb}) is not DEM A's ({datum_a}); convert it first")
    return RasterSource(str(base), dem=True, resampling="bilinear")


def rasterio_open(path):
    from ..io.raster import _open

    return _open(path)


def dem_difference_tiled(dem_a, dem_b, out_dir, *, params: DEMDiffParams = DEMDiffParams(),
                         tiling: TilingParams = TilingParams(), stable_mask: Any = None, mask_is: str = "stable",
                         footprints: Any = None, epoch_a: str = "A", epoch_b: str = "B", datum_a: str | None = None,
                         datum_b: str | None = None, base: Any = None, method: str = "demdiff",
                         prefix: str = "demdiff", plots: bool = True, provenance: dict | None = None,
                         progress: Progress | None = None) -> TiledDEMDiffResult:
    """DEM differencing of two DEM files on tiles, products written to ``out_dir`` (see module docstring).

    Parameters
    ----------
    dem_a, dem_b : paths of DEM A (reference, earlier) and B (later)
    out_dir : output folder (the products of :func:`~geocd.demdiff.products.write_demdiff_products`;
        the work folder ``out_dir/.geocd-work`` makes a killed run resumable)
    params : DEMDiffParams (as :func:`~geocd.demdiff.pipeline.dem_difference`)
    tiling : TilingParams
    stable_mask : optional raster or polygon file (or GeoDataFrame) of stable terrain
    footprints : optional building polygons (file or GeoDataFrame)
    base : optional base DEM (file, .e00 or DEM) the DEMs were merged onto: only cells where both
        differ from it (their surveys) are compared, on A's whole grid (``geocd demdiff --base``)

    Raises
    ------
    NoOverlapError, VerticalDatumError, EmptyDataError, SchedulerError, CancelledError
    """
    t0 = time.perf_counter()
    prog = ensure_progress(progress)
    p = params
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    from ..io.atomic import protect_inputs

    protect_inputs(dem_a, dem_b)
    S, notes = _setup(dem_a, dem_b, datum_a=datum_a, datum_b=datum_b, params=p, stable_mask=stable_mask,
                      mask_is=mask_is, footprints=footprints, tiling=tiling, base=base)
    g = S.grid
    timings: dict[str, float] = {}
    prog(0.01, f"{g.height}×{g.width} cells in tiles of {tiling.tile_size}")
    with open_engine(tiling.scheduler, n_workers=tiling.n_workers, memory_limit=tiling.memory_limit) as eng:
        R = _Runner(S, out, tiling, eng, prog)
        res = _run(R, S, p, epoch_a, epoch_b, method, notes, timings)
        tt = time.perf_counter()
        res.outputs = _write(R, S, res, out, prefix=prefix, plots=plots, provenance=provenance, epoch_a=epoch_a,
                             epoch_b=epoch_b, footprints=S.footprints)
        timings["write_s"] = time.perf_counter() - tt
    res.passes = R.passes
    res.tiles_resumed = R.resumed
    res.summary["wall_s"] = time.perf_counter() - t0
    res.timings = timings
    if not tiling.keep_work:
        remove_work(out)
    prog(1.0, "done")
    return res


def _run(R: _Runner, S: _Setup, p: DEMDiffParams, epoch_a: str, epoch_b: str, method: str, notes: list[str],
         timings: dict) -> TiledDEMDiffResult:
    tt = time.perf_counter()
    loose = replace(p.stable, nmad_factor=p.stable.nmad_factor * p.coreg_stable_factor)
    ccl = stable_overlap(loose)
    # --- co-registration ----------------------------------------------------------------------
    if not p.coregister:
        cells = R.table(_StableDef("valid", exclude=False), None, 0, "table")
        if cells.n_total == 0:
            raise EmptyDataError("no cell is observed in both DEMs (check the observed/survey masks)")
        creg, plan = coregister_cells(_TiledCoregData(R, cells, "coreg"), S.posting,
                                      replace(p.coreg, horizontal=False, vertical=False, tilt=False))
        plan = None
    elif S.user_mask is not None:
        cells = R.table(_StableDef("user", None), None, 0, "table-user")
        if cells.n_total == 0:
            raise EmptyDataError(
                "the stable-terrain mask selects no cell with valid heights in both DEMs (all NaN); check that the "
                "mask covers the DEMs' common area, or omit it to select stable terrain automatically")
        creg, plan = coregister_cells(_TiledCoregData(R, cells, "coreg"), S.posting, p.coreg)
    else:
        cells = R.table(_StableDef("valid"), None, 0, "table-1")
        if cells.n_total == 0:
            raise EmptyDataError("no cell is observed in both DEMs (check the observed/survey masks)")
        c1, plan1 = coregister_cells(_TiledCoregData(R, cells, "coreg-1"), S.posting, p.coreg)
        trusted1 = c1.status == "ok"
        st_plan = plan1 if trusted1 else None
        state0, _info0 = select_stable(_TiledStable(R, st_plan, loose, "stable-1"), loose)
        sd0 = _StableDef("auto", st_plan, state0, loose)
        del cells
        cells = R.table(sd0, st_plan, ccl, "table-2")
        init = c1.fitted_shift_m[:2] if trusted1 else (0.0, 0.0)
        creg, plan = coregister_cells(_TiledCoregData(R, cells, "coreg-2"), S.posting, p.coreg, initial_shift_m=init)
    del cells
    if creg.status != "ok":
        notes.append(creg.summary())
    timings["coreg_s"] = time.perf_counter() - tt
    # --- final stable terrain -----------------------------------------------------------------
    tt = time.perf_counter()
    if S.user_mask is not None:
        sd = _StableDef("user", plan)
    else:
        state, info_auto = select_stable(_TiledStable(R, plan, p.stable, "stable"), p.stable)
        sd = _StableDef("auto", plan, state, p.stable)
    ccs = stable_overlap(p.stable) if sd.kind == "auto" else 0
    et = R.run(_t_errtable, "stable-cells", (S, plan, sd), R.overlap(plan, ccs))
    parts = [s for _, s in et.smalls()]
    n_st = int(sum(s["n"] for s in parts))
    idx = np.concatenate([s["idx"] for s in parts])
    order = np.argsort(idx, kind="stable")
    dh_t = np.concatenate([s["dh"] for s in parts])[order]
    slope_t = np.concatenate([s["slope"] for s in parts])[order].astype(np.float64)
    q_t = (np.concatenate([s["q"] for s in parts])[order].astype(np.float64)
           if p.error.predictor != "none" else None)
    blocks = np.unique(np.concatenate([s["blocks"] for s in parts])) if parts else np.zeros(0)
    bbs = [s["bbox"] for s in parts if s["bbox"] is not None]
    fp_note = ((f"footprints excluded ({int(sum(s['fp_n'] for s in parts))} cells + "
                f"{p.stable.footprint_buffer_cells}-cell buffer)",) if S.footprints is not None else ())
    if sd.kind == "user":
        if n_st == 0:
            raise EmptyDataError(
                "the stable-terrain mask selects no cell with valid heights in both DEMs (all NaN); check that the "
                "mask covers the DEMs' common area, or omit it to select stable terrain automatically")
        info = StableInfo(f"user mask ({S.mask_is})", n_st, 0, float(np.median(dh_t)), nmad(dh_t), 0, fp_note)
    else:
        info = StableInfo(info_auto.source, info_auto.n_cells, info_auto.iterations, info_auto.median_m,
                          info_auto.nmad_m, info_auto.excluded_change_cells, fp_note + info_auto.notes)
    notes.extend(info.notes)
    timings["stable_s"] = time.perf_counter() - tt
    # --- error model, variogram, significance --------------------------------------------------
    tt = time.perf_counter()
    status = "ok"
    em = vg = sig = None
    center = 0.0
    exact = S.fraction >= 1.0
    unc_parts: dict[str, Any] = {}
    if info.n_cells < p.min_stable_cells:
        status = "no_stable_terrain"
        notes.append(f"no usable stable terrain ({info.n_cells} cells, at least {p.min_stable_cells} needed): "
                     "no co-registration shift was invented, and σ and confidence are unknown; give a stable-terrain "
                     "mask (--stable-mask) to test significance")
    else:
        nblk = int(blocks.size)
        if info.n_cells < p.reliable_stable_cells or nblk < p.reliable_stable_blocks:
            status = "uncertainty_indicative"
            notes.append(f"σ learned from only {info.n_cells} stable cells in {nblk} blocks of {p.coreg.block_px} px "
                         f"(reliable from {p.reliable_stable_cells} cells in {p.reliable_stable_blocks} blocks): "
                         "the error model and variogram are indicative only")
        em = fit_error_model(dh_t, np.ones(dh_t.size, bool), slope_t, q_t, p.error)
        sig_t = em.sigma(slope_t, q_t if em.predictor != "none" else None)
        fill = float(math.sqrt(em.coef[0]) * em.scale)
        sig_t = np.where(np.isfinite(sig_t), sig_t, np.where(np.isfinite(dh_t), fill, np.nan)).astype(np.float32)
        m = np.isfinite(dh_t) & np.isfinite(sig_t) & (sig_t > 0)
        med = float(np.median(dh_t[m]))
        absz = np.sort(np.abs((dh_t[m] - med) / sig_t[m].astype(np.float64)))
        if absz.size < 20:
            raise EmptyDataError(f"only {absz.size} stable cells: too few to test significance")
        sig = SignificanceModel(absz, med)
        center = med
        del dh_t, slope_t, q_t, absz, sig_t
        # variogram on the plan's grids
        bb = (min(b[0] for b in bbs), min(b[1] for b in bbs), max(b[2] for b in bbs), max(b[3] for b in bbs))
        vplan = variogram_plan((bb[0], bb[1], bb[2] - bb[0] + 1, bb[3] - bb[1] + 1), S.posting, p.error)
        lags, gam, cnt, zbb = _variogram_tiles(R, S, plan, sd, em, med, vplan, ccs)
        if zbb != vplan.bbox:
            vplan = variogram_plan(zbb, S.posting, p.error)
            lags, gam, cnt, zbb = _variogram_tiles(R, S, plan, sd, em, med, vplan, ccs)
        r0, c0, hh, ww = zbb
        ext = math.hypot(hh * S.posting[1], ww * S.posting[0])
        vg = fit_variogram(lags, gam, cnt, p.error.n_components, max_range_m=ext)
        unc_parts = {"em": em, "vg": vg}
    timings["error_model_s"] = time.perf_counter() - tt
    res = TiledDEMDiffResult({}, {}, creg, info, status, notes, em, vg, sig, exact, S.grid)
    res._plan = plan
    res._sd = sd
    res._ccs = ccs
    res._method = method
    res._unc_parts = unc_parts
    res._epochs = (epoch_a, epoch_b)
    if sig is not None and p.confidence > sig.max_level():
        notes.append(f"{sig.n} stable cells support confidences up to {sig.max_level():.4f} only; "
                     f"nothing can be significant at {p.confidence}")
    return res


def _variogram_tiles(R: _Runner, S: _Setup, plan, sd, em, med, vplan: VariogramPlan, ccs: int):
    r = R.run(_t_zgrids, "variogram", (S, plan, sd, em, med, vplan, S.params.error.clip_z), R.overlap(plan, ccs))
    parts = [s for _, s in r.smalls()]
    bbs = [s["bbox"] for s in parts if s["bbox"] is not None]
    zbb = (min(b[0] for b in bbs), min(b[1] for b in bbs), max(b[2] for b in bbs), max(b[3] for b in bbs))
    zbb = (zbb[0], zbb[1], zbb[2] - zbb[0] + 1, zbb[3] - zbb[1] + 1)
    a0, b0, ah, aw = vplan.bbox

    def assemble(key, shape):
        arr = np.full(shape, np.nan)
        for s in parts:
            pc = s.get(key)
            if pc is not None:
                i, j, blk = pc
                arr[i:i + blk.shape[0], j:j + blk.shape[1]] = blk
        return arr

    if vplan.step == 1:
        lags, gam, cnt = variogram_from_plan(vplan, S.posting, box=assemble("box", (ah, aw)))
    else:
        st_ = vplan.step
        sub = assemble("sub", ((ah + st_ - 1) // st_, (aw + st_ - 1) // st_))
        win = assemble("window", vplan.window[2:])
        lags, gam, cnt = variogram_from_plan(vplan, S.posting, sub=sub, window=win)
    return lags, gam, cnt, zbb


# ------------------------------------------------------------------------------------------
# products
# ------------------------------------------------------------------------------------------
def _write(R: _Runner, S: _Setup, res: TiledDEMDiffResult, out: Path, *, prefix, plots, provenance, epoch_a,
           epoch_b, footprints) -> dict[str, Path]:
    if S.grid.width * S.grid.height <= R.tiling.exact_grid_cells:
        return _write_exact(R, S, res, out, prefix=prefix, plots=plots, provenance=provenance, footprints=footprints)
    return _write_large(R, S, res, out, prefix=prefix, plots=plots, provenance=provenance, footprints=footprints)


def _write_exact(R: _Runner, S: _Setup, res: TiledDEMDiffResult, out: Path, *, prefix, plots, provenance,
                 footprints) -> dict[str, Path]:
    """Small grids: gather the whole grids and finish with the untiled pipeline's own code."""
    from .pipeline import DEMDiffResult, _sign_in_regions, _summary
    from .products import write_demdiff_products
    from .significance import change_sign, significance_map
    from .uncertainty import _window_variance  # noqa: F401  (used through Uncertainty)

    p = S.params
    plan, sd = res._plan, res._sd
    r = R.run(_t_grids, "grids", (S, plan, sd, res.error_model, None), R.overlap(plan, res._ccs))
    dh = r.read("dh64")
    st = r.read("stable").astype(bool)
    A = r.read("a32").astype(np.float64)
    Braw = r.read("b32").astype(np.float64)
    Bc = r.read("bc32").astype(np.float64)
    g = S.grid
    valid = r.read("valid").astype(bool)
    obs = valid & np.isfinite(dh)
    unc = None
    sigma = np.full(g.shape, np.nan, np.float32)
    z = np.full(g.shape, np.nan, np.float32)
    conf = np.full(g.shape, np.nan, np.float32)
    sig_model = res.significance
    if res.error_model is not None:
        su = r.read("sigma_u")
        zz = np.full(g.shape, np.nan)
        m = st & np.isfinite(dh) & np.isfinite(su) & (su > 0)
        zz[m] = np.clip((dh[m] - sig_model.center_m) / su[m].astype(np.float64), -p.error.clip_z, p.error.clip_z)
        w = np.where(np.isfinite(zz), su, 0.0).astype(np.float64)
        k = _k_field(w, res.variogram, S.posting)
        var_sum = float(max(np.sum(w * k), 0.0))
        nst = int(np.isfinite(zz).sum())
        bias = math.sqrt(var_sum) / nst if nst else float("nan")
        neff = float(np.sum(w) ** 2 * res.variogram.total_sill / var_sum) if var_sum > 0 else float("nan")
        unc = Uncertainty(res.error_model, res.variogram, su, (float(S.posting[0]), float(S.posting[1])), bias, neff,
                          nst, k)
        sigma = np.where(obs, unc.sigma_m, np.nan).astype(np.float32)
        unc = unc.with_offset(sig_model.center_m)
        z, conf = significance_map(dh, sigma, sig_model)
    from ..change.regions import change_regions

    if sig_model is not None:
        raw_sign = change_sign(dh, conf, p.confidence, sig_model.center_m)
    elif p.fallback_threshold_m is not None:
        raw_sign = np.where(np.abs(np.nan_to_num(dh)) > p.fallback_threshold_m, np.sign(np.nan_to_num(dh)),
                            0).astype(np.int8)
        res.notes.append(f"changed cells from the fixed threshold |dh| > {p.fallback_threshold_m} m "
                         "(no significance test)")
    else:
        raw_sign = np.zeros(g.shape, np.int8)
    raw_sign = np.where(obs, raw_sign, 0).astype(np.int8)
    cell = float(S.posting[0] * S.posting[1])
    vfn = unc.volume_sigma_fn(cell) if unc is not None else None
    ea, eb = res._epochs
    regions = change_regions(raw_sign, dh, g, confidence=conf if sig_model is not None else None,
                             volume_sigma_fn=vfn, method=res._method, epoch_a=ea, epoch_b=eb,
                             min_cells=p.min_region_cells, cell_area_m2=cell)
    sign = _sign_in_regions(raw_sign, p.min_region_cells)
    sign = np.where(obs, sign, CHANGE_NODATA).astype(np.int8)
    dr = DEMDiffResult(g, S.posting, A.astype(np.float32), Bc.astype(np.float32), dh.astype(np.float32),
                       np.where(valid, Braw - A, np.nan).astype(np.float32), obs, st, res.stable_info, res.coreg, unc,
                       sig_model, sigma, z, conf, sign, regions, ea, eb, p.confidence, res.status, res.notes)
    dr.summary = _summary(dr, Braw, p)
    dr.summary["wall_s"] = time.perf_counter() - R.t0
    res.summary = dr.summary
    res._uncertainty = unc
    return write_demdiff_products(out, dr, footprints=footprints, prefix=prefix, plots=plots,
                                  provenance=provenance)


def _write_large(R: _Runner, S: _Setup, res: TiledDEMDiffResult, out: Path, *, prefix, plots, provenance,
                 footprints) -> dict[str, Path]:
    """Large grids: products tile by tile, correlated sums on a coarse grid, regions merged across seams."""
    raise NotImplementedError
