"""The large RPC stereo scene generator: kernels vs references, geometry of a tiny scene, truth."""

from __future__ import annotations

import numpy as np
import pytest
import rasterio
from scipy.ndimage import map_coordinates

from geocd.errors import ConfigError
from geocd.synth import _kernels as K
from geocd.synth.bigstereo import (
    StereoSceneParams,
    _objects,
    height_band,
    make_buildings,
    make_stereo_scene,
    surface_window,
)


def _rays(rng, n, lo, hi, x0, y0, span):
    ax = x0 + rng.uniform(12, span - 12, n)
    ay = y0 - rng.uniform(12, span - 12, n)
    tilt = rng.uniform(-0.12, 0.12, (2, n))  # the rays stay inside the window
    return ax, ay, ax + tilt[0] * (hi - lo), ay + tilt[1] * (hi - lo)


def test_march_and_albedo_kernels_match_references():
    p = StereoSceneParams(cells=128, seed=3, built_fraction=0.9)
    objs = _objects(make_buildings(p), "A")
    g = p.grid()
    x0, y0 = g.transform.c, g.transform.f
    fs = 0.25
    dsm = surface_window(p, objs, x0, y0, fs, (0, 0, 256, 256))
    lo, hi = height_band(p)
    rng = np.random.default_rng(0)
    ax, ay, bx, by = _rays(rng, 3000, lo, hi, x0, y0, 64.0)
    wx0, wy0 = x0 + 0.5 * fs, y0 - 0.5 * fs
    out = [np.empty(ax.size) for _ in range(4)]
    K.march_dsm(
        ax, ay, bx, by, hi, lo, float(dsm.max()) + 0.5, float(dsm.min()) - 0.5, 0.5 * fs, dsm, wx0, wy0, fs, *out
    )
    ref = K.march_dsm_ref(
        ax, ay, bx, by, hi, lo, float(dsm.max()) + 0.5, float(dsm.min()) - 0.5, 0.5 * fs, dsm, wx0, wy0, fs
    )
    assert np.isfinite(out[2]).mean() > 0.99
    for a, b in zip(out, ref):
        np.testing.assert_allclose(a, b, atol=1e-9, equal_nan=True)
    # the hit lies on the surface (bilinear) and a ray hitting a roof is above the terrain by the building
    fc = (out[0] - wx0) / fs
    fr = (wy0 - out[1]) / fs
    s = map_coordinates(dsm, [fr, fc], order=1, mode="nearest")
    ok = np.isfinite(out[2])
    assert np.max(np.abs(s[ok] - out[2][ok])) < 0.05
    bid = np.rint(rng.uniform(0, 5, ax.size)).astype(np.int64)
    al = np.empty(ax.size)
    K.big_albedo(out[0], out[1], out[2], bid, out[3], 3, al)
    np.testing.assert_allclose(al, K.big_albedo_ref(out[0], out[1], out[2], bid, out[3], 3), atol=1e-12)


def test_dsm_windows_do_not_depend_on_tiling():
    p = StereoSceneParams(cells=256, seed=1)
    objs = _objects(make_buildings(p), "B")
    g = p.grid()
    x0, y0 = g.transform.c, g.transform.f
    whole = surface_window(p, objs, x0, y0, p.posting_m, (0, 0, 256, 256))
    part = surface_window(p, objs, x0, y0, p.posting_m, (100, 37, 80, 120))
    np.testing.assert_array_equal(part, whole[100:180, 37:157])


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory):
    out = tmp_path_factory.mktemp("bigstereo")
    p = StereoSceneParams(cells=256, seed=5, demolished_fraction=0.3, new_fraction=0.3)
    r = make_stereo_scene(out, p, block=160, workers=2)
    return out, p, r


def test_tiny_scene_truth_and_manifest(tiny_scene):
    import geopandas as gpd

    from geocd.io.manifest import load_manifest
    from geocd.stereo.scene import load_epoch_images

    out, p, r = tiny_scene
    b = gpd.read_file(out / "truth" / "buildings.gpkg")
    assert {"new", "demolished", "unchanged"} <= set(b["status"])
    with rasterio.open(out / "truth" / "dh.tif") as ds:
        dh = ds.read(1)
        index = ds.index
    with rasterio.open(out / "truth" / "change_mask.tif") as ds:
        mask = ds.read(1)
    for _, row in b.iterrows():
        rr, c = index(row.geometry.centroid.x, row.geometry.centroid.y)
        v = dh[rr, c]
        want = {"new": row.height_m, "demolished": -row.height_m, "unchanged": 0.0}[row.status]
        assert v == pytest.approx(want, abs=1e-3), row.status
        assert mask[rr, c] == (row.status != "unchanged")
    # nothing changes away from the buildings that changed
    assert np.all(mask[np.abs(dh) <= p.change_threshold_m] == 0)
    m = load_manifest(out / "scene.yaml")
    assert [e.name for e in m.epochs] == ["A", "B"]
    ims = load_epoch_images(m, m.epoch("A"))
    assert len(ims) == 2 and ims[0].camera.kind == "rpc"
    assert max(v["rpc_fit_check_max_px"] for v in r["report"]["views"]) < 1e-3


def _sample(path, lonlat_h):
    from geocd.io.rpc import load_rpc_for_image

    rpc = load_rpc_for_image(path)
    c, r = rpc.project(*lonlat_h)
    with rasterio.open(path) as ds:
        img = ds.read(1).astype(float)
    return map_coordinates(img, [r - 0.5, c - 0.5], order=1, mode="nearest")


def test_ground_points_project_where_their_texture_is(tiny_scene):
    """Points of the truth DSM (roofs and open ground, away from walls), projected through each image's RPC
    read from the file: both views of an epoch see the same texture there, and it is the albedo the
    generator gave those points; 3 m too high, the views disagree."""
    from scipy.ndimage import maximum_filter, minimum_filter

    from geocd.geodesy import to_lonlat

    out, p, _ = tiny_scene
    g = p.grid()
    with rasterio.open(out / "truth" / "dsm_A.tif") as ds:
        dsm = ds.read(1).astype(float)
    flat = (maximum_filter(dsm, 9) - minimum_filter(dsm, 9)) < 0.5  # no wall within 2 m
    flat[:12], flat[-12:], flat[:, :12], flat[:, -12:] = False, False, False, False
    rr, cc = np.nonzero(flat)
    k = np.random.default_rng(0).choice(rr.size, 3000, replace=False)
    rr, cc = rr[k], cc[k]
    x, y = g.xy(rr, cc)
    lon, lat = to_lonlat(x, y, g.crs)
    z = dsm[rr, cc]
    s1 = _sample(out / "images" / "A_sat1.tif", (lon, lat, z))
    s2 = _sample(out / "images" / "A_sat2.tif", (lon, lat, z))
    w1 = _sample(out / "images" / "A_sat1.tif", (lon, lat, z + 3.0))
    w2 = _sample(out / "images" / "A_sat2.tif", (lon, lat, z + 3.0))
    ids = surface_window(
        p,
        _objects(make_buildings(p), "A", "id"),
        g.transform.c,
        g.transform.f,
        p.posting_m,
        (0, 0, g.height, g.width),
        terrain=False,
    )[rr, cc]
    alb = np.empty(rr.size)
    K.big_albedo(
        np.asarray(x, float),
        np.asarray(y, float),
        z,
        np.rint(ids).astype(np.int64),
        np.zeros(rr.size),
        int(p.seed),
        alb,
    )
    right = np.corrcoef(s1, s2)[0, 1]
    wrong = np.corrcoef(w1, w2)[0, 1]
    assert right > 0.9, right
    assert 1.0 - wrong > 2.5 * (1.0 - right), (right, wrong)
    assert np.corrcoef(s1, alb)[0, 1] > 0.9
    # epoch B sees a building where one was built
    import geopandas as gpd

    b = gpd.read_file(out / "truth" / "buildings.gpkg")
    new = b[b.status == "new"].iloc[0]
    with rasterio.open(out / "truth" / "dsm_B.tif") as ds:
        dsm_b = ds.read(1)
        r, c = ds.index(new.geometry.centroid.x, new.geometry.centroid.y)
    zb = float(dsm_b[r, c])
    lon, lat = to_lonlat(new.geometry.centroid.x, new.geometry.centroid.y, g.crs)
    v1 = _sample(out / "images" / "B_sat1.tif", (np.array([lon]), np.array([lat]), np.array([zb])))
    v2 = _sample(out / "images" / "B_sat2.tif", (np.array([lon]), np.array([lat]), np.array([zb])))
    assert abs(v1[0] - v2[0]) < 0.25 * max(v1[0], v2[0])


def test_local_event_changes_only_buildings_inside_the_region():
    """``event_radius_m``: the same buildings, but only those whose centre lies in the disc change; the
    truth dh (B − A) is 0 everywhere farther from the centre than the radius plus a building's half-diagonal."""
    from geocd.synth.bigstereo import event_centre_xy

    kw = {"cells": 512, "seed": 7, "demolished_fraction": 0.5, "new_fraction": 0.5}
    everywhere = make_buildings(StereoSceneParams(**kw))
    p = StereoSceneParams(**kw, event_radius_m=45.0, event_centre_m=(20.0, -15.0))
    local = make_buildings(p)
    ex, ey = event_centre_xy(p)
    g = p.grid()
    assert ex == pytest.approx(g.transform.c + 128.0 + 20.0) and ey == pytest.approx(g.transform.f - 128.0 - 15.0)
    d = np.hypot(local[:, 1] - ex, local[:, 2] - ey)
    changed = local[:, 6] != local[:, 7]
    assert changed.sum() >= 4 and not changed[d > 45.0].any()
    assert (local[changed & (local[:, 6] > 0.5)]).size and (local[changed & (local[:, 7] > 0.5)]).size  # both kinds
    # same buildings (place, size, height) as the scene with change everywhere, minus the new ones outside
    key = lambda b: {tuple(np.round(r[1:6], 9)) for r in b}  # noqa: E731
    assert key(local) <= key(everywhere)
    assert key(everywhere[everywhere[:, 6] > 0.5]) == key(local[local[:, 6] > 0.5])
    # inside the disc the fractions apply as in the everywhere scene: the same slots change
    ein = np.hypot(everywhere[:, 1] - ex, everywhere[:, 2] - ey) <= 45.0
    assert key(everywhere[ein & (everywhere[:, 6] != everywhere[:, 7])]) == key(local[changed])
    x0, y0 = g.transform.c, g.transform.f
    win = (0, 0, g.height, g.width)
    dh = surface_window(p, _objects(local, "B"), x0, y0, p.posting_m, win) - surface_window(
        p, _objects(local, "A"), x0, y0, p.posting_m, win
    )
    X, Y = g.xy(*np.meshgrid(np.arange(g.height), np.arange(g.width), indexing="ij"))
    far = np.hypot(np.asarray(X) - ex, np.asarray(Y) - ey) > 45.0 + 12.0 * np.sqrt(2) + 1.0
    assert far.mean() > 0.5 and np.all(dh[far] == 0.0)
    assert (np.abs(dh) > 1.0).sum() > 1000  # the event itself is there
    with pytest.raises(ConfigError):
        StereoSceneParams(event_radius_m=-1.0)
