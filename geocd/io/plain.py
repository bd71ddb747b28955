"""Plain image pairs (PNG, JPEG, a GeoTIFF without georeference) on a local grid in metres: ``--pixel-size``.

The 2-D methods (``geocd screen``, ``geocd mpp``) compare images on a map grid. An image pair with no
georeference, such as the tiles of the LEVIR-CD, WHU-CD or DSIFN-CD building-change sets, can still be
compared cell for cell when both images are co-registered crops of one place: given the ground size of a
pixel, each image is read through a small VRT that puts pixel (col, row) at x = (col + ½) · s, y = (H − row − ½) · s
metres (lower-left corner at 0, 0, y up) in a local engineering CRS, :data:`LOCAL_IMAGE_CRS_WKT`. The products
carry that CRS: QGIS opens them with "unknown CRS", on top of each other and of the images.
"""

from __future__ import annotations

import contextlib
import hashlib
import math
import os
import tempfile
import warnings
from collections.abc import Iterator, Sequence
from pathlib import Path
from xml.sax.saxutils import escape

from rasterio.errors import NotGeoreferencedWarning

from ..errors import ConfigError
from .raster import _open

#: a local Cartesian frame in metres (x east, y north) that no map projection stands behind
LOCAL_IMAGE_CRS_WKT = (
    'LOCAL_CS["geocd image grid (metres from the lower-left corner)",LOCAL_DATUM["image",32767],'
    'UNIT["metre",1,AUTHORITY["EPSG","9001"]],AXIS["Easting",EAST],AXIS["Northing",NORTH]]'
)
_GDAL_TYPES = {
    "uint8": "Byte",
    "int8": "Int8",
    "uint16": "UInt16",
    "int16": "Int16",
    "uint32": "UInt32",
    "int32": "Int32",
    "float32": "Float32",
    "float64": "Float64",
}


def is_georeferenced(path: os.PathLike | str) -> bool:
    """Whether the raster at ``path`` has a CRS (a map grid to compare it on)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NotGeoreferencedWarning)  # what is being asked
        with _open(path) as ds:
            return ds.crs is not None


def check_pixel_size(pixel_size_m: float) -> float:
    """The pixel size as a positive, finite number of metres, else a :class:`ConfigError`."""
    s = float(pixel_size_m)
    if not (math.isfinite(s) and s > 0):
        raise ConfigError(f"--pixel-size is the ground size of a pixel in metres, > 0; got {pixel_size_m}")
    return s


def plain_image_vrt(path: os.PathLike | str, pixel_size_m: float, folder: os.PathLike | str) -> Path:
    """A VRT in ``folder`` that reads the image at ``path`` on the local grid of ``pixel_size_m`` (module doc).

    Parameters
    ----------
    path : a raster without georeference (any format GDAL reads)
    pixel_size_m : ground size of one pixel, m
    folder : where the VRT is written (named after the image)

    Returns
    -------
    Path of the VRT.

    Raises
    ------
    ConfigError : the image has a georeference (its own grid is the one to use), or the pixel size is not > 0
    """
    s = check_pixel_size(pixel_size_m)
    src = Path(path).resolve()
    with warnings.catch_warnings(), _open(src) as ds:
        warnings.simplefilter("ignore", NotGeoreferencedWarning)  # a plain image has none: that is the point
        if ds.crs is not None:
            raise ConfigError(
                f"--pixel-size is for images without a georeference; {path} has one ({ds.crs.to_string()}): "
                "leave --pixel-size out and its own grid is used"
            )
        w, h, n, dtypes = ds.width, ds.height, ds.count, ds.dtypes
    bands = "".join(
        f'<VRTRasterBand dataType="{_GDAL_TYPES.get(dtypes[i - 1], "Float64")}" band="{i}"><SimpleSource>'
        f'<SourceFilename relativeToVRT="0">{escape(str(src))}</SourceFilename><SourceBand>{i}</SourceBand>'
        "</SimpleSource></VRTRasterBand>"
        for i in range(1, n + 1)
    )
    xml = (
        f'<VRTDataset rasterXSize="{w}" rasterYSize="{h}"><SRS>{escape(LOCAL_IMAGE_CRS_WKT)}</SRS>'
        f"<GeoTransform>0, {s!r}, 0, {h * s!r}, 0, {-s!r}</GeoTransform>{bands}</VRTDataset>\n"
    )
    out = Path(folder) / f"{src.stem}.{hashlib.sha1(str(src).encode()).hexdigest()[:8]}.vrt"  # A/x.png, B/x.png
    out.write_text(xml, encoding="utf-8")
    return out


def plain_images_on_a_grid(
    paths: Sequence[os.PathLike | str], pixel_size_m: float, folder: os.PathLike | str
) -> list[Path]:
    """:func:`plain_image_vrt` of images that must be co-registered crops of one place: the same size in pixels.

    Raises
    ------
    ConfigError : the images differ in size (then they are no cell-for-cell pair), or one has a georeference
    """
    sizes = []
    for p in paths:
        with warnings.catch_warnings(), _open(p) as ds:
            warnings.simplefilter("ignore", NotGeoreferencedWarning)
            sizes.append((ds.width, ds.height))
    if len(set(sizes)) > 1:
        listed = ", ".join(f"{Path(p).name} {w}x{h}" for p, (w, h) in zip(paths, sizes))
        raise ConfigError(
            f"--pixel-size compares plain images cell for cell, so they must have one size; got {listed}. "
            "Crop them to one extent first, or georeference them"
        )
    return [plain_image_vrt(p, pixel_size_m, folder) for p in paths]


@contextlib.contextmanager
def on_local_grid(groups: Sequence[Sequence[os.PathLike | str]], pixel_size_m: float | None) -> Iterator[list[list]]:
    """The rasters of ``groups`` as the methods read them: unchanged without a pixel size; with one, each group
    through :func:`plain_images_on_a_grid` (VRTs in a temporary folder that lasts as long as the ``with``).

    Parameters
    ----------
    groups : groups of images that must be compared cell for cell (an A/B pair, a no-change pair, ...); an
        empty group stays empty
    pixel_size_m : ground size of a pixel, m (``--pixel-size``), or None for georeferenced rasters

    Yields
    ------
    list of lists of paths, group for group
    """
    if pixel_size_m is None:
        yield [list(g) for g in groups]
        return
    with tempfile.TemporaryDirectory(prefix="geocd_plain_") as folder:
        yield [plain_images_on_a_grid(g, pixel_size_m, folder) if g else [] for g in groups]
