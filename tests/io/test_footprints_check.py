"""check_footprints_file: a footprint file is checked from its metadata, before any heavy work."""

from __future__ import annotations

import geopandas as gpd
import pytest
from shapely.geometry import LineString, Polygon

from geocd.errors import CRSError, EmptyDataError, UnsupportedFormatError
from geocd.io.vector import check_footprints_file
from tests.reliability.scenes import write_dem_pair, write_footprints, write_rgb


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("fpcheck")
    a, _ = write_dem_pair(d)
    return d, a


def test_polygons_pass(files):
    d, a = files
    check_footprints_file(write_footprints(d / "fp.gpkg", a))


def test_a_raster_is_named_as_such(files):
    d, a = files
    with pytest.raises(UnsupportedFormatError, match="is a raster .*give a GeoPackage"):
        check_footprints_file(write_rgb(d, a))


def test_garbage_and_lines_and_no_crs(files):
    d, _ = files
    (d / "junk.gpkg").write_bytes(b"\x00garbage" * 100)
    with pytest.raises(UnsupportedFormatError, match="not a vector layer"):
        check_footprints_file(d / "junk.gpkg")
    gpd.GeoDataFrame({"i": [1]}, geometry=[LineString([(0, 0), (1, 1)])], crs="EPSG:32631").to_file(d / "l.gpkg")
    with pytest.raises(EmptyDataError, match="LineString features; footprints must be polygons"):
        check_footprints_file(d / "l.gpkg")
    with pytest.warns(UserWarning):
        gpd.GeoDataFrame({"i": [1]}, geometry=[Polygon([(0, 0), (1, 0), (1, 1)])]).to_file(d / "nocrs.shp")
    with pytest.raises(CRSError, match="have no CRS"):
        check_footprints_file(d / "nocrs.shp")
