import numpy as np
import pytest
import rasterio

from geocd.errors import CRSError, EmptyDataError, InputFileNotFoundError, OutputError
from geocd.geodesy import AOIGrid
from geocd.io.atomic import atomic_path, protect_inputs
from geocd.io.raster import read_dem, read_image, write_cog, write_image
from geocd.io.vector import polygons_to_mask, read_footprints, write_gpkg


@pytest.fixture
def grid():
    return AOIGrid.from_bounds(500000, 4000000, 500064, 4000032, 0.5, "EPSG:32631")


def test_write_cog_round_trip(tmp_path, grid):
    z = np.random.default_rng(0).normal(size=grid.shape).astype(np.float32)
    z[0, :5] = np.nan
    p = write_cog(tmp_path / "p.tif", {"dz_m": z, "score": z * 2}, grid, tags={"method": "test"})
    with rasterio.open(p) as ds:
        assert ds.count == 2 and ds.descriptions == ("dz_m", "score")
        assert ds.tags()["method"] == "test"
        assert ds.crs.to_epsg() == 32631 and ds.transform == grid.transform
        a = ds.read(1)
        assert np.isnan(a[0, :5]).all() and np.allclose(a[1:], z[1:])
        assert ds.profile.get("tiled")
    assert not list(tmp_path.glob(".*part*"))


def test_atomic_write_leaves_nothing_on_failure(tmp_path):
    target = tmp_path / "out.tif"
    target.write_text("previous")
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("boom")
    assert target.read_text() == "previous"
    assert [p.name for p in tmp_path.iterdir()] == ["out.tif"]


def test_refuses_to_overwrite_input(tmp_path, grid):
    src = tmp_path / "input.tif"
    src.write_text("user data")
    protect_inputs(src)
    with pytest.raises(OutputError, match="refusing to overwrite"):
        write_cog(src, np.zeros(grid.shape, np.float32), grid)
    assert src.read_text() == "user data"


def test_read_dem_nodata_and_resample(tmp_path, grid):
    h = np.full(grid.shape, 100.0, np.float32)
    h[:4] = -9999
    p = tmp_path / "dem.tif"
    with rasterio.open(p, "w", **(grid.rasterio_profile("float32") | {"nodata": -9999})) as ds:
        ds.write(h, 1)
    dem = read_dem(p)
    assert np.isnan(dem.height_m[:4]).all() and np.all(dem.height_m[4:] == 100)
    coarse = AOIGrid.from_bounds(*grid.bounds, 2.0, grid.crs)
    d2 = read_dem(p, grid=coarse, resampling="average")
    assert d2.height_m.shape == coarse.shape and np.nanmax(np.abs(d2.height_m - 100)) < 1e-4
    allbad = tmp_path / "bad.tif"
    with rasterio.open(allbad, "w", **(grid.rasterio_profile("float32") | {"nodata": -9999})) as ds:
        ds.write(np.full(grid.shape, -9999, np.float32), 1)
    with pytest.raises(EmptyDataError, match="no valid heights"):
        read_dem(allbad)
    with pytest.raises(InputFileNotFoundError):
        read_dem(tmp_path / "missing.tif")


def test_read_dem_without_crs(tmp_path):
    p = tmp_path / "nocrs.tif"
    write_image(p, np.ones((1, 8, 8), np.float32))
    with pytest.raises(CRSError, match="no CRS"):
        read_dem(p)


def test_read_image_bit_depth_and_mask(tmp_path):
    a = np.random.default_rng(1).integers(0, 2047, size=(1, 20, 30)).astype(np.uint16)
    a[0, 0, 0] = 0
    p = write_image(tmp_path / "i.tif", a, nodata=0, nbits=11)
    im = read_image(p)
    assert im.bit_depth == 11 and im.data.dtype == np.uint16
    assert not im.valid[0, 0] and im.valid.sum() == a.size - (a == 0).sum()
    z = write_image(tmp_path / "z.tif", np.zeros((1, 4, 4), np.uint16), nodata=0)
    with pytest.raises(EmptyDataError):
        read_image(z)


def test_gpkg_layers_and_styles(tmp_path, grid):
    import geopandas as gpd
    import pandas as pd
    import pyogrio
    import sqlite3
    from shapely.geometry import box

    l, b, r, t = grid.bounds
    gdf = gpd.GeoDataFrame(
        {"building_id": [1, 2]},
        geometry=[box(l + 1, b + 1, l + 5, b + 5), box(l + 10, b + 10, l + 20, b + 20)],
        crs=grid.crs,
    )
    curves = pd.DataFrame({"score": [0.1, 0.2], "q99": [1.0, 2.0]})
    p = write_gpkg(
        tmp_path / "o.gpkg",
        {"buildings": gdf, "curves": curves},
        styles={"buildings": "<qgis><renderer-v2 type='singleSymbol'/></qgis>"},
    )
    names = [n for n, _ in pyogrio.list_layers(p)]
    assert set(names) == {"buildings", "curves", "layer_styles"}
    con = sqlite3.connect(p)
    row = con.execute("select f_table_name, useAsDefault, styleQML from layer_styles").fetchone()
    assert row[0] == "buildings" and row[1] == 1 and "renderer-v2" in row[2]
    back = read_footprints(p, layer="buildings", crs="EPSG:4326")
    assert len(back) == 2 and back.crs.to_epsg() == 4326
    m = polygons_to_mask(gdf, grid)
    assert m.sum() == pytest.approx((4 * 4 + 10 * 10) / 0.25, rel=0.02)


def test_read_footprints_errors(tmp_path):
    import geopandas as gpd
    from shapely.geometry import Point

    with pytest.raises(InputFileNotFoundError):
        read_footprints(tmp_path / "none.gpkg")
    pts = gpd.GeoDataFrame({"a": [1]}, geometry=[Point(0, 0)], crs="EPSG:4326")
    pts.to_file(tmp_path / "pts.gpkg")
    with pytest.raises(EmptyDataError, match="no polygon"):
        read_footprints(tmp_path / "pts.gpkg")


def test_gpkg_mixed_polygons_get_one_declared_type(tmp_path, grid):
    """Regions are Polygon or MultiPolygon: the layer must declare MultiPolygon, not 'Unknown (any)'."""
    import geopandas as gpd
    import pyogrio
    from shapely.geometry import MultiPolygon, box

    l, b, _, _ = grid.bounds
    mixed = gpd.GeoDataFrame(
        {"id": [1, 2]},
        geometry=[
            box(l + 1, b + 1, l + 5, b + 5),
            MultiPolygon([box(l + 10, b + 10, l + 12, b + 12), box(l + 14, b + 14, l + 16, b + 16)]),
        ],
        crs=grid.crs,
    )
    pure = gpd.GeoDataFrame({"id": [1]}, geometry=[box(l + 1, b + 1, l + 5, b + 5)], crs=grid.crs)
    p = write_gpkg(tmp_path / "m.gpkg", {"changes": mixed, "buildings": pure})
    assert pyogrio.read_info(p, layer="changes")["geometry_type"] == "MultiPolygon"
    assert pyogrio.read_info(p, layer="buildings")["geometry_type"] == "Polygon"  # footprints keep their type
