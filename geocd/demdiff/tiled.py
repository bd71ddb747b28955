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

import os

import hashlib
import math
import time
from dataclasses import dataclass, field, replace
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from .._fft import fftconvolve
from ..errors import ConfigError, EmptyDataError, ProcessingError
from ..geodesy import AOIGrid, ELLIPSOID, normalize_datum_name, vertical_datum_of
from ..progress import Progress, ensure_progress, sub_progress
from ..tiling import RasterProduct, RasterSource, TileGrid, TileOutput, open_engine, remove_work, run_tiled
from ._kernels import shift_margin, shift_points, shift_window, terrain_attributes
from .coreg import CoregPlan, CoregResult, StableCells, coregister_cells
from .pipeline import CHANGE_NODATA, DEMDiffParams
from .products import write_demdiff_products
from .significance import SignificanceModel
from .stable import StableInfo, StableParams, buffered, nmad, select_stable, stable_overlap, stable_state_mask
from ..tiling.params import TilingParams, keep_cells
from .uncertainty import (
    ErrorModel,
    Uncertainty,
    VariogramModel,
    VariogramPlan,
    fit_error_model,
    fit_variogram,
    variogram_from_plan,
    variogram_plan,
)


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
    return TileOutput(
        small={
            "n": _count_core(st, ctx),
            "idx": idx,
            "a": w.a32[rr, cc],
            "b": w.b32[rr, cc],
            "slope": w.terrain["slope_rad"][rr, cc],
            "aspect": w.terrain["aspect_rad"][rr, cc],
        }
    )


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
    return TileOutput(
        small={
            "v": dh[rr, cc],
            "n": _count_core(m_new, ctx),
            "excluded": int(np.count_nonzero((base & ~m_new)[core])),
            "toggled": int(np.count_nonzero((m_new != m_prev)[core])),
        }
    )


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
    bbox = (
        (int(r_all.min() + R0), int(c_all.min() + C0), int(r_all.max() + R0), int(c_all.max() + C0))
        if r_all.size
        else None
    )
    return TileOutput(
        small={
            "n": int(r_all.size),
            "idx": idx,
            "dh": dh[rr, cc],
            "slope": w.slope[rr, cc],
            "q": q[rr, cc] if q is not None else None,
            "blocks": blocks,
            "bbox": bbox,
            "fp_n": _count_core(w.footprint, ctx) if w.footprint is not None else 0,
        }
    )


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
    out["bbox"] = (int(rr.min() + r0), int(cc.min() + c0), int(rr.max() + r0), int(cc.max() + c0)) if rr.size else None

    def piece(win):  # intersection of the core with a window (row0, col0, h, w) of the grid
        a0, b0, ah, aw = win
        i0, j0 = max(a0, r0), max(b0, c0)
        i1, j1 = min(a0 + ah, r0 + h), min(b0 + aw, c0 + wd)
        if i1 <= i0 or j1 <= j0:
            return None
        return (i0 - a0, j0 - b0, z[i0 - R0 : i1 - R0, j0 - C0 : j1 - C0].copy())

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
            blk = z[i_first - R0 : i_last - R0 + 1 : st_, j_first - C0 : j_last - C0 + 1 : st_]
            out["sub"] = ((i_first - a0) // st_, (j_first - b0) // st_, blk.copy())
        else:
            out["sub"] = None
        out["window"] = piece(vplan.window)
    return TileOutput(small=out)


def _t_grids(arrays, ctx):
    """Whole-grid arrays for small grids: what :func:`finish_difference` takes."""
    S, plan, sd = ctx.params
    w = _Win(arrays, ctx, S)
    dh = w.dh(plan)
    st = w.stable(sd) & np.isfinite(dh)
    bc = w.b_moved(plan).astype(np.float32) if plan is not None else w.b32_raw
    out = {"dh64": dh, "stable": st, "a32": w.a32, "b32": w.b32_raw, "valid": w.valid, "bc32": bc, "slope": w.slope}
    if w.q is not None:
        out["q"] = w.q
    return TileOutput(arrays=out, small={"fp_n": _count_core(w.footprint, ctx) if w.footprint is not None else 0})


@dataclass(frozen=True)
class _RegionSigma:
    """Volume σ of a cell set (:meth:`Uncertainty._variance` with the K field as k_local + a coarse part)."""

    vg: VariogramModel
    posting: tuple[float, float]
    bias_sigma_m: float
    n_stable: int
    offset_m: float
    KC: np.ndarray
    block: int
    cell: float

    def var(self, V: float, n: int, cross: float, include_bias: bool = True) -> float:
        var = V
        if include_bias and self.n_stable:
            var += (n * self.bias_sigma_m) ** 2
            var -= 2.0 * n / self.n_stable * cross
            var = max(var, 0.0) + (n * self.offset_m) ** 2
        return max(var, 0.0)

    def window(self, wv: np.ndarray, k_local: np.ndarray, r0: int, c0: int) -> float:
        """σ of Σ dh × cell over the cells where ``wv`` (σ, 0 outside) is set, on a window at (r0, c0)."""
        from .uncertainty import _window_variance

        h, w = wv.shape
        kw = (
            k_local.astype(np.float64)
            + self.KC[np.arange(r0, r0 + h) // self.block][:, np.arange(c0, c0 + w) // self.block]
        )
        V = _window_variance(wv, self.vg, self.posting)
        return math.sqrt(self.var(V, int(np.count_nonzero(wv)), float(np.sum(wv * kw)))) * self.cell


def _tile_region_sigmas(tr, sigma, k_local, ctx, rs: "_RegionSigma") -> None:
    """σ of every region wholly inside the tile's core (not touching its edges: it cannot continue in a
    neighbour), stored as ``vsig`` per label (NaN for the others, done after the merge)."""
    cr0, cc0, h, w = ctx.tile.core
    R0, C0 = ctx.origin
    for s_, st_ in tr.stats.items():
        vs = np.full(st_["n"].size, np.nan)
        for j, (r0, c0, r1, c1) in enumerate(st_["bbox"]):
            if r0 <= cr0 or c0 <= cc0 or r1 >= cr0 + h or c1 >= cc0 + w:
                continue
            m = tr.labels[r0 - cr0 : r1 - cr0, c0 - cc0 : c1 - cc0] == s_ * (j + 1)
            sg = sigma[r0 - R0 : r1 - R0, c0 - C0 : c1 - C0].astype(np.float64)
            m &= np.isfinite(sg)
            vs[j] = rs.window(np.where(m, sg, 0.0), k_local[r0 - R0 : r1 - R0, c0 - C0 : c1 - C0], int(r0), int(c0))
        st_["vsig"] = vs


def _t_products(arrays, ctx):
    """Per-cell products and the tile's partial sums (large grids)."""
    S, plan, sd, em, sig, level, center, split, fitted_plan, rsig, rtest = ctx.params
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
        conf = (100.0 * conf).astype(np.float32)
        raw = change_sign(dh, conf / 100.0, level / 100.0, center)
    else:
        z = np.full(dh.shape, np.nan, np.float32)
        conf = np.full(dh.shape, np.nan, np.float32)
        if p.fallback_threshold_m is not None:
            raw = np.where(np.abs(np.nan_to_num(dh)) > p.fallback_threshold_m, np.sign(np.nan_to_num(dh)), 0).astype(
                np.int8
            )
        else:
            raw = np.zeros(dh.shape, np.int8)
    raw = np.where(obs, raw, 0).astype(np.int8)
    from .pipeline import _sign_in_regions

    sign = np.where(obs, _sign_in_regions(raw, p.min_region_cells), CHANGE_NODATA).astype(np.int8)
    if rtest is not None and "drop" in rtest:
        # the region test's verdict from the first products pass: its regions' cells, tile by tile
        sign = np.where(_dropped_cells(arrays["labels_first"], ctx.origin, *rtest["drop"]), 0, sign).astype(np.int8)
    conf_pct = np.where(np.isfinite(conf), conf, np.nan).astype(np.float32)
    dh32 = dh.astype(np.float32)
    core = ctx.core
    dhc = dh32[core].astype(np.float64)
    sc = sign[core]
    obc = obs[core]
    stc = st[core]
    ch = (sc == 1) | (sc == -1)
    from ..tiling.regions import tile_regions

    if rtest is not None and "alpha" in rtest:
        # first pass of the region test: each region's cluster mass, no polygons
        from ..consistency import cluster_evidence

        ev = cluster_evidence(1.0 - conf[core].astype(np.float64) / 100.0, rtest["alpha"])
        tr = tile_regions(sc, dh[core], ctx.tile, S.grid, polygons=False, sums={"mass": ev})
        labels = tr.labels
        tr.labels = None  # a tile array, not a small result
        return TileOutput(arrays={"labels": labels}, small={"regions": tr})
    small: dict[str, Any] = {
        "n_obs": int(obc.sum()),
        "n_stable": int(stc.sum()),
        "n_changed": int(ch.sum()),
        "n_raised": int((sc == 1).sum()),
        "n_lowered": int((sc == -1).sum()),
        "sum_changed": float(np.nansum(dhc[ch])),
        "sum_raised": float(np.nansum(dhc[sc == 1])),
        "sum_lowered": float(np.nansum(dhc[sc == -1])),
        "sum_obs": float(np.nansum(dhc[obc])),
        # degenerate stable terrain: identical raw heights, the largest |A| (float32 rounding floor)
        "n_identical": int(np.count_nonzero(stc & (w.a32 == w.b32_raw)[core])),
        "hmax_stable": float(np.max(np.abs(w.A[core][stc]))) if stc.any() else 0.0,
    }
    idx, rr, cc = _core_cells(st, ctx, S)
    small["stable_dh"] = dh32[rr, cc]
    idx, rr, cc = _core_cells(np.isfinite(dh32), ctx, S)
    small["abs_dh"] = np.abs(dh32[rr, cc])
    if fitted_plan is not None and ch.any():
        bf = fitted_plan.apply(w.b32_raw.astype(np.float64), S.posting, ctx.origin, S.shape).astype(np.float64)
        d = np.where(obs, bf - w.A, np.nan)[core]
        small["sum_changed_fitted"] = float(np.nansum(d[ch]))
    # block sums of σ for correlated sums on the coarse grid
    if split is not None and em is not None:
        # correlated sums: block sums (long range), Σ σ² (nugget), exact short-range sums on the window
        sgw = np.where(np.isfinite(sigma), sigma, 0.0).astype(np.float64)
        chw = (sign == 1) | (sign == -1)
        w_obs = np.where(obs, sgw, 0.0)
        w_ch = np.where(chw, sgw, 0.0)
        w_st = np.where(st & (sgw > 0), sgw, 0.0)
        k_st = _short_conv(w_st, split, S.posting)[core]
        small["blocks"] = _block_sums(ctx, split.block, {"obs": w_obs[core], "changed": w_ch[core]})
        small["q_obs"] = float(np.sum(w_obs[core] ** 2))
        small["q_changed"] = float(np.sum(w_ch[core] ** 2))
        small["q_obs_st"] = float(np.sum(w_obs[core] * w_st[core]))
        small["q_changed_st"] = float(np.sum(w_ch[core] * w_st[core]))
        small["v_short_obs"] = float(np.sum(w_obs[core] * _short_conv(w_obs, split, S.posting)[core]))
        small["v_short_changed"] = float(np.sum(w_ch[core] * _short_conv(w_ch, split, S.posting)[core]))
        small["x_short_obs"] = float(np.sum(w_obs[core] * k_st))
        small["x_short_changed"] = float(np.sum(w_ch[core] * k_st))
    # changed regions of this tile, to be merged across seams
    from ..tiling.regions import tile_regions

    tr = tile_regions(sc, dh[core], ctx.tile, S.grid, sigma=sigma[core], confidence=conf[core])
    if rsig is not None and "k_local" in arrays:
        _tile_region_sigmas(tr, sigma, arrays["k_local"], ctx, rsig)
    labels = tr.labels
    tr.labels = None
    small["regions"] = tr
    out = {
        "dh_m": dh32,
        "confidence_pct": conf_pct,
        "sigma_m": sigma,
        "z": z.astype(np.float32),
        "sign": sign,
        "labels": labels,
    }
    if S.footprints is not None:
        out.update(
            a32=w.a32,
            bc32=w.b_moved(plan).astype(np.float32) if plan is not None else w.b32_raw,
            conf=conf.astype(np.float32),
        )
    return TileOutput(arrays=out, small=small)


def _dropped_cells(labels: np.ndarray, origin: tuple[int, int], tile_shape: tuple[int, int], table: dict) -> np.ndarray:
    """Cells of dropped regions on a window of tile-local labels (+k raised, −k lowered).

    ``table[(i, j)] = (drop_raised, drop_lowered)``: bool per local label (index 0 unused)."""
    lab = np.asarray(labels)
    out = np.zeros(lab.shape, bool)
    R0, C0 = origin
    h, w = lab.shape
    th, tw = tile_shape
    for i in range(R0 // th, (R0 + h - 1) // th + 1):
        r0, r1 = max(i * th, R0) - R0, min((i + 1) * th, R0 + h) - R0
        for j in range(C0 // tw, (C0 + w - 1) // tw + 1):
            t = table.get((i, j))
            if t is None:
                continue
            c0, c1 = max(j * tw, C0) - C0, min((j + 1) * tw, C0 + w) - C0
            sub = lab[r0:r1, c0:c1].astype(np.int64)
            # labels beyond a table's end are kept: index a trailing False there
            dp, dn = (np.append(x, False) for x in t)
            out[r0:r1, c0:c1] = np.where(
                sub > 0, dp[np.clip(sub, 0, dp.size - 1)], np.where(sub < 0, dn[np.clip(-sub, 0, dn.size - 1)], False)
            )
    return out


@dataclass(frozen=True)
class CovSplit:
    """The error covariance split for correlated sums on tiles.

    ``nugget`` pairs a cell with itself (exact from Σ σ²); ``short`` (the spherical
    components whose range fits in ``radius`` cells) is summed exactly on tiles with that
    overlap; ``long`` (the others) on the coarse grid of ``block``-cell blocks, where the
    block is small against its ranges.
    """

    nugget: float
    short: VariogramModel | None
    long: VariogramModel | None
    radius: int
    block: int

    @classmethod
    def of(cls, model: VariogramModel, posting_xy_m: tuple[float, float], block: int, max_radius: int) -> "CovSplit":
        pm = min(posting_xy_m)
        sr = [(r, s) for r, s in zip(model.ranges_m, model.sills) if r / pm <= max_radius]
        lr = [(r, s) for r, s in zip(model.ranges_m, model.sills) if r / pm > max_radius]
        short = VariogramModel(0.0, tuple(r for r, _ in sr), tuple(s for _, s in sr)) if sr else None
        long = VariogramModel(0.0, tuple(r for r, _ in lr), tuple(s for _, s in lr)) if lr else None
        radius = int(math.ceil(max(r for r, _ in sr) / pm)) if sr else 0
        return cls(float(model.nugget), short, long, radius, int(block))

    def short_kernel(self, posting_xy_m: tuple[float, float]) -> np.ndarray:
        from .uncertainty import _lag_distance

        R = self.radius
        d = _lag_distance((2 * R + 1, 2 * R + 1), posting_xy_m)
        # the continuous part: C(0) = Σ sills (the nugget is counted apart)
        return self.short.total_sill - self.short.semivariance(d) if self.short is not None else np.zeros((1, 1))


def _short_conv(a: np.ndarray, split: CovSplit, posting_xy_m) -> np.ndarray:
    """Σ_j a_j C_short(|x − x_j|) on a window (exact where the window holds the radius around x)."""
    if split.short is None:
        return np.zeros(a.shape)
    return fftconvolve(a, split.short_kernel(posting_xy_m), "same")


def _t_blocks(arrays, ctx):
    """The stable σ: block sums (coarse grid), Σ σ², its short-range sums and K field (exact on tiles)."""
    S, plan, sd, em, split = ctx.params
    w = _Win(arrays, ctx, S)
    dh = w.dh(plan)
    st = w.stable(sd) & np.isfinite(dh)
    sigma = _sigma_window(w, em, dh)
    m = st & np.isfinite(sigma) & (sigma > 0)
    wS = np.where(m, sigma, 0.0).astype(np.float64)
    kS = _short_conv(wS, split, S.posting)
    core = ctx.core
    ws = wS[core]
    # the local K field: short-range part + the nugget on the stable cells themselves
    k_local = (kS + split.nugget * wS)[core].astype(np.float32)
    return TileOutput(
        arrays={"k_local": k_local},
        small={
            "blocks": _block_sums(ctx, split.block, {"w": ws}),
            "n": _count_core(m, ctx),
            "q": float(np.sum(ws * ws)),
            "v_short": float(np.sum(ws * kS[core])),
        },
    )


def _block_sums(ctx, block: int, fields: dict[str, np.ndarray]) -> dict:
    """Sums of each field (on the core) over the ``block``-cell blocks of the whole grid that the core touches."""
    r0, c0, h, w = ctx.tile.core
    br = np.arange(r0, r0 + h) // block
    bc = np.arange(c0, c0 + w) // block
    rs = np.r_[0, np.nonzero(np.diff(br))[0] + 1]
    cs = np.r_[0, np.nonzero(np.diff(bc))[0] + 1]
    out = {"rows": br[rs], "cols": bc[cs]}
    for k, a in fields.items():
        out[k] = np.add.reduceat(np.add.reduceat(a, rs, axis=0), cs, axis=1)
    return out


def _coarse(parts: list[dict], key: str, shape: tuple[int, int]) -> np.ndarray:
    out = np.zeros(shape)
    for b in parts:
        out[np.ix_(b["rows"], b["cols"])] += b[key]
    return out


# ------------------------------------------------------------------------------------------
# coarse correlated sums (large grids)
# ------------------------------------------------------------------------------------------
def block_covariance(
    model: VariogramModel, block: int, posting_xy_m: tuple[float, float], shape: tuple[int, int], near: int = 3
) -> np.ndarray:
    """Average covariance between the cells of two ``block``² blocks, for every block lag, without the nugget.

    Returns the (2H−1, 2W−1) kernel over block lags (H, W = ``shape`` in blocks), centred,
    of the model's continuous part (its spherical components). Lags within ``near`` blocks
    average it over the cell pairs (a triangle-weighted sum over the within-block offsets:
    exact for uniform σ in a block); farther lags use its value at the blocks' centre
    distance (smooth there). The nugget pairs a cell only with itself: it is added as
    ``nugget × Σ σ²`` (:func:`coarse_sum_variance`), so partly filled blocks keep it exact.
    """
    from .uncertainty import _lag_distance

    H, W = shape

    def cont(d):
        return model.covariance(d) - np.where(np.asarray(d) == 0, model.nugget, 0.0)

    pxb, pyb = posting_xy_m[0] * block, posting_xy_m[1] * block
    cov = cont(_lag_distance((2 * H - 1, 2 * W - 1), (pxb, pyb)))
    d = np.arange(-(block - 1), block)
    t = (block - np.abs(d)) / float(block * block)
    tw = t[:, None] * t[None, :]
    for i in range(-near, near + 1):
        for j in range(-near, near + 1):
            if abs(i) >= H or abs(j) >= W:
                continue
            dy = (i * block + d)[:, None] * posting_xy_m[1]
            dx = (j * block + d)[None, :] * posting_xy_m[0]
            cov[H - 1 + i, W - 1 + j] = float(np.sum(tw * cont(np.hypot(dy, dx))))
    return cov


def coarse_sum_variance(S: np.ndarray, Q: float, model: VariogramModel, kernel: np.ndarray) -> float:
    """Var(Σ dh) over a cell set from its block sums of σ (``S``) and its Σ σ² (``Q``):
    ``nugget·Q + Σ_IJ S_I S_J C̄(I − J)`` with C̄ = :func:`block_covariance`."""
    return float(max(model.nugget * Q + np.sum(S * _coarse_conv(S, kernel)), 0.0))


def _coarse_conv(a: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    return fftconvolve(a, kernel, "same")


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
    warnings: list[str] = field(default_factory=list)
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

    def run(self, func, stage: str, params, overlap: int, products=None, inputs=None):
        self.passes += 1
        f0 = min(self.passes - 1, self.est_passes - 1) / self.est_passes
        f1 = min(self.passes, self.est_passes) / self.est_passes
        r = run_tiled(
            func,
            self.tg.with_overlap(overlap),
            {**self.sources, **(inputs or {})},
            params=params,
            out=self.out,
            stage=f"demdiff-{self.passes:02d}-{stage}",
            key=self.S.ident,
            products=products,
            scheduler=self.eng,
            progress=sub_progress(self.prog, 0.02 + 0.9 * f0, 0.02 + 0.9 * f1, f"{stage}: "),
        )
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

        return StableCells(
            idx // W,
            idx % W,
            cat("a", np.float64),
            cat("b", np.float64),
            cat("slope", np.float64),
            cat("aspect", np.float64),
            self.S.shape,
            int(sum(s["n"] for s in parts)),
        )


class _TiledCoregData:
    """:func:`coregister_cells`' access to tiles: B at the fit cells from gathered patches."""

    def __init__(self, runner: _Runner, cells: StableCells, stage: str):
        self.runner = runner
        self.cells = cells
        self.stage = stage
        self._patch = None  # (idx positions, centre offset, patches, pr, pc)

    def _gather_patches(self, idx: np.ndarray, orow: int, ocol: int) -> None:
        R = self.runner
        M = R.tiling.patch_radius
        W = R.S.grid.width
        lin = self.cells.rows[idx] * W + self.cells.cols[idx]
        r = R.run(_t_patches, f"{self.stage}-patches", (R.S, lin, (orow, ocol), M), M + max(abs(orow), abs(ocol)) + 1)
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
        v, ok = shift_points(
            self._patch[2], self._patch[3], self._patch[4], rows, cols, self.cells.shape, dcol, drow, method
        )
        if not ok:
            self._gather_patches(idx, *centre)
            v, ok = shift_points(
                self._patch[2], self._patch[3], self._patch[4], rows, cols, self.cells.shape, dcol, drow, method
            )
            if not ok:
                raise ProcessingError("co-registration: patches too small for the shift (raise patch_radius)")
        return v

    def shifted_b(self, dcol: float, drow: float) -> np.ndarray:
        R = self.runner
        W = R.S.grid.width
        lin = self.cells.rows * W + self.cells.cols
        r = R.run(
            _t_shifted,
            f"{self.stage}-shifted",
            (R.S, lin, dcol, drow),
            shift_margin(dcol, drow, R.S.params.coreg.resampling),
        )
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
        r = self.R.run(
            _t_stable, f"{self.stage}-{self.k}", (self.R.S, self.plan, self.params, self.prev, state, False), self._ov()
        )
        self.prev = state
        parts = [s for _, s in r.smalls()]
        return (
            np.concatenate([s["v"] for s in parts]),
            int(sum(s["n"] for s in parts)),
            int(sum(s["excluded"] for s in parts)),
            int(sum(s["toggled"] for s in parts)),
        )


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


def _setup(
    path_a,
    path_b,
    *,
    datum_a,
    datum_b,
    params: DEMDiffParams,
    stable_mask,
    mask_is,
    footprints,
    tiling: TilingParams,
    base=None,
    nodata: float | None = None,
) -> tuple[_Setup, list[str]]:
    from ..errors import VerticalDatumError
    from ..io.raster import _open, check_dem_file
    from .align import crop_to_overlap, metric_posting

    notes: list[str] = []
    # the checks read_dem makes in memory, made here before any tile is read (the same errors)
    for p_ in (path_a, path_b, base):
        if isinstance(p_, (str, os.PathLike)) and Path(p_).suffix.lower() != ".e00":
            check_dem_file(p_, nodata=nodata)
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
            f"vertical_datum= in Python); if both are in the same datum, declare it for both"
        )
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
    src_a = RasterSource(str(path_a), dem=True, resampling=params.resampling, nodata=nodata)
    src_b = RasterSource(str(path_b), dem=True, resampling=params.resampling, nodata=nodata)
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
    ident = {
        "a": src_a.identity(),
        "b": src_b.identity(),
        "datums": [conv_a, conv_b],
        "params": params,
        "grid": target.to_dict(),
        "fp": _gdf_key(fp),
        "mask": _gdf_key(um),
        "mask_is": mask_is,
        "frac": frac,
        "patch": tiling.patch_radius,
        "exact": tiling.exact_grid_cells,
        "coarse": tiling.coarse_cells,
        "base": base_src.identity() if base_src is not None else None,
    }
    from ..tiling import make_key

    S = _Setup(
        target,
        metric_posting(target),
        src_a,
        src_b,
        conv_a,
        conv_b,
        params,
        fp,
        um,
        mask_is,
        frac,
        make_key(ident),
        base_src,
    )
    return S, notes


def _base_source(base, grid: AOIGrid, datum_a: str | None):
    """The base DEM on the grid: a window source for GDAL rasters, an in-memory array for .e00 grids."""
    from ..errors import VerticalDatumError
    from ..io.raster import DEM
    from ..tiling import ArraySource
    from .align import _resample

    if isinstance(base, DEM) or Path(str(base)).suffix.lower() == ".e00":
        if not isinstance(base, DEM):
            from ..io.e00 import read_e00_dem

            base = read_e00_dem(base, vertical_datum=datum_a)
        if normalize_datum_name(base.vertical_datum) != datum_a:
            raise VerticalDatumError(
                f"the base DEM's vertical datum ({base.vertical_datum}) is not DEM A's "
                f"({datum_a}); declare it or convert the base first"
            )
        return ArraySource(_resample(base, grid, "bilinear").astype(np.float32))
    with rasterio_open(base) as ds:
        vb = vertical_datum_of(ds.crs)
    if vb is not None and datum_a is not None and normalize_datum_name(vb) != datum_a:
        raise VerticalDatumError(f"the base DEM's vertical datum ({vb}) is not DEM A's ({datum_a}); convert it first")
    return RasterSource(str(base), dem=True, resampling="bilinear")


def rasterio_open(path):
    from ..io.raster import _open

    return _open(path)


def dem_difference_tiled(
    dem_a,
    dem_b,
    out_dir,
    *,
    params: DEMDiffParams = DEMDiffParams(),
    tiling: TilingParams = TilingParams(),
    stable_mask: Any = None,
    mask_is: str = "stable",
    footprints: Any = None,
    epoch_a: str = "A",
    epoch_b: str = "B",
    datum_a: str | None = None,
    datum_b: str | None = None,
    base: Any = None,
    method: str = "demdiff",
    prefix: str = "demdiff",
    plots: bool = True,
    provenance: dict | None = None,
    progress: Progress | None = None,
    nodata: float | None = None,
) -> TiledDEMDiffResult:
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
    nodata : the DEMs' nodata value where the files do not declare it (``geocd demdiff --nodata``)

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
    S, notes = _setup(
        dem_a,
        dem_b,
        datum_a=datum_a,
        datum_b=datum_b,
        params=p,
        stable_mask=stable_mask,
        mask_is=mask_is,
        footprints=footprints,
        tiling=tiling,
        base=base,
        nodata=nodata,
    )
    g = S.grid
    timings: dict[str, float] = {}
    prog(0.01, f"{g.height}×{g.width} cells in tiles of {tiling.tile_size}")
    with open_engine(tiling.scheduler, n_workers=tiling.n_workers, memory_limit=tiling.memory_limit) as eng:
        R = _Runner(S, out, tiling, eng, prog)
        st = _coregister_and_select(R, S, p, notes, timings, (epoch_a, epoch_b), method)
        tt = time.perf_counter()
        if g.width * g.height <= tiling.exact_grid_cells:
            dr = _finish_exact(R, S, st, notes)
            dr.summary["wall_s"] = time.perf_counter() - t0
            timings["model_s"] = time.perf_counter() - tt
            tt = time.perf_counter()
            outputs = write_demdiff_products(
                out, dr, footprints=S.footprints, prefix=prefix, plots=plots, provenance=provenance
            )
            u = dr.uncertainty
            res = TiledDEMDiffResult(
                outputs,
                dr.summary,
                dr.coreg,
                dr.stable_info,
                dr.status,
                dr.notes,
                u.error_model if u else None,
                u.variogram if u else None,
                dr.significance,
                S.fraction >= 1.0,
                g,
                warnings=dr.warnings,
            )
        else:
            model = _model_large(R, S, st, notes)
            timings["model_s"] = time.perf_counter() - tt
            tt = time.perf_counter()
            res = _write_large(R, S, st, model, out, notes, prefix=prefix, plots=plots, provenance=provenance)
        timings["write_s"] = time.perf_counter() - tt
    res.passes = R.passes
    res.tiles_resumed = R.resumed
    res.summary.setdefault("wall_s", time.perf_counter() - t0)
    res.timings = timings
    if not tiling.keep_work:
        remove_work(out)
    prog(1.0, "done")
    return res


@dataclass
class _State:
    """Where the passes stand after co-registration and the final stable terrain."""

    creg: CoregResult
    plan: CoregPlan | None
    sd: _StableDef
    ccs: int
    info_auto: StableInfo | None
    epochs: tuple[str, str]
    method: str


def _coregister_and_select(
    R: _Runner, S: _Setup, p: DEMDiffParams, notes: list[str], timings: dict, epochs, method
) -> _State:
    """:func:`dem_difference`'s co-registration and final stable terrain, pass by pass."""
    tt = time.perf_counter()
    loose = replace(p.stable, nmad_factor=p.stable.nmad_factor * p.coreg_stable_factor)
    ccl = stable_overlap(loose)
    if not p.coregister:
        cells = R.table(_StableDef("valid", exclude=False), None, 0, "table")
        if cells.n_total == 0:
            raise EmptyDataError("no cell is observed in both DEMs (check the observed/survey masks)")
        creg, plan = coregister_cells(
            _TiledCoregData(R, cells, "coreg"),
            S.posting,
            replace(p.coreg, horizontal=False, vertical=False, tilt=False),
        )
        plan = None
    elif S.user_mask is not None:
        cells = R.table(_StableDef("user", None), None, 0, "table-user")
        if cells.n_total == 0:
            raise EmptyDataError(
                "the stable-terrain mask selects no cell with valid heights in both DEMs (all NaN); check that the "
                "mask covers the DEMs' common area, or omit it to select stable terrain automatically"
            )
        creg, plan = coregister_cells(_TiledCoregData(R, cells, "coreg"), S.posting, p.coreg)
    else:
        cells = R.table(_StableDef("valid"), None, 0, "table-1")
        if cells.n_total == 0:
            raise EmptyDataError("no cell is observed in both DEMs (check the observed/survey masks)")
        c1, plan1 = coregister_cells(_TiledCoregData(R, cells, "coreg-1"), S.posting, p.coreg)
        trusted1 = c1.status == "ok"
        st_plan = plan1 if trusted1 else None
        state0, _ = select_stable(_TiledStable(R, st_plan, loose, "stable-1"), loose)
        del cells
        cells = R.table(_StableDef("auto", st_plan, state0, loose), st_plan, ccl, "table-2")
        init = c1.fitted_shift_m[:2] if trusted1 else (0.0, 0.0)
        creg, plan = coregister_cells(_TiledCoregData(R, cells, "coreg-2"), S.posting, p.coreg, initial_shift_m=init)
    del cells
    if creg.status != "ok":
        notes.append(creg.summary())
    timings["coreg_s"] = time.perf_counter() - tt
    tt = time.perf_counter()
    info_auto = None
    if S.user_mask is not None:
        sd = _StableDef("user", plan)
    else:
        state, info_auto = select_stable(_TiledStable(R, plan, p.stable, "stable"), p.stable)
        sd = _StableDef("auto", plan, state, p.stable)
    timings["stable_s"] = time.perf_counter() - tt
    return _State(creg, plan, sd, stable_overlap(p.stable) if sd.kind == "auto" else 0, info_auto, epochs, method)


def _stable_info(S: _Setup, st: _State, n_st: int, dh_st: np.ndarray, fp_cells: int) -> StableInfo:
    """The StableInfo :func:`stable_terrain` reports (user mask: from the stable cells' dh)."""
    p = S.params
    fp_note = (
        (f"footprints excluded ({fp_cells} cells + {p.stable.footprint_buffer_cells}-cell buffer)",)
        if S.footprints is not None
        else ()
    )
    if st.sd.kind == "user":
        if n_st == 0:
            raise EmptyDataError(
                "the stable-terrain mask selects no cell with valid heights in both DEMs (all NaN); check that the "
                "mask covers the DEMs' common area, or omit it to select stable terrain automatically"
            )
        return StableInfo(f"user mask ({S.mask_is})", n_st, 0, float(np.median(dh_st)), nmad(dh_st), 0, fp_note)
    i = st.info_auto
    return StableInfo(
        i.source, i.n_cells, i.iterations, i.median_m, i.nmad_m, i.excluded_change_cells, fp_note + i.notes
    )


def _finish_exact(R: _Runner, S: _Setup, st: _State, notes: list[str]):
    """Small grids: gather the whole grids and finish with the untiled pipeline's own code."""
    from .pipeline import finish_difference

    p = S.params
    r = R.run(_t_grids, "grids", (S, st.plan, st.sd), R.overlap(st.plan, st.ccs))
    dh = r.read("dh64")
    stable = r.read("stable").astype(bool)
    valid = r.read("valid").astype(bool)
    A = r.read("a32").astype(np.float64)
    Braw = r.read("b32").astype(np.float64)
    Bc = r.read("bc32").astype(np.float64)
    slope = r.read("slope")
    q = r.read("q") if p.error.predictor != "none" else None
    fp_cells = int(sum(s_["fp_n"] for _, s_ in r.smalls()))
    obs = valid & np.isfinite(dh)
    info = _stable_info(S, st, int(stable.sum()), dh[stable], fp_cells)
    dh_raw = np.where(valid, Braw - A, np.nan)
    ea, eb = st.epochs
    return finish_difference(
        S.grid,
        S.posting,
        A,
        Braw,
        Bc,
        dh,
        dh_raw,
        obs,
        stable,
        info,
        st.creg,
        slope,
        q,
        notes,
        p,
        epoch_a=ea,
        epoch_b=eb,
        method=st.method,
    )


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
                arr[i : i + blk.shape[0], j : j + blk.shape[1]] = blk
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
@dataclass
class _Model:
    """The whole-scene models of a large grid (from tile reductions)."""

    info: StableInfo
    status: str
    em: ErrorModel | None = None
    vg: VariogramModel | None = None
    sig: SignificanceModel | None = None
    warnings: list[str] = field(default_factory=list)
    degenerate: dict = field(default_factory=dict)


def _model_large(R: _Runner, S: _Setup, st: _State, notes: list[str]) -> _Model:
    """Error model, significance and variogram of a large grid: :func:`finish_difference`'s steps on
    the stable cells gathered from the tiles (a fixed subsample beyond ``sample_cells``)."""
    p = S.params
    plan, sd = st.plan, st.sd
    et = R.run(_t_errtable, "stable-cells", (S, plan, sd), R.overlap(plan, st.ccs))
    parts = [s_ for _, s_ in et.smalls()]
    n_st = int(sum(s_["n"] for s_ in parts))
    idx = np.concatenate([s_["idx"] for s_ in parts])
    order = np.argsort(idx, kind="stable")
    dh_t = np.concatenate([s_["dh"] for s_ in parts])[order]
    slope_t = np.concatenate([s_["slope"] for s_ in parts])[order].astype(np.float64)
    q_t = np.concatenate([s_["q"] for s_ in parts])[order].astype(np.float64) if p.error.predictor != "none" else None
    blocks = np.unique(np.concatenate([s_["blocks"] for s_ in parts])) if parts else np.zeros(0)
    bbs = [s_["bbox"] for s_ in parts if s_["bbox"] is not None]
    info = _stable_info(S, st, n_st, dh_t, int(sum(s_["fp_n"] for s_ in parts)))
    notes.extend(info.notes)
    m = _Model(info, "ok")
    if info.n_cells < p.min_stable_cells:
        m.status = "no_stable_terrain"
        notes.append(
            f"no usable stable terrain ({info.n_cells} cells, at least {p.min_stable_cells} needed): "
            "no co-registration shift was invented, and σ and confidence are unknown; give a stable-terrain "
            "mask (--stable-mask) to test significance"
        )
        return m
    nblk = int(blocks.size)
    if info.n_cells < p.reliable_stable_cells or nblk < p.reliable_stable_blocks:
        m.status = "uncertainty_indicative"
        notes.append(
            f"σ learned from only {info.n_cells} stable cells in {nblk} blocks of {p.coreg.block_px} px "
            f"(reliable from {p.reliable_stable_cells} cells in {p.reliable_stable_blocks} blocks): "
            "the error model and variogram are indicative only"
        )
    em = fit_error_model(dh_t, np.ones(dh_t.size, bool), slope_t, q_t, p.error)
    sig_t = em.sigma(slope_t, q_t if em.predictor != "none" else None)
    fill = float(math.sqrt(em.coef[0]) * em.scale)
    sig_t = np.where(np.isfinite(sig_t), sig_t, np.where(np.isfinite(dh_t), fill, np.nan)).astype(np.float32)
    ok = np.isfinite(dh_t) & np.isfinite(sig_t) & (sig_t > 0)
    if ok.sum() < 20:
        raise EmptyDataError(f"only {int(ok.sum())} stable cells: too few to test significance")
    med = float(np.median(dh_t[ok]))
    sig = SignificanceModel(np.sort(np.abs((dh_t[ok] - med) / sig_t[ok].astype(np.float64))), med)
    del dh_t, slope_t, q_t, sig_t
    bb = (min(b[0] for b in bbs), min(b[1] for b in bbs), max(b[2] for b in bbs), max(b[3] for b in bbs))
    vplan = variogram_plan((bb[0], bb[1], bb[2] - bb[0] + 1, bb[3] - bb[1] + 1), S.posting, p.error)
    lags, gam, cnt, zbb = _variogram_tiles(R, S, plan, sd, em, med, vplan, st.ccs)
    if zbb != vplan.bbox:
        vplan = variogram_plan(zbb, S.posting, p.error)
        lags, gam, cnt, zbb = _variogram_tiles(R, S, plan, sd, em, med, vplan, st.ccs)
    ext = math.hypot(zbb[2] * S.posting[1], zbb[3] * S.posting[0])
    m.em, m.sig = em, sig
    m.vg = fit_variogram(lags, gam, cnt, p.error.n_components, max_range_m=ext)
    if p.confidence > 100.0 * sig.max_level():
        notes.append(
            f"{sig.n} stable cells support confidences up to {100 * sig.max_level():.2f}% "
            f"only; nothing can be significant at {p.confidence:g}%"
        )
    return m


def _write_large(
    R: _Runner, S: _Setup, st: _State, model: _Model, out: Path, notes: list[str], *, prefix, plots, provenance
) -> TiledDEMDiffResult:
    """Large grids: products tile by tile, correlated sums on a coarse grid, regions merged across seams."""
    import json as _json

    from ..change.styles import write_raster_style
    from ..io.vector import qml_for, write_gpkg
    from ..tiling.regions import merge_regions, regions_layer_batches
    from .pipeline import DEMDiffResult
    from .products import _clean, _jsonable, dh_qml, nice_limit, significance_qml, tables, write_json

    p = S.params
    g = S.grid
    H, W = g.shape
    post = S.posting
    cell = float(post[0] * post[1])
    plan, sd = st.plan, st.sd
    em, vg, sig = model.em, model.vg, model.sig
    ea, eb = st.epochs
    footprints = S.footprints
    status = model.status
    block = max(1, int(math.ceil(math.sqrt(H * W / R.tiling.coarse_cells))))
    cshape = (-(-H // block), -(-W // block))
    unc = split = None
    KC = Cb = Cfull = None
    if em is not None:
        split = CovSplit.of(vg, post, block, max_radius=min(256, R.tiling.tile_size // 4))
        rb = R.run(_t_blocks, "stable-blocks", (S, plan, sd, em, split), R.overlap(plan, st.ccs + split.radius))
        parts = [s_ for _, s_ in rb.smalls()]
        Wc = _coarse([s_["blocks"] for s_ in parts], "w", cshape)
        nst = int(sum(s_["n"] for s_ in parts))
        Qst = float(sum(s_["q"] for s_ in parts))
        vsh = float(sum(s_["v_short"] for s_ in parts))
        Cb = block_covariance(split.long, block, post, cshape) if split.long is not None else None
        Cfull = block_covariance(replace(vg, nugget=0.0), block, post, cshape)
        # K(x) = Σ_{j∈S} σ_j C(d): nugget + short range exact per tile (k_local), long range per block (KC)
        KC = _coarse_conv(Wc, Cb) if Cb is not None else np.zeros(cshape)
        var_sum = float(max(split.nugget * Qst + vsh + np.sum(Wc * KC), 0.0))
        bias = math.sqrt(var_sum) / nst if nst else float("nan")
        neff = float(np.sum(Wc) ** 2 * vg.total_sill / var_sum) if var_sum > 0 else float("nan")
        unc = Uncertainty(em, vg, None, (float(post[0]), float(post[1])), bias, neff, nst, None)
        unc = unc.with_offset(sig.center_m)
        kstore = rb.store

    def long_sum(Sx: np.ndarray) -> float:
        return float(np.sum(Sx * _coarse_conv(Sx, Cb))) if Cb is not None else 0.0

    c = st.creg
    fe, fn, fz = c.fitted_shift_m
    fitted_plan = (
        CoregPlan((fe / post[0], -fn / post[1]), fz, None, p.coreg.resampling)
        if (fe or fn) and c.applied in ("vertical", "none")
        else None
    )
    ov = R.overlap(plan, max(st.ccs, p.min_region_cells - 1) + (split.radius if split is not None else 0))
    if fitted_plan is not None:
        ov = max(ov, R.overlap(fitted_plan, 0))
    tags = {
        "method": "demdiff",
        "epoch_a": ea,
        "epoch_b": eb,
        "units": "m",
        "confidence_level_pct": f"{p.confidence:g}",
        "coreg": c.summary(),
    }
    if provenance:
        tags["provenance"] = _json.dumps(_clean(provenance), default=_jsonable)
    products = {
        "dh": RasterProduct(str(out / f"{prefix}_dh.tif"), ("dh_m",), tags=tags),
        "significance": RasterProduct(
            str(out / f"{prefix}_significance.tif"), ("confidence_pct", "sigma_m", "z"), tags=tags
        ),
        "change_mask": RasterProduct(
            str(out / f"{prefix}_change_mask.tif"),
            ("sign",),
            dtype="int8",
            nodata=CHANGE_NODATA,
            tags=tags,
            overview_resampling="nearest",
            descriptions=(None,),
        ),
    }
    center = sig.center_m if sig is not None else 0.0
    rsig = (
        _RegionSigma(
            vg, (float(post[0]), float(post[1])), unc.bias_sigma_m, unc.n_stable, unc.offset_m, KC, block, cell
        )
        if unc is not None
        else None
    )
    kin = {"k_local": kstore.source("k_local")} if unc is not None else {}
    rtest = None
    region_info = None
    if p.region_test == "noise" and sig is not None and unc is not None:
        # region test: a first pass finds the regions and their cluster mass, the products pass drops
        # the regions noise alone would make (same rule as finish_difference's noise_region_filter)
        from .pipeline import region_null_of
        from .significance import noise_mass_needed, region_noise_confidence, resolvable

        r1 = R.run(
            _t_products,
            "regions",
            (
                S,
                plan,
                sd,
                em,
                sig,
                p.confidence,
                center,
                split,
                fitted_plan,
                None,
                {"alpha": 1.0 - p.confidence / 100.0},
            ),
            ov,
            inputs=kin or None,
        )
        m1 = merge_regions([s_["regions"] for _, s_ in r1.smalls()], R.tg, p.min_region_cells)
        null = region_null_of(vg, post, p.confidence, p.min_region_cells)
        drop = (
            region_noise_confidence(m1.extra["mass"], null) < p.confidence
            if len(m1) and resolvable(null, p.confidence)
            else np.zeros(len(m1), bool)
        )
        ks = np.nonzero(drop)[0]
        table: dict = {}
        if ks.size:
            tiles, signs, labs = m1.members.pieces(ks)
            for (i, j), sg_, lb in zip(tiles.tolist(), signs.tolist(), labs.tolist()):
                table.setdefault((i, j), ([], []))[0 if sg_ > 0 else 1].append(lb)
            for key, (lp, ln) in table.items():
                dp = np.zeros(max(lp, default=0) + 1, bool)
                dn = np.zeros(max(ln, default=0) + 1, bool)
                dp[lp] = True
                dn[ln] = True
                table[key] = (dp, dn)
        region_info = {
            "regions_tested": int(len(m1)),
            "regions_dropped": int(ks.size),
            "cells_dropped": int(np.sum(m1.n[ks])),
            "null_regions": int(null.size),
            "mass_needed": noise_mass_needed(null, p.confidence),
        }
        del m1
        rtest = {"drop": (tuple(R.tg.tile_size), table)}
        kin["labels_first"] = r1.store.source("labels")
    rp = R.run(
        _t_products,
        "products",
        (S, plan, sd, em, sig, p.confidence, center, split, fitted_plan, rsig, rtest),
        ov,
        products=products,
        inputs=kin or None,
    )
    sm = [s_ for _, s_ in rp.smalls()]
    tot = {
        k: sum(s_[k] for s_ in sm)
        for k in (
            "n_obs",
            "n_stable",
            "n_changed",
            "n_raised",
            "n_lowered",
            "sum_changed",
            "sum_raised",
            "sum_lowered",
            "sum_obs",
            "n_identical",
        )
    }
    stable_dh = np.concatenate([s_["stable_dh"] for s_ in sm]).astype(np.float64)
    abs_dh = np.concatenate([s_["abs_dh"] for s_ in sm])
    # degenerate stable terrain (identical heights, NMAD at the float32 floor): from the tiles' counts
    warns: list[str] = []
    degenerate: dict = {}
    if model.info.n_cells >= p.min_stable_cells:
        from .pipeline import degenerate_message

        hmax = max((s_["hmax_stable"] for s_ in sm), default=0.0)
        degenerate, warn = degenerate_message(
            int(tot["n_stable"]), int(tot["n_identical"]), nmad(stable_dh) if stable_dh.size else float("nan"), hmax, p
        )
        if warn:
            status = "degenerate_stable_terrain"
            warns.append(warn)
    if sig is None and p.fallback_threshold_m is not None:
        notes.append(f"changed cells from the fixed threshold |dh| > {p.fallback_threshold_m} m (no significance test)")
    # --- regions -----------------------------------------------------------------------------------
    # no more tiles: a LocalCluster's workers give their memory back before the client merges the regions
    R.eng.release_local()
    merged = merge_regions([s_["regions"] for s_ in sm], R.tg, p.min_region_cells)
    for s_ in sm:
        s_.pop("regions", None)
    store = rp.store

    def var_terms(V: float, n: int, cross: float, include_bias: bool = True) -> float:
        return rsig.var(V, n, cross, include_bias)

    def region_sigma(k: int) -> float:
        from ..tiling.regions import region_mask_window

        vs = merged.extra.get("vsig")
        if vs is not None and merged.members.counts[k] == 1 and np.isfinite(vs[k]):
            return float(vs[k])  # wholly inside one tile: computed there
        r0, c0, r1, c1 = (int(v) for v in merged.bbox[k])
        if (r1 - r0) * (c1 - c0) <= R.tiling.exact_grid_cells:
            m, sl = region_mask_window(merged, k, lambda t: store.tile_array(t, "labels"), R.tg)
            sg = store.read("sigma_m", (r0, c0, r1 - r0, c1 - c0)).astype(np.float64)
            m &= np.isfinite(sg)
            return rsig.window(np.where(m, sg, 0.0), kstore.read("k_local", (r0, c0, r1 - r0, c1 - c0)), r0, c0)
        else:
            Sr, Qr = _region_coarse(merged, k, store, R.tg, block, cshape)
            V = coarse_sum_variance(Sr, Qr, vg, Cfull)
            cross = float(np.sum(Sr * KC))
            n = int(merged.n[k])
        return math.sqrt(var_terms(V, n, cross)) * cell

    # written batch by batch: the polygons of millions of regions are never all held at once
    layer = regions_layer_batches(
        merged,
        g,
        cell_area_m2=cell,
        method=st.method,
        epoch_a=ea,
        epoch_b=eb,
        volume_sigma=region_sigma if unc is not None else None,
    )
    # --- summary -----------------------------------------------------------------------------------
    s = {
        "epoch_a": ea,
        "epoch_b": eb,
        "status": status,
        "coreg_status": c.status,
        "coreg_applied": c.applied,
        "shift_applied_m": list(c.shift_m),
        "shift_fitted_m": list(c.fitted_shift_m),
        "shift_sigma_m": list(c.shift_sigma_m),
        "coreg_n_fit": c.n_fit,
        "n_observed": int(tot["n_obs"]),
        "observed_area_m2": float(tot["n_obs"] * cell),
        "n_stable": int(tot["n_stable"]),
        "stable_median_m": float(np.median(stable_dh)) if stable_dh.size else float("nan"),
        "stable_nmad_m": nmad(stable_dh) if stable_dh.size else float("nan"),
        "stable_nmad_before_coreg_m": c.nmad_before_m,
        "changed_cells": int(tot["n_changed"]),
        "changed_area_m2": float(tot["n_changed"] * cell),
        "raised_area_m2": float(tot["n_raised"] * cell),
        "lowered_area_m2": float(tot["n_lowered"] * cell),
        "volume_changed_m3": float(tot["sum_changed"] * cell),
        "volume_raised_m3": float(tot["sum_raised"] * cell),
        "volume_lowered_m3": float(tot["sum_lowered"] * cell),
        "volume_net_observed_m3": float(tot["sum_obs"] * cell),
    }
    nan = float("nan")
    s.update(
        volume_changed_sigma_m3=nan,
        volume_changed_sigma_random_m3=nan,
        volume_net_observed_sigma_m3=nan,
        n_eff_changed=nan,
        variogram_ranges_m=[],
        variogram_sills=[],
        variogram_nugget=nan,
        bias_sigma_m=nan,
    )
    if unc is not None:
        s["variogram_ranges_m"] = list(vg.ranges_m)
        s["variogram_sills"] = list(vg.sills)
        s["variogram_nugget"] = vg.nugget
        s["bias_sigma_m"] = unc.bias_sigma_m
        s["n_eff_stable"] = unc.n_eff_stable
        s["error_model_coef"] = list(em.coef)
        s["error_model_scale"] = em.scale
        blk = [s_["blocks"] for s_ in sm if "blocks" in s_]
        q = {k: float(sum(s_.get(k, 0.0) for s_ in sm)) for k in ("q_obs", "q_changed", "q_obs_st", "q_changed_st")}
        q.update(
            {
                k: float(sum(s_.get(k, 0.0) for s_ in sm))
                for k in ("v_short_obs", "v_short_changed", "x_short_obs", "x_short_changed")
            }
        )
        So = _coarse(blk, "obs", cshape)
        Sc = _coarse(blk, "changed", cshape)
        Vo = max(split.nugget * q["q_obs"] + q["v_short_obs"] + long_sum(So), 0.0)
        cross_o = float(np.sum(So * KC)) + split.nugget * q["q_obs_st"] + q["x_short_obs"]
        s["volume_net_observed_sigma_m3"] = math.sqrt(var_terms(Vo, int(tot["n_obs"]), cross_o)) * cell
        if tot["n_changed"]:
            Vc = max(split.nugget * q["q_changed"] + q["v_short_changed"] + long_sum(Sc), 0.0)
            cross_c = float(np.sum(Sc * KC)) + split.nugget * q["q_changed_st"] + q["x_short_changed"]
            s["volume_changed_sigma_m3"] = math.sqrt(var_terms(Vc, int(tot["n_changed"]), cross_c)) * cell
            s["volume_changed_sigma_random_m3"] = math.sqrt(Vc) * cell
            s["n_eff_changed"] = float(np.sum(Sc) ** 2 * vg.total_sill / Vc) if Vc > 0 else nan
    if fitted_plan is not None and tot["n_changed"]:
        vf = float(sum(s_.get("sum_changed_fitted", 0.0) for s_ in sm) * cell)
        s["volume_changed_if_fitted_shift_applied_m3"] = vf
        sv = s["volume_changed_sigma_m3"]
        s["fitted_shift_volume_effect_sigma"] = (vf - s["volume_changed_m3"]) / sv if sv and math.isfinite(sv) else nan
    s.update(degenerate)
    if region_info is not None:
        s["region_test"] = region_info
    s["wall_s"] = time.perf_counter() - R.t0
    s["tiled"] = {
        "exact": False,
        "sample_fraction": S.fraction,
        "coarse_block_cells": block,
        "tile_size": R.tiling.tile_size,
        "short_range_cells": split.radius if split is not None else 0,
    }
    # --- writing -----------------------------------------------------------------------------------
    paths: dict[str, Path] = dict(rp.products)
    vmax = nice_limit(float(np.nanpercentile(abs_dh, 98)) if abs_dh.size else 1.0)
    write_raster_style(paths["dh"], dh_qml(vmax))
    write_raster_style(paths["significance"], significance_qml())
    write_raster_style(paths["change_mask"], qml_for("change_mask"))
    dr = DEMDiffResult(
        g,
        post,
        None,
        None,
        None,
        None,
        None,
        None,
        model.info,
        c,
        unc,
        sig,
        None,
        None,
        None,
        None,
        None,
        ea,
        eb,
        p.confidence,
        status,
        notes,
        warnings=warns,
    )
    dr.summary = s
    layers: dict[str, Any] = {"changes": layer}
    styles = {"changes": qml_for("changes")}
    if footprints is not None:
        from ..change.building_layer import buildings_qml

        layers["buildings"] = _buildings_windows(footprints, store, R.tg, g, p.confidence)
        styles["buildings"] = buildings_qml()
    layers.update(tables(dr))
    paths["changes"] = write_gpkg(out / f"{prefix}_changes.gpkg", layers, styles=styles)
    if plots:
        paths["dh_png"] = _plot_large(S, paths, out / f"{prefix}_dh.png", s, c, vmax, ea, eb, p.confidence, status)
    rep = dr.to_dict()
    if provenance:
        rep["provenance"] = provenance
    paths["report"] = write_json(out / f"{prefix}_report.json", rep)
    return TiledDEMDiffResult(paths, s, c, model.info, status, notes, em, vg, sig, False, g, warnings=warns)


def _region_coarse(merged, k: int, store, tg: TileGrid, block: int, cshape) -> np.ndarray:
    """Block sums of σ and Σ σ² over region ``k`` (regions too large for a window FFT)."""
    out = np.zeros(cshape)
    q = 0.0
    by_tile: dict = {}
    for ti, s, lab in merged.members[k]:
        by_tile.setdefault(ti, []).append(s * lab)
    for ti, labs in by_tile.items():
        t = tg.tile(*ti)
        r0, c0, h, w = t.core
        m = np.isin(store.tile_array(t, "labels"), labs)
        sg = np.asarray(store.tile_array(t, "sigma_m"), np.float64)
        a = np.where(m & np.isfinite(sg), sg, 0.0)
        br = np.arange(r0, r0 + h) // block
        bc = np.arange(c0, c0 + w) // block
        rs = np.r_[0, np.nonzero(np.diff(br))[0] + 1]
        cs = np.r_[0, np.nonzero(np.diff(bc))[0] + 1]
        out[np.ix_(br[rs], bc[cs])] += np.add.reduceat(np.add.reduceat(a, rs, axis=0), cs, axis=1)
        q += float(np.sum(a * a))
    return out, q


def _buildings_windows(footprints, store, tg: TileGrid, g: AOIGrid, level: float):
    """The building layer (:func:`geocd.change.dsm_buildings.classify_damage`) footprint by footprint on windows
    of the tile arrays: the change mask at ``level`` (percent), heights above a ring around each footprint; no new
    building is searched outside the footprints."""
    import pandas as pd
    import geopandas as gpd

    from ..change.building_layer import empty_layer, footprint_id_field, footprints_with_ids, order_columns
    from ..change.buildings import footprint_windows
    from ..change.dsm_buildings import LevelMasks, classify_damage

    if not len(footprints):
        return empty_layer(g.crs)
    gdf = footprints_with_ids(footprints, g.crs, footprint_id_field(footprints))
    rows = []
    for i, win, sub, near in footprint_windows(gdf, g):
        out = classify_damage(
            gdf.iloc[near],
            LevelMasks(store.read("dh_m", win), {float(level): store.read("sign", win)}),
            sub,
            z_a=store.read("a32", win),
            z_b=store.read("bc32", win),
            report_confidence=float(level),
            id_field="building_id",
        )
        rows.append(out.iloc[int(np.nonzero(near == i)[0][0])].copy())
    res = gpd.GeoDataFrame(pd.DataFrame(rows).reset_index(drop=True), geometry="geometry", crs=gdf.crs)
    return order_columns(res)


def _plot_large(S: _Setup, paths, png: Path, s, c, vmax, ea, eb, level, status) -> Path:
    """The dh map from the COGs' overviews (at most ~2000 cells a side)."""
    import rasterio
    from affine import Affine
    from rasterio.enums import Resampling

    from ..change.plots import plot_dh_map

    g = S.grid
    f = max(1, int(math.ceil(max(g.shape) / 2000)))
    h, w = -(-g.height // f), -(-g.width // f)
    with rasterio.open(paths["dh"]) as ds:
        dh = ds.read(1, out_shape=(h, w), resampling=Resampling.average, masked=True).filled(np.nan)
    with rasterio.open(paths["change_mask"]) as ds:
        sign = ds.read(1, out_shape=(h, w), resampling=Resampling.nearest)
    small = AOIGrid(g.crs, g.transform @ Affine.scale(g.width / w, g.height / h), w, h)
    try:
        from rasterio.windows import from_bounds

        with rasterio.open(S.a.path) as ds:
            win = from_bounds(*g.bounds, transform=ds.transform)
            back = (
                ds.read(1, window=win, out_shape=(h, w), resampling=Resampling.average, masked=True, boundless=True)
                .filled(np.nan)
                .astype(np.float32)
            )
    except Exception:  # noqa: BLE001 - a backdrop is optional
        back = None
    note = f"stable NMAD {s['stable_nmad_m']:.2f} m; coreg {c.status} ({c.applied})"
    if status == "degenerate_stable_terrain":
        note += "\nWARNING: degenerate stable terrain (DEMs identical there): σ is not credible"
    if math.isfinite(s.get("volume_changed_sigma_m3", float("nan"))):
        note += (
            f"\nchanged {s['changed_area_m2'] / 1e6:.3f} km², "
            f"{s['volume_changed_m3'] / 1e6:+.3f} ± {s['volume_changed_sigma_m3'] / 1e6:.3f} Mm³ (1σ)"
        )
    post = (S.posting[0] * g.width / w, S.posting[1] * g.height / h)
    return plot_dh_map(
        dh,
        small,
        png,
        sign=sign,
        backdrop_m=back,
        backdrop_posting_xy_m=post,
        title=f"{ea} → {eb}: Δh after co-registration, changed at {level:g}% (1:{f} overview)",
        vmax=vmax,
        note=note,
    )
