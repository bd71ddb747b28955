"""Vector input and output (footprints, change polygons, tables).

* :func:`read_footprints`: any OGR vector → GeoDataFrame in the AOI CRS.
* :func:`write_gpkg`: several layers (features or plain tables) into one
  GeoPackage, atomically, with optional QGIS styles stored in the GeoPackage's
  ``layer_styles`` table so layers open styled in QGIS.
"""

from __future__ import annotations

import datetime as _dt
import os
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from ..errors import CRSError, EmptyDataError, InputFileNotFoundError, UnsupportedFormatError
from ..geodesy import as_crs
from .atomic import atomic_path


def read_footprints(
    path: os.PathLike | str,
    crs: Any = None,
    layer: str | int | None = None,
    bbox: tuple[float, float, float, float] | None = None,
):
    """Read building footprints (or any polygons) into a GeoDataFrame.

    Parameters
    ----------
    crs : target CRS (the AOI's); the layer is reprojected to it.
    layer : layer name or index for multi-layer sources (default: the first).
    bbox : optional (left, bottom, right, top) filter in the layer's CRS.

    Raises
    ------
    InputFileNotFoundError, UnsupportedFormatError, CRSError, EmptyDataError
    """
    import geopandas as gpd
    import pyogrio

    p = Path(path)
    if not p.exists():
        raise InputFileNotFoundError(f"footprint file {p} does not exist; check the path")
    try:
        gdf = gpd.read_file(p, layer=layer, bbox=bbox, engine="pyogrio")
    except (pyogrio.errors.DataSourceError, pyogrio.errors.DataLayerError) as exc:
        raise UnsupportedFormatError(
            f"cannot read {p} as a vector layer ({exc}); give a GeoPackage, GeoJSON or shapefile"
        ) from exc
    if gdf.crs is None:
        raise CRSError(f"footprints {p} have no CRS; set one (e.g. ogr2ogr -a_srs EPSG:...) before using them")
    gdf = gdf[gdf.geometry.notna() & ~gdf.geometry.is_empty]
    gdf = gdf[gdf.geometry.geom_type.isin(["Polygon", "MultiPolygon"])]
    if gdf.empty:
        raise EmptyDataError(f"{p} holds no polygon features; footprints must be polygons")
    if crs is not None:
        gdf = gdf.to_crs(as_crs(crs))
    if not gdf.geometry.is_valid.all():
        gdf = gdf.copy()
        gdf["geometry"] = gdf.geometry.make_valid()
    return gdf.reset_index(drop=True)


def check_footprints_file(path: os.PathLike | str, layer: str | int | None = None) -> None:
    """Check a footprint file up front, from its metadata only (no feature is read): a vector layer of polygons
    with a CRS and at least one feature. For commands to call before any heavy work; :func:`read_footprints`
    reads it later.

    Raises
    ------
    InputFileNotFoundError, UnsupportedFormatError, CRSError, EmptyDataError
    """
    import pyogrio

    p = Path(path)
    if not p.exists():
        raise InputFileNotFoundError(f"footprint file {p} does not exist; check the path")
    try:
        info = pyogrio.read_info(p, layer=layer)
    except (pyogrio.errors.DataSourceError, pyogrio.errors.DataLayerError) as exc:
        what = "a raster" if _is_raster(p) else "not a vector layer"
        raise UnsupportedFormatError(
            f"footprints {p} is {what} ({' '.join(str(exc).split())[:160]}); footprints are building polygons: "
            "give a GeoPackage, GeoJSON or shapefile"
        ) from None
    gtype = str(info.get("geometry_type") or "")
    if not gtype:
        raise EmptyDataError(f"footprints {p} hold a table without geometries; give a layer of building polygons")
    if not any(k in gtype for k in ("Polygon", "Unknown", "Geometry")):
        raise EmptyDataError(f"footprints {p} hold {gtype} features; footprints must be polygons (building outlines)")
    if info.get("crs") is None:
        raise CRSError(f"footprints {p} have no CRS; set one (e.g. ogr2ogr -a_srs EPSG:...) before using them")
    if info.get("features") == 0:
        raise EmptyDataError(f"footprints {p} hold no features; give a layer of building polygons")


def _is_raster(p: Path) -> bool:
    import rasterio

    try:
        with rasterio.open(p):
            return True
    except Exception:  # noqa: BLE001 - anything rasterio cannot open is not a raster
        return False


#: GeoPackage 1.2: QGIS 3.22 (GDAL 3.6) warns that the 1.4 written by newer GDALs "may only be partially supported"
_GPKG_OPTS = {"dataset_options": {"VERSION": "1.2"}}


def _styles_frame(styles: Mapping[str, str], geometry_columns: Mapping[str, str]):
    import pandas as pd

    now = _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")
    rows = []
    for layer, qml in styles.items():
        rows.append(
            {
                "f_table_catalog": "",
                "f_table_schema": "",
                "f_table_name": layer,
                "f_geometry_column": geometry_columns.get(layer, "geom"),
                "styleName": layer,
                "styleQML": qml,
                "styleSLD": "",
                "useAsDefault": True,
                "description": "geocd default style",
                "owner": "geocd",
                "ui": None,
                "update_time": now,
            }
        )
    return pd.DataFrame(rows)


def write_gpkg(
    path: os.PathLike | str,
    layers: Mapping[str, Any],
    *,
    styles: Mapping[str, str] | None = None,
    overwrite: bool = True,
) -> Path:
    """Write several layers into one GeoPackage atomically.

    Parameters
    ----------
    layers : mapping layer name → GeoDataFrame (features), DataFrame (attribute table), or an
        iterable of GeoDataFrame batches with a ``geometry_type`` attribute (e.g.
        :class:`geocd.tiling.regions.RegionBatches`), appended batch by batch
    styles : mapping layer name → QML text, stored in ``layer_styles`` (QGIS loads it as the
        layer's default style).

    Empty GeoDataFrames are written as empty layers (with their schema), so a
    consumer can tell "no changes" from "not computed".
    """
    import geopandas as gpd
    import pyogrio

    import pandas as pd

    with atomic_path(path, overwrite=overwrite) as tmp:
        geom_cols: dict[str, str] = {}
        for name, df in layers.items():
            if isinstance(df, gpd.GeoDataFrame):
                geom_cols[name] = "geom"
                pyogrio.write_dataframe(df, tmp, layer=name, driver="GPKG", **_GPKG_OPTS)
            elif not isinstance(df, pd.DataFrame):
                # GeoDataFrame batches of one layer (``geometry_type`` known beforehand): appended one by one
                geom_cols[name] = "geom"
                gt = df.geometry_type
                opts = {"geometry_type": gt, "promote_to_multi": gt.startswith("Multi")}
                for i, part in enumerate(df):
                    if i == 0:
                        pyogrio.write_dataframe(part, tmp, layer=name, driver="GPKG", **opts, **_GPKG_OPTS)
                    else:
                        pyogrio.write_dataframe(part, tmp, layer=name, driver="GPKG", append=True, **opts)
            else:
                pyogrio.write_dataframe(df, tmp, layer=name, driver="GPKG", **_GPKG_OPTS)
        if styles:
            pyogrio.write_dataframe(
                _styles_frame(styles, geom_cols), tmp, layer="layer_styles", driver="GPKG", **_GPKG_OPTS
            )
    return Path(path)


def qml_for(name: str) -> str:
    """A QML style shipped with geocd (``geocd/styles/<name>.qml``)."""
    from importlib.resources import files

    try:
        return files("geocd").joinpath("styles", f"{name}.qml").read_text(encoding="utf-8")
    except FileNotFoundError as exc:  # pragma: no cover - packaging error
        raise UnsupportedFormatError(f"style {name!r} is not shipped with geocd") from exc


def polygons_to_mask(gdf, grid, attribute: str | None = None, fill: float = 0) -> np.ndarray:
    """Rasterize polygons onto an AOI grid (value 1, or ``attribute``)."""
    from rasterio.features import rasterize

    g = gdf.to_crs(grid.crs) if gdf.crs is not None and not as_crs(gdf.crs).equals(grid.crs) else gdf
    if attribute is None:
        shapes = [(geom, 1) for geom in g.geometry]
        dtype = "uint8"
    else:
        shapes = list(zip(g.geometry, g[attribute]))
        dtype = "float32"
    if not shapes:
        return np.full(grid.shape, fill, dtype=dtype)
    return rasterize(shapes, out_shape=grid.shape, transform=grid.transform, fill=fill, dtype=dtype)
