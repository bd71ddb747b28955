"""Reader for ArcInfo ASCII export grids (``.e00``, the ``GRD`` section).

GDAL's E00GRID driver is not built into the rasterio wheels, so geocd parses the
(simple) uncompressed format itself. Layout of the sections it reads::

    EXP  0 <original path>                      first line; "EXP  1" = compressed (not supported)
    GRD  2                                      grid section (2 = single, 3 = double precision)
    <ncols> <nrows> <type><nodata>              e.g. "       303       442 2-0.34028234663853E+39"
    <cellsize_x> <cellsize_y>
    <xmin> <ymin>                               lower-left corner of the grid extent
    <xmax> <ymax>                               upper-right corner
    values, row by row from the top; each row starts on a new line, 5 values per
    line (E14.7) in single precision, 3 per line (E24.17) in double precision; the
    last line of a row may be padded to a full line with stale values (ignored)
    EOG
    ...
    PRJ  2                                      projection: "Key value" lines separated by "~"
    Projection    UTM
    Zone          10
    Datum         NAD83
    Units         METERS
    ...
    EOP

The type code after the size is 1 for integer grids (I10 fields, 5 per line) and
2 for floating-point grids. Values equal to the nodata value (or beyond ±1e30)
become NaN.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from affine import Affine

from ..errors import CRSError, InputFileNotFoundError, UnsupportedFormatError
from ..geodesy import AOIGrid, as_crs
from .raster import DEM

_FLOAT = re.compile(r"[-+]?(?:\d+\.\d*|\.\d+|\d+)(?:[EeDd][-+]?\d+)?")


@dataclass(frozen=True)
class E00Grid:
    """A parsed ``GRD`` section.

    Attributes
    ----------
    values : float32 (nrows, ncols), NaN = nodata, first row = northernmost
    cellsize : (x, y) in CRS units
    lower_left, upper_right : corners of the grid extent (x, y)
    nodata : the file's nodata value
    projection : the ``PRJ`` section as a dict (lower-case keys), empty if absent
    """

    values: np.ndarray
    cellsize: tuple[float, float]
    lower_left: tuple[float, float]
    upper_right: tuple[float, float]
    nodata: float
    projection: dict

    @property
    def transform(self) -> Affine:
        return Affine(self.cellsize[0], 0.0, self.lower_left[0], 0.0, -self.cellsize[1], self.upper_right[1])


def _numbers(line: str) -> list[float]:
    return [float(t.replace("D", "E").replace("d", "e")) for t in _FLOAT.findall(line)]


def _fixed_width(line: str, width: int) -> list[float]:
    s = line.rstrip("\r\n")
    out = []
    for k in range(0, len(s), width):
        tok = s[k : k + width].strip()
        if tok:
            out.append(float(tok.replace("D", "E")))
    return out


def parse_e00_grid(text: str, source: str = "<text>") -> E00Grid:
    """Parse the text of an uncompressed ArcInfo ``.e00`` grid export."""
    lines = text.splitlines()
    if not lines or not lines[0].startswith("EXP"):
        raise UnsupportedFormatError(f"{source} is not an ArcInfo export file (no 'EXP' header line)")
    head = lines[0].split()
    if len(head) > 1 and head[1] == "1":
        raise UnsupportedFormatError(
            f"{source} is a compressed .e00 export; decompress it first (e.g. with the e00conv tool or "
            "avcimport) or convert it to GeoTIFF with a GDAL build that has the E00GRID driver"
        )
    try:
        g = next(i for i, ln in enumerate(lines) if ln.startswith("GRD "))
    except StopIteration:
        raise UnsupportedFormatError(
            f"{source} holds no grid (no 'GRD' section); only ArcInfo grid exports are read"
        ) from None
    precision = lines[g].split()[1] if len(lines[g].split()) > 1 else "2"
    try:
        hdr = lines[g + 1]
        ncols, nrows = int(hdr[0:10]), int(hdr[10:20])
        vtype = int(hdr[20:22])
        nodata = float(hdr[22:].strip().replace("D", "E"))
        csx, csy = _numbers(lines[g + 2])[:2]
        x0, y0 = _numbers(lines[g + 3])[:2]
        x1, y1 = _numbers(lines[g + 4])[:2]
    except (ValueError, IndexError) as exc:
        raise UnsupportedFormatError(
            f"{source}: cannot parse the GRD header ({exc}); the file may be truncated"
        ) from exc
    if ncols <= 0 or nrows <= 0 or csx <= 0 or csy <= 0:
        raise UnsupportedFormatError(f"{source}: invalid grid header ({ncols}x{nrows}, cell {csx}x{csy})")
    if vtype == 1:
        width, per_line = 10, 5
    elif precision == "3":
        width, per_line = 24, 3
    else:
        width, per_line = 14, 5
    lines_per_row = -(-ncols // per_line)
    start = g + 5
    end = start + nrows * lines_per_row
    if end > len(lines) or not any(ln.startswith("EOG") for ln in lines[end : end + 2]):
        raise UnsupportedFormatError(
            f"{source}: expected {nrows} rows of {lines_per_row} lines ending with 'EOG'; the file is truncated "
            "or not a plain grid export"
        )
    vals = np.empty((nrows, ncols), dtype=np.float64)
    k = start
    for r in range(nrows):
        row: list[float] = []
        for _ in range(lines_per_row):
            row.extend(_fixed_width(lines[k], width))
            k += 1
        if len(row) < ncols:
            raise UnsupportedFormatError(f"{source}: row {r} holds {len(row)} values, expected {ncols}")
        vals[r] = row[:ncols]  # some writers pad a row's last line with stale values
    bad = (vals == nodata) | (np.abs(vals) > 1e30)
    out = vals.astype(np.float32)
    out[bad] = np.nan
    return E00Grid(out, (csx, csy), (x0, y0), (x1, y1), nodata, _parse_prj(lines[end:]))


def _parse_prj(lines: list[str]) -> dict:
    try:
        p = next(i for i, ln in enumerate(lines) if ln.startswith("PRJ "))
    except StopIteration:
        return {}
    out: dict = {}
    for ln in lines[p + 1 :]:
        if ln.startswith("EOP"):
            break
        s = ln.strip()
        if not s or s == "~":
            continue
        parts = s.split(None, 1)
        if len(parts) == 2:
            out[parts[0].lower()] = parts[1].strip()
        else:
            out.setdefault(parts[0].lower(), "")
    return out


_DATUM_UTM_EPSG = {"NAD83": 26900, "NAD27": 26700, "WGS84": 32600}


def crs_from_prj(prj: dict):
    """A pyproj CRS from an ArcInfo ``PRJ`` block (UTM and geographic; others raise CRSError)."""
    proj = prj.get("projection", "").upper()
    datum = prj.get("datum", "").upper().replace(" ", "")
    units = prj.get("units", "METERS").upper()
    if proj == "UTM":
        try:
            zone = int(prj.get("zone", ""))
        except ValueError:
            raise CRSError(f"UTM projection without a valid zone in the PRJ block {prj}") from None
        if units not in ("METERS", "METRES"):
            raise CRSError(f"UTM grid in units {units!r}; only metres are supported")
        south = zone < 0
        zone = abs(zone)
        base = _DATUM_UTM_EPSG.get(datum)
        if base is not None and not (south and datum != "WGS84"):
            return as_crs(f"EPSG:{base + (100 if south and datum == 'WGS84' else 0) + zone}")
        ell = {"NAD83": "GRS80", "NAD27": "clrk66", "WGS84": "WGS84"}.get(datum, "GRS80")
        return as_crs(f"+proj=utm +zone={zone}{' +south' if south else ''} +ellps={ell} +units=m +no_defs")
    if proj == "GEOGRAPHIC":
        return as_crs({"NAD83": "EPSG:4269", "NAD27": "EPSG:4267"}.get(datum, "EPSG:4326"))
    raise CRSError(
        f"ArcInfo projection {proj or '(none)'} is not supported by geocd's .e00 reader; "
        "convert the grid with GDAL (E00GRID driver) or pass crs= explicitly"
    )


def read_e00_grid(path: os.PathLike | str) -> E00Grid:
    """Read and parse an ``.e00`` grid export."""
    p = Path(path)
    if not p.is_file():
        raise InputFileNotFoundError(f"e00 file {p} does not exist; check the path")
    with open(p, "r", encoding="latin-1", newline=None) as f:
        text = f.read()
    return parse_e00_grid(text, source=str(p))


def read_e00_dem(path: os.PathLike | str, crs=None, vertical_datum: str | None = None) -> DEM:
    """Read an ``.e00`` grid as a :class:`~geocd.io.raster.DEM` (float32 heights, NaN nodata).

    Parameters
    ----------
    crs : optional CRS overriding the file's ``PRJ`` block.
    vertical_datum : optional vertical datum name (e00 files do not record one).
    """
    from .raster import check_vertical_datum

    vertical_datum = check_vertical_datum(vertical_datum, f"DEM {path}")
    g = read_e00_grid(path)
    c = as_crs(crs) if crs is not None else crs_from_prj(g.projection)
    nrows, ncols = g.values.shape
    grid = AOIGrid(c, g.transform, ncols, nrows)
    return DEM(g.values, grid, vertical_datum, str(path))
