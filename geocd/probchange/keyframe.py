"""Key-frame variant: hypotheses along the viewing ray of every key-frame pixel (thesis §5.3).

The key frame I₁ belongs to the depth epoch. For a key pixel x, hypothesis d is
the ray point ``P_d = key.localize(x, h_d(x))`` at ellipsoidal height ``h_d``;
it is projected into the depth epoch's other images (s_d against the key-frame
patch, eq. 5.1) and into the other epoch's images (s'_d between pairs of them,
eq. 5.3). Everything goes through the camera protocol (``localize`` and
``project``), so RPC and frame key frames share one code path.

**Hypothesis spacing.** The n hypotheses are uniform in *disparity*: the image
motion of P_d in the depth epoch's other views (their mean) is the same from one
hypothesis to the next, as in the thesis's "disparity space discretized into 128
blocks". For a frame camera and another perspective view, disparity is affine
in inverse depth (exactly for rectified views), so these are inverse-depth bins;
for an RPC view, projection is affine in height to first order, so they are
height bins. No branch on the camera kind is needed. The range of each ray is
``[min DEM − below, max DEM + above]`` over the DEM cells it crosses (or a given
range / the cameras' range).

**Exactness.** Rays are localized and projected exactly on a lattice of key
pixels (``params.lattice_px``, checked per run against exact projection and
refined until the interpolation error is below ``params.interp_tol_px``); pixels in
between are interpolated bilinearly. Rays must cross the height range (nadir to
oblique aerial and satellite views); a ray that does not (above the horizon) is
NaN and its pixel unobserved.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np
from scipy import ndimage

from ..camera import Camera
from ..errors import ConfigError, EmptyDataError, NoOverlapError
from ..geodesy import AOIGrid, from_lonlat
from ..progress import Progress
from ..stereo.sweep import Tile, iter_tiles
from . import _kernels as K
from .engine import (
    PairMAD,
    StackLayout,
    View,
    VisibilityMasks,
    align_views,
    check_epochs,
    confident_surface,
    harmonize_bands,
    make_pairs,
    map_summary,
    run_tiles,
)
from .likelihood import TileEvidence, TileResult
from .objectspace import ProbChangeResult
from .params import ProbChangeParams


# ---------------------------------------------------------------------------------------------
# height ranges and hypotheses along rays
# ---------------------------------------------------------------------------------------------
class DEMSampler:
    """Bilinear samples of a prior DEM (ellipsoidal m, NaN nodata) at lon/lat points."""

    def __init__(self, height_m: np.ndarray, grid: AOIGrid):
        self.h = np.asarray(height_m, np.float64)
        self.grid = grid

    @classmethod
    def wrap(cls, dem: Any) -> "DEMSampler | None":
        if dem is None or isinstance(dem, DEMSampler):
            return dem
        if hasattr(dem, "height_m") and hasattr(dem, "grid"):
            d = dem.to_ellipsoidal() if hasattr(dem, "to_ellipsoidal") else dem
            return cls(d.height_m, d.grid)
        if isinstance(dem, tuple) and len(dem) == 2:
            return cls(dem[0], dem[1])
        raise ConfigError("dem must be a geocd.io.raster.DEM, a (height_m array, AOIGrid) tuple or None")

    def __call__(self, lon: np.ndarray, lat: np.ndarray) -> np.ndarray:
        x, y = from_lonlat(lon, lat, self.grid.crs)
        r, c = self.grid.rowcol(x, y)
        v = ndimage.map_coordinates(
            self.h, [np.ravel(r) - 0.5, np.ravel(c) - 0.5], order=1, mode="constant", cval=np.nan, prefilter=False
        )
        return v.reshape(np.shape(lon))

    def range(self) -> tuple[float, float]:
        ok = np.isfinite(self.h)
        if not ok.any():
            raise EmptyDataError("the prior DEM has no valid height; check its nodata value and vertical datum")
        return float(self.h[ok].min()), float(self.h[ok].max())


def global_height_range(
    cameras: Sequence[Camera], dem: DEMSampler | None, params: ProbChangeParams
) -> tuple[float, float]:
    """The height range every ray is searched within (ellipsoidal m)."""
    if params.height_range_m is not None:
        return params.height_range_m
    if dem is not None:
        lo, hi = dem.range()
        return lo - params.height_below_m, hi + params.height_above_m
    ranges = [c.height_range() for c in cameras]
    ranges = [r for r in ranges if r is not None]
    if not ranges:
        raise ConfigError(
            "no height range for the hypotheses: the cameras give none (frame cameras) and no prior DEM "
            "was given; pass a DEM or --height-range MIN MAX (ellipsoidal m)"
        )
    lo, hi = max(r[0] for r in ranges), min(r[1] for r in ranges)
    if not hi > lo:
        raise ConfigError(f"the cameras' height ranges {ranges} do not overlap; pass --height-range MIN MAX")
    return float(lo), float(hi)


def ray_height_range(
    key: Camera,
    col: np.ndarray,
    row: np.ndarray,
    lo_g: float,
    hi_g: float,
    dem: DEMSampler | None,
    params: ProbChangeParams,
    n_knots: int = 17,
) -> tuple[np.ndarray, np.ndarray]:
    """Per-ray range: the DEM's min/max along the ray within [lo_g, hi_g], − below / + above."""
    m = np.size(col)
    lo = np.full(m, lo_g)
    hi = np.full(m, hi_g)
    if dem is None or params.height_range_m is not None:
        return lo, hi
    H = np.linspace(lo_g, hi_g, n_knots)[:, None] * np.ones((1, m))
    lon, lat = key.localize(np.broadcast_to(np.ravel(col), H.shape), np.broadcast_to(np.ravel(row), H.shape), H)
    z = dem(lon, lat)
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        zmin, zmax = np.nanmin(z, axis=0), np.nanmax(z, axis=0)
    ok = np.isfinite(zmin)
    lo = np.where(ok, np.maximum(zmin - params.height_below_m, lo_g), lo_g)
    hi = np.where(ok, np.minimum(zmax + params.height_above_m, hi_g), hi_g)
    bad = hi <= lo
    lo[bad], hi[bad] = lo_g, hi_g
    return lo, hi


def ray_hypotheses(
    key: Camera,
    ref_cameras: Sequence[Camera],
    col: np.ndarray,
    row: np.ndarray,
    lo_m: np.ndarray,
    hi_m: np.ndarray,
    n_bins: int,
    n_knots: int = 33,
) -> np.ndarray:
    """Heights of n hypotheses along the rays of key pixels, uniform in disparity.

    Parameters
    ----------
    key : the key frame's camera
    ref_cameras : cameras whose image motion defines disparity (the depth epoch's other views)
    col, row : key-frame pixel coordinates (any shape, m points)
    lo_m, hi_m : per-point height range (m)
    n_bins : n

    Returns
    -------
    float64 (n_bins, *col.shape), increasing along axis 0. Rays whose motion cannot
    be measured (no reference camera sees them) fall back to uniform heights.
    """
    shape = np.shape(col)
    c = np.ravel(np.asarray(col, np.float64))
    r = np.ravel(np.asarray(row, np.float64))
    lo = np.ravel(np.broadcast_to(np.asarray(lo_m, np.float64), shape))
    hi = np.ravel(np.broadcast_to(np.asarray(hi_m, np.float64), shape))
    t = np.linspace(0.0, 1.0, n_knots)[:, None]
    H = lo[None] + t * (hi - lo)[None]  # (K, m)
    lon, lat = key.localize(np.broadcast_to(c, H.shape), np.broadcast_to(r, H.shape), H)
    motion = np.zeros((n_knots - 1, c.size))
    count = np.zeros((n_knots - 1, c.size))
    for cam in ref_cameras:
        pc, pr = cam.project(lon, lat, H)
        dm = np.hypot(np.diff(pc, axis=0), np.diff(pr, axis=0))
        ok = np.isfinite(dm)
        motion += np.where(ok, dm, 0.0)
        count += ok
    with np.errstate(invalid="ignore", divide="ignore"):
        motion = motion / count
    with np.errstate(all="ignore"):
        seg_mean = np.nansum(np.where(np.isfinite(motion), motion, 0.0), axis=0) / np.maximum(
            np.isfinite(motion).sum(axis=0), 1
        )
    seg_mean = np.where(np.isfinite(seg_mean) & (seg_mean > 0), seg_mean, 1.0)
    motion = np.where(np.isfinite(motion) & (motion > 0), motion, seg_mean[None])
    cum = np.vstack([np.zeros((1, c.size)), np.cumsum(motion, axis=0)])
    cum /= cum[-1][None]
    target = np.linspace(0.0, 1.0, n_bins)
    out = np.empty((n_bins, c.size))
    # piecewise-linear inverse of cum(h) per ray (vectorized searchsorted over the knots)
    for q in range(c.size):
        out[:, q] = np.interp(target, cum[:, q], H[:, q])
    return out.reshape((n_bins, *shape))


# ---------------------------------------------------------------------------------------------
# result
# ---------------------------------------------------------------------------------------------
@dataclass
class KeyFrameResult(ProbChangeResult):
    """:class:`ProbChangeResult` in the key frame's geometry (arrays cover the key window).

    Extra attributes: ``key_camera``, ``key_name``, ``col0``, ``row0`` (position of
    the arrays' [0, 0] pixel in the full key image), ``lattice_px`` (used).
    """

    key_camera: Camera | None = None
    key_name: str = ""
    col0: float = 0.0
    row0: float = 0.0
    lattice_px: int = 0

    def pixel_coords(self) -> tuple[np.ndarray, np.ndarray]:
        """(col, row) of every pixel centre in full key-image coordinates."""
        h, w = self.probability.shape
        cc, rr = np.meshgrid(np.arange(w) + 0.5 + self.col0, np.arange(h) + 0.5 + self.row0)
        return cc, rr

    def to_grid(self, grid: AOIGrid, min_weight: float = 0.25) -> ProbChangeResult:
        """Resample onto an AOI grid: each key pixel lands where its most probable depth-epoch point is.

        Bilinear splatting of probability, log-odds, coverage and heights; cells no
        key pixel lands on (hidden from the key frame, outside it) are NaN.
        """
        cc, rr = self.pixel_coords()
        ok = np.isfinite(self.probability) & np.isfinite(self.height_a_m)
        lon, lat = self.key_camera.localize(cc[ok], rr[ok], self.height_a_m[ok].astype(np.float64))
        x, y = from_lonlat(lon, lat, grid.crs)
        gr, gc = grid.rowcol(x, y)
        fcol = np.ascontiguousarray(gc - 0.5, np.float64)
        frow = np.ascontiguousarray(gr - 0.5, np.float64)
        out = {}
        for name in ("probability", "log_odds", "coverage", "height_a_m", "height_b_m"):
            sw = np.zeros(grid.shape)
            sv = np.zeros(grid.shape)
            K.splat_bilinear(fcol, frow, np.ascontiguousarray(getattr(self, name)[ok], np.float64), sw, sv)
            with np.errstate(invalid="ignore", divide="ignore"):
                out[name] = np.where(sw >= min_weight, sv / sw, np.nan).astype(np.float32)
        cov = np.nan_to_num(out["coverage"], nan=0.0)
        return ProbChangeResult(
            out["probability"],
            out["log_odds"],
            cov,
            out["height_a_m"],
            out["height_b_m"],
            self.noise,
            self.pairs,
            self.params,
            grid,
            {**self.diagnostics, "from_key_frame": self.key_name},
        )


# ---------------------------------------------------------------------------------------------
# the detector
# ---------------------------------------------------------------------------------------------
def _check_overlap(key: View, others: Sequence[View], lo: float, hi: float) -> None:
    c0 = key.chips[0]
    h, w = c0.shape
    ox, oy = c0.origin
    cc, rr = np.meshgrid(np.linspace(0.5, w - 0.5, 16) + ox, np.linspace(0.5, h - 0.5, 16) + oy)
    for v in others:
        seen = np.zeros(cc.shape, bool)
        for hh in (lo, 0.5 * (lo + hi), hi):
            lon, lat = key.camera.localize(cc, rr, np.full(cc.shape, hh))
            pc, pr = v.camera.project(lon, lat, np.full(cc.shape, hh))
            seen |= np.isfinite(v.chips[0].warp(pc, pr))
        if not seen.any():
            raise NoOverlapError(
                f"image {v.name!r} does not overlap the key frame {key.name!r} (window {w}x{h} px at "
                f"({ox:.0f}, {oy:.0f})) at any height in {lo:.0f}..{hi:.0f} m; drop it from its epoch, or check its "
                "camera and the height range"
            )


def _alignment_points(
    key: View, dem: DEMSampler | None, lo: float, hi: float, n: int = 160
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ground points for the radiometric alignment: key-pixel rays meeting the prior DEM (else mid-range)."""
    c0 = key.chips[0]
    h, w = c0.shape
    ox, oy = c0.origin
    cc, rr = np.meshgrid(np.linspace(0.5, w - 0.5, min(n, w)) + ox, np.linspace(0.5, h - 0.5, min(n, h)) + oy)
    hh = np.full(cc.shape, 0.5 * (lo + hi))
    if dem is not None:
        d_lo, d_hi = dem.range()
        hh[:] = 0.5 * (d_lo + d_hi)
        for _ in range(5):  # ray–DEM intersection by fixed-point iteration (contracting for nadir-ish views)
            lon, lat = key.camera.localize(cc, rr, hh)
            z = dem(lon, lat)
            hh = np.where(np.isfinite(z), z, hh)
    lon, lat = key.camera.localize(cc, rr, hh)
    return lon, lat, hh


class _KeySweep:
    """Warps every view onto a tile of key pixels for each hypothesis, via an exact lattice."""

    def __init__(
        self,
        key: View,
        layout: StackLayout,
        ref_cams: Sequence[Camera],
        dem: DEMSampler | None,
        lo_g: float,
        hi_g: float,
        params: ProbChangeParams,
        step: int,
    ):
        self.key = key
        self.layout = layout
        self.ref_cams = list(ref_cams)
        self.dem = dem
        self.lo_g, self.hi_g = lo_g, hi_g
        self.params = params
        self.step = int(step)
        self.ox, self.oy = key.chips[0].origin

    def nodes(self, tile: Tile) -> tuple[np.ndarray, np.ndarray]:
        """(col, row) of the lattice nodes of a tile's outer window (full key-image coordinates)."""
        h, w = tile.outer_shape
        s = self.step
        na = int(math.ceil((h - 1) / s)) + 1 if h > 1 else 1
        nb = int(math.ceil((w - 1) / s)) + 1 if w > 1 else 1
        rows = tile.outer[0].start + np.arange(na) * s + 0.5 + self.oy
        cols = tile.outer[1].start + np.arange(nb) * s + 0.5 + self.ox
        C, R = np.meshgrid(cols, rows)
        return C, R

    def heights(self, tile: Tile) -> np.ndarray:
        """Hypothesis heights on the tile's lattice: float64 (n, La, Lb)."""
        C, R = self.nodes(tile)
        lo, hi = ray_height_range(self.key.camera, C, R, self.lo_g, self.hi_g, self.dem, self.params)
        return ray_hypotheses(
            self.key.camera, self.ref_cams, C, R, lo.reshape(C.shape), hi.reshape(C.shape), self.params.n_bins
        )

    def node_projections(self, C: np.ndarray, R: np.ndarray, Hd: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
        lon, lat = self.key.camera.localize(C, R, Hd)
        return [v.camera.project(lon, lat, Hd) for v in self.layout.views[1:]]

    def interpolated(self, lat: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
        out = np.empty(shape, np.float64)
        K.lattice_to_pixels(np.ascontiguousarray(lat, np.float64), self.step, out)
        return out

    def max_interp_error(self, tile: Tile, Hn: np.ndarray) -> float:
        """Largest |interpolated − exact| projection (px) at mid-lattice pixels of a tile."""
        C, R = self.nodes(tile)
        shape = tile.outer_shape
        s = self.step
        if s == 1:
            return 0.0
        ii = np.arange(s // 2, shape[0], s)
        jj = np.arange(s // 2, shape[1], s)
        if ii.size == 0 or jj.size == 0:
            return 0.0
        II, JJ = np.meshgrid(ii, jj, indexing="ij")
        err = 0.0
        n = Hn.shape[0]
        for d in sorted({0, n // 2, n - 1}):
            hp = self.interpolated(Hn[d], shape)[II, JJ]
            cp = (tile.outer[1].start + JJ + 0.5 + self.ox).astype(np.float64)
            rp = (tile.outer[0].start + II + 0.5 + self.oy).astype(np.float64)
            exact = self.node_projections(cp, rp, hp)
            approx = self.node_projections(C, R, Hn[d])
            for (ec, er), (ac, ar) in zip(exact, approx):
                ic = self.interpolated(ac, shape)[II, JJ]
                ir = self.interpolated(ar, shape)[II, JJ]
                e = np.hypot(ic - ec, ir - er)
                e = e[np.isfinite(e)]
                if e.size:
                    err = max(err, float(e.max()))
        return err

    def volumes(self, tile: Tile) -> TileEvidence:
        L = self.layout
        shape = tile.outer_shape
        n = self.params.n_bins
        Hn = self.heights(tile)
        C, R = self.nodes(tile)
        stack = np.empty((L.n_chips, *shape), np.float32)
        for b, chip in enumerate(self.key.chips):  # the key frame itself: the same for every d
            stack[L.band_index[0][b]] = chip.data[tile.outer]
        pa, pb = len(L.pairs_a), len(L.pairs_b)
        s_a = np.empty((pa, n, *shape), np.float32)
        s_b = np.empty((pb, n, *shape), np.float32)
        mad = PairMAD(L, self.params, shape)
        cbuf = np.empty(shape, np.float64)
        rbuf = np.empty(shape, np.float64)
        for d in range(n):
            projs = self.node_projections(C, R, Hn[d])
            for v_idx, (pc, pr) in enumerate(projs, start=1):
                K.lattice_to_pixels(np.ascontiguousarray(pc, np.float64), self.step, cbuf)
                K.lattice_to_pixels(np.ascontiguousarray(pr, np.float64), self.step, rbuf)
                for b, chip in enumerate(L.views[v_idx].chips):
                    chip.warp(cbuf, rbuf, out=stack[L.band_index[v_idx][b]])
            mad(stack, d, s_a, s_b)
        return TileEvidence(s_a, s_b, 0, Hn)


def detect_keyframe(
    key: View,
    others_a: Sequence[View],
    views_b: Sequence[View],
    *,
    dem: Any = None,
    params: ProbChangeParams = ProbChangeParams(),
    progress: Progress | None = None,
) -> KeyFrameResult:
    """Probability of a 3-D change at every pixel of a key frame (thesis §5.3), any camera kind.

    Parameters
    ----------
    key : the key frame (depth epoch); its chips' window is the output window
    others_a : the depth epoch's other views (≥ 1): s_d compares each with the key frame
    views_b : the other epoch's views (≥ 2); pairs per ``params.pairs`` (index 0 = reference)
    dem : optional prior DEM (geocd.io.raster.DEM or (height_m, AOIGrid)), ellipsoidal heights
    params : ProbChangeParams

    Returns
    -------
    KeyFrameResult (arrays of the key window's shape)

    Raises
    ------
    ConfigError
        An epoch with fewer than two images; no height range.
    NoOverlapError
        An image that does not overlap the key frame.
    """
    check_epochs([key, *others_a], views_b)
    va = harmonize_bands([key, *others_a], params.bands)
    vb = harmonize_bands(views_b, params.bands)
    key = va[0]
    dem_s = DEMSampler.wrap(dem)
    lo_g, hi_g = global_height_range([v.camera for v in (*va, *vb)], dem_s, params)
    _check_overlap(key, [*va[1:], *vb], lo_g, hi_g)
    fits: list = []
    if params.align_radiometry:
        lon, lat, h = _alignment_points(key, dem_s, lo_g, hi_g)
        va, fa = align_views(va, lon, lat, h)
        vb, fb = align_views(vb, lon, lat, h)
        fits = fa + fb
    layout = StackLayout.build(va, vb, make_pairs(len(va), "star"), make_pairs(len(vb), params.pairs))
    shape = key.chips[0].shape
    tiles = iter_tiles(shape, params.tile_size, params.radius)
    ref_cams = [v.camera for v in va[1:]]
    # lattice spacing: refine until interpolating projections is exact enough (checked on the central tile)
    step = max(1, int(params.lattice_px))
    probe = tiles[len(tiles) // 2]
    while True:
        ks = _KeySweep(key, layout, ref_cams, dem_s, lo_g, hi_g, params, step)
        if step == 1 or ks.max_interp_error(probe, ks.heights(probe)) <= params.interp_tol_px:
            break
        step = max(1, step // 2)
    out = {
        k: np.full(shape, np.nan, np.float32)
        for k in ("probability", "log_odds", "coverage", "height_a_m", "height_b_m")
    }
    out["coverage"][:] = 0.0

    def heights_at(tile: Tile, Hn: np.ndarray, k: np.ndarray) -> np.ndarray:
        """Hypothesis heights of index map k (−1: NaN) over a tile's outer window."""
        hh = np.full(tile.outer_shape, np.nan)
        for d in np.unique(k[k >= 0]):
            sel = k == d
            hh[sel] = ks.interpolated(Hn[d], tile.outer_shape)[sel]
        return hh

    def store(tile: Tile, ev: TileEvidence, res: TileResult) -> None:
        core, inner = tile.core, tile.inner
        out["probability"][core] = np.where(res.k_a[inner] >= 0, res.prob[inner], np.nan)
        out["log_odds"][core] = res.log_odds[inner]
        out["coverage"][core] = res.coverage[inner]
        out["height_a_m"][core] = heights_at(tile, ev.extra, res.k_a)[inner]
        out["height_b_m"][core] = heights_at(tile, ev.extra, res.k_b)[inner]

    kw: dict = {}
    vis = None
    if params.visibility:
        hmap = {k: np.full(shape, np.nan) for k in ("a", "b", "sa", "sb")}
        vis = VisibilityMasks(layout, params, never=(0,))

        def map_store(tile: Tile, ev: TileEvidence) -> None:
            ka, kb, sa, sb = map_summary(ev)
            for key, k, sm in (("a", ka, sa), ("b", kb, sb)):
                hmap[key][tile.core] = heights_at(tile, ev.extra, k)[tile.inner]
                hmap["s" + key][tile.core] = sm[tile.inner]

        def between(noise) -> None:
            h_, w_ = shape
            cc, rr = np.meshgrid(
                np.arange(w_) + 0.5 + key.chips[0].origin[0], np.arange(h_) + 0.5 + key.chips[0].origin[1]
            )
            surf = []
            for key_h, s_key, sig in (("a", "sa", noise.sigma), ("b", "sb", noise.sigma_prime)):
                hh = confident_surface(hmap[key_h], hmap[s_key], sig)
                lon, lat = key.camera.localize(cc, rr, np.where(np.isfinite(hh), hh, 0.5 * (lo_g + hi_g)))
                surf.append((lon, lat, hh))
            vis.compute(surf[0], surf[1] if params.symmetric else None)

        kw = {"map_store": map_store, "between": between, "mask": lambda tile, ev: vis.apply(ev, tile.outer)}
    noise, diag = run_tiles(tiles, ks.volumes, store, params, progress, **kw)
    ox, oy = key.chips[0].origin
    return KeyFrameResult(
        out["probability"],
        out["log_odds"],
        out["coverage"],
        out["height_a_m"],
        out["height_b_m"],
        noise,
        layout.pair_names(),
        params,
        None,
        {
            "sigma_samples": diag,
            "height_range_m": (lo_g, hi_g),
            "radiometric_fits": fits,
            "hidden_fraction": vis.fraction_hidden() if vis is not None else {},
        },
        key_camera=key.camera,
        key_name=key.name,
        col0=ox,
        row0=oy,
        lattice_px=step,
    )
