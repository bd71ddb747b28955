"""Low-level features of one image (paper §3.1–3.2): gradients, orientation statistics, birth maps,
roof colour and shadow masks, heights; and the texture similarity of two dates.

Angles: a gradient's orientation ϑ and a rectangle's θ are measured in the map sense (counter-clockwise
from the grid's +column axis, with +row pointing south), folded into [−90°, 90°).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from ..errors import ConfigError, EmptyDataError
from ..stereo.photometry import estimate_noise_sigma
from ..terrain import fill_gaps, ground_model
from .params import MPPParams


@dataclass
class ImageFeatures:
    """Everything the energy and the birth process read from one image (arrays (rows, cols) on the grid).

    Attributes
    ----------
    grey : float32, grey level (mean of the bands), invalid cells filled with the median
    valid : bool
    grad_mag : float32, |∇grey| per cell
    grad_ori : float32, gradient orientation (radians, [−π/2, π/2))
    density : float32 (bins, rows, cols), magnitude-weighted orientation density λ_s (sums to 1 over bins)
    alpha, mode_deg : float32, bimodal fit α_s and dominant orientation m_s (degrees, [−90, 0))
    birth : float32, relative birth intensity (mean 1 over the valid cells)
    colour_mask, shadow_mask : uint8 or None (grey images have neither)
    shadow_dir : (dcol, drow) unit vector from a building towards its shadow, or None
    ndsm : float32 height above ground (m) or None
    planar : float32, 1 where the DSM is locally planar (a roof facet, the ground), 0 where it is rough (a tree
        crown), NaN without DSM data; None without a DSM (see :func:`planar_cells`)
    planar_tol_m : the plane-fit residual above which a cell is rough (measured on the ground cells)
    step_min_m : the smallest significant height step at a rectangle's side, 3 √2 σ_z (σ_z: the DSM's
        noise on the ground cells, see :func:`dsm_noise_m`)
    wall_out_m : how far outside the image's edges the DSM's walls fall to 10 % of their height (m; NaN
        when not measurable; see :func:`wall_blur_m`)
    wall_ground_m : the same, where they fall below ``min_height_m`` (the height ring's ground test)
    wall_in_m : how far inside the image's edges they reach 90 % of their height (m)
    noise_sigma : float, grey-level noise σ
    edge_level : float, the top-decile gradient magnitude (what a strong edge is, for snapping births)
    notes : list of str
    """

    grey: np.ndarray
    valid: np.ndarray
    grad_mag: np.ndarray
    grad_ori: np.ndarray
    density: np.ndarray
    alpha: np.ndarray
    mode_deg: np.ndarray
    birth: np.ndarray
    colour_mask: np.ndarray | None = None
    shadow_mask: np.ndarray | None = None
    shadow_dir: tuple[float, float] | None = None
    ndsm: np.ndarray | None = None
    planar: np.ndarray | None = None
    planar_tol_m: float = float("nan")
    step_min_m: float = float("nan")
    wall_out_m: float = float("nan")
    wall_ground_m: float = float("nan")
    wall_in_m: float = float("nan")
    noise_sigma: float = 1.0
    edge_level: float = 0.0
    notes: list[str] = field(default_factory=list)

    @property
    def is_colour(self) -> bool:
        return self.colour_mask is not None


def _bands(image: np.ndarray) -> np.ndarray:
    a = np.asarray(image)
    if a.ndim == 2:
        a = a[None]
    if a.ndim != 3:
        raise ConfigError(f"an image must be (rows, cols) or (bands, rows, cols), got shape {a.shape}")
    return a.astype(np.float32)


def orientation_density(
    grad_mag: np.ndarray, grad_ori: np.ndarray, valid: np.ndarray, window_cells: int, bins: int, kernel_deg: float
) -> np.ndarray:
    """λ_s(ϑ): magnitude-weighted density of gradient orientations over the l×l window around each cell.

    Uniform kernel of half-width ``kernel_deg`` in orientation (circular over 180°), uniform window in
    space. Cells whose window holds no gradient get the uniform density.
    """
    step = 180.0 / bins
    k = np.floor((np.degrees(grad_ori) + 90.0) / step).astype(np.int64) % bins
    w = np.where(valid, grad_mag, 0.0).astype(np.float32)
    half = int(round(kernel_deg / step))
    dens = np.zeros((bins,) + grad_mag.shape, np.float32)
    for b in range(bins):
        m = np.where(k == b, w, 0.0)
        if not m.any():
            continue
        for o in range(-half, half + 1):
            dens[(b + o) % bins] += m
    for b in range(bins):
        dens[b] = ndimage.uniform_filter(dens[b], size=window_cells, mode="constant")
    tot = dens.sum(axis=0)
    ok = tot > 1e-12 * max(float(tot.max()), 1e-30)
    with np.errstate(invalid="ignore", divide="ignore"):
        dens = np.where(ok[None], dens / np.where(ok, tot, 1.0)[None], 1.0 / bins).astype(np.float32)
    return dens


def bimodal_fit(density: np.ndarray, spread_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """α_s = max over m ∈ [−90°, 0) of ∫ λ_s η₂(·, m, d_λ), and the maximising m_s (degrees).

    η₂ is the mixture of two Gaussians (spread d_λ) at m and m + 90°, periodic over 180°.
    """
    bins = density.shape[0]
    step = 180.0 / bins
    d = (np.arange(bins) * step + 90.0) % 180.0 - 90.0  # signed offsets, periodic
    g = np.exp(-0.5 * (d / spread_deg) ** 2)
    g /= g.sum() * step  # density per degree
    # circular correlation along the orientation axis: c[m] = Σ_j λ_j g(j − m)
    F = np.fft.rfft(density, axis=0) * np.conj(np.fft.rfft(g))[:, None, None]
    c = np.fft.irfft(F, n=bins, axis=0) * step
    half = bins // 2
    a2 = 0.5 * (c[:half] + c[half : 2 * half])  # modes at m and m + 90°
    idx = np.argmax(a2, axis=0)
    alpha = np.take_along_axis(a2, idx[None], axis=0)[0].astype(np.float32)
    centres = np.arange(half) * step - 90.0 + 0.5 * step
    return alpha, centres[idx].astype(np.float32)


def colour_masks(bands: np.ndarray, valid: np.ndarray, grey: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Roof-colour mask µ_c (red/terracotta hue, HSV) and shadow mask µ_sh (dark and bluish), paper §3.1.

    Red hue within ±25° of red with saturation ≥ 0.25 and value ≥ 0.15 (of the image's 99th percentile);
    shadow: darker than half the median grey (shadows get only the diffuse sky light, a fraction of the
    direct sun) and blue ≥ red (sky light is blue).
    """
    r, g, b = (bands[k] for k in range(3))
    top = float(np.percentile(np.stack([r, g, b])[:, valid], 99)) or 1.0
    R, G, B = r / top, g / top, b / top
    mx = np.maximum(np.maximum(R, G), B)
    mn = np.minimum(np.minimum(R, G), B)
    with np.errstate(invalid="ignore", divide="ignore"):
        sat = np.where(mx > 0, (mx - mn) / mx, 0.0)
        hue = np.degrees(np.arctan2(math.sqrt(3) * (G - B), 2 * R - G - B))  # 0 = red
    mu_c = (np.abs(hue) <= 25.0) & (sat >= 0.25) & (mx >= 0.15) & valid
    med = float(np.median(grey[valid]))
    mu_sh = (grey < 0.5 * med) & (b >= r) & valid
    return mu_c.astype(np.uint8), mu_sh.astype(np.uint8)


def shadow_direction(
    shadow: np.ndarray, alpha: np.ndarray, reach_cells: float, n_dirs: int = 36
) -> tuple[float, float] | None:
    """Direction (dcol, drow) from buildings to their shadows: the one along which shadow cells have the most
    building-like texture (α) on their sun side, i.e. at ``p − reach · dir``. None when too few shadow cells."""
    ii, jj = np.nonzero(shadow)
    if ii.size < 50:
        return None
    if ii.size > 20000:
        sel = np.random.default_rng(0).choice(ii.size, 20000, replace=False)
        ii, jj = ii[sel], jj[sel]
    H, W = alpha.shape
    best, best_dir = -np.inf, None
    for k in range(n_dirs):
        a = 2 * math.pi * k / n_dirs
        dc, dr = math.cos(a), -math.sin(a)
        js = np.clip(np.round(jj - reach_cells * dc).astype(int), 0, W - 1)
        is_ = np.clip(np.round(ii - reach_cells * dr).astype(int), 0, H - 1)
        jo = np.clip(np.round(jj + reach_cells * dc).astype(int), 0, W - 1)
        io = np.clip(np.round(ii + reach_cells * dr).astype(int), 0, H - 1)
        s = float(np.mean(alpha[is_, js]) - np.mean(alpha[io, jo]))
        if s > best:
            best, best_dir = s, (dc, dr)
    return best_dir


def dsm_ground(dsm_m: np.ndarray, posting_m: float) -> np.ndarray:
    """Terrain under a DSM when none is given: the progressive morphological filter of :mod:`geocd.terrain`
    (gaps filled), which follows a city on a slope where one opening wider than every building sinks to the
    lowest street (on Kahramanmaraş 96 % of the cells stood above such a ground)."""
    d = np.asarray(dsm_m, np.float64)
    if not np.isfinite(d).any():
        return np.zeros(d.shape)
    return fill_gaps(ground_model(d, posting_m)[0]).astype(np.float64)


def fill_roof_holes(
    dsm_m: np.ndarray, ground_m: np.ndarray, min_height_m: float, filled: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Holes of a DSM inside a raised surface take the surface's height; holes half on it become unknown.

    A stereo DSM has no height where matching failed, and that happens on plain roofs as well as on the ground
    beside a building that one view could not see. A DSM's producer may have filled its holes (geocd ortho
    fills them with the terrain, which is right beside a building). A roof cell the matcher missed then reads
    as a pit down to the ground, and the height term takes it for ground inside the building: rectangles stop
    at the pit.

    A hole is a connected set (8-neighbours) of NaN cells and the producer's ``filled`` cells. Its rim is the
    cells with a height that touch it. As geocd ortho reads a hole's surroundings, the rim's lower quartile
    says where it stands: above the ground by more than ``min_height_m`` (the height term's own "raised") or
    not.

    * Enclosed: the rim's lower quartile is raised, no rim cell is low, and the hole does not touch the grid's
      border. The hole is a roof the stereo could not match. Each of its cells takes the height of the nearest
      cell with a height, which lies on that raised rim. A courtyard the matcher missed entirely is filled
      too; a rectangle would cover it anyway.
    * Mixed: the lower quartile is raised but some rim cells are low, or the hole reaches the grid's border.
      The hole may be part roof, or a narrow gap between two buildings. Its cells become NaN, unknown: the
      height term does not count them either way.
    * Other holes are unchanged: NaN stays NaN, and the producer's fill (the terrain beside a building) stays.

    Parameters
    ----------
    dsm_m, ground_m : float (rows, cols), surface and terrain heights (m)
    min_height_m : what stands above the ground (m)
    filled : bool (rows, cols), optional: cells whose height the DSM's producer interpolated (geocd ortho's
        ``filled`` band)

    Returns
    -------
    dsm : float64 (rows, cols), the DSM with its enclosed holes filled and its mixed ones NaN
    roof, unknown : bool (rows, cols), the cells filled and the cells (with a height before) set to NaN here
    """
    d = np.asarray(dsm_m, np.float64).copy()
    hole = ~np.isfinite(d)
    if filled is not None:
        hole |= np.asarray(filled, bool)
    none = np.zeros(d.shape, bool)
    if not hole.any() or hole.all():
        return d, none, none.copy()
    with np.errstate(invalid="ignore"):
        nd = d - np.asarray(ground_m, np.float64)
    eight = np.ones((3, 3), bool)
    lab, n = ndimage.label(hole, structure=eight)
    # each hole's rim: the lower quartile of its nDSM (a rim cell touching two holes counts for one)
    rim_of = ndimage.grey_dilation(lab, footprint=eight) * ~hole
    r = (rim_of > 0) & np.isfinite(nd)
    labs, vals = rim_of[r], nd[r]
    order = np.lexsort((vals, labs))
    labs, vals = labs[order], vals[order]
    counts = np.bincount(labs, minlength=n + 1)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    raised_q = np.zeros(n + 1, bool)
    has = np.flatnonzero(counts > 0)
    pos = starts[has] + 0.25 * (counts[has] - 1)  # np.percentile's linear interpolation
    lo = np.floor(pos).astype(np.int64)
    hi = np.minimum(lo + 1, starts[has] + counts[has] - 1)
    raised_q[has] = vals[lo] + (pos - lo) * (vals[hi] - vals[lo]) > min_height_m
    low = ~hole & ~(nd > min_height_m)  # ground, or no terrain height to tell
    edge = np.zeros(d.shape, bool)
    edge[[0, -1], :] = True
    edge[:, [0, -1]] = True
    touches = np.zeros(n + 1, bool)
    touches[lab[hole & (ndimage.binary_dilation(low, eight) | edge)]] = True
    roof = hole & (raised_q & ~touches)[lab]
    unknown = hole & (raised_q & touches)[lab] & np.isfinite(d)  # NaN cells are unknown already
    if roof.any():
        # the nearest cell with a height to a cell of an enclosed hole lies on that hole's raised rim
        idx = ndimage.distance_transform_edt(hole, return_distances=False, return_indices=True)
        d[roof] = d[idx[0][roof], idx[1][roof]]
    d[unknown] = np.nan
    return d, roof, unknown


def plane_residual(dsm_m: np.ndarray, posting_m: float = 1.0) -> np.ndarray:
    """RMS distance (m) of each cell's 3 × 3 DSM neighbourhood to its least-squares plane, measured along the
    plane's normal (the vertical residual × cos of the slope): a surface's noise does not grow with its tilt.

    3 × 3 is the smallest window that fits a plane: a roof facet or the ground leaves only the DSM's noise, a
    tree crown (a dome with leaves and gaps, rough at the cell scale) or a wall leaves much more. NaN where the
    window holds a cell without height.
    """
    d = np.asarray(dsm_m, np.float64)
    ok = np.isfinite(d)
    z = np.where(ok, d, 0.0)
    full = ndimage.uniform_filter(ok.astype(np.float64), 3, mode="nearest") > 1.0 - 1e-9
    m1 = ndimage.uniform_filter(z, 3, mode="nearest")
    m2 = ndimage.uniform_filter(z * z, 3, mode="nearest")
    kx = np.array([[-1.0, 0.0, 1.0]] * 3) / 6.0  # LS slope per cell along columns (Σx² = 6)
    sx = ndimage.correlate(z, kx, mode="nearest")
    sy = ndimage.correlate(z, kx.T, mode="nearest")
    # residual variance of the plane fit: var(z) − slope² var(x) − slope² var(y), var(x) = var(y) = 2/3
    var = m2 - m1 * m1 - (sx * sx + sy * sy) * (2.0 / 3.0)
    res = np.sqrt(np.maximum(var, 0.0) * 9.0 / 6.0)  # unbiased: 9 cells, 3 plane parameters
    res /= np.sqrt(1.0 + (sx * sx + sy * sy) / (posting_m * posting_m))
    return np.where(full, res, np.nan).astype(np.float32)


def planar_cells(
    dsm_m: np.ndarray, ndsm: np.ndarray, valid: np.ndarray, min_height_m: float, posting_m: float = 1.0
) -> tuple[np.ndarray, float]:
    """Which cells of a DSM lie on a locally planar patch, with the tolerance measured on the DSM itself.

    The tolerance is the noise of one 3 × 3 plane fit on the ground cells (less than ``min_height_m`` above
    the terrain: mostly planar streets, yards and lawns): the median of their residuals + 3 robust σ
    (1.4826 × MAD; walls, cars and bushes are the minority a robust estimate ignores). A cell is planar when
    at least one of the nine 3 × 3 fits that contain it is within that tolerance: a cell on a roof ridge or
    a facet's border lies on a planar patch of its facet, a cell of a tree crown (a dome of leaves and gaps)
    on none. Returns (float32 map: 1 planar, 0 rough, NaN unknown; tolerance in m).
    """
    res = plane_residual(dsm_m, posting_m)
    has = np.isfinite(res) & valid & np.isfinite(ndsm)
    gnd = has & (ndsm < min_height_m)
    if gnd.sum() < 100:  # almost no ground: every observed cell (the median is robust)
        gnd = has
    if not gnd.any():
        return np.full(res.shape, np.nan, np.float32), float("nan")
    r = res[gnd]
    med = float(np.median(r))
    tol = med + 3.0 * 1.4826 * float(np.median(np.abs(r - med)))
    best = ndimage.grey_erosion(np.where(np.isfinite(res), res, np.inf), size=3, mode="nearest")
    planar = np.where(np.isfinite(best), (best <= tol).astype(np.float32), np.nan).astype(np.float32)
    return planar, tol


def dsm_noise_m(
    dsm_m: np.ndarray, ndsm: np.ndarray, valid: np.ndarray, min_height_m: float, posting_m: float = 1.0
) -> float:
    """The DSM's height noise σ_z (m) per cell: the median RMS residual of the 3 × 3 plane fits on the ground
    cells (as in :func:`planar_cells`; a planar patch leaves only the noise, and the median ignores the
    walls, cars and bushes among the ground cells). NaN without ground."""
    res = plane_residual(dsm_m, posting_m)
    has = np.isfinite(res) & valid & np.isfinite(ndsm)
    gnd = has & (ndsm < min_height_m)
    if gnd.sum() < 100:
        gnd = has
    return float(np.median(res[gnd])) if gnd.any() else float("nan")


def wall_blur_m(
    ndsm: np.ndarray,
    grad_mag: np.ndarray,
    grad_ori: np.ndarray,
    valid: np.ndarray,
    edge_level: float,
    posting_m: float,
    min_height_m: float,
    side_min_m: float,
    level: float = 0.1,
    max_cells: int = 20000,
) -> dict:
    """How far a DSM's walls spill outside the image's edges, measured on the scene itself (no truth).

    The image's strong edges (gradient ≥ ``edge_level``, the top decile, and a local maximum across the edge)
    are where the walls are in an orthoimage (a wall is a sharp edge there, a stereo DSM's wall a ramp). Where
    the DSM has a wall across such an edge — it rises by more than ``min_height_m`` from ground (below
    ``min_height_m``) within ``side_min_m`` on the low side to its top within ``side_min_m`` / 2 on the high
    side (half the smallest building: still on its roof) — the nDSM is sampled along the edge's normal
    (bilinear, ¼-cell steps) and scaled to 0 (low) … 1 (high). The median of these profiles falls to
    ``level`` (10 %) at ``out_m`` outside the image edge: the blurred, fattened wall's outer foot. Its rise
    from ``level`` to 1 − ``level`` is ``rise_m``, its half-height crossing ``half_m`` (< 0: outside), and
    ``ground_m`` is where it falls to the ground test of the height ring (nDSM ≤ ``min_height_m``, as a
    fraction of each wall's height, median over the walls); ``in_m`` is how far inside the image edge it
    reaches 1 − ``level`` (90 %): the blurred wall's upper foot.

    Returns a dict: ``out_m`` (m, ≥ 0; NaN when fewer than 50 wall cells are found), ``rise_m``, ``half_m``,
    ``walls`` (the number of edge cells used).
    """
    res = {
        "out_m": float("nan"),
        "ground_m": float("nan"),
        "in_m": float("nan"),
        "rise_m": float("nan"),
        "half_m": float("nan"),
        "walls": 0,
    }
    nd = np.asarray(ndsm, np.float64)
    H, W = nd.shape
    has = np.isfinite(nd)
    if not has.any():
        return res
    ndf = np.where(has, nd, 0.0)
    dc = np.cos(grad_ori).astype(np.float64)  # the gradient's direction in (col, row): (cos, −sin)
    dr = -np.sin(grad_ori).astype(np.float64)
    cand = valid & (grad_mag >= edge_level) & (grad_mag > 0)
    ii, jj = np.nonzero(cand)
    if ii.size == 0:
        return res
    # a local maximum across the edge (nearest cells one step either way along the gradient)
    a = (
        np.clip(np.round(ii + dr[ii, jj]).astype(int), 0, H - 1),
        np.clip(np.round(jj + dc[ii, jj]).astype(int), 0, W - 1),
    )
    b = (
        np.clip(np.round(ii - dr[ii, jj]).astype(int), 0, H - 1),
        np.clip(np.round(jj - dc[ii, jj]).astype(int), 0, W - 1),
    )
    g = grad_mag[ii, jj]
    keep = (g >= grad_mag[a]) & (g >= grad_mag[b])
    ii, jj = ii[keep], jj[keep]
    if ii.size > max_cells:
        sel = np.random.default_rng(0).choice(ii.size, max_cells, replace=False)
        ii, jj = ii[np.sort(sel)], jj[np.sort(sel)]
    step = 0.25
    reach_out = side_min_m / posting_m
    t = np.arange(-reach_out, 0.5 * reach_out + 1e-9, step)  # cells; + towards the high side
    hasf = has.astype(np.float64)

    def profiles(i, j, sign):  # the nDSM at offsets t along sign × the normal (NaN where a sample lacks a height)
        ci = i[:, None] + sign * dr[i, j][:, None] * t[None]
        cj = j[:, None] + sign * dc[i, j][:, None] * t[None]
        at = [ci.ravel(), cj.ravel()]
        pr = ndimage.map_coordinates(ndf, at, order=1, mode="nearest").reshape(ci.shape)
        seen = ndimage.map_coordinates(hasf, at, order=1, mode="nearest").reshape(ci.shape) > 0.999
        return np.where(seen, pr, np.nan)

    prof = profiles(ii, jj, 1.0)
    # orient every profile so that + points to the high side: flip those whose far + end is the lower
    lo_end = np.nanmean(prof[:, t <= -0.5 * reach_out], axis=1)
    hi_end = np.nanmean(prof[:, t >= 0.25 * reach_out], axis=1)
    flip = hi_end < lo_end
    if flip.any():  # sample the other way for those: the same offsets along the reversed normal
        prof[flip] = profiles(ii[flip], jj[flip], -1.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        low = np.nanmin(prof[:, t <= 0], axis=1)
        high = np.nanmax(prof[:, t >= 0], axis=1)
        wall = np.all(np.isfinite(prof), axis=1) & (low < min_height_m) & (high - low > min_height_m)
        if wall.sum() < 50:
            res["walls"] = int(wall.sum())
            return res
        norm = (prof[wall] - low[wall, None]) / (high[wall] - low[wall])[:, None]
        med = np.median(norm, axis=0)

    def crossing(lv):  # from the edge (t = 0) outwards: the first fall below the level
        k0 = int(np.argmin(np.abs(t)))
        if med[k0] < lv:  # already below at the edge: the wall lies inside the image edge
            for k in range(k0, t.size - 1):
                if med[k] < lv <= med[k + 1]:
                    return float(t[k] + (lv - med[k]) / (med[k + 1] - med[k]) * step)
            return float("nan")
        for k in range(k0, 0, -1):
            if med[k - 1] < lv <= med[k]:
                return float(t[k - 1] + (lv - med[k - 1]) / (med[k] - med[k - 1]) * step)
        return float("nan")

    c_lo, c_half, c_hi = crossing(level), crossing(0.5), crossing(1.0 - level)
    # the level of the ground test (nDSM ≤ min_height_m) on the median wall's scale
    lv_g = float(np.median((min_height_m - low[wall]) / (high[wall] - low[wall])))
    c_g = crossing(lv_g) if 0.0 < lv_g < 1.0 else float("nan")
    res.update(
        out_m=max(0.0, -c_lo * posting_m) if np.isfinite(c_lo) else float("nan"),
        ground_m=max(0.0, -c_g * posting_m) if np.isfinite(c_g) else float("nan"),
        in_m=max(0.0, c_hi * posting_m) if np.isfinite(c_hi) else float("nan"),
        rise_m=(c_hi - c_lo) * posting_m,
        half_m=c_half * posting_m,
        walls=int(wall.sum()),
    )
    return res


def segment_sides_m(ndsm: np.ndarray, posting_m: float, min_height_m: float, side_min_m: float) -> np.ndarray:
    """Sides (m) of the raised segments of an nDSM: (n, 2) long and short side of each segment's equivalent
    rectangle (same second moments: side = √12 σ along each principal axis).

    Raised cells (``ndsm > min_height_m``) are opened with a square of ``side_min_m`` / 2 (thin bridges of
    stereo fill between blocks break, segments narrower than half the smallest building vanish), then
    labelled; segments smaller than the smallest building (``side_min_m``²) are skipped.
    """
    raised = np.nan_to_num(ndsm, nan=0.0) > min_height_m
    k = max(1, int(round(0.5 * side_min_m / posting_m)))
    raised = ndimage.binary_opening(raised, structure=np.ones((k, k), bool))
    lab, n = ndimage.label(raised)
    if n == 0:
        return np.zeros((0, 2))
    ii, jj = np.nonzero(lab)
    ll = lab[ii, jj] - 1
    cnt = np.bincount(ll, minlength=n).astype(np.float64)
    mi = np.bincount(ll, ii, n) / cnt
    mj = np.bincount(ll, jj, n) / cnt
    di, dj = ii - mi[ll], jj - mj[ll]
    cii = np.bincount(ll, di * di, n) / cnt
    cjj = np.bincount(ll, dj * dj, n) / cnt
    cij = np.bincount(ll, di * dj, n) / cnt
    tr, det = cii + cjj, cii * cjj - cij * cij
    disc = np.sqrt(np.maximum(0.25 * tr * tr - det, 0.0))
    l1, l2 = 0.5 * tr + disc, np.maximum(0.5 * tr - disc, 0.0)
    sides = np.sqrt(12.0) * np.column_stack([np.sqrt(l1), np.sqrt(l2)]) * posting_m
    keep = cnt * posting_m**2 >= side_min_m**2
    return sides[keep]


def side_max_from_dsm(
    ndsm: np.ndarray, posting_m: float, params: MPPParams = MPPParams(), quantile: float = 0.9
) -> float:
    """The largest rectangle side the scene needs: the ``quantile`` of its raised segments' long sides
    (:func:`segment_sides_m`), never below ``params.side_max_m``. Larger buildings are still unions of
    rectangles, as in the paper; NaN when the nDSM has no raised segment."""
    sides = segment_sides_m(ndsm, posting_m, params.min_height_m, params.side_min_m)
    if sides.shape[0] == 0:
        return float("nan")
    return max(params.side_max_m, float(np.quantile(sides[:, 0], quantile)))


def image_features(
    image: np.ndarray,
    posting_m: float,
    params: MPPParams = MPPParams(),
    *,
    valid: np.ndarray | None = None,
    dsm_m: np.ndarray | None = None,
    ground_m: np.ndarray | None = None,
    use_colour: bool = True,
) -> ImageFeatures:
    """Features of one orthoimage on the AOI grid.

    Parameters
    ----------
    image : (rows, cols) or (bands, rows, cols), any numeric dtype; 3+ bands are read as R, G, B
    posting_m : grid posting (m)
    valid : bool (rows, cols), optional (NaN is invalid too)
    dsm_m, ground_m : optional surface and terrain heights (m) on the grid for the height term; without
        ``ground_m`` the terrain is the progressive morphological filter of :mod:`geocd.terrain` on the DSM
    use_colour : False drops the colour and shadow terms even for a colour image
    """
    bands = _bands(image)
    ok = np.all(np.isfinite(bands), axis=0)
    if valid is not None:
        ok &= np.asarray(valid, bool)
    if not ok.any():
        raise EmptyDataError("the image has no valid cell on the grid; check the orthoimage and its mask")
    notes: list[str] = []
    grey = bands.mean(axis=0)
    med = float(np.median(grey[ok]))
    grey = np.where(ok, grey, med).astype(np.float32)
    sigma = estimate_noise_sigma(np.where(ok, grey, np.nan))
    if not np.isfinite(sigma) or sigma <= 0:
        sigma = float(1.4826 * np.median(np.abs(grey[ok] - med))) * 0.01 or 1e-6
    sm = ndimage.gaussian_filter(grey.astype(np.float64), 1.0)
    gx = ndimage.sobel(sm, axis=1) / 8.0  # per cell, towards +col (east)
    gy = -ndimage.sobel(sm, axis=0) / 8.0  # towards north
    mag = np.hypot(gx, gy).astype(np.float32)
    mag[~ndimage.binary_erosion(ok, iterations=2, border_value=1)] = 0.0  # no edges at nodata borders
    ori = np.arctan2(gy, gx)
    ori = ((ori + np.pi / 2) % np.pi - np.pi / 2).astype(np.float32)
    win = max(3, int(round(params.window / posting_m)) | 1)
    dens = orientation_density(mag, ori, ok, win, params.orient_bins, params.orient_kernel_deg)
    has_grad = ndimage.uniform_filter(mag, size=win, mode="constant") > 1e-9
    alpha, mode = bimodal_fit(dens, params.mode_spread_deg)
    alpha = np.where(has_grad & ok, alpha, 0.0).astype(np.float32)
    births = [alpha / max(float(alpha[ok].mean()), 1e-30)]
    colour = shadow = sdir = None
    if bands.shape[0] >= 3 and use_colour:
        colour, shadow = colour_masks(bands, ok, grey)
        # the colour cue is informative only where the roof-colour mask can hold a building: a connected patch
        # at least as large as the smallest rectangle; otherwise the image is read with the grey-image model
        # (the paper chose its prototypes per data set: no colour, no shadow term for its grey-roofed sets)
        lab, nlab = ndimage.label(colour)
        largest = int(np.bincount(lab.ravel())[1:].max()) if nlab else 0
        smallest = int(math.ceil((params.side_min_m / posting_m) ** 2))
        if largest < smallest:
            notes.append(
                f"the roof-colour mask covers {colour[ok].mean():.1%} of the cells in patches of at most "
                f"{largest} cells, none the size of a building ({smallest} cells): colour and shadow "
                "terms dropped, grey-image model"
            )
            colour = shadow = None
    if colour is not None:
        gam = ndimage.uniform_filter(colour.astype(np.float32), size=win, mode="constant")
        if gam.mean() > 0:
            births.append(gam / float(gam[ok].mean()))
        sdir = shadow_direction(shadow, alpha, 0.5 * win)
        if sdir is not None:
            near = _beside_shadow(shadow.astype(bool), sdir, 0.5 * win)
            frac = float(near[ok].mean())
            if frac > 0:
                births.append(np.where(near, 1.0 / frac, 0.1).astype(np.float32))
            notes.append(
                f"shadows fall towards azimuth {math.degrees(math.atan2(sdir[0], -sdir[1])) % 360:.0f}° "
                "(estimated from the image)"
            )
        else:
            notes.append("too few shadow cells: shadow term dropped")
            shadow = None
    elif bands.shape[0] < 3 or not use_colour:
        notes.append(
            "grey image: colour and shadow terms dropped"
            if bands.shape[0] < 3
            else "colour and shadow terms switched off"
        )
    edge_level = float(np.percentile(mag[ok], 90))  # what a strong edge is (births' snapping, walls)
    ndsm = planar = None
    planar_tol = step_min = wall_out = wall_ground = wall_in = float("nan")
    if dsm_m is not None:
        d = np.asarray(dsm_m, np.float64)
        if d.shape != grey.shape:
            raise ConfigError(f"DSM shape {d.shape} does not match the image {grey.shape}; put both on the grid")
        gr = np.asarray(ground_m, np.float64) if ground_m is not None else dsm_ground(d, posting_m)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            ndsm = (d - gr).astype(np.float32)
        # a median over half the smallest building side removes stereo pits and spikes smaller than any
        # building (holes stay holes)
        k = max(3, int(round(0.5 * params.side_min_m / posting_m)) | 1)
        has = np.isfinite(ndsm)
        med = ndimage.median_filter(np.where(has, ndsm, 0.0), size=k, mode="nearest")
        ndsm = np.where(has, med, np.nan).astype(np.float32)
        planar, planar_tol = planar_cells(d, ndsm, ok, params.min_height_m, posting_m)
        if np.isfinite(planar_tol):
            notes.append(
                f"DSM planarity: a cell is rough above a plane-fit residual of {planar_tol:.2f} m "
                "(the noise of one 3 × 3 plane fit on the ground cells)"
            )
        sigma_z = dsm_noise_m(d, ndsm, ok, params.min_height_m, posting_m)
        if np.isfinite(sigma_z):
            # a step between the mean heights just inside and just outside a side, each as noisy as one cell
            # (stereo DSM errors are correlated over a few cells), is significant at 3 σ of a difference
            step_min = 3.0 * math.sqrt(2.0) * sigma_z
            notes.append(
                f"DSM steps: an outline steps down where inside − outside ≥ {step_min:.2f} m "
                f"(3 √2 σ_z, σ_z = {sigma_z:.3f} m on the ground cells)"
            )
        blur = wall_blur_m(ndsm, mag, ori, ok, edge_level, posting_m, params.min_height_m, params.side_min_m)
        wall_out, wall_ground, wall_in = blur["out_m"], blur["ground_m"], blur["in_m"]
        if np.isfinite(wall_out):
            notes.append(
                f"DSM walls: they rise from 10 % of their height {wall_out:.2f} m outside the image's edges "
                f"to 90 % {wall_in:.2f} m inside, "
                f"below {params.min_height_m:g} m {wall_ground:.2f} m outside (half height "
                f"{-blur['half_m']:+.2f} m outside, 10–90 % rise {blur['rise_m']:.2f} m; median over "
                f"{blur['walls']} wall cells)"
            )
        raised = ndimage.uniform_filter(
            (np.nan_to_num(ndsm, nan=0.0) > params.min_height_m).astype(np.float32),
            size=max(3, win // 2) | 1,
            mode="constant",
        )
        if raised[ok].mean() > 0:
            births.append(raised / float(raised[ok].mean()))
    birth = np.max(np.stack(births), axis=0)
    birth = np.where(ok, birth, 0.0)
    mb = float(birth[ok].mean())
    birth = (birth / mb if mb > 0 else birth).astype(np.float32)
    return ImageFeatures(
        grey=grey,
        valid=ok,
        grad_mag=mag,
        grad_ori=ori,
        density=dens,
        alpha=alpha,
        mode_deg=mode,
        birth=birth,
        colour_mask=colour,
        shadow_mask=shadow,
        shadow_dir=sdir,
        ndsm=ndsm,
        planar=planar,
        planar_tol_m=planar_tol,
        step_min_m=step_min,
        wall_out_m=wall_out,
        wall_ground_m=wall_ground,
        wall_in_m=wall_in,
        noise_sigma=float(sigma),
        edge_level=edge_level,
        notes=notes,
    )


def _beside_shadow(shadow: np.ndarray, sdir: tuple[float, float], reach: float) -> np.ndarray:
    """Cells within ``reach`` of a shadow cell on its sun side (where the casting buildings stand)."""
    out = np.zeros_like(shadow)
    n = max(1, int(math.ceil(reach)))
    for t in range(1, n + 1):
        out |= ndimage.shift(shadow.astype(np.uint8), (-t * sdir[1], -t * sdir[0]), order=0, mode="constant") > 0
    return out & ~shadow


def otsu_threshold(x: np.ndarray, bins: int = 256) -> float:
    """Otsu's threshold: the value that best splits ``x`` into two classes (largest between-class variance)."""
    x = np.asarray(x, np.float64)
    x = x[np.isfinite(x)]
    if x.size == 0 or x.max() <= x.min():
        return float(x.max()) if x.size else 0.0
    h, e = np.histogram(x, bins)
    c = 0.5 * (e[1:] + e[:-1])
    w = np.cumsum(h).astype(np.float64)
    mu = np.cumsum(h * c)
    tot = w[-1]
    m1 = mu / np.maximum(w, 1)
    m2 = (mu[-1] - mu) / np.maximum(tot - w, 1)
    return float(e[1:][np.argmax(w * (tot - w) * (m1 - m2) ** 2)])


def texture_change(f1: ImageFeatures, f2: ImageFeatures) -> tuple[np.ndarray, np.ndarray, float]:
    """Bhattacharyya distance b(s) = −log Σ sqrt(λ¹ λ²) of the two dates' orientation densities, the binary
    similarity B (1 = unchanged texture: b ≤ b0; 0.5 where a date has no data) and b0.

    b0 is Otsu's threshold of b over the cells both images see: the split of the scene into the two most
    distinct classes of texture difference, assuming no change fraction (floor 1e-3: identical textures)."""
    bc = np.sum(np.sqrt(np.maximum(f1.density, 0) * np.maximum(f2.density, 0)), axis=0)
    b = -np.log(np.clip(bc, 1e-12, 1.0)).astype(np.float32)
    both = f1.valid & f2.valid
    b0 = max(otsu_threshold(b[both]), 1e-3) if both.any() else 1e-3
    B = (b <= b0).astype(np.float32)
    B[~both] = 0.5  # no evidence either way
    return b, B, b0


def height_similarity(f1: ImageFeatures, f2: ImageFeatures, min_height_m: float, texture: np.ndarray) -> np.ndarray:
    """The ξ term's similarity B read from the two DSMs instead of the texture (beyond the paper).

    A cell is unchanged (B = 1) when it stands more than ``min_height_m`` above the ground on both dates or
    on neither, changed (B = 0) when it stands on one date only: a building that appeared or went. Tree
    crowns stand on both dates, and a roof seen under another sun or from another view keeps its height,
    where the orientation densities of the paper's texture term differ. Where either DSM has no data, B is
    the texture's (``texture``, float32 (rows, cols), from :func:`texture_change`).

    Returns float32 (rows, cols) in {0, 1} (and the texture's 0.5 where neither image has data).
    """
    if f1.ndsm is None or f2.ndsm is None:
        raise ConfigError("the height evidence for ξ needs a DSM of each date")
    ok = np.isfinite(f1.ndsm) & np.isfinite(f2.ndsm)
    with np.errstate(invalid="ignore"):
        same = (f1.ndsm > min_height_m) == (f2.ndsm > min_height_m)
    return np.where(ok, same.astype(np.float32), np.asarray(texture, np.float32)).astype(np.float32)
