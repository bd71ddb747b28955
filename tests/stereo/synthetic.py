"""A tiny synthetic stereo scene: a textured DSM seen by two affine RPC cameras.

The cameras are RPC00B models whose polynomials are affine in (lon, lat, h): a
parallel projection with a known parallax (pixels per metre of height), i.e. a
pushbroom sensor over a small area. Images are rendered by ray-marching each
pixel's line of sight down through the DSM, so occlusions are real.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from geocd.camera import RPCModel
from geocd.geodesy import AOIGrid, utm_crs_for

LON0, LAT0, H0 = 5.30, 44.10, 200.0
M_PER_DEG_LAT = 111_132.0
M_PER_DEG_LON = 111_320.0 * np.cos(np.radians(LAT0))


def affine_rpc(
    gsd_m: float,
    parallax_px_per_m: tuple[float, float],
    width: int,
    height: int,
    centre_px: tuple[float, float] | None = None,
    lon0: float = LON0,
    lat0: float = LAT0,
    h0: float = H0,
    height_scale_m: float = 500.0,
) -> RPCModel:
    """An RPC that is exactly ``col = cx + Δlon/dlon + pc·(h−h0)``, ``row = cy − Δlat/dlat + pr·(h−h0)``."""
    cx, cy = centre_px if centre_px is not None else (width / 2.0, height / 2.0)
    s_lon = s_lat = 0.01
    s_h = float(height_scale_m)
    dlon_px = gsd_m / M_PER_DEG_LON
    dlat_px = gsd_m / M_PER_DEG_LAT
    z = np.zeros(20)
    samp_num = z.copy()
    samp_num[1] = s_lon / dlon_px
    samp_num[3] = parallax_px_per_m[0] * s_h
    line_num = z.copy()
    line_num[2] = -s_lat / dlat_px
    line_num[3] = parallax_px_per_m[1] * s_h
    den = z.copy()
    den[0] = 1.0
    cam = RPCModel(
        line_num=line_num,
        line_den=den,
        samp_num=samp_num,
        samp_den=den.copy(),
        line_off=cy - 0.5,
        samp_off=cx - 0.5,
        lat_off=lat0,
        lon_off=lon0,
        height_off=h0,
        line_scale=1.0,
        samp_scale=1.0,
        lat_scale=s_lat,
        lon_scale=s_lon,
        height_scale=s_h,
        width=width,
        height=height,
        source="synthetic affine",
    )
    _AFFINE[id(cam)] = (cx, cy, dlon_px, dlat_px, parallax_px_per_m, lon0, lat0, h0, cam)
    return cam


_AFFINE: dict = {}


def localize_affine(cam, col, row, h):
    """Closed-form inverse of :func:`affine_rpc` (what ``cam.localize`` computes iteratively)."""
    cx, cy, dlon, dlat, (pc, pr), lon0, lat0, h0, _ = _AFFINE[id(cam)]
    lon = lon0 + (np.asarray(col) - cx - pc * (np.asarray(h) - h0)) * dlon
    lat = lat0 - (np.asarray(row) - cy - pr * (np.asarray(h) - h0)) * dlat
    return lon, lat


@dataclass
class Scene:
    grid: AOIGrid
    truth: np.ndarray  # ellipsoidal DSM on the grid (m)
    images: list  # raw image arrays (native dtype)
    cameras: list
    names: list
    visible: np.ndarray  # cells seen by both images (not occluded)


def _local_xy(lon, lat):
    return (np.asarray(lon) - LON0) * M_PER_DEG_LON, (np.asarray(lat) - LAT0) * M_PER_DEG_LAT


def dsm_local(x, y):
    """Heights (m) at local metres east/north of (LON0, LAT0)."""
    z = H0 + 0.04 * x - 0.02 * y + 1.5 * np.sin(x / 9.0) * np.cos(y / 11.0)
    b1 = (np.abs(x - 6.0) < 9.0) & (np.abs(y + 4.0) < 7.0)
    z = np.where(b1, H0 + 10.0 + 0.04 * x - 0.02 * y, z)
    b2 = (np.abs(x + 14.0) < 5.0) & (np.abs(y - 12.0) < 5.0)
    z = np.where(b2, H0 + 5.0 + 0.04 * x - 0.02 * y, z)
    return z


class Texture:
    """Smooth random albedo over ±extent_m; ``octaves`` = ((σ in steps, weight of the unit-std component), ...)
    adds coarser structure (real scenes have texture at every scale)."""

    def __init__(self, seed: int = 0, extent_m: float = 120.0, step_m: float = 0.25, octaves=()):
        rng = np.random.default_rng(seed)
        n = int(2 * extent_m / step_m)
        a = ndimage.gaussian_filter(rng.normal(size=(n, n)), 2.0)
        a += 0.5 * ndimage.gaussian_filter(rng.normal(size=(n, n)), 6.0)
        for sigma, weight in octaves:
            f = max(1, int(sigma // 4))  # coarse structure: filter a coarser grid, then interpolate
            m = -(-n // f) + 1
            o = ndimage.gaussian_filter(rng.normal(size=(m, m)), sigma / f)
            o = ndimage.zoom(o, f, order=1)[:n, :n]
            a += weight * a.std() * o / o.std()
        self.a = (a - a.mean()) / a.std()
        self.step = step_m
        self.extent = extent_m

    def __call__(self, x, y):
        c = (np.asarray(x) + self.extent) / self.step
        r = (np.asarray(y) + self.extent) / self.step
        return ndimage.map_coordinates(self.a, [r, c], order=1, mode="reflect")


class RepeatedTexture(Texture):
    """:class:`Texture` with a patch of stripes of ``period_m`` along x (about the epipolar direction of
    :func:`make_scene`'s cameras) in ``box`` = (x0, x1, y0, y1) local metres: a window there matches one
    period away almost as well as at its own height."""

    def __init__(self, seed: int = 0, period_m: float = 2.0, box=(-18.0, -4.0, -18.0, -6.0)):
        super().__init__(seed)
        self.period_m = period_m
        self.box = box

    def inside(self, x, y):
        x0, x1, y0, y1 = self.box
        x, y = np.asarray(x), np.asarray(y)
        return (x > x0) & (x < x1) & (y > y0) & (y < y1)

    def __call__(self, x, y):
        return np.where(
            self.inside(x, y), 1.4 * np.cos(2 * np.pi * np.asarray(x) / self.period_m), super().__call__(x, y)
        )


def render(cam: RPCModel, tex: Texture, h_lo: float = H0 - 6.0, h_hi: float = H0 + 16.0, dh: float = 0.04):
    """Ray-march every pixel centre down from h_hi; returns (intensity, surface height) images."""
    H, W = cam.height, cam.width
    cols, rows = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    found = np.zeros(cols.shape, bool)
    hit_h = np.full(cols.shape, np.nan)
    hx = np.full(cols.shape, np.nan)
    hy = np.full(cols.shape, np.nan)
    for h in np.arange(h_hi, h_lo, -dh):
        todo = ~found
        if not todo.any():
            break
        lon, lat = localize_affine(cam, cols[todo], rows[todo], h)
        x, y = _local_xy(lon, lat)
        below = h <= dsm_local(x, y)
        idx = np.flatnonzero(todo)[below]
        found.flat[idx] = True
        hit_h.flat[idx] = h
        hx.flat[idx] = x[below]
        hy.flat[idx] = y[below]
    inten = tex(hx, hy)
    # roofs brighter, a little shading with height
    inten = inten + 0.02 * (hit_h - H0)
    return inten, hit_h


def make_scene(
    seed: int = 0,
    size_m: float = 48.0,
    posting_m: float = 0.5,
    gsd_m: float = 0.5,
    parallax_a=(0.55, 0.05),
    parallax_b=(-0.45, 0.02),
    noise: float = 0.02,
    texture: Texture | None = None,
) -> Scene:
    crs = utm_crs_for(LON0, LAT0)
    from geocd.geodesy import from_lonlat

    xc, yc = from_lonlat(LON0, LAT0, crs)
    grid = AOIGrid.from_bounds(
        float(xc) - size_m / 2, float(yc) - size_m / 2, float(xc) + size_m / 2, float(yc) + size_m / 2, posting_m, crs
    )
    lon, lat = grid.lonlat()
    truth = dsm_local(*_local_xy(lon, lat))
    npx = int(size_m / gsd_m) + 40
    tex = Texture(seed) if texture is None else texture
    rng = np.random.default_rng(seed + 1)
    cams, imgs = [], []
    for k, par in enumerate((parallax_a, parallax_b)):
        cam = affine_rpc(gsd_m, par, npx, npx)
        inten, _ = render(cam, tex)
        inten = inten + noise * rng.normal(size=inten.shape)
        if k == 0:  # 11-bit in uint16, gain and offset
            img = np.clip(600 + 150 * inten, 0, 2047).astype(np.uint16)
        else:  # 8-bit RGB, another gain/offset
            g = np.clip(110 + 30 * inten, 0, 255)
            img = np.stack([g, 0.9 * g, 0.8 * g]).astype(np.uint8)
        cams.append(cam)
        imgs.append(img)
    # visibility of each cell in both images: the rendered surface height at its projection equals truth
    vis = np.ones(grid.shape, bool)
    for cam in cams:
        c, r = cam.project(lon, lat, truth)
        _, hit = render_at(cam, c, r)
        vis &= np.abs(hit - truth) < 0.3
    return Scene(grid, truth, imgs, cams, ["img_a", "img_b"], vis)


def render_at(cam, cols, rows, h_lo=H0 - 6.0, h_hi=H0 + 16.0, dh=0.04):
    """Surface hit height along the lines of sight of arbitrary image points."""
    shape = cols.shape
    cols = cols.ravel()
    rows = rows.ravel()
    found = np.zeros(cols.shape, bool)
    hit_h = np.full(cols.shape, np.nan)
    for h in np.arange(h_hi, h_lo, -dh):
        todo = ~found
        if not todo.any():
            break
        lon, lat = localize_affine(cam, cols[todo], rows[todo], h)
        below = h <= dsm_local(*_local_xy(lon, lat))
        idx = np.flatnonzero(todo)[below]
        found[idx] = True
        hit_h[idx] = h
    return None, hit_h.reshape(shape)


# ---------------------------------------------------------------------------------------------
# any surface, any camera: a tall structure on a plateau
# ---------------------------------------------------------------------------------------------
def render_surface(
    cam, tex: Texture, dsm_fn, h_lo: float, h_hi: float, dh: float = 2.0, n_bisect: int = 12, cols=None, rows=None
):
    """Ray-march the lines of sight of pixel centres (or of given points) down through ``dsm_fn``.

    ``dsm_fn(x, y)`` gives heights (m) at local metres east/north of (LON0, LAT0). Steps of
    ``dh`` from ``h_hi``, then ``n_bisect`` bisections of the first step that goes below the
    surface (precision dh / 2**n_bisect). Works for any camera of the protocol (closed form
    for :func:`affine_rpc` cameras). Returns (intensity, hit height) with NaN where no hit.
    """
    if cols is None:
        cols, rows = np.meshgrid(np.arange(cam.width) + 0.5, np.arange(cam.height) + 0.5)
    shape = np.shape(cols)
    cols = np.asarray(cols, float).ravel()
    rows = np.asarray(rows, float).ravel()

    def ground(c, r, h):
        if id(cam) in _AFFINE:
            lon, lat = localize_affine(cam, c, r, h)
        else:
            lon, lat = cam.localize(c, r, np.full(c.shape, h) if np.ndim(h) == 0 else h)
        return _local_xy(lon, lat)

    def below(c, r, h):
        x, y = ground(c, r, h)
        with np.errstate(invalid="ignore"):
            return np.asarray(h) <= dsm_fn(x, y)

    found = np.zeros(cols.shape, bool)
    top = np.full(cols.shape, np.nan)
    for h in np.arange(h_hi, h_lo - dh, -dh):
        todo = np.flatnonzero(~found)
        if not todo.size:
            break
        b = below(cols[todo], rows[todo], h)
        idx = todo[b]
        found[idx] = True
        top[idx] = h + dh
    idx = np.flatnonzero(found)
    hi = top[idx]
    lo = hi - dh
    for _ in range(n_bisect):
        mid = 0.5 * (lo + hi)
        b = below(cols[idx], rows[idx], mid)
        lo = np.where(b, mid, lo)
        hi = np.where(b, hi, mid)
    hit = np.full(cols.shape, np.nan)
    hit[idx] = 0.5 * (lo + hi)
    inten = np.full(cols.shape, np.nan)
    x, y = ground(cols[idx], rows[idx], hit[idx])
    # texture pinned to the surface (x, y and height), so steep faces are textured too
    inten[idx] = tex(x + 0.31 * (hit[idx] - H0), y - 0.27 * (hit[idx] - H0)) + 0.005 * (hit[idx] - H0)
    return inten.reshape(shape), hit.reshape(shape)


def pyramid_dsm(
    height_m: float = 150.0,
    half_base_m: float = 75.0,
    centre=(0.0, 0.0),
    plateau_m: float = H0,
    steps: int = 0,
    tower=None,
):
    """A square pyramid on a gently rolling plateau (and, optionally, a tower ``(x, y, half_side, height)``).

    ``steps > 0`` makes it a stepped pyramid (ziggurat) of that many flat terraces above the
    plateau, each ``height_m / steps`` high; the top terrace is ``half_base_m / (steps + 1)``
    from the centre to its edge.
    """

    def f(x, y):
        x = np.asarray(x, float)
        y = np.asarray(y, float)
        z = plateau_m + 0.02 * x - 0.01 * y + 1.5 * np.sin(x / 13.0) * np.cos(y / 17.0)
        d = np.maximum(np.abs(x - centre[0]), np.abs(y - centre[1]))
        if steps > 0:
            k = np.clip(np.floor((steps + 1) * (1.0 - d / half_base_m)), 0, steps)
            z = np.maximum(z, plateau_m + height_m * k / steps)
        else:
            z = np.maximum(z, plateau_m + height_m * (1.0 - d / half_base_m))
        if tower is not None:
            tx, ty, ts, th = tower
            z = np.where((np.abs(x - tx) <= ts) & (np.abs(y - ty) <= ts), plateau_m + th, z)
        return z

    return f


def make_surface_scene(
    dsm_fn,
    *,
    seed: int = 0,
    size_m: float = 300.0,
    posting_m: float = 1.0,
    gsd_m: float = 1.0,
    parallax_a=(0.33, 0.06),
    parallax_b=(-0.31, 0.03),
    noise: float = 0.02,
    h_range=(H0 - 10.0, H0 + 170.0),
    height_scale_m: float = 500.0,
) -> Scene:
    """Two affine RPC views of an arbitrary surface ``dsm_fn`` (heights in m over local metres)."""
    from geocd.geodesy import from_lonlat

    crs = utm_crs_for(LON0, LAT0)
    xc, yc = from_lonlat(LON0, LAT0, crs)
    grid = AOIGrid.from_bounds(
        float(xc) - size_m / 2, float(yc) - size_m / 2, float(xc) + size_m / 2, float(yc) + size_m / 2, posting_m, crs
    )
    lon, lat = grid.lonlat()
    truth = dsm_fn(*_local_xy(lon, lat))
    relief_px = max(abs(v) for p in (parallax_a, parallax_b) for v in p) * (h_range[1] - H0)
    npx = int(size_m / gsd_m + 2 * relief_px) + 40
    tex = Texture(
        seed, extent_m=size_m / 2 + 2 * (h_range[1] - H0) + 20.0, step_m=0.5 * gsd_m, octaves=((16.0, 0.6), (48.0, 0.5))
    )
    rng = np.random.default_rng(seed + 1)
    cams, imgs = [], []
    for par in (parallax_a, parallax_b):
        cam = affine_rpc(gsd_m, par, npx, npx, height_scale_m=height_scale_m)
        inten, _ = render_surface(cam, tex, dsm_fn, *h_range)
        inten = inten + noise * rng.normal(size=inten.shape)
        imgs.append(np.clip(600 + 150 * np.nan_to_num(inten), 0, 2047).astype(np.uint16))
        cams.append(cam)
    vis = np.ones(grid.shape, bool)
    for cam in cams:
        c, r = cam.project(lon, lat, truth)
        _, hit = render_surface(cam, tex, dsm_fn, *h_range, cols=c, rows=r)
        vis &= np.abs(hit - truth) < 0.3
    return Scene(grid, truth, imgs, cams, ["img_a", "img_b"], vis)


def frame_camera(
    position_xy,
    altitude_m: float,
    *,
    width: int = 480,
    height: int = 360,
    focal_px: float = 300.0,
    k1: float = -0.26,
    k2: float = 0.0,
    opk_deg=(0.0, 0.0, 0.0),
):
    """A nadir drone frame camera (Brown distortion) ``altitude_m`` above H0 at local metres ``position_xy``."""
    from geocd.camera import FrameCamera
    from geocd.geodesy import from_lonlat

    crs = utm_crs_for(LON0, LAT0)
    x0, y0 = from_lonlat(LON0, LAT0, crs)
    return FrameCamera(
        width=width,
        height=height,
        focal_px=focal_px,
        crs=crs,
        vertical_datum="ellipsoid",
        position=(float(x0) + position_xy[0], float(y0) + position_xy[1], H0 + altitude_m),
        opk_deg=opk_deg,
        distortion={"k1": k1, "k2": k2},
    )


def make_frame_scene(
    dsm_fn=None,
    *,
    seed: int = 3,
    k1: float = -0.26,
    altitude_m: float = 60.0,
    base_m: float = 24.0,
    aoi_m: float = 200.0,
    posting_m: float = 0.5,
    noise: float = 0.02,
    h_range=(H0 - 10.0, H0 + 20.0),
) -> Scene:
    """Two nadir drone frames with strong barrel distortion over ``dsm_fn`` (default: the two-building scene).

    The AOI grid (``aoi_m`` square) is far larger than the frames' footprints, so most of its cells
    lie where the distortion polynomial folds back (beyond ~48° off the axis for k1 = −0.26).
    """
    from geocd.geodesy import from_lonlat

    f = dsm_fn or (lambda x, y: dsm_local(x, y))
    crs = utm_crs_for(LON0, LAT0)
    xc, yc = from_lonlat(LON0, LAT0, crs)
    grid = AOIGrid.from_bounds(
        float(xc) - aoi_m / 2, float(yc) - aoi_m / 2, float(xc) + aoi_m / 2, float(yc) + aoi_m / 2, posting_m, crs
    )
    cams = [frame_camera((-base_m / 2, 0.0), altitude_m, k1=k1), frame_camera((base_m / 2, 0.0), altitude_m, k1=k1)]
    tex = Texture(seed, extent_m=110.0, step_m=0.25)
    rng = np.random.default_rng(seed + 1)
    imgs = []
    for cam in cams:
        inten, _ = render_surface(cam, tex, f, *h_range, dh=0.5)
        inten = inten + noise * rng.normal(size=inten.shape)
        imgs.append(np.clip(120 + 40 * np.nan_to_num(inten), 0, 255).astype(np.uint8))
    lon, lat = grid.lonlat()
    truth = f(*_local_xy(lon, lat))
    vis = np.ones(grid.shape, bool)
    for cam in cams:
        c, r = cam.project(lon, lat, truth)
        inside = cam.in_image(c, r)
        hit = np.full(grid.shape, np.nan)
        if inside.any():
            _, hit[inside] = render_surface(cam, tex, f, *h_range, dh=0.5, cols=c[inside], rows=r[inside])
        vis &= np.abs(hit - truth) < 0.3
    return Scene(grid, truth, imgs, cams, ["drone_a", "drone_b"], vis)
