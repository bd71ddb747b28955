"""RPC fitting to arbitrary cameras (geocd.camera.rpc_fit)."""

from __future__ import annotations

import numpy as np
import pytest

from geocd.camera.base import Camera
from geocd.camera.frame import FrameCamera
from geocd.camera.rpc import RPCModel
from geocd.camera.rpc_fit import fit_rpc, rpc_camera_difference
from geocd.errors import CameraError, ConfigError
from geocd.geodesy import from_lonlat, utm_crs_for
from geocd.synth.sensors import make_pushbroom

LON0, LAT0, H0 = 1.4440, 43.5620, 196.0


def _cover(h_lo=180.0, h_hi=240.0, half_deg=0.002):
    pts = []
    for lo in (LON0 - half_deg, LON0 + half_deg):
        for la in (LAT0 - half_deg, LAT0 + half_deg):
            for h in (h_lo, h_hi):
                pts.append([lo, la, h])
    return np.array(pts)


@pytest.mark.parametrize("along,across", [(-22.0, 7.0), (0.0, -12.0), (28.0, 25.0)])
def test_fit_pushbroom_reaches_goal(along, across):
    cam = make_pushbroom(LON0, LAT0, H0, along_deg=along, across_deg=across, cover_lonlath=_cover())
    rpc, rep = fit_rpc(cam, (180.0, 240.0))
    # the goal of the issue is 0.01 px; the fit is far better on a smooth pushbroom
    assert rep.check_max_px < 1e-3
    assert rep.fit_max_px < 1e-3
    assert rep.n_check == 20 * 20 * 8 and rep.n_fit == 21 * 21 * 9
    # independent random points in the box, including heights between the layers
    rng = np.random.default_rng(1)
    lon = rng.uniform(*rep.lon_range, 2000)
    lat = rng.uniform(*rep.lat_range, 2000)
    h = rng.uniform(180.0, 240.0, 2000)
    assert rpc_camera_difference(rpc, cam, lon, lat, h).max() < 1e-3
    assert (rpc.width, rpc.height) == (cam.width, cam.height)
    # the height derivative (stereo normalisation) follows too
    d1 = np.array(rpc.dproj_dh(lon[:50], lat[:50], h[:50]))
    d2 = np.array(cam.dproj_dh(lon[:50], lat[:50], h[:50]))
    assert np.abs(d1 - d2).max() < 1e-5


def test_fit_pinhole_is_exact():
    """A pinhole is a ratio of linear polynomials of (x, y, z): the RPC reproduces it to rounding."""
    crs = utm_crs_for(LON0, LAT0)
    e, n = from_lonlat(LON0, LAT0, crs)
    cam = FrameCamera(
        width=800,
        height=600,
        focal_px=3000.0,
        position=(float(e) + 20, float(n) - 30, H0 + 900.0),
        opk_deg=(2.0, -3.0, 10.0),
        crs=crs,
        vertical_datum="ellipsoid",
    )
    rpc, rep = fit_rpc(cam, (180.0, 240.0))
    # UTM is not exactly linear in lon/lat: still far below a thousandth of a pixel
    assert rep.check_max_px < 1e-4


def test_refit_an_rpc_recovers_it():
    cam = make_pushbroom(LON0, LAT0, H0, along_deg=10.0, across_deg=-8.0, cover_lonlath=_cover())
    rpc1, _ = fit_rpc(cam, (180.0, 240.0), n_xy=11, n_h=6)
    rpc2, rep2 = fit_rpc(rpc1, (180.0, 240.0), n_xy=15, n_h=7)
    assert rep2.check_max_px < 1e-6


def test_written_tags_reproduce_the_fit(tmp_path):
    import rasterio

    from geocd.io.raster import write_image

    cam = make_pushbroom(LON0, LAT0, H0, along_deg=-15.0, across_deg=7.0, cover_lonlath=_cover())
    rpc, rep = fit_rpc(cam, (180.0, 240.0))
    p = write_image(tmp_path / "img.tif", np.zeros((1, cam.height, cam.width), np.uint16), rpc=rpc, nbits=11)
    with rasterio.open(p) as ds:
        back = RPCModel.from_rasterio(ds.rpcs, width=ds.width, height=ds.height)
    rng = np.random.default_rng(3)
    lon = rng.uniform(*rep.lon_range, 500)
    lat = rng.uniform(*rep.lat_range, 500)
    h = rng.uniform(180.0, 240.0, 500)
    assert rpc_camera_difference(back, cam, lon, lat, h).max() < 1e-3


def test_explicit_box_and_report_dict():
    cam = make_pushbroom(LON0, LAT0, H0, along_deg=5.0, across_deg=5.0, cover_lonlath=_cover())
    rpc, rep = fit_rpc(
        cam,
        (190.0, 230.0),
        lon_range=(LON0 - 0.001, LON0 + 0.001),
        lat_range=(LAT0 - 0.001, LAT0 + 0.001),
        n_xy=9,
        n_h=5,
    )
    d = rep.to_dict()
    assert d["h_range"] == [190.0, 230.0] and d["lon_range"][0] == pytest.approx(LON0 - 0.001)
    assert rpc.height_range() == pytest.approx((190.0, 230.0))
    assert d["check_max_px"] < 1e-3


def test_bad_inputs():
    cam = make_pushbroom(LON0, LAT0, H0, along_deg=5.0, across_deg=5.0, cover_lonlath=_cover())
    with pytest.raises(ConfigError, match="at least 4"):
        fit_rpc(cam, (180.0, 240.0), n_h=3)
    with pytest.raises(ConfigError, match="empty"):
        fit_rpc(cam, (240.0, 180.0))

    class Broken(Camera):
        kind = "broken-test"
        width = height = 10

        def project(self, lon, lat, h):
            lon = np.asarray(lon, float)
            return np.full(lon.shape, np.nan), np.full(lon.shape, np.nan)

        def localize(self, col, row, h):  # pragma: no cover - not used
            raise NotImplementedError

        def dproj_dh(self, lon, lat, h):  # pragma: no cover
            raise NotImplementedError

        def to_dict(self):  # pragma: no cover
            return {}

        @classmethod
        def from_dict(cls, d):  # pragma: no cover
            return cls()

    with pytest.raises(CameraError, match="cannot project"):
        fit_rpc(Broken(), (0.0, 10.0), lon_range=(0.0, 0.01), lat_range=(0.0, 0.01))


class _Jittered(Camera):
    """A camera whose projections are moved by seeded noise of ``eps_px`` (a stand-in for another machine's rounding)."""

    kind = "jittered-test"

    def __init__(self, cam, eps_px, seed):
        self.cam, self.eps_px, self.seed = cam, eps_px, seed
        self.width, self.height = cam.width, cam.height

    def project(self, lon, lat, h):
        c, r = self.cam.project(lon, lat, h)
        rng = np.random.default_rng(self.seed)
        c = np.asarray(c, float)
        return c + self.eps_px * rng.standard_normal(c.shape), np.asarray(r, float) + self.eps_px * rng.standard_normal(
            c.shape
        )

    def footprint(self, h, densify=16):
        return self.cam.footprint(h, densify=densify)

    def localize(self, col, row, h):  # pragma: no cover - not used
        return self.cam.localize(col, row, h)

    def dproj_dh(self, lon, lat, h):  # pragma: no cover
        return self.cam.dproj_dh(lon, lat, h)

    def to_dict(self):  # pragma: no cover
        return {}

    @classmethod
    def from_dict(cls, d):  # pragma: no cover
        raise NotImplementedError


def test_fit_is_well_posed():
    """Inputs that differ at 1e-9 px (1000x more than rounding differs between machines) give the same RPC.

    Unregularised, the 39-unknown fit of a near-affine pushbroom has a condition number ~1e12: such a jitter moved
    coefficients by ~1e-3 and the committed sample_aoi RPCs could not be regenerated on another machine. With the
    fixed conditioning the coefficients move by < 1e-6 and the projections by < 1e-8 px.
    """
    cam = make_pushbroom(LON0, LAT0, H0, along_deg=-22.0, across_deg=7.0, cover_lonlath=_cover())
    box = dict(lon_range=(LON0 - 0.002, LON0 + 0.002), lat_range=(LAT0 - 0.002, LAT0 + 0.002))
    rpc0, rep0 = fit_rpc(cam, (180.0, 240.0), **box)
    assert rep0.fit_max_px < 1e-6 and rep0.check_max_px < 1e-5  # the ridge costs no accuracy that matters
    rng = np.random.default_rng(7)
    lon = rng.uniform(*box["lon_range"], 3000)
    lat = rng.uniform(*box["lat_range"], 3000)
    h = rng.uniform(180.0, 240.0, 3000)
    for seed in (1, 2, 3):
        rpc1, _ = fit_rpc(_Jittered(cam, 1e-9, seed), (180.0, 240.0), **box)
        assert np.abs(rpc1._coefs - rpc0._coefs).max() < 1e-6
        assert rpc_camera_difference(rpc1, rpc0, lon, lat, h).max() < 1e-8
