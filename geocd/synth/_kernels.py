"""numba kernels of the scene renderer, with pure-numpy references.

The scene is packed into :class:`SceneArrays` (a namedtuple of arrays, see
:func:`geocd.synth.render.pack_scene`) in map space: ``x, y`` metres from the
scene origin, ``z`` ellipsoidal metres.

* Terrain: a bilinear height field; a ray is marched in steps of at most 1 m
  (horizontal and vertical) and the first crossing refined by bisection to
  1e-9 m. The terrain is smooth (bumps of tens of metres), so no crossing hides
  between two steps.
* Objects: convex polyhedra (intersections of half-spaces ``n·p ≤ d``: building
  parts with flat or gabled roofs, car bodies and cabins), intersected exactly
  by Cyrus–Beck clipping, and ellipsoids (tree crowns). A uniform 2-D grid of
  bins (CSR lists) is walked with a 2-D DDA along the ray, so a ray tests only
  the objects near its path and stops at the first hit.
* Shading: Lambertian with a sun term (a shadow ray towards the sun against the
  same geometry: cast shadows are real) and a sky term; albedo from procedural
  textures in *world* coordinates (value noise), identical for every view.

Object ids: ``out_obj`` is the object index (≥ 0), −1 for the terrain and −2
when nothing was hit.
"""

from __future__ import annotations

from collections import namedtuple

import numpy as np
from numba import njit, prange

from .._jit import parallel_njit

SceneArrays = namedtuple(
    "SceneArrays",
    [
        "terr",  # (ny, nx) float64 heights
        "terr_meta",  # (5,) x0, y0, step, hmin, hmax
        "terr_block_max",  # (by, bx) the highest of the terrain's posts under each block of TERR_BLOCK cells
        "kind",  # (n,) int64: 0 polyhedron, 1 ellipsoid
        "cls",  # (n,) int64: 1 building, 2 car, 3 tree
        "planes",  # (n, 8, 4) float64: n·p <= d
        "nplanes",  # (n,) int64
        "ell",  # (n, 5) float64: cx, cy, cz, r, rz
        "rgb",  # (n, 3) primary colour (roof, car, tree tint)
        "rgb2",  # (n, 3) secondary colour (walls)
        "par",  # (n, 4): ground_m, storey_m, role (0 flat roof, 1 gabled, 2 car body, 3 car cabin, 4 tree), seed
        "grid_meta",  # (5,) gx0, gy0, gsize, gnx, gny
        "grid_start",  # (gnx*gny + 1,) int64
        "grid_items",  # (m,) int64
        "zrange",  # (2,) min and max z of all objects
        "streets",  # (ns, 7): x0, y0, ux, uy, length, half_width, sidewalk
        "patches",  # (np, 6): cx, cy, half_len, half_wid, angle, material
        "colours",  # (9, 3): grass, vegetation multiplier, asphalt, pavement, soil, marking, glass, tree base,
        #   near-infrared albedo of (grass, trees, unused)
    ],
)

M_GRASS, M_ASPHALT, M_PAVEMENT, M_SOIL, M_MARKING = 0, 1, 2, 3, 10
INF = np.inf
TERR_BLOCK = 8  # terrain cells a side of one block of ``terr_block_max``


# ------------------------------------------------------------------------------------------
# hashing and value noise
# ------------------------------------------------------------------------------------------
@njit(cache=True, inline="always")
def _hash3(ix, iy, iz, seed):
    h = np.uint64(ix) * np.uint64(0x9E3779B97F4A7C15)
    h ^= np.uint64(iy) * np.uint64(0xC2B2AE3D27D4EB4F)
    h ^= np.uint64(iz) * np.uint64(0x165667B19E3779F9)
    h ^= np.uint64(seed) * np.uint64(0x27D4EB2F165667C5)
    h ^= h >> np.uint64(33)
    h *= np.uint64(0xFF51AFD7ED558CCD)
    h ^= h >> np.uint64(33)
    h *= np.uint64(0xC4CEB9FE1A85EC53)
    h ^= h >> np.uint64(33)
    return np.float64(h >> np.uint64(11)) * (1.0 / 9007199254740992.0)


@njit(cache=True)
def vnoise(x, y, z, seed):
    """3-D value noise in [0, 1): smoothstep interpolation of hashed lattice values."""
    fx = np.floor(x)
    fy = np.floor(y)
    fz = np.floor(z)
    ix = np.int64(fx)
    iy = np.int64(fy)
    iz = np.int64(fz)
    tx = x - fx
    ty = y - fy
    tz = z - fz
    sx = tx * tx * (3.0 - 2.0 * tx)
    sy = ty * ty * (3.0 - 2.0 * ty)
    sz = tz * tz * (3.0 - 2.0 * tz)
    c000 = _hash3(ix, iy, iz, seed)
    c100 = _hash3(ix + 1, iy, iz, seed)
    c010 = _hash3(ix, iy + 1, iz, seed)
    c110 = _hash3(ix + 1, iy + 1, iz, seed)
    c001 = _hash3(ix, iy, iz + 1, seed)
    c101 = _hash3(ix + 1, iy, iz + 1, seed)
    c011 = _hash3(ix, iy + 1, iz + 1, seed)
    c111 = _hash3(ix + 1, iy + 1, iz + 1, seed)
    a = c000 + sx * (c100 - c000)
    b = c010 + sx * (c110 - c010)
    c = c001 + sx * (c101 - c001)
    d = c011 + sx * (c111 - c011)
    e = a + sy * (b - a)
    f = c + sy * (d - c)
    return e + sz * (f - e)


@njit(cache=True)
def fbm(x, y, z, seed, octaves):
    """Fractal sum of value noise (octaves halving in size), normalised to [0, 1)."""
    s = 0.0
    amp = 1.0
    tot = 0.0
    f = 1.0
    for o in range(octaves):
        s += amp * vnoise(x * f, y * f, z * f, seed + o)
        tot += amp
        amp *= 0.5
        f *= 2.0
    return s / tot


@parallel_njit()
def vnoise_many(x, y, z, seed, out):
    for i in prange(x.shape[0]):
        out[i] = vnoise(x[i], y[i], z[i], seed)


# ------------------------------------------------------------------------------------------
# geometry
# ------------------------------------------------------------------------------------------
@njit(cache=True, inline="always")
def _terrain_cell(terr, meta, x, y):
    """(row, col) of (x, y) in the terrain's posts, fractional, clamped inside the last cell."""
    ny, nx = terr.shape
    fj = (x - meta[0]) / meta[2]
    fi = (y - meta[1]) / meta[2]
    if fj < 0.0:
        fj = 0.0
    if fj > nx - 1.000001:
        fj = nx - 1.000001
    if fi < 0.0:
        fi = 0.0
    if fi > ny - 1.000001:
        fi = ny - 1.000001
    return fi, fj


@njit(cache=True)
def terrain_at(terr, meta, x, y):
    """Bilinear height and its gradient (clamped at the grid edges)."""
    fi, fj = _terrain_cell(terr, meta, x, y)
    j = np.int64(np.floor(fj))
    i = np.int64(np.floor(fi))
    a = fj - j
    b = fi - i
    h00 = terr[i, j]
    h01 = terr[i, j + 1]
    h10 = terr[i + 1, j]
    h11 = terr[i + 1, j + 1]
    h = (1 - a) * (1 - b) * h00 + a * (1 - b) * h01 + (1 - a) * b * h10 + a * b * h11
    hx = ((1 - b) * (h01 - h00) + b * (h11 - h10)) / meta[2]
    hy = ((1 - a) * (h10 - h00) + a * (h11 - h01)) / meta[2]
    return h, hx, hy


@njit(cache=True)
def _terrain_f(terr, meta, ox, oy, oz, dx, dy, dz, t):
    h, _, _ = terrain_at(terr, meta, ox + t * dx, oy + t * dy)
    return oz + t * dz - h


def terrain_block_max(terr: np.ndarray, block: int = TERR_BLOCK) -> np.ndarray:
    """The highest post of each block of ``block`` × ``block`` terrain cells, its far edges included: (by, bx).

    The bilinear surface of a cell lies between its four posts, so it stays below its block's value."""
    ny, nx = terr.shape
    by = (ny - 2) // block + 1
    bx = (nx - 2) // block + 1
    out = np.empty((by, bx))
    for i in range(by):
        for j in range(bx):
            out[i, j] = terr[i * block : i * block + block + 1, j * block : j * block + block + 1].max()
    return out


@njit(cache=True)
def _above_block(terr, meta, bmax, x, y, z):
    """True when z is surely above the terrain at (x, y): above the highest post of its cell's block."""
    fi, fj = _terrain_cell(terr, meta, x, y)
    # 1e-6 m: far above the rounding of the bilinear sum (~1e-13 m at these heights)
    return z - bmax[np.int64(fi) // TERR_BLOCK, np.int64(fj) // TERR_BLOCK] > 1e-6


@njit(cache=True)
def terrain_hit(terr, meta, bmax, ox, oy, oz, dx, dy, dz, t0, t1):
    """First t in [t0, t1] where the ray meets the terrain (inf when it does not).

    The ray is marched in steps of at most 1 m of travel in x, y or z, and the first step that ends at or below
    the surface is refined by regula falsi. A step end surely above its block's highest post (``bmax``,
    :func:`terrain_block_max`) is passed without evaluating the surface: the same steps, the same answer.
    """
    hmin = meta[3] - 0.01
    hmax = meta[4] + 0.01
    ta = t0
    tb = t1
    if dz < 0.0:
        ta = max(ta, (hmax - oz) / dz)
        tb = min(tb, (hmin - oz) / dz)
    elif dz > 0.0:
        tb = min(tb, (hmax - oz) / dz)
    if ta > tb:
        return INF
    hs = np.sqrt(dx * dx + dy * dy)
    step = INF
    if hs > 0.0:
        step = 1.0 / hs
    if dz != 0.0:
        step = min(step, 1.0 / abs(dz))
    t = ta
    # f at the start of the march: the regula falsi below starts from it whichever step brackets the surface (as
    # it always has: the committed sample_aoi's pixels depend on it to the last bit); evaluated when needed
    f = 1.0
    known = False
    if not _above_block(terr, meta, bmax, ox + t * dx, oy + t * dy, oz + t * dz):
        f = _terrain_f(terr, meta, ox, oy, oz, dx, dy, dz, t)
        known = True
        if f <= 0.0:
            return t
    while t < tb:
        tn = min(t + step, tb)
        if _above_block(terr, meta, bmax, ox + tn * dx, oy + tn * dy, oz + tn * dz):
            t = tn
            continue
        fn = _terrain_f(terr, meta, ox, oy, oz, dx, dy, dz, tn)
        if fn <= 0.0:
            if not known:
                f = _terrain_f(terr, meta, ox, oy, oz, dx, dy, dz, ta)
            # Illinois (modified regula falsi): f > 0 at lo, f <= 0 at hi
            lo = t
            hi = tn
            flo = f
            fhi = fn
            side = 0
            for _ in range(100):
                if hi - lo < 1e-10 or fhi == 0.0:
                    break
                mid = (lo * fhi - hi * flo) / (fhi - flo)
                if not (lo < mid < hi):
                    mid = 0.5 * (lo + hi)
                fm = _terrain_f(terr, meta, ox, oy, oz, dx, dy, dz, mid)
                if fm > 0.0:
                    lo = mid
                    flo = fm
                    if side == 1:
                        fhi *= 0.5
                    side = 1
                else:
                    hi = mid
                    fhi = fm
                    if side == -1:
                        flo *= 0.5
                    side = -1
                if abs(fm) < 1e-10:
                    return mid
            return hi
        t = tn
    return INF


@njit(cache=True)
def poly_hit(planes, npl, ox, oy, oz, dx, dy, dz, tlo, thi):
    """Entry of the ray into a convex polyhedron within [tlo, thi]: (t, face) or (inf, -1)."""
    tin = -INF
    tout = INF
    face = -1
    for p in range(npl):
        nx = planes[p, 0]
        ny = planes[p, 1]
        nz = planes[p, 2]
        den = nx * dx + ny * dy + nz * dz
        num = planes[p, 3] - (nx * ox + ny * oy + nz * oz)
        if den == 0.0:
            if num < 0.0:
                return INF, -1
            continue
        t = num / den
        if den < 0.0:
            if t > tin:
                tin = t
                face = p
        else:
            if t < tout:
                tout = t
        if tin > tout:
            return INF, -1
    if face < 0 or tin < tlo or tin > thi:
        return INF, -1
    return tin, face


@njit(cache=True)
def ellipsoid_hit(e, ox, oy, oz, dx, dy, dz, tlo, thi):
    """First intersection with the ellipsoid (cx, cy, cz, r, rz) within [tlo, thi], or inf."""
    r = e[3]
    rz = e[4]
    qx = (ox - e[0]) / r
    qy = (oy - e[1]) / r
    qz = (oz - e[2]) / rz
    ux = dx / r
    uy = dy / r
    uz = dz / rz
    a = ux * ux + uy * uy + uz * uz
    b = qx * ux + qy * uy + qz * uz
    c = qx * qx + qy * qy + qz * qz - 1.0
    disc = b * b - a * c
    if disc < 0.0:
        return INF
    t = (-b - np.sqrt(disc)) / a
    if t < tlo or t > thi:
        return INF
    return t


@njit(cache=True)
def _test_object(S, k, ox, oy, oz, dx, dy, dz, tlo, thi):
    if S.kind[k] == 0:
        return poly_hit(S.planes[k], S.nplanes[k], ox, oy, oz, dx, dy, dz, tlo, thi)
    t = ellipsoid_hit(S.ell[k], ox, oy, oz, dx, dy, dz, tlo, thi)
    return t, 0


@njit(cache=True)
def objects_hit(S, ox, oy, oz, dx, dy, dz, t0, t1):
    """Nearest object hit in [t0, t1] by a 2-D DDA over the bin grid: (t, obj, face)."""
    best = t1
    bobj = -2
    bface = -1
    zlo = S.zrange[0]
    zhi = S.zrange[1]
    if dz != 0.0:
        ta = (zlo - oz) / dz
        tb = (zhi - oz) / dz
        if ta > tb:
            ta, tb = tb, ta
        t0 = max(t0, ta)
        t1 = min(t1, tb)
    elif oz < zlo or oz > zhi:
        return INF, -2, -1
    gx0 = S.grid_meta[0]
    gy0 = S.grid_meta[1]
    gs = S.grid_meta[2]
    gnx = np.int64(S.grid_meta[3])
    gny = np.int64(S.grid_meta[4])
    gx1 = gx0 + gnx * gs
    gy1 = gy0 + gny * gs
    # clip to the grid box in x and y
    if dx != 0.0:
        ta = (gx0 - ox) / dx
        tb = (gx1 - ox) / dx
        if ta > tb:
            ta, tb = tb, ta
        t0 = max(t0, ta)
        t1 = min(t1, tb)
    elif ox < gx0 or ox > gx1:
        return INF, -2, -1
    if dy != 0.0:
        ta = (gy0 - oy) / dy
        tb = (gy1 - oy) / dy
        if ta > tb:
            ta, tb = tb, ta
        t0 = max(t0, ta)
        t1 = min(t1, tb)
    elif oy < gy0 or oy > gy1:
        return INF, -2, -1
    if t0 > t1:
        return INF, -2, -1
    x = ox + t0 * dx
    y = oy + t0 * dy
    ix = np.int64(np.floor((x - gx0) / gs))
    iy = np.int64(np.floor((y - gy0) / gs))
    ix = min(max(ix, 0), gnx - 1)
    iy = min(max(iy, 0), gny - 1)
    if dx > 0.0:
        sx = 1
        tmx = (gx0 + (ix + 1) * gs - ox) / dx
        tdx = gs / dx
    elif dx < 0.0:
        sx = -1
        tmx = (gx0 + ix * gs - ox) / dx
        tdx = -gs / dx
    else:
        sx = 0
        tmx = INF
        tdx = INF
    if dy > 0.0:
        sy = 1
        tmy = (gy0 + (iy + 1) * gs - oy) / dy
        tdy = gs / dy
    elif dy < 0.0:
        sy = -1
        tmy = (gy0 + iy * gs - oy) / dy
        tdy = -gs / dy
    else:
        sy = 0
        tmy = INF
        tdy = INF
    tlo = t0
    while True:
        cell = iy * gnx + ix
        for q in range(S.grid_start[cell], S.grid_start[cell + 1]):
            k = S.grid_items[q]
            t, f = _test_object(S, k, ox, oy, oz, dx, dy, dz, tlo, best)
            if t < best or (t == best and bobj < 0 and t < INF):
                best = t
                bobj = k
                bface = f
        texit = min(tmx, tmy)
        if bobj >= 0 and best <= texit:
            break
        if texit >= t1:
            break
        if tmx < tmy:
            ix += sx
            tmx += tdx
        else:
            iy += sy
            tmy += tdy
        if ix < 0 or iy < 0 or ix >= gnx or iy >= gny:
            break
    if bobj < 0:
        return INF, -2, -1
    return best, bobj, bface


@njit(cache=True)
def first_hit(S, ox, oy, oz, dx, dy, dz, t0, t1):
    """First surface along the ray: (t, obj, face) with obj −1 = terrain, −2 = nothing."""
    tt = terrain_hit(S.terr, S.terr_meta, S.terr_block_max, ox, oy, oz, dx, dy, dz, t0, t1)
    tb = tt if tt < t1 else t1
    t, k, f = objects_hit(S, ox, oy, oz, dx, dy, dz, t0, tb)
    if k >= 0 and t <= tb:
        return t, k, f
    if tt < INF:
        return tt, -1, -1
    return INF, -2, -1


@njit(cache=True)
def surface_normal(S, obj, face, x, y, z):
    if obj == -1:
        _, hx, hy = terrain_at(S.terr, S.terr_meta, x, y)
        n = np.sqrt(hx * hx + hy * hy + 1.0)
        return -hx / n, -hy / n, 1.0 / n
    if S.kind[obj] == 0:
        p = S.planes[obj, face]
        return p[0], p[1], p[2]
    e = S.ell[obj]
    gx = (x - e[0]) / (e[3] * e[3])
    gy = (y - e[1]) / (e[3] * e[3])
    gz = (z - e[2]) / (e[4] * e[4])
    n = np.sqrt(gx * gx + gy * gy + gz * gz)
    return gx / n, gy / n, gz / n


@parallel_njit()
def trace_first_hit(orig, dirs, t_max, S, out_t, out_obj, out_face):
    """First hit of many rays (geometry only). orig, dirs: (N, 3); t_max: (N,)."""
    for i in prange(orig.shape[0]):
        t, k, f = first_hit(S, orig[i, 0], orig[i, 1], orig[i, 2], dirs[i, 0], dirs[i, 1], dirs[i, 2], 0.0, t_max[i])
        out_t[i] = t
        out_obj[i] = k
        out_face[i] = f


@njit(cache=True)
def _cubic_map(coef, scale, h0, e, n, u):
    a = e / scale
    b = n / scale
    c = u / scale
    T = (
        1.0,
        a,
        b,
        c,
        a * a,
        b * b,
        c * c,
        a * b,
        a * c,
        b * c,
        a * a * a,
        b * b * b,
        c * c * c,
        a * a * b,
        a * a * c,
        b * b * a,
        b * b * c,
        c * c * a,
        c * c * b,
        a * b * c,
    )
    x = 0.0
    y = 0.0
    z = 0.0
    for k in range(20):
        x += T[k] * coef[k, 0]
        y += T[k] * coef[k, 1]
        z += T[k] * coef[k, 2]
    return x, y, z + h0


@parallel_njit()
def enu_rays_to_map(o, d, u_top, u_bot, coef, scale, h0, out_o, out_d, out_len):
    """ENU rays (origin, unit direction) → map-space chords between the ENU heights u_top and u_bot.

    ``coef`` (20, 3), ``scale``, ``h0``: the scene frame's cubic ENU → map polynomial
    (:meth:`geocd.synth.scene.SceneFrame.enu_to_map` is the numpy reference).
    """
    for i in prange(o.shape[0]):
        st = (u_top - o[i, 2]) / d[i, 2]
        sb = (u_bot - o[i, 2]) / d[i, 2]
        xa, ya, za = _cubic_map(coef, scale, h0, o[i, 0] + st * d[i, 0], o[i, 1] + st * d[i, 1], o[i, 2] + st * d[i, 2])
        xb, yb, zb = _cubic_map(coef, scale, h0, o[i, 0] + sb * d[i, 0], o[i, 1] + sb * d[i, 1], o[i, 2] + sb * d[i, 2])
        vx = xb - xa
        vy = yb - ya
        vz = zb - za
        L = np.sqrt(vx * vx + vy * vy + vz * vz)
        out_o[i, 0] = xa
        out_o[i, 1] = ya
        out_o[i, 2] = za
        out_d[i, 0] = vx / L
        out_d[i, 1] = vy / L
        out_d[i, 2] = vz / L
        out_len[i] = L


# ------------------------------------------------------------------------------------------
# materials
# ------------------------------------------------------------------------------------------
@njit(cache=True)
def ground_material(S, x, y):
    """Material of the ground at (x, y): patches, then streets/sidewalks/markings, else grass."""
    for q in range(S.patches.shape[0]):
        pa = S.patches[q]
        # outside the patch's circumscribed circle (padded far beyond rounding): the rotated test below would
        # say outside too, without its cosine and sine
        dx = x - pa[0]
        dy = y - pa[1]
        if dx * dx + dy * dy > (pa[2] * pa[2] + pa[3] * pa[3]) * 1.000001 + 1e-6:
            continue
        c = np.cos(pa[4])
        s = np.sin(pa[4])
        u = (x - pa[0]) * c + (y - pa[1]) * s
        v = -(x - pa[0]) * s + (y - pa[1]) * c
        if abs(u) <= pa[2] and abs(v) <= pa[3]:
            return np.int64(pa[5])
    mat = M_GRASS
    for q in range(S.streets.shape[0]):
        st = S.streets[q]
        px = x - st[0]
        py = y - st[1]
        al = px * st[2] + py * st[3]
        if al < 0.0 or al > st[4]:
            continue
        ac = abs(-px * st[3] + py * st[2])
        if ac <= st[5]:
            if ac < 0.1 and (al % 6.0) < 3.0:
                return M_MARKING
            return M_ASPHALT
        if ac <= st[5] + st[6]:
            mat = M_PAVEMENT
    return mat


@parallel_njit()
def ground_material_many(S, x, y, out):
    for i in prange(x.shape[0]):
        out[i] = ground_material(S, x[i], y[i])


@njit(cache=True, inline="always")
def _grey(r, g, b, bump):
    """Man-made materials: near-infrared reflectance close to the visible mean."""
    return r, g, b, 1.05 * (r + g + b) / 3.0, bump


@njit(cache=True)
def albedo(S, obj, face, x, y, z, nx, ny, nz):
    """Albedo (r, g, b, nir) and a normal perturbation amplitude at a surface point."""
    C = S.colours
    if obj < 0:
        m = ground_material(S, x, y)
        if m == M_GRASS:
            t = (0.70 + 0.55 * fbm(x / 1.3, y / 1.3, 0.0, 11, 3)) * (0.80 + 0.40 * vnoise(x / 9.0, y / 9.0, 0.5, 12))
            return C[0, 0] * C[1, 0] * t, C[0, 1] * C[1, 1] * t, C[0, 2] * C[1, 2] * t, C[8, 0] * t, 0.0
        if m == M_ASPHALT:
            t = (0.78 + 0.45 * fbm(x / 0.7, y / 0.7, 0.0, 21, 2)) * (0.85 + 0.3 * vnoise(x / 6.0, y / 6.0, 0.0, 22))
            return _grey(C[2, 0] * t, C[2, 1] * t, C[2, 2] * t, 0.0)
        if m == M_PAVEMENT:
            t = 0.80 + 0.40 * fbm(x / 0.8, y / 0.8, 0.0, 31, 2)
            return _grey(C[3, 0] * t, C[3, 1] * t, C[3, 2] * t, 0.0)
        if m == M_SOIL:
            t = 0.65 + 0.65 * fbm(x / 0.9, y / 0.9, 0.0, 41, 3)
            return _grey(C[4, 0] * t, C[4, 1] * t, C[4, 2] * t, 0.0)
        if m == M_MARKING:
            return _grey(C[5, 0], C[5, 1], C[5, 2], 0.0)
        return _grey(0.3, 0.3, 0.3, 0.0)
    role = np.int64(S.par[obj, 2])
    seed = np.int64(S.par[obj, 3])
    if role == 4:  # tree crown
        t = 0.45 + 1.1 * fbm(x / 0.7, y / 0.7, z / 0.7, seed, 3)
        return (
            C[7, 0] * C[1, 0] * S.rgb[obj, 0] * t,
            C[7, 1] * C[1, 1] * S.rgb[obj, 1] * t,
            C[7, 2] * C[1, 2] * S.rgb[obj, 2] * t,
            C[8, 1] * S.rgb[obj, 0] * t,
            0.6,
        )
    if role == 2 or role == 3:  # car body / cabin
        if role == 3 and nz < 0.5:
            return _grey(C[6, 0], C[6, 1], C[6, 2], 0.0)
        t = 0.92 + 0.12 * vnoise(x / 0.5, y / 0.5, z / 0.5, seed)
        return _grey(S.rgb[obj, 0] * t, S.rgb[obj, 1] * t, S.rgb[obj, 2] * t, 0.0)
    # building: roof or wall
    if nz > 0.3:
        if role == 1:  # tiles
            t = (0.78 + 0.40 * fbm(x / 0.9, y / 0.9, z / 0.9, seed, 3)) * (
                0.85 + 0.3 * vnoise(x / 4.0, y / 4.0, z, seed + 7)
            )
        else:  # gravel / membrane with equipment
            t = 0.74 + 0.48 * fbm(x / 1.1, y / 1.1, 0.0, seed, 3)
            if vnoise(x / 2.2, y / 2.2, 3.0, seed + 5) > 0.78:
                t *= 0.55
        return _grey(S.rgb[obj, 0] * t, S.rgb[obj, 1] * t, S.rgb[obj, 2] * t, 0.0)
    # wall with windows
    s = -x * ny + y * nx
    zz = (z - S.par[obj, 0]) / S.par[obj, 1]
    fz = zz - np.floor(zz)
    fs = s / 2.8 - np.floor(s / 2.8)
    if zz > 0.0 and 0.32 < fz < 0.75 and 0.25 < fs < 0.72:
        return _grey(C[6, 0], C[6, 1], C[6, 2], 0.0)
    t = 0.85 + 0.25 * vnoise(s / 0.8, z / 0.8, 0.0, seed + 3)
    return _grey(S.rgb2[obj, 0] * t, S.rgb2[obj, 1] * t, S.rgb2[obj, 2] * t, 0.0)


@njit(cache=True)
def in_shadow(S, x, y, z, nx, ny, nz, sx, sy, sz):
    """True when the sun is hidden from the point (x, y, z) with normal n."""
    ox = x + 2e-3 * nx + 1e-4 * sx
    oy = y + 2e-3 * ny + 1e-4 * sy
    oz = z + 2e-3 * nz + 1e-4 * sz
    if terrain_hit(S.terr, S.terr_meta, S.terr_block_max, ox, oy, oz, sx, sy, sz, 0.0, INF) < INF:
        return True
    t, k, f = objects_hit(S, ox, oy, oz, sx, sy, sz, 0.0, INF)
    return k >= 0


@njit(cache=True)
def shade_one(S, ox, oy, oz, dx, dy, dz, t_max, sun, light):
    """Radiance (r, g, b, nir) seen along one ray, plus the hit (t, obj)."""
    t, k, f = first_hit(S, ox, oy, oz, dx, dy, dz, 0.0, t_max)
    if k == -2:
        return 0.0, 0.0, 0.0, 0.0, t, k
    x = ox + t * dx
    y = oy + t * dy
    z = oz + t * dz
    nx, ny, nz = surface_normal(S, k, f, x, y, z)
    ar, ag, ab, an, bump = albedo(S, k, f, x, y, z, nx, ny, nz)
    mx, my, mz = nx, ny, nz
    if bump > 0.0:
        seed = np.int64(S.par[k, 3])
        mx += bump * (vnoise(x / 0.5, y / 0.5, z / 0.5, seed + 101) - 0.5)
        my += bump * (vnoise(x / 0.5, y / 0.5, z / 0.5, seed + 102) - 0.5)
        mz += bump * (vnoise(x / 0.5, y / 0.5, z / 0.5, seed + 103) - 0.5)
        nn = np.sqrt(mx * mx + my * my + mz * mz)
        mx /= nn
        my /= nn
        mz /= nn
    cos_i = mx * sun[0] + my * sun[1] + mz * sun[2]
    direct = 0.0
    if cos_i > 0.0 and (nx * sun[0] + ny * sun[1] + nz * sun[2]) > 0.0:
        if not in_shadow(S, x, y, z, nx, ny, nz, sun[0], sun[1], sun[2]):
            direct = light[0] * cos_i
    sky = light[1] * (0.6 + 0.4 * mz)
    e = direct + sky
    return ar * e, ag * e, ab * e, an * e, t, k


@parallel_njit()
def render_rays(orig, dirs, t_max, sun, light, S, out_rgb, out_t, out_obj):
    """Shade many rays. orig, dirs: (N, 3) map space; sun: (3,) unit; light: (E_sun, E_sky).

    out_rgb: (N, 4) radiance in R, G, B and near-infrared; out_t, out_obj: the first hit.
    """
    for i in prange(orig.shape[0]):
        r, g, b, nir, t, k = shade_one(
            S, orig[i, 0], orig[i, 1], orig[i, 2], dirs[i, 0], dirs[i, 1], dirs[i, 2], t_max[i], sun, light
        )
        out_rgb[i, 0] = r
        out_rgb[i, 1] = g
        out_rgb[i, 2] = b
        out_rgb[i, 3] = nir
        out_t[i] = t
        out_obj[i] = k


# ------------------------------------------------------------------------------------------
# pure-numpy references (slow, obviously correct; tests compare the kernels with them)
# ------------------------------------------------------------------------------------------
_M64 = np.uint64(0xFFFFFFFFFFFFFFFF)


def _hash3_ref(ix, iy, iz, seed):
    with np.errstate(over="ignore"):
        ix = np.asarray(ix, np.int64).astype(np.uint64)
        iy = np.asarray(iy, np.int64).astype(np.uint64)
        iz = np.asarray(iz, np.int64).astype(np.uint64)
        s = np.asarray(seed, np.int64).astype(np.uint64)
        h = ix * np.uint64(0x9E3779B97F4A7C15)
        h ^= iy * np.uint64(0xC2B2AE3D27D4EB4F)
        h ^= iz * np.uint64(0x165667B19E3779F9)
        h ^= s * np.uint64(0x27D4EB2F165667C5)
        h ^= h >> np.uint64(33)
        h *= np.uint64(0xFF51AFD7ED558CCD)
        h ^= h >> np.uint64(33)
        h *= np.uint64(0xC4CEB9FE1A85EC53)
        h ^= h >> np.uint64(33)
    return (h >> np.uint64(11)).astype(np.float64) * (1.0 / 9007199254740992.0)


def vnoise_ref(x, y, z, seed):
    x, y, z = (np.asarray(a, float) for a in (x, y, z))
    fx, fy, fz = np.floor(x), np.floor(y), np.floor(z)
    ix, iy, iz = fx.astype(np.int64), fy.astype(np.int64), fz.astype(np.int64)
    sx, sy, sz = ((t * t * (3 - 2 * t)) for t in (x - fx, y - fy, z - fz))
    c = {(a, b, d): _hash3_ref(ix + a, iy + b, iz + d, seed) for a in (0, 1) for b in (0, 1) for d in (0, 1)}
    lerp = lambda p, q, s: p + s * (q - p)  # noqa: E731
    e = lerp(lerp(c[0, 0, 0], c[1, 0, 0], sx), lerp(c[0, 1, 0], c[1, 1, 0], sx), sy)
    f = lerp(lerp(c[0, 0, 1], c[1, 0, 1], sx), lerp(c[0, 1, 1], c[1, 1, 1], sx), sy)
    return lerp(e, f, sz)


def first_hit_ref(
    S: SceneArrays, orig: np.ndarray, dirs: np.ndarray, t_max: np.ndarray, terrain_step: float = 0.01
) -> tuple[np.ndarray, np.ndarray]:
    """Brute force: every object for every ray, terrain by fine sampling (accuracy ~1e-4 m).

    Returns (t, obj) like :func:`trace_first_hit`.
    """
    n = orig.shape[0]
    best = np.full(n, np.inf)
    obj = np.full(n, -2, dtype=np.int64)
    o, d = orig, dirs
    # terrain: sample the ray densely within the terrain's height band
    from types import SimpleNamespace  # noqa: F401

    meta = S.terr_meta
    for i in range(n):
        if d[i, 2] >= 0:
            continue
        ta = max(0.0, (meta[4] + 0.01 - o[i, 2]) / d[i, 2])
        tb = min(t_max[i], (meta[3] - 0.01 - o[i, 2]) / d[i, 2])
        if ta > tb:
            continue
        ts = np.arange(ta, tb + terrain_step, terrain_step)
        x, y, z = o[i, 0] + ts * d[i, 0], o[i, 1] + ts * d[i, 1], o[i, 2] + ts * d[i, 2]
        h = _terrain_ref(S, x, y)
        below = np.nonzero(z - h <= 0)[0]
        if below.size:
            j = below[0]
            if j == 0:
                best[i] = ts[0]
            else:
                f0, f1 = z[j - 1] - h[j - 1], z[j] - h[j]
                best[i] = ts[j - 1] + (ts[j] - ts[j - 1]) * f0 / (f0 - f1)
            obj[i] = -1
    for k in range(S.kind.shape[0]):
        if S.kind[k] == 0:
            P = S.planes[k, : S.nplanes[k]]
            den = d @ P[:, :3].T  # (n, p)
            num = P[:, 3][None, :] - o @ P[:, :3].T
            with np.errstate(divide="ignore", invalid="ignore"):
                t = num / den
            tin = np.where(den < 0, t, -np.inf).max(axis=1)
            tout = np.where(den > 0, t, np.inf).min(axis=1)
            parallel_out = ((den == 0) & (num < 0)).any(axis=1)
            hit = (tin <= tout) & ~parallel_out & (tin >= 0) & np.isfinite(tin)
        else:
            e = S.ell[k]
            sc = np.array([e[3], e[3], e[4]])
            q = (o - e[:3]) / sc
            u = d / sc
            a = (u * u).sum(1)
            b = (q * u).sum(1)
            c = (q * q).sum(1) - 1
            disc = b * b - a * c
            with np.errstate(invalid="ignore"):
                tin = (-b - np.sqrt(disc)) / a
            hit = (disc >= 0) & (tin >= 0)
        upd = hit & (tin <= t_max) & (tin < best)
        best[upd] = tin[upd]
        obj[upd] = k
    return best, obj


def _terrain_ref(S: SceneArrays, x, y):
    meta = S.terr_meta
    ny, nx = S.terr.shape
    fj = np.clip((x - meta[0]) / meta[2], 0, nx - 1.000001)
    fi = np.clip((y - meta[1]) / meta[2], 0, ny - 1.000001)
    j, i = np.floor(fj).astype(int), np.floor(fi).astype(int)
    a, b = fj - j, fi - i
    T = S.terr
    return (1 - a) * (1 - b) * T[i, j] + a * (1 - b) * T[i, j + 1] + (1 - a) * b * T[i + 1, j] + a * b * T[i + 1, j + 1]


def fbm_ref(x, y, z, seed, octaves):
    s, amp, tot, f = 0.0, 1.0, 0.0, 1.0
    for o in range(octaves):
        s = s + amp * vnoise_ref(x * f, y * f, z * f, seed + o)
        tot += amp
        amp *= 0.5
        f *= 2.0
    return s / tot


def ground_material_ref(S: SceneArrays, x: float, y: float) -> int:
    for pa in S.patches:
        c, s = np.cos(pa[4]), np.sin(pa[4])
        u = (x - pa[0]) * c + (y - pa[1]) * s
        v = -(x - pa[0]) * s + (y - pa[1]) * c
        if abs(u) <= pa[2] and abs(v) <= pa[3]:
            return int(pa[5])
    mat = M_GRASS
    for st in S.streets:
        px, py = x - st[0], y - st[1]
        al = px * st[2] + py * st[3]
        if al < 0.0 or al > st[4]:
            continue
        ac = abs(-px * st[3] + py * st[2])
        if ac <= st[5]:
            return M_MARKING if (ac < 0.1 and (al % 6.0) < 3.0) else M_ASPHALT
        if ac <= st[5] + st[6]:
            mat = M_PAVEMENT
    return mat


def albedo_ref(S: SceneArrays, obj: int, x: float, y: float, z: float, n: np.ndarray):
    """(r, g, b, nir, bump) — the same texture rules as :func:`albedo`, written plainly."""
    C = S.colours
    f = lambda *a: float(fbm_ref(*a))  # noqa: E731
    v = lambda *a: float(vnoise_ref(*a))  # noqa: E731
    grey = lambda r, g, b: (r, g, b, 1.05 * (r + g + b) / 3.0, 0.0)  # noqa: E731
    if obj < 0:
        m = ground_material_ref(S, x, y)
        if m == M_GRASS:
            t = (0.70 + 0.55 * f(x / 1.3, y / 1.3, 0.0, 11, 3)) * (0.80 + 0.40 * v(x / 9.0, y / 9.0, 0.5, 12))
            return (*(C[0] * C[1] * t), C[8, 0] * t, 0.0)
        if m == M_ASPHALT:
            t = (0.78 + 0.45 * f(x / 0.7, y / 0.7, 0.0, 21, 2)) * (0.85 + 0.3 * v(x / 6.0, y / 6.0, 0.0, 22))
            return grey(*(C[2] * t))
        if m == M_PAVEMENT:
            return grey(*(C[3] * (0.80 + 0.40 * f(x / 0.8, y / 0.8, 0.0, 31, 2))))
        if m == M_SOIL:
            return grey(*(C[4] * (0.65 + 0.65 * f(x / 0.9, y / 0.9, 0.0, 41, 3))))
        if m == M_MARKING:
            return grey(*C[5])
        return grey(0.3, 0.3, 0.3)
    role, seed = int(S.par[obj, 2]), int(S.par[obj, 3])
    if role == 4:
        t = 0.45 + 1.1 * f(x / 0.7, y / 0.7, z / 0.7, seed, 3)
        return (*(C[7] * C[1] * S.rgb[obj] * t), C[8, 1] * S.rgb[obj, 0] * t, 0.6)
    if role in (2, 3):
        if role == 3 and n[2] < 0.5:
            return grey(*C[6])
        return grey(*(S.rgb[obj] * (0.92 + 0.12 * v(x / 0.5, y / 0.5, z / 0.5, seed))))
    if n[2] > 0.3:
        if role == 1:
            t = (0.78 + 0.40 * f(x / 0.9, y / 0.9, z / 0.9, seed, 3)) * (0.85 + 0.3 * v(x / 4.0, y / 4.0, z, seed + 7))
        else:
            t = 0.74 + 0.48 * f(x / 1.1, y / 1.1, 0.0, seed, 3)
            if v(x / 2.2, y / 2.2, 3.0, seed + 5) > 0.78:
                t *= 0.55
        return grey(*(S.rgb[obj] * t))
    s = -x * n[1] + y * n[0]
    zz = (z - S.par[obj, 0]) / S.par[obj, 1]
    fz, fs = zz - np.floor(zz), s / 2.8 - np.floor(s / 2.8)
    if zz > 0.0 and 0.32 < fz < 0.75 and 0.25 < fs < 0.72:
        return grey(*C[6])
    return grey(*(S.rgb2[obj] * (0.85 + 0.25 * v(s / 0.8, z / 0.8, 0.0, seed + 3))))


def _normal_ref(S: SceneArrays, obj: int, p: np.ndarray, d: np.ndarray) -> np.ndarray:
    if obj == -1:  # the bilinear patch's gradient from the cell's corner values
        meta = S.terr_meta
        ny, nx = S.terr.shape
        fj = min(max((p[0] - meta[0]) / meta[2], 0.0), nx - 1.000001)
        fi = min(max((p[1] - meta[1]) / meta[2], 0.0), ny - 1.000001)
        j, i = int(np.floor(fj)), int(np.floor(fi))
        a, b = fj - j, fi - i
        T = S.terr
        hx = ((1 - b) * (T[i, j + 1] - T[i, j]) + b * (T[i + 1, j + 1] - T[i + 1, j])) / meta[2]
        hy = ((1 - a) * (T[i + 1, j] - T[i, j]) + a * (T[i + 1, j + 1] - T[i, j + 1])) / meta[2]
        n = np.array([-hx, -hy, 1.0])
        return n / np.linalg.norm(n)
    if S.kind[obj] == 0:
        # the face the ray enters through: the entering plane with the largest entry parameter
        P = S.planes[obj, : S.nplanes[obj]]
        den = P[:, :3] @ d
        return P[np.argmin(np.where(den < 0, np.abs(P[:, :3] @ p - P[:, 3]), np.inf)), :3].copy()
    e = S.ell[obj]
    g = np.array([(p[0] - e[0]) / e[3] ** 2, (p[1] - e[1]) / e[3] ** 2, (p[2] - e[2]) / e[4] ** 2])
    return g / np.linalg.norm(g)


def shade_ref(
    S: SceneArrays, orig: np.ndarray, dirs: np.ndarray, t_max: np.ndarray, sun: np.ndarray, light: np.ndarray
) -> np.ndarray:
    """Plain re-implementation of :func:`render_rays` (brute-force hits, shadows by brute force too)."""
    t, obj = first_hit_ref(S, orig, dirs, t_max, terrain_step=0.002)
    out = np.zeros((orig.shape[0], 4))
    for i in range(orig.shape[0]):
        if obj[i] == -2:
            continue
        p = orig[i] + t[i] * dirs[i]
        n = _normal_ref(S, int(obj[i]), p, dirs[i])
        r, g, b, nir, bump = albedo_ref(S, int(obj[i]), *p, n)
        m = n.copy()
        if bump > 0:
            seed = int(S.par[obj[i], 3])
            m = m + bump * np.array([float(vnoise_ref(*(p / 0.5), seed + k)) - 0.5 for k in (101, 102, 103)])
            m /= np.linalg.norm(m)
        cos_i = float(m @ sun)
        direct = 0.0
        if cos_i > 0 and float(n @ sun) > 0:
            o2 = (p + 2e-3 * n + 1e-4 * sun)[None]
            t2, ob2 = first_hit_ref(S, o2, sun[None], np.array([1e4]), terrain_step=0.002)
            up_ok = True
            # first_hit_ref only casts downward rays at the terrain: test upward terrain crossings here
            ts = np.arange(0.0, max(0.0, (S.terr_meta[4] + 0.01 - o2[0, 2]) / sun[2]) + 0.5, 0.05)
            q = o2[0] + ts[:, None] * sun
            if (q[:, 2] - _terrain_ref(S, q[:, 0], q[:, 1]) <= 0).any():
                up_ok = False
            if ob2[0] < 0 and up_ok:
                direct = light[0] * cos_i
        e = direct + light[1] * (0.6 + 0.4 * m[2])
        out[i] = (r * e, g * e, b * e, nir * e)
    return out


# ------------------------------------------------------------------------------------------
# large DEM pairs (geocd.synth.bigdem): procedural terrain, DEM errors and changes per window
# ------------------------------------------------------------------------------------------
@njit(cache=True, nogil=True)
def dem_window(
    x0, y0, post, row0, col0, nr, nc, de, dn, dz, seed, scales, amps, err_scale, err_corr, err_white, objects, out
):  # pragma: no cover - numba
    """Heights of one window of a procedural DEM (see :func:`geocd.synth.bigdem.dem_window_ref`).

    Cell (r, c) of the window is cell (row0 + r, col0 + c) of the whole grid whose corner
    is (x0, y0) with square cells of ``post`` m. The surface is the terrain at
    (x − de, y − dn) plus ``dz``, plus the ``objects`` (rows: kind, cx, cy, a, b, h; kind 0
    a box of half-sizes a × b raised by h, 1 a paraboloid of radius a and height h, 2 a
    void: NaN), plus DEM errors: correlated value noise (``err_corr`` m at ``err_scale`` m)
    and white noise (``err_white`` m) hashed from the cell's whole-grid index, so every
    window of the grid gets the same values whatever the tiling.
    """
    for r in range(nr):
        gr = row0 + r
        y = y0 - (gr + 0.5) * post
        for c in range(nc):
            gc = col0 + c
            x = x0 + (gc + 0.5) * post
            xs = x - de
            ys = y - dn
            z = dz
            for k in range(scales.shape[0]):
                z += amps[k] * (2.0 * vnoise(xs / scales[k], ys / scales[k], 0.5, seed + k) - 1.0)
            if err_corr > 0.0:
                z += err_corr * (2.0 * vnoise(x / err_scale, y / err_scale, 0.5, seed + 1000) - 1.0)
            if err_white > 0.0:
                u1 = _hash3(gr, gc, 1, seed + 2000)
                u2 = _hash3(gr, gc, 2, seed + 2000)
                z += err_white * np.sqrt(-2.0 * np.log(1.0 - u1)) * np.cos(2.0 * np.pi * u2)
            out[r, c] = z
    for k in range(objects.shape[0]):
        kind = int(objects[k, 0])
        cx = objects[k, 1]
        cy = objects[k, 2]
        a = objects[k, 3]
        b = objects[k, 4]
        h = objects[k, 5]
        ext = a if kind != 0 else max(a, b)
        c_lo = max(int(np.floor((cx - ext - x0) / post - 0.5)) - col0, 0)
        c_hi = min(int(np.ceil((cx + ext - x0) / post - 0.5)) - col0, nc - 1)
        r_lo = max(int(np.floor((y0 - cy - ext) / post - 0.5)) - row0, 0)
        r_hi = min(int(np.ceil((y0 - cy + ext) / post - 0.5)) - row0, nr - 1)
        for r in range(r_lo, r_hi + 1):
            y = y0 - (row0 + r + 0.5) * post
            for c in range(c_lo, c_hi + 1):
                x = x0 + (col0 + c + 0.5) * post
                if kind == 0:
                    if abs(x - cx) <= a and abs(y - cy) <= b:
                        out[r, c] += h
                else:
                    q = ((x - cx) ** 2 + (y - cy) ** 2) / (a * a)
                    if q < 1.0:
                        if kind == 1:
                            out[r, c] += h * (1.0 - q)
                        else:
                            out[r, c] = np.nan


# ------------------------------------------------------------------------------------------
# large stereo scenes (geocd.synth.bigstereo): rays marched through a DSM window, textures
# ------------------------------------------------------------------------------------------
@njit(cache=True, inline="always")
def _bilin(dsm, gx0, gy0, gs, x, y):
    """Bilinear height of ``dsm`` (row 0 at the top; cell (0, 0) centred at (gx0, gy0)) at (x, y), edge-clamped."""
    nr, nc = dsm.shape
    fc = (x - gx0) / gs
    fr = (gy0 - y) / gs
    fc = min(max(fc, 0.0), nc - 1.000001)
    fr = min(max(fr, 0.0), nr - 1.000001)
    c = int(fc)
    r = int(fr)
    tc = fc - c
    tr = fr - r
    a = dsm[r, c] + tc * (dsm[r, c + 1] - dsm[r, c])
    b = dsm[r + 1, c] + tc * (dsm[r + 1, c + 1] - dsm[r + 1, c])
    return a + tr * (b - a)


REFINE_STEPS = 6


@njit(cache=True, nogil=True)
def march_dsm(
    ax, ay, bx, by, h_top, h_bot, z_start, z_end, step_m, dsm, gx0, gy0, gs, out_x, out_y, out_z, out_slope
):  # pragma: no cover - numba
    """First crossing of each ray with a DSM window (see :func:`march_dsm_ref`).

    Ray k passes through (ax[k], ay[k]) at height ``h_top`` and (bx[k], by[k]) at ``h_bot``
    (map coordinates, straight chord). It is marched downwards from ``z_start`` to ``z_end``
    in steps that move it ``step_m`` horizontally (at most 2 m vertically); between the last
    step above the bilinear surface and the first below it the crossing is refined by
    ``REFINE_STEPS`` regula-falsi steps. ``out_slope`` is the surface gradient's magnitude at the hit (walls: ≫ 1).
    A ray that does not cross gets NaN.
    """
    n = ax.shape[0]
    inv = 1.0 / (h_top - h_bot)
    for k in range(n):
        ux = (bx[k] - ax[k]) * inv  # map shift per metre of descent
        uy = (by[k] - ay[k]) * inv
        t = np.sqrt(ux * ux + uy * uy)
        dz = 2.0
        if t * dz > step_m:
            dz = step_m / t
        z = z_start
        x = ax[k] + (h_top - z) * ux
        y = ay[k] + (h_top - z) * uy
        f = z - _bilin(dsm, gx0, gy0, gs, x, y)
        hit = False
        while z > z_end:
            zn = z - dz
            xn = ax[k] + (h_top - zn) * ux
            yn = ay[k] + (h_top - zn) * uy
            fn = zn - _bilin(dsm, gx0, gy0, gs, xn, yn)
            if fn <= 0.0:
                # regula falsi between the last step above and the first below (the bilinear surface
                # has kinks at cell edges: one linear interpolation can be off on steep faces)
                zh, fh, zl, fl = z, f, zn, fn
                z = zn
                for _ in range(REFINE_STEPS):
                    z = zh - fh * (zh - zl) / (fh - fl) if fh != fl else zl
                    fm = z - _bilin(dsm, gx0, gy0, gs, ax[k] + (h_top - z) * ux, ay[k] + (h_top - z) * uy)
                    if fm > 0.0:
                        zh, fh = z, fm
                    else:
                        zl, fl = z, fm
                hit = True
                break
            z, f = zn, fn
        if hit:
            x = ax[k] + (h_top - z) * ux
            y = ay[k] + (h_top - z) * uy
            out_x[k] = x
            out_y[k] = y
            out_z[k] = z
            e = 0.25 * gs
            gx = (_bilin(dsm, gx0, gy0, gs, x + e, y) - _bilin(dsm, gx0, gy0, gs, x - e, y)) / (2 * e)
            gy = (_bilin(dsm, gx0, gy0, gs, x, y + e) - _bilin(dsm, gx0, gy0, gs, x, y - e)) / (2 * e)
            out_slope[k] = np.sqrt(gx * gx + gy * gy)
        else:
            out_x[k] = np.nan
            out_y[k] = np.nan
            out_z[k] = np.nan
            out_slope[k] = np.nan


def march_dsm_ref(ax, ay, bx, by, h_top, h_bot, z_start, z_end, step_m, dsm, gx0, gy0, gs):
    """Pure-numpy reference of :func:`march_dsm`: the same steps, all rays at once. Returns x, y, z, slope."""
    from scipy.ndimage import map_coordinates

    def surf(x, y):
        fc = np.clip((x - gx0) / gs, 0.0, dsm.shape[1] - 1.000001)
        fr = np.clip((gy0 - y) / gs, 0.0, dsm.shape[0] - 1.000001)
        return map_coordinates(dsm, [fr, fc], order=1, mode="nearest")

    ux = (bx - ax) / (h_top - h_bot)
    uy = (by - ay) / (h_top - h_bot)
    t = np.hypot(ux, uy)
    dz = np.where(t * 2.0 > step_m, step_m / np.maximum(t, 1e-300), 2.0)
    z = np.full(ax.shape, float(z_start))
    f = z - surf(ax + (h_top - z) * ux, ay + (h_top - z) * uy)
    zh = np.full(ax.shape, np.nan)
    live = np.ones(ax.shape, bool)
    while live.any():
        live &= z > z_end
        zn = z - dz
        fn = zn - surf(ax + (h_top - zn) * ux, ay + (h_top - zn) * uy)
        now = live & (fn <= 0.0)
        zhi, fhi, zlo, flo = z[now], f[now], zn[now], fn[now]
        zz = zlo.copy()
        axn, ayn, uxn, uyn = ax[now], ay[now], ux[now], uy[now]
        for _ in range(REFINE_STEPS):
            with np.errstate(invalid="ignore", divide="ignore"):
                zz = np.where(fhi != flo, zhi - fhi * (zhi - zlo) / (fhi - flo), zlo)
            fm = zz - surf(axn + (h_top - zz) * uxn, ayn + (h_top - zz) * uyn)
            up = fm > 0.0
            zhi, fhi = np.where(up, zz, zhi), np.where(up, fm, fhi)
            zlo, flo = np.where(up, zlo, zz), np.where(up, flo, fm)
        zh[now] = zz
        live &= ~now
        z = np.where(live, zn, z)
        f = np.where(live, fn, f)
    x = ax + (h_top - zh) * ux
    y = ay + (h_top - zh) * uy
    e = 0.25 * gs
    gx = (surf(x + e, y) - surf(x - e, y)) / (2 * e)
    gy = (surf(x, y + e) - surf(x, y - e)) / (2 * e)
    return x, y, zh, np.hypot(gx, gy)


@njit(cache=True, nogil=True)
def big_albedo(x, y, z, bid, slope, seed, out):  # pragma: no cover - numba
    """Albedo of hit points (see :func:`big_albedo_ref`): ground, roofs (per-building tone) and walls."""
    for k in range(x.shape[0]):
        if not np.isfinite(z[k]):
            out[k] = 0.0
            continue
        b = bid[k]
        if b <= 0:
            a = (
                0.12
                + 0.30 * fbm(x[k] / 6.0, y[k] / 6.0, 0.5, seed, 4)
                + 0.10 * vnoise(x[k] / 0.9, y[k] / 0.9, 0.5, seed + 11)
            )
        else:
            tone = 0.15 + 0.55 * _hash3(b, 7, 3, seed)
            if slope[k] > 3.0:  # wall: darker, banded by height
                a = 0.5 * tone * (0.7 + 0.3 * vnoise((x[k] + y[k]) / 1.5, z[k] / 1.0, 0.5, seed + 21))
            else:
                a = tone * (0.75 + 0.5 * fbm(x[k] / 2.5, y[k] / 2.5, 0.5, seed + 31, 3))
        out[k] = a


def big_albedo_ref(x, y, z, bid, slope, seed):
    """Pure-numpy reference of :func:`big_albedo`."""

    def fbm_(xs, ys, s, octaves):
        return fbm_ref(xs, ys, np.full(xs.shape, 0.5), s, octaves)

    half = np.full(x.shape, 0.5)
    ground = 0.12 + 0.30 * fbm_(x / 6.0, y / 6.0, seed, 4) + 0.10 * vnoise_ref(x / 0.9, y / 0.9, half, seed + 11)
    tone = 0.15 + 0.55 * _hash3_ref(bid, np.full(x.shape, 7), np.full(x.shape, 3), seed)
    wall = 0.5 * tone * (0.7 + 0.3 * vnoise_ref((x + y) / 1.5, z / 1.0, half, seed + 21))
    roof = tone * (0.75 + 0.5 * fbm_(x / 2.5, y / 2.5, seed + 31, 3))
    out = np.where(bid <= 0, ground, np.where(slope > 3.0, wall, roof))
    return np.where(np.isfinite(z), out, 0.0)
