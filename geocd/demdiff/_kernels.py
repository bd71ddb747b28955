"""Numba kernels of DEM differencing, each with a small pure-numpy reference.

* :func:`terrain_attributes` — slope, aspect (Horn 1981), maximum curvature
  (Zevenbergen & Thorne 1987) and roughness (max − min of the 3×3 window) of a
  north-up DEM; NaN where the 3×3 window is incomplete.
* :func:`shift_grid` — translate a DEM by a sub-pixel offset (bilinear or Keys
  cubic convolution, NaN-aware: a cell is NaN when its support touches NaN);
  :func:`shift_window` does the same on a window of a larger grid (tiles) with the
  whole grid's arithmetic, so a tile's cells equal the whole grid's.
* :func:`variogram_bins` — empirical semivariance of scattered samples, all
  pairs, binned by distance.

The references (``*_ref``) are what the tests compare the kernels with.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np


# ------------------------------------------------------------------------------------------
# terrain attributes
# ------------------------------------------------------------------------------------------
@nb.njit(cache=True, nogil=True)
def _terrain_kernel(h, px, py, slope, aspect, maxc, rough):  # pragma: no cover - numba
    nr, nc = h.shape
    for r in range(nr):
        for c in range(nc):
            slope[r, c] = np.nan
            aspect[r, c] = np.nan
            maxc[r, c] = np.nan
            rough[r, c] = np.nan
            if r == 0 or c == 0 or r == nr - 1 or c == nc - 1:
                continue
            z1 = h[r - 1, c - 1]
            z2 = h[r - 1, c]
            z3 = h[r - 1, c + 1]
            z4 = h[r, c - 1]
            z5 = h[r, c]
            z6 = h[r, c + 1]
            z7 = h[r + 1, c - 1]
            z8 = h[r + 1, c]
            z9 = h[r + 1, c + 1]
            s = z1 + z2 + z3 + z4 + z5 + z6 + z7 + z8 + z9
            if not math.isfinite(s):
                continue
            # Horn: dz/dx (east), dz/dy (north; rows go south)
            dzdx = ((z3 + 2.0 * z6 + z9) - (z1 + 2.0 * z4 + z7)) / (8.0 * px)
            dzdy = ((z1 + 2.0 * z2 + z3) - (z7 + 2.0 * z8 + z9)) / (8.0 * py)
            g = math.sqrt(dzdx * dzdx + dzdy * dzdy)
            slope[r, c] = math.atan(g)
            # aspect: azimuth (clockwise from north) of steepest descent = direction of -grad
            a = math.atan2(-dzdx, -dzdy)
            if a < 0.0:
                a += 2.0 * math.pi
            aspect[r, c] = a
            # Zevenbergen & Thorne second derivatives (y axis northwards)
            d = ((z4 + z6) / 2.0 - z5) / (px * px)
            e = ((z2 + z8) / 2.0 - z5) / (py * py)
            f = (-z1 + z3 + z7 - z9) / (4.0 * px * py)
            gx = (z6 - z4) / (2.0 * px)
            hy = (z2 - z8) / (2.0 * py)
            p2 = gx * gx + hy * hy
            if p2 > 1e-12:
                prof = -2.0 * (d * gx * gx + e * hy * hy + f * gx * hy) / p2
                plan = 2.0 * (d * hy * hy + e * gx * gx - f * gx * hy) / p2
            else:
                prof = -2.0 * (d + e)
                plan = prof
            maxc[r, c] = 100.0 * max(abs(prof), abs(plan))
            mx = z1
            mn = z1
            for v in (z2, z3, z4, z5, z6, z7, z8, z9):
                if v > mx:
                    mx = v
                if v < mn:
                    mn = v
            rough[r, c] = mx - mn


def terrain_attributes(height_m: np.ndarray, posting_xy_m: tuple[float, float]) -> dict[str, np.ndarray]:
    """Slope, aspect, maximum curvature and roughness of a north-up DEM.

    Parameters
    ----------
    height_m : float (rows, cols), NaN = nodata
    posting_xy_m : (x, y) cell size in metres (positive)

    Returns
    -------
    dict of float32 (rows, cols) arrays: ``slope_rad`` (0..π/2), ``aspect_rad`` (azimuth of
    steepest descent, clockwise from north, 0..2π), ``max_curvature`` (100/m, the larger of
    |profile| and |planform| curvature), ``roughness_m`` (max − min in the 3×3 window).
    NaN where the 3×3 window is incomplete (edges, next to nodata).
    """
    h = np.ascontiguousarray(height_m, dtype=np.float64)
    out = [np.empty(h.shape, np.float64) for _ in range(4)]
    _terrain_kernel(h, float(posting_xy_m[0]), float(posting_xy_m[1]), *out)
    names = ("slope_rad", "aspect_rad", "max_curvature", "roughness_m")
    return {k: v.astype(np.float32) for k, v in zip(names, out)}


def terrain_attributes_ref(height_m: np.ndarray, posting_xy_m: tuple[float, float]) -> dict[str, np.ndarray]:
    """Pure-numpy reference of :func:`terrain_attributes`."""
    h = np.asarray(height_m, np.float64)
    px, py = posting_xy_m
    nr, nc = h.shape
    pad = np.full((nr + 2, nc + 2), np.nan)
    pad[1:-1, 1:-1] = h
    z = {
        k: pad[1 + dr : nr + 1 + dr, 1 + dc : nc + 1 + dc]
        for k, (dr, dc) in {
            1: (-1, -1),
            2: (-1, 0),
            3: (-1, 1),
            4: (0, -1),
            5: (0, 0),
            6: (0, 1),
            7: (1, -1),
            8: (1, 0),
            9: (1, 1),
        }.items()
    }
    with np.errstate(invalid="ignore", divide="ignore"):
        dzdx = ((z[3] + 2 * z[6] + z[9]) - (z[1] + 2 * z[4] + z[7])) / (8 * px)
        dzdy = ((z[1] + 2 * z[2] + z[3]) - (z[7] + 2 * z[8] + z[9])) / (8 * py)
        slope = np.arctan(np.hypot(dzdx, dzdy))
        aspect = np.mod(np.arctan2(-dzdx, -dzdy), 2 * np.pi)
        d = ((z[4] + z[6]) / 2 - z[5]) / px**2
        e = ((z[2] + z[8]) / 2 - z[5]) / py**2
        f = (-z[1] + z[3] + z[7] - z[9]) / (4 * px * py)
        gx = (z[6] - z[4]) / (2 * px)
        hy = (z[2] - z[8]) / (2 * py)
        p2 = gx**2 + hy**2
        flat = p2 <= 1e-12
        p2s = np.where(flat, 1.0, p2)
        prof = np.where(flat, -2 * (d + e), -2 * (d * gx**2 + e * hy**2 + f * gx * hy) / p2s)
        plan = np.where(flat, -2 * (d + e), 2 * (d * hy**2 + e * gx**2 - f * gx * hy) / p2s)
        maxc = 100 * np.maximum(np.abs(prof), np.abs(plan))
        stack = np.stack([z[k] for k in range(1, 10)])
        rough = stack.max(axis=0) - stack.min(axis=0)
    bad = ~np.isfinite(stack.sum(axis=0))
    out = {"slope_rad": slope, "aspect_rad": aspect, "max_curvature": maxc, "roughness_m": rough}
    for k in out:
        out[k] = np.where(bad, np.nan, out[k]).astype(np.float32)
    return out


# ------------------------------------------------------------------------------------------
# sub-pixel translation
# ------------------------------------------------------------------------------------------
@nb.njit(cache=True, inline="always")
def _keys(t):  # pragma: no cover - numba
    a = -0.5
    t = abs(t)
    if t <= 1.0:
        return (a + 2.0) * t**3 - (a + 3.0) * t**2 + 1.0
    if t < 2.0:
        return a * t**3 - 5.0 * a * t**2 + 8.0 * a * t - 4.0 * a
    return 0.0


@nb.njit(cache=True, nogil=True)
def _shift_kernel(h, dcol, drow, cubic, out):  # pragma: no cover - numba
    nr, nc = h.shape
    lo = -1 if cubic else 0
    hi = 3 if cubic else 2
    wy = np.zeros(4)
    wx = np.zeros(4)
    for r in range(nr):
        y = r - drow
        r0 = int(math.floor(y))
        fy = y - r0
        for k in range(lo, hi):
            wy[k - lo] = _keys(k - fy) if cubic else (1.0 - fy if k == 0 else fy)
        for c in range(nc):
            # value at (r, c) of the translated surface = h at (r - drow, c - dcol)
            x = c - dcol
            c0 = int(math.floor(x))
            fx = x - c0
            for k in range(lo, hi):
                wx[k - lo] = _keys(k - fx) if cubic else (1.0 - fx if k == 0 else fx)
            acc = 0.0
            ok = True
            for i in range(lo, hi):
                a = wy[i - lo]
                if a == 0.0:
                    continue
                rr = r0 + i
                if rr < 0 or rr >= nr:
                    ok = False
                    break
                for j in range(lo, hi):
                    b = wx[j - lo]
                    if b == 0.0:
                        continue
                    cc = c0 + j
                    if cc < 0 or cc >= nc:
                        ok = False
                        break
                    acc += a * b * h[rr, cc]
                if not ok:
                    break
            out[r, c] = acc if ok else np.nan


def shift_grid(height_m: np.ndarray, shift_col_px: float, shift_row_px: float, method: str = "bilinear") -> np.ndarray:
    """Translate a raster surface by a sub-pixel offset.

    ``out[r, c] = height_m(r − shift_row_px, c − shift_col_px)``: the surface moves by
    +shift columns (east on a north-up grid) and +shift rows (south). Cells whose
    interpolation support (taps with non-zero weight) leaves the grid or touches NaN
    are NaN; a zero shift returns the input unchanged.

    Parameters
    ----------
    height_m : float (rows, cols)
    method : "bilinear" (2×2 support) or "cubic" (Keys a = −0.5, 4×4 support)
    """
    if method not in ("bilinear", "cubic"):
        raise ValueError(f"method must be 'bilinear' or 'cubic', got {method!r}")
    h = np.ascontiguousarray(height_m, dtype=np.float64)
    out = np.empty_like(h)
    _shift_kernel(h, float(shift_col_px), float(shift_row_px), method == "cubic", out)
    return out


@nb.njit(cache=True, nogil=True)
def _shift_window_kernel(h, r0, c0, nr, nc, dcol, drow, cubic, out):  # pragma: no cover - numba
    # _shift_kernel on a window of a grid of nr × nc cells whose first cell is (r0, c0): the same
    # arithmetic on whole-grid indices, so every cell gets the value it gets on the whole grid.
    # Returns False when a tap falls outside the window but inside the grid (window too small).
    wr, wc = h.shape
    lo = -1 if cubic else 0
    hi = 3 if cubic else 2
    wy = np.zeros(4)
    wx = np.zeros(4)
    enough = True
    for r in range(wr):
        y = (r0 + r) - drow
        rb = int(math.floor(y))
        fy = y - rb
        for k in range(lo, hi):
            wy[k - lo] = _keys(k - fy) if cubic else (1.0 - fy if k == 0 else fy)
        for c in range(wc):
            x = (c0 + c) - dcol
            cb = int(math.floor(x))
            fx = x - cb
            for k in range(lo, hi):
                wx[k - lo] = _keys(k - fx) if cubic else (1.0 - fx if k == 0 else fx)
            acc = 0.0
            ok = True
            inside = True
            for i in range(lo, hi):
                a = wy[i - lo]
                if a == 0.0:
                    continue
                rr = rb + i
                if rr < 0 or rr >= nr:
                    ok = False
                    break
                for j in range(lo, hi):
                    b = wx[j - lo]
                    if b == 0.0:
                        continue
                    cc = cb + j
                    if cc < 0 or cc >= nc:
                        ok = False
                        break
                    if rr - r0 < 0 or rr - r0 >= wr or cc - c0 < 0 or cc - c0 >= wc:
                        inside = False
                        continue
                    acc += a * b * h[rr - r0, cc - c0]
                if not ok:
                    break
            if ok and not inside:
                out[r, c] = np.nan
                enough = False
            else:
                out[r, c] = acc if ok else np.nan
    return enough


def shift_window(
    height_m: np.ndarray,
    origin: tuple[int, int],
    full_shape: tuple[int, int],
    shift_col_px: float,
    shift_row_px: float,
    method: str = "bilinear",
) -> np.ndarray:
    """:func:`shift_grid` on a window of a larger grid, with the whole grid's arithmetic and borders.

    ``height_m`` is the window of a grid of ``full_shape`` whose first cell is ``origin`` (row, col).
    A cell whose interpolation support lies inside the window gets exactly the value
    :func:`shift_grid` gives it on the whole grid; a cell whose support leaves the window
    (but not the grid) is NaN: a tile needs :func:`shift_margin` cells of overlap.
    """
    if method not in ("bilinear", "cubic"):
        raise ValueError(f"method must be 'bilinear' or 'cubic', got {method!r}")
    h = np.ascontiguousarray(height_m, dtype=np.float64)
    out = np.empty_like(h)
    _shift_window_kernel(
        h,
        int(origin[0]),
        int(origin[1]),
        int(full_shape[0]),
        int(full_shape[1]),
        float(shift_col_px),
        float(shift_row_px),
        method == "cubic",
        out,
    )
    return out


@nb.njit(cache=True, nogil=True)
def _shift_points_kernel(patches, pr0, pc0, rows, cols, nr, nc, dcol, drow, cubic, out):  # pragma: no cover
    # _shift_kernel's value at whole-grid cells (rows[k], cols[k]), the grid known only on a patch
    # around each cell (patches[k] starts at (pr0[k], pc0[k])). Returns False when a tap inside the
    # grid falls outside its patch (that cell is NaN: gather larger patches).
    P, Q = patches.shape[1], patches.shape[2]
    lo = -1 if cubic else 0
    hi = 3 if cubic else 2
    wy = np.zeros(4)
    wx = np.zeros(4)
    enough = True
    for k in range(rows.shape[0]):
        y = rows[k] - drow
        rb = int(math.floor(y))
        fy = y - rb
        for q in range(lo, hi):
            wy[q - lo] = _keys(q - fy) if cubic else (1.0 - fy if q == 0 else fy)
        x = cols[k] - dcol
        cb = int(math.floor(x))
        fx = x - cb
        for q in range(lo, hi):
            wx[q - lo] = _keys(q - fx) if cubic else (1.0 - fx if q == 0 else fx)
        acc = 0.0
        ok = True
        inside = True
        for i in range(lo, hi):
            a = wy[i - lo]
            if a == 0.0:
                continue
            rr = rb + i
            if rr < 0 or rr >= nr:
                ok = False
                break
            for j in range(lo, hi):
                b = wx[j - lo]
                if b == 0.0:
                    continue
                cc = cb + j
                if cc < 0 or cc >= nc:
                    ok = False
                    break
                pi = rr - pr0[k]
                pj = cc - pc0[k]
                if pi < 0 or pi >= P or pj < 0 or pj >= Q:
                    inside = False
                    continue
                acc += a * b * patches[k, pi, pj]
            if not ok:
                break
        if ok and not inside:
            out[k] = np.nan
            enough = False
        else:
            out[k] = acc if ok else np.nan
    return enough


def shift_points(
    patches: np.ndarray,
    patch_rows: np.ndarray,
    patch_cols: np.ndarray,
    rows: np.ndarray,
    cols: np.ndarray,
    full_shape: tuple[int, int],
    shift_col_px: float,
    shift_row_px: float,
    method: str = "bilinear",
) -> tuple[np.ndarray, bool]:
    """:func:`shift_grid` at chosen cells of a grid known only on a patch around each cell.

    Parameters
    ----------
    patches : float (n, P, Q), the grid's values on a window around each cell
    patch_rows, patch_cols : int (n,), whole-grid index of each patch's first cell
    rows, cols : int (n,), the cells
    full_shape : (rows, cols) of the whole grid (its borders make cells NaN as in :func:`shift_grid`)

    Returns
    -------
    values : float64 (n,), what ``shift_grid(grid, ...)[rows, cols]`` holds
    complete : False when some cell's support left its patch (those cells are NaN)
    """
    if method not in ("bilinear", "cubic"):
        raise ValueError(f"method must be 'bilinear' or 'cubic', got {method!r}")
    pa = np.ascontiguousarray(patches, dtype=np.float64)
    out = np.empty(pa.shape[0], np.float64)
    ok = _shift_points_kernel(
        pa,
        np.ascontiguousarray(patch_rows, np.int64),
        np.ascontiguousarray(patch_cols, np.int64),
        np.ascontiguousarray(rows, np.int64),
        np.ascontiguousarray(cols, np.int64),
        int(full_shape[0]),
        int(full_shape[1]),
        float(shift_col_px),
        float(shift_row_px),
        method == "cubic",
        out,
    )
    return out, bool(ok)


def shift_margin(shift_col_px: float, shift_row_px: float, method: str = "bilinear") -> int:
    """Cells of context a window needs for :func:`shift_window` to equal :func:`shift_grid` on its core."""
    return int(math.ceil(max(abs(shift_col_px), abs(shift_row_px)))) + (3 if method == "cubic" else 2)


def _weights_ref(f: np.ndarray, cubic: bool) -> list[tuple[int, np.ndarray]]:
    if not cubic:
        return [(0, 1.0 - f), (1, f)]
    a = -0.5
    out = []
    for k in range(-1, 3):
        t = np.abs(k - f)
        w = np.where(
            t <= 1,
            (a + 2) * t**3 - (a + 3) * t**2 + 1,
            np.where(t < 2, a * t**3 - 5 * a * t**2 + 8 * a * t - 4 * a, 0.0),
        )
        out.append((k, w))
    return out


def shift_grid_ref(
    height_m: np.ndarray, shift_col_px: float, shift_row_px: float, method: str = "bilinear"
) -> np.ndarray:
    """Pure-numpy reference of :func:`shift_grid`."""
    h = np.asarray(height_m, np.float64)
    nr, nc = h.shape
    cubic = method == "cubic"
    y = np.arange(nr) - shift_row_px
    x = np.arange(nc) - shift_col_px
    r0 = np.floor(y).astype(int)
    c0 = np.floor(x).astype(int)
    wys = _weights_ref(y - r0, cubic)
    wxs = _weights_ref(x - c0, cubic)
    acc = np.zeros(h.shape)
    ok = np.ones(h.shape, bool)
    for i, wy in wys:
        rr = r0 + i
        rin = (rr >= 0) & (rr < nr)
        for j, wx in wxs:
            cc = c0 + j
            cin = (cc >= 0) & (cc < nc)
            w = wy[:, None] * wx[None, :]
            use = w != 0
            vals = h[np.clip(rr, 0, nr - 1)][:, np.clip(cc, 0, nc - 1)]
            ok &= ~use | (rin[:, None] & cin[None, :])
            acc += np.where(use, w * vals, 0.0)
    return np.where(ok, acc, np.nan)


# ------------------------------------------------------------------------------------------
# empirical variogram
# ------------------------------------------------------------------------------------------
@nb.njit(cache=True, nogil=True)
def _variogram_kernel(x, y, z, edges, sums, counts):  # pragma: no cover - numba
    n = x.shape[0]
    nb_ = edges.shape[0] - 1
    e0 = edges[0]
    emax = edges[nb_]
    e0sq = e0 * e0
    emaxsq = emax * emax
    for i in range(n):
        xi = x[i]
        yi = y[i]
        zi = z[i]
        for j in range(i + 1, n):
            dx = x[j] - xi
            dy = y[j] - yi
            d2 = dx * dx + dy * dy
            if d2 < e0sq or d2 >= emaxsq:
                continue
            d = math.sqrt(d2)
            # binary search of the bin
            lo = 0
            hi = nb_
            while hi - lo > 1:
                mid = (lo + hi) // 2
                if d >= edges[mid]:
                    lo = mid
                else:
                    hi = mid
            dz = z[j] - zi
            sums[lo] += 0.5 * dz * dz
            counts[lo] += 1


def variogram_bins(
    x_m: np.ndarray, y_m: np.ndarray, values: np.ndarray, edges_m: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Empirical semivariance of all sample pairs, binned by distance.

    Parameters
    ----------
    x_m, y_m, values : float (n,)
    edges_m : float (nbins + 1,), increasing distance bin edges (left-closed)

    Returns
    -------
    gamma : float (nbins,), mean of ½(z_i − z_j)² over the pairs in each bin (NaN when empty)
    counts : int64 (nbins,), number of pairs
    """
    edges = np.ascontiguousarray(edges_m, np.float64)
    sums = np.zeros(edges.size - 1)
    counts = np.zeros(edges.size - 1, np.int64)
    _variogram_kernel(
        np.ascontiguousarray(x_m, np.float64),
        np.ascontiguousarray(y_m, np.float64),
        np.ascontiguousarray(values, np.float64),
        edges,
        sums,
        counts,
    )
    with np.errstate(invalid="ignore", divide="ignore"):
        gamma = np.where(counts > 0, sums / np.maximum(counts, 1), np.nan)
    return gamma, counts


def variogram_bins_ref(x_m, y_m, values, edges_m) -> tuple[np.ndarray, np.ndarray]:
    """Pure-numpy reference of :func:`variogram_bins` (O(n²) memory: small n only)."""
    from scipy.spatial.distance import pdist

    pts = np.column_stack([x_m, y_m]).astype(np.float64)
    d = pdist(pts)
    g = 0.5 * pdist(np.asarray(values, np.float64)[:, None], "sqeuclidean")
    edges = np.asarray(edges_m, np.float64)
    idx = np.searchsorted(edges, d, side="right") - 1
    ok = (idx >= 0) & (idx < edges.size - 1) & (d < edges[-1])
    counts = np.bincount(idx[ok], minlength=edges.size - 1).astype(np.int64)
    sums = np.bincount(idx[ok], weights=g[ok], minlength=edges.size - 1)
    with np.errstate(invalid="ignore", divide="ignore"):
        gamma = np.where(counts > 0, sums / np.maximum(counts, 1), np.nan)
    return gamma, counts
