"""numba kernels of the tie-point search (numpy references: :func:`ncc_at_offsets_ref`)."""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from .._jit import parallel_njit


@njit(cache=True)
def _integrals(a):
    """Summed-area tables (H+1, W+1) of a, a² and of the NaN count (NaN read as 0)."""
    H, W = a.shape
    s1 = np.zeros((H + 1, W + 1))
    s2 = np.zeros((H + 1, W + 1))
    sn = np.zeros((H + 1, W + 1))
    for i in range(H):
        r1 = 0.0
        r2 = 0.0
        rn = 0.0
        for j in range(W):
            v = a[i, j]
            if np.isfinite(v):
                r1 += v
                r2 += v * v
            else:
                rn += 1.0
            s1[i + 1, j + 1] = s1[i, j + 1] + r1
            s2[i + 1, j + 1] = s2[i, j + 1] + r2
            sn[i + 1, j + 1] = sn[i, j + 1] + rn
    return s1, s2, sn


@njit(cache=True, forceinline=True)
def _box(s, i0, j0, i1, j1):
    return s[i1, j1] - s[i0, j1] - s[i1, j0] + s[i0, j0]


@njit(cache=True, forceinline=True)
def _ncc_one(ref, oth, s1, s2, sn, i, j, ci, cj, P, ma, va):
    """NCC between ref's (2P+1)² window at (i, j) (mean ma, centred sum of squares va) and oth's at (ci, cj)."""
    H, W = oth.shape
    if ci - P < 0 or cj - P < 0 or ci + P + 1 > H or cj + P + 1 > W:
        return -2.0
    i0, j0, i1, j1 = ci - P, cj - P, ci + P + 1, cj + P + 1
    if _box(sn, i0, j0, i1, j1) > 0.5:
        return -2.0
    n = (2 * P + 1) * (2 * P + 1)
    sb = _box(s1, i0, j0, i1, j1)
    vb = _box(s2, i0, j0, i1, j1) - sb * sb / n
    if vb <= 1e-9 * n:
        return -2.0
    sab = 0.0
    for a in range(-P, P + 1):
        for b in range(-P, P + 1):
            sab += (ref[i + a, j + b] - ma) * oth[ci + a, cj + b]
    return sab / np.sqrt(va * vb)


@parallel_njit()
def ncc_at_offsets(ref, oth, pts, centres, offsets, P):
    """Best NCC of each point's template over a set of integer offsets around its centre in ``oth``.

    Parameters
    ----------
    ref, oth : float32 (H, W) orthos (NaN = no data)
    pts : int64 (n, 2) template centres (row, col) in ``ref``
    centres : int64 (n, 2) search centres (row, col) in ``oth``
    offsets : int64 (m, 2) offsets (drow, dcol) tried around each centre
    P : template half-size

    Returns
    -------
    best : float64 (n, 3) — row, col (sub-pixel, parabola through the 4-neighbours) and NCC of the best
        offset; NaN row when no valid offset or when the best is not a local maximum (search edge).
    """
    n = pts.shape[0]
    m = offsets.shape[0]
    out = np.full((n, 3), np.nan)
    s1, s2, sn = _integrals(oth)
    nn = (2 * P + 1) * (2 * P + 1)
    for k in prange(n):
        i, j = pts[k, 0], pts[k, 1]
        if i - P < 0 or j - P < 0 or i + P + 1 > ref.shape[0] or j + P + 1 > ref.shape[1]:
            continue
        sa = 0.0
        saa = 0.0
        bad = False
        for a in range(-P, P + 1):
            for b in range(-P, P + 1):
                x = ref[i + a, j + b]
                if not np.isfinite(x):
                    bad = True
                sa += x
                saa += x * x
        if bad:
            continue
        ma = sa / nn
        va = saa - sa * sa / nn
        if va <= 1e-9 * nn:
            continue
        best = -2.0
        bi = 0
        bj = 0
        for q in range(m):
            ci = centres[k, 0] + offsets[q, 0]
            cj = centres[k, 1] + offsets[q, 1]
            v = _ncc_one(ref, oth, s1, s2, sn, i, j, ci, cj, P, ma, va)
            if v > best:
                best = v
                bi = ci
                bj = cj
        if best <= -1.5:
            continue
        up = _ncc_one(ref, oth, s1, s2, sn, i, j, bi - 1, bj, P, ma, va)
        dn = _ncc_one(ref, oth, s1, s2, sn, i, j, bi + 1, bj, P, ma, va)
        lf = _ncc_one(ref, oth, s1, s2, sn, i, j, bi, bj - 1, P, ma, va)
        rt = _ncc_one(ref, oth, s1, s2, sn, i, j, bi, bj + 1, P, ma, va)
        if up > best or dn > best or lf > best or rt > best or min(up, dn, lf, rt) <= -1.5:
            continue
        dr = 0.0
        den = up - 2.0 * best + dn
        if den < 0:
            dr = 0.5 * (up - dn) / den
        dc = 0.0
        den = lf - 2.0 * best + rt
        if den < 0:
            dc = 0.5 * (lf - rt) / den
        out[k, 0] = bi + dr
        out[k, 1] = bj + dc
        out[k, 2] = best
    return out


def ncc_at_offsets_ref(ref, oth, pts, centres, offsets, P):
    """Pure numpy reference of :func:`ncc_at_offsets`."""

    def ncc(i, j, ci, cj):
        H, W = oth.shape
        if ci - P < 0 or cj - P < 0 or ci + P + 1 > H or cj + P + 1 > W:
            return -2.0
        a = ref[i - P : i + P + 1, j - P : j + P + 1].astype(np.float64)
        b = oth[ci - P : ci + P + 1, cj - P : cj + P + 1].astype(np.float64)
        if not (np.isfinite(a).all() and np.isfinite(b).all()):
            return -2.0
        a = a - a.mean()
        b = b - b.mean()
        va, vb = (a * a).sum(), (b * b).sum()
        if va <= 1e-9 * a.size or vb <= 1e-9 * a.size:
            return -2.0
        return float((a * b).sum() / np.sqrt(va * vb))

    out = np.full((len(pts), 3), np.nan)
    for k, (i, j) in enumerate(pts):
        if i - P < 0 or j - P < 0 or i + P + 1 > ref.shape[0] or j + P + 1 > ref.shape[1]:
            continue
        vals = [ncc(i, j, centres[k, 0] + o[0], centres[k, 1] + o[1]) for o in offsets]
        q = int(np.argmax(vals))
        best = vals[q]
        if best <= -1.5:
            continue
        bi, bj = centres[k, 0] + offsets[q, 0], centres[k, 1] + offsets[q, 1]
        up, dn, lf, rt = ncc(i, j, bi - 1, bj), ncc(i, j, bi + 1, bj), ncc(i, j, bi, bj - 1), ncc(i, j, bi, bj + 1)
        if max(up, dn, lf, rt) > best or min(up, dn, lf, rt) <= -1.5:
            continue
        den = up - 2 * best + dn
        dr = 0.5 * (up - dn) / den if den < 0 else 0.0
        den = lf - 2 * best + rt
        dc = 0.5 * (lf - rt) / den if den < 0 else 0.0
        out[k] = (bi + dr, bj + dc, best)
    return out
