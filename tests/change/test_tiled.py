"""The self-consistency change test tile by tile == change_test + write_change_products."""

from __future__ import annotations

import numpy as np
import pytest
import rasterio
import geopandas as gpd
from affine import Affine

from geocd.change.products import write_change_products
from geocd.change.tiled import change_test_tiled
from geocd.consistency import ChangeParams, ConsistencyParams, change_test, learn_self_consistency
from geocd.tiling.params import TilingParams
from geocd.geodesy import AOIGrid
from geocd.stereo.products import PairDEM, read_pair_dem, write_pair_dem

SHAPE = (150, 140)
GRID = AOIGrid("EPSG:32631", Affine(0.5, 0, 370000.0, 0, -0.5, 4824000.0), SHAPE[1], SHAPE[0])


def _pair(truth, rng, name, epoch, offset=0.0):
    score = rng.uniform(-2.0, 1.0, SHAPE).astype(np.float32)
    sigma_px = 0.1 + 0.3 * (score + 2.0)
    from scipy.ndimage import gaussian_filter

    # errors correlated over a few cells (as matching windows make them): the static comparisons then
    # hold candidate regions, the region test's null
    f = gaussian_filter(rng.normal(size=SHAPE), 1.5)
    err = f / f.std() * sigma_px
    bad = rng.random(SHAPE) < 0.01
    err[bad] += rng.normal(scale=10, size=bad.sum())
    g = np.full(SHAPE, 1.3, np.float32)
    z = truth + err / g + offset
    valid = rng.random(SHAPE) > 0.05
    return PairDEM(
        np.where(valid, z, np.nan).astype(np.float32),
        score,
        g,
        valid,
        GRID,
        name=name,
        epoch=epoch,
        meta={"params": {"window": 2}},
    )


@pytest.fixture(scope="module")
def recs(tmp_path_factory):
    d = tmp_path_factory.mktemp("sc")
    rng = np.random.default_rng(7)
    ta = np.zeros(SHAPE, np.float32)
    tb = ta.copy()
    tb[20:55, 30:70] += 9.0  # a new building across a tile seam
    tb[90:130, 60:100] -= 6.0  # a lowered one
    tb[5:8, 5:120] += 4.0  # a long thin change through many tiles
    A = [_pair(ta, rng, f"A{i}", "A", offset=0.3 * i) for i in range(3)]
    B = [_pair(tb, rng, f"B{i}", "B", offset=-0.2 * i) for i in range(2)]
    model = learn_self_consistency([A, B], ConsistencyParams(n_score_bins=8, min_bin_count=300))
    pa = [write_pair_dem(d / f"{p.name}.tif", p) for p in A]
    pb = [write_pair_dem(d / f"{p.name}.tif", p) for p in B]
    return d, pa, pb, model


@pytest.mark.parametrize("significance", ["region", pytest.param("cell", marks=pytest.mark.slow)])
def test_change_test_tiled_equals_untiled(recs, tmp_path, significance):
    d, pa, pb, model = recs
    params = ChangeParams(significance=significance, confidences=(90.0, 95.0, 99.0))
    A = [read_pair_dem(p) for p in pa]
    B = [read_pair_dem(p) for p in pb]
    res = change_test(A, B, model, params)
    assert res.significance == significance and (res.change == 1).sum() > 500
    write_change_products(
        tmp_path / "untiled", res, GRID, epoch_a="A", epoch_b="B", model=model, prefix="sc", plots=False
    )
    t = change_test_tiled(
        pa,
        pb,
        model,
        tmp_path / "tiled",
        params=params,
        epoch_names=("A", "B"),
        plots=False,
        tiling=TilingParams(tile_size=64, scheduler="sync"),
    )
    assert t.exact and t.vertical_offsets_m == res.vertical_offsets_m
    for name in ("sc_change", "sc_change_mask"):
        with (
            rasterio.open(tmp_path / "untiled" / f"{name}.tif") as a,
            rasterio.open(tmp_path / "tiled" / f"{name}.tif") as b,
        ):
            np.testing.assert_array_equal(a.read(), b.read(), err_msg=name)
            assert a.descriptions == b.descriptions and a.units == b.units and a.tags() == b.tags()
    a = gpd.read_file(tmp_path / "untiled" / "sc_changes.gpkg", layer="changes")
    b = gpd.read_file(tmp_path / "tiled" / "sc_changes.gpkg", layer="changes")
    assert a.equals(b)
    # the large-grid path: rasters and regions written tile by tile, regions merged across seams
    t2 = change_test_tiled(
        pa,
        pb,
        model,
        tmp_path / "large",
        params=params,
        epoch_names=("A", "B"),
        plots=False,
        tiling=TilingParams(tile_size=64, scheduler="sync", exact_grid_cells=1000),
    )
    # one pass more than the exact path (the mask's); the change raster is assembled from the test's own
    # tiles, not from a pass that copies its six bands (a second copy on disk: 9 GB at 20 000² cells)
    assert t2.passes == t.passes + 1
    for name in ("sc_change", "sc_change_mask"):
        with (
            rasterio.open(tmp_path / "untiled" / f"{name}.tif") as x,
            rasterio.open(tmp_path / "large" / f"{name}.tif") as y,
        ):
            np.testing.assert_array_equal(x.read(), y.read(), err_msg=name)
            assert x.descriptions == y.descriptions and x.units == y.units
    c = gpd.read_file(tmp_path / "large" / "sc_changes.gpkg", layer="changes")
    assert len(c) == len(a)
    np.testing.assert_array_equal(c["n_cells"], a["n_cells"])
    for col in ("volume_m3", "volume_sigma_m3", "confidence", "mean_dz_m"):
        np.testing.assert_allclose(c[col], a[col], rtol=1e-9, err_msg=col)


@pytest.mark.slow
def test_tiled_calibration_of_a_transferred_model_equals_untiled(recs, tmp_path):
    """The transfer calibration is a whole-scene fit: the tiled test gathers every tile's cells for it (slopes with
    one cell of overlap) and gets the untiled products exactly."""
    import copy

    d, pa, pb, model = recs
    foreign = copy.deepcopy(model)
    foreign.provenance["comparisons"] = ["other_a vs other_b"]  # learned elsewhere: auto calibrates
    params = ChangeParams(confidences=(90.0, 95.0, 99.0))
    res = change_test([read_pair_dem(p) for p in pa], [read_pair_dem(p) for p in pb], foreign, params)
    assert res.calibration is not None
    write_change_products(
        tmp_path / "untiled", res, GRID, epoch_a="A", epoch_b="B", model=foreign, prefix="sc", plots=False
    )
    t = change_test_tiled(
        pa,
        pb,
        foreign,
        tmp_path / "tiled",
        params=params,
        epoch_names=("A", "B"),
        plots=False,
        tiling=TilingParams(tile_size=64, scheduler="sync"),
    )
    assert t.exact and t.summary["calibration"] == res.calibration.to_dict()
    for name in ("sc_change", "sc_change_mask"):
        with (
            rasterio.open(tmp_path / "untiled" / f"{name}.tif") as a,
            rasterio.open(tmp_path / "tiled" / f"{name}.tif") as b,
        ):
            np.testing.assert_array_equal(a.read(), b.read(), err_msg=name)
            assert a.tags() == b.tags() and "model_calibration" in a.tags()


@pytest.mark.slow
def test_tiled_building_layer_follows_the_schema(recs, tmp_path):
    """`geocd change --tiled --footprints` writes the one building layer: on the exact path the in-memory layer
    (footprints and the new buildings of the change map outside them), on the large-grid path footprint by
    footprint (heights above a ring around each footprint; no search for new buildings) with the same classes."""
    from shapely.geometry import box

    from geocd.change.building_layer import check_building_layer
    from geocd.change.dsm_buildings import building_layer
    from geocd.stereo.surface import epoch_surface

    d, pa, pb, model = recs
    t = GRID.transform

    def cells(r0, r1, c0, c1):
        return box(t.c + c0 * 0.5, t.f - r1 * 0.5, t.c + c1 * 0.5, t.f - r0 * 0.5)

    fps = gpd.GeoDataFrame(
        {"id": [5, 6]}, geometry=[cells(92, 128, 62, 98), cells(60, 85, 100, 130)], crs=GRID.crs
    )  # the lowered block, a static one
    fp_path = tmp_path / "fp.gpkg"
    fps.to_file(fp_path, driver="GPKG")
    params = ChangeParams(confidences=(90.0, 95.0, 99.0))
    A, B = [read_pair_dem(p) for p in pa], [read_pair_dem(p) for p in pb]
    res = change_test(A, B, model, params)
    mem, _ = building_layer(fps, res, GRID, z_a=epoch_surface(A), z_b=epoch_surface(B), model=model)
    layers = {}
    for name, cells_max in (("exact", None), ("large", 1000)):
        tiling = TilingParams(tile_size=64, scheduler="sync", **({"exact_grid_cells": cells_max} if cells_max else {}))
        change_test_tiled(
            pa,
            pb,
            model,
            tmp_path / name,
            params=params,
            epoch_names=("A", "B"),
            plots=False,
            tiling=tiling,
            footprints=str(fp_path),
        )
        layers[name] = gpd.read_file(tmp_path / name / "sc_changes.gpkg", layer="buildings")
        check_building_layer(layers[name])
    ex, lg = layers["exact"], layers["large"]
    assert list(ex["class"]) == list(mem["class"]) and list(ex["building_id"]) == list(mem["building_id"])
    np.testing.assert_allclose(ex["volume_change_m3"], mem["volume_change_m3"])
    # the new building and the thin raised strip stand outside both footprints
    assert list(ex["source"]) == ["footprints", "footprints", "change map", "change map"]
    assert list(ex["class"]) == ["collapsed", "unchanged", "new", "new"]  # the block sank 6 m below the ground
    assert ex["area_m2"].iloc[2] == pytest.approx(35 * 40 * 0.25, rel=0.1)
    assert list(lg["building_id"]) == [5, 6] and list(lg["class"]) == list(ex["class"][:2])
    assert list(lg["confidence_pct"]) == list(ex["confidence_pct"][:2])
    assert lg["height_before_m"].iloc[0] == pytest.approx(0, abs=1) and lg["height_after_m"].iloc[0] < -4


@pytest.mark.slow
def test_cli_change_footprints_writes_the_building_layer(recs, tmp_path):
    """`geocd change --footprints` in memory: the same building layer as the tiled exact path."""
    from click.testing import CliRunner
    from shapely.geometry import box

    from geocd.change.building_layer import check_building_layer
    from geocd.cli import main

    d, pa, pb, model = recs
    t = GRID.transform
    fps = gpd.GeoDataFrame(
        {"id": [5]}, geometry=[box(t.c + 62 * 0.5, t.f - 128 * 0.5, t.c + 98 * 0.5, t.f - 92 * 0.5)], crs=GRID.crs
    )
    fps.to_file(tmp_path / "fp.gpkg", driver="GPKG")
    mp = model.save(tmp_path / "model.json")
    out = {}
    for name, extra in (("mem", []), ("tiled", ["--tiled", "--tile-size", "64", "--scheduler", "sync"])):
        args = [
            "change",
            *sum((["--pair-dem-a", str(p)] for p in pa), []),
            *sum((["--pair-dem-b", str(p)] for p in pb), []),
        ]
        args += ["--model", str(mp), "--footprints", str(tmp_path / "fp.gpkg"), "--out", str(tmp_path / name)]
        r = CliRunner().invoke(main, [*args, *extra])
        assert r.exit_code == 0, r.output
        out[name] = gpd.read_file(tmp_path / name / "sc_changes.gpkg", layer="buildings")
        check_building_layer(out[name])
    assert list(out["mem"]["class"]) == list(out["tiled"]["class"]) == ["collapsed", "new", "new"]
    np.testing.assert_allclose(out["mem"]["volume_change_m3"], out["tiled"]["volume_change_m3"])
