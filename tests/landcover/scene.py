"""A tiny land-cover scene: a georeferenced RGB image of grass (left) and road (right) with a roof block."""

from __future__ import annotations

import numpy as np
from affine import Affine

CRS = "EPSG:32631"
X0, Y1 = 500000.0, 4800000.0


def cover(n: int = 96) -> np.ndarray:
    """True cover: 1 vegetation (left half, minus a roof block), 0 other."""
    v = np.zeros((n, n), np.uint8)
    v[:, : n // 2] = 1
    v[n // 4 : n // 4 + 12, n // 4 : n // 4 + 12] = 0  # a roof inside the grass
    return v


def rgb(n: int = 96, seed: int = 0, gain: float = 1.0) -> np.ndarray:
    """uint8 (3, n, n): textured green grass, smooth grey road / roof."""
    rng = np.random.default_rng(seed)
    v = cover(n).astype(bool)
    img = np.empty((3, n, n))
    tex = rng.normal(0, 18, (n, n))
    img[0] = np.where(v, 70 + tex, 120 + rng.normal(0, 4, (n, n)))
    img[1] = np.where(v, 120 + tex, 122 + rng.normal(0, 4, (n, n)))
    img[2] = np.where(v, 50 + tex, 125 + rng.normal(0, 4, (n, n)))
    return np.clip(img * gain, 0, 255).astype(np.uint8)


def transform(posting: float = 1.0) -> Affine:
    return Affine(posting, 0, X0, 0, -posting, Y1)


def write_scene(d, n: int = 96):
    """Image, DEM, labels (map CRS) and a truth raster in folder ``d``; returns their paths."""
    import geopandas as gpd
    import rasterio
    from shapely.geometry import box

    img = d / "ortho.tif"
    with rasterio.open(
        img, "w", driver="GTiff", width=n, height=n, count=3, dtype="uint8", crs=CRS, transform=transform()
    ) as ds:
        ds.write(rgb(n))
    dem = d / "dem.tif"
    with rasterio.open(
        dem, "w", driver="GTiff", width=n, height=n, count=1, dtype="float32", crs=CRS, transform=transform()
    ) as ds:
        ds.write(np.full((1, n, n), 100.0, np.float32))
    truth = d / "truth.tif"
    with rasterio.open(
        truth, "w", driver="GTiff", width=n, height=n, count=1, dtype="uint8", crs=CRS, transform=transform()
    ) as ds:
        ds.write(cover(n)[None])
    labels = d / "labels.gpkg"
    polys = [
        ("vegetation", box(X0 + 5, Y1 - 90, X0 + 15, Y1 - 70)),
        ("vegetation", box(X0 + 30, Y1 - 15, X0 + 42, Y1 - 5)),
        ("other", box(X0 + 60, Y1 - 90, X0 + 75, Y1 - 75)),
        ("other", box(X0 + 80, Y1 - 30, X0 + 92, Y1 - 10)),
    ]
    gpd.GeoDataFrame({"class": [p[0] for p in polys]}, geometry=[p[1] for p in polys], crs=CRS).to_file(labels)
    return {"image": img, "dem": dem, "truth": truth, "labels": labels}
