"""The change layers: every file readable by rasterio/OGR, styled, written atomically."""

import sqlite3

import numpy as np
import pyogrio
import pytest
import rasterio

from geocd.change.products import write_change_products
from geocd.consistency import CHANGE_NODATA, learn_self_consistency, change_test
from geocd.geodesy import AOIGrid
from tests.test_consistency import SHAPE, make_rec


@pytest.fixture
def result():
    rng = np.random.default_rng(3)
    grid = AOIGrid.from_bounds(500000, 4000000, 500000 + SHAPE[1] * 0.5, 4000000 + SHAPE[0] * 0.5, 0.5, "EPSG:32631")
    ta = np.zeros(SHAPE, np.float32)
    tb = ta.copy()
    tb[20:50, 20:50] += 9
    A = [make_rec(ta, rng, f"A{i}", outlier_frac=0.05) for i in range(3)]
    B = [make_rec(tb, rng, f"B{i}", outlier_frac=0.05) for i in range(3)]
    for r in A + B:
        r.grid = grid
    model = learn_self_consistency([A, B])
    return change_test(A, B, model), model, grid


def test_products_are_readable_and_styled(tmp_path, result):
    import geopandas as gpd
    from shapely.geometry import box

    res, model, grid = result
    l, b, r, t = grid.bounds
    fps = gpd.GeoDataFrame(
        {"building_id": [7, 8]},
        geometry=[box(l + 10, t - 25, l + 25, t - 10), box(l + 40, b + 5, l + 50, b + 15)],
        crs=grid.crs,
    )
    from geocd.change.building_layer import check_building_layer
    from geocd.change.buildings import classify_buildings
    from geocd.change.dsm_buildings import footprint_layer

    za = np.zeros(SHAPE, np.float32)
    bld = footprint_layer(
        fps, res, grid, z_a=za, z_b=za + res.dz_m, report_confidence=95, model=model, id_field="building_id"
    )
    # only the building layer's schema is written
    raw = classify_buildings(fps, res.changed_at(95), res.dz_m, grid, z_a=za, id_field="building_id")
    with pytest.raises(ValueError, match="does not follow the schema"):
        write_change_products(tmp_path / "raw", res, grid, buildings=raw, region_confidence=95, plots=False)
    paths = write_change_products(tmp_path, res, grid, model=model, buildings=bld, region_confidence=95, prefix="sc")
    with rasterio.open(paths["change"]) as ds:
        assert ds.descriptions == ("dz_m", "dtilde", "score", "confidence", "cell_confidence", "dz_sigma_m")
        assert ds.units == ("m", "px", "bit/px", "%", "%", "m")
        assert all(ds.tags(i).get("long_name") for i in range(1, ds.count + 1))
        assert ds.tags()["method"] == "self-consistency"
    with rasterio.open(paths["change_mask"]) as ds:
        m = ds.read(1)
        assert ds.nodata == CHANGE_NODATA and set(np.unique(m)) <= {-128, -1, 0, 1}
        assert ds.tags()["mask_confidence_pct"] == "95"
        assert ds.descriptions == ("change",) and ds.units == ("class",) and "raised" in ds.tags(1)["long_name"]
    # the mask is the map at the reported confidence, not at the lowest tested level
    assert (res.changed_at(90) != res.changed_at(95)).any()
    assert np.array_equal(m, res.changed_at(95))
    assert (tmp_path / "sc_change_mask.qml").exists() and (tmp_path / "sc_change.qml").exists()
    layers = dict(pyogrio.list_layers(paths["changes"]))
    assert {"changes", "buildings", "curves", "layer_styles"} <= set(layers)
    ch = gpd.read_file(paths["changes"], layer="changes")
    assert len(ch) >= 1 and (ch["sign"] == 1).any()
    big = ch.loc[ch["area_m2"].idxmax()]
    assert big["area_m2"] == pytest.approx(15 * 15, rel=0.25) and big["mean_dz_m"] == pytest.approx(9, abs=1.5)
    # percent, the region test's; σ of the volume from the error model (finite in every row)
    assert (ch["confidence"] >= 95).all() and (ch["confidence"] <= 100).all()
    assert np.isfinite(ch["volume_sigma_m3"]).all() and (ch["volume_sigma_m3"] > 0).all()
    assert big["volume_sigma_m3"] < 0.2 * abs(big["volume_m3"])
    b = gpd.read_file(paths["changes"], layer="buildings")
    check_building_layer(b)
    assert list(b["class"]) == ["new", "unchanged"] and list(b["confidence_pct"]) == [99.0, 0.0]
    styles = sqlite3.connect(paths["changes"]).execute("select f_table_name from layer_styles").fetchall()
    assert {s[0] for s in styles} == {"changes", "buildings"}
    assert paths["scatter"].stat().st_size > 10_000 and paths["quicklook"].stat().st_size > 10_000
    assert not list(tmp_path.glob(".*part*"))


def test_every_cog_band_has_a_name_and_a_unit_where_one_is_known(tmp_path):
    from geocd.io.raster import write_cog

    grid = AOIGrid.from_bounds(500000, 4000000, 500050, 4000050, 0.5, "EPSG:32631")
    z = np.zeros(grid.shape, np.float32)
    p1 = write_cog(tmp_path / "a.tif", {"dz_m": z, "confidence": z, "volume_m3": z, "score": z}, grid)
    p2 = write_cog(tmp_path / "dsm_A.tif", z, grid, tags={"units": "metre"})
    p3 = write_cog(tmp_path / "mask.tif", z.astype(np.int8), grid, dtype="int8", tags={"units": "m"})
    p4 = write_cog(tmp_path / "b.tif", {"z": z}, grid, units={"z": "m (ellipsoidal)"})
    with rasterio.open(p1) as ds:
        assert ds.descriptions == ("dz_m", "confidence", "volume_m3", "score") and ds.units == ("m", "%", "m3", None)
    with rasterio.open(p2) as ds:
        assert ds.descriptions == ("dsm_A",) and ds.units == ("m",)
    with rasterio.open(p3) as ds:  # an integer mask does not take the dataset's metre
        assert ds.descriptions == ("mask",) and ds.units == (None,)
    with rasterio.open(p4) as ds:
        assert ds.units == ("m (ellipsoidal)",)
