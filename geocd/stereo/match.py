"""The object-space stereo matcher (issue 4).

For every cell of the AOI grid and every candidate height, both images are
warped onto the grid (:class:`~geocd.stereo.sweep.PlaneSweep`), window
statistics are aggregated with running sums (O(cells × heights), whatever the
window size), and the height with the best regularized NCC is kept, refined to
sub-step precision with a parabola. Large height ranges are narrowed
coarse-to-fine (grids 2×, 4×, … coarser, anti-aliased images). Each match gets
the MDL score (and NCC, SSD), the disparity-per-metre factor ``g`` and a valid
mask; see :func:`match_pair`.

Left–right consistency in object space: an image pixel can see only one
surface point, so after matching every cell is projected into each image at its
height and a cell hidden behind a higher cell that lands on the same pixel is
invalid (z-buffer). Together with the uniqueness test (no other height matches
almost as well) this replaces the image-space left–right check.
"""

from __future__ import annotations

import math
import time
import warnings
from typing import Any, Sequence

import numpy as np
from scipy import ndimage, sparse, special
from scipy.sparse import csgraph

from ..camera import Camera
from ..errors import ConfigError, CRSError, EmptyDataError, NoOverlapError
from ..geodesy import AOIGrid
from ..progress import Progress, ensure_progress, sub_progress
from . import _kernels as K
from .params import StereoParams
from .pointing import relative_pointing
from .products import FLAGS, PairDEM
from .scores import mdl_from_stats, ncc_from_stats, ssd_from_stats
from .surface import fill_narrow_holes, surface_median
from .sweep import (
    HeightSearch,
    ImageChip,
    PlaneSweep,
    chip_valid_at,
    coarse_grid,
    image_sampling_px_per_m,
    sample_cells,
    sweep_progress,
    upsample_nearest,
)


class StereoGeometryWarning(UserWarning):
    """A pair's viewing geometry makes its heights unreliable (e.g. near-zero base/height)."""


# ---------------------------------------------------------------------------------------------
# height range
# ---------------------------------------------------------------------------------------------
def _fill_nearest(a: np.ndarray) -> np.ndarray:
    ok = np.isfinite(a)
    if ok.all():
        return a
    idx = ndimage.distance_transform_edt(~ok, return_distances=False, return_indices=True)
    return a[tuple(idx)]


def dem_on_grid(dem: Any, grid: AOIGrid) -> np.ndarray:
    """A prior DEM as float64 ellipsoidal heights on ``grid`` (NaN = nodata).

    ``dem`` is an array already on ``grid`` (ellipsoidal heights) or a
    :class:`geocd.io.raster.DEM` (converted to ellipsoidal heights and resampled).
    """
    if hasattr(dem, "height_m") and hasattr(dem, "grid"):
        from ..io.raster import reproject_array

        d = dem.to_ellipsoidal()
        h = d.height_m if d.grid.same_as(grid) else reproject_array(d.height_m, d.grid, grid, "bilinear")
        return np.asarray(h, np.float64)
    a = np.asarray(dem, np.float64)
    if a.shape != grid.shape:
        raise ConfigError(
            f"prior DEM array has shape {a.shape}, the AOI grid {grid.shape}; resample it onto the "
            "grid (geocd.io.raster.read_dem(path, grid=grid)) first"
        )
    return a


def height_bounds(
    grid: AOIGrid, cameras: Sequence[Camera], dem: Any = None, params: StereoParams = StereoParams()
) -> tuple[np.ndarray, np.ndarray, str]:
    """Per-cell ellipsoidal search bounds ``(lo, hi)`` and where they came from.

    A prior DEM gives ``[min − margin, max + margin]`` of the DEM over a
    ``params.dem_window`` neighbourhood (clipped to ``params.height_range_m`` when
    given); otherwise ``params.height_range_m``; otherwise the intersection of the
    cameras' own height ranges (RPC validity).

    Raises
    ------
    ConfigError
        No range at all (frame cameras and no DEM), or camera ranges that do not overlap.
    EmptyDataError
        The DEM has no valid height over the AOI.
    """
    if dem is not None:
        d = dem_on_grid(dem, grid)
        if not np.isfinite(d).any():
            raise EmptyDataError(
                "the prior DEM has no valid height over the AOI grid; check that it covers the AOI "
                "or drop it (the cameras' height range is then used)"
            )
        d = _fill_nearest(d)
        w = max(1, int(params.dem_window))
        lo = ndimage.minimum_filter(d, size=w, mode="nearest") - params.dem_margin_m
        hi = ndimage.maximum_filter(d, size=w, mode="nearest") + params.dem_margin_m
        if params.height_range_m is not None:
            lo = np.maximum(lo, params.height_range_m[0])
            hi = np.minimum(hi, params.height_range_m[1])
            if np.any(hi <= lo):
                raise ConfigError(
                    f"the prior DEM ± {params.dem_margin_m} m lies outside the height range "
                    f"{params.height_range_m}; widen the range or check the DEM's vertical datum"
                )
        return lo, hi, "dem"
    if params.height_range_m is not None:
        lo_v, hi_v = params.height_range_m
        return np.full(grid.shape, lo_v), np.full(grid.shape, hi_v), "parameter"
    ranges = [c.height_range() for c in cameras]
    ranges = [r for r in ranges if r is not None]
    if not ranges:
        raise ConfigError(
            "this pair has no height search range: its cameras give none (frame cameras) and no prior DEM was "
            "given; add 'dem:' to the manifest (a coarse DEM is enough), or pass --height-range MIN MAX "
            "(ellipsoidal metres)"
        )
    lo_v = max(float(r[0]) for r in ranges)
    hi_v = min(float(r[1]) for r in ranges)
    if not hi_v > lo_v:
        raise ConfigError(
            f"the cameras' height ranges {ranges} do not overlap, so no height is valid for both; "
            "check the camera files or pass --height-range MIN MAX"
        )
    return np.full(grid.shape, lo_v), np.full(grid.shape, hi_v), "cameras"


# ---------------------------------------------------------------------------------------------
# pair geometry on sample cells
# ---------------------------------------------------------------------------------------------
def pair_geometry(
    grid: AOIGrid,
    cameras: Sequence[Camera],
    chips: Sequence[ImageChip],
    lo: np.ndarray,
    hi: np.ndarray,
    n_sample: int = 48,
) -> dict[str, Any]:
    """Overlap test and geometry summary of a pair on sample cells.

    Returns a dict with ``jmax`` (largest |∂u/∂z| in either image, px/m), ``g``
    (disparity per metre at sample cells), ``rho`` (image pixels per ground metre,
    one per camera), ``base_height`` (≈ g / rho at sample cells) and ``overlap``
    (fraction of sample cells seen by both images at some candidate height).

    Raises
    ------
    NoOverlapError
        When no sample cell falls in both images at any candidate height.
    """
    rows, cols = sample_cells(grid.shape, n_sample)
    x, y = grid.xy(rows, cols)
    lo_s, hi_s = lo[rows, cols], hi[rows, cols]
    mid_s = 0.5 * (lo_s + hi_s)
    seen = np.zeros(rows.shape, bool)
    jmax = 0.0
    projs = [cam.ground_projector(x, y, grid.crs) for cam in cameras]
    # sensitivities only where a cell lands on valid pixels of that image: outside it a camera model
    # may be meaningless (a frame camera's distortion folds back there, at thousands of px/m)
    for h in (lo_s, mid_s, hi_s):
        ok = np.ones(rows.shape, bool)
        for pr, chip in zip(projs, chips):
            c, r = pr.project(h)
            inside = chip_valid_at(chip, c, r)
            ok &= inside
            if inside.any():
                dc, dr = pr.dproj_dh(h)
                jmax = max(jmax, float(np.nanmax(np.where(inside, np.hypot(dc, dr), np.nan))))
        seen |= ok
    if not seen.any():
        names = " and ".join(repr(c.name or f"image {i + 1}") for i, c in enumerate(chips))
        raise NoOverlapError(
            f"images {names} do not overlap over the AOI at any height in the search range "
            f"[{float(np.min(lo)):.0f}, {float(np.max(hi)):.0f}] m; pick a pair that sees the same ground, or check "
            "the AOI and the height range (a wrong vertical datum shifts footprints)"
        )
    J = []
    for pr in projs:
        dc, dr = pr.dproj_dh(mid_s)
        J.append(np.stack([dc, dr]))
    g = np.where(seen, np.hypot(*(J[0] - J[1])), np.nan)
    rho = [
        float(np.nanmedian(image_sampling_px_per_m(cam, grid, rows[seen], cols[seen], mid_s[seen]))) for cam in cameras
    ]
    return {
        "jmax": jmax,
        "g": g,
        "rho": rho,
        "base_height": g / np.mean(rho),
        "overlap": float(seen.mean()),
        "seen": seen,
    }


# ---------------------------------------------------------------------------------------------
# one level of the sweep
# ---------------------------------------------------------------------------------------------
_PLANES = {
    "best_c": K.BEST_C,
    "best_k": K.BEST_K,
    "best_cm": K.BEST_CM,
    "best_cp": K.BEST_CP,
    "va": K.BEST_VA,
    "vb": K.BEST_VB,
    "cov": K.BEST_COV,
    "n": K.BEST_N,
    "sec_c": K.SEC_C,
    "sec_k": K.SEC_K,
    "nfinite": K.NFINITE,
}


def sweep_ncc(
    grid: AOIGrid,
    chips: Sequence[ImageChip],
    cameras: Sequence[Camera],
    search: HeightSearch,
    params: StereoParams,
    *,
    noise_sigma: float,
    excl_steps: float,
    progress: Progress | None = None,
    prefix: str = "",
    lonlat: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[dict[str, np.ndarray], int]:
    """Sweep the heights of ``search`` and keep, per cell, the best NCC match.

    Returns
    -------
    planes : dict of float64 (rows, cols)
        best_c (1 − NCC_reg), best_k, best_cm, best_cp (costs one step below/above),
        va, vb, cov, n (window statistics at the best height), sec_c, sec_k (best other
        minimum), nfinite (heights with a defined cost), z_raw (sub-step height, m).
    evaluations : int
        Cell × height evaluations (core cells).
    """
    r = params.radius
    min_n = float(math.ceil(params.min_valid_fraction * params.window**2))
    eps = float(noise_sigma) ** 2
    sweep = PlaneSweep(grid, chips[:2], cameras[:2], search, tile_size=params.tile_size, margin=r, lonlat=lonlat)
    out = {k: np.full(grid.shape, np.nan) for k in _PLANES}
    out["best_k"][:] = -1
    for tile in sweep.tiles():
        k0, k1 = sweep.k_range(tile)
        nk = k1 - k0
        if nk <= 0:
            continue
        shape = tile.outer_shape
        st = K.new_state(shape)
        work = np.empty((6, *shape))
        kmin = sweep.kmin(tile)
        kmax = sweep.kmax(tile)
        for sl in sweep.slices(tile):
            K.sweep_step(sl.stack[0], sl.stack[1], r, sl.k, kmin, kmax, min_n, eps, float(excl_steps), st, work)
            if (sl.k - k0) % 8 == 0:
                sweep_progress(progress, tile, sl.k - k0, nk, prefix)
        K.sweep_finish(k1, float(excl_steps), st)
        for name, p in _PLANES.items():
            out[name][tile.core] = st[p][tile.inner]
    # sub-step height: parabola through (k−1, k, k+1)
    k = out["best_k"]
    cm, c0, cp = out["best_cm"], out["best_c"], out["best_cp"]
    with np.errstate(all="ignore"):
        den = cm - 2.0 * c0 + cp
        delta = np.where(np.isfinite(den) & (den > 0), 0.5 * (cm - cp) / den, 0.0)
    delta = np.clip(np.nan_to_num(delta), -0.5, 0.5)
    has = k >= 0
    out["z_raw"] = np.where(has, search.height(k + delta), np.nan)
    kmax = search.kmax()
    out["nsearched"] = np.where(kmax >= 0, kmax - search.kmin() + 1, 0).astype(np.float64)
    return out, sweep.n_evaluations()


def coherent_neighbours(z: np.ndarray, tol_m: float, radius: int = 2) -> np.ndarray:
    """For each cell, how many cells of its (2r+1)² neighbourhood have a height within ``tol_m`` (NaN = none)."""
    H, W = z.shape
    pad = np.pad(z, radius, mode="constant", constant_values=np.nan)
    n = np.zeros(z.shape, np.int32)
    with np.errstate(invalid="ignore"):
        for di in range(-radius, radius + 1):
            for dj in range(-radius, radius + 1):
                if di == 0 and dj == 0:
                    continue
                nb = pad[radius + di : radius + di + H, radius + dj : radius + dj + W]
                n += np.abs(nb - z) <= tol_m
    return n


def confident_coherent(planes: dict[str, np.ndarray], bin_m: float, min_ncc: float = 0.7) -> np.ndarray:
    """Matches that correlate well (NCC ≥ ``min_ncc``) and agree with ≥ 3 neighbours within 0.3 bin (a surface)."""
    z = planes["z_raw"]
    with np.errstate(invalid="ignore"):
        good = np.isfinite(z) & (planes["best_c"] <= 1.0 - min_ncc)
    # right matches also agree with their neighbours (a surface); wrong ones scatter
    good &= coherent_neighbours(np.where(good, z, np.nan), tol_m=0.3 * bin_m, radius=2) >= 3
    return good


def isolated_matches(z_m: np.ndarray, valid: np.ndarray, tol_m: np.ndarray | float, min_cells: int) -> np.ndarray:
    """Valid cells whose surface patch is smaller than ``min_cells`` (neighbour agreement).

    Valid cells are joined to their 4-neighbours when their heights differ by less than ``tol_m`` (an array:
    the smaller of the two cells' tolerances); a connected patch of fewer than ``min_cells`` cells stands
    alone against every neighbour — a height no surface around it supports. :func:`match_pair` gives
    ``min_cells`` = one matching window (the smallest surface a window matcher resolves) and ``tol_m`` = one
    pixel of disparity (``1 / g``).

    Parameters
    ----------
    z_m : (H, W) float array
        Heights (m); read where ``valid``.
    valid : (H, W) bool array
    tol_m : float or (H, W) float array
        Largest height difference (m) between neighbours of one surface.
    min_cells : int

    Returns
    -------
    (H, W) bool array
        True for valid cells in patches of fewer than ``min_cells`` cells.
    """
    h, w = z_m.shape
    valid = np.asarray(valid, bool)
    if min_cells <= 1 or not valid.any():
        return np.zeros((h, w), bool)
    z = np.where(valid, np.asarray(z_m, np.float64), np.nan)
    tol = np.broadcast_to(np.asarray(tol_m, np.float64), (h, w))
    idx = np.arange(h * w).reshape(h, w)
    src, dst = [], []
    with np.errstate(invalid="ignore"):
        for sl_a, sl_b in (
            ((slice(None), slice(None, -1)), (slice(None), slice(1, None))),
            ((slice(None, -1), slice(None)), (slice(1, None), slice(None))),
        ):
            ok = np.abs(z[sl_a] - z[sl_b]) < np.minimum(tol[sl_a], tol[sl_b])  # False where either is NaN
            src.append(idx[sl_a][ok])
            dst.append(idx[sl_b][ok])
    i = np.concatenate(src)
    j = np.concatenate(dst)
    graph = sparse.coo_matrix((np.ones(i.size, np.int8), (i, j)), shape=(h * w, h * w))
    _, label = csgraph.connected_components(graph, directed=False)
    size = np.bincount(label)[label].reshape(h, w)
    return valid & (size < min_cells)


def surface_slope(z: np.ndarray, good: np.ndarray, posting_m: float, q: float = 99.0) -> float:
    """The ``q``-th percentile of |Δz| / posting between 4-neighbours that are both ``good`` (m per m)."""
    d = []
    for a, b, ok in ((z[:, 1:], z[:, :-1], good[:, 1:] & good[:, :-1]), (z[1:], z[:-1], good[1:] & good[:-1])):
        d.append(np.abs(a - b)[ok])
    d = np.concatenate(d)
    return float(np.percentile(d, q)) / posting_m if d.size else 0.0


def interval_margin_m(
    planes: dict[str, np.ndarray], good: np.ndarray, posting_m: float, step_m: float, radius: int
) -> float:
    """How far the surface may lie beyond the heights a coarse level matched (m).

    A coarse match is the height of a fronto-parallel window ``2·radius + 1`` coarse
    cells wide: on a slope ``s`` the surface inside the window spans ``±(radius + 1)·posting·s``
    around it (a peak's apex lies that far above the window's height), and the parabola
    resolves one height step. ``s`` is the steepest (99th percentile) slope between
    neighbouring confident matches of that level — the data's own, not a constant.
    """
    s = surface_slope(planes["z_raw"], good, posting_m)
    return float(step_m + (radius + 1) * posting_m * s)


def poisson_threshold(lam: float, alpha: float = 1e-3) -> int:
    """Smallest count n with P(Poisson(lam) ≥ n) ≤ alpha: ``scipy.stats.poisson.isf(alpha, lam) + 1``.

    From the regularized incomplete gamma function (``scipy.special.pdtrc``), so that a stereo run does not
    import ``scipy.stats`` (1.3 s of start-up).
    """
    lam = max(float(lam), 1e-12)
    k = max(int(math.ceil(special.pdtrik(1.0 - alpha, lam))), 0)  # the continuous inverse, then the exact count
    while k > 0 and special.pdtrc(k - 1, lam) <= alpha:
        k -= 1
    while special.pdtrc(k, lam) > alpha:
        k += 1
    return k + 1


def _occupied_bins(
    z: np.ndarray,
    good: np.ndarray,
    glo: float,
    bin_m: float,
    nb: int,
    alpha: float,
    lam: float | None = None,
    strong_n: int | None = None,
) -> tuple[float, int, int, np.ndarray]:
    """Background rate, first and last occupied bin grown from the fullest one, and the bin edges.

    Bins with at least ``strong_n`` matches are kept wherever they are (a flat roof high above
    the ground leaves empty bins between)."""
    h, e = np.histogram(z[good], bins=nb, range=(glo, glo + nb * bin_m))
    if lam is None:
        lam = max(float(np.mean(np.sort(h)[: (nb + 1) // 2])), 1.0 / nb)
    occ = h >= poisson_threshold(lam, alpha)
    m = int(np.argmax(h))
    i0 = i1 = m
    while i0 - 1 >= 0 and occ[i0 - 1]:
        i0 -= 1
    while i1 + 1 < nb and occ[i1 + 1]:
        i1 += 1
    if strong_n is not None:
        strong = np.flatnonzero(h >= strong_n)
        if strong.size:
            i0, i1 = min(i0, int(strong[0])), max(i1, int(strong[-1]))
    return lam, i0, i1, e


def robust_height_interval(
    planes: dict[str, np.ndarray],
    lo: np.ndarray,
    hi: np.ndarray,
    bin_m: float,
    min_ncc: float = 0.7,
    margin_m: float | None = None,
    alpha: float = 1e-3,
    window: int | None = None,
    info: dict | None = None,
) -> tuple[float, float] | None:
    """Height interval of the scene from a coarse level's confident matches, or None.

    Right matches pile up at the scene's heights, wrong ones scatter. Histogram
    the heights of the confident, coherent matches (:func:`confident_coherent`) in bins of
    ``bin_m``. The wrong matches that survive those filters scatter over the whole range:
    their count per bin is Poisson with a rate estimated from the emptier half of the
    bins (at least one wrong match over the whole range). A bin is *occupied* when its
    count is significant against that background (P < ``alpha``) — however few cells
    the surface has there (a pyramid's apex). Start from the fullest bin and grow over
    occupied bins (a false match echoed by its neighbours' overlapping windows can make a
    significant bin of its own, so an empty bin is not bridged). With ``window`` (the matching window, in
    cells), a bin holding more than ``(2·window − 1)²`` matches is kept even across empty
    bins: more cells than every window sharing a pixel with one false match — more than one
    wrong match can echo — so a surface (a high flat roof). Add ``margin_m`` (default:
    one bin; see :func:`interval_margin_m`) each side. None when there are too few matches
    or when the interval would not narrow the range at least twofold. ``info``, when
    given, receives ``background_per_bin`` (the Poisson rate above).
    """
    z = planes["z_raw"]
    good = confident_coherent(planes, bin_m, min_ncc)
    if good.sum() < 50:
        return None
    glo, ghi = float(np.nanmin(lo)), float(np.nanmax(hi))
    nb = int(np.ceil((ghi - glo) / bin_m))
    if nb < 8:
        return None
    strong_n = None if window is None else (2 * int(window) - 1) ** 2 + 1
    lam, i0, i1, e = _occupied_bins(z, good, glo, bin_m, nb, alpha, strong_n=strong_n)
    if info is not None:
        info["background_per_bin"] = lam
    margin = bin_m if margin_m is None else float(margin_m)
    a, b = max(e[i0] - margin, glo), min(e[i1 + 1] + margin, ghi)
    if (b - a) > 0.5 * (ghi - glo):
        return None
    return float(a), float(b)


def epipolar_normal(grid: AOIGrid, cams: Sequence[Camera], h: float) -> np.ndarray:
    """Unit vector across the epipolar direction in image b's pixels, at the grid centre and height h.

    As the height of a point seen at a fixed pixel of image a changes, its image in
    b moves along ``e_b = ∂u_b/∂z − ∂u_b/∂(x,y) · A_a`` with ``A_a`` image a's relief
    displacement; the normal is ``e_b`` turned by 90°.
    """
    from .pointing import _jacobians

    H, W = grid.shape
    xc, yc = grid.xy(np.array([H // 2]), np.array([W // 2]))
    Ja_xy, Ja = _jacobians(cams[0], grid, float(xc[0]), float(yc[0]), h)
    Jb_xy, Jb = _jacobians(cams[1], grid, float(xc[0]), float(yc[0]), h)
    e = Jb - Jb_xy @ np.linalg.solve(Ja_xy, Ja)
    n = np.array([-e[1], e[0]])
    return n / max(float(np.linalg.norm(n)), 1e-12)


def _coarsest_pass(g_l, grid, f, chips, cams, lo, hi, step_l, blur, params, sig, excl_steps, progress, prefix):
    """The coarsest level: cross-epipolar offset search, robust height interval, final coarse sweep.

    1. With ``pointing_correction``, sweep the heights for several shifts of image b
       across the epipolar direction (up to ``max_pointing_px``) and keep the shift
       whose matches correlate best (median NCC): a relative pointing error of a few
       pixels otherwise spoils even the coarse matches.
    2. Narrow the height range to the heights where coherent confident matches pile up
       (:func:`robust_height_interval`) and sweep again.
    """
    info: dict[str, Any] = {}
    evaluations = 0
    lo_l = _block_reduce(lo, f, np.min)
    hi_l = _block_reduce(hi, f, np.max)
    shift = np.zeros(2)
    offsets = [0.0]
    if params.pointing_correction and params.max_pointing_px > 0:
        h_mid = float(np.nanmedian(0.5 * (lo + hi)))
        normal = epipolar_normal(grid, cams, h_mid)
        d = max(1.0, 0.5 * f)
        n = int(np.floor(params.max_pointing_px / d))
        offsets = [k * d for k in range(-n, n + 1)]

    blurred = [chips[0].blurred(blur[0]), chips[1].blurred(blur[1])]

    def run(grid_, search, off, pfx):
        cb = blurred[1].shifted(*(off * normal)) if off else blurred[1]
        return sweep_ncc(
            grid_,
            [blurred[0], cb],
            cams,
            search,
            params,
            noise_sigma=sig,
            excl_steps=excl_steps,
            progress=progress,
            prefix=pfx,
        )

    search = HeightSearch(lo_l, hi_l, step_l)
    off = 0.0
    if len(offsets) > 1:
        # the offset is one number for the pair: a central block of the coarse grid is enough to find it
        H, W = g_l.shape
        n = 96
        r0, c0 = max(0, (H - n) // 2), max(0, (W - n) // 2)
        sg = g_l.subgrid(r0, c0, min(n, H), min(n, W))
        ss = HeightSearch(
            lo_l[r0 : r0 + sg.height, c0 : c0 + sg.width],
            hi_l[r0 : r0 + sg.height, c0 : c0 + sg.width],
            step_l,
            search.origin_m,
        )
        best = None
        scores = []
        for o in offsets:
            pl, ev = run(sg, ss, o, f"{prefix}pointing offset {o:+.1f} px ")
            evaluations += ev
            c = pl["best_c"]
            q = float(np.median(1.0 - c[np.isfinite(c)])) if np.isfinite(c).any() else -np.inf
            scores.append(q)
            if best is None or q > best[0]:
                best = (q, o)
        off = best[1]
    planes, ev = run(g_l, search, off, prefix)
    evaluations += ev
    if len(offsets) > 1:
        i = offsets.index(off)
        if 0 < i < len(offsets) - 1:
            cm, c0, cp = scores[i - 1], scores[i], scores[i + 1]
            den = cm - 2 * c0 + cp
            if den < 0:
                off = off + 0.5 * (cm - cp) / den * (offsets[1] - offsets[0])
        shift = off * normal
        info["coarse_pointing_px"] = [float(shift[0]), float(shift[1])]
        info["coarse_pointing_scores"] = {f"{o:+.1f}": round(q, 4) for o, q in zip(offsets, scores)}
    bin_m = 10.0 * step_l
    margin = interval_margin_m(planes, confident_coherent(planes, bin_m), g_l.posting_m, step_l, params.radius)
    stats: dict[str, float] = {}
    iv = robust_height_interval(planes, lo_l, hi_l, bin_m, margin_m=margin, window=params.window, info=stats)
    strong_n = (2 * params.window - 1) ** 2 + 1
    beyond = np.zeros(g_l.shape, bool)
    if iv is not None:
        glo, ghi = float(np.nanmin(lo)), float(np.nanmax(hi))
        nb = int(np.ceil((ghi - glo) / bin_m))
        a, b = iv

        def narrowed(a_, b_):
            lo_n, hi_n = np.maximum(lo, a_), np.minimum(hi, b_)
            bad = ~(hi_n > lo_n)
            return np.where(bad, a_, lo_n), np.where(bad, b_, hi_n)

        lo_n, hi_n = narrowed(a, b)
        planes, ev = run(
            g_l,
            HeightSearch(_block_reduce(lo_n, f, np.min), _block_reduce(hi_n, f, np.max), step_l, search.origin_m),
            float(off),
            f"{prefix}narrowed ",
        )
        evaluations += ev
        # re-search beyond each bound that cut the range: a surface there (a peak whose coarse matches were
        # too few to show in the histogram) matches better beyond the bound than inside it
        extended = []
        for side in (1, -1):
            while True:
                bound, limit = (b, ghi) if side > 0 else (a, glo)
                if (limit - bound) * side <= step_l:
                    break
                width = max(b - a, margin)
                band = (bound, min(bound + width, limit)) if side > 0 else (max(bound - width, limit), bound)
                lo_b = np.maximum(lo_l, band[0])
                hi_b = np.minimum(hi_l, band[1])
                ok_b = hi_b > lo_b
                pb, ev = run(
                    g_l,
                    HeightSearch(np.where(ok_b, lo_b, np.nan), np.where(ok_b, hi_b, np.nan), step_l, search.origin_m),
                    float(off),
                    f"{prefix}beyond {band[0]:.0f}..{band[1]:.0f} m ",
                )
                evaluations += ev
                inside_c = np.where(np.isfinite(planes["best_c"]), planes["best_c"], np.inf)
                with np.errstate(invalid="ignore"):
                    better = np.isfinite(pb["best_c"]) & (pb["best_c"] < inside_c)
                # the scene's interval with these cells' better heights: does the surface go on past the bound?
                comb = {k: np.where(better, pb[k], planes[k]) for k in ("z_raw", "best_c")}
                good_c = confident_coherent(comb, bin_m)
                _, i0, i1, e = _occupied_bins(
                    comb["z_raw"], good_c, glo, bin_m, nb, 1e-3, stats["background_per_bin"], strong_n
                )
                new = min(float(e[i1 + 1]) + margin, ghi) if side > 0 else max(float(e[i0]) - margin, glo)
                if (new - bound) * side > step_l:
                    a, b = (a, new) if side > 0 else (new, b)
                    extended.append([float(band[0]), float(band[1]), round(new, 2)])
                    lo_n, hi_n = narrowed(a, b)
                    planes, ev = run(
                        g_l,
                        HeightSearch(
                            _block_reduce(lo_n, f, np.min), _block_reduce(hi_n, f, np.max), step_l, search.origin_m
                        ),
                        float(off),
                        f"{prefix}extended ",
                    )
                    evaluations += ev
                    continue
                # confident surface patches beyond the bound that do not move it (too few, or apart from the
                # scene's heights): those cells' heights inside it cannot be trusted
                beyond |= better & good_c & ((comb["z_raw"] - bound) * side > 0)
                break
        lo, hi = lo_n, hi_n
        info["coarse_interval_m"] = [float(a), float(b)]
        info["coarse_interval_margin_m"] = float(margin)
        if extended:
            info["coarse_interval_extended"] = extended
        info["beyond_interval_cells"] = int(beyond.sum())
    return planes, lo, hi, evaluations, info, beyond


def incomplete_search(planes: dict[str, np.ndarray]) -> np.ndarray:
    """Cells with a match whose cost was undefined at some heights of their range (out of an image, nodata)."""
    return (planes["best_k"] >= 0) & (planes["nfinite"] < planes["nsearched"])


def _surface_from_planes(planes: dict[str, np.ndarray], factor: int, shape: tuple[int, int]) -> np.ndarray:
    """A smooth approximate surface on the fine grid from a coarse level's matches."""
    z = planes["z_raw"]
    usable = np.isfinite(z) & (planes["best_c"] < 0.8)
    if not usable.any():
        return np.full(shape, np.nan)
    zf = ndimage.median_filter(_fill_nearest(np.where(usable, z, np.nan)), size=5, mode="nearest")
    return upsample_nearest(zf, factor, shape)


def _block_reduce(a: np.ndarray, f: int, fn) -> np.ndarray:
    if f == 1:
        return a
    H, W = a.shape
    Hc, Wc = -(-H // f), -(-W // f)
    pad = np.pad(a, ((0, Hc * f - H), (0, Wc * f - W)), mode="edge")
    return fn(fn(pad.reshape(Hc, f, Wc, f), axis=3), axis=1)


def refine_search(
    planes: dict[str, np.ndarray],
    lo_f: np.ndarray,
    hi_f: np.ndarray,
    factor: int,
    step_coarse: float,
    step_fine: float,
    params: StereoParams,
) -> HeightSearch:
    """Narrow the fine level's search around a coarse level's heights (5×5 min/max ± margin)."""
    z = planes["z_raw"]
    m = params.refine_margin_steps * step_coarse
    usable = np.isfinite(z) & (planes["best_c"] < 0.8)
    if not usable.any():
        return HeightSearch(lo_f, hi_f, step_fine)
    zf = _fill_nearest(np.where(usable, z, np.nan))
    zf = ndimage.median_filter(zf, size=3, mode="nearest")
    w = 5
    lo_c = ndimage.minimum_filter(zf, size=w, mode="nearest") - m
    hi_c = ndimage.maximum_filter(zf, size=w, mode="nearest") + m
    lo = np.maximum(upsample_nearest(lo_c, factor, lo_f.shape), lo_f)
    hi = np.minimum(upsample_nearest(hi_c, factor, hi_f.shape), hi_f)
    bad = ~(hi > lo)
    lo = np.where(bad, lo_f, lo)
    hi = np.where(bad, hi_f, hi)
    return HeightSearch(lo, hi, step_fine)


# ---------------------------------------------------------------------------------------------
# the matcher
# ---------------------------------------------------------------------------------------------
def pad_grid(grid: AOIGrid, pad: int) -> AOIGrid:
    """The grid grown by ``pad`` cells on every side."""
    from affine import Affine

    if pad <= 0:
        return grid
    return AOIGrid(
        grid.crs, grid.transform @ Affine.translation(-pad, -pad), grid.width + 2 * pad, grid.height + 2 * pad
    )


def _crop(a: np.ndarray, pad: int) -> np.ndarray:
    return a[pad : a.shape[0] - pad, pad : a.shape[1] - pad] if pad > 0 else a


def _check_grid(grid: AOIGrid) -> None:
    if grid.crs.is_geographic:
        raise CRSError(
            "the stereo AOI grid must be in a projected CRS in metres (e.g. UTM: geocd.geodesy.utm_crs_for)"
            f", got {grid.crs.name}"
        )


def _empty_pair(grid, name, names, epoch, g, flags_value, meta) -> PairDEM:
    nan = np.full(grid.shape, np.nan, np.float32)
    return PairDEM(
        z_m=nan.copy(),
        score=nan.copy(),
        g_px_per_m=g.astype(np.float32),
        valid=np.zeros(grid.shape, bool),
        grid=grid,
        name=name,
        camera_names=names,
        ncc=nan.copy(),
        ssd=nan.copy(),
        flags=np.full(grid.shape, flags_value, np.uint8),
        z_raw_m=nan.copy(),
        epoch=epoch,
        meta=meta,
    )


def match_pair(
    chip_a: ImageChip,
    chip_b: ImageChip,
    camera_a: Camera,
    camera_b: Camera,
    grid: AOIGrid,
    *,
    dem: Any = None,
    params: StereoParams = StereoParams(),
    name: str | None = None,
    epoch: str = "",
    progress: Progress | None = None,
) -> PairDEM:
    """Dense heights of one image pair on an AOI grid (object-space sweep).

    Parameters
    ----------
    chip_a, chip_b : ImageChip
        Normalized images (:func:`geocd.stereo.prepare_chip`; windows of large images
        carry their offset).
    camera_a, camera_b : Camera
        Any camera kinds (RPC, frame, mixed).
    grid : AOIGrid
        Projected CRS (metres); heights are WGS84 ellipsoidal.
    dem : array on ``grid`` or geocd DEM, optional
        Prior surface for the height search (± ``params.dem_margin_m``).
    params : StereoParams
    name : str, optional
        Pair name (default "<a>__<b>" from the chips' names).
    progress : callable, optional
        ``progress(fraction, message)``, called between tiles and heights.

    Returns
    -------
    PairDEM

    Raises
    ------
    NoOverlapError, ConfigError, EmptyDataError, CRSError
        Images that do not overlap over the AOI, no height range, empty images,
        geographic grid.

    Warns
    -----
    StereoGeometryWarning
        When the pair's base/height ratio is below ``params.min_base_height`` (the
        cells concerned are invalid; the whole pair when it is below everywhere).
    """
    t_start = time.perf_counter()
    _check_grid(grid)
    prog = ensure_progress(progress)
    chips = [chip_a, chip_b]
    cams = [camera_a, camera_b]
    for i, c in enumerate(chips):
        if not np.isfinite(c.data).any():
            raise EmptyDataError(
                f"image {c.name or i + 1} is entirely nodata; check its nodata value and that it covers the AOI"
            )
    names = (chip_a.name or "a", chip_b.name or "b")
    name = name or f"{names[0]}__{names[1]}"
    # match on the grid padded by the window radius, so border cells get whole windows
    out_grid = grid
    pad = params.radius
    grid = pad_grid(out_grid, pad)
    if dem is not None and not (hasattr(dem, "height_m") and hasattr(dem, "grid")):
        dem = np.pad(dem_on_grid(dem, out_grid), pad, mode="edge")
    lo, hi, source = height_bounds(grid, cams, dem, params)
    geo = pair_geometry(grid, cams, chips, lo, hi)
    lonlat = grid.lonlat()  # one CRS transform of the (padded) grid for the whole match
    sig = params.noise_sigma
    if sig is None:
        s = [c.noise_sigma for c in chips if np.isfinite(c.noise_sigma)]
        sig = float(np.sqrt(np.mean(np.square(s)))) if s else 1.0
    sig = max(float(sig), 0.5)
    bh_med = float(np.nanmedian(geo["base_height"]))
    meta: dict[str, Any] = {
        "score_kind": params.score,
        "noise_sigma": sig,
        "height_source": source,
        "base_height_median": bh_med,
        "g_median_px_per_m": float(np.nanmedian(geo["g"])),
        "jmax_px_per_m": geo["jmax"],
        "rho_px_per_m": geo["rho"],
        "overlap": geo["overlap"],
        "params": params.to_dict(),
    }
    # --- degenerate geometry: warn, and skip the sweep when hopeless everywhere
    bh_seen = geo["base_height"][np.isfinite(geo["base_height"])]
    if geo["jmax"] < 1e-6 or np.all(bh_seen < params.min_base_height):
        warnings.warn(
            f"pair {name}: base/height ratio ≈ {bh_med:.3f} is below {params.min_base_height} everywhere "
            "(the two views are nearly the same): its heights would be noise, so every cell is invalid; "
            "use a pair with a wider base",
            StereoGeometryWarning,
            stacklevel=2,
        )
        g = _g_field(out_grid, cams, _crop(0.5 * (lo + hi), pad))[0]
        meta.update(step_m=float("nan"), levels=0, evaluations=0, wall_s=time.perf_counter() - t_start)
        return _empty_pair(out_grid, name, names, epoch, g, FLAGS["weak_geometry"], meta)
    if bh_med < params.min_base_height:
        warnings.warn(
            f"pair {name}: median base/height ratio ≈ {bh_med:.3f} is below {params.min_base_height}; cells "
            "with too weak a geometry are invalidated",
            StereoGeometryWarning,
            stacklevel=2,
        )
    step0 = params.max_step_px / geo["jmax"]
    g_med = max(float(np.nanmedian(geo["g"])), 1e-9)
    excl_steps = max(1.0, params.uniqueness_exclusion_px / (g_med * step0))
    # --- levels: coarse-to-fine while the range needs too many heights
    k0 = float(np.nanmax(hi - lo)) / step0
    level = 0
    while k0 / 2**level > params.max_heights and min(grid.shape) / 2 ** (level + 1) >= 4 * params.window:
        level += 1
    if params.pointing_correction and level < 2:
        # the pointing correction needs an approximate surface: a coarse pass gives it. Its heights also
        # narrow the finer searches: sweeping the full range at full resolution instead (tried) let many
        # more false minima win — on sample_aoi's widest-base pair completeness fell from 93% to 81%.
        while level < 2 and min(grid.shape) / 2 ** (level + 1) >= 4 * params.window:
            level += 1
    if k0 / 2**level > params.max_coarse_heights:
        raise ConfigError(
            f"pair {name}: the height range [{float(np.nanmin(lo)):.0f}, {float(np.nanmax(hi)):.0f}] m needs "
            f"{k0:.0f} height planes of {step0:.3g} m (the images move up to {geo['jmax']:.3g} px per metre of "
            f"height over the AOI) and the {grid.width} × {grid.height}-cell AOI allows only {level} coarser "
            f"level(s), so {k0 / 2**level:.0f} planes per cell at the coarsest, more than the "
            f"{params.max_coarse_heights} allowed; narrow the range (--height-range MIN MAX, ellipsoidal metres), "
            "give a prior DEM ('dem:' in the manifest), or match a larger AOI"
        )
    order = list(range(level, -1, -1))
    pointing: dict[str, Any] = {"applied": False}
    evaluations = 0
    planes = None
    beyond_fine = None
    n_levels = len(order)
    for i, L in enumerate(order):
        f = 2**L
        g_l = coarse_grid(grid, f)
        step_l = step0 * f
        lo_l = _block_reduce(lo, f, np.min)
        hi_l = _block_reduce(hi, f, np.max)
        blur = [max(1, int(round(g_l.posting_m * rho))) for rho in geo["rho"]]
        sub = sub_progress(prog, 0.9 * i / n_levels, 0.9 * (i + 1) / n_levels)
        prefix = f"{name}: level {L} ({g_l.posting_m:g} m) "
        if i == 0 and L > 0:
            planes, lo, hi, ev, info, beyond = _coarsest_pass(
                g_l, grid, f, chips, cams, lo, hi, step_l, blur, params, sig, excl_steps, sub, prefix
            )
            beyond_fine = upsample_nearest(beyond, f, grid.shape)
            evaluations += ev
            meta.update(info)
            if params.pointing_correction:
                chip_b0 = chips[1]
                if info.get("coarse_pointing_px"):
                    chips[1] = chips[1].shifted(*info["coarse_pointing_px"])
                surf = _surface_from_planes(planes, f, grid.shape)
                pointing = relative_pointing(grid, chips, cams, surf, min_patches=params.min_pointing_patches)
                if pointing["applied"]:
                    chips[1] = chips[1].shifted(pointing["dcol"], pointing["drow"])
                pointing["total_shift_px"] = list(chips[1].shift)
                moved = float(np.hypot(chips[1].shift[0] - chip_b0.shift[0], chips[1].shift[1] - chip_b0.shift[1]))
                if moved < params.min_pointing_px:  # below the estimator's own bias: leave b where its camera puts it
                    chips[1] = chip_b0
                    pointing.update(
                        applied=False,
                        not_applied="below min_pointing_px",
                        estimated_shift_px=moved,
                        total_shift_px=list(chip_b0.shift),
                    )
            continue
        search = (
            HeightSearch(lo_l, hi_l, step_l)
            if planes is None
            else refine_search(planes, lo_l, hi_l, 2, step_l * 2, step_l, params)
        )
        chips_l = [c.blurred(b) for c, b in zip(chips, blur)]
        planes, ev = sweep_ncc(
            g_l,
            chips_l,
            cams,
            search,
            params,
            noise_sigma=sig,
            excl_steps=excl_steps,
            progress=sub,
            prefix=prefix,
            lonlat=lonlat if L == 0 else None,
        )
        evaluations += ev
    prog(0.92, f"{name}: scores and checks")
    # chips_l: the images as the finest level matched them (same boxes and shifts as chips)
    out = _finalize(grid, cams, chips_l, planes, search, params, sig, geo, lo, hi, lonlat, beyond_fine)
    out = {k: _crop(v, pad) for k, v in out.items()}
    grid = out_grid
    meta.update(
        step_m=step0,
        levels=n_levels,
        evaluations=evaluations,
        excl_steps=excl_steps,
        pointing=pointing,
        wall_s=time.perf_counter() - t_start,
    )
    prog(1.0, f"{name}: done")
    return PairDEM(grid=grid, name=name, camera_names=names, epoch=epoch, meta=meta, **out)


def _g_field(
    grid: AOIGrid, cams: Sequence[Camera], z: np.ndarray, lonlat: tuple[np.ndarray, np.ndarray] | None = None
) -> tuple[np.ndarray, list[np.ndarray]]:
    """g = ‖J_a − J_b‖ on the grid at heights z, and |J| per camera (px/m)."""
    lon, lat = lonlat if lonlat is not None else grid.lonlat()
    J = []
    for cam in cams:
        dc, dr = cam.ground_projector(lon, lat, None).dproj_dh(z)
        J.append((dc, dr))
    g = np.hypot(J[0][0] - J[1][0], J[0][1] - J[1][1])
    return g, [np.hypot(*j) for j in J]


def occlusion_mask(
    grid: AOIGrid,
    cams: Sequence[Camera],
    chips: Sequence[ImageChip],
    z: np.ndarray,
    cost: np.ndarray,
    tol_m: Sequence[np.ndarray],
    lonlat: tuple[np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """Cells that lose an image pixel to a better-matched cell at another height (see ``zbuffer_occluded``)."""
    ok = np.isfinite(z)
    occ = np.zeros(grid.shape, bool)
    if not ok.any():
        return occ
    lon, lat = lonlat if lonlat is not None else grid.lonlat()
    xs, ys, zs = lon[ok], lat[ok], z[ok].astype(np.float64)
    cs = np.ascontiguousarray(np.where(np.isfinite(cost[ok]), cost[ok], np.inf), np.float64)
    for cam, chip, tol in zip(cams, chips, tol_m):
        c, r = cam.ground_projector(xs, ys, None).project(zs)
        c = c + chip.shift[0]
        r = r + chip.shift[1]
        c0, r0, c1, r1 = chip.box
        o = np.zeros(zs.shape, bool)
        K.zbuffer_occluded(
            np.ascontiguousarray(c, np.float64),
            np.ascontiguousarray(r, np.float64),
            zs,
            cs,
            np.ascontiguousarray(tol[ok], np.float64),
            c0,
            r0,
            c1 - c0,
            r1 - r0,
            o,
        )
        occ[ok] |= o
    return occ


def local_projection(
    grid: AOIGrid, cam: Camera, chip: ImageChip, z: np.ndarray, lonlat: tuple[np.ndarray, np.ndarray] | None = None
) -> np.ndarray:
    """Where each grid cell lands in a chip at height ``z``, and how that moves per grid column and row.

    Returns float64 ``(6, rows, cols)``: col, row (relative to the chip's data, pixel-corner
    convention), ∂col/∂j, ∂row/∂j, ∂col/∂i, ∂row/∂i — the next column's / row's ground
    position projected at the *same* height (forward differences; the last column/row
    extrapolates). NaN where ``z`` is not finite.
    """
    lon, lat = lonlat if lonlat is not None else grid.lonlat()

    def nxt(a: np.ndarray, axis: int) -> np.ndarray:
        a1 = np.take(a, np.arange(1, a.shape[axis]), axis=axis)
        last = 2.0 * np.take(a, [-1], axis=axis) - np.take(a, [-2], axis=axis)
        return np.concatenate([a1, last], axis=axis)

    ok = np.isfinite(z)
    zf = np.where(ok, z, float(np.nanmedian(z)) if ok.any() else 0.0).astype(np.float64)
    c0, r0 = chip.origin
    out = np.empty((6, *z.shape))
    col, row = cam.ground_projector(lon, lat, None).project(zf)
    out[0] = np.where(ok, col - c0, np.nan)
    out[1] = np.where(ok, row - r0, np.nan)
    for n, axis in ((2, 1), (4, 0)):
        c, r = cam.ground_projector(nxt(lon, axis), nxt(lat, axis), None).project(zf)
        out[n] = c - col
        out[n + 1] = r - row
    return out


def subwindow_mdl(
    grid: AOIGrid,
    cams: Sequence[Camera],
    chips: Sequence[ImageChip],
    z: np.ndarray,
    params: StereoParams,
    noise_sigma: float,
    lonlat: tuple[np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """The MDL score of each cell's match as the worst of its sub-windows' scores (bits/pixel).

    Each cell's ``window``² matching window is sampled in both images at the cell's
    height ``z`` (the local projection is affine over a window), cut into
    ``score_subwindow``² sub-windows that tile it (:func:`geocd.stereo._kernels.subwindow_centres`),
    and each sub-window is scored with the MDL formula of :mod:`geocd.stereo.scores`; the
    largest (worst) is returned. A window whose contrast is explained by one surface but
    whose other part is not (it straddles a height step, the classic source of
    "foreground fattening") thus scores like its unexplained part.

    Parameters
    ----------
    grid : AOIGrid; cams, chips : the pair (chips as matched); z : float (rows, cols), m
    params : StereoParams (window, score_subwindow, min_valid_fraction); noise_sigma : σ_n

    Returns
    -------
    float64 (rows, cols), NaN where ``z`` is not finite or no sub-window has enough valid pixels.
    """
    r = params.radius
    q = params.score_subwindow // 2
    geo_ab = [local_projection(grid, cam, chip, z, lonlat) for cam, chip in zip(cams[:2], chips[:2])]
    min_n = float(math.ceil(params.min_valid_fraction * (2 * min(q, r) + 1) ** 2))
    out = np.empty(z.shape)
    K.subwindow_mdl(
        chips[0].data,
        chips[1].data,
        geo_ab[0],
        geo_ab[1],
        r,
        q,
        K.subwindow_centres(r, q),
        min_n,
        float(noise_sigma) ** 2,
        out,
    )
    return out


def _finalize(
    grid, cams, chips, planes, search, params: StereoParams, sig: float, geo, lo, hi, lonlat=None, beyond=None
) -> dict[str, Any]:
    k = planes["best_k"]
    has = k >= 0
    z_raw = planes["z_raw"]
    va, vb, cov = planes["va"], planes["vb"], planes["cov"]
    ncc = np.where(has, ncc_from_stats(va, vb, cov), np.nan)
    ssd = np.where(has, ssd_from_stats(va, vb, cov), np.nan)
    mdl_window = np.where(has, mdl_from_stats(va, vb, cov, sig), np.nan)
    mdl = mdl_window
    if params.score == "mdl" and params.score_subwindow < params.window:
        mdl = subwindow_mdl(grid, cams, chips, z_raw, params, sig, lonlat)
        mdl = np.where(has & np.isfinite(mdl), mdl, mdl_window)
    score = {"mdl": mdl, "ncc": 1.0 - ncc, "ssd": ssd}[params.score]
    flags = np.zeros(grid.shape, np.uint8)
    flags[~has] |= FLAGS["out_of_image"]
    with np.errstate(invalid="ignore"):
        flags[has & (np.minimum(va, vb) < (params.texture_min_snr * sig) ** 2)] |= FLAGS["low_texture"]
        sec = planes["sec_c"]
        flags[has & np.isfinite(sec) & (planes["best_c"] > params.uniqueness_ratio * sec)] |= FLAGS["not_unique"]
        flags[has & ~(np.isfinite(planes["best_cm"]) & np.isfinite(planes["best_cp"]))] |= FLAGS["range_limit"]
        if beyond is not None:  # the coarse level matched these cells better outside the narrowed range
            flags[has & beyond] |= FLAGS["range_limit"]
        # a cell that left an image (or met nodata) over part of its final range was not searched there
        flags[incomplete_search(planes)] |= FLAGS["range_limit"]
        flags[has & ~(ncc >= params.min_ncc)] |= FLAGS["low_ncc"]
    z_eval = np.where(np.isfinite(z_raw), z_raw, 0.5 * (lo + hi))
    # a cell whose own point falls outside an image (or its valid domain) has no height, even when most
    # of its window does
    lon_, lat_ = lonlat if lonlat is not None else grid.lonlat()
    for cam, chip in zip(cams[:2], chips[:2]):
        c, r = cam.ground_projector(lon_, lat_, None).project(z_eval)
        flags[has & ~np.isfinite(chip.warp(c, r))] |= FLAGS["out_of_image"]
    g, jn = _g_field(grid, cams, z_eval, lonlat)
    rho = float(np.mean(geo["rho"]))
    flags[g / rho < params.min_base_height] |= FLAGS["weak_geometry"]
    if params.occlusion_check:
        cand = np.where(flags == 0, z_raw, np.nan)
        tol = [np.maximum(params.occlusion_tol_px / np.maximum(j, 1e-9), 2.0 * search.step_m) for j in jn]
        flags[occlusion_mask(grid, cams, chips, cand, planes["best_c"], tol, lonlat)] |= FLAGS["occluded"]
    min_cells = params.isolation_cells
    if min_cells > 1:
        with np.errstate(divide="ignore", invalid="ignore"):
            tol_m = np.where(g > 0, params.isolation_tol_px / g, 0.0)
        flags[isolated_matches(z_raw, flags == 0, tol_m, min_cells)] |= FLAGS["not_unique"]
    valid = flags == 0
    z_out = np.where(valid, z_raw, np.nan)
    if params.median_size > 1 and valid.any():
        z_out = surface_median(z_out, params.median_size)
    if params.fill_holes and valid.any():
        z_out, filled = fill_narrow_holes(z_out, valid, params.radius)
        flags[filled] |= FLAGS["filled"]
    f32 = np.float32
    return {
        "z_m": z_out.astype(f32),
        "score": score.astype(f32),
        "g_px_per_m": g.astype(f32),
        "valid": valid,
        "ncc": ncc.astype(f32),
        "ssd": ssd.astype(f32),
        "flags": flags,
        "z_raw_m": z_raw.astype(f32),
        "mdl_window": mdl_window.astype(f32),
    }
