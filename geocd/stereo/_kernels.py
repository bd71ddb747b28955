"""numba kernels of the object-space stereo matcher, each with a pure-numpy reference.

Conventions
-----------
* Images are float32 ``(rows, cols)`` with NaN for invalid pixels; image
  coordinates ``(col, row)`` are continuous with ``(0, 0)`` at the upper-left
  *corner* of the upper-left pixel (geocd/GDAL convention), so the centre of
  array element ``[i, j]`` is ``(j + 0.5, i + 0.5)``.
* Window moments are sums over the ``(2r+1)²`` cells around each cell (clipped
  at the array border) of the cells where *both* images are valid:
  ``m[0] = n``, ``m[1] = Σa``, ``m[2] = Σb``, ``m[3] = Σa²``, ``m[4] = Σb²``,
  ``m[5] = Σab`` (float64).
* The sweep state (:data:`NSTATE` planes per cell) follows the matching cost
  ``c(k) = 1 − NCC_reg(k)`` along the height index ``k`` and keeps the best and
  second-best local minima (see :func:`sweep_update`).
"""

from __future__ import annotations

import warnings

import numpy as np
from numba import njit, prange
from numpy.lib.stride_tricks import sliding_window_view

from .._jit import parallel_njit
from .._select import select_kth as _select

# ---------------------------------------------------------------------------------------------
# bilinear warp
# ---------------------------------------------------------------------------------------------


@njit(cache=True, inline="always")
def _bilinear(img, x, y):
    """Bilinear sample of ``img`` at ``(x, y)`` = (col, row) − 0.5; NaN outside (see :func:`warp_bilinear`)."""
    H, W = img.shape
    if not (x >= 0.0 and y >= 0.0 and x <= W - 1 and y <= H - 1):
        return np.nan
    j0 = int(x)
    i0 = int(y)
    if j0 > W - 2:
        j0 = W - 2
    if i0 > H - 2:
        i0 = H - 2
    if j0 < 0 or i0 < 0:  # 1-pixel-wide image
        return np.nan
    fx = x - j0
    fy = y - i0
    v00 = img[i0, j0]
    v01 = img[i0, j0 + 1]
    v10 = img[i0 + 1, j0]
    v11 = img[i0 + 1, j0 + 1]
    return (v00 * (1.0 - fx) + v01 * fx) * (1.0 - fy) + (v10 * (1.0 - fx) + v11 * fx) * fy


@parallel_njit()
def warp_bilinear(img, col, row, out):
    """Sample ``img`` at continuous ``(col, row)`` (pixel-corner convention), bilinear.

    A sample is NaN when any of its four neighbours is outside the image or NaN.

    Parameters
    ----------
    img : float32 (H, W)
    col, row : float64 (h, w), image coordinates relative to ``img``
    out : float32 (h, w), written
    """
    h, w = col.shape
    for i in prange(h):
        for j in range(w):
            out[i, j] = _bilinear(img, col[i, j] - 0.5, row[i, j] - 0.5)


def warp_bilinear_ref(img: np.ndarray, col: np.ndarray, row: np.ndarray) -> np.ndarray:
    """numpy reference of :func:`warp_bilinear`."""
    H, W = img.shape
    x = col - 0.5
    y = row - 0.5
    inside = (x >= 0) & (y >= 0) & (x <= W - 1) & (y <= H - 1)
    xs = np.where(inside, x, 0.0)
    ys = np.where(inside, y, 0.0)
    j0 = np.minimum(np.floor(xs).astype(np.int64), max(W - 2, 0))
    i0 = np.minimum(np.floor(ys).astype(np.int64), max(H - 2, 0))
    fx = xs - j0
    fy = ys - i0
    j1 = np.minimum(j0 + 1, W - 1)
    i1 = np.minimum(i0 + 1, H - 1)
    v = (img[i0, j0] * (1 - fx) + img[i0, j1] * fx) * (1 - fy) + (img[i1, j0] * (1 - fx) + img[i1, j1] * fx) * fy
    v = v.astype(np.float32)
    v[~inside] = np.nan
    if W < 2 or H < 2:
        v[:] = np.nan
    return v


@parallel_njit()
def warp_bilinear_lerp(img, col_a, row_a, col_b, row_b, t, col0, row0, out):
    """:func:`warp_bilinear` at coordinates interpolated between two projections.

    Samples ``img`` at ``(col_a + t (col_b − col_a) − col0, row_a + t (row_b − row_a) − row0)``:
    the sweep projects exactly every few planes and interpolates in between.
    """
    H, W = img.shape
    h, w = col_a.shape
    for i in prange(h):
        for j in range(w):
            x = col_a[i, j] + t * (col_b[i, j] - col_a[i, j]) - col0 - 0.5
            y = row_a[i, j] + t * (row_b[i, j] - row_a[i, j]) - row0 - 0.5
            out[i, j] = _bilinear(img, x, y)


# ---------------------------------------------------------------------------------------------
# window moments by running sums (separable box filter)
# ---------------------------------------------------------------------------------------------


@njit(cache=True, inline="always")
def _row_moments(a, b, r, i, work):
    """Running sums of row ``i`` over windows of ``2r+1`` columns (both-valid pixels) into ``work[:, i, :]``:
    n, Σa, Σb, Σa², Σb², Σab (the horizontal pass of :func:`box_moments` and :func:`sweep_step`)."""
    w = a.shape[1]
    s0 = 0.0
    s1 = 0.0
    s2 = 0.0
    s3 = 0.0
    s4 = 0.0
    s5 = 0.0
    # prime with columns [0, r-1]
    for j in range(min(r, w)):
        x = np.float64(a[i, j])
        y = np.float64(b[i, j])
        if x == x and y == y:
            s0 += 1.0
            s1 += x
            s2 += y
            s3 += x * x
            s4 += y * y
            s5 += x * y
    for j in range(w):
        jin = j + r
        if jin < w:
            x = np.float64(a[i, jin])
            y = np.float64(b[i, jin])
            if x == x and y == y:
                s0 += 1.0
                s1 += x
                s2 += y
                s3 += x * x
                s4 += y * y
                s5 += x * y
        jout = j - r - 1
        if jout >= 0:
            x = np.float64(a[i, jout])
            y = np.float64(b[i, jout])
            if x == x and y == y:
                s0 -= 1.0
                s1 -= x
                s2 -= y
                s3 -= x * x
                s4 -= y * y
                s5 -= x * y
        work[0, i, j] = s0
        work[1, i, j] = s1
        work[2, i, j] = s2
        work[3, i, j] = s3
        work[4, i, j] = s4
        work[5, i, j] = s5


@parallel_njit()
def box_moments(a, b, r, out, work):
    """Window moments of two images over ``(2r+1)²`` windows, both-valid pixels only.

    Cost O(cells) whatever the window (running sums along rows, then columns).

    Parameters
    ----------
    a, b : float32 (h, w), NaN = invalid
    r : int, window radius (cells)
    out : float64 (6, h, w), written: n, Σa, Σb, Σa², Σb², Σab
    work : float64 (6, h, w), scratch
    """
    h, w = a.shape
    # horizontal running sums, one row per thread
    for i in prange(h):
        _row_moments(a, b, r, i, work)
    # vertical running sums, one block of columns per thread (rows stay contiguous)
    nblk = (w + 31) // 32
    for bk in prange(nblk):
        j0 = bk * 32
        j1 = min(w, j0 + 32)
        for c in range(6):
            for j in range(j0, j1):
                out[c, 0, j] = 0.0
            for i in range(min(r, h)):
                for j in range(j0, j1):
                    out[c, 0, j] += work[c, i, j]
            # out row 0 holds rows [0, r-1]; now walk
            for i in range(h):
                iin = i + r
                iout = i - r - 1
                for j in range(j0, j1):
                    v = out[c, i - 1, j] if i > 0 else out[c, 0, j]
                    if iin < h:
                        v += work[c, iin, j]
                    if iout >= 0:
                        v -= work[c, iout, j]
                    out[c, i, j] = v


def box_moments_ref(a: np.ndarray, b: np.ndarray, r: int) -> np.ndarray:
    """numpy reference of :func:`box_moments` (integral images)."""
    ok = np.isfinite(a) & np.isfinite(b)
    A = np.where(ok, a, 0.0).astype(np.float64)
    B = np.where(ok, b, 0.0).astype(np.float64)
    planes = [ok.astype(np.float64), A, B, A * A, B * B, A * B]
    h, w = a.shape
    out = np.empty((6, h, w))
    i0 = np.clip(np.arange(h) - r, 0, h)
    i1 = np.clip(np.arange(h) + r + 1, 0, h)
    j0 = np.clip(np.arange(w) - r, 0, w)
    j1 = np.clip(np.arange(w) + r + 1, 0, w)
    for c, p in enumerate(planes):
        S = np.zeros((h + 1, w + 1))
        S[1:, 1:] = p.cumsum(0).cumsum(1)
        out[c] = S[i1][:, j1] - S[i0][:, j1] - S[i1][:, j0] + S[i0][:, j0]
    return out


@parallel_njit()
def box_mean(x, r, out, count, work):
    """Mean of the valid (finite) values of ``x`` over ``(2r+1)²`` windows, by running sums.

    Parameters
    ----------
    x : float32 or float64 (h, w), NaN = invalid
    out : float64 (h, w), written (NaN where the window holds no valid value)
    count : float64 (h, w), written: valid values per window
    work : float64 (2, h, w), scratch
    """
    h, w = x.shape
    for i in prange(h):
        s = 0.0
        n = 0.0
        for j in range(min(r, w)):
            v = np.float64(x[i, j])
            if v == v:
                s += v
                n += 1.0
        for j in range(w):
            jin = j + r
            if jin < w:
                v = np.float64(x[i, jin])
                if v == v:
                    s += v
                    n += 1.0
            jout = j - r - 1
            if jout >= 0:
                v = np.float64(x[i, jout])
                if v == v:
                    s -= v
                    n -= 1.0
            work[0, i, j] = s
            work[1, i, j] = n
    for j in prange(w):
        s = 0.0
        n = 0.0
        for i in range(min(r, h)):
            s += work[0, i, j]
            n += work[1, i, j]
        for i in range(h):
            iin = i + r
            iout = i - r - 1
            if iin < h:
                s += work[0, iin, j]
                n += work[1, iin, j]
            if iout >= 0:
                s -= work[0, iout, j]
                n -= work[1, iout, j]
            count[i, j] = n
            out[i, j] = s / n if n > 0.5 else np.nan


def box_mean_ref(x: np.ndarray, r: int) -> tuple[np.ndarray, np.ndarray]:
    """numpy reference of :func:`box_mean`: (mean, count)."""
    ok = np.isfinite(x)
    m = box_moments_ref(np.where(ok, x, np.nan).astype(np.float64), np.zeros_like(x, np.float64), r)
    n = m[0]
    with np.errstate(all="ignore"):
        mean = np.where(n > 0.5, m[1] / n, np.nan)
    return mean, n


# ---------------------------------------------------------------------------------------------
# the sweep state: best / second-best local minima of the cost along k
# ---------------------------------------------------------------------------------------------

#: state planes
(
    PREV1,
    PREV2,
    BEST_C,
    BEST_K,
    BEST_CM,
    BEST_CP,
    BEST_VA,
    BEST_VB,
    BEST_COV,
    BEST_N,
    SEC_C,
    SEC_K,
    PREV_VA,
    PREV_VB,
    PREV_COV,
    PREV_N,
    NFINITE,
) = range(17)
NSTATE = 17


def new_state(shape: tuple[int, int]) -> np.ndarray:
    """A fresh sweep state (float64 ``(NSTATE, h, w)``)."""
    s = np.zeros((NSTATE, *shape))
    for p in (PREV1, PREV2, BEST_C, BEST_CM, BEST_CP, SEC_C):
        s[p] = np.inf
    s[BEST_K] = -1
    s[SEC_K] = -1
    return s


@njit(cache=True, inline="always")
def _ncc_cost(n, sa, sb, saa, sbb, sab, min_n, eps):
    """(cost, va, vb, cov) from window sums; cost = 1 − cov/sqrt((va+eps)(vb+eps)); inf if n < min_n."""
    if n < min_n or n <= 0.0:
        return np.inf, 0.0, 0.0, 0.0
    inv = 1.0 / n
    ma = sa * inv
    mb = sb * inv
    va = saa * inv - ma * ma
    vb = sbb * inv - mb * mb
    if va < 0.0:
        va = 0.0
    if vb < 0.0:
        vb = 0.0
    cov = sab * inv - ma * mb
    return 1.0 - cov / np.sqrt((va + eps) * (vb + eps)), va, vb, cov


@njit(cache=True, inline="always")
def _insert_min(st, i, j, c0, kk, cm, cp, va, vb, cov, n, excl):
    bc = st[BEST_C, i, j]
    bk = st[BEST_K, i, j]
    if c0 < bc:
        if bk >= 0.0 and abs(bk - kk) > excl:
            st[SEC_C, i, j] = bc
            st[SEC_K, i, j] = bk
        elif st[SEC_K, i, j] >= 0.0 and abs(st[SEC_K, i, j] - kk) <= excl:
            st[SEC_C, i, j] = np.inf
            st[SEC_K, i, j] = -1.0
        st[BEST_C, i, j] = c0
        st[BEST_K, i, j] = kk
        st[BEST_CM, i, j] = cm
        st[BEST_CP, i, j] = cp
        st[BEST_VA, i, j] = va
        st[BEST_VB, i, j] = vb
        st[BEST_COV, i, j] = cov
        st[BEST_N, i, j] = n
    elif abs(kk - bk) > excl and c0 < st[SEC_C, i, j]:
        st[SEC_C, i, j] = c0
        st[SEC_K, i, j] = kk


@njit(cache=True, inline="always")
def _fold_cell(st, i, j, k, kmin_ij, kmax_ij, n, sa, sb, saa, sbb, sab, min_n, eps, excl):
    """Fold height index ``k`` of cell (i, j), given its window sums, into the sweep state (see :func:`sweep_update`)."""
    if k > kmax_ij or k < kmin_ij:
        c = np.inf
        va = 0.0
        vb = 0.0
        cov = 0.0
        n = 0.0
    else:
        c, va, vb, cov = _ncc_cost(n, sa, sb, saa, sbb, sab, min_n, eps)
    if c < np.inf:
        st[NFINITE, i, j] += 1.0
    p1 = st[PREV1, i, j]
    p2 = st[PREV2, i, j]
    if p1 < p2 and p1 <= c:
        _insert_min(
            st,
            i,
            j,
            p1,
            k - 1.0,
            p2,
            c,
            st[PREV_VA, i, j],
            st[PREV_VB, i, j],
            st[PREV_COV, i, j],
            st[PREV_N, i, j],
            excl,
        )
    st[PREV2, i, j] = p1
    st[PREV1, i, j] = c
    st[PREV_VA, i, j] = va
    st[PREV_VB, i, j] = vb
    st[PREV_COV, i, j] = cov
    st[PREV_N, i, j] = n


@parallel_njit()
def sweep_update(mom, k, kmin, kmax, min_n, eps, excl, st):
    """Fold height index ``k`` into the sweep state.

    The cost at ``k`` is ``1 − NCC_reg`` from the window moments ``mom``
    (``NCC_reg = cov / sqrt((va + eps)(vb + eps))``: ``eps`` = noise variance,
    so textureless windows score ≈ 0 instead of noise); cells outside their
    range ``kmin ≤ k ≤ kmax`` or with fewer than ``min_n`` valid window cells get
    ``+inf``.
    A local minimum at ``k − 1`` (``c(k−2) > c(k−1) ≤ c(k)``) is recorded with its
    neighbours' costs (for the parabola) and its window statistics. The best
    minimum is kept, and the best *other* minimum more than ``excl`` steps away
    (for the uniqueness test). Call :func:`sweep_finish` after the last ``k``.

    Parameters
    ----------
    mom : float64 (6, h, w), window moments at height index k (or None-like zeros)
    k : int
    kmin, kmax : int32 (h, w), first and last height index of each cell
    st : float64 (NSTATE, h, w), updated in place
    """
    h, w = kmax.shape
    for i in prange(h):
        for j in range(w):
            _fold_cell(
                st,
                i,
                j,
                k,
                kmin[i, j],
                kmax[i, j],
                mom[0, i, j],
                mom[1, i, j],
                mom[2, i, j],
                mom[3, i, j],
                mom[4, i, j],
                mom[5, i, j],
                min_n,
                eps,
                excl,
            )


@parallel_njit()
def sweep_finish(k_end, excl, st):
    """Close the sweep after the last index ``k_end − 1`` (a minimum there has ``c+ = inf``)."""
    h = st.shape[1]
    w = st.shape[2]
    for i in prange(h):
        for j in range(w):
            p1 = st[PREV1, i, j]
            p2 = st[PREV2, i, j]
            if p1 < p2 and p1 < np.inf:
                _insert_min(
                    st,
                    i,
                    j,
                    p1,
                    k_end - 1.0,
                    p2,
                    np.inf,
                    st[PREV_VA, i, j],
                    st[PREV_VB, i, j],
                    st[PREV_COV, i, j],
                    st[PREV_N, i, j],
                    excl,
                )
            st[PREV2, i, j] = p1
            st[PREV1, i, j] = np.inf


@parallel_njit()
def sweep_step(a, b, r, k, kmin, kmax, min_n, eps, excl, st, work):
    """:func:`box_moments` followed by :func:`sweep_update`, fused (the moments are never stored).

    Parameters as those two kernels; ``work`` is float64 (6, h, w) scratch.
    """
    h, w = a.shape
    for i in prange(h):
        _row_moments(a, b, r, i, work)
    nblk = (w + 31) // 32
    for bk in prange(nblk):
        j0 = bk * 32
        j1 = min(w, j0 + 32)
        nb = j1 - j0
        acc = np.zeros((6, nb))
        for i in range(min(r, h)):
            for c in range(6):
                for jj in range(nb):
                    acc[c, jj] += work[c, i, j0 + jj]
        for i in range(h):
            iin = i + r
            iout = i - r - 1
            for c in range(6):
                for jj in range(nb):
                    v = acc[c, jj]
                    if iin < h:
                        v += work[c, iin, j0 + jj]
                    if iout >= 0:
                        v -= work[c, iout, j0 + jj]
                    acc[c, jj] = v
            for jj in range(nb):
                j = j0 + jj
                _fold_cell(
                    st,
                    i,
                    j,
                    k,
                    kmin[i, j],
                    kmax[i, j],
                    acc[0, jj],
                    acc[1, jj],
                    acc[2, jj],
                    acc[3, jj],
                    acc[4, jj],
                    acc[5, jj],
                    min_n,
                    eps,
                    excl,
                )


def ncc_cost_ref(mom: np.ndarray, min_n: float, eps: float) -> tuple[np.ndarray, ...]:
    """numpy reference of the cost: (cost, va, vb, cov) arrays from moments (6, ...)."""
    from .scores import window_stats

    n, va, vb, cov = window_stats(mom)
    with np.errstate(all="ignore"):
        c = 1.0 - cov / np.sqrt((va + eps) * (vb + eps))
    bad = (n < min_n) | (n <= 0)
    c = np.where(bad, np.inf, c)
    return c, np.where(bad, 0, va), np.where(bad, 0, vb), np.where(bad, 0, cov)


def sweep_ref(costs: np.ndarray, excl: float) -> dict[str, np.ndarray]:
    """numpy reference of the sweep on a full cost volume ``costs[k, ...]`` (inf = no cost).

    Returns the best local minimum (cost, k, c−, c+) and the best minimum more than
    ``excl`` away from it, found with the same streaming rule as the kernel (so that
    results agree exactly, including its approximation for clustered minima).
    """
    K = costs.shape[0]
    shape = costs.shape[1:]
    ext = np.concatenate([np.full((1, *shape), np.inf), costs, np.full((1, *shape), np.inf)])
    best_c = np.full(shape, np.inf)
    best_k = np.full(shape, -1.0)
    best_cm = np.full(shape, np.inf)
    best_cp = np.full(shape, np.inf)
    sec_c = np.full(shape, np.inf)
    sec_k = np.full(shape, -1.0)
    for kk in range(K):
        c0 = ext[kk + 1]
        cm = ext[kk]
        cp = ext[kk + 2]
        is_min = (c0 < cm) & (c0 <= cp) & np.isfinite(c0)
        if kk == K - 1:
            is_min = (c0 < cm) & np.isfinite(c0)
        better = is_min & (c0 < best_c)
        far_old = better & (best_k >= 0) & (np.abs(best_k - kk) > excl)
        drop_sec = better & ~far_old & (sec_k >= 0) & (np.abs(sec_k - kk) <= excl)
        sec_c = np.where(far_old, best_c, np.where(drop_sec, np.inf, sec_c))
        sec_k = np.where(far_old, best_k, np.where(drop_sec, -1.0, sec_k))
        worse = is_min & ~better & (np.abs(kk - best_k) > excl) & (c0 < sec_c)
        sec_c = np.where(worse, c0, sec_c)
        sec_k = np.where(worse, kk, sec_k)
        best_c = np.where(better, c0, best_c)
        best_k = np.where(better, kk, best_k)
        best_cm = np.where(better, cm, best_cm)
        best_cp = np.where(better, cp, best_cp)
    return {"best_c": best_c, "best_k": best_k, "best_cm": best_cm, "best_cp": best_cp, "sec_c": sec_c, "sec_k": sec_k}


# ---------------------------------------------------------------------------------------------
# the MDL score of a match from its sub-windows
# ---------------------------------------------------------------------------------------------


@njit(cache=True, inline="always")
def _mdl_ratio(va, vb, cov, s2):
    """2^(2·MDL score) of two windows from their variances and covariance (k = 2): the score of
    :func:`geocd.stereo.scores.mdl_from_stats` is ½·log2 of it, so the worst of several windows is
    found without a logarithm each."""
    st2 = max((va + vb + 2.0 * cov) / 4.0, 0.0)
    v = max((va + vb - 2.0 * cov) / 2.0, 0.0)
    return (st2 + s2) * (v + s2) / ((va + s2) * (vb + s2))


@parallel_njit()
def subwindow_mdl(img_a, img_b, geo_a, geo_b, r, q, centres, min_n, s2, out):
    """Worst MDL score over the sub-windows of each cell's matching window, at the cell's height.

    The ``(2r+1)²`` window of cell ``(i, j)`` is sampled in each image at the cell's
    own height through the local affine map of the projection: window cell ``(u, v)``
    (rows, cols from the centre) lies at ``col + v·∂col/∂j + u·∂col/∂i`` (same for
    rows). Every ``(2q+1)²`` sub-window centred on ``centres × centres`` with at least
    ``min_n`` pixels valid in both images is scored with the MDL formula; ``out`` is
    the largest (worst) of these scores, NaN when none qualifies.

    Parameters
    ----------
    img_a, img_b : float32 (H, W) image chips (NaN = invalid)
    geo_a, geo_b : float64 (6, h, w): col, row (relative to the chip, pixel-corner
        convention), ∂col/∂j, ∂row/∂j, ∂col/∂i, ∂row/∂i per grid cell; NaN col = no match
    r, q : window and sub-window radii (cells); centres : int64 (m,) sub-window centre offsets
    min_n : float, valid pixels a sub-window needs; s2 : noise variance σ_n²
    out : float64 (h, w), written
    """
    h, w = out.shape
    side = 2 * r + 1
    m = centres.shape[0]
    for i in prange(h):
        wa = np.empty((side, side))
        wb = np.empty((side, side))
        for j in range(w):
            ca = geo_a[0, i, j]
            cb = geo_b[0, i, j]
            if not (np.isfinite(ca) and np.isfinite(cb)):
                out[i, j] = np.nan
                continue
            for u in range(-r, r + 1):
                for v in range(-r, r + 1):
                    xa = ca + v * geo_a[2, i, j] + u * geo_a[4, i, j] - 0.5
                    ya = geo_a[1, i, j] + v * geo_a[3, i, j] + u * geo_a[5, i, j] - 0.5
                    xb = cb + v * geo_b[2, i, j] + u * geo_b[4, i, j] - 0.5
                    yb = geo_b[1, i, j] + v * geo_b[3, i, j] + u * geo_b[5, i, j] - 0.5
                    wa[u + r, v + r] = _bilinear(img_a, xa, ya)
                    wb[u + r, v + r] = _bilinear(img_b, xb, yb)
            worst = -1.0  # largest 2^(2·score) so far (ratios are > 0)
            for p in range(m):
                for t in range(m):
                    n = 0.0
                    sa = 0.0
                    sb = 0.0
                    saa = 0.0
                    sbb = 0.0
                    sab = 0.0
                    for u in range(centres[p] - q, centres[p] + q + 1):
                        for v in range(centres[t] - q, centres[t] + q + 1):
                            a = wa[u + r, v + r]
                            b = wb[u + r, v + r]
                            if np.isfinite(a) and np.isfinite(b):
                                n += 1.0
                                sa += a
                                sb += b
                                saa += a * a
                                sbb += b * b
                                sab += a * b
                    if n < min_n or n < 2.0:
                        continue
                    ma = sa / n
                    mb = sb / n
                    q2 = _mdl_ratio(max(saa / n - ma * ma, 0.0), max(sbb / n - mb * mb, 0.0), sab / n - ma * mb, s2)
                    if q2 > worst:
                        worst = q2
            out[i, j] = 0.5 * np.log2(worst) if worst > 0.0 else np.nan


def subwindow_mdl_ref(img_a, img_b, geo_a, geo_b, r, q, centres, min_n, s2) -> np.ndarray:
    """numpy reference of :func:`subwindow_mdl` (windows warped with :func:`warp_bilinear_ref`,
    scores with :func:`geocd.stereo.scores.mdl_from_stats`)."""
    from .scores import mdl_from_stats, window_stats

    side = 2 * r + 1
    win = []
    for img, g in ((img_a, geo_a), (img_b, geo_b)):
        st = np.empty((side, side, *g.shape[1:]), np.float64)
        for u in range(-r, r + 1):
            for v in range(-r, r + 1):
                col = g[0] + v * g[2] + u * g[4]
                row = g[1] + v * g[3] + u * g[5]
                st[u + r, v + r] = warp_bilinear_ref(img, np.nan_to_num(col, nan=-1e9), np.nan_to_num(row, nan=-1e9))
        win.append(st)
    A, B = win
    scores = []
    for cu in centres:
        for cv in centres:
            a = A[cu - q + r : cu + q + r + 1, cv - q + r : cv + q + r + 1].reshape(-1, *A.shape[2:])
            b = B[cu - q + r : cu + q + r + 1, cv - q + r : cv + q + r + 1].reshape(-1, *B.shape[2:])
            ok = np.isfinite(a) & np.isfinite(b)
            a0 = np.where(ok, a, 0.0)
            b0 = np.where(ok, b, 0.0)
            mom = np.stack([ok.sum(0), a0.sum(0), b0.sum(0), (a0 * a0).sum(0), (b0 * b0).sum(0), (a0 * b0).sum(0)])
            n, va, vb, cov = window_stats(mom.astype(np.float64))
            with np.errstate(all="ignore"):
                sc = mdl_from_stats(va, vb, cov, np.sqrt(s2))
            scores.append(np.where((n >= min_n) & (n >= 2), sc, -np.inf))
    worst = np.max(scores, axis=0)
    worst[~(np.isfinite(geo_a[0]) & np.isfinite(geo_b[0]))] = -np.inf
    return np.where(np.isfinite(worst), worst, np.nan)


def subwindow_centres(r: int, q: int) -> np.ndarray:
    """Centre offsets (cells) of sub-windows of radius ``q`` that tile a window of radius ``r``,
    neighbours overlapping by at least one cell (r = 3, q = 1 → −2, 0, 2; q ≥ r → the window itself)."""
    if q >= r:
        return np.zeros(1, np.int64)
    m = int(np.ceil((r - q) / q)) + 1
    return np.unique(np.round(np.linspace(-(r - q), r - q, m)).astype(np.int64))


# ---------------------------------------------------------------------------------------------
# occlusion: z-buffer in image space
# ---------------------------------------------------------------------------------------------


@njit(cache=True)
def zbuffer_occluded(col, row, z, cost, tol_m, c0, r0, W, H, out):
    """Image-space uniqueness: each pixel sees one surface point.

    Every cell is projected (at its matched height) into one image; the cell
    with the best (lowest) matching cost among those landing on a pixel owns
    it, and any other cell on that pixel whose height differs from the owner's
    by more than ``tol_m[cell]`` is marked. When the owner is higher, the
    marked cell is hidden behind it (occlusion: along a ray the higher point is
    nearer the sensor, for every camera kind looking down); when the owner is
    lower, the marked cell is a higher match that the image contradicts (the
    object-space form of the left–right consistency check). Non-finite inputs
    are ignored.

    Parameters
    ----------
    col, row, z, cost, tol_m : float64 (n,)
    c0, r0, W, H : the pixel box the buffer covers
    out : bool (n,), written
    """
    bc = np.full((H, W), np.inf)
    bz = np.full((H, W), np.nan)
    n = col.shape[0]
    for t in range(n):
        if not (np.isfinite(col[t]) and np.isfinite(row[t]) and np.isfinite(z[t])):
            continue
        jj = int(np.floor(col[t])) - c0
        ii = int(np.floor(row[t])) - r0
        if 0 <= ii < H and 0 <= jj < W and cost[t] < bc[ii, jj]:
            bc[ii, jj] = cost[t]
            bz[ii, jj] = z[t]
    for t in range(n):
        out[t] = False
        if not (np.isfinite(col[t]) and np.isfinite(row[t]) and np.isfinite(z[t])):
            continue
        jj = int(np.floor(col[t])) - c0
        ii = int(np.floor(row[t])) - r0
        if 0 <= ii < H and 0 <= jj < W and abs(z[t] - bz[ii, jj]) > tol_m[t]:
            out[t] = True


def zbuffer_occluded_ref(col, row, z, cost, tol_m, c0, r0, W, H) -> np.ndarray:
    """numpy reference of :func:`zbuffer_occluded` (ties: the first cell in order wins)."""
    ok = np.isfinite(col) & np.isfinite(row) & np.isfinite(z)
    jj = np.where(ok, np.floor(np.where(ok, col, 0)), -1).astype(np.int64) - c0
    ii = np.where(ok, np.floor(np.where(ok, row, 0)), -1).astype(np.int64) - r0
    inside = ok & (ii >= 0) & (ii < H) & (jj >= 0) & (jj < W)
    idx = np.flatnonzero(inside)
    pix = ii[idx] * W + jj[idx]
    order = np.lexsort((idx, cost[idx], pix))  # by pixel, then cost, then position
    first = np.ones(order.size, bool)
    first[1:] = pix[order][1:] != pix[order][:-1]
    owner_z = np.full(H * W, np.nan)
    owner_z[pix[order][first]] = z[idx[order][first]]
    out = np.zeros(col.shape, bool)
    out[idx] = np.abs(z[idx] - owner_z[pix]) > tol_m[idx]
    return out


# ---------------------------------------------------------------------------------------------
# the median of the valid heights around each valid cell
# ---------------------------------------------------------------------------------------------
@parallel_njit()
def valid_median(z, r, out):
    """Median of the finite values of ``z`` in the ``(2r+1)²`` window around each cell with a finite ``z``.

    The window is clipped at the array border; an even count takes the mean of the two middle values
    (as ``np.nanmedian``). ``out`` (float64, like ``z``) is NaN where ``z`` is not finite.
    """
    H, W = z.shape
    w = 2 * r + 1
    for i in prange(H):
        buf = np.empty(w * w)
        for j in range(W):
            if not np.isfinite(z[i, j]):
                out[i, j] = np.nan
                continue
            n = 0
            for ii in range(max(i - r, 0), min(i + r + 1, H)):
                for jj in range(max(j - r, 0), min(j + r + 1, W)):
                    v = z[ii, jj]
                    if np.isfinite(v):
                        buf[n] = v
                        n += 1
            h = n // 2
            m = _select(buf, n, h)
            if n % 2 == 0:  # the largest of the lower half
                lo = buf[0]
                for q in range(1, h):
                    if buf[q] > lo:
                        lo = buf[q]
                m = 0.5 * (lo + m)
            out[i, j] = m


def valid_median_ref(z: np.ndarray, r: int) -> np.ndarray:
    """numpy reference of :func:`valid_median`."""
    w = 2 * r + 1
    p = np.pad(np.asarray(z, np.float64), r, constant_values=np.nan)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN windows
        med = np.nanmedian(sliding_window_view(p, (w, w)).reshape(*z.shape, -1), axis=-1)
    return np.where(np.isfinite(z), med, np.nan)
