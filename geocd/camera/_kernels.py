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

# RPC00B term order: 1, L, P, H, LP, LH, PH, L², P², H², PLH, L³, LP², LH², L²P, P³, PH², L²H, P²H, H³
TERMS_RPC00B = ("1", "L", "P", "H", "LP", "LH", "PH", "LL", "PP", "HH",
                "PLH", "LLL", "LPP", "LHH", "LLP", "PPP", "PHH", "LLH", "PPH", "HHH")


@njit(cache=True, inline="always")
def _poly(c, L, P, H):
    return (c[0] + c[1] * L + c[2] * P + c[3] * H + c[4] * L * P + c[5] * L * H + c[6] * P * H
            + c[7] * L * L + c[8] * P * P + c[9] * H * H + c[10] * P * L * H + c[11] * L * L * L
            + c[12] * L * P * P + c[13] * L * H * H + c[14] * L * L * P + c[15] * P * P * P
            + c[16] * P * H * H + c[17] * L * L * H + c[18] * P * P * H + c[19] * H * H * H)


@njit(cache=True, inline="always")
def _poly_dL(c, L, P, H):
    return (c[1] + c[4] * P + c[5] * H + 2.0 * c[7] * L + c[10] * P * H + 3.0 * c[11] * L * L
            + c[12] * P * P + c[13] * H * H + 2.0 * c[14] * L * P + 2.0 * c[17] * L * H)


@njit(cache=True, inline="always")
def _poly_dP(c, L, P, H):
    return (c[2] + c[4] * L + c[6] * H + 2.0 * c[8] * P + c[10] * L * H + 2.0 * c[12] * L * P
            + c[14] * L * L + 3.0 * c[15] * P * P + c[16] * H * H + 2.0 * c[18] * P * H)


@njit(cache=True, inline="always")
def _poly_dH(c, L, P, H):
    return (c[3] + c[5] * L + c[6] * P + 2.0 * c[9] * H + c[10] * P * L + 2.0 * c[13] * L * H
            + 2.0 * c[16] * P * H + c[17] * L * L + c[18] * P * P + 3.0 * c[19] * H * H)


@njit(cache=True, parallel=True)
def rpc_project(lon, lat, h, coefs, norm, out_samp, out_line):
    """Ground (flat float64 arrays) → RPC (samp, line), RPC pixel convention."""
    ln_c, ld_c, sn_c, sd_c = coefs[0], coefs[1], coefs[2], coefs[3]
    for i in prange(lon.shape[0]):
        L = (lon[i] - norm[3]) / norm[8]
        P = (lat[i] - norm[2]) / norm[7]
        H = (h[i] - norm[4]) / norm[9]
        out_line[i] = _poly(ln_c, L, P, H) / _poly(ld_c, L, P, H) * norm[5] + norm[0]
        out_samp[i] = _poly(sn_c, L, P, H) / _poly(sd_c, L, P, H) * norm[6] + norm[1]


@njit(cache=True, parallel=True)
def rpc_dproj_dh(lon, lat, h, coefs, norm, out_dsamp, out_dline):
    """∂(samp, line)/∂h (pixels per metre) at fixed lon/lat."""
    ln_c, ld_c, sn_c, sd_c = coefs[0], coefs[1], coefs[2], coefs[3]
    for i in prange(lon.shape[0]):
        L = (lon[i] - norm[3]) / norm[8]
        P = (lat[i] - norm[2]) / norm[7]
        H = (h[i] - norm[4]) / norm[9]
        n = _poly(ln_c, L, P, H)
        d = _poly(ld_c, L, P, H)
        out_dline[i] = (_poly_dH(ln_c, L, P, H) * d - n * _poly_dH(ld_c, L, P, H)) / (d * d) * norm[5] / norm[9]
        n = _poly(sn_c, L, P, H)
        d = _poly(sd_c, L, P, H)
        out_dsamp[i] = (_poly_dH(sn_c, L, P, H) * d - n * _poly_dH(sd_c, L, P, H)) / (d * d) * norm[6] / norm[9]


@njit(cache=True, inline="always")
def _residual_and_jacobian(coefs, L, P, H, st, lt, ss, ls):
    """Residual (pixels) of the normalised model against targets st, lt, and its Jacobian."""
    ln_c, ld_c, sn_c, sd_c = coefs[0], coefs[1], coefs[2], coefs[3]
    nl = _poly(ln_c, L, P, H)
    dl = _poly(ld_c, L, P, H)
    ns = _poly(sn_c, L, P, H)
    ds = _poly(sd_c, L, P, H)
    rs = (ns / ds - st) * ss
    rl = (nl / dl - lt) * ls
    # quotient rule, scaled to pixels per normalised unit
    j_sL = (_poly_dL(sn_c, L, P, H) * ds - ns * _poly_dL(sd_c, L, P, H)) / (ds * ds) * ss
    j_sP = (_poly_dP(sn_c, L, P, H) * ds - ns * _poly_dP(sd_c, L, P, H)) / (ds * ds) * ss
    j_lL = (_poly_dL(ln_c, L, P, H) * dl - nl * _poly_dL(ld_c, L, P, H)) / (dl * dl) * ls
    j_lP = (_poly_dP(ln_c, L, P, H) * dl - nl * _poly_dP(ld_c, L, P, H)) / (dl * dl) * ls
    return rs, rl, j_sL, j_sP, j_lL, j_lP


@njit(cache=True, parallel=True)
def rpc_localize(samp, line, h, coefs, norm, init, tol_px, max_iter, out_lon, out_lat, out_iter):
    """RPC (samp, line) + height → (lon, lat) by damped Newton on the exact Jacobian.

    ``init`` (8,) holds an affine start: [L, P] = M @ ([sn, ln] - a - b*H) with
    M = init[0:4] (row-major 2x2), a = init[4:6], b = init[6:8].
    Converges when the image residual is below ``tol_px`` pixels. A full Newton
    step that does not reduce the residual is halved (up to 40 times), so the
    iteration cannot wander off. Non-converged samples get NaN and
    ``out_iter = -1``; otherwise ``out_iter`` is the number of iterations.
    """
    ss, ls = norm[6], norm[5]
    for i in prange(samp.shape[0]):
        st = (samp[i] - norm[1]) / ss
        lt = (line[i] - norm[0]) / ls
        H = (h[i] - norm[4]) / norm[9]
        if not (np.isfinite(st) and np.isfinite(lt) and np.isfinite(H)):
            out_lon[i] = np.nan
            out_lat[i] = np.nan
            out_iter[i] = -1
            continue
        u = st - init[4] - init[6] * H
        v = lt - init[5] - init[7] * H
        L = init[0] * u + init[1] * v
        P = init[2] * u + init[3] * v
        rs, rl, a, b, c, d = _residual_and_jacobian(coefs, L, P, H, st, lt, ss, ls)
        r2 = rs * rs + rl * rl
        it = 0
        ok = r2 <= tol_px * tol_px
        while not ok and it < max_iter:
            it += 1
            det = a * d - b * c
            if det == 0.0 or not np.isfinite(det):
                break
            dL = (d * rs - b * rl) / det
            dP = (-c * rs + a * rl) / det
            step = 1.0
            improved = False
            for _ in range(40):
                Ln = L - step * dL
                Pn = P - step * dP
                rs2, rl2, a2, b2, c2, d2 = _residual_and_jacobian(coefs, Ln, Pn, H, st, lt, ss, ls)
                r2n = rs2 * rs2 + rl2 * rl2
                if np.isfinite(r2n) and r2n < r2:
                    improved = True
                    break
                step *= 0.5
            if not improved:
                # no descent possible: either converged to machine precision or stuck
                ok = r2 <= tol_px * tol_px * 1e4
                break
            L, P, rs, rl, a, b, c, d, r2 = Ln, Pn, rs2, rl2, a2, b2, c2, d2, r2n
            ok = r2 <= tol_px * tol_px
        if ok:
            out_lon[i] = L * norm[8] + norm[3]
            out_lat[i] = P * norm[7] + norm[2]
            out_iter[i] = it
        else:
            out_lon[i] = np.nan
            out_lat[i] = np.nan
            out_iter[i] = -1


# ---------------------------------------------------------------------------------------
# pure-numpy references (slow, obviously correct; tests check the kernels against them)
# ---------------------------------------------------------------------------------------
def terms_ref(L: np.ndarray, P: np.ndarray, H: np.ndarray) -> np.ndarray:
    """(20, N) matrix of RPC00B monomials."""
    one = np.ones_like(L)
    return np.stack([one, L, P, H, L * P, L * H, P * H, L**2, P**2, H**2, P * L * H, L**3,
                     L * P**2, L * H**2, L**2 * P, P**3, P * H**2, L**2 * H, P**2 * H, H**3])


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
