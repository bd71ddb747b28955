"""Tiny synthetic DEM scenes with known shifts, volumes and error structure."""

from __future__ import annotations

import numpy as np
from affine import Affine

from geocd.geodesy import AOIGrid
from geocd.io.raster import DEM


def grid(
    n_rows: int = 160,
    n_cols: int = 180,
    posting: float = 10.0,
    crs: str = "EPSG:32610",
    x0: float = 500000.0,
    y0: float = 5100000.0,
) -> AOIGrid:
    return AOIGrid(crs, Affine(posting, 0, x0, 0, -posting, y0), n_cols, n_rows)


def terrain(x: np.ndarray, y: np.ndarray, bounds, seed: int = 0) -> np.ndarray:
    """Smooth hilly terrain (m) at map points (x, y): a fixed surface for given ``bounds``
    (left, bottom, right, top) and seed, with slopes in all directions."""
    rng = np.random.default_rng(seed)
    l, b, r, t = bounds
    z = 1500.0 + 0.02 * (x - 0.5 * (l + r)) - 0.015 * (y - 0.5 * (b + t))
    for _ in range(14):
        cx, cy = rng.uniform(l, r), rng.uniform(b, t)
        s = rng.uniform(150, 450)
        a = rng.uniform(-120, 160)
        z = z + a * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * s * s))
    z = z + 8.0 * np.sin(x / 173.0) * np.cos(y / 217.0)
    return z


def correlated_noise(shape, sigma: float, corr_px: float, rng, white: float = 0.0) -> np.ndarray:
    """Gaussian random field: white noise filtered by a Gaussian kernel (std ``corr_px`` px),
    rescaled to std ``sigma``, plus independent white noise of std ``white``."""
    from scipy.ndimage import gaussian_filter

    f = gaussian_filter(rng.normal(size=shape), corr_px, mode="wrap")
    f *= sigma / f.std()
    if white:
        f = f + rng.normal(scale=white, size=shape)
    return f


def pair(
    shift_m=(0.0, 0.0, 0.0),
    noise_m: float = 0.3,
    bump_m: float = 0.0,
    seed: int = 1,
    g: AOIGrid | None = None,
    bump_centre=(0.5, 0.5),
    bump_radius_px: float = 12.0,
):
    """DEM A, and B = A displaced by shift_m (B(x) = A(x − d) + dz) plus noise and an optional bump.

    Returns (dem_a, dem_b, info) where info["volume_m3"] is the bump's true volume on B's grid cells.
    """
    g = g or grid()
    rng = np.random.default_rng(seed)
    x, y = g.xy()
    za = terrain(x, y, g.bounds)
    de, dn, dz = shift_m
    zb = terrain(x - de, y - dn, g.bounds) + dz
    info = {"volume_m3": 0.0, "bump": np.zeros(g.shape, bool)}
    if bump_m:
        r0 = bump_centre[0] * g.height
        c0 = bump_centre[1] * g.width
        rr, cc = np.mgrid[0 : g.height, 0 : g.width]
        d2 = ((rr + 0.5 - r0) ** 2 + (cc + 0.5 - c0) ** 2) / bump_radius_px**2
        bump = np.where(d2 < 1, bump_m * (1 - d2), 0.0)
        zb = zb + bump
        info["volume_m3"] = float(bump.sum() * g.cell_area_m2)
        info["bump"] = bump > 0
    za = za + rng.normal(scale=noise_m, size=g.shape)
    zb = zb + rng.normal(scale=noise_m, size=g.shape)
    return (DEM(za.astype(np.float32), g, None, "A"), DEM(zb.astype(np.float32), g, None, "B"), info)
