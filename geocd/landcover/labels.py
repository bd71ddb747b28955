"""Training labels: polygons a user drew, as class rasters on an image or on the AOI grid.

A label layer is any OGR vector layer of polygons with a class attribute (the
way a QGIS user labels: digitise a few polygons of "vegetation" and "other").
It may be drawn

* **on the AOI grid / the map** (the layer has a CRS): the polygons are
  rasterised on the grid and reach each image through its camera and the
  surface heights (see :mod:`geocd.landcover.pipeline`), or directly through an
  orthoimage's geotransform;
* **on an image in pixel coordinates** (the layer has no CRS): x = column,
  y = row, with y either growing downwards (GDAL pixel/line) or negative
  downwards (QGIS shows an un-georeferenced raster with y = −row); the sign is
  detected. An ``image`` attribute, when present, says which image (by file
  stem) each polygon was drawn on.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..errors import ConfigError, InputFileNotFoundError, UnsupportedFormatError
from .classifier import LabelError

#: attribute names tried (in order) when the class field is not given
CLASS_FIELDS = ("class", "label", "landcover", "cover", "type", "name")


def read_labels(path: os.PathLike | str, layer: str | int | None = None, class_field: str | None = None):
    """Read a label layer → GeoDataFrame with columns ``label`` (str), ``polygon_id`` (int) and the geometry.

    The CRS is kept (None for pixel-coordinate layers).
    """
    import geopandas as gpd
    import pyogrio

    p = Path(path)
    if not p.exists():
        raise InputFileNotFoundError(f"label layer {p} does not exist; check the path")
    try:
        gdf = gpd.read_file(p, layer=layer, engine="pyogrio")
    except (pyogrio.errors.DataSourceError, pyogrio.errors.DataLayerError) as exc:
        raise UnsupportedFormatError(
            f"cannot read {p} as a vector layer ({exc}); give a GeoPackage, GeoJSON or shapefile of polygons"
        ) from exc
    gdf = gdf[gdf.geometry.notna() & ~gdf.geometry.is_empty]
    gdf = gdf[gdf.geometry.geom_type.isin(["Polygon", "MultiPolygon"])]
    if gdf.empty:
        raise LabelError(f"{p} holds no polygon; draw label polygons (points and lines are not used)")
    if class_field is None:
        lower = {c.lower(): c for c in gdf.columns}
        class_field = next((lower[c] for c in CLASS_FIELDS if c in lower), None)
        if class_field is None:
            raise ConfigError(
                f"{p} has no class attribute (tried {list(CLASS_FIELDS)}); name it with --class-field "
                f"(attributes: {[c for c in gdf.columns if c != 'geometry']})"
            )
    elif class_field not in gdf.columns:
        raise ConfigError(
            f"{p} has no attribute {class_field!r}; attributes: {[c for c in gdf.columns if c != 'geometry']}"
        )
    gdf = gdf[gdf[class_field].notna()].copy()
    if gdf.empty:
        raise LabelError(f"every polygon of {p} has an empty {class_field!r}; give each polygon its class")
    gdf["label"] = gdf[class_field].map(_class_name)
    gdf["polygon_id"] = np.arange(len(gdf), dtype=np.int64)
    if not gdf.geometry.is_valid.all():
        gdf["geometry"] = gdf.geometry.make_valid()
    return gdf.reset_index(drop=True)


def _class_name(v) -> str:
    if isinstance(v, float) and v.is_integer():
        v = int(v)
    return str(v)


def class_list(gdf, positive: str | None = None) -> list[str]:
    """Sorted class names; with ``positive`` given and two classes, the positive one goes last (index 1)."""
    names = sorted(set(gdf["label"]))
    if positive is not None:
        positive = str(positive)
        if positive not in names:
            raise ConfigError(f"class {positive!r} is not in the labels; they hold {names}")
        names = [n for n in names if n != positive] + [positive]
    return names


def pixel_layer_rows(gdf, shape: tuple[int, int]):
    """Map a pixel-coordinate layer to rows pointing down (y = −row when every y ≤ 0, as QGIS draws)."""
    from shapely.affinity import scale

    if len(gdf) and float(gdf.total_bounds[3]) <= 0.0:
        gdf = gdf.copy()
        gdf["geometry"] = gdf.geometry.map(lambda g: scale(g, 1.0, -1.0, origin=(0, 0)))
    return gdf


def rasterize_labels(gdf, shape: tuple[int, int], transform, classes: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """Class index (int16, −1 unlabelled) and polygon id (int32, −1) of every pixel/cell of a raster.

    ``transform`` maps pixel (col, row) to the layer's coordinates (an orthoimage's or a grid's
    geotransform, or the identity for pixel-coordinate layers). Overlapping polygons of different
    classes leave their overlap unlabelled.
    """
    from rasterio.features import rasterize

    idx = {c: k for k, c in enumerate(classes)}
    cls = np.full(shape, -1, np.int16)
    pid = np.full(shape, -1, np.int32)
    if len(gdf) == 0:
        return cls, pid
    seen = np.zeros(shape, np.int16)
    for c in classes:
        sub = gdf[gdf["label"] == c]
        if sub.empty:
            continue
        m = rasterize(
            [(g, 1) for g in sub.geometry], out_shape=shape, transform=transform, fill=0, dtype="uint8"
        ).astype(bool)
        cls[m] = idx[c]
        seen += m.astype(np.int16)
    conflict = seen > 1
    cls[conflict] = -1
    pid_r = (
        rasterize(
            [(g, int(i) + 1) for g, i in zip(gdf.geometry, gdf["polygon_id"])],
            out_shape=shape,
            transform=transform,
            fill=0,
            dtype="int32",
        )
        - 1
    )
    pid[:] = np.where(cls >= 0, pid_r, -1)
    return cls, pid


def polygons_for_image(gdf, image_path: os.PathLike | str):
    """The polygons of a pixel-coordinate layer that belong to ``image_path`` (by an ``image`` attribute)."""
    if "image" not in gdf.columns:
        return gdf
    stem = Path(image_path).stem
    names = gdf["image"].astype(str).map(lambda s: Path(s).stem)
    return gdf[names == stem]
