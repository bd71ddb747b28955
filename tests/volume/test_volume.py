"""End-to-end behaviour of geocd.volume on the tiny town of toyscene.py (frame cameras, boxes on a plane)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from geocd.change.metrics import roc_curve
from geocd.errors import CameraError, CancelledError, CRSError, NoOverlapError, ProcessingError
from geocd.geodesy import AOIGrid, to_lonlat
from geocd.volume import (
    DetectParams,
    VolumeModel,
    VolumeParams,
    detect_change,
    expected_height_map,
    expected_image,
    load_model,
    save_model,
    update_model,
)

from geocd.volume.prior import seed_from_dem

from . import toyscene as T


@pytest.fixture(scope="module")
def toy():
    return T.make_toy()


def _train(toy, params=None, passes=3, init_depth=1, geom=None, dem_prior=True):
    geom = geom or T.volume_geometry()
    m = VolumeModel.create(geom, params or VolumeParams(), init_depth=init_depth)
    if dem_prior:  # the flat ground of the toy town as the prior DEM
        grid = T.aoi_grid(0.5)
        seed_from_dem(m, np.full(grid.shape, T.H0), grid)
    for _ in range(passes):
        for i, (c, im) in enumerate(zip(toy.cameras, toy.images)):
            update_model(m, im, c, name=f"v{i}", supersample=2)
    return m


@pytest.fixture(scope="module")
def trained(toy):
    return _train(toy)


def _truth_height(grid):
    x, y = grid.xy()
    lon, lat = to_lonlat(x, y, grid.crs)
    e, n, _ = T.FRAME.to_enu(lon, lat, np.full(lon.shape, T.H0))
    z, _ = T.dsm(e, n)
    return z + T.H0, (np.abs(e) < 12) & (np.abs(n) < 12)


@pytest.mark.slow
def test_model_learns_the_scene(toy, trained):
    h, grid = expected_height_map(trained)
    truth, centre = _truth_height(grid)
    dz = np.abs(h - truth)[centre]
    assert np.nanmedian(dz) < 0.8
    assert np.mean(dz < 1.0) > 0.6
    # the held-out view is predicted better than a flat grey image
    r = expected_image(trained, toy.test_camera, toy.test_image_a.shape)
    known = r.vis_inf < 0.2
    mse = np.mean((r.expected[known] - toy.test_image_a[known]) ** 2)
    mse_flat = np.mean((toy.test_image_a[known] - toy.test_image_a[known].mean()) ** 2)
    assert mse < 0.75 * mse_flat
    # variable resolution: only part of the volume is refined to the finest level
    rep = trained.size_report()
    assert rep["leaves_per_level"][3] < 0.5 * rep["fixed_grid_cells"]


def test_change_detection_finds_the_new_building(toy, trained):
    res = detect_change(trained, toy.test_image_b, toy.test_camera)
    ok = ~res.unknown
    _, _, _, auc = roc_curve(res.probability, toy.change_mask_b, ok)
    assert auc > 0.9
    res_a = detect_change(trained, toy.test_image_a, toy.test_camera)
    assert np.nanmedian(res_a.probability) < np.nanmedian(res.probability[toy.change_mask_b & ok])
    # the n×n variant tolerates misregistration: a 1-pixel shift hurts it less than the plain density
    shifted = np.roll(toy.test_image_a, 1, axis=1)
    r1 = detect_change(trained, shifted, toy.test_camera, params=DetectParams(neighborhood=1))
    r3 = detect_change(trained, shifted, toy.test_camera)  # the default is the 3×3 variant
    p1, p3 = r1.probability, r3.probability
    assert DetectParams().neighborhood == 3 and np.nanmean(p3) < np.nanmean(p1)
    # the n×n result carries the plain per-pixel probability of its own ray pass, equal to the 1×1 detection's
    np.testing.assert_array_equal(r3.probability_1x1, p1)
    assert r1.probability_1x1 is None


def test_fixed_grid_mode_never_refines(toy):
    geom = T.volume_geometry()
    m = VolumeModel.create(geom, VolumeParams(refine=False), init_depth=geom.max_depth)
    n0 = m.n_nodes
    update_model(m, toy.images[0], toy.cameras[0])
    update_model(m, toy.images[1], toy.cameras[1])
    assert m.n_nodes == n0
    assert m.size_report()["fixed_grid_ratio"] < 1.0  # the grid plus its tree is larger than a plain grid


def test_save_load_roundtrip_and_incremental_update(toy, trained, tmp_path):
    p = save_model(trained, tmp_path / "model")
    m2 = load_model(p)
    for k in ("child", "level", "alpha", "app", "block_root"):
        np.testing.assert_array_equal(getattr(m2, k), getattr(trained, k))
    assert m2.geometry == trained.geometry
    assert m2.params == trained.params
    assert len(m2.history) == len(trained.history)
    r1 = detect_change(trained, toy.test_image_b, toy.test_camera)
    r2 = detect_change(m2, toy.test_image_b, toy.test_camera)
    np.testing.assert_array_equal(r1.probability, r2.probability)
    update_model(m2, toy.images[2], toy.cameras[2], name="again")
    save_model(m2, p)
    m3 = load_model(p)
    assert m3.history[-1]["name"] == "again"
    assert len(m3.history) == len(trained.history) + 1


def test_cancel_mid_update_leaves_model_and_disk_untouched(toy, trained, tmp_path):
    p = save_model(trained, tmp_path / "model")
    m = load_model(p)
    before = {k: getattr(m, k).copy() for k in ("child", "alpha", "app")}
    calls = []

    def cancel(f, msg=""):
        calls.append(f)
        if len(calls) > 1:
            raise CancelledError("stop")

    with pytest.raises(CancelledError):
        update_model(m, toy.images[0], toy.cameras[0], progress=cancel)
    for k, v in before.items():
        np.testing.assert_array_equal(getattr(m, k), v)
    assert len(m.history) == len(trained.history)


def test_crash_while_saving_keeps_the_previous_model(toy, trained, tmp_path, monkeypatch):
    p = save_model(trained, tmp_path / "model")
    m = load_model(p)
    update_model(m, toy.images[0], toy.cameras[0], name="lost")
    import geocd.volume.io as vio

    real_save = np.save
    n = {"k": 0}

    def failing_save(path, arr, **kw):
        n["k"] += 1
        if n["k"] == 3:
            raise OSError("disk full (simulated)")
        return real_save(path, arr, **kw)

    monkeypatch.setattr(vio.np, "save", failing_save)
    with pytest.raises(OSError):
        save_model(m, p)
    monkeypatch.setattr(vio.np, "save", real_save)
    back = load_model(p)
    assert len(back.history) == len(trained.history)
    np.testing.assert_array_equal(back.alpha, trained.alpha)
    assert not [f for f in p.parent.iterdir() if f.name.endswith(".part")]


def test_bad_inputs_give_clear_errors(toy, trained):
    # camera looking away from the volume (far to the east)
    far = T.look_at_camera(0, 0)
    d = far.to_dict()
    d["position"] = [d["position"][0] + 5000.0, d["position"][1], d["position"][2]]
    from geocd.camera import camera_from_dict

    away = camera_from_dict(d)
    with pytest.raises(NoOverlapError, match="does not see the volume"):
        update_model(trained.copy(), toy.images[0], away)
    # a camera whose rays are all NaN (NaN parameters got through a lenient reader)

    class NaNCamera:
        width, height = toy.cameras[0].width, toy.cameras[0].height

        def localize(self, col, row, h):
            return np.full(np.shape(col), np.nan), np.full(np.shape(col), np.nan)

        def project(self, lon, lat, h):
            return np.full(np.shape(lon), np.nan), np.full(np.shape(lon), np.nan)

    with pytest.raises(CameraError, match="no finite viewing ray"):
        update_model(trained.copy(), toy.images[0], NaNCamera())
    # a frame camera with NaN parameters is refused by the camera itself
    d = toy.cameras[0].to_dict()
    d["position"] = [math.nan, d["position"][1], d["position"][2]]
    with pytest.raises(CameraError):
        camera_from_dict(d)
    # image and camera sizes disagree
    with pytest.raises(CameraError, match="pixels but its camera"):
        update_model(trained.copy(), toy.images[0][:40], toy.cameras[0])
    # a grid (or manifest) in another CRS than the model's
    cx, cy = 500000.0, 4980000.0
    other = AOIGrid.from_bounds(cx, cy, cx + 10, cy + 10, 1.0, "EPSG:32633")
    with pytest.raises(CRSError, match="was built in"):
        expected_height_map(trained, other)
    # detection with a model that has seen nothing
    fresh = VolumeModel.create(T.volume_geometry())
    with pytest.raises(ProcessingError, match="no appearance"):
        detect_change(fresh, toy.test_image_b, toy.test_camera)


def test_sun_bins_and_relighting(toy):
    geom = T.volume_geometry()
    m = VolumeModel.create(geom, VolumeParams(n_bins=2))
    sun_a = (135.0, 60.0)
    for _ in range(2):
        for c, im in zip(toy.cameras, toy.images):
            update_model(m, im, c, sun=sun_a, supersample=2)
    assert len(m.sun_bins) == 1 and m.sun_bins[0][2] == 2 * len(toy.cameras)
    assert m.sun_bin((140.0, 58.0), create=False) == 0
    res = detect_change(m, toy.test_image_b, toy.test_camera, sun=(160.0, 45.0))
    assert res.relight is not None and res.sun_offset_deg > 12
    assert set(res.relight["fit"]) == {"lit>lit", "lit>shadow", "shadow>lit", "shadow>shadow"}
    ok = ~res.unknown
    assert roc_curve(res.probability, toy.change_mask_b, ok)[3] > 0.85
    one = detect_change(m, toy.test_image_b, toy.test_camera, sun=(160.0, 45.0), params=DetectParams(neighborhood=1))
    np.testing.assert_array_equal(res.probability_1x1, one.probability)  # relit: the same mapping, the same pass
    plain = detect_change(m, toy.test_image_b, toy.test_camera, sun=(160.0, 45.0), params=DetectParams(relight=False))
    assert plain.relight is None


def test_dsm_shadow_height_of_a_block_under_a_southern_sun():
    """A 10 m block on flat ground at 0.5 m posting, sun due south at 45°: the shadow reaches 10 m north of the
    block's north wall and falls off by tan(45°) per metre; nothing is shaded south of it or beside it.
    Checked against the exact geometry; a sun at the horizon shades everything."""
    from geocd.volume.relight import dsm_shadow_height

    z = np.zeros((80, 40))
    z[50:60, 15:25] = 10.0  # rows 50..59 (north wall at row 50), columns 15..24
    h = dsm_shadow_height(z, 0.5, (180.0, 45.0))
    north = np.arange(30, 50)  # 10 m north of the wall: rows 30..49
    expect = 10.0 - (50 - north - 0.0) * 0.5  # distance to the first block cell along the ray
    np.testing.assert_allclose(h[north, 20], expect, atol=0.26)  # within half a step (bilinear at the wall)
    assert np.all(h[north, 20] > 0) and np.all(h[:28, 20] <= 0.0)
    assert np.all(h[62:, 20] <= 0.0) and np.all(h[30:50, :13] <= 0.0)
    assert np.all(np.isinf(dsm_shadow_height(z, 0.5, (180.0, 0.0))))
    nan = z.copy()
    nan[50:60, 15:25] = np.nan  # holes cast nothing
    assert np.all(dsm_shadow_height(nan, 0.5, (180.0, 45.0))[north, 20] <= 0.0)


def test_a_shading_scale_enters_the_lit_class_fit_and_mapping(toy):
    """``lit_scale`` multiplies the expected intensity of the lit → lit pixels only: a scale of 1 changes
    nothing, a uniform scale of 2 halves that class's slope in the fit and leaves the mapped mixture as it was
    (a class too small to fit, which borrows the lit → lit line, borrows the unscaled one); the DSM is sampled
    at the pixels' surface points."""
    from geocd.volume.relight import relight_mapping, surface_dsm_sample

    geom = T.volume_geometry()
    m = VolumeModel.create(geom, VolumeParams(n_bins=2))
    for c, im in zip(toy.cameras, toy.images):
        update_model(m, im, c, sun=(135.0, 60.0), supersample=2)
    grid = T.aoi_grid()
    dsm, _ = _truth_height(grid)
    args = (m, toy.test_image_b, toy.test_camera, 0, (135.0, 60.0), (160.0, 30.0))
    (a0, b0, s0), info0 = relight_mapping(*args, shadow_dsm=(dsm, grid))
    (a1, b1, s1), info1 = relight_mapping(*args, shadow_dsm=(dsm, grid), lit_scale=lambda d: np.ones(d.shape))
    assert info1["fit"] == info0["fit"]
    np.testing.assert_array_equal(b1, b0)
    (a2, b2, s2), info2 = relight_mapping(*args, shadow_dsm=(dsm, grid), lit_scale=lambda d: np.full(d.shape, 2.0))
    lit = info0["fit"]["lit>lit"]
    assert info2["fit"]["lit>lit"]["b"] == pytest.approx(lit["b"] / 2, rel=1e-6)
    assert info2["fit"]["lit>shadow"] == info0["fit"]["lit>shadow"]
    np.testing.assert_allclose(b2, b0, rtol=1e-6)
    np.testing.assert_allclose(a2, a0, atol=1e-9)
    # the DSM sampled at the pixels' surface points: most pixels have one, and the samples are the DSM's values
    from geocd.volume.render import render_image

    depth = render_image(m, toy.test_camera, toy.test_image_b.shape, app_bin=0).depth_m
    (z,), h = surface_dsm_sample(m, toy.test_camera, depth, [dsm], grid)
    ok = np.isfinite(z) & np.isfinite(h)
    assert ok.mean() > 0.5
    assert np.nanmin(dsm) - 1e-6 <= z[ok].min() and z[ok].max() <= np.nanmax(dsm) + 1e-6


def test_relighting_with_the_shadows_of_a_dsm(toy):
    """The relighting's lit/shadow classes from a DSM's cast shadows (the scene's own surface here): detection
    runs, says so, still finds the new building; a DSM that does not fit the model is refused."""
    from geocd.errors import ConfigError

    geom = T.volume_geometry()
    m = VolumeModel.create(geom, VolumeParams(n_bins=2))
    for _ in range(2):
        for c, im in zip(toy.cameras, toy.images):
            update_model(m, im, c, sun=(135.0, 60.0), supersample=2)
    grid = T.aoi_grid()
    dsm, _ = _truth_height(grid)
    res = detect_change(m, toy.test_image_b, toy.test_camera, sun=(160.0, 30.0), shadow_dsm=(dsm, grid))
    assert res.relight["shadows"] == "DSM"
    frac = res.relight["class_fraction"]
    assert frac["lit>shadow"] > 0.02 and frac["lit>lit"] > 0.5, frac  # the boxes shade the ground north
    assert roc_curve(res.probability, toy.change_mask_b, ~res.unknown)[3] > 0.85
    own = detect_change(m, toy.test_image_b, toy.test_camera, sun=(160.0, 30.0))
    assert own.relight["shadows"] == "model density"
    with pytest.raises(ConfigError, match="shape"):
        detect_change(m, toy.test_image_b, toy.test_camera, sun=(160.0, 30.0), shadow_dsm=(dsm[:-1], grid))
    with pytest.raises(ConfigError, match="no valid height"):
        detect_change(
            m, toy.test_image_b, toy.test_camera, sun=(160.0, 30.0), shadow_dsm=(np.full(dsm.shape, np.nan), grid)
        )
    cx, cy = 500000.0, 4980000.0
    other = AOIGrid.from_bounds(cx, cy, cx + 32, cy + 32, 0.5, "EPSG:32633")
    with pytest.raises(CRSError):
        detect_change(m, toy.test_image_b, toy.test_camera, sun=(160.0, 30.0), shadow_dsm=(dsm, other))
