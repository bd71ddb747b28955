"""Coordinate frames, AOI grids and vertical datums.

* Map order is always (x, y) = (easting, northing) or (lon, lat); every pyproj
  transformer is built with ``always_xy=True``.
* :class:`AOIGrid` is the georeferenced raster grid every product lives on
  (transform, shape, CRS, posting), with cell-centre coordinates.
* :class:`LocalFrame` is a local vertical Cartesian frame (East-North-Up) at an
  AOI origin, exact (via ECEF), for methods that need metric 3-D space.
* Vertical datums are explicit: RPC heights are ellipsoidal (WGS84); DEMs often
  hold geoid heights (EGM96, EGM2008). :func:`geoid_undulation` converts with a
  geoid grid found on the machine (PROJ data folders, ``GEOCD_GEOID_DIR``) or
  raises :class:`~geocd.errors.VerticalDatumError` saying which file is needed.
"""

from __future__ import annotations

import functools
import math
import os
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable

import numpy as np
from affine import Affine
from pyproj import CRS, Transformer

from .errors import CRSError, GridError, NoOverlapError, VerticalDatumError

WGS84_GEOG = CRS.from_epsg(4326)
WGS84_3D = CRS.from_epsg(4979)
WGS84_ECEF = CRS.from_epsg(4978)


# ------------------------------------------------------------------------------------------
# CRS helpers
# ------------------------------------------------------------------------------------------
def as_crs(crs: Any) -> CRS:
    """Anything pyproj/rasterio accepts → :class:`pyproj.CRS` (None → EPSG:4326)."""
    if crs is None:
        return WGS84_GEOG
    if isinstance(crs, CRS):
        return crs
    try:
        if hasattr(crs, "to_wkt"):  # rasterio CRS
            return CRS.from_wkt(crs.to_wkt())
        return CRS.from_user_input(crs)
    except Exception as exc:  # pyproj raises its own CRSError
        raise CRSError(
            f"cannot interpret {crs!r} as a CRS ({exc}); give an EPSG code like 'EPSG:32631' or WKT"
        ) from exc


def horizontal_crs(crs: Any) -> CRS:
    """The horizontal part of a (possibly compound) CRS."""
    c = as_crs(crs)
    if c.is_compound:
        return c.sub_crs_list[0]
    return c


@functools.lru_cache(maxsize=64)
def _transformer(src_wkt: str, dst_wkt: str) -> Transformer:
    return Transformer.from_crs(CRS.from_wkt(src_wkt), CRS.from_wkt(dst_wkt), always_xy=True)


def transformer(src: Any, dst: Any) -> Transformer:
    """A cached ``always_xy`` transformer between the horizontal parts of two CRSs."""
    return _transformer(horizontal_crs(src).to_wkt(), horizontal_crs(dst).to_wkt())


def to_lonlat(x: Any, y: Any, crs: Any = None) -> tuple[np.ndarray, np.ndarray]:
    """Map coordinates in ``crs`` → WGS84 lon/lat degrees (horizontal only)."""
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    c = horizontal_crs(crs)
    if c.is_geographic and c.equals(WGS84_GEOG, ignore_axis_order=True):
        return x.copy(), y.copy()
    lon, lat = transformer(c, WGS84_GEOG).transform(x, y)
    return np.asarray(lon, dtype=np.float64), np.asarray(lat, dtype=np.float64)


def from_lonlat(lon: Any, lat: Any, crs: Any) -> tuple[np.ndarray, np.ndarray]:
    """WGS84 lon/lat degrees → map coordinates in ``crs``."""
    lon = np.asarray(lon, dtype=np.float64)
    lat = np.asarray(lat, dtype=np.float64)
    c = horizontal_crs(crs)
    if c.is_geographic and c.equals(WGS84_GEOG, ignore_axis_order=True):
        return lon.copy(), lat.copy()
    x, y = transformer(WGS84_GEOG, c).transform(lon, lat)
    return np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)


def utm_crs_for(lon: float, lat: float) -> CRS:
    """The WGS84 UTM zone CRS containing (lon, lat)."""
    zone = int(math.floor((lon + 180.0) / 6.0)) % 60 + 1
    return CRS.from_epsg((32600 if lat >= 0 else 32700) + zone)


# ------------------------------------------------------------------------------------------
# AOI grid
# ------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class AOIGrid:
    """A north-up raster grid: the common support of every geocd product.

    Parameters
    ----------
    crs : pyproj.CRS
        Horizontal CRS of the grid (projected, metres, for products).
    transform : affine.Affine
        Pixel-corner geotransform (GDAL/rasterio convention).
    width, height : int
        Number of columns and rows.
    """

    crs: CRS
    transform: Affine
    width: int
    height: int

    def __post_init__(self) -> None:
        object.__setattr__(self, "crs", horizontal_crs(self.crs))
        if self.width <= 0 or self.height <= 0:
            raise GridError(f"AOI grid must have a positive size, got {self.width}x{self.height}")
        t = self.transform
        if t.b != 0 or t.d != 0:
            raise GridError("AOI grids are north-up (no rotation); resample rotated rasters first")
        if t.a <= 0 or t.e >= 0:
            raise GridError(f"AOI grid transform must have positive x and negative y steps, got {t}")

    # --- constructors -----------------------------------------------------------------
    @classmethod
    def from_bounds(cls, left: float, bottom: float, right: float, top: float, posting_m: float, crs: Any) -> "AOIGrid":
        """Grid covering the bounds with square cells of ``posting_m``, snapped to multiples of it."""
        if not (posting_m > 0):
            raise GridError(f"posting must be positive, got {posting_m}")
        if not (right > left and top > bottom):
            raise GridError(f"empty bounds ({left}, {bottom}, {right}, {top})")
        x0 = math.floor(left / posting_m) * posting_m
        y1 = math.ceil(top / posting_m) * posting_m
        w = int(math.ceil((right - x0) / posting_m - 1e-9))
        h = int(math.ceil((y1 - bottom) / posting_m - 1e-9))
        return cls(as_crs(crs), Affine(posting_m, 0.0, x0, 0.0, -posting_m, y1), w, h)

    @classmethod
    def from_raster(cls, dataset) -> "AOIGrid":
        """The grid of an open rasterio dataset (must be georeferenced and north-up)."""
        if dataset.crs is None:
            raise CRSError(f"{dataset.name} has no CRS; it cannot define an AOI grid")
        return cls(as_crs(dataset.crs), dataset.transform, dataset.width, dataset.height)

    # --- properties ----------------------------------------------------------------------
    @property
    def shape(self) -> tuple[int, int]:
        """(rows, cols) of arrays on this grid."""
        return (self.height, self.width)

    @property
    def posting(self) -> tuple[float, float]:
        """Cell size (x, y) in CRS units (positive)."""
        return (self.transform.a, -self.transform.e)

    @property
    def posting_m(self) -> float:
        """Cell size in metres (square grids; the mean of x and y otherwise)."""
        return 0.5 * (self.transform.a - self.transform.e)

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """(left, bottom, right, top)."""
        t = self.transform
        return (t.c, t.f + t.e * self.height, t.c + t.a * self.width, t.f)

    @property
    def cell_area_m2(self) -> float:
        return abs(self.transform.a * self.transform.e)

    def xy(self, rows: Any = None, cols: Any = None) -> tuple[np.ndarray, np.ndarray]:
        """Cell-centre map coordinates; all cells (shape ``self.shape``) by default."""
        if rows is None and cols is None:
            cols, rows = np.meshgrid(np.arange(self.width) + 0.5, np.arange(self.height) + 0.5)
        else:
            rows = np.asarray(rows, float) + 0.5
            cols = np.asarray(cols, float) + 0.5
        t = self.transform
        return t.c + t.a * cols, t.f + t.e * rows

    def lonlat(self) -> tuple[np.ndarray, np.ndarray]:
        """Cell-centre WGS84 lon/lat (degrees), shape ``self.shape``."""
        x, y = self.xy()
        return to_lonlat(x, y, self.crs)

    def rowcol(self, x: Any, y: Any) -> tuple[np.ndarray, np.ndarray]:
        """Continuous (row, col) of map points (cell centres at integer + 0.5)."""
        inv = ~self.transform
        x = np.asarray(x, float)
        y = np.asarray(y, float)
        col = inv.a * x + inv.b * y + inv.c
        row = inv.d * x + inv.e * y + inv.f
        return row, col

    def footprint_lonlat(self):
        """Grid outline as a shapely polygon in lon/lat."""
        from shapely.geometry import Polygon

        l, b, r, t = self.bounds
        n = 16
        xs = np.concatenate([np.linspace(l, r, n), np.full(n, r), np.linspace(r, l, n), np.full(n, l)])
        ys = np.concatenate([np.full(n, t), np.linspace(t, b, n), np.full(n, b), np.linspace(b, t, n)])
        lon, lat = to_lonlat(xs, ys, self.crs)
        return Polygon(np.column_stack([lon, lat]))

    def subgrid(self, row0: int, col0: int, height: int, width: int) -> "AOIGrid":
        """A window of this grid (for tiling)."""
        if row0 < 0 or col0 < 0 or row0 + height > self.height or col0 + width > self.width:
            raise GridError(f"window ({row0}, {col0}, {height}, {width}) exceeds the grid {self.shape}")
        return AOIGrid(self.crs, self.transform @ Affine.translation(col0, row0), width, height)

    def same_as(self, other: "AOIGrid", tol: float = 1e-6) -> bool:
        """True when ``other`` is the same grid (CRS, size, transform within ``tol`` cells)."""
        if (self.width, self.height) != (other.width, other.height):
            return False
        if not self.crs.equals(other.crs, ignore_axis_order=True):
            return False
        a, b = np.array(self.transform)[:6], np.array(other.transform)[:6]
        return bool(np.all(np.abs(a - b) <= tol * self.posting_m))

    def rasterio_profile(self, dtype: str = "float32", count: int = 1, nodata: Any = None) -> dict:
        from rasterio.crs import CRS as RioCRS

        return {
            "driver": "GTiff",
            "width": self.width,
            "height": self.height,
            "count": count,
            "dtype": dtype,
            "crs": RioCRS.from_wkt(self.crs.to_wkt()),
            "transform": self.transform,
            "nodata": nodata,
        }

    def to_dict(self) -> dict:
        return {
            "crs": self.crs.to_string() if self.crs.to_epsg() else self.crs.to_wkt(),
            "transform": list(self.transform)[:6],
            "width": self.width,
            "height": self.height,
        }

    @classmethod
    def from_dict(cls, d: dict) -> "AOIGrid":
        try:
            return cls(as_crs(d["crs"]), Affine(*d["transform"][:6]), int(d["width"]), int(d["height"]))
        except KeyError as exc:
            raise GridError(f"grid description lacks {exc}; it needs crs, transform, width, height") from exc


def intersect_bounds(*bounds: tuple[float, float, float, float]) -> tuple[float, float, float, float]:
    """Intersection of (left, bottom, right, top) boxes; :class:`NoOverlapError` when empty."""
    l = max(b[0] for b in bounds)
    bt = max(b[1] for b in bounds)
    r = min(b[2] for b in bounds)
    t = min(b[3] for b in bounds)
    if not (r > l and t > bt):
        raise NoOverlapError(f"the inputs do not overlap (bounds {list(bounds)}); check that they cover the same area")
    return (l, bt, r, t)


# ------------------------------------------------------------------------------------------
# Local ENU frame
# ------------------------------------------------------------------------------------------
_A = 6378137.0
_F = 1.0 / 298.257223563
_E2 = _F * (2.0 - _F)


def geodetic_to_ecef(lon: Any, lat: Any, h: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """WGS84 geodetic (deg, deg, m) → ECEF (m), closed form."""
    lam = np.radians(np.asarray(lon, float))
    phi = np.radians(np.asarray(lat, float))
    h = np.asarray(h, float)
    s = np.sin(phi)
    n = _A / np.sqrt(1.0 - _E2 * s * s)
    x = (n + h) * np.cos(phi) * np.cos(lam)
    y = (n + h) * np.cos(phi) * np.sin(lam)
    z = (n * (1.0 - _E2) + h) * s
    return x, y, z


def ecef_to_geodetic(x: Any, y: Any, z: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ECEF (m) → WGS84 geodetic (deg, deg, m); iterative, converged to < 1e-9 m."""
    x = np.asarray(x, float)
    y = np.asarray(y, float)
    z = np.asarray(z, float)
    lon = np.arctan2(y, x)
    p = np.hypot(x, y)
    lat = np.arctan2(z, p * (1.0 - _E2))
    h = np.zeros_like(p)
    for _ in range(10):
        s = np.sin(lat)
        n = _A / np.sqrt(1.0 - _E2 * s * s)
        h = p / np.cos(lat) - n
        lat_new = np.arctan2(z, p * (1.0 - _E2 * n / (n + h)))
        if np.all(np.abs(lat_new - lat) < 1e-14):
            lat = lat_new
            break
        lat = lat_new
    s = np.sin(lat)
    n = _A / np.sqrt(1.0 - _E2 * s * s)
    h = p / np.cos(lat) - n
    return np.degrees(lon), np.degrees(lat), h


@dataclass(frozen=True)
class LocalFrame:
    """Local East-North-Up Cartesian frame tangent to the WGS84 ellipsoid.

    Parameters
    ----------
    lon0, lat0 : float, degrees
    h0 : float, metres (ellipsoidal)
    """

    lon0: float
    lat0: float
    h0: float = 0.0

    @property
    def _rot(self) -> np.ndarray:
        lam, phi = math.radians(self.lon0), math.radians(self.lat0)
        sl, cl, sp, cp = math.sin(lam), math.cos(lam), math.sin(phi), math.cos(phi)
        # rows: east, north, up (in ECEF components)
        return np.array([[-sl, cl, 0.0], [-sp * cl, -sp * sl, cp], [cp * cl, cp * sl, sp]])

    @property
    def _origin(self) -> np.ndarray:
        return np.array(geodetic_to_ecef(self.lon0, self.lat0, self.h0), dtype=float)

    def to_enu(self, lon: Any, lat: Any, h: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Geodetic → local (e, n, u) metres."""
        x, y, z = geodetic_to_ecef(lon, lat, h)
        o = self._origin
        d = np.stack([x - o[0], y - o[1], z - o[2]])
        e, n, u = np.tensordot(self._rot, d, axes=1)
        return e, n, u

    def from_enu(self, e: Any, n: Any, u: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Local (e, n, u) metres → geodetic (lon, lat, h)."""
        d = np.stack(np.broadcast_arrays(np.asarray(e, float), np.asarray(n, float), np.asarray(u, float)))
        xyz = np.tensordot(self._rot.T, d, axes=1)
        o = self._origin
        return ecef_to_geodetic(xyz[0] + o[0], xyz[1] + o[1], xyz[2] + o[2])

    def to_dict(self) -> dict:
        return {"lon0": self.lon0, "lat0": self.lat0, "h0": self.h0}


# ------------------------------------------------------------------------------------------
# Vertical datums
# ------------------------------------------------------------------------------------------
ELLIPSOID = "ellipsoid"
EGM96 = "egm96"
EGM2008 = "egm2008"

#: grid file names by model, in order of preference (PROJ-data names, then legacy .gtx)
GEOID_GRID_FILES = {
    EGM96: ("us_nga_egm96_15.tif", "egm96_15.gtx", "egm96_15.tif"),
    EGM2008: ("us_nga_egm08_25.tif", "egm08_25.gtx", "egm2008-2_5.tif", "egm08_1.gtx"),
}

_EPSG_VERTICAL = {5773: EGM96, 3855: EGM2008, 5798: EGM2008, 10190: EGM2008}


def vertical_datum_of(crs: Any, default: str | None = None) -> str | None:
    """Name the vertical datum of a (compound or 3-D) CRS.

    Returns ``"ellipsoid"``, ``"egm96"``, ``"egm2008"``, another lower-case
    vertical datum name, or ``default`` when the CRS has no vertical component.
    """
    if crs is None:
        return default
    c = as_crs(crs)
    if c.is_compound:
        v = c.sub_crs_list[1]
        code = v.to_epsg()
        if code in _EPSG_VERTICAL:
            return _EPSG_VERTICAL[code]
        name = (v.name or "").lower().replace(" ", "")
        if "egm2008" in name or "egm08" in name:
            return EGM2008
        if "egm96" in name:
            return EGM96
        return v.name.lower() if v.name else default
    if len(c.axis_info) == 3 and c.is_geographic:
        return ELLIPSOID
    return default


def normalize_datum_name(name: str | None) -> str | None:
    if name is None:
        return None
    n = str(name).strip().lower().replace(" ", "").replace("-", "")
    aliases = {
        "ellipsoid": ELLIPSOID,
        "ellipsoidal": ELLIPSOID,
        "wgs84": ELLIPSOID,
        "hae": ELLIPSOID,
        "egm96": EGM96,
        "egm1996": EGM96,
        "egm2008": EGM2008,
        "egm08": EGM2008,
    }
    return aliases.get(n, n)


def geoid_search_dirs() -> list[Path]:
    """Folders searched for geoid grids, in order."""
    dirs: list[Path] = []
    if os.environ.get("GEOCD_GEOID_DIR"):
        dirs.append(Path(os.environ["GEOCD_GEOID_DIR"]))
    for var in ("PROJ_DATA", "PROJ_LIB"):
        for p in os.environ.get(var, "").split(os.pathsep):
            if p:
                dirs.append(Path(p))
    try:
        import pyproj.datadir

        dirs.append(Path(pyproj.datadir.get_data_dir()))
        dirs.append(Path(pyproj.datadir.get_user_data_dir()))
    except Exception:  # pragma: no cover - pyproj always has these
        pass
    dirs += [Path("/usr/share/proj"), Path("/usr/local/share/proj")]
    seen, out = set(), []
    for d in dirs:
        if d not in seen:
            seen.add(d)
            out.append(d)
    return out


def find_geoid_grid(model: str) -> Path | None:
    model = normalize_datum_name(model)
    for name in GEOID_GRID_FILES.get(model, ()):
        for d in geoid_search_dirs():
            p = d / name
            if p.is_file():
                return p
    return None


@functools.lru_cache(maxsize=4)
def _load_geoid(path: str) -> tuple[np.ndarray, Affine]:
    import rasterio

    with rasterio.open(path) as ds:
        arr = ds.read(1).astype(np.float64)
        nod = ds.nodata
        t = ds.transform
    if nod is not None:
        arr[arr == nod] = np.nan
    return arr, t


def _bilinear_global(arr: np.ndarray, t: Affine, lon: np.ndarray, lat: np.ndarray) -> np.ndarray:
    """Bilinear sample of a global lon/lat grid (pixel-is-area transform), wrapping longitude."""
    h, w = arr.shape
    # continuous index of cell centres
    c = (lon - t.c) / t.a - 0.5
    r = (lat - t.f) / t.e - 0.5
    period = 360.0 / t.a
    c0 = np.floor(c)
    r0 = np.clip(np.floor(r), 0, h - 2)
    fc = c - c0
    fr = np.clip(r - r0, 0.0, 1.0)
    c0 = c0.astype(np.int64)
    r0 = r0.astype(np.int64)
    wrap = int(round(period))
    c0m = np.mod(c0, wrap) if wrap <= w else np.clip(c0, 0, w - 1)
    c1m = np.mod(c0 + 1, wrap) if wrap <= w else np.clip(c0 + 1, 0, w - 1)
    c0m = np.clip(c0m, 0, w - 1)
    c1m = np.clip(c1m, 0, w - 1)
    v00 = arr[r0, c0m]
    v01 = arr[r0, c1m]
    v10 = arr[r0 + 1, c0m]
    v11 = arr[r0 + 1, c1m]
    return v00 * (1 - fc) * (1 - fr) + v01 * fc * (1 - fr) + v10 * (1 - fc) * fr + v11 * fc * fr


def geoid_undulation(lon: Any, lat: Any, model: str, *, allow_substitute: bool = False) -> np.ndarray:
    """Geoid height N (metres) so that ellipsoidal h = orthometric H + N.

    Parameters
    ----------
    model : "egm96" or "egm2008"
    allow_substitute : bool
        When the EGM2008 grid is missing but EGM96 is present, use EGM96 with a
        warning (they differ by < 1 m over most land, a few metres in high
        mountains). Off by default: a missing grid is an error.
    """
    m = normalize_datum_name(model)
    if m == ELLIPSOID:
        return np.zeros(np.broadcast(np.asarray(lon), np.asarray(lat)).shape)
    if m not in GEOID_GRID_FILES:
        raise VerticalDatumError(
            f"geocd cannot convert heights in vertical datum {model!r}; convert the DEM to ellipsoidal "
            "(WGS84) or EGM96/EGM2008 heights first, or declare vertical_datum: ellipsoid if it already is"
        )
    path = find_geoid_grid(m)
    if path is None and allow_substitute and m == EGM2008:
        path = find_geoid_grid(EGM96)
        if path is not None:
            warnings.warn(
                "EGM2008 geoid grid not found; using EGM96 instead (differences are usually < 1 m, "
                "up to a few metres in high mountains)",
                stacklevel=2,
            )
    if path is None:
        names = " or ".join(GEOID_GRID_FILES[m])
        raise VerticalDatumError(
            f"heights are in {m.upper()} but the geoid grid ({names}) was not found in "
            f"{[str(d) for d in geoid_search_dirs()]}; install Debian's proj-data package "
            "(apt-get install proj-data, which ships egm96_15.gtx), put the grid in a folder named by "
            "GEOCD_GEOID_DIR, or convert the DEM to ellipsoidal heights"
            + (
                "; for EGM2008 you may also allow the EGM96 substitute (--allow-geoid-substitute)"
                if m == EGM2008
                else ""
            )
        )
    arr, t = _load_geoid(str(path))
    lon, lat = np.broadcast_arrays(np.asarray(lon, float), np.asarray(lat, float))
    ok = np.isfinite(lon) & np.isfinite(lat)
    if ok.all():
        return _bilinear_global(arr, t, lon, lat)
    out = np.full(lon.shape, np.nan)  # NaN in → NaN out (no invalid integer casts)
    out[ok] = _bilinear_global(arr, t, lon[ok], lat[ok])
    return out


def to_ellipsoidal(height: Any, lon: Any, lat: Any, datum: str | None, **kw: Any) -> np.ndarray:
    """Heights in ``datum`` → WGS84 ellipsoidal heights (``datum`` None/ellipsoid: unchanged)."""
    d = normalize_datum_name(datum)
    h = np.asarray(height, float)
    if d in (None, ELLIPSOID):
        return h
    return h + geoid_undulation(lon, lat, d, **kw)


def bounds_of_points(x: Iterable[float], y: Iterable[float]) -> tuple[float, float, float, float]:
    x = np.asarray(list(x) if not isinstance(x, np.ndarray) else x, float)
    y = np.asarray(list(y) if not isinstance(y, np.ndarray) else y, float)
    return (float(np.nanmin(x)), float(np.nanmin(y)), float(np.nanmax(x)), float(np.nanmax(y)))
