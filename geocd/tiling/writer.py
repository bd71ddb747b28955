"""The single writer: tile results → one tiled GeoTIFF → a Cloud-Optimized GeoTIFF, atomically.

Follows :func:`geocd.io.raster.write_cog`'s conventions (256-pixel blocks, DEFLATE,
average overviews at 2, 4, … 32 while the overview keeps ≥ 64 cells, band
descriptions and tags, NaN nodata for floats), so a tiled product and an untiled
one hold the same pixels. The tiled GeoTIFF is assembled in the work folder, block
by block (bounded memory); the COG is written to a hidden temporary file next to
the target and renamed onto it only when complete.
"""

from __future__ import annotations

import contextlib
import os
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from ..errors import DiskFullError
from ..faults import free_bytes
from ..geodesy import AOIGrid
from ..io.atomic import atomic_path
from ..io.outputs import OutputFolderWarning
from .grid import TileGrid
from .sources import GDAL_CACHE_MB
from .store import TileStore


@dataclass(frozen=True)
class RasterProduct:
    """A raster product assembled from tile arrays.

    Parameters
    ----------
    path : the COG to write
    bands : names of the tile arrays, one per band (each array 2-D on the tile core)
    dtype, nodata : as :func:`geocd.io.raster.write_cog` (NaN nodata for floats by default)
    descriptions : band descriptions (default: the array names; None entries: the file's stem, as
        :func:`geocd.io.raster.write_cog` names unnamed bands)
    units : one unit per band (default: from the descriptions, :func:`geocd.io.raster.band_unit`)
    tags, band_tags, colormap : as :func:`geocd.io.raster.write_cog`
    fill : band name → the value written on the cores of tiles the pass did not process (a
        :class:`~geocd.tiling.grid.TileGrid` with a selection); default the nodata value (0 without one)
    """

    path: str
    bands: tuple[str, ...]
    dtype: str = "float32"
    nodata: float | int | None = None
    descriptions: tuple[str | None, ...] | None = None
    units: tuple[str, ...] | None = None
    tags: Mapping[str, Any] = field(default_factory=dict)
    band_tags: Sequence[Mapping[str, Any]] | None = None
    colormap: Mapping[int, tuple] | None = None
    compress: str = "deflate"
    overview_resampling: str = "average"
    fill: Mapping[str, float] | None = None


def overview_factors(shape: tuple[int, int]) -> list[int]:
    """The overview levels :func:`geocd.io.raster.write_cog` builds for a grid of ``shape``."""
    return [f for f in (2, 4, 8, 16, 32) if min(shape) // f >= 64]


def assembly_bytes(product: RasterProduct, shape: tuple[int, int]) -> int:
    """Bytes of ``product`` on a grid of ``shape`` (rows, cols), uncompressed, its overviews included.

    The assembly GeoTIFF in the work folder is this size; the COG is this size divided by its
    compression ratio (DEFLATE: ~1.1–3 on float products, far more on masks).
    """
    cells = int(shape[0]) * int(shape[1])
    ov = sum(1.0 / (f * f) for f in overview_factors(shape))
    return int(cells * len(product.bands) * np.dtype(product.dtype).itemsize * (1.0 + ov))


def _device(path: Path) -> int | None:
    for q in (path, *path.parents):
        try:
            return os.stat(q).st_dev
        except OSError:
            continue
    return None


def check_assembly_room(
    product: RasterProduct, shape: tuple[int, int], work: Path, target: Path, compression: float = 4.0
) -> None:
    """Refuse to assemble ``product`` when the disk cannot hold it, before a byte is written.

    The assembly needs its uncompressed GeoTIFF in ``work`` and then the COG beside ``target``
    (both at once). Refused (:class:`~geocd.errors.DiskFullError`) when even a COG ``compression``
    times smaller than the uncompressed raster would not fit; warned about
    (:class:`~geocd.io.outputs.OutputFolderWarning`) when an incompressible one would not.
    """
    raw = assembly_bytes(product, shape)
    work, target = Path(work), Path(target)
    dev = _device(work)
    same = dev is not None and dev == _device(target.parent)
    needs = (
        [(work, raw + raw / compression, raw + raw)]
        if same
        else [(work, raw, raw), (target.parent, raw / compression, raw)]
    )
    gb = 1e9
    for where, low, high in needs:
        free = free_bytes(where)
        if free is None:
            continue
        if free < low:
            raise DiskFullError(
                f"not enough free disk to assemble {target.name}: it needs about {low / gb:,.1f} GB on the disk of "
                f"{where} (an uncompressed {len(product.bands)}-band {np.dtype(product.dtype).name} raster of "
                f"{shape[1]} x {shape[0]} cells with overviews while its COG is written), {free / gb:,.1f} GB are "
                f"free. The finished tiles are kept in {work.parent}: free some space and run the same command "
                "again; it resumes and only assembles the products"
            )
        if free < high:
            warnings.warn(
                f"assembling {target.name} may need up to {high / gb:,.1f} GB on the disk of {where} "
                f"(if it compresses poorly); {free / gb:,.1f} GB are free",
                OutputFolderWarning,
                stacklevel=3,
            )


def write_product(
    store: TileStore,
    product: RasterProduct,
    grid: AOIGrid | None = None,
    tile_grid: TileGrid | None = None,
    band_stores: Mapping[str, TileStore] | None = None,
) -> Path:
    """Assemble ``product`` from the tiles of ``store`` and write it as a COG (atomic).

    ``band_stores`` (band name → store) takes a band from another pass's store, read on each tile's
    core: a product can gather the arrays of several passes without a pass that copies them.
    """
    import rasterio
    from rasterio.enums import Resampling
    from rasterio.shutil import copy as rio_copy
    from rasterio.windows import Window

    tg = tile_grid or store.tile_grid
    g = grid or tg.grid
    dtype = product.dtype
    nodata = product.nodata
    if nodata is None and np.issubdtype(np.dtype(dtype), np.floating):
        nodata = float("nan")
    profile = g.rasterio_profile(dtype=dtype, count=len(product.bands), nodata=nodata)
    profile.update(tiled=True, blockxsize=256, blockysize=256, BIGTIFF="IF_SAFER")
    from ..io.raster import band_unit

    target = Path(product.path)
    names = list(product.descriptions or product.bands)
    if any(n is None for n in names):
        stem = target.stem
        names = [
            n if n is not None else (stem if len(names) == 1 else f"{stem}_{i}") for i, n in enumerate(names, start=1)
        ]
    units = list(product.units) if product.units is not None else [band_unit(n) for n in names]
    for i, bt in enumerate(product.band_tags or []):  # a "units" band tag is the unit too (as write_cog)
        if i < len(units) and not units[i] and bt and bt.get("units"):
            units[i] = str(bt["units"])
    check_assembly_room(product, g.shape, store.path, target)
    tmp_tif = store.path / f"{target.stem}.assemble.part.tif"
    with contextlib.suppress(OSError):
        tmp_tif.unlink()
    try:
        with rasterio.Env(GDAL_CACHEMAX=GDAL_CACHE_MB):
            with rasterio.open(tmp_tif, "w", **profile) as dst:
                for t in tg.all_tiles():  # tiles the pass did not process: the product's fill value
                    if tg.is_selected(t):
                        continue
                    r0, c0, h, w = t.core
                    for b, name in enumerate(product.bands, start=1):
                        fv = (product.fill or {}).get(name, nodata if nodata is not None else 0)
                        dst.write(np.full((h, w), fv, dtype), b, window=Window(c0, r0, w, h))
                for t in tg:  # processed tiles (or runs of tiles)
                    r0, c0, h, w = t.core
                    for b, name in enumerate(product.bands, start=1):
                        other = (band_stores or {}).get(name)
                        a = store.tile_array(t, name) if other is None else other.read(name, t.core)
                        a = np.asarray(a).astype(dtype, copy=False)
                        dst.write(a, b, window=Window(c0, r0, w, h))
                for i, nm in enumerate(names, start=1):
                    dst.set_band_description(i, str(nm))
                    if units[i - 1]:
                        dst.set_band_unit(i, units[i - 1])
                    bt = product.band_tags
                    if bt and i - 1 < len(bt) and bt[i - 1]:
                        dst.update_tags(i, **{k: str(v) for k, v in bt[i - 1].items()})
                if product.tags:
                    dst.update_tags(**{k: str(v) for k, v in product.tags.items()})
                if product.colormap is not None:
                    dst.write_colormap(1, product.colormap)
                ov = overview_factors(g.shape)
                if ov:
                    dst.build_overviews(ov, getattr(Resampling, product.overview_resampling))
            ovr = product.overview_resampling
            with atomic_path(target) as tmp:
                rio_copy(
                    str(tmp_tif),
                    str(tmp),
                    driver="COG",
                    compress=product.compress.upper(),
                    overview_resampling=ovr.upper() if ovr != "average" else "AVERAGE",
                    BIGTIFF="IF_SAFER",
                )
    finally:
        with contextlib.suppress(OSError):
            tmp_tif.unlink()
    return target
