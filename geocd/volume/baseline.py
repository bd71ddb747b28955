"""2-D change-detection baselines for comparison with the volume model.

Both predict a new (test) image from one earlier (reference) image warped into
the test image's geometry through a DEM, i.e. "orthorectify on the DEM and
difference", done in the test image's own geometry so that the scores line up
with per-image truth masks:

* :func:`difference_score`: ``|c_test − c_ref|`` of the rank-normalised images.
* :func:`carlotto_score`: Carlotto's joint-histogram predictor — the test
  intensity predicted by its conditional mean given the reference intensity
  (estimated from the joint histogram of the two images, i.e. a global,
  non-parametric radiometric mapping), the score being the residual in units
  of the conditional standard deviation (Carlotto 1997).

Buildings lean differently in two views and the DEM has no buildings, so both
baselines mark building edges, walls and occlusions as change: that is the
weakness a 3-D model addresses.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..geodesy import AOIGrid, to_lonlat
from .scene import VolumeGeometry


def sample_grid(values: np.ndarray, grid: AOIGrid, lon: np.ndarray, lat: np.ndarray, order: int = 1) -> np.ndarray:
    """Bilinear (``order=1``) sample of a raster on ``grid`` at lon/lat points (NaN outside)."""
    from scipy.ndimage import map_coordinates

    from ..geodesy import from_lonlat

    x, y = from_lonlat(lon, lat, grid.crs)
    r, c = grid.rowcol(x, y)
    v = np.where(np.isfinite(values), values, np.nanmedian(values))
    out = map_coordinates(v, [np.ravel(r) - 0.5, np.ravel(c) - 0.5], order=order, mode="nearest")
    bad = (
        ~np.isfinite(np.ravel(r))
        | (np.ravel(r) < 0)
        | (np.ravel(c) < 0)
        | (np.ravel(r) > grid.height)
        | (np.ravel(c) > grid.width)
    )
    out[bad] = np.nan
    return out.reshape(np.shape(lon))


def ground_on_dem(
    camera: Any, cols: np.ndarray, rows: np.ndarray, dem_m: np.ndarray, grid: AOIGrid, iters: int = 6
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where the pixels' rays meet a DEM (fixed-point iteration on the height; ellipsoidal metres)."""
    h = np.full(np.shape(cols), float(np.nanmedian(dem_m)))
    lon = lat = None
    for _ in range(iters):
        lon, lat = camera.localize(cols, rows, h)
        hn = sample_grid(dem_m, grid, lon, lat)
        h = np.where(np.isfinite(hn), hn, h)
    return lon, lat, h


def warp_reference(
    test_camera: Any,
    shape: tuple[int, int],
    ref_intensity: np.ndarray,
    ref_camera: Any,
    dem_m: np.ndarray,
    grid: AOIGrid,
) -> np.ndarray:
    """The reference image resampled (bilinear) into the test image's pixels through the DEM."""
    from scipy.ndimage import map_coordinates

    rows, cols = shape
    R, C = np.mgrid[0:rows, 0:cols]
    lon, lat, h = ground_on_dem(test_camera, C.ravel() + 0.5, R.ravel() + 0.5, dem_m, grid)
    c, r = ref_camera.project(lon, lat, h)
    img = np.where(np.isfinite(ref_intensity), ref_intensity, 0.0)
    out = map_coordinates(img, [r - 0.5, c - 0.5], order=1, mode="constant", cval=np.nan)
    valid = map_coordinates(
        np.isfinite(ref_intensity).astype(float), [r - 0.5, c - 0.5], order=1, mode="constant", cval=0.0
    )
    out[(valid < 0.99) | ~np.isfinite(c)] = np.nan
    return out.reshape(shape)


def difference_score(test: np.ndarray, ref_warped: np.ndarray) -> np.ndarray:
    """``|test − ref|`` (NaN where either is invalid)."""
    return np.abs(test - ref_warped)


def carlotto_score(test: np.ndarray, ref_warped: np.ndarray, bins: int = 64) -> np.ndarray:
    """Residual of the joint-histogram predictor ``E[test | ref]`` in conditional standard deviations."""
    ok = np.isfinite(test) & np.isfinite(ref_warped)
    k = np.zeros(test.shape, dtype=int)
    k[ok] = np.clip((ref_warped[ok] * bins).astype(int), 0, bins - 1)
    n = np.bincount(k[ok], minlength=bins).astype(float)
    s1 = np.bincount(k[ok], weights=test[ok], minlength=bins)
    s2 = np.bincount(k[ok], weights=test[ok] ** 2, minlength=bins)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = s1 / n
        sd = np.sqrt(np.maximum(s2 / n - mean**2, 0.0))
    gm = float(np.mean(test[ok]))
    gsd = float(np.std(test[ok]))
    mean = np.where(n >= 20, mean, gm)
    sd = np.maximum(np.where(n >= 20, sd, gsd), 0.02)
    out = np.abs(test - mean[k]) / sd[k]
    out[~ok] = np.nan
    return out


def view_direction(camera: Any, geometry: VolumeGeometry, width: int, height: int) -> np.ndarray:
    """Unit ENU direction of the camera's ray through the image centre."""
    from .rays import pixel_rays

    _, d = pixel_rays(camera, geometry, np.array([width / 2.0]), np.array([height / 2.0]))
    return d[0]


def nearest_view(test_camera: Any, test_shape: tuple[int, int], candidates: list, geometry: VolumeGeometry) -> int:
    """Index of the candidate view (objects with ``camera`` and ``intensity``) seen from the closest direction."""
    dt = view_direction(test_camera, geometry, test_shape[1], test_shape[0])
    best, best_c = -1, -2.0
    for i, v in enumerate(candidates):
        d = view_direction(v.camera, geometry, v.intensity.shape[1], v.intensity.shape[0])
        c = float(d @ dt)
        if c > best_c:
            best, best_c = i, c
    return best


def first_surface_height(
    camera: Any,
    shape: tuple[int, int],
    dsm_m: np.ndarray,
    grid: AOIGrid,
    geometry: VolumeGeometry,
    step_m: float = 0.25,
) -> np.ndarray:
    """Height (ellipsoidal m) of the first DSM surface each pixel's ray meets (ray marching; NaN = none).

    Used to find building edges and occlusion boundaries in image geometry for the evaluation.
    """
    from .rays import pixel_rays

    rows, cols = shape
    R, C = np.mgrid[0:rows, 0:cols]
    o, d = pixel_rays(camera, geometry, C.ravel() + 0.5, R.ravel() + 0.5)
    fr = geometry.frame
    # ENU (e, n) -> grid (row, col) is affine to far below a centimetre over an AOI: fit it once
    l, b, r, t = grid.bounds
    gx, gy = np.meshgrid(np.linspace(l, r, 5), np.linspace(b, t, 5))
    lon, lat = to_lonlat(gx.ravel(), gy.ravel(), grid.crs)
    e, n, _ = fr.to_enu(lon, lat, np.full(lon.shape, fr.h0))
    rr, cc = grid.rowcol(gx.ravel(), gy.ravel())
    A = np.column_stack([e, n, np.ones_like(e)])
    coef_r, *_ = np.linalg.lstsq(A, rr, rcond=None)
    coef_c, *_ = np.linalg.lstsq(A, cc, rcond=None)
    z_enu = np.where(np.isfinite(dsm_m), dsm_m - fr.h0, -np.inf)
    top = float(np.nanmax(dsm_m)) - fr.h0 + 0.5
    bot = float(np.nanmin(dsm_m)) - fr.h0 - 0.5
    out = np.full(o.shape[0], np.nan)
    alive = np.all(np.isfinite(o), axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        t = (o[:, 2] - top) / -d[:, 2]
        t_end = (o[:, 2] - bot) / -d[:, 2]
    while alive.any():
        idx = np.nonzero(alive)[0]
        p = o[idx] + t[idx, None] * d[idx]
        ri = np.floor(coef_r[0] * p[:, 0] + coef_r[1] * p[:, 1] + coef_r[2]).astype(int)
        ci = np.floor(coef_c[0] * p[:, 0] + coef_c[1] * p[:, 1] + coef_c[2]).astype(int)
        inside = (ri >= 0) & (ci >= 0) & (ri < grid.height) & (ci < grid.width)
        zs = np.full(idx.size, -np.inf)
        zs[inside] = z_enu[ri[inside], ci[inside]]
        hit = p[:, 2] <= zs
        out[idx[hit]] = zs[hit] + fr.h0
        done = hit | (t[idx] > t_end[idx])
        alive[idx[done]] = False
        t[idx] += step_m
    return out.reshape(shape)


def edge_zone(height_img: np.ndarray, jump_m: float = 2.0, radius_px: int = 2) -> np.ndarray:
    """Pixels within ``radius_px`` of a first-surface height jump above ``jump_m`` (building edges, occlusions)."""
    from scipy.ndimage import distance_transform_edt, maximum_filter, minimum_filter

    ok = np.isfinite(height_img)
    if not ok.any():
        return np.zeros(height_img.shape, bool)
    # fill pixels without a surface (outside the DSM) with their nearest surface: no jump at the DSM's border
    _, (ri, ci) = distance_transform_edt(~ok, return_indices=True)
    h = height_img[ri, ci]
    k = 2 * radius_px + 1
    return ((maximum_filter(h, k) - minimum_filter(h, k)) > jump_m) & ok
