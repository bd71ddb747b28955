"""The reusable sweep machinery and the pair-DEM product."""

import numpy as np
import pytest
import rasterio

from tests.conftest import shared_data

from geocd.stereo import BANDS, HeightSearch, PlaneSweep, iter_tiles, read_pair_dem, write_pair_dem


def test_tiles_cover_the_grid_once():
    tiles = iter_tiles((70, 45), 32, 3)
    cover = np.zeros((70, 45), int)
    for t in tiles:
        cover[t.core] += 1
        assert t.outer[0].start <= t.core[0].start and t.outer[1].stop >= t.core[1].stop
        assert t.inner[0].stop - t.inner[0].start == t.core[0].stop - t.core[0].start
    assert (cover == 1).all()


def test_plane_sweep_warps_each_image_at_each_plane(scene, chips):
    search = HeightSearch.uniform(scene.grid.shape, 195.0, 200.0, 1.0)
    sweep = PlaneSweep(scene.grid, chips, scene.cameras, search, tile_size=40, margin=2)
    seen = []
    for tile in sweep.tiles():
        assert sweep.k_range(tile) == (0, 6)
        for sl in sweep.slices(tile):
            assert sl.stack.shape == (2, *tile.outer_shape)
            if sl.k == 3:
                full = sweep.warp_at(np.full(scene.grid.shape, sl.height_m))
                np.testing.assert_allclose(
                    sl.stack[:, tile.inner[0], tile.inner[1]], full[:, tile.core[0], tile.core[1]], atol=1e-3
                )
            seen.append((tile.index, sl.k, sl.height_m))
    assert {h for _, _, h in seen} == {195.0, 196.0, 197.0, 198.0, 199.0, 200.0}
    assert sweep.n_evaluations() == scene.grid.width * scene.grid.height * 6


def test_height_search_per_cell_ranges():
    lo = np.array([[0.0, 10.0], [np.nan, 3.3]])
    hi = np.array([[5.0, 12.0], [4.0, 3.4]])
    s = HeightSearch(lo, hi, 1.0)
    np.testing.assert_array_equal(s.kmin(), [[0, 10], [0, 4]])
    np.testing.assert_array_equal(s.kmax(), [[5, 12], [-1, 4]])
    assert s.height(2.5) == 2.5


def test_pair_dem_round_trip(tmp_path, pair_dem):
    p = write_pair_dem(tmp_path / "a__b.tif", pair_dem, tags={"images": ["a.tif", "b.tif"]})
    with rasterio.open(p) as ds:
        assert ds.descriptions == BANDS
        assert ds.tags()["geocd_product"] == "stereo_pair"
        assert ds.profile["tiled"]
    back = read_pair_dem(p)
    assert back.grid.same_as(pair_dem.grid)
    np.testing.assert_array_equal(back.valid, pair_dem.valid)
    np.testing.assert_array_equal(back.z_m, pair_dem.z_m)
    np.testing.assert_array_equal(back.g_px_per_m, pair_dem.g_px_per_m)
    np.testing.assert_array_equal(back.flags, pair_dem.flags)
    assert back.camera_names == pair_dem.camera_names
    assert back.meta["score_kind"] == "mdl" and back.name == pair_dem.name


def test_pair_dem_feeds_the_consistency_test(pair_dem):
    """The consumer (issue 5) takes PairDEMs as they are."""
    from geocd.consistency import match_pairs

    dt, score, dz, both = match_pairs(pair_dem, pair_dem)
    assert both.sum() == pair_dem.valid.sum()
    assert np.nanmax(np.abs(dt)) == 0.0


@pytest.mark.realdata
def test_projection_interpolation_is_within_tolerance():
    """Real RPCs (s2p Pléiades crop): interpolated planes agree with exact projection."""
    import rasterio

    from geocd.camera import RPCModel
    from geocd.geodesy import AOIGrid
    from geocd.stereo import ImageChip

    path = shared_data("s2p_pleiades", "input_pair", "img_01.tif")
    with rasterio.open(path) as ds:
        cam = RPCModel.from_rasterio(ds.rpcs, width=ds.width, height=ds.height)
        img = ds.read(1).astype(np.float32)
    grid = AOIGrid.from_bounds(359800, 7651600, 359900, 7651700, 0.5, "EPSG:32740")
    chip = ImageChip(img)
    search = HeightSearch.uniform(grid.shape, 2250.0, 2400.0, 1.5)
    fast = PlaneSweep(grid, [chip], [cam], search, tile_size=64)
    exact = PlaneSweep(grid, [chip], [cam], search, tile_size=64, interp_tol_px=0)
    t = fast.tiles()[0]
    proj = fast.projectors(t)
    assert fast.interval(proj, *fast.k_range(t)) == 16
    for a, b in zip(fast.slices(t), exact.slices(t)):
        d = np.abs(a.stack - b.stack)
        assert np.nanmax(d) < 0.05 * np.nanstd(img)  # a hundredth of a pixel of shift
