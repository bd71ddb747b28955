"""numba kernels of the marked point process, each with a pure-numpy reference.

Rectangles are rows of a float64 array ``(n, 5)``: centre column, centre row (array-index coordinates:
cell centres at integers), side lengths ``e_L`` and ``e_l`` (cells) and θ (radians, map sense: the
``e_L`` side points along (cos θ, sin θ) in (east, north), i.e. (cos θ, −sin θ) in (col, row)).

For a cell at offset (dx, dy) = (j − c_x, i − c_y) from the centre, ``u = dx cos θ − dy sin θ`` runs
along the ``e_L`` side and ``v = dx sin θ + dy cos θ`` along the ``e_l`` side; the cell is inside when
``|u| ≤ e_L/2`` and ``|v| ≤ e_l/2``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from .._select import select_kth

#: columns of the raw object features (per rectangle and image)
(
    F_GRADIENT,
    F_KURTOSIS,
    F_COMPLETE,
    F_COLOUR_IN,
    F_COLOUR_OUT,
    F_SHADOW_IN,
    F_SHADOW_OUT,
    F_RAISED_IN,
    F_RAISED_OUT,
    F_VALID,
    F_AREA,
    F_GRADIENT_SIDES,
) = range(12)
N_FEATURES = 12


@njit(cache=True)
def _uv(i, j, cx, cy, c, s):
    dx = j - cx
    dy = i - cy
    return dx * c - dy * s, dx * s + dy * c


@njit(cache=True)
def _row_span(i, cx, cy, c, s, au, av, j0, j1):
    """Columns of row ``i`` (within [j0, j1]) that can satisfy |u| ≤ au and |v| ≤ av."""
    dy = i - cy
    lo = float(j0)
    hi = float(j1)
    # u = dx c − dy s ∈ [−au, au];  v = dx s + dy c ∈ [−av, av]
    for coef, off, lim in ((c, -dy * s, au), (s, dy * c, av)):
        if abs(coef) > 1e-12:
            a = (-lim - off) / coef
            b = (lim - off) / coef
            if a > b:
                a, b = b, a
            lo = max(lo, cx + a)
            hi = min(hi, cx + b)
        elif abs(off) > lim:
            return 1, 0
    return int(math.ceil(lo - 1e-9)), int(math.floor(hi + 1e-9))


@njit(cache=True)
def _kurt(n, s1, s2, s3, s4):
    if n < 5:
        return np.nan
    m = s1 / n
    v = s2 / n - m * m
    if v <= 1e-12:
        return np.nan
    m4 = s4 / n - 4 * m * s3 / n + 6 * m * m * s2 / n - 3 * m**4
    return m4 / (v * v)


@njit(cache=True)
def _pooled_var(mom, k):
    n = mom[k, 0] + mom[k + 1, 0]
    if n <= 0:
        return np.inf
    acc = 0.0
    for h in (k, k + 1):
        if mom[h, 0] > 0:
            acc += mom[h, 2] - mom[h, 1] * mom[h, 1] / mom[h, 0]
    return acc / n


@njit(cache=True)
def rect_features(
    rects,
    grey,
    valid,
    mag,
    ori,
    colour,
    shadow,
    sdx,
    sdy,
    ndsm,
    min_h,
    edge_w,
    ring_w,
    shadow_w,
    flood_tol,
    flood_spread,
    grad_gate,
    ring_in,
    core_in,
    out,
):
    """Raw object features of every rectangle on one image (see ``F_*``).

    Parameters
    ----------
    rects : float64 (n, 5)
    grey, mag, ori : float32 (H, W); valid : bool (H, W)
    colour, shadow : uint8 (H, W) or (0, 0) when absent; ndsm : float32 (H, W) or (0, 0)
    sdx, sdy : shadow direction (cells), ignored without ``shadow``
    min_h, edge_w, ring_w, shadow_w, flood_tol : float (m, cells, cells, cells, grey levels)
    flood_spread : a roof half floods cells within max(flood_tol, flood_spread × its own std)
    grad_gate : below this edge feature (``F_GRADIENT`` or ``F_GRADIENT_SIDES``, whichever is larger) the
        homogeneity features are not computed (NaN): a caller whose every homogeneity prototype also needs
        the gradient passes its d_Λ (the object is repulsive anyway), else −inf
    ring_in : the outer limit (cells) of the DSM's blurred-wall band. The height ring ("the ring outside is
        ground") lies between ``edge_w`` and ``edge_w + ring_w`` outside the rectangle; a ring cell counts as
        ground when its height is at most ``min_h`` or, within ``ring_in`` of the rectangle, at most half the
        rectangle's height (the nDSM at its centre, as the height births' level): a true wall's blurred lower
        half, not a roof that goes on. ``ring_in`` ≤ ``edge_w``: the plain ground test everywhere
    core_in : the raised fraction inside is counted over the cells at least ``core_in`` (cells) inside the
        sides (a blurred wall's upper part, low or rough, is not roof; all inside cells when none is that
        deep); 0: every inside cell
    out : float64 (n, N_FEATURES), written (NaN = feature unavailable)
    """
    H, W = grey.shape
    has_c = colour.shape[0] == H
    has_s = shadow.shape[0] == H
    has_h = ndsm.shape[0] == H
    nsh = int(math.ceil(shadow_w))
    for r in range(rects.shape[0]):
        cx, cy, eL, el, th = rects[r, 0], rects[r, 1], rects[r, 2], rects[r, 3], rects[r, 4]
        c = math.cos(th)
        s = math.sin(th)
        hL = 0.5 * eL
        hl = 0.5 * el
        pad = max(ring_w, shadow_w, edge_w) + 1.0
        rad = math.sqrt(hL * hL + hl * hl) + pad
        i0 = max(int(math.floor(cy - rad)), 0)
        i1 = min(int(math.ceil(cy + rad)), H - 1)
        j0 = max(int(math.floor(cx - rad)), 0)
        j1 = min(int(math.ceil(cx + rad)), W - 1)
        g_sum = 0.0
        g_n = 0
        gs = np.zeros(4)
        gn = np.zeros(4)
        n_in = 0
        n_in_valid = 0
        col_in = 0.0
        sh_in = 0.0
        ra_in = 0.0
        ra_in_n = 0
        ra_core = 0.0
        ra_core_n = 0
        ring_n = 0
        col_out = 0.0
        ra_out = 0.0
        ra_out_n = 0
        shr_n = 0
        shr = 0.0
        # halves about either axis (v-split: about the e_L axis; u-split: about the e_l axis): grey moments
        mom = np.zeros((4, 5))
        x0 = grey[min(max(int(round(cy)), 0), H - 1), min(max(int(round(cx)), 0), W - 1)]
        half_h = min_h
        if has_h:
            hc = ndsm[min(max(int(round(cy)), 0), H - 1), min(max(int(round(cx)), 0), W - 1)]
            if hc == hc:
                half_h = max(min_h, 0.5 * hc)
        for i in range(i0, i1 + 1):
            ja, jb = _row_span(i, cx, cy, c, s, hL + pad, hl + pad, j0, j1)
            for j in range(ja, jb + 1):
                u, v = _uv(i, j, cx, cy, c, s)
                du = abs(u) - hL
                dv = abs(v) - hl
                inside = du <= 0.0 and dv <= 0.0
                if inside:
                    dist = min(-du, -dv)
                    vside = -dv < -du
                else:
                    dist = math.sqrt(max(du, 0.0) ** 2 + max(dv, 0.0) ** 2)
                    vside = dv > du
                if inside:
                    n_in += 1
                if not valid[i, j]:
                    continue
                if dist <= edge_w:
                    d = ori[i, j] - th
                    w = abs(math.sin(d)) if vside else abs(math.cos(d))
                    g_sum += mag[i, j] * w
                    g_n += 1
                    side = (2 if vside else 0) + (1 if (v if vside else u) < 0.0 else 0)
                    gs[side] += mag[i, j] * w
                    gn[side] += 1.0
                if inside:
                    n_in_valid += 1
                    if has_c:
                        col_in += colour[i, j]
                    if has_s:
                        sh_in += 1.0 - shadow[i, j]
                    if has_h and ndsm[i, j] == ndsm[i, j]:
                        ra_in_n += 1
                        if ndsm[i, j] > min_h:
                            ra_in += 1.0
                        if dist >= core_in:
                            ra_core_n += 1
                            if ndsm[i, j] > min_h:
                                ra_core += 1.0
                    if dist >= 1.0:
                        x = grey[i, j] - x0
                        hv = 1 if v < 0.0 else 0
                        hu = 3 if u < 0.0 else 2
                        for h in (hv, hu):
                            mom[h, 0] += 1.0
                            mom[h, 1] += x
                            mom[h, 2] += x * x
                            mom[h, 3] += x * x * x
                            mom[h, 4] += x * x * x * x
                else:
                    if dist <= ring_w:
                        ring_n += 1
                        if has_c:
                            col_out += 1.0 - colour[i, j]
                    if has_h and edge_w < dist <= edge_w + ring_w and ndsm[i, j] == ndsm[i, j]:
                        ra_out_n += 1
                        if ndsm[i, j] <= (half_h if dist <= ring_in else min_h):
                            ra_out += 1.0
                    if has_s:
                        hit = False
                        for t in range(1, nsh + 1):
                            tt = min(float(t), shadow_w)
                            u2, v2 = _uv(i - tt * sdy, j - tt * sdx, cx, cy, c, s)
                            if abs(u2) <= hL and abs(v2) <= hl:
                                hit = True
                                break
                        if hit:
                            shr_n += 1
                            shr += shadow[i, j]
        out[r, F_GRADIENT] = g_sum / g_n if g_n > 0 else 0.0
        gmin = np.inf
        for q in range(4):
            gmin = min(gmin, gs[q] / gn[q] if gn[q] > 0 else 0.0)
        out[r, F_GRADIENT_SIDES] = gmin
        if max(out[r, F_GRADIENT], gmin) < grad_gate:
            out[r, F_KURTOSIS] = np.nan
            out[r, F_COMPLETE] = np.nan
        else:
            _homogeneity(
                grey, valid, cx, cy, c, s, hL, hl, ring_w, flood_tol, flood_spread, mom, x0, i0, i1, j0, j1, out[r]
            )
        nv = max(n_in_valid, 1)
        out[r, F_COLOUR_IN] = col_in / nv if has_c else np.nan
        out[r, F_COLOUR_OUT] = (col_out / ring_n if ring_n > 0 else 0.0) if has_c else np.nan
        out[r, F_SHADOW_IN] = sh_in / nv if has_s else np.nan
        out[r, F_SHADOW_OUT] = (shr / shr_n if shr_n > 0 else 0.0) if has_s else np.nan
        if ra_core_n > 0:
            ra_in, ra_in_n = ra_core, ra_core_n
        out[r, F_RAISED_IN] = (ra_in / ra_in_n if ra_in_n > 0 else 0.0) if has_h else np.nan
        out[r, F_RAISED_OUT] = (ra_out / ra_out_n if ra_out_n > 0 else 0.0) if has_h else np.nan
        out[r, F_VALID] = n_in_valid / n_in if n_in > 0 else 0.0
        out[r, F_AREA] = n_in


@njit(cache=True)
def _homogeneity(grey, valid, cx, cy, c, s, hL, hl, ring_w, flood_tol, flood_spread, mom, x0, i0, i1, j0, j1, out):
    """Kurtosis of the roof halves about the symmetry axis and flood-fill completeness → out[F_KURTOSIS, F_COMPLETE]."""
    # the symmetry axis: the split whose halves are the more homogeneous (least pooled variance)
    split_v = _pooled_var(mom, 0) <= _pooled_var(mom, 2)
    if not split_v:
        for q in range(5):  # element by element: a row assignment compiles numba's broadcasting machinery
            mom[0, q] = mom[2, q]
            mom[1, q] = mom[3, q]
    k0 = _kurt(mom[0, 0], mom[0, 1], mom[0, 2], mom[0, 3], mom[0, 4])
    k1 = _kurt(mom[1, 0], mom[1, 1], mom[1, 2], mom[1, 3], mom[1, 4])
    out[F_KURTOSIS] = min(k0, k1) if (k0 == k0 and k1 == k1) else np.nan
    out[F_COMPLETE] = _completeness(
        grey, valid, cx, cy, c, s, hL, hl, ring_w, flood_tol, flood_spread, mom, x0, split_v, i0, i1, j0, j1
    )


@njit(cache=True)
def _completeness(grey, valid, cx, cy, c, s, hL, hl, ring_w, tol, spread, mom, x0, split_v, i0, i1, j0, j1):
    """1 − leak of the flood fill from the roof halves into the end (NH) and side (NV) neighbourhoods.

    A half fills the 4-connected cells within ``max(tol, spread × the half's own standard deviation)`` of its
    mean grey level: a textured surface (grass, asphalt) floods wide and leaks; a roof stops at its edges.
    ``seen`` holds which half's fill reached a cell (1, 2; 0: none): the cells either half filled are its
    non-zero cells. Rows are scanned over the columns that can meet the rectangle's core or rings only
    (:func:`_row_span`, 1e-6 cells wider; every cell is then tested)."""
    h = i1 - i0 + 1
    w = j1 - j0 + 1
    seen = np.zeros((h, w), np.uint8)
    stack_i = np.empty(h * w, np.int64)
    stack_j = np.empty(h * w, np.int64)
    for half in range(2):
        if mom[half, 0] < 3:
            continue
        ref = mom[half, 1] / mom[half, 0] + x0
        var = mom[half, 2] / mom[half, 0] - (mom[half, 1] / mom[half, 0]) ** 2
        tol_h = max(tol, spread * math.sqrt(max(var, 0.0)))
        stamp = half + 1
        top = 0
        for i in range(i0, i1 + 1):
            ja, jb = _row_span(i, cx, cy, c, s, hL - 1.0 + 1e-6, hl - 1.0 + 1e-6, j0, j1)
            for j in range(ja, jb + 1):
                u, v = _uv(i, j, cx, cy, c, s)
                if abs(u) <= hL - 1.0 and abs(v) <= hl - 1.0 and valid[i, j]:
                    hh = (1 if v < 0.0 else 0) if split_v else (1 if u < 0.0 else 0)
                    if hh == half and abs(grey[i, j] - ref) <= tol_h and seen[i - i0, j - j0] != stamp:
                        seen[i - i0, j - j0] = stamp
                        stack_i[top] = i
                        stack_j[top] = j
                        top += 1
        while top > 0:
            top -= 1
            i = stack_i[top]
            j = stack_j[top]
            for k in range(4):
                ii = i + (1 if k == 0 else (-1 if k == 1 else 0))
                jj = j + (1 if k == 2 else (-1 if k == 3 else 0))
                if ii < i0 or ii > i1 or jj < j0 or jj > j1:
                    continue
                if seen[ii - i0, jj - j0] == stamp or not valid[ii, jj]:
                    continue
                u, v = _uv(ii, jj, cx, cy, c, s)
                if abs(u) > hL + ring_w or abs(v) > hl + ring_w:
                    continue
                if abs(grey[ii, jj] - ref) <= tol_h:
                    seen[ii - i0, jj - j0] = stamp
                    stack_i[top] = ii
                    stack_j[top] = jj
                    top += 1
    nh = 0
    fh = 0
    nv = 0
    fv = 0
    for i in range(i0, i1 + 1):
        ja, jb = _row_span(i, cx, cy, c, s, hL + ring_w + 1e-6, hl + ring_w + 1e-6, j0, j1)
        for j in range(ja, jb + 1):
            u, v = _uv(i, j, cx, cy, c, s)
            au = abs(u)
            av = abs(v)
            if hL < au <= hL + ring_w and av <= hl:
                nh += 1
                fh += seen[i - i0, j - j0] != 0
            elif hl < av <= hl + ring_w and au <= hL:
                nv += 1
                fv += seen[i - i0, j - j0] != 0
    leak = 0.0
    if nh > 0:
        leak = max(leak, fh / nh)
    if nv > 0:
        leak = max(leak, fv / nv)
    return 1.0 - leak


@njit(cache=True)
def rect_means(rects, field, out):
    """Mean of ``field`` (float32 (H, W), NaN skipped) over each rectangle's cells; NaN when none."""
    H, W = field.shape
    for r in range(rects.shape[0]):
        cx, cy, eL, el, th = rects[r, 0], rects[r, 1], rects[r, 2], rects[r, 3], rects[r, 4]
        c = math.cos(th)
        s = math.sin(th)
        hL = 0.5 * eL
        hl = 0.5 * el
        rad = math.sqrt(hL * hL + hl * hl) + 1.0
        acc = 0.0
        n = 0
        j0 = max(int(math.floor(cx - rad)), 0)
        j1 = min(int(math.ceil(cx + rad)), W - 1)
        for i in range(max(int(math.floor(cy - rad)), 0), min(int(math.ceil(cy + rad)), H - 1) + 1):
            ja, jb = _row_span(i, cx, cy, c, s, hL + 1e-6, hl + 1e-6, j0, j1)  # then every cell is tested
            for j in range(ja, jb + 1):
                u, v = _uv(i, j, cx, cy, c, s)
                if abs(u) <= hL and abs(v) <= hl:
                    x = field[i, j]
                    if x == x:
                        acc += x
                        n += 1
        out[r] = acc / n if n > 0 else np.nan


@njit(cache=True)
def rect_steps(rects, height, step_min, step_frac, edge_w, ring_w, seg_len, out):
    """Share of a rectangle's outline along which the surface steps down steeply from inside to outside.

    Each side is cut into segments of about ``seg_len`` cells. A segment compares the mean height of the band
    ``edge_w < d ≤ edge_w + ring_w`` inside the side with the same band outside it (the corners' outside
    cells belong to no side; a band between them is left clear of the walls, which a stereo DSM blurs). The
    segment steps when inside − outside ≥ max(``step_min``, ``step_frac`` × inside): a drop larger than the
    noise, and a steep one — across the wall band the surface loses at least that share of its height above
    the ground (a wall; a slope loses little over the few metres between the bands). It is observed when
    each band has ≥ 2 cells with a height. ``out[r]`` = stepping segments / max(observed segments, half of
    all segments): an outline seen on under half of its length cannot pass.

    Parameters
    ----------
    rects : float64 (n, 5)
    height : float32 (H, W) height above the ground (m), NaN = no height
    step_min : smallest step (m); step_frac : smallest step as a share of the inside height
    edge_w, ring_w, seg_len : cells
    out : float64 (n,), written (0 for a rectangle without segments)
    """
    H, W = height.shape
    for r in range(rects.shape[0]):
        cx, cy, eL, el, th = rects[r, 0], rects[r, 1], rects[r, 2], rects[r, 3], rects[r, 4]
        c = math.cos(th)
        s = math.sin(th)
        hL = 0.5 * eL
        hl = 0.5 * el
        nL = max(1, int(eL / seg_len))
        nl = max(1, int(el / seg_len))
        nmax = max(nL, nl)
        acc = np.zeros((4, nmax, 4))  # side, segment, (sum in, n in, sum out, n out)
        pad = edge_w + ring_w + 1.0
        rad = math.sqrt(hL * hL + hl * hl) + pad
        i0 = max(int(math.floor(cy - rad)), 0)
        i1 = min(int(math.ceil(cy + rad)), H - 1)
        j0 = max(int(math.floor(cx - rad)), 0)
        j1 = min(int(math.ceil(cx + rad)), W - 1)
        for i in range(i0, i1 + 1):
            ja, jb = _row_span(i, cx, cy, c, s, hL + pad, hl + pad, j0, j1)
            for j in range(ja, jb + 1):
                x = height[i, j]
                if x != x:
                    continue
                u, v = _uv(i, j, cx, cy, c, s)
                du = abs(u) - hL
                dv = abs(v) - hl
                if du <= 0.0 and dv <= 0.0:
                    inside = True
                    dist = min(-du, -dv)
                    vside = -dv < -du
                elif du <= 0.0:
                    inside = False
                    dist = dv
                    vside = True
                elif dv <= 0.0:
                    inside = False
                    dist = du
                    vside = False
                else:
                    continue
                if dist <= edge_w or dist > edge_w + ring_w:
                    continue
                if vside:
                    q = 2 + (1 if v < 0.0 else 0)
                    along = min(max(u + hL, 0.0), eL)
                    k = min(int(along / eL * nL), nL - 1)
                else:
                    q = 1 if u < 0.0 else 0
                    along = min(max(v + hl, 0.0), el)
                    k = min(int(along / el * nl), nl - 1)
                b = 0 if inside else 2
                acc[q, k, b] += x
                acc[q, k, b + 1] += 1.0
        total = 0
        seen = 0
        step = 0
        for q in range(4):
            nq = nL if q >= 2 else nl
            for k in range(nq):
                total += 1
                if acc[q, k, 1] >= 2.0 and acc[q, k, 3] >= 2.0:
                    seen += 1
                    hin = acc[q, k, 0] / acc[q, k, 1]
                    if hin - acc[q, k, 2] / acc[q, k, 3] >= max(step_min, step_frac * hin):
                        step += 1
        out[r] = step / max(float(seen), 0.5 * total) if total > 0 else 0.0


@njit(cache=True)
def pair_overlaps(rects, pi, pj, areas, H, W, out):
    """I(u, v) = #(R_u ∩ R_v) / #(R_u ∪ R_v) in cells of the (H, W) grid, for the pairs (pi[k], pj[k]);
    ``areas`` are the rectangles' cell counts on the grid (``F_AREA``)."""
    for k in range(pi.shape[0]):
        a = pi[k]
        b = pj[k]
        ca, sa = math.cos(rects[a, 4]), math.sin(rects[a, 4])
        cb, sb = math.cos(rects[b, 4]), math.sin(rects[b, 4])
        ra = math.sqrt(rects[a, 2] ** 2 + rects[a, 3] ** 2) * 0.5 + 1.0
        rb = math.sqrt(rects[b, 2] ** 2 + rects[b, 3] ** 2) * 0.5 + 1.0
        i0 = max(int(math.floor(max(rects[a, 1] - ra, rects[b, 1] - rb))), 0)
        i1 = min(int(math.ceil(min(rects[a, 1] + ra, rects[b, 1] + rb))), H - 1)
        j0 = max(int(math.floor(max(rects[a, 0] - ra, rects[b, 0] - rb))), 0)
        j1 = min(int(math.ceil(min(rects[a, 0] + ra, rects[b, 0] + rb))), W - 1)
        inter = 0
        for i in range(i0, i1 + 1):
            # the columns of this row that can be in both (a few 1e-6 cells wider; every cell is then tested)
            ja, jb = _row_span(
                i, rects[a, 0], rects[a, 1], ca, sa, 0.5 * rects[a, 2] + 1e-6, 0.5 * rects[a, 3] + 1e-6, j0, j1
            )
            ka, kb = _row_span(
                i, rects[b, 0], rects[b, 1], cb, sb, 0.5 * rects[b, 2] + 1e-6, 0.5 * rects[b, 3] + 1e-6, ja, jb
            )
            for j in range(max(ja, ka), min(jb, kb) + 1):
                u, v = _uv(i, j, rects[a, 0], rects[a, 1], ca, sa)
                if abs(u) <= 0.5 * rects[a, 2] and abs(v) <= 0.5 * rects[a, 3]:
                    u, v = _uv(i, j, rects[b, 0], rects[b, 1], cb, sb)
                    if abs(u) <= 0.5 * rects[b, 2] and abs(v) <= 0.5 * rects[b, 3]:
                        inter += 1
        uni = areas[a] + areas[b] - inter
        out[k] = inter / uni if uni > 0 else 0.0


@njit(cache=True)
def death_pass(order, indptr, nbr, w, energy, alive, beta, delta, gamma, rand):
    """One death step of multiple birth and death: visit ``order``; for each live object u,
    ΔΦ = Φ(ω \\ {u}) − Φ(ω) = −A_D(u) − γ Σ_{v ~ u, alive} I(u, v); remove it with probability
    δa / (1 + δa), a = exp(−β ΔΦ), using ``rand[u]``. ``alive`` is updated in place."""
    for k in range(order.shape[0]):
        u = order[k]
        if not alive[u]:
            continue
        inter = 0.0
        for p in range(indptr[u], indptr[u + 1]):
            if alive[nbr[p]]:
                inter += w[p]
        dphi = -energy[u] - gamma * inter
        x = beta * dphi - math.log(delta)  # δa = exp(−x)
        if x > 700.0:
            d = 0.0
        elif x < -700.0:
            d = 1.0
        else:
            d = 1.0 / (1.0 + math.exp(x))
        if rand[u] < d:
            alive[u] = False


# ---------------------------------------------------------------------------------------------
# numpy references
# ---------------------------------------------------------------------------------------------
def _rect_grid(rect, shape, pad):
    cx, cy, eL, el, th = rect
    H, W = shape
    rad = np.hypot(eL / 2, el / 2) + pad
    i0, i1 = max(int(np.floor(cy - rad)), 0), min(int(np.ceil(cy + rad)), H - 1)
    j0, j1 = max(int(np.floor(cx - rad)), 0), min(int(np.ceil(cx + rad)), W - 1)
    i1, j1 = max(i1, i0 - 1), max(j1, j0 - 1)  # a rectangle wholly off the grid: no cells
    ii, jj = np.mgrid[i0 : i1 + 1, j0 : j1 + 1].astype(np.float64)
    c, s = np.cos(th), np.sin(th)
    dx, dy = jj - cx, ii - cy
    return (slice(i0, i1 + 1), slice(j0, j1 + 1)), dx * c - dy * s, dx * s + dy * c, (i0, i1, j0, j1)


def _kurt_ref(x):
    if x.size < 5:
        return np.nan
    m = x.mean()
    v = np.mean((x - m) ** 2)
    if v <= 1e-12:
        return np.nan
    return float(np.mean((x - m) ** 4) / v**2)


def rect_features_ref(
    rects,
    grey,
    valid,
    mag,
    ori,
    colour,
    shadow,
    sdx,
    sdy,
    ndsm,
    min_h,
    edge_w,
    ring_w,
    shadow_w,
    flood_tol,
    flood_spread,
    grad_gate=-np.inf,
    ring_in=None,
    core_in=0.0,
) -> np.ndarray:
    """numpy reference of :func:`rect_features` (``ring_in`` None: ``edge_w``)."""
    from scipy import ndimage

    H, W = grey.shape
    has_c, has_s, has_h = colour.shape[0] == H, shadow.shape[0] == H, ndsm.shape[0] == H
    out = np.full((rects.shape[0], N_FEATURES), np.nan)
    for r, rect in enumerate(rects):
        eL, el, th = rect[2], rect[3], rect[4]
        hL, hl = eL / 2, el / 2
        r_in = edge_w if ring_in is None else ring_in
        sl, u, v, (i0, i1, j0, j1) = _rect_grid(rect, (H, W), max(ring_w, shadow_w, edge_w) + 1.0)
        du, dv = np.abs(u) - hL, np.abs(v) - hl
        inside = (du <= 0) & (dv <= 0)
        dist = np.where(inside, np.minimum(-du, -dv), np.hypot(np.maximum(du, 0), np.maximum(dv, 0)))
        vside = np.where(inside, -dv < -du, dv > du)
        ok = valid[sl]
        edge = ok & (dist <= edge_w)
        d = ori[sl] - th
        wgt = np.where(vside, np.abs(np.sin(d)), np.abs(np.cos(d)))
        out[r, F_GRADIENT] = float(np.sum((mag[sl] * wgt)[edge]) / edge.sum()) if edge.any() else 0.0
        side = np.where(vside, 2 + (v < 0), (u < 0).astype(int))
        sm = [
            float(np.sum((mag[sl] * wgt)[edge & (side == q)]) / (edge & (side == q)).sum())
            if (edge & (side == q)).any()
            else 0.0
            for q in range(4)
        ]
        out[r, F_GRADIENT_SIDES] = min(sm)
        inn = inside & ok
        nv = max(int(inn.sum()), 1)
        ring = ~inside & ok & (dist <= ring_w)
        core = inn & (dist >= 1.0)
        g = grey[sl].astype(np.float64)

        def pooled(h):
            n = core.sum()
            return (
                sum(
                    ((g[core & (h == x)] - g[core & (h == x)].mean()) ** 2).sum()
                    for x in (False, True)
                    if (core & (h == x)).any()
                )
                / n
                if n
                else np.inf
            )

        half = (v < 0) if pooled(v < 0) <= pooled(u < 0) else (u < 0)
        ks = [_kurt_ref(g[core & (half == h)]) for h in (False, True)]
        out[r, F_KURTOSIS] = min(ks) if np.all(np.isfinite(ks)) else np.nan
        # flood fill: 4-connected components of in-tolerance cells inside the dilated box, seeded from the halves
        box = (np.abs(u) <= hL + ring_w) & (np.abs(v) <= hl + ring_w) & ok
        seedzone = (np.abs(u) <= hL - 1) & (np.abs(v) <= hl - 1) & ok
        filled = np.zeros(u.shape, bool)
        for h in (False, True):
            sel = core & (half == h)
            if sel.sum() < 3:
                continue
            ref = g[sel].mean()
            tol = max(flood_tol, flood_spread * g[sel].std())
            cand = box & (np.abs(g - ref) <= tol)
            seeds = seedzone & (half == h) & (np.abs(g - ref) <= tol)
            lab, _ = ndimage.label(cand)
            ids = np.unique(lab[seeds])
            filled |= np.isin(lab, ids[ids > 0])
        au, av = np.abs(u), np.abs(v)
        nh_m = (au > hL) & (au <= hL + ring_w) & (av <= hl)
        nv_m = (av > hl) & (av <= hl + ring_w) & (au <= hL) & ~nh_m
        leak = 0.0
        if nh_m.any():
            leak = max(leak, filled[nh_m].sum() / nh_m.sum())
        if nv_m.any():
            leak = max(leak, filled[nv_m].sum() / nv_m.sum())
        out[r, F_COMPLETE] = 1.0 - leak
        if max(out[r, F_GRADIENT], out[r, F_GRADIENT_SIDES]) < grad_gate:
            out[r, F_KURTOSIS] = out[r, F_COMPLETE] = np.nan
        if has_c:
            cc = colour[sl].astype(np.float64)
            out[r, F_COLOUR_IN] = cc[inn].sum() / nv
            out[r, F_COLOUR_OUT] = (1 - cc[ring]).mean() if ring.any() else 0.0
        if has_s:
            sh = shadow[sl].astype(np.float64)
            out[r, F_SHADOW_IN] = (1 - sh[inn]).sum() / nv
            ii, jj = np.mgrid[i0 : i1 + 1, j0 : j1 + 1].astype(np.float64)
            hit = np.zeros(u.shape, bool)
            c, s = np.cos(th), np.sin(th)
            for t in range(1, int(np.ceil(shadow_w)) + 1):
                tt = min(float(t), shadow_w)
                dx, dy = jj - tt * sdx - rect[0], ii - tt * sdy - rect[1]
                hit |= (np.abs(dx * c - dy * s) <= hL) & (np.abs(dx * s + dy * c) <= hl)
            shr = ~inside & ok & hit
            out[r, F_SHADOW_OUT] = sh[shr].mean() if shr.any() else 0.0
        if has_h:
            nd = ndsm[sl]
            fin = inn & np.isfinite(nd)
            fout = ~inside & ok & (dist > edge_w) & (dist <= edge_w + ring_w) & np.isfinite(nd)
            hc = ndsm[min(max(int(round(rect[1])), 0), H - 1), min(max(int(round(rect[0])), 0), W - 1)]
            half_h = max(min_h, 0.5 * hc) if np.isfinite(hc) else min_h
            ground = nd <= np.where(dist <= r_in, half_h, min_h)
            if (fin & (dist >= core_in)).any():
                fin = fin & (dist >= core_in)
            out[r, F_RAISED_IN] = (nd[fin] > min_h).mean() if fin.any() else 0.0
            out[r, F_RAISED_OUT] = ground[fout].mean() if fout.any() else 0.0
        out[r, F_VALID] = inn.sum() / inside.sum() if inside.any() else 0.0
        out[r, F_AREA] = inside.sum()
    return out


def rect_mask_ref(rect, shape) -> np.ndarray:
    """bool (H, W): the cells of one rectangle."""
    H, W = shape
    ii, jj = np.mgrid[0:H, 0:W].astype(np.float64)
    c, s = np.cos(rect[4]), np.sin(rect[4])
    dx, dy = jj - rect[0], ii - rect[1]
    return (np.abs(dx * c - dy * s) <= rect[2] / 2) & (np.abs(dx * s + dy * c) <= rect[3] / 2)


def rect_steps_ref(rects, height, step_min, step_frac, edge_w, ring_w, seg_len) -> np.ndarray:
    """numpy reference of :func:`rect_steps`."""
    out = np.zeros(rects.shape[0])
    for r, rect in enumerate(rects):
        eL, el = rect[2], rect[3]
        hL, hl = eL / 2, el / 2
        nL, nl = max(1, int(eL / seg_len)), max(1, int(el / seg_len))
        sl, u, v, _ = _rect_grid(rect, height.shape, edge_w + ring_w + 1.0)
        h = height[sl].astype(np.float64)
        du, dv = np.abs(u) - hL, np.abs(v) - hl
        inside = (du <= 0) & (dv <= 0)
        dist = np.select([inside, du <= 0, dv <= 0], [np.minimum(-du, -dv), dv, du], np.nan)
        vside = np.where(inside, -dv < -du, du <= 0)
        use = np.isfinite(h) & np.isfinite(dist) & (dist > edge_w) & (dist <= edge_w + ring_w)
        q = np.where(vside, 2 + (v < 0), (u < 0).astype(int))
        with np.errstate(invalid="ignore"):
            kL = np.minimum((np.clip(u + hL, 0, eL) / eL * nL).astype(int), nL - 1)
            kl = np.minimum((np.clip(v + hl, 0, el) / el * nl).astype(int), nl - 1)
        k = np.where(vside, kL, kl)
        acc = np.zeros((4, max(nL, nl), 4))
        b = np.where(inside, 0, 2)
        np.add.at(acc, (q[use], k[use], b[use]), h[use])
        np.add.at(acc, (q[use], k[use], b[use] + 1), 1.0)
        total = seen = step = 0
        for side in range(4):
            for seg in range(nL if side >= 2 else nl):
                total += 1
                a = acc[side, seg]
                if a[1] >= 2 and a[3] >= 2:
                    seen += 1
                    step += a[0] / a[1] - a[2] / a[3] >= max(step_min, step_frac * (a[0] / a[1]))
        out[r] = step / max(seen, 0.5 * total)
    return out


def pair_overlaps_ref(rects, pi, pj, shape) -> np.ndarray:
    """numpy reference of :func:`pair_overlaps` on a grid of ``shape``."""
    out = np.zeros(len(pi))
    for k, (a, b) in enumerate(zip(pi, pj)):
        ma, mb = rect_mask_ref(rects[a], shape), rect_mask_ref(rects[b], shape)
        uni = (ma | mb).sum()
        out[k] = (ma & mb).sum() / uni if uni else 0.0
    return out


def death_pass_ref(order, indptr, nbr, w, energy, alive, beta, delta, gamma, rand) -> np.ndarray:
    """numpy reference of :func:`death_pass` → the updated ``alive`` (a copy)."""
    alive = alive.copy()
    for u in order:
        if not alive[u]:
            continue
        nb = nbr[indptr[u] : indptr[u + 1]]
        dphi = -energy[u] - gamma * float(np.sum(w[indptr[u] : indptr[u + 1]][alive[nb]]))
        x = beta * dphi - np.log(delta)
        d = 0.0 if x > 700 else (1.0 if x < -700 else 1.0 / (1.0 + np.exp(x)))
        if rand[u] < d:
            alive[u] = False
    return alive


@njit(cache=True)
def snap_rects(rects, mag, ori, thresh, smin, smax):
    """Move each rectangle's four sides onto the nearest strong edges seen from its centre (in place).

    From the centre, march along ±(e_L axis) and ±(e_l axis) one cell at a time up to ``smax`` cells; the
    first cell whose gradient component along the march direction reaches ``thresh`` is an edge. A side
    with an edge on both ways is re-centred between them and sized to their distance (clipped to
    [smin, smax]); an axis without both edges keeps its size. Returns the number of rectangles changed.
    """
    H, W = mag.shape
    changed = 0
    for r in range(rects.shape[0]):
        cx, cy, th = rects[r, 0], rects[r, 1], rects[r, 4]
        c = math.cos(th)
        s = math.sin(th)
        hit = False
        # axis 0: e_L along (c, −s) in (col, row); axis 1: e_l along (s, c)
        for ax in range(2):
            dc = c if ax == 0 else s
            dr = -s if ax == 0 else c
            ang = th if ax == 0 else th + 0.5 * math.pi  # map-sense direction of the march
            ends = np.zeros(2)
            found = 0
            for k in range(2):
                sg = 1.0 if k == 0 else -1.0
                t = 1.0
                while t <= smax:
                    j = int(round(cx + sg * t * dc))
                    i = int(round(cy + sg * t * dr))
                    if i < 0 or j < 0 or i >= H or j >= W:
                        break
                    if mag[i, j] * abs(math.cos(ori[i, j] - ang)) >= thresh:
                        ends[k] = sg * t
                        found += 1
                        break
                    t += 1.0
            if found == 2:
                size = ends[0] - ends[1]
                if smin <= size <= smax:
                    mid = 0.5 * (ends[0] + ends[1])
                    cx += mid * dc
                    cy += mid * dr
                    rects[r, 2 + ax] = size
                    hit = True
        if hit:
            rects[r, 0] = cx
            rects[r, 1] = cy
            changed += 1
    return changed


def snap_rects_ref(rects, mag, ori, thresh, smin, smax) -> np.ndarray:
    """numpy reference of :func:`snap_rects` (returns a snapped copy)."""
    out = rects.copy()
    H, W = mag.shape
    for r in range(out.shape[0]):
        cx, cy, th = out[r, 0], out[r, 1], out[r, 4]
        c, s = np.cos(th), np.sin(th)
        for ax in range(2):
            d = np.array([c, -s]) if ax == 0 else np.array([s, c])
            ang = th if ax == 0 else th + np.pi / 2
            ends = []
            for sg in (1.0, -1.0):
                t = np.arange(1.0, np.floor(smax) + 1.0)
                j = np.round(cx + sg * t * d[0]).astype(int)
                i = np.round(cy + sg * t * d[1]).astype(int)
                inside = (i >= 0) & (j >= 0) & (i < H) & (j < W)
                stop = np.argmin(inside) if not inside.all() else t.size
                i, j, t = i[:stop], j[:stop], t[:stop]
                e = mag[i, j] * np.abs(np.cos(ori[i, j] - ang)) >= thresh
                if e.any():
                    ends.append(sg * t[np.argmax(e)])
            if len(ends) == 2 and smin <= ends[0] - ends[1] <= smax:
                mid = 0.5 * (ends[0] + ends[1])
                cx, cy = cx + mid * d[0], cy + mid * d[1]
                out[r, 2 + ax] = ends[0] - ends[1]
        out[r, 0], out[r, 1] = cx, cy
    return out


@njit(cache=True)
def snap_rects_height(rects, ndsm, min_h, smin, smax):
    """Like :func:`snap_rects` on a height map: from a raised centre (``ndsm > min_h``), each side moves to
    where the surface first drops to half the centre's height (at least ``min_h``; the half-height crossing
    locates a wall that stereo blurs over a few cells) or has no height, along its axis. Rectangles born on
    low ground are left as they are. Returns the number changed."""
    H, W = ndsm.shape
    changed = 0
    for r in range(rects.shape[0]):
        cx, cy, th = rects[r, 0], rects[r, 1], rects[r, 4]
        i0 = int(round(cy))
        j0 = int(round(cx))
        if i0 < 0 or j0 < 0 or i0 >= H or j0 >= W or not ndsm[i0, j0] > min_h:
            continue
        level = max(min_h, 0.5 * ndsm[i0, j0])
        c = math.cos(th)
        s = math.sin(th)
        hit = False
        for ax in range(2):
            dc = c if ax == 0 else s
            dr = -s if ax == 0 else c
            ends = np.zeros(2)
            found = 0
            for k in range(2):
                sg = 1.0 if k == 0 else -1.0
                t = 1.0
                while t <= smax:
                    j = int(round(cx + sg * t * dc))
                    i = int(round(cy + sg * t * dr))
                    if i < 0 or j < 0 or i >= H or j >= W:
                        break
                    if not ndsm[i, j] > level:
                        ends[k] = sg * (t - 0.5)
                        found += 1
                        break
                    t += 1.0
            if found == 2:
                size = ends[0] - ends[1]
                if smin <= size <= smax:
                    mid = 0.5 * (ends[0] + ends[1])
                    cx += mid * dc
                    cy += mid * dr
                    rects[r, 2 + ax] = size
                    hit = True
        if hit:
            rects[r, 0] = cx
            rects[r, 1] = cy
            changed += 1
    return changed


def snap_rects_height_ref(rects, ndsm, min_h, smin, smax) -> np.ndarray:
    """numpy reference of :func:`snap_rects_height` (returns a snapped copy)."""
    out = rects.copy()
    H, W = ndsm.shape
    for r in range(out.shape[0]):
        cx, cy, th = out[r, 0], out[r, 1], out[r, 4]
        i0, j0 = int(np.round(cy)), int(np.round(cx))
        if not (0 <= i0 < H and 0 <= j0 < W) or not ndsm[i0, j0] > min_h:
            continue
        level = max(min_h, 0.5 * ndsm[i0, j0])
        c, s = np.cos(th), np.sin(th)
        for ax in range(2):
            d = np.array([c, -s]) if ax == 0 else np.array([s, c])
            ends = []
            for sg in (1.0, -1.0):
                t = np.arange(1.0, np.floor(smax) + 1.0)
                j = np.round(cx + sg * t * d[0]).astype(int)
                i = np.round(cy + sg * t * d[1]).astype(int)
                inside = (i >= 0) & (j >= 0) & (i < H) & (j < W)
                stop = np.argmin(inside) if not inside.all() else t.size
                i, j, t = i[:stop], j[:stop], t[:stop]
                with np.errstate(invalid="ignore"):
                    low = ~(ndsm[i, j] > level)
                if low.any():
                    ends.append(sg * (t[np.argmax(low)] - 0.5))
            if len(ends) == 2 and smin <= ends[0] - ends[1] <= smax:
                mid = 0.5 * (ends[0] + ends[1])
                cx, cy = cx + mid * d[0], cy + mid * d[1]
                out[r, 2 + ax] = ends[0] - ends[1]
        out[r, 0], out[r, 1] = cx, cy
    return out


@njit(cache=True)
def refine_sides(rects, mag, ori, reach, n_along):
    """Move each side of each rectangle (in place), within ±``reach`` cells of where it is, to the offset
    where the mean gradient across the side (``mag · |cos(ori − normal)|`` at ``n_along`` points along its
    middle 80 %, nearest cell) is strongest: a height map's blurred walls put the sides within a few cells,
    the image's edges put them on the walls. Half-cell steps; sizes stay ≥ 2 cells."""
    H, W = mag.shape
    nsteps = int(2 * reach / 0.5) + 1
    for r in range(rects.shape[0]):
        cx, cy, eL, el, th = rects[r, 0], rects[r, 1], rects[r, 2], rects[r, 3], rects[r, 4]
        c = math.cos(th)
        s = math.sin(th)
        # side k: 0 = +u end, 1 = −u end (normal along the e_L axis), 2 = +v, 3 = −v (normal along e_l)
        pos = np.array([0.5 * eL, -0.5 * eL, 0.5 * el, -0.5 * el])
        for k in range(4):
            if k < 2:
                nc, nr, tc, tr, half_len, ang = c, -s, s, c, 0.5 * el, th
            else:
                nc, nr, tc, tr, half_len, ang = s, c, c, -s, 0.5 * eL, th + 0.5 * math.pi
            best = -1.0
            best_d = 0.0
            for q in range(nsteps):
                d = -reach + 0.5 * q
                p = pos[k] + d
                acc = 0.0
                cnt = 0
                for a in range(n_along):
                    f = -0.8 + 1.6 * a / max(n_along - 1, 1)
                    x = cx + p * nc + f * half_len * tc
                    y = cy + p * nr + f * half_len * tr
                    j = int(round(x))
                    i = int(round(y))
                    if 0 <= i < H and 0 <= j < W:
                        acc += mag[i, j] * abs(math.cos(ori[i, j] - ang))
                        cnt += 1
                if cnt > 0 and acc / cnt > best + 1e-12:
                    best = acc / cnt
                    best_d = d
            pos[k] += best_d
        if pos[0] - pos[1] >= 2.0 and pos[2] - pos[3] >= 2.0:
            mu = 0.5 * (pos[0] + pos[1])
            mv = 0.5 * (pos[2] + pos[3])
            rects[r, 0] = cx + mu * c + mv * s
            rects[r, 1] = cy - mu * s + mv * c
            rects[r, 2] = pos[0] - pos[1]
            rects[r, 3] = pos[2] - pos[3]


def refine_sides_ref(rects, mag, ori, reach, n_along) -> np.ndarray:
    """numpy reference of :func:`refine_sides` (returns a refined copy)."""
    out = rects.copy()
    H, W = mag.shape
    offs = -reach + 0.5 * np.arange(int(2 * reach / 0.5) + 1)
    f = -0.8 + 1.6 * np.arange(n_along) / max(n_along - 1, 1)
    for r in range(out.shape[0]):
        cx, cy, eL, el, th = out[r]
        c, s = np.cos(th), np.sin(th)
        pos = np.array([0.5 * eL, -0.5 * eL, 0.5 * el, -0.5 * el])
        for k in range(4):
            if k < 2:
                n_, t_, half_len, ang = (c, -s), (s, c), 0.5 * el, th
            else:
                n_, t_, half_len, ang = (s, c), (c, -s), 0.5 * eL, th + np.pi / 2
            scores = []
            for d in offs:
                p = pos[k] + d
                j = np.round(cx + p * n_[0] + f * half_len * t_[0]).astype(int)
                i = np.round(cy + p * n_[1] + f * half_len * t_[1]).astype(int)
                ok = (i >= 0) & (i < H) & (j >= 0) & (j < W)
                scores.append(
                    np.mean(mag[i[ok], j[ok]] * np.abs(np.cos(ori[i[ok], j[ok]] - ang))) if ok.any() else -np.inf
                )
            scores = np.array(scores)
            best, best_d = -1.0, 0.0
            for d, sc in zip(offs, scores):
                if np.isfinite(sc) and sc > best + 1e-12:
                    best, best_d = sc, d
            pos[k] += best_d
        if pos[0] - pos[1] >= 2.0 and pos[2] - pos[3] >= 2.0:
            mu, mv = 0.5 * (pos[0] + pos[1]), 0.5 * (pos[2] + pos[3])
            out[r, 0], out[r, 1] = cx + mu * c + mv * s, cy - mu * s + mv * c
            out[r, 2], out[r, 3] = pos[0] - pos[1], pos[2] - pos[3]
    return out


@njit(cache=True)
def _stencil(H, W, y, x):
    """The bilinear stencil at (row y, col x) of an H × W grid (cell centres at integers):
    (i, j, i1, j1, fy, fx), with i = -1 off the grid."""
    if not (0.0 <= y <= H - 1 and 0.0 <= x <= W - 1):
        return -1, -1, -1, -1, 0.0, 0.0
    i = min(int(math.floor(y)), H - 2) if H > 1 else 0
    j = min(int(math.floor(x)), W - 2) if W > 1 else 0
    return i, j, min(i + 1, H - 1), min(j + 1, W - 1), y - i, x - j


@njit(cache=True)
def _bilinear(a, y, x):
    """Bilinear value of ``a`` at (row y, col x) (cell centres at integers); NaN off the grid."""
    i, j, i1, j1, fy, fx = _stencil(a.shape[0], a.shape[1], y, x)
    if i < 0:
        return np.nan
    return (1 - fy) * ((1 - fx) * a[i, j] + fx * a[i, j1]) + fy * ((1 - fx) * a[i1, j] + fx * a[i1, j1])


@njit(cache=True)
def _bilinear_across(mag, ori, y, x, ang):
    """Bilinear gradient component across a side of map direction ``ang`` (|∇| |cos(ϑ − ang)|); NaN off the grid."""
    i, j, i1, j1, fy, fx = _stencil(mag.shape[0], mag.shape[1], y, x)
    if i < 0:
        return np.nan
    g00 = mag[i, j] * abs(math.cos(ori[i, j] - ang))
    g01 = mag[i, j1] * abs(math.cos(ori[i, j1] - ang))
    g10 = mag[i1, j] * abs(math.cos(ori[i1, j] - ang))
    g11 = mag[i1, j1] * abs(math.cos(ori[i1, j1] - ang))
    return (1 - fy) * ((1 - fx) * g00 + fx * g01) + fy * ((1 - fx) * g10 + fx * g11)


@njit(cache=True)
def fit_sides(rects, use, mags, oris, ndsms, has_dsm, min_h, reach, step, gate_in, gate_out, smin, smax):
    """Move each side of each rectangle along its normal, in ``step``-cell steps within ±``reach`` cells, to
    where the images' gradient across the side is strongest *where the DSM agrees there is a wall* (in place).

    A side is sampled at one point per cell along its middle 80 %, bilinearly (sub-cell positions). At an
    offset, a sample counts its gradient across the side (summed over the images the rectangle exists on,
    ``use``) when, on that date's height map, the surface ``gate_in`` cells inside the candidate side is above
    the half-height level and ``gate_out`` cells outside it is below (level: half the nDSM at the centre, at
    least ``min_h``, as the height births use); other samples count zero. An offset is eligible when at least
    half its samples pass; the best eligible offset wins (ties: the smaller move). Without DSMs
    (``has_dsm`` False) every sample counts: the image edge alone. A rectangle whose fitted sides would give
    a side outside [smin, smax] is left as it was; so is one with no usable date (a date's DSM low at its
    centre). Returns the number of rectangles moved.

    Parameters
    ----------
    rects : float64 (n, 5), changed in place
    use : bool (n, m) — which of the m images each rectangle exists on
    mags, oris : float32 (m, H, W) — gradient magnitude and orientation per image
    ndsms : float32 (m, H, W) — height above ground per date (ignored when ``has_dsm`` is False)
    """
    m, H, W = mags.shape
    nstep = int(round(reach / step))
    moved = 0
    for r in range(rects.shape[0]):
        cx, cy, eL, el, th = rects[r, 0], rects[r, 1], rects[r, 2], rects[r, 3], rects[r, 4]
        c = math.cos(th)
        s = math.sin(th)
        level = np.full(m, np.nan)
        ok = np.zeros(m, np.bool_)
        n_ok = 0
        for k in range(m):
            if not use[r, k]:
                continue
            if has_dsm:
                i0 = int(round(cy))
                j0 = int(round(cx))
                if not (0 <= i0 < H and 0 <= j0 < W) or not ndsms[k, i0, j0] > min_h:
                    continue
                level[k] = max(min_h, 0.5 * ndsms[k, i0, j0])
            ok[k] = True
            n_ok += 1
        if n_ok == 0:
            continue
        pos = np.array([0.5 * eL, -0.5 * eL, 0.5 * el, -0.5 * el])
        new = pos.copy()
        for side in range(4):
            sg = 1.0 if side % 2 == 0 else -1.0  # outward along the normal
            if side < 2:
                nc, nr, tc, tr, half_len, ang = c, -s, s, c, 0.5 * el, th
            else:
                nc, nr, tc, tr, half_len, ang = s, c, c, -s, 0.5 * eL, th + 0.5 * math.pi
            n_along = max(3, int(1.6 * half_len) + 1)
            best = -1.0
            best_d = 0.0
            for q in range(2 * nstep + 1):
                d = step * ((q + 1) // 2) * (1.0 if q % 2 == 1 else -1.0)
                p = pos[side] + sg * d  # d > 0 moves the side outwards
                acc = 0.0
                tot = 0
                passed = 0
                for a in range(n_along):
                    f = -0.8 + 1.6 * a / (n_along - 1)
                    x = cx + p * nc + f * half_len * tc
                    y = cy + p * nr + f * half_len * tr
                    for k in range(m):
                        if not ok[k]:
                            continue
                        g = _bilinear_across(mags[k], oris[k], y, x, ang)
                        if not g == g:
                            continue
                        tot += 1
                        if has_dsm:
                            h_in = _bilinear(ndsms[k], y - sg * gate_in * nr, x - sg * gate_in * nc)
                            h_out = _bilinear(ndsms[k], y + sg * gate_out * nr, x + sg * gate_out * nc)
                            if not (h_in > level[k] and h_out < level[k]):
                                continue
                        acc += g
                        passed += 1
                if tot == 0 or 2 * passed < tot:
                    continue
                score = acc / tot
                if score > best + 1e-12:
                    best = score
                    best_d = d
            new[side] = pos[side] + sg * best_d
        a_size = new[0] - new[1]
        b_size = new[2] - new[3]
        if not (smin <= a_size <= smax and smin <= b_size <= smax):
            continue
        if new[0] == pos[0] and new[1] == pos[1] and new[2] == pos[2] and new[3] == pos[3]:
            continue
        mu = 0.5 * (new[0] + new[1])
        mv = 0.5 * (new[2] + new[3])
        rects[r, 0] = cx + mu * c + mv * s
        rects[r, 1] = cy - mu * s + mv * c
        rects[r, 2] = a_size
        rects[r, 3] = b_size
        moved += 1
    return moved


def _stencil_ref(H, W, y, x):
    """Vectorised :func:`_stencil`: (inside, i, j, i1, j1, fy, fx), indices clipped onto the grid."""
    y, x = np.asarray(y, float), np.asarray(x, float)
    inside = (y >= 0) & (y <= H - 1) & (x >= 0) & (x <= W - 1)
    yc, xc = np.clip(y, 0, H - 1), np.clip(x, 0, W - 1)
    i = np.minimum(np.floor(yc).astype(int), max(H - 2, 0))
    j = np.minimum(np.floor(xc).astype(int), max(W - 2, 0))
    return inside, i, j, np.minimum(i + 1, H - 1), np.minimum(j + 1, W - 1), yc - i, xc - j


def _bilinear_ref(a, y, x):
    inside, i, j, i1, j1, fy, fx = _stencil_ref(a.shape[0], a.shape[1], y, x)
    v = (1 - fy) * ((1 - fx) * a[i, j] + fx * a[i, j1]) + fy * ((1 - fx) * a[i1, j] + fx * a[i1, j1])
    return np.where(inside, v, np.nan)


def fit_sides_ref(
    rects, use, mags, oris, ndsms, has_dsm, min_h, reach, step, gate_in, gate_out, smin, smax
) -> np.ndarray:
    """numpy reference of :func:`fit_sides` (returns a fitted copy)."""
    out = rects.copy()
    m, H, W = mags.shape
    nstep = int(round(reach / step))
    q = np.arange(2 * nstep + 1)
    offs = step * ((q + 1) // 2) * np.where(q % 2 == 1, 1.0, -1.0)
    for r in range(out.shape[0]):
        cx, cy, eL, el, th = out[r]
        c, s = np.cos(th), np.sin(th)
        ks, levels = [], []
        for k in range(m):
            if not use[r, k]:
                continue
            if has_dsm:
                i0, j0 = int(np.round(cy)), int(np.round(cx))
                if not (0 <= i0 < H and 0 <= j0 < W) or not ndsms[k, i0, j0] > min_h:
                    continue
                levels.append(max(min_h, 0.5 * float(ndsms[k, i0, j0])))
            else:
                levels.append(np.nan)
            ks.append(k)
        if not ks:
            continue
        pos = np.array([0.5 * eL, -0.5 * eL, 0.5 * el, -0.5 * el])
        new = pos.copy()
        for side in range(4):
            sg = 1.0 if side % 2 == 0 else -1.0
            if side < 2:
                n_, t_, half_len, ang = (c, -s), (s, c), 0.5 * el, th
            else:
                n_, t_, half_len, ang = (s, c), (c, -s), 0.5 * eL, th + np.pi / 2
            n_along = max(3, int(1.6 * half_len) + 1)
            f = -0.8 + 1.6 * np.arange(n_along) / (n_along - 1)
            # every offset at once: row q of x, y is the side moved by offs[q]
            p = pos[side] + sg * offs[:, None]
            x = cx + p * n_[0] + f * half_len * t_[0]
            y = cy + p * n_[1] + f * half_len * t_[1]
            acc, tot, passed = np.zeros(offs.size), np.zeros(offs.size, int), np.zeros(offs.size, int)
            for k, lev in zip(ks, levels):
                # the across-side component at the four neighbours, then bilinear (as the kernel)
                inside, i, j, i1, j1, fy, fx = _stencil_ref(H, W, y, x)
                gc = [
                    mags[k][a, b] * np.abs(np.cos(oris[k][a, b] - ang)) for a, b in ((i, j), (i, j1), (i1, j), (i1, j1))
                ]
                g = (1 - fy) * ((1 - fx) * gc[0] + fx * gc[1]) + fy * ((1 - fx) * gc[2] + fx * gc[3])
                g = np.where(inside, g, np.nan)
                have = np.isfinite(g)
                tot += have.sum(axis=1)
                if has_dsm:
                    h_in = _bilinear_ref(ndsms[k], y - sg * gate_in * n_[1], x - sg * gate_in * n_[0])
                    h_out = _bilinear_ref(ndsms[k], y + sg * gate_out * n_[1], x + sg * gate_out * n_[0])
                    with np.errstate(invalid="ignore"):
                        have &= (h_in > lev) & (h_out < lev)
                acc += [float(gq[hq].sum()) for gq, hq in zip(g, have)]
                passed += have.sum(axis=1)
            best, best_d = -1.0, 0.0
            for q, d in enumerate(offs):
                if tot[q] == 0 or 2 * passed[q] < tot[q]:
                    continue
                if acc[q] / tot[q] > best + 1e-12:
                    best, best_d = acc[q] / tot[q], d
            new[side] = pos[side] + sg * best_d
        a_size, b_size = new[0] - new[1], new[2] - new[3]
        if not (smin <= a_size <= smax and smin <= b_size <= smax) or np.array_equal(new, pos):
            continue
        mu, mv = 0.5 * (new[0] + new[1]), 0.5 * (new[2] + new[3])
        out[r] = cx + mu * c + mv * s, cy - mu * s + mv * c, a_size, b_size, th
    return out


@njit(cache=True)
def _median(a):
    """``np.median`` of a 1-D float array without NaN: its middle value, or the mean of the two middle ones.

    Quickselect on a copy; numba's ``np.median`` takes seconds to compile."""
    n = a.shape[0]
    t = np.empty(n)
    for q in range(n):
        t[q] = a[q]
    h = n // 2
    m = select_kth(t, n, h)  # every value before rank h is ≤ it
    if n % 2 == 0:  # and the value of rank h − 1: the largest before it
        below = t[0]
        for q in range(1, h):
            if t[q] > below:
                below = t[q]
        m = (below + m) / 2
    return m


@njit(cache=True)
def grow_sides(rects, use, ndsms, min_h, smax, frac, valley, grew):
    """Push each side of each rectangle outward over the raised surface it stands on (in place).

    The level of a rectangle on a date is half the median height of its cells above the ground (at least
    ``min_h``). A side moves out one cell at a time while the strip of cells just beyond it (sampled at one
    point per cell along its middle 80 %, nearest cell) stands above that level in at least ``frac`` of its
    samples on every date the rectangle exists on (``use``), and while the strip is neither mostly off the
    grid nor mostly inside another rectangle; no side grows past ``smax``. A roof half whose other facet the
    stereo DSM reads low or rough in places still stands above half the roof's height, so its rectangle
    reaches the building's far wall (a few cells past it, where the blurred wall falls to half height: the
    side fit then puts the side on the image's edge). The growth also stops in a valley: when on a date the
    strip's median height rises by more than ``valley[k]`` above the lowest strip crossed so far, and that
    lowest strip lies more than ``valley[k]`` below the rectangle's median height, the side stays at the
    lowest strip. One roof seen from inside (a facet falling to its eave, a flat or a shed roof) never
    falls and rises again; two buildings whose gap a blurred DSM fills above half height do (NaN: no valley
    test on that date). ``grew[r]`` is set True where a side moved. Returns the number of rectangles grown.

    Parameters
    ----------
    rects : float64 (n, 5), changed in place
    use : bool (n, m) — which of the m dates each rectangle exists on
    ndsms : float32 (m, H, W) — height above ground per date (m), NaN = no height
    min_h, smax, frac : float (m, cells, share)
    valley : float64 (m,) — the smallest significant rise per date (m)
    grew : bool (n,), written
    """
    m, H, W = ndsms.shape
    n = rects.shape[0]
    orig = rects.copy()
    n_grown = 0
    for r in range(n):
        grew[r] = False
        cx, cy, eL, el, th = orig[r, 0], orig[r, 1], orig[r, 2], orig[r, 3], orig[r, 4]
        c = math.cos(th)
        s = math.sin(th)
        levels = np.full(m, np.inf)
        medians = np.full(m, np.nan)
        n_use = 0
        rad = math.sqrt(0.25 * eL * eL + 0.25 * el * el) + 1.0
        i0 = max(int(math.floor(cy - rad)), 0)
        i1 = min(int(math.ceil(cy + rad)), H - 1)
        j0 = max(int(math.floor(cx - rad)), 0)
        j1 = min(int(math.ceil(cx + rad)), W - 1)
        for k in range(m):
            if not use[r, k]:
                continue
            n_use += 1
            vals = np.empty(max((i1 - i0 + 1) * (j1 - j0 + 1), 1))
            nv = 0
            for i in range(i0, i1 + 1):
                for j in range(j0, j1 + 1):
                    u, v = _uv(i, j, cx, cy, c, s)
                    if abs(u) <= 0.5 * eL and abs(v) <= 0.5 * el:
                        x = ndsms[k, i, j]
                        if x == x:
                            vals[nv] = x
                            nv += 1
            if nv > 0:
                medians[k] = _median(vals[:nv])
                levels[k] = max(min_h, 0.5 * medians[k])
        if n_use == 0:
            continue
        sizes = np.array([eL, el])
        ext = np.zeros((2, 2))
        for ax in range(2):
            dc = c if ax == 0 else s
            dr = -s if ax == 0 else c
            pc = s if ax == 0 else c
            pr = c if ax == 0 else -s
            other = sizes[1 - ax]
            na = int(math.floor(0.8 * other)) + 1
            for kk in range(2):
                sg = 1.0 if kk == 0 else -1.0
                t = 0.5
                last = 0.0
                low = np.full(m, np.inf)  # the lowest strip median so far, per date
                low_t = np.zeros(m)
                strip = np.empty((m, na))
                while sizes[ax] + ext[ax, 0] + ext[ax, 1] + t + 0.5 <= smax:
                    ns = 0
                    owned = 0
                    cnt = np.zeros(m)
                    nh = np.zeros(m, np.int64)
                    for q in range(na):
                        a = -0.4 * other + q
                        x = cx + sg * (0.5 * sizes[ax] + t) * dc + a * pc
                        y = cy + sg * (0.5 * sizes[ax] + t) * dr + a * pr
                        j = int(math.floor(x + 0.5))
                        i = int(math.floor(y + 0.5))
                        if i < 0 or j < 0 or i >= H or j >= W:
                            continue
                        ns += 1
                        for o in range(n):
                            if o == r:
                                continue
                            co = math.cos(orig[o, 4])
                            so = math.sin(orig[o, 4])
                            uo, vo = _uv(i, j, orig[o, 0], orig[o, 1], co, so)
                            if abs(uo) <= 0.5 * orig[o, 2] and abs(vo) <= 0.5 * orig[o, 3]:
                                owned += 1
                                break
                        for k in range(m):
                            if use[r, k]:
                                x = ndsms[k, i, j]
                                if x > levels[k]:
                                    cnt[k] += 1.0
                                if x == x:
                                    strip[k, nh[k]] = x
                                    nh[k] += 1
                    if ns < 0.5 * na or owned > 0.5 * ns:
                        break
                    roof = True
                    for k in range(m):
                        if use[r, k] and cnt[k] < frac * ns:
                            roof = False
                    if not roof:
                        break
                    valley_at = -1.0
                    for k in range(m):
                        if not use[r, k] or nh[k] == 0:
                            continue
                        h = _median(strip[k, : nh[k]])
                        if valley[k] == valley[k] and h > low[k] + valley[k] and low[k] < medians[k] - valley[k]:
                            valley_at = max(valley_at, low_t[k])
                        if h < low[k]:
                            low[k] = h
                            low_t[k] = t
                    if valley_at >= 0.0:
                        last = valley_at + 0.5
                        break
                    last = t + 0.5
                    t += 1.0
                ext[ax, kk] = last
        moved = False
        for ax in range(2):
            if ext[ax, 0] + ext[ax, 1] > 0.0:
                dc = c if ax == 0 else s
                dr = -s if ax == 0 else c
                rects[r, 2 + ax] = sizes[ax] + ext[ax, 0] + ext[ax, 1]
                rects[r, 0] += dc * 0.5 * (ext[ax, 0] - ext[ax, 1])
                rects[r, 1] += dr * 0.5 * (ext[ax, 0] - ext[ax, 1])
                moved = True
        if moved:
            grew[r] = True
            n_grown += 1
    return n_grown


def grow_sides_ref(rects, use, ndsms, min_h, smax, frac, valley) -> tuple[np.ndarray, np.ndarray]:
    """numpy reference of :func:`grow_sides` (returns the grown copy and ``grew``)."""
    m, H, W = ndsms.shape
    orig = np.array(rects, np.float64)
    out = orig.copy()
    grew = np.zeros(orig.shape[0], bool)

    def inside(rect, j, i):
        c, s = np.cos(rect[4]), np.sin(rect[4])
        dx, dy = j - rect[0], i - rect[1]
        return (np.abs(dx * c - dy * s) <= rect[2] / 2) & (np.abs(dx * s + dy * c) <= rect[3] / 2)

    for r, (cx, cy, eL, el, th) in enumerate(orig):
        ks = [k for k in range(m) if use[r, k]]
        if not ks:
            continue
        mask = rect_mask_ref(orig[r], (H, W))
        levels, medians = {}, {}
        for k in ks:
            v = ndsms[k][mask]
            v = v[np.isfinite(v)]
            medians[k] = float(np.median(v)) if v.size else np.nan
            levels[k] = max(min_h, 0.5 * medians[k]) if v.size else np.inf
        c, s = np.cos(th), np.sin(th)
        sizes = [eL, el]
        ext = np.zeros((2, 2))
        for ax in range(2):
            d = np.array([c, -s]) if ax == 0 else np.array([s, c])
            p = np.array([s, c]) if ax == 0 else np.array([c, -s])
            other = sizes[1 - ax]
            a = -0.4 * other + np.arange(int(np.floor(0.8 * other)) + 1)
            for kk, sg in enumerate((1.0, -1.0)):
                t, last = 0.5, 0.0
                low = {k: (np.inf, 0.0) for k in ks}
                while sizes[ax] + ext[ax].sum() + t + 0.5 <= smax:
                    pts = np.array([cx, cy]) + sg * (sizes[ax] / 2 + t) * d + a[:, None] * p
                    j = np.floor(pts[:, 0] + 0.5).astype(int)
                    i = np.floor(pts[:, 1] + 0.5).astype(int)
                    ok = (i >= 0) & (j >= 0) & (i < H) & (j < W)
                    i, j = i[ok], j[ok]
                    owned = np.zeros(i.size, bool)
                    for o in range(orig.shape[0]):
                        if o != r:
                            owned |= inside(orig[o], j, i)
                    if i.size < 0.5 * a.size or owned.sum() > 0.5 * i.size:
                        break
                    if not all((ndsms[k][i, j] > levels[k]).sum() >= frac * i.size for k in ks):
                        break
                    bottoms = []
                    for k in ks:
                        v = ndsms[k][i, j]
                        v = v[np.isfinite(v)]
                        if not v.size:
                            continue
                        h = float(np.median(v))
                        lo, lo_t = low[k]
                        if np.isfinite(valley[k]) and h > lo + valley[k] and lo < medians[k] - valley[k]:
                            bottoms.append(lo_t)
                        if h < lo:
                            low[k] = (h, t)
                    if bottoms:
                        last = max(bottoms) + 0.5
                        break
                    last = t + 0.5
                    t += 1.0
                ext[ax, kk] = last
            if ext[ax].sum() > 0:
                out[r, 2 + ax] = sizes[ax] + ext[ax].sum()
                out[r, 0:2] += d * 0.5 * (ext[ax, 0] - ext[ax, 1])
                grew[r] = True
    return out, grew


@njit(cache=True)
def _box(S, q0, q1, p0, p1):
    """Sum of the cells [q0, q1) × [p0, p1) of the array whose integral image is ``S``."""
    return S[q1, p1] - S[q0, p1] - S[q1, p0] + S[q0, p0]


@njit(cache=True)
def _integral(a, S):
    """The integral image of ``a`` (nv, nu) into ``S`` (nv + 1, nu + 1), zero on its first row and column."""
    nv, nu = a.shape
    for q in range(nv):
        for p in range(nu):
            S[q + 1, p + 1] = a[q, p] + S[q, p + 1] + S[q + 1, p] - S[q, p]


@njit(cache=True)
def _notch_span(n, k, sign, ew):
    """On one lattice axis of ``n`` points, a notch of ``k`` points at the ``sign`` end: its range [a, b), the
    cut (the boundary between the notch and the rest: points cut − 1 and cut lie on either side of it), and
    the edge band [cut − ew, cut + ew) clipped to the axis."""
    a = n - k if sign > 0 else 0
    b = n if sign > 0 else k
    cut = n - k if sign > 0 else k
    return a, b, cut, max(cut - ew, 0), min(cut + ew, n)


@njit(cache=True)
def carve_corners(rects, use, mags, oris, hmaps, valids, min_h, edge_w, smin, d_grad, out):
    """The best corner notch of each rectangle: a corner rectangle to cut away, whose cells are not raised
    and whose two inner sides are edges, on every date the rectangle exists on (``out`` written).

    The rectangle is sampled on its own lattice, one point per cell (``round(e_L) × round(e_l)`` points,
    nearest cell). A notch keeps ``k_u`` lattice columns and ``k_v`` rows at one corner, with
    ``k ≥ 2 edge_w`` cells on each axis (the inner sides' edge bands lie inside the rectangle) and at least
    ``smin`` cells left on each axis (the two arms of the L stay building-sized). On a date, a notch passes
    when under half of its cells with a height stand above ``min_h`` on the height map (the height term's
    "raised", 0.5 its Q midpoint) and the mean gradient across its two inner sides, over their edge bands
    (``edge_w`` lattice steps on each side of the cut, along the notch), exceeds that image's ``d_grad`` (the
    gradient term's Q midpoint: what the model calls an outline's edge). Of the notches that pass on every
    date of ``use``, the one whose cuts lie on the strongest edges wins: the largest Σ over dates of the mean
    gradient across the two lattice lines on either side of each cut, / ``d_grad``. Lattice points off the
    grid count nowhere: a rectangle the grid's border cuts is judged on what the grid shows of it, and one
    arm of its L may lie wholly off the grid.

    Parameters
    ----------
    rects : float64 (n, 5); use : bool (n, m)
    mags, oris : float32 (m, H, W) — gradient magnitude and orientation per image
    hmaps : float32 (m, H, W) — the height term's map per date (m above ground; NaN: no height)
    valids : bool (m, H, W) — valid image cells
    min_h, edge_w, smin : float (m, cells, cells); d_grad : float64 (m,)
    out : float64 (n, 5), written: corner signs s_u, s_v (±1; 0, 0 when no notch passes), the notch's
        sides a_u, a_v (cells) and its score
    """
    m, H, W = mags.shape
    ew = max(1, int(round(edge_w)))
    for r in range(rects.shape[0]):
        out[r, 0] = 0.0
        out[r, 1] = 0.0
        out[r, 2] = 0.0
        out[r, 3] = 0.0
        out[r, 4] = -1.0
        cx, cy, eL, el, th = rects[r, 0], rects[r, 1], rects[r, 2], rects[r, 3], rects[r, 4]
        nu = max(1, int(round(eL)))
        nv = max(1, int(round(el)))
        du = eL / nu
        dv = el / nv
        ku0 = max(2 * ew, int(math.ceil(2.0 * edge_w / du - 1e-9)))
        kv0 = max(2 * ew, int(math.ceil(2.0 * edge_w / dv - 1e-9)))
        ku1 = min(int(math.floor((eL - smin) / du + 1e-9)), nu - 2)
        kv1 = min(int(math.floor((el - smin) / dv + 1e-9)), nv - 2)
        if ku1 < ku0 or kv1 < kv0:
            continue
        c = math.cos(th)
        s = math.sin(th)
        ks = np.empty(m, np.int64)
        nk = 0
        for k in range(m):
            if use[r, k]:
                ks[nk] = k
                nk += 1
        if nk == 0:
            continue
        SR = np.zeros((nk, nv + 1, nu + 1))
        SF = np.zeros((nk, nv + 1, nu + 1))
        SGU = np.zeros((nk, nv + 1, nu + 1))
        SGV = np.zeros((nk, nv + 1, nu + 1))
        SV = np.zeros((nk, nv + 1, nu + 1))
        for a in range(nk):
            k = ks[a]
            R = np.zeros((nv, nu))
            F = np.zeros((nv, nu))
            GU = np.zeros((nv, nu))
            GV = np.zeros((nv, nu))
            V = np.zeros((nv, nu))
            for q in range(nv):
                vv = -0.5 * el + (q + 0.5) * dv
                for p in range(nu):
                    uu = -0.5 * eL + (p + 0.5) * du
                    j = int(math.floor(cx + c * uu + s * vv + 0.5))
                    i = int(math.floor(cy - s * uu + c * vv + 0.5))
                    if i < 0 or j < 0 or i >= H or j >= W:
                        continue
                    h = hmaps[k, i, j]
                    if h == h:
                        F[q, p] = 1.0
                        if h > min_h:
                            R[q, p] = 1.0
                    if valids[k, i, j]:
                        V[q, p] = 1.0
                        d = oris[k, i, j] - th
                        GU[q, p] = mags[k, i, j] * abs(math.cos(d))
                        GV[q, p] = mags[k, i, j] * abs(math.sin(d))
            _integral(R, SR[a])  # in place: assigning an array to SR[a] compiles numba's broadcasting
            _integral(F, SF[a])
            _integral(GU, SGU[a])
            _integral(GV, SGV[a])
            _integral(V, SV[a])
        best = -1.0
        for corner in range(4):
            su = 1 if corner % 2 == 0 else -1
            sv = 1 if corner < 2 else -1
            for ku in range(ku0, ku1 + 1):
                # notch columns, and the columns of the band across its side normal to u
                p0, p1, cut_u, bu0, bu1 = _notch_span(nu, ku, su, ew)
                for kv in range(kv0, kv1 + 1):
                    q0, q1, cut_v, bv0, bv1 = _notch_span(nv, kv, sv, ew)
                    score = 0.0
                    ok = True
                    for a in range(nk):
                        f = _box(SF[a], q0, q1, p0, p1)
                        if f <= 0 or _box(SR[a], q0, q1, p0, p1) >= 0.5 * f:
                            ok = False
                            break
                        n1 = _box(SV[a], q0, q1, bu0, bu1)
                        n2 = _box(SV[a], bv0, bv1, p0, p1)
                        if n1 + n2 <= 0:
                            ok = False
                            break
                        g = (_box(SGU[a], q0, q1, bu0, bu1) + _box(SGV[a], bv0, bv1, p0, p1)) / (n1 + n2)
                        if not g > d_grad[ks[a]]:
                            ok = False
                            break
                        # the score reads the two lattice lines on either side of each cut: a band of
                        # 2 edge_w holds an edge at several cut positions, these lines only at the edge
                        m1 = _box(SV[a], q0, q1, cut_u - 1, cut_u + 1)
                        m2 = _box(SV[a], cut_v - 1, cut_v + 1, p0, p1)
                        score += (
                            (_box(SGU[a], q0, q1, cut_u - 1, cut_u + 1) + _box(SGV[a], cut_v - 1, cut_v + 1, p0, p1))
                            / max(m1 + m2, 1.0)
                        ) / d_grad[ks[a]]
                    if ok and score > best:
                        best = score
                        out[r, 0] = su
                        out[r, 1] = sv
                        out[r, 2] = ku * du
                        out[r, 3] = kv * dv
                        out[r, 4] = score
    return out


def carve_corners_ref(rects, use, mags, oris, hmaps, valids, min_h, edge_w, smin, d_grad) -> np.ndarray:
    """numpy reference of :func:`carve_corners` (returns ``out``): masks on the lattice, no integral images."""
    m, H, W = mags.shape
    ew = max(1, int(round(edge_w)))
    out = np.zeros((rects.shape[0], 5))
    out[:, 4] = -1.0
    for r, (cx, cy, eL, el, th) in enumerate(rects):
        nu, nv = max(1, int(round(eL))), max(1, int(round(el)))
        du, dv = eL / nu, el / nv
        ku0 = max(2 * ew, int(np.ceil(2.0 * edge_w / du - 1e-9)))
        kv0 = max(2 * ew, int(np.ceil(2.0 * edge_w / dv - 1e-9)))
        ku1 = min(int(np.floor((eL - smin) / du + 1e-9)), nu - 2)
        kv1 = min(int(np.floor((el - smin) / dv + 1e-9)), nv - 2)
        ks = [k for k in range(m) if use[r, k]]
        if ku1 < ku0 or kv1 < kv0 or not ks:
            continue
        uu = -0.5 * eL + (np.arange(nu) + 0.5) * du
        vv = -0.5 * el + (np.arange(nv) + 0.5) * dv
        U, Vv = np.meshgrid(uu, vv)
        c, s = np.cos(th), np.sin(th)
        j = np.floor(cx + c * U + s * Vv + 0.5).astype(int)
        i = np.floor(cy - s * U + c * Vv + 0.5).astype(int)
        on = (i >= 0) & (j >= 0) & (i < H) & (j < W)
        ic, jc = np.clip(i, 0, H - 1), np.clip(j, 0, W - 1)
        lat = {}
        for k in ks:
            h = np.where(on, hmaps[k][ic, jc], np.nan)
            val = on & valids[k][ic, jc]
            d = oris[k][ic, jc] - th
            lat[k] = (
                np.isfinite(h),
                np.isfinite(h) & (h > min_h),
                val,
                np.where(val, mags[k][ic, jc] * np.abs(np.cos(d)), 0.0),
                np.where(val, mags[k][ic, jc] * np.abs(np.sin(d)), 0.0),
            )
        P, Q_ = np.meshgrid(np.arange(nu), np.arange(nv))
        best = -1.0
        for corner in range(4):
            su, sv = (1 if corner % 2 == 0 else -1), (1 if corner < 2 else -1)
            for ku in range(ku0, ku1 + 1):
                cols = (P >= nu - ku) if su > 0 else (P < ku)
                cut_u = nu - ku if su > 0 else ku
                band_u = (P >= cut_u - ew) & (P < cut_u + ew)
                for kv in range(kv0, kv1 + 1):
                    rows = (Q_ >= nv - kv) if sv > 0 else (Q_ < kv)
                    cut_v = nv - kv if sv > 0 else kv
                    band_v = (Q_ >= cut_v - ew) & (Q_ < cut_v + ew)
                    notch, e1, e2 = cols & rows, rows & band_u, cols & band_v
                    l1 = rows & (P >= cut_u - 1) & (P < cut_u + 1)
                    l2 = cols & (Q_ >= cut_v - 1) & (Q_ < cut_v + 1)
                    score, ok = 0.0, True
                    for k in ks:
                        fin, rai, val, gu, gv = lat[k]
                        f = fin[notch].sum()
                        n = val[e1].sum() + val[e2].sum()
                        if f == 0 or rai[notch].sum() >= 0.5 * f or n == 0:
                            ok = False
                            break
                        g = (gu[e1].sum() + gv[e2].sum()) / n
                        if not g > d_grad[k]:
                            ok = False
                            break
                        gl = (gu[l1].sum() + gv[l2].sum()) / max(val[l1].sum() + val[l2].sum(), 1)
                        score += gl / d_grad[k]
                    if ok and score > best:
                        best = score
                        out[r] = (su, sv, ku * du, kv * dv, score)
    return out
