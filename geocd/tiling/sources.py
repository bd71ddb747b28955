"""Lazy window readers: what a tile task reads, and only its own window.

A source is a small picklable object with ``read(grid, window) → ndarray``: it is
shipped to the worker that runs a tile, opens its file there and reads the tile's
read window only (rasterio windows; a GDAL warped VRT when the file is not on the
processing grid). Nothing is read on the client.
"""

from __future__ import annotations

import math
import os
import warnings
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import CRSError, ConfigError
from ..geodesy import AOIGrid
from ..io.raster import blank_non_heights

#: GDAL block cache per process while a tile reads or writes (MB): bounded memory
GDAL_CACHE_MB = 128


def _aligned_offset(src_grid: AOIGrid, grid: AOIGrid) -> tuple[int, int] | None:
    """(row, col) offset of ``grid``'s origin in ``src_grid`` when both share CRS and posting
    and the offset is a whole number of cells; else None."""
    if not src_grid.crs.equals(grid.crs, ignore_axis_order=True):
        return None
    a, b = src_grid.transform, grid.transform
    if not (math.isclose(a.a, b.a, rel_tol=1e-9) and math.isclose(a.e, b.e, rel_tol=1e-9)):
        return None
    c = (b.c - a.c) / a.a
    r = (b.f - a.f) / a.e
    if abs(c - round(c)) > 1e-6 or abs(r - round(r)) > 1e-6:
        return None
    return int(round(r)), int(round(c))


@dataclass(frozen=True)
class RasterSource:
    """One band of a raster file, read by window on the processing grid.

    Parameters
    ----------
    path : str
    band : int (1-based)
    resampling : how the file is resampled when it is not on the processing grid
        (GDAL warped VRT); on the grid (same CRS and posting, whole-cell offset) windows
        are read as they are
    dem : apply :func:`geocd.io.raster.read_dem`'s rules (nodata, and values that are not heights → NaN:
        :func:`~geocd.io.raster.blank_non_heights`; the file is checked up front by
        :func:`~geocd.io.raster.check_dem_file`); otherwise nodata → NaN only
    nodata : the file's nodata value when it does not declare it (``--nodata``); None: the file's own
    """

    path: str
    band: int = 1
    resampling: str = "bilinear"
    dem: bool = False
    nodata: float | None = None

    def read(self, grid: AOIGrid, window: tuple[int, int, int, int]) -> np.ndarray:
        """float32 (h, w) values of ``window`` (row0, col0, h, w) of ``grid``; NaN = nodata/outside."""
        import rasterio
        from rasterio.windows import Window

        from ..io.raster import _open

        r0, c0, h, w = window
        with rasterio.Env(GDAL_CACHEMAX=GDAL_CACHE_MB), _open(self.path) as ds:
            if ds.crs is None:
                raise CRSError(f"{self.path} has no CRS; assign one (gdal_edit.py -a_srs EPSG:...) before tiling it")
            nodata = ds.nodata if self.nodata is None else self.nodata
            src_grid = AOIGrid.from_raster(ds)
            off = _aligned_offset(src_grid, grid)
            if off is not None:
                from rasterio.enums import MaskFlags

                win = Window(c0 + off[1], r0 + off[0], w, h)
                inside = (
                    off[0] + r0 >= 0
                    and off[1] + c0 >= 0
                    and off[0] + r0 + h <= ds.height
                    and off[1] + c0 + w <= ds.width
                )
                flags = set(ds.mask_flag_enums[self.band - 1])
                if inside and flags <= {MaskFlags.nodata, MaskFlags.all_valid}:
                    # the mask is the nodata value (handled below) or nothing: a plain read, half the work
                    out = ds.read(self.band, window=win).astype(np.float32)
                else:
                    a = ds.read(self.band, window=win, masked=True, boundless=not inside)
                    out = np.ma.filled(a.astype(np.float32), np.nan)
            else:
                out = self._warped(ds, grid, window, nodata)
        if self.dem:
            return blank_non_heights(out, nodata)
        if nodata is not None and np.isfinite(nodata):
            out[out == np.float32(nodata)] = np.nan
        return out

    def _warped(self, ds, grid: AOIGrid, window, nodata: float | None) -> np.ndarray:
        from rasterio.crs import CRS as RioCRS
        from rasterio.enums import Resampling
        from rasterio.vrt import WarpedVRT
        from rasterio.windows import Window

        from ..io.raster import RESAMPLING

        if self.resampling not in RESAMPLING:
            raise ConfigError(f"resampling must be one of {RESAMPLING}, got {self.resampling!r}")
        r0, c0, h, w = window
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            with WarpedVRT(
                ds,
                crs=RioCRS.from_wkt(grid.crs.to_wkt()),
                transform=grid.transform,
                width=grid.width,
                height=grid.height,
                resampling=getattr(Resampling, self.resampling),
                src_nodata=nodata,
                nodata=np.nan,
                dtype="float32",
            ) as vrt:
                return vrt.read(self.band, window=Window(c0, r0, w, h)).astype(np.float32)

    def identity(self) -> dict[str, Any]:
        """What makes this input this input (for the resume key): path, size, mtime, band."""
        st = os.stat(self.path)
        return {
            "path": os.path.abspath(self.path),
            "size": st.st_size,
            "mtime_ns": st.st_mtime_ns,
            "band": self.band,
            "resampling": self.resampling,
            "dem": self.dem,
            "nodata": self.nodata,
        }


@dataclass(frozen=True)
class ArraySource:
    """An in-memory array on the processing grid (small scenes, tests, sequential runs).

    With a process or cluster scheduler the whole array travels with every task: use a
    file (:class:`RasterSource`) for anything large.
    """

    array: np.ndarray

    def read(self, grid: AOIGrid, window: tuple[int, int, int, int]) -> np.ndarray:
        r0, c0, h, w = window
        if self.array.shape[-2:] != grid.shape:
            raise ConfigError(f"array {self.array.shape} is not on the processing grid {grid.shape}")
        return np.array(self.array[..., r0 : r0 + h, c0 : c0 + w])

    def identity(self) -> dict[str, Any]:
        import hashlib

        a = np.ascontiguousarray(self.array)
        return {"array_sha1": hashlib.sha1(a.view(np.uint8)).hexdigest(), "dtype": str(a.dtype), "shape": a.shape}
