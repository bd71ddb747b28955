"""Renderer: pixel sampling, ray generation for every camera kind, occlusions, sensor model, speed."""

from __future__ import annotations

import time

import numpy as np
import pytest

from geocd.camera.base import Camera
from geocd.synth import _kernels as K
from geocd.synth.generate import make_aerial_cameras, make_satellite_cameras
from geocd.synth.render import (
    RenderParams,
    SensorRadiometry,
    camera_rays,
    render_view,
    scene_z_band,
    sun_direction_map,
    to_sensor_counts,
    trace_view,
)
from geocd.synth.sensors import sun_direction_enu

SUN = sun_direction_enu(137.0, 62.0)


@pytest.fixture(scope="module")
def cams(tiny_params, tiny_town):
    return {**make_satellite_cameras(tiny_params, tiny_town), **make_aerial_cameras(tiny_params, tiny_town)}


class _Generic(Camera):
    """Delegates the protocol only (no fast ray path): exercises the localize-based rays."""

    kind = "generic-test"

    def __init__(self, cam):
        self.cam = cam
        self.width, self.height = cam.width, cam.height

    def project(self, lon, lat, h):
        return self.cam.project(lon, lat, h)

    def localize(self, col, row, h):
        return self.cam.localize(col, row, h)

    def dproj_dh(self, lon, lat, h):
        return self.cam.dproj_dh(lon, lat, h)

    def to_dict(self):  # pragma: no cover
        return {}

    @classmethod
    def from_dict(cls, d):  # pragma: no cover
        raise NotImplementedError


@pytest.mark.parametrize("name", ["A_sat1", "A_air1"])
def test_fast_rays_equal_protocol_rays(tiny_town, tiny_scenes, cams, name):
    cam = cams[name]
    rng = np.random.default_rng(0)
    col = rng.uniform(0, cam.width, 400)
    row = rng.uniform(0, cam.height, 400)
    band = scene_z_band(tiny_scenes["A"])
    o1, d1, _ = camera_rays(tiny_town, cam, col, row, band)
    o2, d2, _ = camera_rays(tiny_town, _Generic(cam), col, row, band)
    # same line: compare the points at a common height
    for z in (band[0] + 1.0, band[1] - 1.0):
        p1 = o1 + ((z - o1[:, 2]) / d1[:, 2])[:, None] * d1
        p2 = o2 + ((z - o2[:, 2]) / d2[:, 2])[:, None] * d2
        assert np.abs(p1 - p2).max() < 2e-4


def test_pixel_is_the_mean_of_its_samples(tiny_town, tiny_scenes, cams):
    """render_view's pixel (i, j) integrates rays at (j + 0.5 ± 0.25, i + 0.5 ± 0.25): geocd's pixel convention."""
    cam = cams["A_sat1"]
    S = tiny_scenes["A"]
    res = render_view(
        tiny_town, "A", cam, SUN, RenderParams(supersample=2, block_rows=7), scene=S, window=(40, 30, 20, 25)
    )
    sun = sun_direction_map(tiny_town, SUN)
    for i, j in ((0, 0), (13, 21), (19, 24), (7, 3)):
        r, c = 40 + i, 30 + j
        cc = np.array([c + 0.25, c + 0.75, c + 0.25, c + 0.75])
        rr = np.array([r + 0.25, r + 0.25, r + 0.75, r + 0.75])
        o, d, tm = camera_rays(tiny_town, cam, cc, rr, scene_z_band(S))
        rgb = np.empty((4, 4))
        t = np.empty(4)
        ob = np.empty(4, np.int64)
        K.render_rays(o, d, tm, sun, np.array([1.0, 0.25]), S, rgb, t, ob)
        assert np.allclose(res.radiance[:, i, j], rgb.mean(axis=0), rtol=1e-5, atol=1e-6)


def test_tall_building_hides_what_is_behind_it(tiny_town, tiny_scenes, cams):
    """Occlusion: a ground point on the far side of the tallest building is not what the pixel shows."""
    S = tiny_scenes["A"]
    cam = cams["A_sat1"]
    b = max(tiny_town.epochs["A"].buildings, key=lambda b: b.top_m)
    p = b.parts[0]
    lon, lat = tiny_town.frame.to_lonlat(p.cx, p.cy)
    c, r = cam.project(lon, lat, b.eave_m)
    o, d, tm = camera_rays(tiny_town, cam, np.atleast_1d(c), np.atleast_1d(r), scene_z_band(S))
    # where that ray would meet the bare terrain
    tg = K.terrain_hit(S.terr, S.terr_meta, S.terr_block_max, *o[0], *d[0], 0.0, tm[0])
    ground = o[0] + tg * d[0]
    glon, glat = tiny_town.frame.to_lonlat(ground[0], ground[1])
    gc, gr = cam.project(glon, glat, ground[2])
    assert np.hypot(gc - c, gr - r) < 1e-4  # the same pixel sees both points
    hit, ob = trace_view(tiny_town, cam, S, np.atleast_1d(gc), np.atleast_1d(gr))
    assert ob[0] >= 0 and S.cls[ob[0]] == 1  # the building, not the ground
    assert np.linalg.norm(hit[0] - ground) > 3.0


def test_tiny_scene_renders_in_a_few_seconds(tiny_town, tiny_scenes, cams):
    cam = cams["A_sat1"]
    render_view(tiny_town, "A", cam, SUN, scene=tiny_scenes["A"], window=(0, 0, 4, 4))  # compile / load
    t0 = time.perf_counter()
    res = render_view(tiny_town, "A", cam, SUN, scene=tiny_scenes["A"])
    dt = time.perf_counter() - t0
    assert res.radiance.shape == (4, cam.height, cam.width)
    assert np.all(np.isfinite(res.radiance)) and res.radiance.min() >= 0
    assert dt < 5.0, f"tiny view ({cam.width}x{cam.height}) took {dt:.2f} s"


def test_sensor_counts():
    rng = np.random.default_rng(0)
    rad = np.full((4, 64, 64), 0.4, np.float32)
    pan = to_sensor_counts(rad, SensorRadiometry(nbits=11, gain=1500.0, dark=40.0, haze=0.02), rng)
    assert pan.dtype == np.uint16 and pan.shape == (1, 64, 64)
    assert pan.mean() == pytest.approx(1500 * 0.42 + 40, rel=0.01)
    # shot + read noise: variance ≈ counts / e-per-count + read²
    assert pan.std() == pytest.approx(np.sqrt(670 / 8.0 + 4.0), rel=0.15)
    bright = to_sensor_counts(np.full((4, 8, 8), 5.0, np.float32), SensorRadiometry(nbits=11), rng)
    assert bright.max() == 2047
    rgb = to_sensor_counts(rad, SensorRadiometry(nbits=8, gain=215.0, dark=4.0, gamma=2.2, bands="rgb"), rng)
    assert rgb.dtype == np.uint8 and rgb.shape == (3, 64, 64)
