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
from geocd.geodesy import AOIGrid, to_lonlat, utm_crs_for

LON0, LAT0, H0 = 5.30, 44.10, 200.0
M_PER_DEG_LAT = 111_132.0
M_PER_DEG_LON = 111_320.0 * np.cos(np.radians(LAT0))


def affine_rpc(gsd_m: float, parallax_px_per_m: tuple[float, float], width: int, height: int,
               centre_px: tuple[float, float] | None = None, lon0: float = LON0, lat0: float = LAT0,
               h0: float = H0) -> RPCModel:
    """An RPC that is exactly ``col = cx + Δlon/dlon + pc·(h−h0)``, ``row = cy − Δlat/dlat + pr·(h−h0)``."""
    cx, cy = centre_px if centre_px is not None else (width / 2.0, height / 2.0)
    s_lon = s_lat = 0.01
    s_h = 500.0
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
    cam = RPCModel(line_num=line_num, line_den=den, samp_num=samp_num, samp_den=den.copy(),
                    line_off=cy - 0.5, samp_off=cx - 0.5, lat_off=lat0, lon_off=lon0, height_off=h0,
                    line_scale=1.0, samp_scale=1.0, lat_scale=s_lat, lon_scale=s_lon, height_scale=s_h,
                    width=width, height=height, source="synthetic affine")
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
    truth: np.ndarray          # ellipsoidal DSM on the grid (m)
    images: list               # raw image arrays (native dtype)
    cameras: list
    names: list
    visible: np.ndarray        # cells seen by both images (not occluded)


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
    def __init__(self, seed: int = 0, extent_m: float = 120.0, step_m: float = 0.25):
        rng = np.random.default_rng(seed)
        n = int(2 * extent_m / step_m)
        a = ndimage.gaussian_filter(rng.normal(size=(n, n)), 2.0)
        a += 0.5 * ndimage.gaussian_filter(rng.normal(size=(n, n)), 6.0)
        self.a = (a - a.mean()) / a.std()
        self.step = step_m
        self.extent = extent_m

    def __call__(self, x, y):
        c = (np.asarray(x) + self.extent) / self.step
        r = (np.asarray(y) + self.extent) / self.step
        return ndimage.map_coordinates(self.a, [r, c], order=1, mode="reflect")


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


def make_scene(seed: int = 0, size_m: float = 48.0, posting_m: float = 0.5, gsd_m: float = 0.5,
               parallax_a=(0.55, 0.05), parallax_b=(-0.45, 0.02), noise: float = 0.02) -> Scene:
    crs = utm_crs_for(LON0, LAT0)
    from geocd.geodesy import from_lonlat

    xc, yc = from_lonlat(LON0, LAT0, crs)
    grid = AOIGrid.from_bounds(float(xc) - size_m / 2, float(yc) - size_m / 2, float(xc) + size_m / 2,
                               float(yc) + size_m / 2, posting_m, crs)
    lon, lat = grid.lonlat()
    truth = dsm_local(*_local_xy(lon, lat))
    npx = int(size_m / gsd_m) + 40
    tex = Texture(seed)
    rng = np.random.default_rng(seed + 1)
    cams, imgs = [], []
    for k, par in enumerate((parallax_a, parallax_b)):
        cam = affine_rpc(gsd_m, par, npx, npx)
        inten, _ = render(cam, tex)
        inten = inten + noise * rng.normal(size=inten.shape)
        if k == 0:   # 11-bit in uint16, gain and offset
            img = np.clip(600 + 150 * inten, 0, 2047).astype(np.uint16)
        else:        # 8-bit RGB, another gain/offset
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
