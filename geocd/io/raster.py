"""Raster input and output.

* Images keep their native dtype (uint8, uint16 11-bit, multi-band) with a valid
  mask; DEMs are float32 with NaN for nodata.
* Every writer is atomic (:mod:`geocd.io.atomic`); products are Cloud-Optimized
  GeoTIFFs with band descriptions and tags.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from ..errors import (
    CRSError,
    EmptyDataError,
    InputFileNotFoundError,
    OutputError,
    UnsupportedFormatError,
    VerticalDatumError,
)
from ..geodesy import EGM96, EGM2008, ELLIPSOID, AOIGrid, as_crs, normalize_datum_name, vertical_datum_of
from .atomic import atomic_path, refuse_special_file

#: vertical datums a user may name (``--datum``, manifest ``vertical_datum``)
VERTICAL_DATUMS = (ELLIPSOID, EGM96, EGM2008)
#: plausible terrain heights, metres (deepest ocean floor .. above Everest); a DEM with more than 1 % of its
#: cells outside is refused as not being heights in metres
HEIGHT_RANGE_M = (-11_500.0, 9_500.0)
_HEIGHT_BAND_NAMES = ("z", "z_m", "height", "height_m", "elevation", "dem", "dsm", "dtm", "h", "alt", "altitude")
#: values DEM producers write for "no data" without always declaring it (ESRI, SRTM, USGS, GDAL's float extremes)
KNOWN_SENTINELS = (
    -9999.0,
    -99999.0,
    -32768.0,
    -32767.0,
    32767.0,
    65535.0,
    -1e10,
    -1e20,
    1e20,
    -1e30,
    1e30,
    float(np.finfo(np.float32).min),
    float(np.finfo(np.float32).max),
)
#: an undeclared nodata value stands this far (m) beyond every other value of the DEM: real terrain, sampled densely,
#: leaves no empty kilometre in its height histogram beside its lowest or highest value (checked on every DEM in
#: ../shared/data, tests/io/test_dem_checks.py)
SENTINEL_GAP_M = 1000.0
#: an extreme value not among :data:`KNOWN_SENTINELS` counts as a sentinel only when this share of the cells holds it
SENTINEL_MIN_SHARE = 1e-4
#: out-of-range heights (beyond :data:`HEIGHT_RANGE_M`, or ±inf) up to this share are blanked with a warning; more:
#: the raster is refused as not heights in metres
OUT_OF_RANGE_MAX_SHARE = 0.01
#: cells read to check a DEM's values (a larger DEM is checked on evenly spaced strips of whole rows, at full
#: resolution: never an overview, whose averages would hide an exact sentinel)
CHECK_CELLS = 4_000_000


#: band units (GDAL's unit type) of heights that are not metres → the factor to metres
_NON_METRE_UNITS = {
    "ft": 0.3048,
    "feet": 0.3048,
    "foot": 0.3048,
    "international foot": 0.3048,
    "us-ft": 0.3048006096,
    "ftus": 0.3048006096,
    "us survey foot": 0.3048006096,
    "us_survey_foot": 0.3048006096,
    "cm": 0.01,
    "centimetre": 0.01,
    "centimeter": 0.01,
    "centimetres": 0.01,
    "centimeters": 0.01,
    "mm": 0.001,
    "millimetre": 0.001,
    "millimeter": 0.001,
    "dm": 0.1,
    "decimetre": 0.1,
    "decimeter": 0.1,
}
_UNIT_NAMES = {
    0.3048: "feet",
    0.3048006096: "US survey feet",
    0.01: "centimetres",
    0.001: "millimetres",
    0.1: "decimetres",
}


class DEMValueWarning(UserWarning):
    """A DEM held a few values that are not heights (out of range, infinite); they were treated as nodata."""


def check_vertical_datum(name: str | None, where: str = "vertical datum") -> str | None:
    """A vertical datum name geocd knows (ellipsoid, egm96, egm2008 and their aliases), normalised; None passes.

    Raises
    ------
    VerticalDatumError
    """
    if name is None or str(name).strip() == "":
        return None
    n = normalize_datum_name(name)
    if n not in VERTICAL_DATUMS:
        import difflib

        close = difflib.get_close_matches(
            str(name).lower(), ["ellipsoid", "ellipsoidal", "wgs84", "egm96", "egm2008"], n=1, cutoff=0.5
        )
        hint = f"; did you mean {close[0]!r}?" if close else ""
        raise VerticalDatumError(
            f"{where}: unknown vertical datum {name!r}; use ellipsoid (WGS84 ellipsoidal "
            f"heights), egm96 or egm2008{hint}"
        )
    return n


def _read_failure(path, exc: Exception) -> UnsupportedFormatError:
    """A rasterio/GDAL failure while reading pixels: the file is truncated or corrupt."""
    msg = " ".join(str(exc).split())[:200]
    return UnsupportedFormatError(
        f"cannot read the pixels of {path} ({msg}); the file is truncated or corrupt: copy or export it again"
    )


RESAMPLING = ("nearest", "bilinear", "cubic", "average", "min", "max", "med")


def _open(path: os.PathLike | str):
    import rasterio
    from rasterio.errors import RasterioError, RasterioIOError

    p = Path(path)
    if not p.exists() and "://" not in str(path) and not str(path).startswith("/vsi"):
        raise InputFileNotFoundError(f"raster {p} does not exist; check the path")
    refuse_special_file(path, "raster")
    try:
        import warnings

        from rasterio.errors import NotGeoreferencedWarning

        with warnings.catch_warnings():
            # images with RPCs or crop-offset geotransforms are legitimately "not georeferenced"
            warnings.simplefilter("ignore", NotGeoreferencedWarning)
            return rasterio.open(p)
    except RasterioIOError as exc:
        raise UnsupportedFormatError(
            f"cannot read {p} as a raster ({exc}); give a GeoTIFF or another GDAL format"
        ) from exc
    except (RasterioError, UnicodeError, ValueError, OverflowError) as exc:
        # a corrupt header: rasterio fails decoding a CRS citation, a tag, a metadata string
        raise UnsupportedFormatError(
            f"cannot read {p} as a raster: its header is corrupt ({type(exc).__name__}: "
            f"{' '.join(str(exc).split())[:120]}); copy or export the file again"
        ) from exc


@dataclass
class Image:
    """An image as geocd sees it.

    Attributes
    ----------
    data : ndarray, shape (bands, rows, cols), native dtype
    valid : ndarray of bool, shape (rows, cols); False where any band is nodata
    path : str
    bit_depth : int
        Effective bits per sample (8 for uint8; 11 for 11-bit data in uint16, ...).
    crs, transform : georeference of the file when it has one (may be None)
    """

    data: np.ndarray
    valid: np.ndarray
    path: str = ""
    bit_depth: int = 8
    crs: Any = None
    transform: Any = None
    tags: dict = field(default_factory=dict)

    @property
    def bands(self) -> int:
        return self.data.shape[0]

    @property
    def shape(self) -> tuple[int, int]:
        return self.data.shape[1:]

    def gray(self) -> np.ndarray:
        """float32 (rows, cols) mean over bands (NaN where invalid)."""
        g = self.data.astype(np.float32).mean(axis=0)
        g[~self.valid] = np.nan
        return g


def effective_bit_depth(data: np.ndarray, tags: Mapping[str, str] | None = None) -> int:
    """Bits per sample: NBITS metadata when present, else from the dtype and the data range."""
    if tags:
        for k in ("NBITS", "nbits"):
            if k in tags:
                try:
                    return int(tags[k])
                except ValueError:
                    pass
    if data.dtype == np.uint8:
        return 8
    if np.issubdtype(data.dtype, np.integer):
        mx = int(data.max()) if data.size else 0
        return max(8, int(np.ceil(np.log2(mx + 1)))) if mx > 0 else 8
    return 32


def read_image(path: os.PathLike | str, window: Any = None, bands: Sequence[int] | None = None) -> Image:
    """Read an image (all bands by default) with its valid mask and bit depth."""
    from rasterio.errors import RasterioError

    with _open(path) as ds:
        idx = list(bands) if bands is not None else list(range(1, ds.count + 1))
        try:
            data = ds.read(idx, window=window)
            masks = ds.read_masks(idx, window=window)
        except RasterioError as exc:
            raise _read_failure(path, exc) from exc
        valid = np.all(masks > 0, axis=0)
        tags = ds.tags(1) | ds.tags(1, "IMAGE_STRUCTURE") if ds.count else {}
        bit_depth = effective_bit_depth(data[:, valid] if valid.any() else data, tags)
        crs = ds.crs
        transform = ds.transform
    if not valid.any():
        raise EmptyDataError(f"image {path} is entirely nodata; check the file or its nodata value")
    return Image(data=data, valid=valid, path=str(path), bit_depth=bit_depth, crs=crs, transform=transform, tags=tags)


@dataclass
class DEM:
    """A DEM on a grid: float32 heights (NaN = nodata) with its vertical datum.

    Attributes
    ----------
    height_m : ndarray float32 (rows, cols)
    grid : AOIGrid
    vertical_datum : str or None
        "ellipsoid", "egm96", "egm2008", another datum name, or None (unknown).
    path : str
    """

    height_m: np.ndarray
    grid: AOIGrid
    vertical_datum: str | None = None
    path: str = ""

    @property
    def valid(self) -> np.ndarray:
        return np.isfinite(self.height_m)

    def to_ellipsoidal(self, *, allow_substitute: bool = False) -> "DEM":
        """The same DEM with WGS84 ellipsoidal heights (geoid grid needed for EGM heights)."""
        from ..geodesy import ELLIPSOID, to_ellipsoidal

        if self.vertical_datum in (None, ELLIPSOID):
            return self
        lon, lat = self.grid.lonlat()
        h = to_ellipsoidal(self.height_m, lon, lat, self.vertical_datum, allow_substitute=allow_substitute)
        return DEM(h.astype(np.float32), self.grid, ELLIPSOID, self.path)


def undeclared_nodata(values: np.ndarray) -> list[tuple[float, int, float]]:
    """Values of a DEM that are nodata markers, not heights: ``[(value, cells, gap_m), ...]``.

    A sentinel is the lowest or highest value of the DEM, standing more than :data:`SENTINEL_GAP_M` from every
    other value, and either a value producers use for nodata (:data:`KNOWN_SENTINELS`) or held by at least
    :data:`SENTINEL_MIN_SHARE` of the cells. Peeled from both ends, so −9999 and −3.4e38 are both found.

    Parameters
    ----------
    values : ndarray
        The DEM's values (any shape; NaN and ±inf are ignored), declared nodata already removed.
    """
    v = np.asarray(values, np.float64).ravel()
    v = v[np.isfinite(v)]
    if v.size < 2:
        return []
    u, counts = np.unique(v, return_counts=True)
    known = {float(np.float32(k)) for k in KNOWN_SENTINELS}
    found = []
    lo, hi = 0, u.size - 1
    while hi > lo:
        progressed = False
        for end in ("low", "high"):
            if hi <= lo:
                break
            i, j = (lo, lo + 1) if end == "low" else (hi, hi - 1)
            c, gap = float(u[i]), abs(float(u[j] - u[i]))
            if gap > SENTINEL_GAP_M and (
                float(np.float32(c)) in known or counts[i] >= max(2, SENTINEL_MIN_SHARE * v.size)
            ):
                found.append((c, int(counts[i]), gap))
                lo, hi = (lo + 1, hi) if end == "low" else (lo, hi - 1)
                progressed = True
        if not progressed:
            break
    return found


def _fmt_value(v: float, dtype: str = "float64") -> str:
    """A raster value as the user types it back: float32 values at float32 precision (1e+30, not 1.00000002e+30)."""
    if dtype == "float32":
        s = str(np.float32(v))
        return s[:-2] if s.endswith(".0") else s
    return f"{v:.9g}"


def _check_dem_values(ds, path, band: int, nodata: float | None) -> None:
    """Refuse a DEM whose values are not heights in metres, before anything is computed from it.

    On the file's own values (before any resampling mixes a sentinel into its neighbours): undeclared nodata
    sentinels (:func:`undeclared_nodata`) are refused with the ``--nodata`` fix; more than
    :data:`OUT_OF_RANGE_MAX_SHARE` of values beyond :data:`HEIGHT_RANGE_M` (or infinite) are refused as not metres;
    fewer are reported (:class:`DEMValueWarning`) and read as nodata.
    """
    import warnings

    from rasterio.errors import RasterioError

    unit = str((ds.units or [None] * ds.count)[band - 1] or "").strip().lower()
    factor = _NON_METRE_UNITS.get(unit)
    if factor is not None:
        raise UnsupportedFormatError(
            f"DEM {path}: its band unit is {unit!r} ({_UNIT_NAMES.get(factor, unit)}); geocd needs heights in metres: "
            f"convert it (gdal_calc.py -A {path} --calc 'A*{factor:g}' --outfile dem_m.tif) and give that file"
        )
    # the file's own values at full resolution: a decimated read would take an overview, whose averages hide an
    # exact sentinel. A large DEM is read as evenly spaced strips of whole rows (every column is seen).
    rows_wanted = max(1, CHECK_CELLS // max(ds.width, 1))
    strip = 8
    step = max(1, int(np.ceil(ds.height / rows_wanted)))
    if step == 1:
        windows = [None]
    else:
        from rasterio.windows import Window

        windows = [Window(0, r, ds.width, min(strip, ds.height - r)) for r in range(0, ds.height, step * strip)]
    try:
        parts = [ds.read(band, masked=nodata is None, window=w) for w in windows]
    except RasterioError as exc:
        raise _read_failure(path, exc) from exc
    with np.errstate(invalid="ignore"):  # a garbled file's masked values may not cast cleanly: they are masked
        h = np.concatenate(
            [
                (np.ma.filled(a.astype(np.float64), np.nan) if np.ma.isMaskedArray(a) else a.astype(np.float64))
                for a in parts
            ]
        )
    if nodata is not None:  # compared as the file stores it (a float32 file holds float32(-3.4028235e38))
        h[h == (float(np.float32(nodata)) if ds.dtypes[band - 1] == "float32" else float(nodata))] = np.nan
    sample = "" if step == 1 else f" (checked on strips of whole rows, 1 row in {step})"
    sentinels = undeclared_nodata(h)
    if sentinels:
        finite = np.isfinite(h).sum()
        dt = ds.dtypes[band - 1]
        said = "; ".join(
            f"{_fmt_value(c, dt)} in {100 * k / max(finite, 1):.2g} % of its cells ({gap:,.0f} m beyond "
            "every other value)"
            for c, k, gap in sentinels
        )
        v0 = _fmt_value(sentinels[0][0], dt)
        declared = f" (its declared nodata is {_fmt_value(ds.nodata, dt)})" if ds.nodata is not None else ""
        raise UnsupportedFormatError(
            f"DEM {path} holds undeclared nodata values, not heights{declared}: {said}{sample}. Declare the "
            f"value in the file (gdal_edit.py -a_nodata {v0} {path}), or with geocd demdiff: --nodata {v0} "
            "(nodata= in Python)"
        )
    valid = ~np.isnan(h)
    lo, hi = HEIGHT_RANGE_M
    with np.errstate(invalid="ignore"):
        bad = valid & ((h < lo) | (h > hi))
    share = float(bad.sum()) / max(int(valid.sum()), 1)
    if share > OUT_OF_RANGE_MAX_SHARE:
        v = h[valid & np.isfinite(h)]
        rng = f" (range {np.min(v):g} .. {np.max(v):g})" if v.size else ""
        raise UnsupportedFormatError(
            f"DEM {path}: {100 * share:.0f}% of its values lie outside {lo:g}..{hi:g} m or are infinite{rng}"
            f"{sample}; these are not terrain heights in metres (feet? centimetres? an undeclared nodata value?): "
            "convert the DEM to metres or declare its nodata value (--nodata)"
        )
    if bad.any():
        warnings.warn(
            f"DEM {path}: {int(bad.sum())} value(s) ({100 * share:.2g} % of its cells{sample}) lie outside "
            f"{lo:g}..{hi:g} m or are infinite; they are read as nodata",
            DEMValueWarning,
            stacklevel=3,
        )


def check_dem_file(path: os.PathLike | str, band: int = 1, nodata: float | None = None) -> int:
    """Every check :func:`read_dem` makes on a DEM file, without reading it whole: a CRS, one band of real
    heights (not an image, not complex), values that are heights in metres with no undeclared nodata. For paths
    that read the DEM tile by tile; returns the band.

    Raises
    ------
    CRSError, UnsupportedFormatError, InputFileNotFoundError
    """
    with _open(path) as ds:
        if ds.crs is None:
            raise CRSError(f"DEM {path} has no CRS; assign one (gdal_edit.py -a_srs EPSG:...) before using it")
        band = _check_dem_like(ds, path, band)
        _check_dem_values(ds, path, band, nodata)
    return band


def blank_non_heights(h: np.ndarray, nodata: float | None = None) -> np.ndarray:
    """``h`` (float32, in place) with the declared ``nodata`` and values that are not heights (beyond
    :data:`HEIGHT_RANGE_M`, ±inf; checked and reported by :func:`check_dem_file`) set to NaN."""
    if nodata is not None and np.isfinite(nodata):
        h[h == np.float32(nodata)] = np.nan
    lo, hi = HEIGHT_RANGE_M
    with np.errstate(invalid="ignore"):
        h[~np.isfinite(h) | (h < lo) | (h > hi)] = np.nan
    return h


def read_dem(
    path: os.PathLike | str,
    grid: AOIGrid | None = None,
    resampling: str = "bilinear",
    vertical_datum: str | None = None,
    band: int = 1,
    nodata: float | None = None,
) -> DEM:
    """Read a DEM: float32 heights, nodata → NaN, optionally resampled onto ``grid``.

    Parameters
    ----------
    grid : AOIGrid, optional
        Target grid; the DEM is reprojected/resampled onto it (cells outside the
        DEM become NaN).
    resampling : str
        One of :data:`RESAMPLING` (explicit; bilinear by default for heights).
    vertical_datum : str, optional
        Overrides the datum read from the file's CRS ("ellipsoid", "egm96", ...).
        SRTM .hgt tiles carry no vertical CRS but are EGM96 by specification:
        declare it.
    nodata : float, optional
        The DEM's nodata value when the file does not declare it (or declares another): ``--nodata``. A DEM
        holding an undeclared nodata value (−9999, −32768, −3.4e38, ...) is refused without it.

    Raises
    ------
    UnsupportedFormatError
        Not a DEM (an image, complex values), undeclared nodata values, or more than 1 % of values that are not
        heights in metres (a few are read as nodata, with a :class:`DEMValueWarning`).
    """
    from rasterio.errors import RasterioError

    vertical_datum = check_vertical_datum(vertical_datum, f"DEM {path}")
    if nodata is not None and not np.isfinite(nodata) and not np.isnan(nodata):
        raise UnsupportedFormatError(f"nodata {nodata} for DEM {path}: give a finite value (or nan)")
    with _open(path) as ds:
        if ds.crs is None:
            raise CRSError(f"DEM {path} has no CRS; assign one (gdal_edit.py -a_srs EPSG:...) before using it")
        band = _check_dem_like(ds, path, band)
        vd = vertical_datum or vertical_datum_of(ds.crs)
        if grid is not None:
            _check_dem_covers(ds, path, grid)
        _check_read_memory(path, grid.shape if grid is not None else (ds.height, ds.width), grid)
        _check_dem_values(ds, path, band, nodata)
        nodata = ds.nodata if nodata is None else nodata
        try:
            if grid is None:
                arr = ds.read(band, masked=True).astype(np.float32)
                h = arr.filled(np.nan)
                g = AOIGrid(as_crs(ds.crs), ds.transform, ds.width, ds.height)
            else:
                h = reproject_band(ds, band, grid, resampling, nodata=nodata, heights=True)
                g = grid
        except RasterioError as exc:
            raise _read_failure(path, exc) from exc
    blank_non_heights(h, nodata)
    if not np.isfinite(h).any():
        where = "on the requested grid" if grid is not None else ""
        raise EmptyDataError(
            f"DEM {path} has no valid heights {where}(all nodata); check its nodata value and that it covers the AOI"
        )
    return DEM(h, g, vd, str(path))


def _check_dem_like(ds, path, band: int) -> int:
    """Refuse rasters that are not DEMs: images (8-bit, RGB/palette, several bands), complex values."""
    from rasterio.enums import ColorInterp

    dtypes = set(ds.dtypes)
    interp = list(ds.colorinterp or [])
    looks = f"{ds.count} band(s) of {ds.dtypes[0]}"
    if not 1 <= band <= ds.count:
        raise UnsupportedFormatError(f"DEM {path} has {ds.count} band(s); band {band} does not exist")
    rgb = {ColorInterp.red, ColorInterp.green, ColorInterp.blue, ColorInterp.palette, ColorInterp.alpha}
    if dtypes & {"uint8", "int8", "bool"} or (interp and interp[band - 1] in rgb):
        raise UnsupportedFormatError(
            f"{path} is not a DEM: it holds {looks}"
            f"{' (' + '/'.join(c.name for c in interp[:4]) + ')' if interp else ''}, an image rather than heights. "
            "Give a single-band elevation raster (float or 16/32-bit integer heights in metres)"
        )
    if any(d.startswith("complex") for d in dtypes):
        raise UnsupportedFormatError(f"{path} holds complex values ({looks}); a DEM holds real heights in metres")
    if ds.count > 1:
        names = [str(d or "").strip().lower() for d in ds.descriptions]
        if names[band - 1] not in _HEIGHT_BAND_NAMES:
            raise UnsupportedFormatError(
                f"DEM {path} has {ds.count} bands and band {band} is not named as heights "
                f"({names[band - 1] or 'no description'}); a DEM has one band of heights: extract it first "
                "(gdal_translate -b N in.tif dem.tif)"
            )
    return band


def _check_read_memory(path, shape: tuple[int, int], grid: AOIGrid | None = None, bytes_per_cell: int = 13) -> None:
    """Refuse to read a raster that cannot fit (float32 heights, a mask, a working copy per cell)."""
    from .outputs import check_resources

    rows, cols = int(shape[0]), int(shape[1])
    if grid is None:
        what = f"reading {path} ({cols} x {rows} cells)"
        fix = "crop it to the area of interest first (gdal_translate -projwin ...) or resample it coarser"
    else:
        what = f"the AOI grid ({cols} x {rows} cells at {grid.posting_m:g} m, reading {Path(path).name} onto it)"
        fix = "use a coarser posting or a smaller AOI"
    check_resources(what, memory_bytes=rows * cols * bytes_per_cell, fix=fix)


def _check_dem_covers(ds, path, grid: AOIGrid) -> None:
    """A DEM that does not reach the AOI at all: say so, with the distance (not 'all nodata')."""
    from rasterio.warp import transform_bounds

    from ..errors import NoOverlapError

    try:
        l, b, r, t = transform_bounds(ds.crs, grid.crs.to_wkt(), *ds.bounds, densify_pts=21)
    except Exception:  # noqa: BLE001 - a CRS pair rasterio cannot transform: let the read decide
        return
    gl, gb, gr, gt = grid.bounds
    dx = max(gl - r, l - gr, 0.0)
    dy = max(gb - t, b - gt, 0.0)
    if dx > 0 or dy > 0:
        d = float(np.hypot(dx, dy))
        raise NoOverlapError(
            f"DEM {path} does not cover the AOI: it ends {d / 1000:.1f} km from it (DEM bounds "
            f"{tuple(round(x, 1) for x in (l, b, r, t))}, AOI {tuple(round(x, 1) for x in grid.bounds)} in the AOI's "
            "CRS); give a DEM of this area, or check the AOI (aoi.bounds / aoi.crs)"
        )


def reproject_band(
    ds, band: int, grid: AOIGrid, resampling: str = "bilinear", nodata: float | None = None, heights: bool = False
) -> np.ndarray:
    """Reproject one band of an open dataset onto ``grid`` (float32, NaN outside/nodata; ``nodata`` overrides
    the file's nodata value; ``heights``: values that are not heights are nodata too, before they are resampled
    into their neighbours)."""
    from rasterio.crs import CRS as RioCRS
    from rasterio.enums import Resampling
    from rasterio.warp import reproject

    if resampling not in RESAMPLING:
        raise ValueError(f"resampling must be one of {RESAMPLING}, got {resampling!r}")
    out = np.full(grid.shape, np.nan, dtype=np.float32)
    src = ds.read(band).astype(np.float32)
    nodata = ds.nodata if nodata is None else nodata
    if heights:
        blank_non_heights(src, nodata)
    elif nodata is not None and np.isfinite(nodata):
        src[src == np.float32(nodata)] = np.nan
    reproject(
        src,
        out,
        src_transform=ds.transform,
        src_crs=ds.crs,
        src_nodata=np.nan,
        dst_transform=grid.transform,
        dst_crs=RioCRS.from_wkt(grid.crs.to_wkt()),
        dst_nodata=np.nan,
        resampling=getattr(Resampling, resampling),
    )
    return out


def reproject_array(
    array: np.ndarray, src_grid: AOIGrid, dst_grid: AOIGrid, resampling: str = "bilinear"
) -> np.ndarray:
    """Reproject a float array from one grid to another (NaN = nodata)."""
    from rasterio.crs import CRS as RioCRS
    from rasterio.enums import Resampling
    from rasterio.warp import reproject

    out = np.full(dst_grid.shape, np.nan, dtype=np.float32)
    reproject(
        array.astype(np.float32),
        out,
        src_transform=src_grid.transform,
        src_crs=RioCRS.from_wkt(src_grid.crs.to_wkt()),
        src_nodata=np.nan,
        dst_transform=dst_grid.transform,
        dst_crs=RioCRS.from_wkt(dst_grid.crs.to_wkt()),
        dst_nodata=np.nan,
        resampling=getattr(Resampling, resampling),
    )
    return out


def band_unit(name: str) -> str:
    """The unit a band name says by geocd's naming convention ("" when it says none)."""
    n = name.lower()
    for suffix, unit in (
        ("_m3", "m3"),
        ("_m2", "m2"),
        ("_m", "m"),
        ("_px", "px"),
        ("_deg", "degree"),
        ("_pct", "%"),
        ("_s", "s"),
    ):
        if n.endswith(suffix):
            return unit
    if "confidence" in n:
        return "%"
    if n in ("probability", "change_probability", "coverage", "vis_inf", "ncc", "valid"):
        return "1"
    return ""


def write_cog(
    path: os.PathLike | str,
    bands: np.ndarray | Mapping[str, np.ndarray],
    grid: AOIGrid,
    *,
    nodata: float | int | None = None,
    dtype: str | None = None,
    tags: Mapping[str, Any] | None = None,
    band_tags: Sequence[Mapping[str, Any]] | None = None,
    overwrite: bool = True,
    compress: str = "deflate",
    colormap: Mapping[int, tuple] | None = None,
    overview_resampling: str = "average",
    mask: np.ndarray | None = None,
    units: Mapping[str, str] | Sequence[str] | None = None,
) -> Path:
    """Write a Cloud-Optimized GeoTIFF atomically.

    Every band gets a description (what QGIS shows as its name) and, where known, a unit
    (GDAL's band unit type, what ``gdalinfo`` prints as "Unit Type").

    Parameters
    ----------
    bands : ndarray (rows, cols) or (bands, rows, cols), or mapping name → 2-D array
        Mapping keys become band descriptions; unnamed bands are described by the file's
        stem (and their number when there are several).
    grid : AOIGrid
    nodata : number, optional
        NaN in float data is nodata by default.
    tags : mapping, optional
        Dataset metadata (e.g. method, provenance JSON).
    mask : bool ndarray (rows, cols), optional
        Written as the GDAL internal mask band (False = nodata, transparent in QGIS):
        for integer images whose every value is legitimate data.
    units : mapping name → unit, or one unit per band, optional
        Band units; default: from the band names' suffixes (:func:`band_unit`: ``_m`` → m,
        ``confidence`` → %, ...).
    """
    from rasterio.io import MemoryFile
    from rasterio.shutil import copy as rio_copy

    if isinstance(bands, Mapping):
        names = list(bands.keys())
        arr = np.stack([np.asarray(bands[k]) for k in names])
    else:
        arr = np.asarray(bands)
        if arr.ndim == 2:
            arr = arr[None]
        stem = Path(path).stem
        names = [stem] if arr.shape[0] == 1 else [f"{stem}_{i}" for i in range(1, arr.shape[0] + 1)]
    if isinstance(units, Mapping):
        unit_list = [units.get(n, band_unit(n)) for n in names]
    elif units is not None:
        unit_list = [str(u) for u in units]
    else:
        unit_list = [band_unit(n) for n in names]
    for i, bt in enumerate(band_tags or []):  # a "units" band tag (stereo products) is the unit too
        if i < len(unit_list) and not unit_list[i] and bt and bt.get("units"):
            unit_list[i] = str(bt["units"])
    if (
        len(unit_list) == 1
        and not unit_list[0]
        and tags
        and tags.get("units")
        and np.issubdtype(np.dtype(dtype or arr.dtype), np.floating)
    ):  # one float band: the dataset's unit
        unit_list[0] = {"metre": "m", "meter": "m", "metres": "m"}.get(str(tags["units"]), str(tags["units"]))
    if arr.shape[1:] != grid.shape:
        raise OutputError(f"array shape {arr.shape[1:]} does not match the grid {grid.shape}")
    dtype = dtype or str(arr.dtype)
    if nodata is None and np.issubdtype(np.dtype(dtype), np.floating):
        nodata = float("nan")
    profile = grid.rasterio_profile(dtype=dtype, count=arr.shape[0], nodata=nodata)
    profile.update(tiled=True, blockxsize=256, blockysize=256)
    with atomic_path(path, overwrite=overwrite) as tmp:
        with MemoryFile() as mem:
            with mem.open(**profile) as dst:
                dst.write(arr.astype(dtype))
                for i, name in enumerate(names, start=1):
                    dst.set_band_description(i, str(name))
                    if i - 1 < len(unit_list) and unit_list[i - 1]:
                        dst.set_band_unit(i, unit_list[i - 1])
                    if band_tags and i - 1 < len(band_tags) and band_tags[i - 1]:
                        dst.update_tags(i, **{k: str(v) for k, v in band_tags[i - 1].items()})
                if tags:
                    dst.update_tags(**{k: str(v) for k, v in tags.items()})
                if colormap is not None:
                    dst.write_colormap(1, colormap)
                if mask is not None:
                    if mask.shape != grid.shape:
                        raise OutputError(f"mask shape {mask.shape} does not match the grid {grid.shape}")
                    dst.write_mask(np.where(mask, 255, 0).astype(np.uint8))
                ov = [f for f in (2, 4, 8, 16, 32) if min(grid.shape) // f >= 64]
                if ov:
                    from rasterio.enums import Resampling

                    dst.build_overviews(ov, getattr(Resampling, overview_resampling))
            rio_copy(
                mem.open(),
                str(tmp),
                driver="COG",
                compress=compress.upper(),
                overview_resampling=overview_resampling.upper() if overview_resampling != "average" else "AVERAGE",
            )
    return Path(path)


def write_image(
    path: os.PathLike | str,
    data: np.ndarray,
    *,
    rpc=None,
    crs: Any = None,
    transform: Any = None,
    nodata: float | int | None = None,
    nbits: int | None = None,
    tags: Mapping[str, Any] | None = None,
    overwrite: bool = True,
    photometric: str | None = None,
) -> Path:
    """Write a (bands, rows, cols) image as GeoTIFF atomically, optionally with RPC tags.

    Parameters
    ----------
    rpc : RPCModel, optional
        Written as GeoTIFF RPC tags (``RPCCoefficientTag``), readable by GDAL.
    nbits : int, optional
        e.g. 11 for 11-bit data in uint16 (sets the NBITS creation option).
    """
    import rasterio

    arr = np.asarray(data)
    if arr.ndim == 2:
        arr = arr[None]
    profile: dict[str, Any] = {
        "driver": "GTiff",
        "width": arr.shape[2],
        "height": arr.shape[1],
        "count": arr.shape[0],
        "dtype": str(arr.dtype),
        "compress": "deflate",
        "tiled": True,
        "blockxsize": 256,
        "blockysize": 256,
    }
    if nodata is not None:
        profile["nodata"] = nodata
    if crs is not None:
        profile["crs"] = crs
    if transform is not None:
        profile["transform"] = transform
    if nbits is not None:
        profile["nbits"] = int(nbits)
    if photometric is not None:
        profile["photometric"] = photometric
    if rpc is not None:
        profile["rpcs"] = rpc.to_rasterio()
    with atomic_path(path, overwrite=overwrite) as tmp:
        import warnings

        from rasterio.errors import NotGeoreferencedWarning

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", NotGeoreferencedWarning)
            with rasterio.open(tmp, "w", **profile) as dst:
                dst.write(arr)
                if tags:
                    dst.update_tags(**{k: str(v) for k, v in tags.items()})
    return Path(path)


def read_on_grid(path: os.PathLike | str, grid: AOIGrid, resampling: str = "nearest", band: int = 1) -> np.ndarray:
    """Any single band (a mask, classes, a product) resampled onto ``grid``: float32, NaN outside / nodata.

    Unlike :func:`read_dem`, values are not checked to be heights.
    """
    from rasterio.errors import RasterioError

    with _open(path) as ds:
        if ds.crs is None:
            raise CRSError(f"{path} has no CRS; assign one (gdal_edit.py -a_srs EPSG:...) before using it")
        _check_read_memory(path, grid.shape, grid)
        try:
            return reproject_band(ds, band, grid, resampling)
        except RasterioError as exc:
            raise _read_failure(path, exc) from exc


def read_band(path: os.PathLike | str, band: int = 1) -> tuple[np.ndarray, AOIGrid]:
    """Read one band of a georeferenced product as float32 (nodata → NaN) with its grid."""
    from rasterio.errors import RasterioError

    with _open(path) as ds:
        if ds.crs is None:
            raise CRSError(f"{path} has no CRS")
        try:
            a = ds.read(band, masked=True).astype(np.float32).filled(np.nan)
        except RasterioError as exc:
            raise _read_failure(path, exc) from exc
        return a, AOIGrid(as_crs(ds.crs), ds.transform, ds.width, ds.height)
