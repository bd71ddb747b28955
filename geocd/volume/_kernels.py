"""Numba kernels of the volumetric model, each with a small pure-numpy reference.

Conventions shared by every kernel
----------------------------------
* ``geo`` is float64[8]: ``x0, y0, z0`` (lower box corner, ENU m), block edge,
  ``nbx, nby, nbz``, ``max_depth`` (see :meth:`VolumeGeometry.geo_array`).
* Rays are ``orig (N, 3)`` and unit ``dirs (N, 3)`` in ENU metres; a ray is
  clipped to the box ``[lo, hi]`` before it is traced.
* A ray is cut into *segments* ``(cell, length ℓ, entry distance t)``, one per
  octree leaf it crosses, by a 3-D DDA: from the current point, descend from the
  block's root to the leaf containing it (≤ max_depth steps), leave the leaf's box
  through the nearest face, repeat. Block faces are leaf faces, so blocks need no
  separate walk.
* Per-ray kernels are allocation-free: the caller passes scratch buffers sized
  by :func:`max_segments`.
* Appearance ``app[cell, bin, mode, (mean, sigma, weight, n_obs)]``; a bin with
  no weight is a uniform density on [0, 1] (density 1, mean 0.5). ``bin < 0``
  means "no appearance": every cell is uniform.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

INV_SQRT_2PI = 0.3989422804014327
POST_MAX = 1.0 - 1e-7  # posterior occlusion probabilities are clamped below 1 (log of eq. 25)


def max_segments(geo: np.ndarray) -> int:
    """An upper bound on the segments of one ray: finest-grid plane crossings + margin."""
    k = 1 << int(geo[7])
    return int((geo[4] + geo[5] + geo[6]) * k) + 16


# ------------------------------------------------------------------------------------------
# ray / box / octree traversal
# ------------------------------------------------------------------------------------------
@njit(cache=True)
def clip_ray(ox, oy, oz, dx, dy, dz, lo, hi):
    """Distances ``(t0, t1)`` where the ray ``o + t d`` (t ≥ 0) is inside the box; t1 <= t0 when it misses."""
    t0 = 0.0
    t1 = 1e300
    o = (ox, oy, oz)
    d = (dx, dy, dz)
    for a in range(3):
        if d[a] != 0.0:
            ta = (lo[a] - o[a]) / d[a]
            tb = (hi[a] - o[a]) / d[a]
            if ta > tb:
                ta, tb = tb, ta
            if ta > t0:
                t0 = ta
            if tb < t1:
                t1 = tb
        elif o[a] < lo[a] or o[a] > hi[a]:
            return 0.0, -1.0
    return t0, t1


@njit(cache=True)
def trace_ray(ox, oy, oz, dx, dy, dz, t0, t1, geo, block_root, child, seg_cell, seg_len, seg_t):
    """Cut the ray between ``t0`` and ``t1`` into leaf segments; returns their number.

    Fills ``seg_cell[:n]`` (node index), ``seg_len[:n]`` (m) and ``seg_t[:n]``
    (entry distance, m). Stops early (without error) when the buffers are full.
    """
    x0 = geo[0]
    y0 = geo[1]
    z0 = geo[2]
    bs = geo[3]
    nbx = int(geo[4])
    nby = int(geo[5])
    nbz = int(geo[6])
    finest = bs / (1 << int(geo[7]))
    eps = 1e-6 * finest
    inv = 1.0 / bs
    nmax = seg_cell.shape[0]
    n = 0
    t = t0
    while n < nmax:
        tm = t + eps
        if tm >= t1:
            break
        fx = (ox + tm * dx - x0) * inv
        fy = (oy + tm * dy - y0) * inv
        fz = (oz + tm * dz - z0) * inv
        bx = int(math.floor(fx))
        by = int(math.floor(fy))
        bz = int(math.floor(fz))
        if bx < 0 or by < 0 or bz < 0 or bx >= nbx or by >= nby or bz >= nbz:
            break
        ux = fx - bx
        uy = fy - by
        uz = fz - bz
        node = int(block_root[bx, by, bz])
        lvl = 0
        cx = 0
        cy = 0
        cz = 0
        while child[node] >= 0:
            lvl += 1
            s = 1 << lvl
            cx = int(ux * s)
            cy = int(uy * s)
            cz = int(uz * s)
            if cx >= s:
                cx = s - 1
            if cy >= s:
                cy = s - 1
            if cz >= s:
                cz = s - 1
            node = int(child[node]) + ((cx & 1) | ((cy & 1) << 1) | ((cz & 1) << 2))
        size = bs / (1 << lvl)
        lox = x0 + bx * bs + cx * size
        loy = y0 + by * bs + cy * size
        loz = z0 + bz * bs + cz * size
        te = t1
        if dx > 0.0:
            tt = (lox + size - ox) / dx
            if tt < te:
                te = tt
        elif dx < 0.0:
            tt = (lox - ox) / dx
            if tt < te:
                te = tt
        if dy > 0.0:
            tt = (loy + size - oy) / dy
            if tt < te:
                te = tt
        elif dy < 0.0:
            tt = (loy - oy) / dy
            if tt < te:
                te = tt
        if dz > 0.0:
            tt = (loz + size - oz) / dz
            if tt < te:
                te = tt
        elif dz < 0.0:
            tt = (loz - oz) / dz
            if tt < te:
                te = tt
        if te < tm:
            te = tm
        seg_cell[n] = node
        seg_len[n] = te - t
        seg_t[n] = t
        n += 1
        t = te
    return n


# ------------------------------------------------------------------------------------------
# appearance mixtures
# ------------------------------------------------------------------------------------------
@njit(cache=True)
def mog_density(app, cell, b, x, w0):
    """Density of intensity ``x`` under the cell's mixture in bin ``b``.

    The mixture is blended with the uniform density in proportion to the
    evidence behind it: ``(N p_mog(x) + w0) / (N + w0)`` with ``N = Σ n_obs`` the
    cell's total (visibility-weighted) observation weight and ``w0`` the prior
    weight. A cell never clearly seen (occluded, outside the views) thus predicts
    "anything" rather than the appearance of whatever hid it.
    """
    if b < 0:
        return 1.0
    p = 0.0
    ws = 0.0
    nobs = 0.0
    for k in range(app.shape[2]):
        w = app[cell, b, k, 2]
        if w > 0.0:
            s = app[cell, b, k, 1]
            z = (x - app[cell, b, k, 0]) / s
            p += w * math.exp(-0.5 * z * z) / s
            ws += w
            nobs += app[cell, b, k, 3]
    if ws <= 0.0:
        return 1.0
    return (nobs * p * INV_SQRT_2PI / ws + w0) / (nobs + w0)


@njit(cache=True)
def mog_density_mapped(app, cell, b, x, w0, ma, mb, ms):
    """:func:`mog_density` of the mixture mapped by ``μ → ma + mb μ``, ``σ → sqrt((mb σ)² + ms²)``
    (relighting; ``mb = 1, ma = ms = 0`` is the identity)."""
    if b < 0:
        return 1.0
    p = 0.0
    ws = 0.0
    nobs = 0.0
    amb = abs(mb)
    for k in range(app.shape[2]):
        w = app[cell, b, k, 2]
        if w > 0.0:
            sg = app[cell, b, k, 1] * amb
            s = math.sqrt(sg * sg + ms * ms)
            mu = ma + mb * app[cell, b, k, 0]
            z = (x - mu) / s
            p += w * math.exp(-0.5 * z * z) / s
            ws += w
            nobs += app[cell, b, k, 3]
    if ws <= 0.0:
        return 1.0
    return (nobs * p * INV_SQRT_2PI / ws + w0) / (nobs + w0)


@njit(cache=True)
def mog_density_cells(app, b, x, w0, out):
    """``out[cell] = mog_density(app, cell, b, x[cell], w0)`` for every cell (``x``, ``out``: (n_cells,))."""
    for cell in range(x.shape[0]):
        out[cell] = mog_density(app, cell, b, x[cell], w0)


@njit(cache=True)
def mog_mean(app, cell, b, w0):
    """Mean intensity of the cell's blended density in bin ``b`` (0.5 when empty; see :func:`mog_density`)."""
    if b < 0:
        return 0.5
    m = 0.0
    ws = 0.0
    nobs = 0.0
    for k in range(app.shape[2]):
        w = app[cell, b, k, 2]
        if w > 0.0:
            m += w * app[cell, b, k, 0]
            ws += w
            nobs += app[cell, b, k, 3]
    if ws <= 0.0:
        return 0.5
    return (nobs * m / ws + 0.5 * w0) / (nobs + w0)


@njit(cache=True)
def mog_update(app, cell, b, x, w, sigma_init, sigma_min, match_sigmas):
    """Stauffer–Grimson online update of one mixture with observation ``x`` of weight ``w``.

    Modes are kept sorted by ``weight / sigma`` (most reliable first). A matched
    mode learns at rate ``w / n_obs``; mode weights learn at ``w / Σ n_obs``; an
    unmatched observation replaces the last mode (``sigma_init``).
    """
    nm = app.shape[2]
    total = 0.0
    for k in range(nm):
        total += app[cell, b, k, 3]
    total += w
    rate = w / total
    match = -1
    for k in range(nm):
        if app[cell, b, k, 2] > 0.0:
            if abs(x - app[cell, b, k, 0]) <= match_sigmas * app[cell, b, k, 1]:
                match = k
                break
    if match >= 0:
        n_k = app[cell, b, match, 3] + w
        rho = w / n_k
        d = x - app[cell, b, match, 0]
        app[cell, b, match, 0] += rho * d
        var = (1.0 - rho) * (app[cell, b, match, 1] ** 2 + rho * d * d)
        s = math.sqrt(var)
        app[cell, b, match, 1] = s if s > sigma_min else sigma_min
        app[cell, b, match, 3] = n_k
        for k in range(nm):
            if app[cell, b, k, 2] > 0.0 or k == match:
                app[cell, b, k, 2] = (1.0 - rate) * app[cell, b, k, 2] + (rate if k == match else 0.0)
    else:
        k_new = nm - 1
        for k in range(nm):
            if app[cell, b, k, 2] <= 0.0:
                k_new = k
                break
        # drop the replaced mode's weight, rescale the others to 1 - rate
        rest = 0.0
        for k in range(nm):
            if k != k_new:
                rest += app[cell, b, k, 2]
        for k in range(nm):
            if k != k_new:
                app[cell, b, k, 2] = app[cell, b, k, 2] * (1.0 - rate) / rest if rest > 0.0 else 0.0
        app[cell, b, k_new, 0] = x
        app[cell, b, k_new, 1] = sigma_init
        app[cell, b, k_new, 2] = rate if rest > 0.0 else 1.0
        app[cell, b, k_new, 3] = w
    # keep modes sorted by weight / sigma (descending); empty modes last
    for i in range(nm):
        for j in range(nm - 1 - i):
            wa = app[cell, b, j, 2]
            wb = app[cell, b, j + 1, 2]
            ka = wa / app[cell, b, j, 1] if wa > 0.0 else -1.0
            kb = wb / app[cell, b, j + 1, 1] if wb > 0.0 else -1.0
            if kb > ka:
                for f in range(app.shape[3]):
                    tmp = app[cell, b, j, f]
                    app[cell, b, j, f] = app[cell, b, j + 1, f]
                    app[cell, b, j + 1, f] = tmp


# ------------------------------------------------------------------------------------------
# update (paper §V): one pass over an image's rays accumulates per-cell sums
# ------------------------------------------------------------------------------------------
@njit(cache=True)
def seglen_rays(orig, dirs, obs, lo, hi, geo, block_root, child, acc_len, acc_obs, seg_cell, seg_len, seg_t):
    """First pass: per cell, ``acc_len += ℓ`` and ``acc_obs += ℓ c`` over the rays with a finite
    observation (the cell's length-weighted mean observation is ``acc_obs / acc_len``).
    Returns the number of segments traced."""
    total = 0
    for r in range(orig.shape[0]):
        c = obs[r]
        if not math.isfinite(c):
            continue
        t0, t1 = clip_ray(orig[r, 0], orig[r, 1], orig[r, 2], dirs[r, 0], dirs[r, 1], dirs[r, 2], lo, hi)
        if t1 <= t0:
            continue
        n = trace_ray(
            orig[r, 0],
            orig[r, 1],
            orig[r, 2],
            dirs[r, 0],
            dirs[r, 1],
            dirs[r, 2],
            t0,
            t1,
            geo,
            block_root,
            child,
            seg_cell,
            seg_len,
            seg_t,
        )
        total += n
        for i in range(n):
            acc_len[seg_cell[i]] += seg_len[i]
            acc_obs[seg_cell[i]] += seg_len[i] * c
    return total


@njit(cache=True)
def update_rays(
    orig,
    dirs,
    obs,
    cell_pa,
    lo,
    hi,
    geo,
    block_root,
    child,
    alpha,
    app,
    b,
    p_bg,
    w0,
    acc_len,
    acc_log,
    acc_obs,
    acc_vis,
    seg_cell,
    seg_len,
    seg_t,
    s_vis,
    s_pq,
    s_pa,
    s_pre,
):
    """Accumulate, per cell, the statistics of eqs. 20–25 over the rays of one image.

    For each ray with a finite observation ``obs[r]`` (intensity in [0, 1]):
    ``P(Q_i) = 1 - exp(-α_i ℓ_i)``, ``vis_i = Π_{j<i} (1 - P(Q_j))``,
    ``pre_i = Σ_{j<i} P(Q_j) vis_j p_j(c_i)`` and the posterior (eq. 22)
    ``P(Q_i|D) = P(Q_i) (pre_i + vis_i p_i(c_i)) / (pre_∞ + vis_∞ p_bg)``; then

    * ``acc_len[cell] += ℓ_i``, ``acc_log[cell] += log(1 - P(Q_i|D))`` (eq. 25),
    * ``acc_obs[cell] += ℓ_i c``, ``acc_vis[cell] += ℓ_i vis_i`` (appearance).

    ``p_i(c_i)`` is the cell's density (:func:`mog_density`) at the pixel's
    intensity when ``cell_pa`` is empty (the paper's eq. 20), else ``cell_pa[cell]``,
    its density at the cell's mean observation in this image (boxm2's practice: a
    large cell's mixture, which learns mean observations, is compared with the
    mean, so coarse cells on a textured surface still gain occlusion density and
    get refined). That density depends on the cell alone, so the caller computes
    it once per cell (:func:`mog_density_cells`) rather than once per segment.

    Returns the number of segments traced.
    """
    use_cell = cell_pa.shape[0] > 0
    total = 0
    for r in range(orig.shape[0]):
        c = obs[r]
        if not math.isfinite(c):
            continue
        ox = orig[r, 0]
        oy = orig[r, 1]
        oz = orig[r, 2]
        dx = dirs[r, 0]
        dy = dirs[r, 1]
        dz = dirs[r, 2]
        t0, t1 = clip_ray(ox, oy, oz, dx, dy, dz, lo, hi)
        if t1 <= t0:
            continue
        n = trace_ray(ox, oy, oz, dx, dy, dz, t0, t1, geo, block_root, child, seg_cell, seg_len, seg_t)
        total += n
        vis = 1.0
        pre = 0.0
        for i in range(n):
            cell = seg_cell[i]
            pq = 1.0 - math.exp(-alpha[cell] * seg_len[i])
            pa = cell_pa[cell] if use_cell else mog_density(app, cell, b, c, w0)
            s_vis[i] = vis
            s_pq[i] = pq
            s_pa[i] = pa
            s_pre[i] = pre
            pre += pq * vis * pa
            vis *= 1.0 - pq
        denom = pre + vis * p_bg
        if not (denom > 1e-300):
            continue
        for i in range(n):
            cell = seg_cell[i]
            post = s_pq[i] * (s_pre[i] + s_vis[i] * s_pa[i]) / denom
            if post > POST_MAX:
                post = POST_MAX
            ln = seg_len[i]
            acc_len[cell] += ln
            acc_log[cell] += math.log1p(-post)
            acc_obs[cell] += ln * c
            acc_vis[cell] += ln * s_vis[i]
    return total


@njit(cache=True)
def finalize_update(
    acc_len,
    acc_log,
    acc_obs,
    acc_vis,
    alpha,
    app,
    b,
    alpha_min,
    alpha_max,
    sigma_init,
    sigma_min,
    match_sigmas,
    min_obs_weight,
):
    """Per cell seen by the image: α ← -Σ log(1 - P(Q_k|D)) / Σ ℓ_k (eq. 25), clamped;
    appearance ← mixture update with the length-weighted mean observation, weighted by the
    length-weighted mean visibility. Returns the number of cells updated."""
    cnt = 0
    for cell in range(acc_len.shape[0]):
        ln = acc_len[cell]
        if ln <= 0.0:
            continue
        cnt += 1
        a = -acc_log[cell] / ln
        if a < alpha_min:
            a = alpha_min
        elif a > alpha_max:
            a = alpha_max
        alpha[cell] = a
        if b >= 0:
            w = acc_vis[cell] / ln
            if w > min_obs_weight:
                mog_update(app, cell, b, acc_obs[cell] / ln, w, sigma_init, sigma_min, match_sigmas)
    return cnt


# ------------------------------------------------------------------------------------------
# rendering and change detection (paper §VI)
# ------------------------------------------------------------------------------------------
@njit(cache=True)
def render_rays(
    orig,
    dirs,
    obs,
    lo,
    hi,
    geo,
    block_root,
    child,
    alpha,
    app,
    b,
    p_bg,
    mean_bg,
    w0,
    map_a,
    map_b,
    map_s,
    out_density,
    out_expected,
    out_visinf,
    out_tmed,
    seg_cell,
    seg_len,
    seg_t,
):
    """Per ray: density of ``obs[r]`` (eq. 27, + vis_∞ p_bg; NaN when obs is NaN),
    expected intensity ``Σ vis_i P(Q_i) E[p_i] + vis_∞ mean_bg``, ``vis_∞`` and the
    distance where visibility falls to 0.5 (NaN if it never does).

    ``map_a, map_b, map_s`` (length N, or empty for none) map every mixture along ray
    ``r`` (see :func:`mog_density_mapped`) for the density and the expected value.
    Returns the number of segments traced."""
    use_map = map_a.shape[0] > 0
    total = 0
    for r in range(orig.shape[0]):
        c = obs[r]
        ox = orig[r, 0]
        oy = orig[r, 1]
        oz = orig[r, 2]
        dx = dirs[r, 0]
        dy = dirs[r, 1]
        dz = dirs[r, 2]
        n = 0
        if math.isfinite(ox) and math.isfinite(dx):
            t0, t1 = clip_ray(ox, oy, oz, dx, dy, dz, lo, hi)
            if t1 > t0:
                n = trace_ray(ox, oy, oz, dx, dy, dz, t0, t1, geo, block_root, child, seg_cell, seg_len, seg_t)
        total += n
        vis = 1.0
        dens = 0.0
        expv = 0.0
        tmed = np.nan
        has_obs = math.isfinite(c)
        ma = map_a[r] if use_map else 0.0
        mb = map_b[r] if use_map else 1.0
        ms = map_s[r] if use_map else 0.0
        for i in range(n):
            cell = seg_cell[i]
            a = alpha[cell]
            pq = 1.0 - math.exp(-a * seg_len[i])
            w = vis * pq
            if has_obs:
                if use_map:
                    dens += w * mog_density_mapped(app, cell, b, c, w0, ma, mb, ms)
                else:
                    dens += w * mog_density(app, cell, b, c, w0)
            if use_map:
                expv += w * (ma + mb * mog_mean(app, cell, b, w0))
            else:
                expv += w * mog_mean(app, cell, b, w0)
            nv = vis * (1.0 - pq)
            if vis >= 0.5 and nv < 0.5 and not math.isfinite(tmed):
                tmed = seg_t[i] + math.log(vis / 0.5) / a
            vis = nv
        out_density[r] = dens + vis * p_bg if has_obs else np.nan
        out_expected[r] = expv + vis * mean_bg
        out_visinf[r] = vis
        out_tmed[r] = tmed
    return total


@njit(cache=True)
def density_nxn(
    orig,
    dirs,
    img,
    width,
    half,
    lo,
    hi,
    geo,
    block_root,
    child,
    alpha,
    app,
    b,
    p_bg,
    w0,
    map_a,
    map_b,
    map_s,
    out_max,
    seg_cell,
    seg_len,
    seg_t,
    s_w,
):
    """n×n change variant: ``out_max[q]`` = max over the rays of q's (2·half+1)² neighbours of
    the density of q's intensity. Rays are row-major over an image of ``width`` columns
    (``orig.shape[0] == rows * width``); ``out_max`` must start at 0. Returns segments traced."""
    use_map = map_a.shape[0] > 0
    total = 0
    nr = orig.shape[0]
    rows = nr // width
    for r in range(nr):
        ox = orig[r, 0]
        oy = orig[r, 1]
        oz = orig[r, 2]
        dx = dirs[r, 0]
        dy = dirs[r, 1]
        dz = dirs[r, 2]
        n = 0
        if math.isfinite(ox) and math.isfinite(dx):
            t0, t1 = clip_ray(ox, oy, oz, dx, dy, dz, lo, hi)
            if t1 > t0:
                n = trace_ray(ox, oy, oz, dx, dy, dz, t0, t1, geo, block_root, child, seg_cell, seg_len, seg_t)
        total += n
        vis = 1.0
        for i in range(n):
            pq = 1.0 - math.exp(-alpha[seg_cell[i]] * seg_len[i])
            s_w[i] = vis * pq
            vis *= 1.0 - pq
        ri = r // width
        ci = r - ri * width
        for di in range(-half, half + 1):
            qi = ri + di
            if qi < 0 or qi >= rows:
                continue
            for dj in range(-half, half + 1):
                qj = ci + dj
                if qj < 0 or qj >= width:
                    continue
                c = img[qi, qj]
                if not math.isfinite(c):
                    continue
                p = vis * p_bg
                if use_map:
                    for i in range(n):
                        p += s_w[i] * mog_density_mapped(app, seg_cell[i], b, c, w0, map_a[r], map_b[r], map_s[r])
                else:
                    for i in range(n):
                        p += s_w[i] * mog_density(app, seg_cell[i], b, c, w0)
                if p > out_max[qi, qj]:
                    out_max[qi, qj] = p
    return total


# ------------------------------------------------------------------------------------------
# pure-numpy references (small scenes only; used by the agreement tests)
# ------------------------------------------------------------------------------------------
def _leaf_at_ref(p, geo, block_root, child):
    x0, y0, z0, bs = geo[:4]
    f = (np.asarray(p) - np.array([x0, y0, z0])) / bs
    bidx = np.floor(f).astype(int)
    node = int(block_root[tuple(bidx)])
    u = f - bidx
    lvl = 0
    while child[node] >= 0:
        lvl += 1
        c = np.minimum((u * 2**lvl).astype(int), 2**lvl - 1)
        node = int(child[node]) + int((c[0] & 1) | ((c[1] & 1) << 1) | ((c[2] & 1) << 2))
    return node


def trace_ray_ref(o, d, geo, block_root, child, lo, hi):
    """Segments of one ray by another method: every finest-grid plane crossing, merged by leaf."""
    o = np.asarray(o, float)
    d = np.asarray(d, float)
    t0, t1 = clip_ray.py_func(o[0], o[1], o[2], d[0], d[1], d[2], lo, hi)
    if t1 <= t0:
        return np.zeros(0, np.int64), np.zeros(0), np.zeros(0)
    f = geo[3] / 2 ** int(geo[7])
    ts = [t0, t1]
    for a in range(3):
        if d[a] != 0.0:
            k = np.arange(int(round((hi[a] - lo[a]) / f)) + 1)
            t = (lo[a] + k * f - o[a]) / d[a]
            ts.extend(t[(t > t0) & (t < t1)].tolist())
    ts = np.unique(np.array(ts))
    cells, lens, starts = [], [], []
    for a, bnd in zip(ts[:-1], ts[1:]):
        if bnd - a <= 1e-12:
            continue
        node = _leaf_at_ref(o + 0.5 * (a + bnd) * d, geo, block_root, child)
        if cells and cells[-1] == node:
            lens[-1] += bnd - a
        else:
            cells.append(node)
            lens.append(bnd - a)
            starts.append(a)
    return np.array(cells, np.int64), np.array(lens), np.array(starts)


def mog_density_ref(app, cell, b, x, w0):
    if b < 0:
        return 1.0
    m = app[cell, b]
    w = m[:, 2].astype(float)
    if w.sum() <= 0:
        return 1.0
    ok = w > 0
    mu, s = m[ok, 0].astype(float), m[ok, 1].astype(float)
    n = float(m[ok, 3].sum())
    p = float(np.sum(w[ok] * np.exp(-0.5 * ((x - mu) / s) ** 2) / s) * INV_SQRT_2PI / w.sum())
    return (n * p + w0) / (n + w0)


def mog_density_cells_ref(app, b, x, w0):
    """Reference of :func:`mog_density_cells`: the densities as a new (n_cells,) array."""
    return np.array([mog_density_ref(app, k, b, x[k], w0) for k in range(len(x))])


def mog_mean_ref(app, cell, b, w0):
    if b < 0:
        return 0.5
    m = app[cell, b]
    w = m[:, 2].astype(float)
    if w.sum() <= 0:
        return 0.5
    n = float(m[w > 0, 3].sum())
    return (n * float(np.sum(w * m[:, 0]) / w.sum()) + 0.5 * w0) / (n + w0)


def update_rays_ref(orig, dirs, obs, cell_obs, lo, hi, geo, block_root, child, alpha, app, b, p_bg, w0, n_cells):
    """Reference of :func:`update_rays`: returns (acc_len, acc_log, acc_obs, acc_vis)."""
    acc = np.zeros((4, n_cells))
    for r in range(len(orig)):
        c = obs[r]
        if not np.isfinite(c):
            continue
        cells, lens, _ = trace_ray_ref(orig[r], dirs[r], geo, block_root, child, lo, hi)
        if cells.size == 0:
            continue
        pq = 1.0 - np.exp(-alpha[cells].astype(float) * lens)
        vis = np.concatenate([[1.0], np.cumprod(1.0 - pq)])
        pa = np.array([mog_density_ref(app, k, b, cell_obs[k] if len(cell_obs) else c, w0) for k in cells])
        contrib = pq * vis[:-1] * pa
        pre = np.concatenate([[0.0], np.cumsum(contrib)])
        denom = pre[-1] + vis[-1] * p_bg
        post = np.minimum(pq * (pre[:-1] + vis[:-1] * pa) / denom, POST_MAX)
        np.add.at(acc[0], cells, lens)
        np.add.at(acc[1], cells, np.log1p(-post))
        np.add.at(acc[2], cells, lens * c)
        np.add.at(acc[3], cells, lens * vis[:-1])
    return acc


def render_rays_ref(orig, dirs, obs, lo, hi, geo, block_root, child, alpha, app, b, p_bg, mean_bg, w0):
    """Reference of :func:`render_rays`: (density, expected, vis_inf, t_median) per ray."""
    out = np.full((4, len(orig)), np.nan)
    for r in range(len(orig)):
        cells, lens, starts = trace_ray_ref(orig[r], dirs[r], geo, block_root, child, lo, hi)
        a = alpha[cells].astype(float)
        pq = 1.0 - np.exp(-a * lens)
        vis = np.concatenate([[1.0], np.cumprod(1.0 - pq)])
        w = vis[:-1] * pq
        if np.isfinite(obs[r]):
            out[0, r] = np.sum(w * np.array([mog_density_ref(app, k, b, obs[r], w0) for k in cells])) + vis[-1] * p_bg
        out[1, r] = np.sum(w * np.array([mog_mean_ref(app, k, b, w0) for k in cells])) + vis[-1] * mean_bg
        out[2, r] = vis[-1]
        k = np.nonzero((vis[:-1] >= 0.5) & (vis[1:] < 0.5))[0]
        if k.size:
            i = k[0]
            out[3, r] = starts[i] + np.log(vis[i] / 0.5) / a[i]
    return out


def mog_update_ref(m, x, w, sigma_init, sigma_min, match_sigmas):
    """Reference of :func:`mog_update` on one (modes, 4) float64 array (returns a new array)."""
    m = np.array(m, dtype=float)
    total = m[:, 3].sum() + w
    rate = w / total
    live = m[:, 2] > 0
    match = next((k for k in range(len(m)) if live[k] and abs(x - m[k, 0]) <= match_sigmas * m[k, 1]), -1)
    if match >= 0:
        n_k = m[match, 3] + w
        rho = w / n_k
        d = x - m[match, 0]
        m[match, 0] += rho * d
        m[match, 1] = max(np.sqrt((1 - rho) * (m[match, 1] ** 2 + rho * d * d)), sigma_min)
        m[match, 3] = n_k
        sel = live.copy()
        sel[match] = True
        m[sel, 2] = (1 - rate) * m[sel, 2] + rate * (np.arange(len(m))[sel] == match)
    else:
        empty = np.nonzero(~live)[0]
        k = int(empty[0]) if empty.size else len(m) - 1
        others = np.arange(len(m)) != k
        rest = m[others, 2].sum()
        m[others, 2] = m[others, 2] * (1 - rate) / rest if rest > 0 else 0.0
        m[k] = [x, sigma_init, rate if rest > 0 else 1.0, w]
    key = np.where(m[:, 2] > 0, m[:, 2] / m[:, 1], -1.0)
    order = np.argsort(-key, kind="stable")
    return m[order]


# ------------------------------------------------------------------------------------------
# cell geometry, sun visibility and ray-weighted cell values (relighting)
# ------------------------------------------------------------------------------------------
@njit(cache=True)
def node_boxes(geo, block_root, child, out_center, out_size):
    """Centre (ENU m) and edge (m) of every node, walking each block's tree from its root."""
    x0 = geo[0]
    y0 = geo[1]
    z0 = geo[2]
    bs = geo[3]
    nbx = int(geo[4])
    nby = int(geo[5])
    nbz = int(geo[6])
    stack = np.empty(64 * 8, dtype=np.int64)
    for bx in range(nbx):
        for by in range(nby):
            for bz in range(nbz):
                root = block_root[bx, by, bz]
                out_center[root, 0] = x0 + (bx + 0.5) * bs
                out_center[root, 1] = y0 + (by + 0.5) * bs
                out_center[root, 2] = z0 + (bz + 0.5) * bs
                out_size[root] = bs
                sp = 0
                stack[sp] = root
                sp += 1
                while sp > 0:
                    sp -= 1
                    node = stack[sp]
                    c = child[node]
                    if c < 0:
                        continue
                    h = 0.5 * out_size[node]
                    for k in range(8):
                        ch = c + k
                        out_size[ch] = h
                        out_center[ch, 0] = out_center[node, 0] + (((k & 1) * 2 - 1) * 0.5) * h
                        out_center[ch, 1] = out_center[node, 1] + ((((k >> 1) & 1) * 2 - 1) * 0.5) * h
                        out_center[ch, 2] = out_center[node, 2] + ((((k >> 2) & 1) * 2 - 1) * 0.5) * h
                        stack[sp] = ch
                        sp += 1


@njit(cache=True, inline="always")
def _transmittance(ox, oy, oz, dx, dy, dz, skip, lo, hi, geo, block_root, child, alpha, seg_cell, seg_len, seg_t):
    """``(exp(-Σ α ℓ), segments traced)`` along the ray ``o + t d`` inside the volume, beyond ``t = skip``."""
    t0, t1 = clip_ray(ox, oy, oz, dx, dy, dz, lo, hi)
    if t0 < skip:
        t0 = skip
    tau = 0.0
    n = 0
    if t1 > t0:
        n = trace_ray(ox, oy, oz, dx, dy, dz, t0, t1, geo, block_root, child, seg_cell, seg_len, seg_t)
        for i in range(n):
            tau += alpha[seg_cell[i]] * seg_len[i]
    return math.exp(-tau), n


@njit(cache=True)
def sun_visibility(
    cells, centers, sizes, sun_dir, skip_cells, lo, hi, geo, block_root, child, alpha, out, seg_cell, seg_len, seg_t
):
    """``out[j] = exp(-Σ α ℓ)`` along the ray towards the sun from the centre of the top face of
    ``cells[j]`` (the surface a cell of the visible top layer offers to the sun), ignoring the
    first ``skip_cells`` cell edges of the path (neighbours of the same surface layer).
    Returns the number of segments traced."""
    total = 0
    dx = sun_dir[0]
    dy = sun_dir[1]
    dz = sun_dir[2]
    for j in range(cells.shape[0]):
        c = cells[j]
        ox = centers[c, 0]
        oy = centers[c, 1]
        oz = centers[c, 2] + 0.5 * sizes[c]
        skip = skip_cells * sizes[c]
        out[j], n = _transmittance(
            ox, oy, oz, dx, dy, dz, skip, lo, hi, geo, block_root, child, alpha, seg_cell, seg_len, seg_t
        )
        total += n
    return total


@njit(cache=True)
def ray_cell_average(
    orig, dirs, lo, hi, geo, block_root, child, alpha, values, out, out_wsum, seg_cell, seg_len, seg_t
):
    """Per ray, the average of per-cell ``values[cell, :]`` weighted by ``vis_i (1 - e^{-α_i ℓ_i})``
    (what the ray sees), and the total weight ``1 - vis_∞``. NaN where the weight is 0."""
    nv = values.shape[1]
    total = 0
    for r in range(orig.shape[0]):
        for k in range(nv):
            out[r, k] = 0.0
        n = 0
        if math.isfinite(orig[r, 0]) and math.isfinite(dirs[r, 0]):
            t0, t1 = clip_ray(orig[r, 0], orig[r, 1], orig[r, 2], dirs[r, 0], dirs[r, 1], dirs[r, 2], lo, hi)
            if t1 > t0:
                n = trace_ray(
                    orig[r, 0],
                    orig[r, 1],
                    orig[r, 2],
                    dirs[r, 0],
                    dirs[r, 1],
                    dirs[r, 2],
                    t0,
                    t1,
                    geo,
                    block_root,
                    child,
                    seg_cell,
                    seg_len,
                    seg_t,
                )
        total += n
        vis = 1.0
        for i in range(n):
            c = seg_cell[i]
            pq = 1.0 - math.exp(-alpha[c] * seg_len[i])
            w = vis * pq
            for k in range(nv):
                out[r, k] += w * values[c, k]
            vis *= 1.0 - pq
        ws = 1.0 - vis
        out_wsum[r] = ws
        for k in range(nv):
            out[r, k] = out[r, k] / ws if ws > 0.0 else np.nan
    return total


def sun_visibility_ref(cells, centers, sizes, sun_dir, skip_cells, lo, hi, geo, block_root, child, alpha):
    """Reference of :func:`sun_visibility`."""
    out = np.empty(len(cells))
    for j, c in enumerate(cells):
        o = centers[c] + np.array([0.0, 0.0, 0.5 * sizes[c]])
        cc, ll, tt = trace_ray_ref(o, sun_dir, geo, block_root, child, lo, hi)
        skip = skip_cells * sizes[c]
        # keep the parts of the segments beyond the skip distance
        end = tt + ll
        part = np.clip(end - np.maximum(tt, skip), 0.0, None)
        out[j] = np.exp(-np.sum(alpha[cc].astype(float) * part))
    return out


# ------------------------------------------------------------------------------------------
# coarsening: merge sibling leaves back into their parent, compact the arrays
# ------------------------------------------------------------------------------------------
@njit(cache=True)
def merge_pass(child, level, alpha, app, block_size, threshold):
    """Merge every inner node whose 8 children are leaves that eq. 26 would not split even at
    the parent's size (``1 - exp(-ℓ_max(parent) α_child) < threshold`` for all 8). The parent
    takes the children's mean α and the appearance of the child with the most observations.
    Children become unreachable (compact afterwards). Returns the number of merges."""
    n = child.shape[0]
    merged = 0
    sqrt3 = math.sqrt(3.0)
    for node in range(n):
        c = child[node]
        if c < 0:
            continue
        ok = True
        for k in range(8):
            if child[c + k] >= 0:
                ok = False
                break
        if not ok:
            continue
        lmax = sqrt3 * block_size / (1 << level[node])
        amax = 0.0
        asum = 0.0
        for k in range(8):
            a = alpha[c + k]
            asum += a
            if a > amax:
                amax = a
        if 1.0 - math.exp(-lmax * amax) >= threshold:
            continue
        best = c
        best_n = -1.0
        for k in range(8):
            tot = 0.0
            for b in range(app.shape[1]):
                for m in range(app.shape[2]):
                    tot += app[c + k, b, m, 3]
            if tot > best_n:
                best_n = tot
                best = c + k
        alpha[node] = asum / 8.0
        for b in range(app.shape[1]):
            for m in range(app.shape[2]):
                for f in range(app.shape[3]):
                    app[node, b, m, f] = app[best, b, m, f]
        child[node] = -1
        merged += 1
    return merged


@njit(cache=True)
def compact_order(block_root, child):
    """Reachable nodes in a new order (each block breadth-first, children contiguous).

    Returns ``order`` (old index of each new node), ``new_child`` and ``new_root``."""
    n = child.shape[0]
    order = np.empty(n, dtype=np.int64)
    new_child = np.full(n, -1, dtype=np.int32)
    new_root = np.empty(block_root.shape, dtype=np.int32)
    nb0, nb1, nb2 = block_root.shape
    m = 0
    for bx in range(nb0):
        for by in range(nb1):
            for bz in range(nb2):
                head = m
                order[m] = block_root[bx, by, bz]
                new_root[bx, by, bz] = m
                m += 1
                while head < m:
                    old = order[head]
                    c = child[old]
                    if c >= 0:
                        new_child[head] = m
                        for k in range(8):
                            order[m] = c + k
                            m += 1
                    head += 1
    return order[:m], new_child[:m], new_root


@njit(cache=True)
def surface_sun(
    orig, dirs, tmed, sun_dir, lift, skip, lo, hi, geo, block_root, child, alpha, out, seg_cell, seg_len, seg_t
):
    """Sun visibility of the median visible surface point of each ray: from
    ``o + tmed d`` lifted by ``lift`` metres, ``exp(-Σ α ℓ)`` towards the sun beyond ``skip``
    metres (1 where ``tmed`` is NaN). Returns the number of segments traced."""
    total = 0
    dx = sun_dir[0]
    dy = sun_dir[1]
    dz = sun_dir[2]
    for r in range(orig.shape[0]):
        t = tmed[r]
        if not math.isfinite(t):
            out[r] = 1.0
            continue
        ox = orig[r, 0] + t * dirs[r, 0]
        oy = orig[r, 1] + t * dirs[r, 1]
        oz = orig[r, 2] + t * dirs[r, 2] + lift
        out[r], n = _transmittance(
            ox, oy, oz, dx, dy, dz, skip, lo, hi, geo, block_root, child, alpha, seg_cell, seg_len, seg_t
        )
        total += n
    return total
