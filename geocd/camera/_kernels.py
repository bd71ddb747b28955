"""numba kernels for the RPC model, with pure-numpy references.

Coefficients are packed as ``coefs[4, 20]`` = (line_num, line_den, samp_num,
samp_den) in RPC00B term order, and normalisation as ``norm[10]`` =
(line_off, samp_off, lat_off, lon_off, h_off, line_scale, samp_scale, lat_scale,
lon_scale, h_scale). Kernels work in the RPC's own pixel convention (origin at
the centre of the first pixel); :mod:`geocd.camera.rpc` adds GDAL's 0.5.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from .._jit import parallel_njit

# RPC00B term order: 1, L, P, H, LP, LH, PH, L², P², H², PLH, L³, LP², LH², L²P, P³, PH², L²H, P²H, H³
TERMS_RPC00B = (
    "1",
    "L",
    "P",
    "H",
    "LP",
    "LH",
    "PH",
    "LL",
    "PP",
    "HH",
    "PLH",
    "LLL",
    "LPP",
    "LHH",
    "LLP",
    "PPP",
    "PHH",
    "LLH",
    "PPH",
    "HHH",
)


# Kernels use error_model="numpy" (a float division by zero gives inf/NaN instead of raising,
# so the loops have no hidden branches and vectorize) and fastmath "contract" + "arcp" (FMA, and
# divisions may become multiplications by a reciprocal: ~1 ulp, about twice the throughput).
# NaN/inf semantics are kept ("nnan"/"ninf" are not set): the localization relies on them.
#
# The small helpers below are inlined by LLVM (forceinline), not by numba's IR inliner (inline="always"), which
# type-infers and lowers every inlined copy anew: the localization and projection kernels took 51 s of CPU to
# compile cold that way, 12 s now. The price: parallel (prange) loops over them are no longer SIMD-vectorized
# (1e6 localizations on 2 threads: 25 ms then, 75 ms now; serial builds got faster, 160 -> 115 ms).


@njit(cache=True, forceinline=True, error_model="numpy", fastmath={"contract", "arcp"})
def _monomials(L, P, H):
    """The 20 RPC00B monomials (and the products the derivatives reuse)."""
    LP = L * P
    LH = L * H
    PH = P * H
    LL = L * L
    PP = P * P
    HH = H * H
    return (
        L,
        P,
        H,
        LP,
        LH,
        PH,
        LL,
        PP,
        HH,
        LP * H,
        LL * L,
        L * PP,
        L * HH,
        LL * P,
        PP * P,
        P * HH,
        LL * H,
        PP * H,
        HH * H,
    )


@njit(cache=True, forceinline=True, error_model="numpy", fastmath={"contract", "arcp"})
def _dot(c, t):
    """c · (1, t...) for the 20-term RPC00B polynomial with monomials ``t`` from :func:`_monomials`."""
    return (
        c[0]
        + c[1] * t[0]
        + c[2] * t[1]
        + c[3] * t[2]
        + c[4] * t[3]
        + c[5] * t[4]
        + c[6] * t[5]
        + c[7] * t[6]
        + c[8] * t[7]
        + c[9] * t[8]
        + c[10] * t[9]
        + c[11] * t[10]
        + c[12] * t[11]
        + c[13] * t[12]
        + c[14] * t[13]
        + c[15] * t[14]
        + c[16] * t[15]
        + c[17] * t[16]
        + c[18] * t[17]
        + c[19] * t[18]
    )


@njit(cache=True, forceinline=True, error_model="numpy", fastmath={"contract", "arcp"})
def _dot_dL(c, L, P, H, t):
    # d/dL of (1, L, P, H, LP, LH, PH, LL, PP, HH, PLH, LLL, LPP, LHH, LLP, PPP, PHH, LLH, PPH, HHH)
    return (
        c[1]
        + c[4] * P
        + c[5] * H
        + 2.0 * c[7] * L
        + c[10] * t[5]
        + 3.0 * c[11] * t[6]
        + c[12] * t[7]
        + c[13] * t[8]
        + 2.0 * c[14] * t[3]
        + 2.0 * c[17] * t[4]
    )


@njit(cache=True, forceinline=True, error_model="numpy", fastmath={"contract", "arcp"})
def _dot_dP(c, L, P, H, t):
    return (
        c[2]
        + c[4] * L
        + c[6] * H
        + 2.0 * c[8] * P
        + c[10] * t[4]
        + 2.0 * c[12] * t[3]
        + c[14] * t[6]
        + 3.0 * c[15] * t[7]
        + c[16] * t[8]
        + 2.0 * c[18] * t[5]
    )


@njit(cache=True, forceinline=True, error_model="numpy", fastmath={"contract", "arcp"})
def _dot_dH(c, L, P, H, t):
    return (
        c[3]
        + c[5] * L
        + c[6] * P
        + 2.0 * c[9] * H
        + c[10] * t[3]
        + 2.0 * c[13] * t[4]
        + 2.0 * c[16] * t[5]
        + c[17] * t[6]
        + c[18] * t[7]
        + 3.0 * c[19] * t[8]
    )


@parallel_njit(error_model="numpy", fastmath={"contract", "arcp"})
def rpc_project(lon, lat, h, coefs, norm, out_samp, out_line):
    """Ground (flat float64 arrays) → RPC (samp, line), RPC pixel convention."""
    ln_c, ld_c, sn_c, sd_c = coefs[0], coefs[1], coefs[2], coefs[3]
    for i in prange(lon.shape[0]):
        L = (lon[i] - norm[3]) / norm[8]
        P = (lat[i] - norm[2]) / norm[7]
        H = (h[i] - norm[4]) / norm[9]
        t = _monomials(L, P, H)
        out_line[i] = _dot(ln_c, t) / _dot(ld_c, t) * norm[5] + norm[0]
        out_samp[i] = _dot(sn_c, t) / _dot(sd_c, t) * norm[6] + norm[1]


@parallel_njit(error_model="numpy", fastmath={"contract", "arcp"})
def rpc_dproj_dh(lon, lat, h, coefs, norm, out_dsamp, out_dline):
    """∂(samp, line)/∂h (pixels per metre) at fixed lon/lat."""
    ln_c, ld_c, sn_c, sd_c = coefs[0], coefs[1], coefs[2], coefs[3]
    for i in prange(lon.shape[0]):
        L = (lon[i] - norm[3]) / norm[8]
        P = (lat[i] - norm[2]) / norm[7]
        H = (h[i] - norm[4]) / norm[9]
        t = _monomials(L, P, H)
        n = _dot(ln_c, t)
        d = _dot(ld_c, t)
        out_dline[i] = (_dot_dH(ln_c, L, P, H, t) * d - n * _dot_dH(ld_c, L, P, H, t)) / (d * d) * norm[5] / norm[9]
        n = _dot(sn_c, t)
        d = _dot(sd_c, t)
        out_dsamp[i] = (_dot_dH(sn_c, L, P, H, t) * d - n * _dot_dH(sd_c, L, P, H, t)) / (d * d) * norm[6] / norm[9]


@njit(cache=True, forceinline=True, error_model="numpy", fastmath={"contract", "arcp"})
def _residual(coefs, L, P, H, st, lt, ss, ls):
    """Image residual (pixels) of the normalised model at (L, P, H) against targets st, lt."""
    t = _monomials(L, P, H)
    rs = (_dot(coefs[2], t) / _dot(coefs[3], t) - st) * ss
    rl = (_dot(coefs[0], t) / _dot(coefs[1], t) - lt) * ls
    return rs, rl


@njit(cache=True, forceinline=True, error_model="numpy", fastmath={"contract", "arcp"})
def _residual_and_jacobian(coefs, L, P, H, st, lt, ss, ls):
    """Residual (pixels) of the normalised model against targets st, lt, and its Jacobian."""
    ln_c, ld_c, sn_c, sd_c = coefs[0], coefs[1], coefs[2], coefs[3]
    t = _monomials(L, P, H)
    nl = _dot(ln_c, t)
    dl = _dot(ld_c, t)
    ns = _dot(sn_c, t)
    ds = _dot(sd_c, t)
    rs = (ns / ds - st) * ss
    rl = (nl / dl - lt) * ls
    # quotient rule, scaled to pixels per normalised unit
    qs = ss / (ds * ds)
    ql = ls / (dl * dl)
    j_sL = (_dot_dL(sn_c, L, P, H, t) * ds - ns * _dot_dL(sd_c, L, P, H, t)) * qs
    j_sP = (_dot_dP(sn_c, L, P, H, t) * ds - ns * _dot_dP(sd_c, L, P, H, t)) * qs
    j_lL = (_dot_dL(ln_c, L, P, H, t) * dl - nl * _dot_dL(ld_c, L, P, H, t)) * ql
    j_lP = (_dot_dP(ln_c, L, P, H, t) * dl - nl * _dot_dP(ld_c, L, P, H, t)) * ql
    return rs, rl, j_sL, j_sP, j_lL, j_lP


#: layout of the ``init`` vector of :func:`rpc_localize`
INIT_AFFINE = slice(0, 8)
INIT_INNER = slice(8, 48)
INIT_OUTER = slice(48, 88)
INIT_BOX = slice(88, 92)
INIT_SIZE = 92
#: the cubic start is used inside its fit box, enlarged by this factor
CUBIC_START_LIMIT = 1.25


# the robust path's helpers are called, not inlined at numba's IR level: each inlined copy is compiled
# anew (a cold start paid minutes for them), and the path runs for the rare samples the fast pass misses
@njit(cache=True, error_model="numpy", fastmath={"contract", "arcp"})
def _start(init, st, lt, H):
    """Newton start (L, P): cubic inverse fits inside their boxes, affine inverse elsewhere."""
    if abs(st) <= CUBIC_START_LIMIT and abs(lt) <= CUBIC_START_LIMIT:
        t = _monomials(st, lt, H)
        return _dot(init[8:28], t), _dot(init[28:48], t)
    u = (st - init[88]) / init[89]
    v = (lt - init[90]) / init[91]
    if abs(u) <= CUBIC_START_LIMIT and abs(v) <= CUBIC_START_LIMIT:
        t = _monomials(u, v, H)
        return _dot(init[48:68], t), _dot(init[68:88], t)
    u = st - init[4] - init[6] * H
    v = lt - init[5] - init[7] * H
    return init[0] * u + init[1] * v, init[2] * u + init[3] * v


@njit(cache=True, error_model="numpy", fastmath={"contract", "arcp"})
def _newton(coefs, L, P, H, st, lt, ss, ls, tol2, max_iter):
    """Damped Newton from (L, P); returns (L, P, iterations, converged)."""
    rs, rl, a, b, c, d = _residual_and_jacobian(coefs, L, P, H, st, lt, ss, ls)
    r2 = rs * rs + rl * rl
    it = 0
    if not np.isfinite(r2):
        return L, P, it, False
    ok = r2 <= tol2
    while not ok and it < max_iter:
        it += 1
        det = a * d - b * c
        if det == 0.0 or not np.isfinite(det):
            break
        dL = (d * rs - b * rl) / det
        dP = (-c * rs + a * rl) / det
        step = 1.0
        improved = False
        Ln = L
        Pn = P
        rs2 = rs
        rl2 = rl
        r2n = r2
        for _ in range(40):
            Ln = L - step * dL
            Pn = P - step * dP
            rs2, rl2 = _residual(coefs, Ln, Pn, H, st, lt, ss, ls)
            r2n = rs2 * rs2 + rl2 * rl2
            if np.isfinite(r2n) and r2n < r2:
                improved = True
                break
            step *= 0.5
        if not improved:
            # no descent possible: either converged to machine precision or stuck
            ok = r2 <= tol2 * 1e4
            break
        L = Ln
        P = Pn
        r2 = r2n
        ok = r2 <= tol2
        if not ok:
            rs, rl, a, b, c, d = _residual_and_jacobian(coefs, L, P, H, st, lt, ss, ls)
    return L, P, it, ok


@njit(cache=True, error_model="numpy", fastmath={"contract", "arcp"})
def _multistart(coefs, H, st, lt, ss, ls, tol2, max_iter):  # returns (L, P, iterations, converged)
    """Fallback: Newton from the grid node whose image is nearest the target.

    The grid covers the validity box [-1, 1]² first, then [-2, 2]² (RPCs can fold outside
    their validity box, so the wider grid alone may pick a node of another branch).
    """
    n = 41
    total = 0
    for half in (1.0, 2.0):
        best = np.inf
        bL = 0.0
        bP = 0.0
        for j in range(n):
            Lg = half * (-1.0 + 2.0 * j / (n - 1))
            for k in range(n):
                Pg = half * (-1.0 + 2.0 * k / (n - 1))
                rs, rl = _residual(coefs, Lg, Pg, H, st, lt, ss, ls)
                r2 = rs * rs + rl * rl
                if np.isfinite(r2) and r2 < best:
                    best = r2
                    bL = Lg
                    bP = Pg
        if np.isfinite(best):
            L, P, it, ok = _newton(coefs, bL, bP, H, st, lt, ss, ls, tol2, max_iter)
            total += it
            if ok:
                return L, P, total, ok
    return 0.0, 0.0, total, False


#: ``out_iter`` marker of the fast pass for samples the robust pass must redo
_REDO = -2


@parallel_njit(error_model="numpy", fastmath={"contract", "arcp"})
def _localize_fast(samp, line, h, coefs, norm, init, tol2, out_lon, out_lat, out_iter):
    """One full Newton step from the cubic start, without branches.

    Samples whose residual after the step is not below the tolerance get ``out_iter = -2``.
    """
    ss, ls = norm[6], norm[5]
    ci0, ci1, co0, co1 = init[8:28], init[28:48], init[48:68], init[68:88]
    cu, hu, cv, hv = init[88], init[89], init[90], init[91]
    lim = CUBIC_START_LIMIT
    for i in prange(samp.shape[0]):
        st = (samp[i] - norm[1]) / ss
        lt = (line[i] - norm[0]) / ls
        H = (h[i] - norm[4]) / norm[9]
        inner = (abs(st) <= lim) and (abs(lt) <= lim)
        ti = _monomials(st, lt, H)
        to = _monomials((st - cu) / hu, (lt - cv) / hv, H)
        L0 = _dot(ci0, ti) if inner else _dot(co0, to)
        P0 = _dot(ci1, ti) if inner else _dot(co1, to)
        rs, rl, a, b, c, d = _residual_and_jacobian(coefs, L0, P0, H, st, lt, ss, ls)
        det = a * d - b * c
        L1 = L0 - (d * rs - b * rl) / det
        P1 = P0 - (a * rl - c * rs) / det
        rs1, rl1 = _residual(coefs, L1, P1, H, st, lt, ss, ls)
        ok = rs1 * rs1 + rl1 * rl1 <= tol2  # False for NaN
        out_lon[i] = L1 * norm[8] + norm[3]
        out_lat[i] = P1 * norm[7] + norm[2]
        out_iter[i] = 1 if ok else _REDO


# serial: it runs for the few samples the fast pass leaves, and a parallel build costs twice the compile time
@njit(cache=True, error_model="numpy", fastmath={"contract", "arcp"})
def _localize_robust(samp, line, h, coefs, norm, init, tol2, max_iter, out_lon, out_lat, out_iter):
    """Damped Newton (with the multi-start fallback) for the samples marked by the fast pass."""
    ss, ls = norm[6], norm[5]
    for i in range(samp.shape[0]):
        if out_iter[i] != _REDO:
            continue
        st = (samp[i] - norm[1]) / ss
        lt = (line[i] - norm[0]) / ls
        H = (h[i] - norm[4]) / norm[9]
        if not (np.isfinite(st) and np.isfinite(lt) and np.isfinite(H)):
            out_lon[i] = np.nan
            out_lat[i] = np.nan
            out_iter[i] = -1
            continue
        L0, P0 = _start(init, st, lt, H)
        # from a good start Newton converges in a few steps: do not insist (<= 12) before the next start
        L, P, it, ok = _newton(coefs, L0, P0, H, st, lt, ss, ls, tol2, min(max_iter, 12))
        its = 1 + it  # the fast pass's step counts too
        if not ok:  # the cubic start may extrapolate badly far outside the image: affine start
            u = st - init[4] - init[6] * H
            v = lt - init[5] - init[7] * H
            L, P, it, ok = _newton(
                coefs, init[0] * u + init[1] * v, init[2] * u + init[3] * v, H, st, lt, ss, ls, tol2, max_iter
            )
            its += it
        if not ok:
            L, P, it, ok = _multistart(coefs, H, st, lt, ss, ls, tol2, max_iter)
            its += it
        if ok:
            out_lon[i] = L * norm[8] + norm[3]
            out_lat[i] = P * norm[7] + norm[2]
            out_iter[i] = its
        else:
            out_lon[i] = np.nan
            out_lat[i] = np.nan
            out_iter[i] = -1


def rpc_localize(samp, line, h, coefs, norm, init, tol_px, max_iter, out_lon, out_lat, out_iter):
    """RPC (samp, line) + height → (lon, lat) by Newton on the exact Jacobian.

    ``init`` (92,) holds three starts, all in normalised coordinates:
    ``init[0:8]`` an affine inverse [L, P] = M @ ([sn, ln] - a - b*H) with M = init[0:4]
    (row-major 2x2), a = init[4:6], b = init[6:8]; ``init[8:48]`` a cubic inverse over
    the image box, L = init[8:28] · T(sn, ln, H), P = init[28:48] · T(sn, ln, H)
    (T = RPC00B monomials), used where |sn|, |ln| <= 1.25; ``init[48:88]`` the same over
    the image of the validity cube, in u = (sn - init[88]) / init[89],
    v = (ln - init[90]) / init[91], used where |u|, |v| <= 1.25.

    Two passes. The fast pass (:func:`_localize_fast`) takes one full Newton
    step from the cubic start and keeps it when the image residual is below ``tol_px``
    pixels (nearly every sample: the cubic start is within ~1e-3 px). The robust pass
    (:func:`_localize_robust`) redoes the others with damped Newton: a step that does not
    reduce the residual is halved (up to 40 times), so the iteration cannot wander off;
    samples that do not converge are retried from the affine start, then from the nearest
    node of a coarse grid over the validity box, then over [-2, 2]² (each attempt at most
    ``max_iter`` iterations). Non-converged samples get NaN and ``out_iter = -1``;
    otherwise ``out_iter`` is the number of Newton iterations over all attempts.
    """
    tol2 = float(tol_px) * float(tol_px)
    _localize_fast(samp, line, h, coefs, norm, init, tol2, out_lon, out_lat, out_iter)
    _localize_robust(samp, line, h, coefs, norm, init, tol2, int(max_iter), out_lon, out_lat, out_iter)


# ---------------------------------------------------------------------------------------
# pure-numpy references (slow, obviously correct; tests check the kernels against them)
# ---------------------------------------------------------------------------------------
def terms_ref(L: np.ndarray, P: np.ndarray, H: np.ndarray) -> np.ndarray:
    """(20, N) matrix of RPC00B monomials."""
    one = np.ones_like(L)
    return np.stack(
        [
            one,
            L,
            P,
            H,
            L * P,
            L * H,
            P * H,
            L**2,
            P**2,
            H**2,
            P * L * H,
            L**3,
            L * P**2,
            L * H**2,
            L**2 * P,
            P**3,
            P * H**2,
            L**2 * H,
            P**2 * H,
            H**3,
        ]
    )


def project_ref(lon, lat, h, coefs, norm):
    L = (np.asarray(lon, float) - norm[3]) / norm[8]
    P = (np.asarray(lat, float) - norm[2]) / norm[7]
    H = (np.asarray(h, float) - norm[4]) / norm[9]
    T = terms_ref(L, P, H)
    line = (coefs[0] @ T) / (coefs[1] @ T) * norm[5] + norm[0]
    samp = (coefs[2] @ T) / (coefs[3] @ T) * norm[6] + norm[1]
    return samp, line


def dproj_dh_ref(lon, lat, h, coefs, norm, eps_m: float = 1e-3):
    """Central finite difference of :func:`project_ref` (pixels per metre)."""
    s1, l1 = project_ref(lon, lat, np.asarray(h, float) + eps_m, coefs, norm)
    s0, l0 = project_ref(lon, lat, np.asarray(h, float) - eps_m, coefs, norm)
    return (s1 - s0) / (2 * eps_m), (l1 - l0) / (2 * eps_m)


def localize_ref(samp, line, h, coefs, norm, tol_px: float = 1e-9, max_iter: int = 50, init=None):
    """Damped Newton on :func:`project_ref` with a central-difference Jacobian.

    The start is the affine inverse of ``init[0:8]`` (see :func:`rpc_localize`) when given, as the
    kernels' fallback start is, else the centre of the validity box (which may lie far outside the
    image of an RPC whose crop moved its sample offset). A step that does not reduce the image
    residual is halved, up to 40 times. RPC pixel convention (like the kernels). Samples not
    converged after ``max_iter`` iterations are NaN. Slow and simple: the numpy reference for
    :func:`rpc_localize`, and the localizer of summaries that should not compile kernels.
    """
    samp, line, h = np.broadcast_arrays(*(np.asarray(a, float) for a in (samp, line, h)))
    if init is None:
        lon = np.full(samp.shape, float(norm[3]))
        lat = np.full(samp.shape, float(norm[2]))
    else:
        st = (samp - norm[1]) / norm[6]
        lt = (line - norm[0]) / norm[5]
        H = (h - norm[4]) / norm[9]
        u = st - init[4] - init[6] * H
        v = lt - init[5] - init[7] * H
        lon = (init[0] * u + init[1] * v) * norm[8] + norm[3]
        lat = (init[2] * u + init[3] * v) * norm[7] + norm[2]
    e_lon, e_lat = 1e-6 * abs(norm[8]), 1e-6 * abs(norm[7])

    def residual(lo, la):
        with np.errstate(all="ignore"):
            s, l = project_ref(lo, la, h, coefs, norm)
        return s - samp, l - line

    rs, rl = residual(lon, lat)
    r2 = rs * rs + rl * rl
    done = r2 <= tol_px * tol_px
    for _ in range(max_iter):
        if done.all():
            break
        with np.errstate(all="ignore"):
            sp, lp = project_ref(lon + e_lon, lat, h, coefs, norm)
            sm, lm = project_ref(lon - e_lon, lat, h, coefs, norm)
            a, c = (sp - sm) / (2 * e_lon), (lp - lm) / (2 * e_lon)
            sp, lp = project_ref(lon, lat + e_lat, h, coefs, norm)
            sm, lm = project_ref(lon, lat - e_lat, h, coefs, norm)
            b, d = (sp - sm) / (2 * e_lat), (lp - lm) / (2 * e_lat)
            det = a * d - b * c
            dlon = (d * rs - b * rl) / det
            dlat = (a * rl - c * rs) / det
        step = np.ones(samp.shape)
        todo = ~done & np.isfinite(dlon) & np.isfinite(dlat)
        new_lon, new_lat, new_r2 = lon.copy(), lat.copy(), r2.copy()
        for _ in range(40):  # halve the step where it does not reduce the residual
            if not todo.any():
                break
            tl = lon - step * dlon
            ta = lat - step * dlat
            trs, trl = residual(tl, ta)
            t2 = trs * trs + trl * trl
            better = todo & np.isfinite(t2) & (t2 < r2)
            new_lon[better], new_lat[better], new_r2[better] = tl[better], ta[better], t2[better]
            todo &= ~better
            step[todo] *= 0.5
        stuck = ~done & ~(new_r2 < r2)
        # no descent possible: converged to machine precision (as the kernels accept it) or stuck
        done |= stuck & (r2 <= tol_px * tol_px * 1e4)
        if not (~done & ~stuck).any():
            break
        lon, lat, r2 = new_lon, new_lat, new_r2
        rs, rl = residual(lon, lat)
        done |= r2 <= tol_px * tol_px
    return np.where(done, lon, np.nan), np.where(done, lat, np.nan)
