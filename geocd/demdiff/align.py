"""Bring two DEMs onto one grid and one vertical datum before differencing.

* **Grid**: by default the reference DEM's (A's) grid, cropped to the overlap of
  both DEMs; B is resampled onto it with an explicit ``resampling`` (bilinear by
  default; "cubic", "average" for a finer B, "nearest" to keep values). Another
  target grid can be given (e.g. an AOI).
* **Vertical datum**: both DEMs must be in the same vertical datum. When they
  differ and both are known (ellipsoid, EGM96, EGM2008), both are converted to
  ellipsoidal heights with the geoid grid (:class:`~geocd.errors.VerticalDatumError`
  when the grid file is missing). When one is declared and the other unknown, geocd
  does not guess: it raises and asks for the missing datum.
* **Geographic grids** (EPSG:4326 SRTM tiles) are kept as they are; the metric cell
  size at the grid centre (:func:`metric_posting`) is what slopes and shifts use.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..errors import ConfigError, EmptyDataError, NoOverlapError, VerticalDatumError
from ..geodesy import AOIGrid, ELLIPSOID, intersect_bounds, normalize_datum_name, transformer
from ..io.raster import DEM, RESAMPLING, reproject_array

_A = 6378137.0
_F = 1.0 / 298.257223563
_E2 = _F * (2.0 - _F)


def metric_posting(grid: AOIGrid) -> tuple[float, float]:
    """Cell size (x, y) in metres: the posting for projected grids, the local scale at the
    grid centre for geographic (degree) grids."""
    if not grid.crs.is_geographic:
        f = 1.0
        try:
            f = float(grid.crs.axis_info[0].unit_conversion_factor)
        except (IndexError, AttributeError, TypeError):
            pass
        return (grid.posting[0] * f, grid.posting[1] * f)
    l, b, r, t = grid.bounds
    lat = math.radians(0.5 * (b + t))
    s = math.sin(lat)
    n = _A / math.sqrt(1 - _E2 * s * s)
    m = _A * (1 - _E2) / (1 - _E2 * s * s) ** 1.5
    return (math.radians(grid.posting[0]) * n * math.cos(lat), math.radians(grid.posting[1]) * m)


@dataclass
class AlignedPair:
    """Two DEMs on one grid and datum.

    Attributes
    ----------
    height_a_m, height_b_m : float32 (rows, cols), NaN = nodata
    grid : AOIGrid
    vertical_datum : the common datum ("ellipsoid" after a conversion; None = unknown but the same)
    posting_xy_m : metric cell size
    notes : what was done (resampling, conversions)
    """

    height_a_m: np.ndarray
    height_b_m: np.ndarray
    grid: AOIGrid
    vertical_datum: str | None
    posting_xy_m: tuple[float, float]
    notes: list[str] = field(default_factory=list)

    @property
    def valid(self) -> np.ndarray:
        return np.isfinite(self.height_a_m) & np.isfinite(self.height_b_m)


def _bounds_in(grid: AOIGrid, crs) -> tuple[float, float, float, float]:
    l, b, r, t = grid.bounds
    if grid.crs.equals(crs, ignore_axis_order=True):
        return (l, b, r, t)
    xs = np.concatenate([np.linspace(l, r, 21), np.full(21, r), np.linspace(r, l, 21), np.full(21, l)])
    ys = np.concatenate([np.full(21, t), np.linspace(t, b, 21), np.full(21, b), np.linspace(b, t, 21)])
    x, y = transformer(grid.crs, crs).transform(xs, ys)
    return (float(np.min(x)), float(np.min(y)), float(np.max(x)), float(np.max(y)))


def crop_to_overlap(grid: AOIGrid, other: AOIGrid) -> AOIGrid:
    """``grid`` cropped (whole cells) to its overlap with ``other``; NoOverlapError when none."""
    ob = _bounds_in(other, grid.crs)
    try:
        l, b, r, t = intersect_bounds(grid.bounds, ob)
    except NoOverlapError:
        raise NoOverlapError(
            f"the DEMs do not overlap: A covers {tuple(round(v, 3) for v in grid.bounds)} and B covers "
            f"{tuple(round(v, 3) for v in ob)} (in A's CRS {grid.crs.to_string()}); give two DEMs of the same area"
        ) from None
    inv = ~grid.transform
    c0, r0 = inv @ (l, t)
    c1, r1 = inv @ (r, b)
    c0 = max(0, int(math.floor(c0 + 1e-6)))
    r0 = max(0, int(math.floor(r0 + 1e-6)))
    c1 = min(grid.width, int(math.ceil(c1 - 1e-6)))
    r1 = min(grid.height, int(math.ceil(r1 - 1e-6)))
    if c1 <= c0 or r1 <= r0:
        raise NoOverlapError("the DEMs overlap by less than one cell; give two DEMs of the same area")
    return grid.subgrid(r0, c0, r1 - r0, c1 - c0)


def _resample(dem: DEM, grid: AOIGrid, resampling: str) -> np.ndarray:
    if dem.grid.same_as(grid):
        return np.asarray(dem.height_m, np.float32)
    # the same grid cropped: slice instead of resampling
    if dem.grid.crs.equals(grid.crs, ignore_axis_order=True) and np.allclose(
        np.array(dem.grid.transform)[[0, 1, 3, 4]], np.array(grid.transform)[[0, 1, 3, 4]]
    ):
        inv = ~dem.grid.transform
        c, r = inv @ (grid.transform.c, grid.transform.f)
        if abs(c - round(c)) < 1e-6 and abs(r - round(r)) < 1e-6:
            c, r = int(round(c)), int(round(r))
            out = np.full(grid.shape, np.nan, np.float32)
            rs0, cs0 = max(r, 0), max(c, 0)
            rs1, cs1 = min(r + grid.height, dem.grid.height), min(c + grid.width, dem.grid.width)
            if rs1 > rs0 and cs1 > cs0:
                out[rs0 - r : rs1 - r, cs0 - c : cs1 - c] = dem.height_m[rs0:rs1, cs0:cs1]
            return out
    return reproject_array(np.asarray(dem.height_m, np.float32), dem.grid, grid, resampling)


def align_dems(
    dem_a: DEM,
    dem_b: DEM,
    grid: AOIGrid | None = None,
    *,
    resampling: str = "bilinear",
    allow_geoid_substitute: bool = False,
    crop: bool = True,
) -> AlignedPair:
    """Put B (and A if needed) on one grid and one vertical datum.

    Parameters
    ----------
    dem_a : reference (earlier) DEM; its grid is the default target
    dem_b : DEM to compare (later)
    grid : optional target grid
    resampling : one of :data:`geocd.io.raster.RESAMPLING`
    crop : crop the target grid to the overlap of both DEMs (default True)

    Raises
    ------
    NoOverlapError, VerticalDatumError, EmptyDataError
    """
    if resampling not in RESAMPLING:
        raise ConfigError(f"resampling must be one of {RESAMPLING}, got {resampling!r}")
    notes: list[str] = []
    da = normalize_datum_name(dem_a.vertical_datum)
    db = normalize_datum_name(dem_b.vertical_datum)
    if (da is None) != (db is None):
        known, which = (da, "B") if da is not None else (db, "A")
        raise VerticalDatumError(
            f"DEM A's vertical datum is {da or 'unknown'} and DEM B's is {db or 'unknown'}: geocd will not guess. "
            f"Declare DEM {which}'s vertical datum (--datum-{which.lower()} ellipsoid|egm96|egm2008, or "
            f"vertical_datum= in Python); if both are in the same datum, declare it for both"
        )
    target = grid or dem_a.grid
    target = crop_to_overlap(target, dem_b.grid) if crop else target
    if grid is not None and crop:
        target = crop_to_overlap(target, dem_a.grid)
    if da != db:
        notes.append(f"vertical datums differ ({da} vs {db}): both converted to ellipsoidal heights")
        dem_a = dem_a.to_ellipsoidal(allow_substitute=allow_geoid_substitute) if da != ELLIPSOID else dem_a
        dem_b = dem_b.to_ellipsoidal(allow_substitute=allow_geoid_substitute) if db != ELLIPSOID else dem_b
        vd = ELLIPSOID
    else:
        vd = da
    ha = _resample(dem_a, target, resampling)
    hb = _resample(dem_b, target, resampling)
    if not dem_b.grid.same_as(target):
        notes.append(f"B resampled onto the {'AOI' if grid is not None else 'reference'} grid ({resampling})")
    both = np.isfinite(ha) & np.isfinite(hb)
    if not both.any():
        raise EmptyDataError(
            "the DEMs share no cell with heights in both (their valid areas do not overlap); "
            "check nodata values and that they cover the same area"
        )
    return AlignedPair(ha.astype(np.float32), hb.astype(np.float32), target, vd, metric_posting(target), notes)
