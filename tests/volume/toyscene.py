"""A tiny synthetic town for the volume tests: boxes on a plane, seen by frame cameras.

Everything lives in the ENU frame of a point at lon 10°, lat 45°, ellipsoidal height
100 m; cameras are :class:`geocd.camera.FrameCamera` in UTM 32N with ellipsoidal
heights, so rays go through the camera protocol like real data. Images are
rendered by marching each pixel's ray through the height field (8 cm steps).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from geocd.camera.frame import FrameCamera, rotation_to_opk
from geocd.geodesy import AOIGrid, LocalFrame, from_lonlat
from geocd.volume import geometry_for_aoi
from geocd.volume.rays import pixel_rays

LON0, LAT0, H0 = 10.0, 45.0, 100.0
CRS = "EPSG:32632"
FRAME = LocalFrame(LON0, LAT0, H0)
# boxes: (e0, e1, n0, n1, height m, roof intensity)
BOXES_A = [(-12.0, -4.0, -10.0, -2.0, 6.0, 0.85), (3.0, 12.0, 2.0, 8.0, 4.0, 0.7), (4.0, 8.0, -12.0, -6.0, 8.0, 0.95)]
NEW_BOX = (-10.0, -3.0, 4.0, 11.0, 5.0, 0.9)  # appears in epoch B
BOXES_B = BOXES_A + [NEW_BOX]


_TEX = np.random.default_rng(1234).uniform(0.0, 1.0, (64, 64))


def dsm(e: np.ndarray, n: np.ndarray, boxes=BOXES_A, stripes: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """Surface height (ENU up, m) and roof/ground intensity at ENU points (roofs striped by ``stripes``; 0: uniform)."""
    z = np.zeros(np.shape(e))
    # ground texture: random 1.25 m tiles (non-periodic over the scene) + a smooth ramp
    i = np.floor(np.asarray(e) / 1.25).astype(int) % _TEX.shape[0]
    j = np.floor(np.asarray(n) / 1.25).astype(int) % _TEX.shape[1]
    col = 0.25 + 0.35 * _TEX[i, j] + 0.05 * np.sin(np.asarray(e) / 7.0)
    for e0, e1, n0, n1, h, c in boxes:
        m = (e >= e0) & (e < e1) & (n >= n0) & (n < n1)
        z = np.where(m & (h > z), h, z)
        roof = c - stripes * ((np.floor(e / 1.5)) % 2)
        col = np.where(m & (z == h), roof, col)
    return z, col


WALL = 0.12


def render(camera, shape, boxes=BOXES_A, noise=0.01, seed=0, stripes: float = 0.1) -> np.ndarray:
    """Ray-march the height field: intensity image (rows, cols) in [0, 1]."""
    rows, cols = shape
    geom = volume_geometry()
    R, C = np.mgrid[0:rows, 0:cols]
    o, d = pixel_rays(camera, geom, C.ravel() + 0.5, R.ravel() + 0.5)
    # start at u = 12 m
    t = (o[:, 2] - 12.0) / -d[:, 2]
    step = 0.08
    out = np.full(o.shape[0], np.nan)
    prev_z = None
    alive = np.ones(o.shape[0], bool)
    for _ in range(int(40.0 / step)):
        p = o + t[:, None] * d
        z, col = dsm(p[:, 0], p[:, 1], boxes, stripes)
        hit = alive & (p[:, 2] <= z)
        if hit.any():
            wall = hit & (prev_z is not None) & (z > (prev_z if prev_z is not None else z) + 1e-9)
            out[hit] = np.where(wall[hit], WALL, col[hit])
            alive &= ~hit
        if not alive.any():
            break
        prev_z = z
        t = t + step
    rng = np.random.default_rng(seed)
    out = out + noise * rng.standard_normal(out.shape)
    return np.clip(out, 0, 1).reshape(rows, cols)


def look_at_camera(
    off_nadir_deg: float, azimuth_deg: float, *, altitude_m: float = 300.0, size: int = 56, gsd_m: float = 0.8
) -> FrameCamera:
    """A frame camera looking at the scene centre from ``off_nadir_deg`` towards ``azimuth_deg``."""
    a, z = math.radians(azimuth_deg), math.radians(off_nadir_deg)
    dist = altitude_m / math.cos(z)
    # camera position in ENU, then in UTM (x, y) + ellipsoidal height
    pe = np.array([math.sin(a) * math.sin(z), math.cos(a) * math.sin(z), math.cos(z)]) * dist
    lon, lat, h = FRAME.from_enu(pe[0], pe[1], pe[2])
    x, y = from_lonlat(lon, lat, CRS)
    tx, ty = from_lonlat(LON0, LAT0, CRS)
    fwd = np.array([float(tx) - float(x), float(ty) - float(y), H0 - float(h)])
    fwd /= np.linalg.norm(fwd)
    north = np.array([0.0, 1.0, 0.0])
    yd = -north - (-north @ fwd) * fwd
    if np.linalg.norm(yd) < 1e-6:
        yd = np.array([0.0, -1.0, 0.0])
    yd /= np.linalg.norm(yd)
    xr = np.cross(yd, fwd)
    r_cv = np.column_stack([xr, yd, fwd])
    opk = rotation_to_opk(r_cv @ np.diag([1.0, -1.0, -1.0]))
    f = dist / gsd_m
    return FrameCamera(
        width=size,
        height=size,
        focal_px=f,
        position=(float(x), float(y), float(h)),
        opk_deg=opk,
        crs=CRS,
        vertical_datum="ellipsoid",
    )


def aoi_grid(posting_m: float = 0.5) -> AOIGrid:
    cx, cy = from_lonlat(LON0, LAT0, CRS)
    return AOIGrid.from_bounds(float(cx) - 16, float(cy) - 16, float(cx) + 16, float(cy) + 16, posting_m, CRS)


def volume_geometry(finest_cell_m: float = 0.5, max_depth: int = 3):
    return geometry_for_aoi(
        aoi_grid(), z_min_m=H0 - 1.0, z_max_m=H0 + 11.0, finest_cell_m=finest_cell_m, max_depth=max_depth, frame=FRAME
    )


TRAIN_VIEWS = [(0, 0), (20, 0), (20, 90), (20, 180), (20, 270), (30, 45), (30, 225), (30, 135), (30, 315)]
TEST_VIEW = (15, 120)


@dataclass
class ToyData:
    cameras: list
    images: list
    test_camera: object
    test_image_a: np.ndarray
    test_image_b: np.ndarray
    change_mask_b: np.ndarray


def make_toy(size: int = 56) -> ToyData:
    cams = [look_at_camera(z, a, size=size) for z, a in TRAIN_VIEWS]
    imgs = [render(c, (size, size), seed=i) for i, c in enumerate(cams)]
    tc = look_at_camera(*TEST_VIEW, size=size)
    ta = render(tc, (size, size), BOXES_A, seed=100)
    tb = render(tc, (size, size), BOXES_B, seed=101)
    # truth: pixels whose first surface differs between A and B (3-D change seen by this view)
    mask = np.abs(render(tc, (size, size), BOXES_B, noise=0) - render(tc, (size, size), BOXES_A, noise=0)) > 1e-6
    return ToyData(cams, imgs, tc, ta, tb, mask)
