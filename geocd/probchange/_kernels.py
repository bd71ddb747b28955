"""numba kernels of the probabilistic change detector, each with a pure-numpy reference.

Conventions
-----------
* A *stack* is float32 ``(N, h, w)``: N single-band images (bands of images)
  resampled onto the same reference pixels (key-frame pixels or AOI-grid cells)
  for one depth hypothesis; NaN = outside the image / invalid.
* A *volume* is float32 ``(P, n, h, w)``: the patch dissimilarity of P image
  pairs for n hypotheses; NaN = not observed (patch invalid or hypothesis outside
  the pixel's range).
* Log-probabilities are float32 with ``-inf`` for impossible hypotheses; sums of
  log terms are accumulated in float64.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from .._jit import parallel_njit

NEG_INF = -np.inf
#: log p(d) below which a hypothesis's term in the log-likelihood ratio is negligible (skipped)
LOGP_NEGLIGIBLE = -40.0


# ---------------------------------------------------------------------------------------------
# patch mean absolute difference (eq. 5.1)
# ---------------------------------------------------------------------------------------------
@parallel_njit()
def patch_mad(stack, ia, ib, r, min_count, out, hs, hc):
    """Mean absolute difference of ``(2r+1)²`` patches between two images of a stack, over bands.

    ``s(x) = Σ_{δ∈W} Σ_b |A_b(x+δ) − B_b(x+δ)| / (B · #valid)`` where a pixel is
    valid when every band of both images is finite (eq. 5.1 of the thesis, with
    the window clipped at the array border). Running sums along rows, then a
    (2r+1)-row sum: O(pixels · bands), whatever the window.

    Parameters
    ----------
    stack : float32 (N, h, w)
    ia, ib : int64 (B,), the stack indices of the bands of image A and of image B
    r : int, window radius
    min_count : int, valid pixels a window needs; fewer → NaN
    out : float32 (h, w), written
    hs : float64 (h, w), hc : int32 (h, w) — work arrays (horizontal sums and counts)
    """
    nb = ia.shape[0]
    _, h, w = stack.shape
    for i in prange(h):
        rd = np.empty(w)
        rv = np.empty(w, np.int32)
        for j in range(w):
            d = 0.0
            ok = 1
            for b in range(nb):
                va = stack[ia[b], i, j]
                vb = stack[ib[b], i, j]
                if not (va == va and vb == vb):
                    ok = 0
                    break
                d += abs(va - vb)
            rd[j] = d if ok else 0.0
            rv[j] = ok
        s = 0.0
        c = 0
        for j in range(min(r, w)):
            s += rd[j]
            c += rv[j]
        for j in range(w):
            jn = j + r
            if jn < w:
                s += rd[jn]
                c += rv[jn]
            jo = j - r - 1
            if jo >= 0:
                s -= rd[jo]
                c -= rv[jo]
            hs[i, j] = s
            hc[i, j] = c
    for i in prange(h):
        i0 = max(i - r, 0)
        i1 = min(i + r + 1, h)
        for j in range(w):
            s = 0.0
            c = 0
            for ii in range(i0, i1):
                s += hs[ii, j]
                c += hc[ii, j]
            if c >= min_count:
                out[i, j] = s / (c * nb)
            else:
                out[i, j] = np.nan


def patch_mad_ref(stack: np.ndarray, ia, ib, r: int, min_count: int) -> np.ndarray:
    """numpy reference of :func:`patch_mad` (explicit window loop over offsets)."""
    a = stack[np.asarray(ia)].astype(np.float64)
    b = stack[np.asarray(ib)].astype(np.float64)
    nb = a.shape[0]
    valid = np.all(np.isfinite(a) & np.isfinite(b), axis=0)
    d = np.where(valid, np.abs(a - b).sum(axis=0), 0.0)
    h, w = d.shape
    s = np.zeros((h, w))
    c = np.zeros((h, w))
    dp = np.pad(d, r)
    vp = np.pad(valid.astype(float), r)
    for di in range(2 * r + 1):
        for dj in range(2 * r + 1):
            s += dp[di : di + h, dj : dj + w]
            c += vp[di : di + h, dj : dj + w]
    with np.errstate(invalid="ignore", divide="ignore"):
        out = s / (c * nb)
    out[c < min_count] = np.nan
    return out.astype(np.float32)


# ---------------------------------------------------------------------------------------------
# depth density p(d) ∝ exp(−s_d / σ) (eq. 5.2), several pairs as independent observations
# ---------------------------------------------------------------------------------------------
@parallel_njit()
def depth_logprob(vol, inv_sigma, log_s_over_sigma, log_none, log_1m_none, out, kbest, none_out):
    """log p(d) from the dissimilarities of P pairs, with an optional "no consistent depth" hypothesis.

    Posterior over the ray's depth given the pairs, each pair an independent
    observation with ``p(s|depth = d) = e^{−s/σ}/σ`` at d and ``U = 1/S`` elsewhere:
    ``p(d) ∝ (1 − π∅)/n · Π_p (S/σ) e^{−s_{p,d}/σ}``. With π∅ = 0 this is the
    thesis's ``p(d) ∝ exp(−Σ_p s_{p,d}/σ)`` (eq. 5.2). With π∅ > 0 a hypothesis ∅
    ("no hypothesis is the surface": occluded in a view, a depth edge inside the
    patch, out of range) has ``p(∅) ∝ π∅`` (every s uniform), so p(d) sums to 1 − p(∅).

    A pair whose patch is invalid at a hypothesis is imputed with the mean of the
    pair values that are valid there (so hypotheses are not favoured for being
    seen by fewer pairs); a hypothesis no pair observes has log p = −inf and does
    not count in n.

    Parameters
    ----------
    vol : float32 (P, n, h, w)
    inv_sigma : float, 1/σ
    log_s_over_sigma : float, log(S/σ)
    log_none, log_1m_none : float, log π∅ (−inf for the thesis's model) and log(1 − π∅)
    out : float32 (n, h, w), written (log p(d); −inf where impossible)
    kbest : int32 (h, w), written: argmax_d p(d), −1 where no hypothesis is observed
    none_out : float32 (h, w), written: log p(∅) (−inf when π∅ = 0; 0 where nothing is observed)
    """
    P, n, h, w = vol.shape
    for i in prange(h):
        e = np.empty((n, w))
        mx = np.full(w, -np.inf)
        kb = np.full(w, -1, np.int32)
        nv = np.zeros(w)
        for d in range(n):
            for j in range(w):
                tot = 0.0
                c = 0
                for p in range(P):
                    v = vol[p, d, i, j]
                    if v == v:
                        tot += v
                        c += 1
                if c == 0:
                    e[d, j] = -np.inf
                else:
                    val = P * (log_s_over_sigma - (tot / c) * inv_sigma)
                    e[d, j] = val
                    nv[j] += 1.0
                    if val > mx[j]:
                        mx[j] = val
                        kb[j] = d
        for j in range(w):
            kbest[i, j] = kb[j]
            if nv[j] == 0.0:
                none_out[i, j] = 0.0
                for d in range(n):
                    out[d, i, j] = -np.inf
                continue
            prior_d = log_1m_none - math.log(nv[j])
            m = mx[j] + prior_d
            if log_none > m:
                m = log_none
            ssum = math.exp(log_none - m) if log_none > -np.inf else 0.0
            for d in range(n):
                if e[d, j] > -np.inf:
                    ssum += math.exp(e[d, j] + prior_d - m)
            lz = m + math.log(ssum)
            none_out[i, j] = log_none - lz if log_none > -np.inf else -np.inf
            for d in range(n):
                if e[d, j] > -np.inf:
                    out[d, i, j] = e[d, j] + prior_d - lz
                else:
                    out[d, i, j] = -np.inf


def depth_logprob_ref(
    vol: np.ndarray, sigma: float, s_range: float = 1.0, none_prior: float = 0.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """numpy reference of :func:`depth_logprob`: (log p (n, h, w), argmax (h, w), log p(∅) (h, w))."""
    v = vol.astype(np.float64)
    P = v.shape[0]
    cnt = np.isfinite(v).sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.nansum(v, axis=0) / cnt
    e = np.where(cnt > 0, P * (np.log(s_range / sigma) - mean / sigma), -np.inf)
    nv = np.isfinite(e).sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        prior_d = np.log1p(-none_prior) - np.log(nv)
        ed = e + prior_d[None]
        e_none = np.log(none_prior) if none_prior > 0 else -np.inf
        m = np.maximum(np.max(ed, axis=0), e_none)
        lz = m + np.log(np.sum(np.exp(ed - m[None]), axis=0) + (np.exp(e_none - m) if none_prior > 0 else 0.0))
        logp = np.where(np.isfinite(e), ed - lz[None], -np.inf)
        lnone = np.where(nv > 0, e_none - lz, 0.0) if none_prior > 0 else np.where(nv > 0, -np.inf, 0.0)
    kb = np.where(nv > 0, np.argmax(e, axis=0), -1)
    return logp.astype(np.float32), kb.astype(np.int32), lnone.astype(np.float32)


# ---------------------------------------------------------------------------------------------
# log-likelihood ratio of "no change" against "change" (eqs. 5.5–5.11)
# ---------------------------------------------------------------------------------------------
@njit(cache=True, inline="always")
def _logaddexp(a, b):
    m = a if a > b else b
    if m == -np.inf:
        return -np.inf
    return m + math.log1p(math.exp(-abs(a - b)))


@njit(cache=True, inline="always")
def _log1mexp(x):
    """log(1 − e^x) for x ≤ 0 (−inf at x = 0), accurate near both ends."""
    if x >= 0.0:
        return -np.inf
    if x > -0.6931471805599453:
        return math.log(-math.expm1(x))
    return math.log1p(-math.exp(x))


@parallel_njit()
def change_llr(logp, vol, inv_sigma, log_s_over_sigma, log_eps, log_1meps, llr, coverage):
    """Σ_pairs Σ_d log[p(s'_d | c=0) / p(s'_d | c=1)] with the thesis's models.

    Per hypothesis (eqs. 5.8–5.11): ``p(s'|c=0) = p(d) L(s') + (1 − p(d)) U`` and
    ``p(s'|c=1) ≈ U`` (the eq. 5.11 approximation), with ``U = 1/S`` uniform and
    ``L(s') = [(1 − ε) e^{−s'/σ'}/σ' + ε U]`` (ε = 0: the half-Laplace of the thesis).
    The per-hypothesis term is ``log(p r + 1 − p)`` with ``r = L/U``, evaluated as
    ``logaddexp(log p + log r, log(1 − p))`` — no underflow for any n. Hypotheses
    with ``p(d) < e^-40`` are skipped: their term is ``≈ p (r − 1)``, below
    ``4e-18 · S/σ'`` each.

    Parameters
    ----------
    logp : float32 (n, h, w), log p(d) (−inf: impossible)
    vol : float32 (Q, n, h, w), s' of Q pairs (NaN = not observed: the term is skipped)
    inv_sigma : float, 1/σ'
    log_s_over_sigma : float, log(S/σ')
    log_eps, log_1meps : float, log ε and log(1 − ε) (log ε = −inf when ε = 0)
    llr : float64 (h, w), written
    coverage : float32 (h, w), written: fraction of the depth mass Σ_d p(d) that the pairs observe
        (mean over pairs; 0 where p(d) has no mass)
    """
    Q, n, h, w = vol.shape
    for i in prange(h):
        acc = np.zeros(w)
        cov = np.zeros(w)
        tot = np.zeros(w)
        for d in range(n):
            for j in range(w):
                lp = logp[d, i, j]
                if not lp > LOGP_NEGLIGIBLE:
                    continue
                l1m = _log1mexp(lp)
                pd = math.exp(lp)
                tot[j] += pd
                for q in range(Q):
                    s = vol[q, d, i, j]
                    if s != s:
                        continue
                    lr = log_s_over_sigma - s * inv_sigma
                    if log_eps > -np.inf:
                        lr = _logaddexp(log_1meps + lr, log_eps)
                    acc[j] += _logaddexp(lp + lr, l1m)
                    cov[j] += pd
        for j in range(w):
            llr[i, j] = acc[j]
            coverage[i, j] = cov[j] / (Q * tot[j]) if Q > 0 and tot[j] > 0.0 else 0.0


def change_llr_ref(
    logp: np.ndarray, vol: np.ndarray, sigma: float, s_range: float, eps: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """numpy reference of :func:`change_llr` (probability domain where safe, float64)."""
    p = np.exp(logp.astype(np.float64))  # (n, h, w)
    s = vol.astype(np.float64)  # (Q, n, h, w)
    U = 1.0 / s_range
    L = (1.0 - eps) * np.exp(-s / sigma) / sigma + eps * U
    with np.errstate(divide="ignore", invalid="ignore"):
        term = np.log(p[None] * L / U + (1.0 - p[None]))
    ok = np.isfinite(s) & (p[None] > 0)
    term = np.where(ok, term, 0.0)
    tot = p.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        cov = np.where(np.isfinite(s), p[None], 0.0).sum(axis=1).mean(axis=0) / tot
    return term.sum(axis=(0, 1)), np.where(tot > 0, cov, 0.0).astype(np.float32)


# ---------------------------------------------------------------------------------------------
# lattice → pixels (key-frame hypotheses are projected exactly on a lattice only)
# ---------------------------------------------------------------------------------------------
@parallel_njit()
def lattice_to_pixels(lat, step, out):
    """Bilinear interpolation of lattice values onto every pixel.

    Lattice node ``(a, b)`` sits on pixel ``(a·step, b·step)`` (array indices);
    the lattice covers the array (its last node is at or beyond the last pixel).

    Parameters
    ----------
    lat : float64 (La, Lb), La ≥ 2 and Lb ≥ 2 (or 1 when the array has one row/column)
    step : int
    out : float64 (h, w), written
    """
    La, Lb = lat.shape
    h, w = out.shape
    for i in prange(h):
        fa = i / step
        a0 = min(int(fa), La - 2) if La > 1 else 0
        ta = fa - a0 if La > 1 else 0.0
        a1 = a0 + 1 if La > 1 else 0
        for j in range(w):
            fb = j / step
            b0 = min(int(fb), Lb - 2) if Lb > 1 else 0
            tb = fb - b0 if Lb > 1 else 0.0
            b1 = b0 + 1 if Lb > 1 else 0
            out[i, j] = (lat[a0, b0] * (1.0 - tb) + lat[a0, b1] * tb) * (1.0 - ta) + (
                lat[a1, b0] * (1.0 - tb) + lat[a1, b1] * tb
            ) * ta


def lattice_to_pixels_ref(lat: np.ndarray, step: int, shape: tuple[int, int]) -> np.ndarray:
    """numpy reference of :func:`lattice_to_pixels`."""
    from scipy.interpolate import RegularGridInterpolator

    La, Lb = lat.shape
    ra = np.arange(La) * float(step)
    rb = np.arange(Lb) * float(step)
    if La == 1:
        lat = np.vstack([lat, lat])
        ra = np.array([0.0, 1e9])
    if Lb == 1:
        lat = np.hstack([lat, lat])
        rb = np.array([0.0, 1e9])
    f = RegularGridInterpolator((ra, rb), lat, method="linear", bounds_error=False, fill_value=None)
    ii, jj = np.meshgrid(np.arange(shape[0], dtype=float), np.arange(shape[1], dtype=float), indexing="ij")
    return f(np.stack([ii.ravel(), jj.ravel()], axis=1)).reshape(shape)


# ---------------------------------------------------------------------------------------------
# key-frame values → AOI grid (bilinear splatting)
# ---------------------------------------------------------------------------------------------
@njit(cache=True)
def splat_bilinear(fcol, frow, value, sum_w, sum_v):
    """Accumulate values at fractional grid positions into the four nearest cells.

    ``fcol, frow`` are continuous grid coordinates with cell centres at integers
    (+0.5 convention removed by the caller); NaN positions or values are skipped.

    Parameters
    ----------
    fcol, frow, value : float64 (m,)
    sum_w, sum_v : float64 (H, W), accumulated in place
    """
    H, W = sum_w.shape
    for k in range(fcol.shape[0]):
        x = fcol[k]
        y = frow[k]
        v = value[k]
        if not (x == x and y == y and v == v):
            continue
        if x < -1.0 or y < -1.0 or x > W or y > H:
            continue
        j0 = int(math.floor(x))
        i0 = int(math.floor(y))
        fx = x - j0
        fy = y - i0
        for di in range(2):
            ii = i0 + di
            if ii < 0 or ii >= H:
                continue
            wy = fy if di == 1 else 1.0 - fy
            for dj in range(2):
                jj = j0 + dj
                if jj < 0 or jj >= W:
                    continue
                wgt = wy * (fx if dj == 1 else 1.0 - fx)
                if wgt <= 0.0:
                    continue
                sum_w[ii, jj] += wgt
                sum_v[ii, jj] += wgt * v


def splat_bilinear_ref(
    fcol: np.ndarray, frow: np.ndarray, value: np.ndarray, shape: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray]:
    """numpy reference of :func:`splat_bilinear` (np.add.at)."""
    H, W = shape
    sw = np.zeros(shape)
    sv = np.zeros(shape)
    ok = np.isfinite(fcol) & np.isfinite(frow) & np.isfinite(value)
    ok &= (fcol >= -1) & (frow >= -1) & (fcol <= W) & (frow <= H)
    x, y, v = fcol[ok], frow[ok], value[ok]
    j0 = np.floor(x).astype(int)
    i0 = np.floor(y).astype(int)
    fx, fy = x - j0, y - i0
    for di in (0, 1):
        for dj in (0, 1):
            wgt = (fy if di else 1 - fy) * (fx if dj else 1 - fx)
            ii, jj = i0 + di, j0 + dj
            m = (ii >= 0) & (ii < H) & (jj >= 0) & (jj < W) & (wgt > 0)
            np.add.at(sw, (ii[m], jj[m]), wgt[m])
            np.add.at(sv, (ii[m], jj[m]), wgt[m] * v[m])
    return sw, sv


# ---------------------------------------------------------------------------------------------
# visibility: height z-buffer in a view
# ---------------------------------------------------------------------------------------------
@njit(cache=True)
def zbuffer_max(col, row, z, buf):
    """Keep, per image pixel, the highest of the points landing on it (pixel = floor(col), floor(row)).

    Parameters
    ----------
    col, row, z : float64 (m,), image coordinates relative to the buffer and heights (NaN skipped)
    buf : float64 (H, W), −inf initially; updated in place
    """
    H, W = buf.shape
    for t in range(col.shape[0]):
        c = col[t]
        r = row[t]
        zz = z[t]
        if not (c == c and r == r and zz == zz):
            continue
        if c < 0.0 or r < 0.0:
            continue
        j = int(c)
        i = int(r)
        if i < H and j < W and zz > buf[i, j]:
            buf[i, j] = zz


@njit(cache=True)
def zbuffer_test(col, row, z, buf, tol, out):
    """``out[t] = buf[pixel of t] − z[t] > tol`` (False for NaN or outside the buffer)."""
    H, W = buf.shape
    for t in range(col.shape[0]):
        c = col[t]
        r = row[t]
        zz = z[t]
        out[t] = False
        if not (c == c and r == r and zz == zz) or c < 0.0 or r < 0.0:
            continue
        j = int(c)
        i = int(r)
        if i < H and j < W and buf[i, j] - zz > tol:
            out[t] = True


def zbuffer_ref(
    col: np.ndarray, row: np.ndarray, z: np.ndarray, shape: tuple[int, int], tol: float
) -> tuple[np.ndarray, np.ndarray]:
    """numpy reference of :func:`zbuffer_max` + :func:`zbuffer_test` (no dilation): (buffer, occluded)."""
    H, W = shape
    ok = np.isfinite(col) & np.isfinite(row) & np.isfinite(z) & (col >= 0) & (row >= 0)
    j = np.where(ok, np.floor(np.where(ok, col, 0)), -1).astype(int)
    i = np.where(ok, np.floor(np.where(ok, row, 0)), -1).astype(int)
    ok &= (i < H) & (j < W)
    buf = np.full(shape, -np.inf)
    np.maximum.at(buf, (i[ok], j[ok]), z[ok])
    occ = np.zeros(col.shape, bool)
    occ[ok] = buf[i[ok], j[ok]] - z[ok] > tol
    return buf, occ
