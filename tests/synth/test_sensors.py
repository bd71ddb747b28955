"""Physical pushbroom model and sun geometry."""

from __future__ import annotations

import datetime as dt

import numpy as np
import pytest

from geocd.camera import camera_from_dict
from geocd.errors import CameraError, ConfigError
from geocd.geodesy import LocalFrame
from geocd.synth.sensors import PushbroomCamera, make_pushbroom, sun_direction_enu, sun_position

LON0, LAT0, H0 = 1.4440, 43.5620, 196.0


@pytest.fixture(scope="module")
def cam():
    cover = np.array(
        [
            [LON0 - 0.0015, LAT0 - 0.0012, 190.0],
            [LON0 + 0.0015, LAT0 + 0.0012, 230.0],
            [LON0 - 0.0015, LAT0 + 0.0012, 230.0],
            [LON0 + 0.0015, LAT0 - 0.0012, 190.0],
        ]
    )
    return make_pushbroom(LON0, LAT0, H0, along_deg=-20.0, across_deg=8.0, cover_lonlath=cover, gsd_m=0.5)


def test_angles_altitude_and_gsd(cam):
    i = cam.info
    # off-nadir at the platform from pitch and roll: tan² = tan²(along) + tan²(across)
    expect = np.degrees(np.arctan(np.hypot(np.tan(np.radians(20.0)), np.tan(np.radians(8.0)))))
    assert i["off_nadir_deg"] == pytest.approx(expect, abs=1e-4)
    assert i["incidence_deg"] > i["off_nadir_deg"]  # Earth curvature
    assert i["satellite_height_m"] == pytest.approx(620e3, abs=1e-3)
    assert 600e3 < i["slant_range_m"] < 720e3
    # ground sampling distance at the centre, both directions
    fr = LocalFrame(LON0, LAT0, H0)
    c, r = cam.project(LON0, LAT0, H0)
    lon, lat = cam.localize(np.array([c - 0.5, c + 0.5, c, c]), np.array([r, r, r - 0.5, r + 0.5]), np.full(4, H0))
    e, n, _ = fr.to_enu(lon, lat, np.full(4, H0))
    assert np.hypot(e[1] - e[0], n[1] - n[0]) == pytest.approx(0.5, rel=1e-6)
    assert np.hypot(e[3] - e[2], n[3] - n[2]) == pytest.approx(0.5, rel=1e-6)


def test_project_localize_roundtrip(cam):
    rng = np.random.default_rng(0)
    lon = LON0 + rng.uniform(-0.0015, 0.0015, 5000)
    lat = LAT0 + rng.uniform(-0.0012, 0.0012, 5000)
    h = rng.uniform(180.0, 240.0, 5000)
    c, r = cam.project(lon, lat, h)
    assert np.all((c > 0) & (c < cam.width) & (r > 0) & (r < cam.height))
    lon2, lat2 = cam.localize(c, r, h)
    fr = LocalFrame(LON0, LAT0, H0)
    e1, n1, _ = fr.to_enu(lon, lat, h)
    e2, n2, _ = fr.to_enu(lon2, lat2, h)
    assert np.abs(np.hypot(e1 - e2, n1 - n2)).max() < 1e-6


def test_rays_and_dproj_dh(cam):
    # a point and its pixel: the pixel's ray passes through the point
    c, r = cam.project(LON0 + 0.0005, LAT0 - 0.0003, 210.0)
    o, d = cam.rays_enu(c, r)
    fr = LocalFrame(LON0, LAT0, H0)
    X = np.array(fr.to_enu(LON0 + 0.0005, LAT0 - 0.0003, 210.0), float).ravel()
    t = (X - o) @ d
    assert np.linalg.norm(o + t * d - X) < 1e-6
    # derivative against the protocol's definition
    dc, dr = cam.dproj_dh(LON0, LAT0, 200.0)
    c1, r1 = cam.project(LON0, LAT0, 200.1)
    c0, r0 = cam.project(LON0, LAT0, 199.9)
    assert dc == pytest.approx((c1 - c0) / 0.2, abs=1e-7)
    assert dr == pytest.approx((r1 - r0) / 0.2, abs=1e-7)
    # with a 20° pitch and an 8° roll the height parallax is mostly along track (rows)
    assert abs(dr) > abs(dc)


def test_serialisation_roundtrip(cam):
    back = camera_from_dict(cam.to_dict())
    assert isinstance(back, PushbroomCamera)
    lon, lat, h = LON0 + 0.0004, LAT0 + 0.0002, 205.0
    assert np.allclose(back.project(lon, lat, h), cam.project(lon, lat, h), atol=1e-9)
    with pytest.raises(CameraError):
        PushbroomCamera.from_dict({"kind": "pushbroom", "lon0": 0})


def test_bad_geometry():
    with pytest.raises(ConfigError):
        make_pushbroom(LON0, LAT0, H0, along_deg=70.0, across_deg=0.0)
    with pytest.raises(ConfigError):
        make_pushbroom(LON0, LAT0, H0, along_deg=0.0, across_deg=0.0, altitude_m=100.0)
    d = make_pushbroom(LON0, LAT0, H0, along_deg=0.0, across_deg=10.0).to_dict()
    d["x_axis"] = [1.0, 1.0, 0.0]
    with pytest.raises(CameraError, match="orthonormal"):
        PushbroomCamera.from_dict(d)


def test_sun_position_sanity():
    # local solar noon at the June solstice: elevation 90 - lat + 23.44, due south
    lon, lat = 0.0, 45.0
    az, el = sun_position(lon, lat, dt.datetime(2023, 6, 21, 12, 2))
    assert el == pytest.approx(90 - 45 + 23.44, abs=0.4)
    assert az == pytest.approx(180.0, abs=2.0)
    # morning sun in the east, evening in the west
    assert 45 < sun_position(lon, lat, dt.datetime(2023, 6, 21, 7, 0))[0] < 135
    assert 225 < sun_position(lon, lat, dt.datetime(2023, 6, 21, 17, 0))[0] < 315
    # equinox noon at the equator: almost overhead
    assert sun_position(0.0, 0.0, dt.datetime(2023, 3, 20, 12, 7))[1] > 89.0
    s = sun_direction_enu(90.0, 30.0)
    assert np.allclose(s, [np.cos(np.radians(30)), 0.0, 0.5], atol=1e-12)
