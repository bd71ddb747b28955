"""The surface after the tests: the valid-height median (kernel vs numpy reference) and narrow-hole filling."""

import numpy as np
import pytest

from geocd.errors import ConfigError
from geocd.pipeline import RunConfig
from geocd.stereo import FLAGS, StereoParams, match_pair
from geocd.stereo import _kernels as K
from geocd.stereo.surface import fill_narrow_holes, narrow_holes, surface_median


@pytest.mark.parametrize("r", [1, 2, 3])
def test_valid_median_kernel_agrees_with_numpy(r):
    rng = np.random.default_rng(r)
    z = rng.normal(100.0, 3.0, (37, 53))
    z[rng.random(z.shape) < 0.35] = np.nan
    z[:4, :6] = np.nan  # a window with no valid value around valid cells
    out = np.empty_like(z)
    K.valid_median(z, r, out)
    ref = K.valid_median_ref(z, r)
    assert np.array_equal(np.isnan(out), np.isnan(z)) and np.array_equal(np.isnan(ref), np.isnan(z))
    np.testing.assert_allclose(out, ref, rtol=0, atol=1e-12)


def test_surface_median_removes_outliers_and_keeps_a_step():
    z = np.where(np.arange(40)[None, :] < 20, 10.0, 30.0) * np.ones((30, 1))
    z[10, 5] = 500.0  # an isolated wrong match
    z[12, 25] = np.nan
    m = surface_median(z, 7)
    assert m[10, 5] == 10.0 and np.isnan(m[12, 25])
    ok = np.isfinite(z)
    assert (m[:, :20][ok[:, :20]] == 10.0).all()  # a step between flat surfaces stays where it is
    assert (m[:, 20:][ok[:, 20:]] == 30.0).all()
    np.testing.assert_array_equal(surface_median(z, 1), z)
    with pytest.raises(ConfigError):
        surface_median(z, 4)
    with pytest.raises(ConfigError):
        StereoParams(surface_median=2)
    assert StereoParams().median_size == 7 and StereoParams(window=9).median_size == 9
    assert StereoParams(surface_median=1).median_size == 1


def test_narrow_holes_are_the_ones_within_a_window_radius():
    valid = np.ones((60, 60), bool)
    valid[10:15, 10:17] = False  # 5 × 7: no cell more than 3 from a valid one → filled
    valid[30:45, 30:45] = False  # 15 × 15: its centre is 8 cells from valid ones → kept empty
    valid[0:3, 40:44] = False  # touches the border: an open edge, not a hole
    valid[50, 5] = False  # one cell
    h = narrow_holes(valid, 3)
    assert h[10:15, 10:17].all() and h[50, 5]
    assert not h[30:45, 30:45].any() and not h[0:3, 40:44].any() and not h[valid].any()
    assert not narrow_holes(valid, 0).any()


def test_fill_narrow_holes_interpolates_a_plane():
    y, x = np.mgrid[0:50, 0:50].astype(float)
    z = 100.0 + 0.3 * x - 0.2 * y
    valid = np.ones(z.shape, bool)
    valid[20:25, 20:26] = False
    valid[5:25, 35:45] = False  # too wide for radius 3
    zf, filled = fill_narrow_holes(np.where(valid, z, np.nan), valid, 3)
    assert filled[20:25, 20:26].all() and not filled[5:25, 35:45].any() and not filled[valid].any()
    assert np.abs(zf - z)[filled].max() < 0.5  # inverse-distance weighting of a plane: close
    assert np.isnan(zf[5:25, 35:45]).all() and np.array_equal(zf[valid], z[valid])


def test_filled_cells_are_flagged_invalid_with_heights(scene, chips, pair_dem):
    pd = pair_dem
    filled = (pd.flags & FLAGS["filled"]) > 0
    assert filled.any()
    assert not pd.valid[filled].any() and np.isfinite(pd.z_m[filled]).all()
    assert (pd.flags[filled] & ~np.uint8(FLAGS["filled"])).all()  # the reason it is invalid is kept
    # interpolated, never extrapolated: within the valid heights around (here the holes sit at the buildings'
    # edges, between roof and ground: a median 2–3 m off the truth, which is why they are never valid)
    from scipy import ndimage

    zv = np.where(pd.valid, pd.z_m, np.nan).astype(float)
    lo = ndimage.minimum_filter(np.where(pd.valid, zv, np.inf), size=4 * 3 + 3)
    hi = ndimage.maximum_filter(np.where(pd.valid, zv, -np.inf), size=4 * 3 + 3)
    assert ((pd.z_m >= lo - 1e-3) & (pd.z_m <= hi + 1e-3))[filled].all()
    off = match_pair(
        chips[0],
        chips[1],
        scene.cameras[0],
        scene.cameras[1],
        scene.grid,
        params=StereoParams(height_range_m=(185.0, 225.0), fill_holes=False),
    )
    assert not (off.flags & FLAGS["filled"]).any()
    np.testing.assert_array_equal(off.valid, pd.valid)
    assert np.isnan(off.z_m[~off.valid]).all()


def test_the_change_run_reads_each_cells_own_match():
    assert RunConfig().stereo.surface_median == 1
    assert RunConfig.from_dict({"stereo": {"window": 9}}).stereo.surface_median == 1
    assert RunConfig.from_dict({"stereo": {"surface_median": 5}}).stereo.surface_median == 5
    # nor a validity that depends on the neighbours' heights
    assert RunConfig().stereo.isolation_cells == 1 and StereoParams().isolation_cells == 49


def test_change_commands_warn_about_smoothed_pair_dems(tmp_path):
    import warnings

    from geocd.cli.change import _read_pairs
    from geocd.geodesy import AOIGrid, as_crs
    from geocd.stereo import PairDEM, write_pair_dem

    grid = AOIGrid.from_bounds(500000.0, 4000000.0, 500010.0, 4000010.0, 0.5, as_crs("EPSG:32631"))
    z = np.full(grid.shape, 100.0, np.float32)
    paths = {}
    for label, sm, iso in (("smoothed", None, 1), ("isolated", 1, None), ("own", 1, 1)):
        pd = PairDEM(
            z_m=z,
            score=z * 0,
            g_px_per_m=z * 0 + 1,
            valid=np.ones(grid.shape, bool),
            grid=grid,
            name=label,
            meta={"params": StereoParams(surface_median=sm, isolation_min_cells=iso).to_dict()},
        )
        paths[label] = write_pair_dem(tmp_path / f"{label}.tif", pd)
    with pytest.warns(UserWarning, match="surface median"):
        _read_pairs([paths["smoothed"], paths["own"]])
    with pytest.warns(UserWarning, match=r"isolated were matched with the neighbour-agreement test"):
        _read_pairs([paths["isolated"], paths["own"]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _read_pairs([paths["own"]])


def test_ground_height_hint_uses_matches_flagged_only_for_an_incomplete_search():
    """Over the cameras' whole height range most cells leave an image at some heights (range_limit); the hint
    still reads their heights, but not those at the range's ends nor cells failing another test."""
    from geocd.geodesy import AOIGrid, as_crs
    from geocd.stereo import PairDEM
    from geocd.stereo.scene import _hint_from_match

    grid = AOIGrid.from_bounds(500000.0, 4000000.0, 500020.0, 4000020.0, 1.0, as_crs("EPSG:32631"))
    z_raw = np.full(grid.shape, 2300.0, np.float32)
    flags = np.full(grid.shape, FLAGS["range_limit"], np.uint8)
    z_raw[:2] = 2609.0  # at the range's top: no minimum
    z_raw[2:4] = 50.0
    flags[2:4] |= FLAGS["not_unique"]  # fails another test
    nan = np.full(grid.shape, np.nan, np.float32)
    pd = PairDEM(
        z_m=nan,
        score=nan,
        g_px_per_m=nan + 1,
        valid=np.zeros(grid.shape, bool),
        grid=grid,
        flags=flags,
        z_raw_m=z_raw,
        meta={"step_m": 2.0, "levels": 3},
    )
    assert _hint_from_match(pd, -20.0, 2610.0, 1295.0) == pytest.approx(2300.0)
    pd.flags[:] |= FLAGS["low_ncc"]
    assert _hint_from_match(pd, -20.0, 2610.0, 1295.0) == 1295.0
