"""Object-space variant: vertical rays on the AOI grid (the natural form for satellites).

Every AOI cell is a "key pixel" whose ray is the vertical line through its
centre; hypotheses are n heights between ``DEM − below`` and ``DEM + above``
(or a given range). :class:`geocd.stereo.PlaneSweep` warps every image of both
epochs onto the grid for each height (camera protocol only: RPC and frame
cameras alike), and the 5 × 5 patches of eq. 5.1 are windows of grid cells, i.e.
orthorectified patches at the hypothesis height. The depth epoch's pairs give
p(h) ∝ exp(−Σ s_h/σ), the other epoch's pairs give s'_h, and eqs. 5.5–5.11 give
p(c = 1) per cell (:mod:`geocd.probchange.likelihood`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np
from scipy import ndimage

from ..camera import Camera
from ..errors import ConfigError, EmptyDataError, NoOverlapError
from ..geodesy import AOIGrid
from ..progress import Progress
from ..stereo.sweep import HeightSearch, PlaneSweep, chip_valid_at, sample_cells
from .engine import (
    PairMAD,
    StackLayout,
    View,
    VisibilityMasks,
    align_views,
    check_epochs,
    harmonize_bands,
    make_pairs,
    confident_surface,
    map_summary,
    run_tiles,
)
from .likelihood import NoiseModel, TileEvidence, TileResult
from .params import ProbChangeParams


@dataclass
class ProbChangeResult:
    """Change probability and by-products on a set of reference pixels (grid cells or key-frame pixels).

    Attributes
    ----------
    probability : float32 — p(c = 1 | s'), NaN where no hypothesis was observed
    log_odds : float32 — natural log-odds of change
    coverage : float32 — share of the depth epoch's probability seen by the other epoch (0–1): the
        depth mass at hypotheses the other epoch's pairs observe, times 1 − p(no consistent depth);
        the larger of the two directions in the symmetric test
    height_a_m, height_b_m : float32 — most probable hypothesis height of each epoch (by-product,
        not used for the decision; NaN where none)
    observed : bool — coverage ≥ 0.5 (elsewhere the posterior stays near the prior: no decision)
    noise : NoiseModel — σ, σ', S used
    pairs : {"a": [...], "b": [...]} names of the pairs
    params : ProbChangeParams
    grid : AOIGrid (object space) or None (key frame)
    """

    probability: np.ndarray
    log_odds: np.ndarray
    coverage: np.ndarray
    height_a_m: np.ndarray
    height_b_m: np.ndarray
    noise: NoiseModel
    pairs: dict
    params: ProbChangeParams
    grid: AOIGrid | None = None
    diagnostics: dict = field(default_factory=dict)

    @property
    def observed(self) -> np.ndarray:
        return np.isfinite(self.probability) & (self.coverage >= 0.5)

    @property
    def dz_m(self) -> np.ndarray:
        """height_b − height_a of the most probable hypotheses (m): sign and size of a change, roughly."""
        return (self.height_b_m - self.height_a_m).astype(np.float32)

    def changed(self, threshold: float | None = None) -> np.ndarray:
        """bool: p(c = 1) > threshold (default ``params.threshold``, 0.5) where observed."""
        t = self.params.threshold if threshold is None else float(threshold)
        return self.observed & (np.nan_to_num(self.probability, nan=0.0) > t)

    def change_mask(self, threshold: float | None = None, nodata: int = -128) -> np.ndarray:
        """int8: +1 changed, higher in B (or direction unknown); −1 changed, lower; 0 not; ``nodata`` unobserved."""
        ch = self.changed(threshold)
        dz = self.dz_m
        sign = np.where(np.nan_to_num(dz, nan=0.0) < 0, -1, 1)
        return np.where(self.observed, np.where(ch, sign, 0), nodata).astype(np.int8)


def object_height_bounds(
    grid: AOIGrid, cameras: Sequence[Camera], dem: Any, params: ProbChangeParams
) -> tuple[np.ndarray, np.ndarray, str]:
    """Per-cell hypothesis range (ellipsoidal m) and its source.

    ``params.height_range_m`` wins; else a prior DEM (array on ``grid`` or a
    :class:`geocd.io.raster.DEM`): ``[min − below, max + above]`` over
    ``params.dem_window`` cells; else the intersection of the cameras' ranges.

    Raises
    ------
    ConfigError
        No range at all (frame cameras and no DEM), or disjoint camera ranges.
    EmptyDataError
        The DEM has no valid height over the grid.
    """
    from ..stereo.match import dem_on_grid

    if params.height_range_m is not None:
        lo, hi = params.height_range_m
        return np.full(grid.shape, lo), np.full(grid.shape, hi), "parameter"
    if dem is not None:
        d = dem_on_grid(dem, grid)
        ok = np.isfinite(d)
        if not ok.any():
            raise EmptyDataError(
                "the prior DEM has no valid height over the AOI grid; check that it covers the AOI, "
                "its vertical datum, or pass a height range (--height-range MIN MAX)"
            )
        if not ok.all():
            idx = ndimage.distance_transform_edt(~ok, return_distances=False, return_indices=True)
            d = d[tuple(idx)]
        w = max(1, int(params.dem_window))
        lo = ndimage.minimum_filter(d, size=w, mode="nearest") - params.height_below_m
        hi = ndimage.maximum_filter(d, size=w, mode="nearest") + params.height_above_m
        return lo, hi, "dem"
    ranges = [c.height_range() for c in cameras]
    ranges = [r for r in ranges if r is not None]
    if not ranges:
        raise ConfigError(
            "no height range for the hypotheses: the cameras give none (frame cameras) and no prior "
            "DEM was given; add 'dem:' to the manifest or pass --height-range MIN MAX (ellipsoidal m)"
        )
    lo_v = max(float(r[0]) for r in ranges)
    hi_v = min(float(r[1]) for r in ranges)
    if not hi_v > lo_v:
        raise ConfigError(f"the cameras' height ranges {ranges} do not overlap; pass --height-range MIN MAX")
    return np.full(grid.shape, lo_v), np.full(grid.shape, hi_v), "cameras"


def _check_overlap(grid: AOIGrid, layout: StackLayout, lo: np.ndarray, hi: np.ndarray) -> None:
    """Every view must see part of the AOI at some hypothesis height."""
    rows, cols = sample_cells(grid.shape, 24)
    x, y = grid.xy(rows, cols)
    for v in layout.views:
        pr = v.camera.ground_projector(x, y, grid.crs)
        seen = np.zeros(rows.shape, bool)
        for h in (lo[rows, cols], 0.5 * (lo[rows, cols] + hi[rows, cols]), hi[rows, cols]):
            c, r = pr.project(h)
            seen |= chip_valid_at(v.chips[0], c, r)
        if not seen.any():
            raise NoOverlapError(
                f"image {v.name!r} does not see the AOI {tuple(round(b, 1) for b in grid.bounds)} at "
                f"any hypothesis height ({float(np.min(lo)):.0f}..{float(np.max(hi)):.0f} m); drop it "
                "from the epoch, or check its camera, the AOI and the height range"
            )


def _alignment_points(
    grid: AOIGrid, dem: Any, lo: np.ndarray, hi: np.ndarray, max_points: int = 40_000
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ground points for the radiometric alignment: a lattice of cells on the prior DEM (else mid-range)."""
    from ..geodesy import to_lonlat
    from ..stereo.match import dem_on_grid

    H, W = grid.shape
    stride = max(1, int(math.ceil(math.sqrt(H * W / max_points))))
    rows, cols = np.meshgrid(np.arange(0, H, stride), np.arange(0, W, stride), indexing="ij")
    x, y = grid.xy(rows, cols)
    lon, lat = to_lonlat(x, y, grid.crs)
    h = 0.5 * (lo + hi)[rows, cols]
    if dem is not None:
        d = dem_on_grid(dem, grid)[rows, cols]
        h = np.where(np.isfinite(d), d, h)
    return lon, lat, h


def detect_objectspace(
    views_a: Sequence[View],
    views_b: Sequence[View],
    grid: AOIGrid,
    *,
    dem: Any = None,
    params: ProbChangeParams = ProbChangeParams(),
    progress: Progress | None = None,
) -> ProbChangeResult:
    """Probability of a 3-D change at every AOI cell, without reconstructing either epoch.

    Parameters
    ----------
    views_a : the depth epoch's views (≥ 2); pairs per ``params.pairs`` (index 0 = reference)
    views_b : the other epoch's views (≥ 2)
    grid : AOIGrid of the result
    dem : optional prior bare-earth DEM (array on ``grid``, ellipsoidal m, or a DEM object)
    params : ProbChangeParams

    Returns
    -------
    ProbChangeResult on ``grid``

    Raises
    ------
    ConfigError
        An epoch with fewer than two images; no height range.
    NoOverlapError
        An image that does not see the AOI.
    """
    check_epochs(views_a, views_b)
    va = harmonize_bands(views_a, params.bands)
    vb = harmonize_bands(views_b, params.bands)
    cams = [v.camera for v in (*va, *vb)]
    lo, hi, _ = object_height_bounds(grid, cams, dem, params)
    fits: list = []
    if params.align_radiometry:
        lon, lat, h = _alignment_points(grid, dem, lo, hi)
        va, fa = align_views(va, lon, lat, h)
        vb, fb = align_views(vb, lon, lat, h)
        fits = fa + fb
    layout = StackLayout.build(va, vb, make_pairs(len(va), params.pairs), make_pairs(len(vb), params.pairs))
    span = float(np.max(hi - lo))
    step = span / max(params.n_bins - 1, 1)
    search = HeightSearch(np.asarray(lo, np.float64), np.asarray(hi, np.float64), step)
    _check_overlap(grid, layout, lo, hi)
    r = params.radius
    sweep = PlaneSweep(
        grid,
        layout.chips(),
        layout.chip_cameras(),
        search,
        tile_size=params.tile_size,
        margin=r,
        interp_tol_px=min(params.interp_tol_px, 0.05),
    )
    H, W = grid.shape
    out = {
        k: np.full((H, W), np.nan, np.float32)
        for k in ("probability", "log_odds", "coverage", "height_a_m", "height_b_m")
    }
    out["coverage"][:] = 0.0
    pa, pb = len(layout.pairs_a), len(layout.pairs_b)

    def volumes(tile) -> TileEvidence | None:
        k0, k1 = sweep.k_range(tile)
        nk = k1 - k0
        if nk <= 0:
            return None
        shape = tile.outer_shape
        s_a = np.empty((pa, nk, *shape), np.float32)
        s_b = np.empty((pb, nk, *shape), np.float32)
        mad = PairMAD(layout, params, shape)
        for sl in sweep.slices(tile, (k0, k1)):
            mad(sl.stack, sl.k - k0, s_a, s_b)
        # hypotheses outside a cell's own range do not exist for that cell
        kk = np.arange(k0, k1)[:, None, None]
        outside = (kk < sweep.kmin(tile)[None]) | (kk > sweep.kmax(tile)[None])
        s_a[:, outside] = np.nan
        s_b[:, outside] = np.nan
        return TileEvidence(s_a, s_b, k0)

    def store(tile, ev: TileEvidence, res: TileResult) -> None:
        core, inner = tile.core, tile.inner
        k0 = ev.k0
        out["probability"][core] = res.prob[inner]
        out["log_odds"][core] = res.log_odds[inner]
        out["coverage"][core] = res.coverage[inner]
        for key, kmap in (("height_a_m", res.k_a), ("height_b_m", res.k_b)):
            k = kmap[inner]
            out[key][core] = np.where(k >= 0, search.height(k0 + k), np.nan)
        nohyp = res.k_a[inner] < 0
        out["probability"][core] = np.where(nohyp, np.nan, out["probability"][core])

    kw: dict = {}
    vis = None
    if params.visibility:
        hmap = {k: np.full((H, W), np.nan) for k in ("a", "b", "sa", "sb")}
        vis = VisibilityMasks(layout, params)

        def map_store(tile, ev: TileEvidence) -> None:
            ka, kb, sa, sb = map_summary(ev)
            for key, k, sm in (("a", ka, sa), ("b", kb, sb)):
                ki = k[tile.inner]
                hmap[key][tile.core] = np.where(ki >= 0, search.height(ev.k0 + ki), np.nan)
                hmap["s" + key][tile.core] = sm[tile.inner]

        def between(noise) -> None:
            lon, lat = grid.lonlat()
            ha = confident_surface(hmap["a"], hmap["sa"], noise.sigma)
            hb = confident_surface(hmap["b"], hmap["sb"], noise.sigma_prime)
            vis.compute((lon, lat, ha), (lon, lat, hb) if params.symmetric else None)

        kw = {"map_store": map_store, "between": between, "mask": lambda tile, ev: vis.apply(ev, tile.outer)}
    noise, diag = run_tiles(sweep.tiles(), volumes, store, params, progress, **kw)
    return ProbChangeResult(
        out["probability"],
        out["log_odds"],
        out["coverage"],
        out["height_a_m"],
        out["height_b_m"],
        noise,
        layout.pair_names(),
        params,
        grid,
        {
            "sigma_samples": diag,
            "height_step_m": step,
            "n_planes": search.n_planes(),
            "radiometric_fits": fits,
            "hidden_fraction": vis.fraction_hidden() if vis is not None else {},
        },
    )
