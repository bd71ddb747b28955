"""Tiled DEM differencing == the untiled pipeline (bit-identical products up to the exact-size limits)."""

from __future__ import annotations

import json
from pathlib import Path

import geopandas as gpd
import numpy as np
import pytest
import rasterio

from geocd.demdiff import CoregParams, DEMDiffParams, dem_difference, write_demdiff_products
from geocd.demdiff.tiled import dem_difference_tiled
from geocd.tiling.params import TilingParams, keep_cells
from geocd.io.raster import read_dem, write_cog

from ..conftest import shared_data
from .synthetic import grid, pair

RASTERS = ("dh", "significance", "change_mask")
LAYERS = ("changes", "summary", "error_model", "variogram", "buildings")


def assert_same_products(d1: Path, d2: Path, prefix: str = "demdiff") -> None:
    """Every raster band, tag and description, every GeoPackage layer and the report (but its wall time)."""
    for name in RASTERS:
        with rasterio.open(d1 / f"{prefix}_{name}.tif") as a, rasterio.open(d2 / f"{prefix}_{name}.tif") as b:
            np.testing.assert_array_equal(a.read(), b.read(), err_msg=name)
            assert a.units == b.units
            assert (
                a.tags() == b.tags()
                and a.descriptions == b.descriptions
                and a.nodata is b.nodata
                or (np.isnan(a.nodata) and np.isnan(b.nodata))
                or a.nodata == b.nodata
            )
            assert a.profile["blockxsize"] == b.profile["blockxsize"] and a.overviews(1) == b.overviews(1)
        assert (d1 / f"{prefix}_{name}.qml").read_text() == (d2 / f"{prefix}_{name}.qml").read_text()
    r1 = json.loads((d1 / f"{prefix}_report.json").read_text())
    r2 = json.loads((d2 / f"{prefix}_report.json").read_text())
    r1["summary"].pop("wall_s")
    r2["summary"].pop("wall_s")
    assert r1 == r2
    import pyogrio

    layers = {n for n, _ in pyogrio.list_layers(d1 / f"{prefix}_changes.gpkg")}
    assert layers == {n for n, _ in pyogrio.list_layers(d2 / f"{prefix}_changes.gpkg")}
    for layer in LAYERS:
        if layer in layers:
            a = gpd.read_file(d1 / f"{prefix}_changes.gpkg", layer=layer)
            b = gpd.read_file(d2 / f"{prefix}_changes.gpkg", layer=layer)
            assert a.equals(b), layer


@pytest.fixture(scope="module")
def shifted_pair(tmp_path_factory):
    d = tmp_path_factory.mktemp("pair")
    a, b, info = pair(shift_m=(4.0, -3.0, 1.5), bump_m=20.0, g=grid(170, 150), seed=2)
    write_cog(d / "a.tif", a.height_m, a.grid)
    write_cog(d / "b.tif", b.height_m, b.grid)
    return d


@pytest.mark.slow
@pytest.mark.parametrize("case", ["default", "tilt"])
def test_tiled_equals_untiled_bitwise(shifted_pair, tmp_path, case):
    params = DEMDiffParams() if case == "default" else DEMDiffParams(coreg=CoregParams(tilt=True))
    d = shifted_pair
    res = dem_difference(read_dem(d / "a.tif"), read_dem(d / "b.tif"), params=params)
    assert res.coreg.status == "ok" and abs(res.coreg.shift_m[0] + 4.0) < 0.1 and res.summary["changed_cells"] > 100
    write_demdiff_products(tmp_path / "untiled", res)
    # 3 × 3 tiles of 64 cells; every whole-scene step gathers every cell (exact)
    t = dem_difference_tiled(
        d / "a.tif", d / "b.tif", tmp_path / "tiled", params=params, tiling=TilingParams(tile_size=64, scheduler="sync")
    )
    assert t.exact and t.passes >= 8
    assert_same_products(tmp_path / "untiled", tmp_path / "tiled")
    assert not (tmp_path / "tiled" / ".geocd-work").exists()


def test_tiled_building_layer_equals_untiled(shifted_pair, tmp_path):
    """With footprints both paths write the one building layer; footprint by footprint on windows (tiled) the
    rows of the footprints are the untiled ones (heights above a ring around each footprint in both); only the
    untiled layer searches the change map for new buildings outside them."""
    from shapely.geometry import box

    from geocd.change.building_layer import check_building_layer

    d = shifted_pair
    a, b = read_dem(d / "a.tif"), read_dem(d / "b.tif")
    l, bt, r, t = a.grid.bounds
    cx, cy = (l + r) / 2, (bt + t) / 2
    fp = gpd.GeoDataFrame(
        {"id": [3, 4]},
        geometry=[box(cx - 30, cy - 30, cx + 30, cy + 30), box(l + 20, bt + 20, l + 60, bt + 60)],
        crs=a.grid.crs,
    )
    res = dem_difference(a, b)
    write_demdiff_products(tmp_path / "untiled", res, footprints=fp, plots=False)
    dem_difference_tiled(
        d / "a.tif",
        d / "b.tif",
        tmp_path / "tiled",
        footprints=fp,
        plots=False,
        tiling=TilingParams(tile_size=64, scheduler="sync", exact_grid_cells=1000),
    )
    u = gpd.read_file(tmp_path / "untiled" / "demdiff_changes.gpkg", layer="buildings")
    tl = gpd.read_file(tmp_path / "tiled" / "demdiff_changes.gpkg", layer="buildings")
    check_building_layer(u)
    check_building_layer(tl)
    fpu = u[u["source"] == "footprints"].reset_index(drop=True)
    assert list(fpu["building_id"]) == list(tl["building_id"]) == [3, 4]
    assert list(fpu["class"]) == list(tl["class"])
    for c in ("confidence_pct", "frac_changed", "height_before_m", "height_after_m", "volume_change_m3"):
        np.testing.assert_allclose(fpu[c], tl[c], err_msg=c)


@pytest.mark.slow
def test_tiled_threads_and_user_mask(shifted_pair, tmp_path):
    from shapely.geometry import box

    d = shifted_pair
    a = read_dem(d / "a.tif")
    l, bt, r, t = a.grid.bounds
    poly = gpd.GeoDataFrame(geometry=[box(l, bt, l + 0.55 * (r - l), t)], crs=a.grid.crs)
    poly.to_file(tmp_path / "mask.gpkg")
    res = dem_difference(a, read_dem(d / "b.tif"), stable_mask=poly)
    write_demdiff_products(tmp_path / "untiled", res)
    dem_difference_tiled(
        d / "a.tif",
        d / "b.tif",
        tmp_path / "tiled",
        stable_mask=tmp_path / "mask.gpkg",
        tiling=TilingParams(tile_size=64, scheduler="threads", n_workers=2),
    )
    assert_same_products(tmp_path / "untiled", tmp_path / "tiled")


def test_keep_cells_is_a_fixed_uniform_subsample():
    r, c = np.mgrid[0:400, 0:500]
    k = keep_cells(r, c, 500, 0.1)
    assert abs(k.mean() - 0.1) < 0.005
    # the same cells whatever the order or the window they are asked in
    np.testing.assert_array_equal(k[100:200, 250:300], keep_cells(r[100:200, 250:300], c[100:200, 250:300], 500, 0.1))
    assert keep_cells(r, c, 500, 1.0).all()


@pytest.mark.realdata
@pytest.mark.slow
def test_tiled_msh_with_base_equals_untiled(tmp_path):
    from geocd.demdiff.align import align_dems
    from geocd.demdiff.timeseries import survey_footprint
    from geocd.io.e00 import read_e00_dem

    pa = shared_data("usgs_msh_dome_dems", "geotiff_utm10n", "26.tif")
    pb = shared_data("usgs_msh_dome_dems", "geotiff_utm10n", "27.tif")
    pbase = shared_data("usgs_msh_dome_dems", "raw_e00", "1_msh00_83.e00")
    A, B = read_dem(pa), read_dem(pb)
    pr = align_dems(A, B, A.grid, crop=False)
    bh = align_dems(A, read_e00_dem(pbase), A.grid, crop=False).height_b_m
    obs = survey_footprint(pr.height_a_m, bh) & survey_footprint(pr.height_b_m, bh)
    res = dem_difference(pr, observed=obs)
    assert res.coreg.status == "not_improving" and res.summary["changed_cells"] > 3000
    write_demdiff_products(tmp_path / "untiled", res)
    dem_difference_tiled(pa, pb, tmp_path / "tiled", base=pbase, tiling=TilingParams(tile_size=100, scheduler="sync"))
    assert_same_products(tmp_path / "untiled", tmp_path / "tiled")


@pytest.mark.slow
def test_large_path_equals_untiled(shifted_pair, tmp_path):
    """Products tile by tile, regions merged across seams, correlated sums on tiles + a coarse grid: the
    same rasters, the same regions and the same figures to 1e-9 (floating-point summation order)."""
    d = shifted_pair
    res = dem_difference(read_dem(d / "a.tif"), read_dem(d / "b.tif"))
    write_demdiff_products(tmp_path / "untiled", res)
    t = dem_difference_tiled(
        d / "a.tif",
        d / "b.tif",
        tmp_path / "tiled",
        tiling=TilingParams(tile_size=64, scheduler="sync", exact_grid_cells=5000, coarse_cells=2000),
    )
    assert not t.exact
    for name in RASTERS:
        with (
            rasterio.open(tmp_path / "untiled" / f"demdiff_{name}.tif") as a,
            rasterio.open(tmp_path / "tiled" / f"demdiff_{name}.tif") as b,
        ):
            np.testing.assert_array_equal(a.read(), b.read(), err_msg=name)
            assert a.descriptions == b.descriptions and a.units == b.units
    u = res.summary
    s = t.summary
    for k, v in u.items():
        if k == "wall_s" or not isinstance(v, (int, float)):
            continue
        assert s[k] == pytest.approx(v, rel=1e-9, abs=1e-12, nan_ok=True), k
    a = gpd.read_file(tmp_path / "untiled" / "demdiff_changes.gpkg", layer="changes")
    b = gpd.read_file(tmp_path / "tiled" / "demdiff_changes.gpkg", layer="changes")
    assert len(a) == len(b) > 3
    np.testing.assert_array_equal(a["n_cells"], b["n_cells"])
    for c in ("volume_m3", "volume_sigma_m3", "confidence", "mean_dz_m"):
        np.testing.assert_allclose(b[c], a[c], rtol=1e-9, err_msg=c)
    assert all(ga.symmetric_difference(gb).area < 1e-6 for ga, gb in zip(a.geometry, b.geometry))


@pytest.mark.parametrize("exact", [True, False])
@pytest.mark.slow
def test_region_test_tiled_equals_untiled(shifted_pair, tmp_path, exact):
    """The noise region test tiled: exact path bit-identical; large path (a first pass for the regions' mass,
    the products pass dropping them across seams) gives the same rasters, regions and figures."""
    d = shifted_pair
    params = DEMDiffParams(region_test="noise")
    res = dem_difference(read_dem(d / "a.tif"), read_dem(d / "b.tif"), params=params)
    assert res.summary["region_test"]["regions_dropped"] > 0
    write_demdiff_products(tmp_path / "untiled", res)
    tiling = (
        TilingParams(tile_size=64, scheduler="sync")
        if exact
        else TilingParams(tile_size=64, scheduler="sync", exact_grid_cells=5000, coarse_cells=2000)
    )
    t = dem_difference_tiled(d / "a.tif", d / "b.tif", tmp_path / "tiled", params=params, tiling=tiling)
    assert t.exact is exact
    if exact:
        assert_same_products(tmp_path / "untiled", tmp_path / "tiled")
        return
    for name in RASTERS:
        with (
            rasterio.open(tmp_path / "untiled" / f"demdiff_{name}.tif") as a,
            rasterio.open(tmp_path / "tiled" / f"demdiff_{name}.tif") as b,
        ):
            np.testing.assert_array_equal(a.read(), b.read(), err_msg=name)
    assert t.summary["region_test"] == res.summary["region_test"]
    for k in ("changed_cells", "volume_changed_m3", "volume_changed_sigma_m3"):
        assert t.summary[k] == pytest.approx(res.summary[k], rel=1e-9), k
    a = gpd.read_file(tmp_path / "untiled" / "demdiff_changes.gpkg", layer="changes")
    b = gpd.read_file(tmp_path / "tiled" / "demdiff_changes.gpkg", layer="changes")
    assert len(a) == len(b) == len(res.regions)
    np.testing.assert_array_equal(a["n_cells"], b["n_cells"])
    np.testing.assert_allclose(b["volume_sigma_m3"], a["volume_sigma_m3"], rtol=1e-9)
