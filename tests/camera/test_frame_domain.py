"""Frame cameras with strong distortion: the model's valid domain (no fold-back points)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from geocd.camera import _frame_kernels as K
from geocd.camera.frame import FrameCamera
from geocd.geodesy import from_lonlat, to_lonlat

UTM35S = "EPSG:32735"
LON0, LAT0 = 24.40, -33.69
X0, Y0 = (float(v) for v in from_lonlat(LON0, LAT0, UTM35S))


def drone(k1=-0.26, k2=0.0, k3=0.0, p1=0.0, p2=0.0, focal=480.0) -> FrameCamera:
    return FrameCamera(
        width=480,
        height=360,
        focal_px=focal,
        position=(X0, Y0, 60.0),
        opk_deg=(0.0, 0.0, 0.0),
        crs=UTM35S,
        vertical_datum="ellipsoid",
        distortion=dict(k1=k1, k2=k2, k3=k3, p1=p1, p2=p2),
    )


def test_max_radius_is_the_first_fold_of_the_radial_polynomial():
    assert K.max_radius2(0.0, 0.0, 0.0) == math.inf
    assert K.max_radius2(0.05, 0.01, 0.0) == math.inf  # pincushion never folds
    assert K.max_radius2(-0.26, 0.0, 0.0) == pytest.approx(1.0 / (3 * 0.26))
    for k in [(-0.3, 0.05, -0.01), (-0.12, -0.02, 0.003)]:
        u = K.max_radius2(*k)
        r = np.sqrt(np.linspace(0.0, u, 2001))
        rd = r * (1 + k[0] * r**2 + k[1] * r**4 + k[2] * r**6)
        assert np.all(np.diff(rd) > 0)  # monotonic up to it
        r2 = np.sqrt(u) * 1.01
        assert r2 * (1 + k[0] * r2**2 + k[1] * r2**4 + k[2] * r2**6) < rd[-1]  # and not beyond
    assert drone().max_field_angle_deg == pytest.approx(math.degrees(math.atan(math.sqrt(1 / 0.78))))


def test_fold_back_points_do_not_project_into_the_image():
    cam = drone()
    # ground points all around, out to 3× the flying height: without the domain check ~20 % of the
    # points that "land" in the image come from beyond the fold (48.5° off the axis)
    xs, ys = np.meshgrid(np.linspace(-180, 180, 121), np.linspace(-180, 180, 121))
    x, y, z = X0 + xs.ravel(), Y0 + ys.ravel(), np.zeros(xs.size)
    col, row = cam.project_world(x, y, z)
    angle = np.degrees(np.arctan(np.hypot(xs.ravel(), ys.ravel()) / 60.0))
    assert np.all(np.isnan(col[angle > cam.max_field_angle_deg + 1e-6]))
    inside = cam.in_image(col, row)
    assert inside.sum() > 200
    # the same camera without its domain lets fold-back points land in the image
    p = cam.params
    p[21] = np.inf
    c_nd, r_nd = np.empty(x.size), np.empty(x.size)
    K.frame_project(x, y, z, p, c_nd, r_nd)
    folded = cam.in_image(c_nd, r_nd) & (angle > cam.max_field_angle_deg)
    assert folded.sum() > 0.1 * inside.sum()
    # every point that lands in the image localizes back to itself (was: errors up to hundreds of metres)
    lon, lat = to_lonlat(x[inside], y[inside], UTM35S)
    lo2, la2 = cam.localize(col[inside], row[inside], z[inside])
    xb, yb = from_lonlat(lo2, la2, UTM35S)
    assert np.nanmax(np.hypot(xb - x[inside], yb - y[inside])) < 1e-4
    # derivatives too: NaN beyond the fold, bounded inside
    dc, dr = cam.dproj_dz_world(x, y, z)
    assert np.all(np.isnan(dc[angle > cam.max_field_angle_deg + 1e-6]))
    assert np.nanmax(np.hypot(dc, dr)) < 10.0
    # the numpy reference agrees
    cr, rr = K.project_ref(x, y, z, cam.params)
    np.testing.assert_allclose(col, cr, atol=1e-9)


def test_pixels_beyond_the_reachable_radius_do_not_localize():
    # with a short focal length the image corners lie beyond what the polynomial can reach
    cam = drone(focal=300.0)
    xn, yn = cam.undistort([240.0, 0.0, 240.0], [180.0, 0.0, 0.0])
    assert np.isfinite(xn[0]) and np.isnan(xn[1])  # centre ok, corner (r_d = 1.0 > 0.755) refused
    r2 = np.asarray(xn) ** 2 + np.asarray(yn) ** 2
    assert np.all(~(r2 >= K.max_radius2(-0.26, 0.0, 0.0)))
    xr, yr = K.undistort_ref([240.0, 0.0], [180.0, 0.0], cam.params, n_iter=200)
    assert np.isfinite(xr[0]) and np.isnan(xr[1])


def test_tangential_distortion_domain_uses_the_jacobian():
    cam = drone(k1=0.0, p1=0.2)
    x = np.array([0.0, 0.5, -0.5, 3.0, -3.0])  # det = 1 − 4 p1² x² < 0 beyond |x| = 2.5
    y = np.zeros_like(x)
    ok = K.in_domain_ref(x, y, cam.params)
    col, _ = cam.project_world(X0 + 60 * x, Y0 - 60 * y, np.zeros_like(x))
    np.testing.assert_array_equal(np.isfinite(col), ok)
    assert ok[0] and not ok.all()
