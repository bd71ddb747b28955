"""Frame (pinhole) camera: conventions, kernels vs references, inverses, sidecar and orthority I/O."""

from __future__ import annotations

import json
import math
import warnings

import numpy as np
import pytest

from geocd.camera import camera_from_dict
from geocd.camera import _frame_kernels as K
from geocd.camera.frame import FrameCamera, FrameGroundProjector, opk_to_rotation, rotation_to_opk
from geocd.errors import FrameCameraError, InputFileNotFoundError
from geocd.geodesy import find_geoid_grid, from_lonlat, to_lonlat
from geocd.io.frame import (
    find_frame_sidecar,
    read_frame_sidecar,
    read_orthority_cameras,
    sidecar_path_for,
    write_frame_sidecar,
)
from tests.conftest import shared_data

UTM35S = "EPSG:32735"
LON0, LAT0 = 24.40, -33.69
X0, Y0 = (float(v) for v in from_lonlat(LON0, LAT0, UTM35S))
DIST = {"k1": -0.08, "k2": 0.03, "k3": -0.004, "p1": 4e-4, "p2": -3e-4}

needs_egm96 = pytest.mark.skipif(find_geoid_grid("egm96") is None, reason="EGM96 grid (egm96_15.gtx) not installed")


def make_cam(**kw) -> FrameCamera:
    d = dict(
        width=1000,
        height=800,
        focal_px=(1500.0, 1502.0),
        principal_point_px=(503.2, 396.7),
        position=(X0, Y0, 3000.0),
        opk_deg=(2.0, -3.0, 30.0),
        crs=UTM35S,
        vertical_datum="ellipsoid",
        distortion=DIST,
    )
    d.update(kw)
    return FrameCamera(**d)


def image_grid(cam: FrameCamera, n: int = 15) -> tuple[np.ndarray, np.ndarray]:
    c, r = np.meshgrid(np.linspace(0, cam.width, n), np.linspace(0, cam.height, n))
    return c.ravel(), r.ravel()


def ground_points(cam: FrameCamera, n: int = 200, seed: int = 0):
    """Random ground points inside the image at heights 100..600 m (ellipsoidal)."""
    rng = np.random.default_rng(seed)
    col = rng.uniform(0, cam.width, n)
    row = rng.uniform(0, cam.height, n)
    h = rng.uniform(100, 600, n)
    lon, lat = cam.localize(col, row, h)
    return lon, lat, h, col, row


# ------------------------------------------------------------------------------------------
# conventions
# ------------------------------------------------------------------------------------------
def orthority_world_to_pixel(xyz, im_size, focal_len, sensor_size, cx, cy, pos, opk_rad):
    """Independent port of orthority's PinholeCamera.world_to_pixel (pixel centres at integers)."""
    o, p, k = opk_rad
    rx = np.array([[1, 0, 0], [0, np.cos(o), -np.sin(o)], [0, np.sin(o), np.cos(o)]])
    ry = np.array([[np.cos(p), 0, np.sin(p)], [0, 1, 0], [-np.sin(p), 0, np.cos(p)]])
    rz = np.array([[np.cos(k), -np.sin(k), 0], [np.sin(k), np.cos(k), 0], [0, 0, 1]])
    r = rx.dot(ry).dot(rz).dot(np.array([[1, 0, 0], [0, -1, 0], [0, 0, -1]]))
    im = np.array(im_size, float)
    sigma = np.array(focal_len) * im / np.array(sensor_size)
    c = (im - 1) / 2 + im.max() * np.array([cx, cy])
    kk = np.array([[sigma[0], 0, c[0]], [0, sigma[1], c[1]], [0, 0, 1]])
    xc = r.T.dot(xyz - np.array(pos).reshape(3, 1))
    xc = xc / xc[2]
    return kk.dot(xc)[:2]


def test_matches_orthority_pinhole_formula():
    # the Baviaans DMC camera with an off-centre principal point and an oblique attitude
    opk = (math.radians(1.3), math.radians(-2.1), math.radians(-179.0))
    pos = (-55094.5, -3727407.0, 5258.3)
    cam = FrameCamera(
        width=640,
        height=1152,
        focal_px=(120 * 640 / 92.16, 120 * 1152 / 165.888),
        principal_point_px=(320 + 1152 * 0.01, 576 - 1152 * 0.02),
        position=pos,
        opk_deg=tuple(math.degrees(a) for a in opk),
        crs="+proj=tmerc +lat_0=0 +lon_0=25 +k=1 +x_0=0 +y_0=0 +datum=WGS84 +units=m",
        vertical_datum="ellipsoid",
    )
    rng = np.random.default_rng(1)
    xyz = np.stack(
        [pos[0] + rng.uniform(-2500, 2500, 50), pos[1] + rng.uniform(-4000, 4000, 50), rng.uniform(100, 800, 50)]
    )
    ji = orthority_world_to_pixel(xyz, (640, 1152), 120.0, (92.16, 165.888), 0.01, -0.02, pos, opk)
    col, row = cam.project_world(*xyz)
    np.testing.assert_allclose(col, ji[0] + 0.5, atol=1e-9)
    np.testing.assert_allclose(row, ji[1] + 0.5, atol=1e-9)


def test_nadir_camera_is_north_up_and_centred():
    cam = make_cam(opk_deg=(0, 0, 0), distortion=None, principal_point_px=None, focal_px=1000.0)
    c, r = cam.project_world([X0, X0 + 100, X0], [Y0, Y0, Y0 + 100], [0.0, 0.0, 0.0])
    assert c[0] == pytest.approx(500.0) and r[0] == pytest.approx(400.0)
    assert c[1] > c[0] and r[1] == pytest.approx(r[0])  # east → right
    assert r[2] < r[0] and c[2] == pytest.approx(c[0])  # north → up
    assert c[1] - c[0] == pytest.approx(1000.0 * 100 / 3000)  # scale f/H


def test_opk_rotation_round_trip():
    rng = np.random.default_rng(2)
    for _ in range(20):
        opk = (rng.uniform(-80, 80), rng.uniform(-80, 80), rng.uniform(-179, 179))
        np.testing.assert_allclose(rotation_to_opk(opk_to_rotation(opk)), opk, atol=1e-9)
        r = opk_to_rotation(opk)
        np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)


# ------------------------------------------------------------------------------------------
# kernels against numpy references
# ------------------------------------------------------------------------------------------
def test_kernels_agree_with_references():
    cam = make_cam()
    rng = np.random.default_rng(3)
    x = X0 + rng.uniform(-1500, 1500, 500)
    y = Y0 + rng.uniform(-1500, 1500, 500)
    z = rng.uniform(0, 800, 500)
    z[:5] = 3500.0  # above the camera: behind it
    col, row = cam.project_world(x, y, z)
    cr, rr = K.project_ref(x, y, z, cam.params)
    np.testing.assert_allclose(col, cr, rtol=0, atol=1e-9)
    np.testing.assert_allclose(row, rr, rtol=0, atol=1e-9)
    assert np.all(np.isnan(col[:5])) and np.all(np.isnan(row[:5]))
    dc, dr = cam.dproj_dz_world(x[5:], y[5:], z[5:])
    dcr, drr = K.dproj_dz_ref(x[5:], y[5:], z[5:], cam.params)
    np.testing.assert_allclose(dc, dcr, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(dr, drr, rtol=1e-6, atol=1e-9)
    c, r = image_grid(cam)
    xn, yn = cam.undistort(c, r)
    xr, yr = K.undistort_ref(c, r, cam.params, n_iter=200)
    np.testing.assert_allclose(xn, xr, atol=1e-10)
    np.testing.assert_allclose(yn, yr, atol=1e-10)


def test_undistort_inverts_distortion_to_1e6_px():
    cam = make_cam()
    c, r = image_grid(cam, 41)
    xn, yn = cam.undistort(c, r)
    assert np.all(np.isfinite(xn))
    xd, yd = K.distort_ref(xn, yn, [DIST[k] for k in ("k1", "k2", "k3", "p1", "p2")])
    (fx, fy), (cx, cy) = cam.focal_px, cam.principal_point_px
    err = np.hypot(fx * xd + cx - c, fy * yd + cy - r)
    assert err.max() < 1e-6


def test_no_distortion_undistort_is_linear():
    cam = make_cam(distortion=None)
    assert not cam.has_distortion
    xn, yn = cam.undistort([503.2, 1503.2], [396.7, 396.7])
    np.testing.assert_allclose(xn, [0.0, 1000 / 1500.0])
    np.testing.assert_allclose(yn, [0.0, 0.0])


# ------------------------------------------------------------------------------------------
# protocol: project / localize / dproj_dh / ground projector
# ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("datum", ["ellipsoid", pytest.param("egm96", marks=needs_egm96)])
def test_project_localize_round_trip(datum):
    cam = make_cam(vertical_datum=datum)
    lon, lat, h, col, row = ground_points(cam)
    assert np.all(np.isfinite(lon))
    c2, r2 = cam.project(lon, lat, h)
    np.testing.assert_allclose(c2, col, atol=1e-6)
    np.testing.assert_allclose(r2, row, atol=1e-6)


@needs_egm96
def test_geoid_datum_shifts_heights():
    """An EGM96 camera sees ellipsoidal height h where an ellipsoidal one sees h - N."""
    ce = make_cam(vertical_datum="ellipsoid")
    cg = make_cam(vertical_datum="egm96")
    lon, lat, h, _, _ = ground_points(ce, 20)
    n = cg.undulation(lon, lat)
    assert np.all(np.abs(n) > 1.0)
    np.testing.assert_allclose(np.array(cg.project(lon, lat, h)), np.array(ce.project(lon, lat, h - n)), atol=1e-9)


@pytest.mark.parametrize("datum", ["ellipsoid", pytest.param("egm96", marks=needs_egm96)])
def test_dproj_dh_matches_finite_difference(datum):
    cam = make_cam(vertical_datum=datum)
    lon, lat, h, _, _ = ground_points(cam, 100)
    dc, dr = cam.dproj_dh(lon, lat, h)
    eps = 0.01
    c1, r1 = cam.project(lon, lat, h + eps)
    c0, r0 = cam.project(lon, lat, h - eps)
    np.testing.assert_allclose(dc, (c1 - c0) / (2 * eps), rtol=1e-6, atol=1e-8)
    np.testing.assert_allclose(dr, (r1 - r0) / (2 * eps), rtol=1e-6, atol=1e-8)
    # a nadir camera: the image of a rising point moves away from the nadir point
    assert np.all(np.isfinite(dc))


def test_behind_camera_and_upward_rays_are_nan():
    cam = make_cam(distortion=None)
    lon, lat = to_lonlat(X0, Y0, UTM35S)
    c, r = cam.project(lon, lat, 4000.0)  # straight above the camera
    assert np.isnan(c) and np.isnan(r)
    dc, dr = cam.dproj_dh(lon, lat, 4000.0)
    assert np.isnan(dc) and np.isnan(dr)
    lo, la = cam.localize(500.0, 400.0, 3500.0)  # surface above the camera: ray points down
    assert np.isnan(lo) and np.isnan(la)
    # an oblique camera looking past the horizon: the top rows never reach the ground
    obl = make_cam(opk_deg=(0.0, 0.0, 0.0), distortion=None)
    obl = obl.replace(opk_deg=(80.0, 0.0, 0.0))
    lo, la = obl.localize([500.0, 500.0], [0.0, 800.0], [0.0, 0.0])
    assert np.isnan(lo[0]) != np.isnan(lo[1])


@pytest.mark.parametrize("datum", ["ellipsoid", pytest.param("egm96", marks=needs_egm96)])
def test_ground_projector_matches_project(datum):
    cam = make_cam(vertical_datum=datum)
    lon, lat, h, _, _ = ground_points(cam, 150)
    # points given in a different projected CRS (UTM 34S), in lon/lat, and in the camera CRS
    for crs in ("EPSG:32734", None, UTM35S):
        x, y = (lon, lat) if crs is None else from_lonlat(lon, lat, crs)
        gp = cam.ground_projector(x.reshape(10, 15), y.reshape(10, 15), crs)
        assert isinstance(gp, FrameGroundProjector) and gp.shape == (10, 15)
        for hh in (h.reshape(10, 15), 250.0):
            c, r = gp.project(hh)
            cr, rr = cam.project(lon.reshape(10, 15), lat.reshape(10, 15), hh)
            np.testing.assert_allclose(c, cr, atol=1e-6)
            np.testing.assert_allclose(r, rr, atol=1e-6)
            dc, dr = gp.dproj_dh(hh)
            dcr, drr = cam.dproj_dh(lon.reshape(10, 15), lat.reshape(10, 15), hh)
            np.testing.assert_allclose(dc, dcr, rtol=1e-9, atol=1e-12)
            np.testing.assert_allclose(dr, drr, rtol=1e-9, atol=1e-12)


def test_footprint_and_position():
    cam = make_cam(opk_deg=(0, 0, 0))
    from shapely.geometry import Point

    fp = cam.footprint(0.0)
    assert fp.is_valid and fp.contains(Point(LON0, LAT0))
    lon, lat, h = cam.position_lonlat_h()
    assert lon == pytest.approx(LON0, abs=1e-9) and lat == pytest.approx(LAT0, abs=1e-9) and h == 3000.0


def test_cropped_and_rescaled_are_exact():
    cam = make_cam()
    lon, lat, h, col, row = ground_points(cam, 50)
    crop = cam.cropped(100, 50, 600, 500)
    c, r = crop.project(lon, lat, h)
    np.testing.assert_allclose(c, col - 100, atol=1e-9)
    np.testing.assert_allclose(r, row - 50, atol=1e-9)
    half = cam.rescaled(500, 400)
    c, r = half.project(lon, lat, h)
    np.testing.assert_allclose(c, col / 2, atol=1e-9)
    np.testing.assert_allclose(r, row / 2, atol=1e-9)


# ------------------------------------------------------------------------------------------
# construction, validation, serialisation
# ------------------------------------------------------------------------------------------
def test_from_mm_and_dict_round_trip():
    cam = FrameCamera.from_mm(
        640,
        1152,
        120.0,
        0.144,
        principal_point_mm=(0.0144, -0.288),
        position=(X0, Y0, 5000.0),
        opk_deg=(0.1, 0.2, 0.3),
        crs=UTM35S,
        vertical_datum="egm2008",
        allow_geoid_substitute=True,
        distortion={"k1": 1e-3},
    )
    assert cam.focal_px == pytest.approx((833.3333333, 833.3333333))
    assert cam.principal_point_px == pytest.approx((320.1, 574.0))
    d = cam.to_dict()
    assert d["kind"] == "frame" and d["crs"] == "EPSG:32735" and d["vertical_datum"] == "egm2008"
    json.dumps(d)  # serialisable
    for c2 in (camera_from_dict(d), FrameCamera.from_dict(json.loads(json.dumps(d)))):
        assert isinstance(c2, FrameCamera)
        np.testing.assert_array_equal(c2.params, cam.params)
        assert c2.vertical_datum == "egm2008" and c2.allow_geoid_substitute
    # the metric variant of the schema
    dm = {k: v for k, v in d.items() if k not in ("focal_px", "principal_point_px")}
    dm.update(focal_mm=120.0, pixel_size_mm=0.144, principal_point_mm=[0.0144, -0.288])
    np.testing.assert_allclose(FrameCamera.from_dict(dm).params, cam.params, rtol=1e-12)


def test_compound_crs_gives_vertical_datum():
    cam = make_cam(vertical_datum=None, crs="EPSG:32735+5773")
    assert cam.vertical_datum == "egm96"
    assert cam.crs.to_epsg() == 32735


@pytest.mark.parametrize(
    "change, field",
    [
        (dict(vertical_datum=None), "vertical_datum"),
        (dict(vertical_datum="navd88"), "vertical_datum"),
        (dict(crs="EPSG:4326"), "crs"),
        (dict(crs="EPSG:2263"), "crs"),  # US survey feet
        (dict(crs=None), "crs"),
        (dict(focal_px=-3.0), "focal_px"),
        (dict(focal_px="wide"), "focal_px"),
        (dict(width=0), "width"),
        (dict(height=10.5), "height"),
        (dict(position=(1.0, 2.0)), "position"),
        (dict(opk_deg=(0.0, float("nan"), 0.0)), "opk_deg"),
        (dict(distortion={"k4": 0.1}), "distortion"),
        (dict(distortion=[0.1, 0.0, 0.0, 0.0, 0.0]), "distortion"),
    ],
)
def test_invalid_fields_name_the_field(change, field):
    with pytest.raises(FrameCameraError, match=field):
        make_cam(**change)


@pytest.mark.parametrize(
    "edit, word",
    [
        (lambda d: d.pop("focal_px"), "focal"),
        (lambda d: d.pop("position"), "position"),
        (lambda d: d.pop("opk_deg"), "opk_deg"),
        (lambda d: d.update(foo=1), "unknown fields"),
        (lambda d: d.update(kind="rpc"), "kind"),
        (lambda d: (d.pop("focal_px"), d.update(focal_mm=100.0)), "pixel_size_mm"),
    ],
)
def test_from_dict_errors(edit, word):
    d = make_cam().to_dict()
    edit(d)
    with pytest.raises(FrameCameraError, match=word):
        FrameCamera.from_dict(d)


# ------------------------------------------------------------------------------------------
# sidecar I/O
# ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("fmt", ["json", "yaml"])
def test_sidecar_round_trip(tmp_path, fmt):
    cam = make_cam(source="synthetic")
    img = tmp_path / "IMG_0001.tif"
    img.write_bytes(b"")
    assert find_frame_sidecar(img) is None
    p = write_frame_sidecar(img, cam, fmt=fmt)
    assert p == sidecar_path_for(img, fmt) == tmp_path / f"IMG_0001.camera.{fmt}"
    assert find_frame_sidecar(img) == p
    c2 = read_frame_sidecar(p)
    np.testing.assert_array_equal(c2.params, cam.params)
    assert c2.to_dict() == cam.to_dict()
    # a sidecar path written directly
    p2 = write_frame_sidecar(tmp_path / "other.camera.json", cam)
    assert read_frame_sidecar(p2).to_dict() == cam.to_dict()


@pytest.mark.filterwarnings("ignore::rasterio.errors.NotGeoreferencedWarning")
def test_load_camera_finds_frame_sidecar(tmp_path):
    rasterio = pytest.importorskip("rasterio")
    cam = make_cam()
    img = tmp_path / "frame.tif"
    with rasterio.open(img, "w", driver="GTiff", width=cam.width, height=cam.height, count=1, dtype="uint8") as ds:
        ds.write(np.zeros((1, cam.height, cam.width), np.uint8))
    write_frame_sidecar(img, cam)
    from geocd.io.cameras import load_camera

    loaded = load_camera(img)
    assert isinstance(loaded, FrameCamera)
    np.testing.assert_array_equal(loaded.params, cam.params)


def test_sidecar_errors(tmp_path):
    with pytest.raises(InputFileNotFoundError):
        read_frame_sidecar(tmp_path / "missing.camera.json")
    bad = tmp_path / "bad.camera.json"
    bad.write_text("{not json")
    with pytest.raises(FrameCameraError, match="not valid JSON"):
        read_frame_sidecar(bad)
    d = make_cam().to_dict()
    d.pop("vertical_datum")
    p = tmp_path / "nodatum.camera.yaml"
    import yaml

    p.write_text(yaml.safe_dump(d))
    with pytest.raises(FrameCameraError, match=r"nodatum\.camera\.yaml.*vertical_datum"):
        read_frame_sidecar(p)


# ------------------------------------------------------------------------------------------
# orthority / ngi readers
# ------------------------------------------------------------------------------------------
INT_YAML = """\
My Camera:
    type: brown
    im_size: [1000, 800]
    focal_len: 12.0
    sensor_size: [10.0, 8.0]
    cx: 0.01
    cy: -0.02
    k1: -0.1
    p2: 0.001
"""


def test_orthority_readers(tmp_path):
    (tmp_path / "int.yaml").write_text(INT_YAML)
    (tmp_path / "ext.csv").write_text(
        f"filename,easting,northing,altitude,omega,phi,kappa,camera\na,{X0},{Y0},3000,1.0,2.0,3.0,My Camera\n"
    )
    (tmp_path / "ext.prj").write_text("EPSG:32735")
    (tmp_path / "pos.txt").write_text(f"a {X0} {Y0} 3000 1.0 2.0 3.0\n")
    (tmp_path / "ext.geojson").write_text(
        json.dumps(
            {
                "type": "FeatureCollection",
                "world_crs": "EPSG:32735",
                "features": [
                    {
                        "type": "Feature",
                        "properties": {
                            "filename": "a",
                            "camera": "My Camera",
                            "xyz": [X0, Y0, 3000],
                            "opk": [math.radians(v) for v in (1.0, 2.0, 3.0)],
                        },
                        "geometry": {"type": "Point", "coordinates": [LON0, LAT0, 3000]},
                    }
                ],
            }
        )
    )
    cams = [
        read_orthority_cameras(tmp_path / "int.yaml", tmp_path / "ext.csv", vertical_datum="ellipsoid")["a"],
        read_orthority_cameras(tmp_path / "int.yaml", tmp_path / "pos.txt", crs=UTM35S, vertical_datum="ellipsoid")[
            "a"
        ],
        read_orthority_cameras(tmp_path / "int.yaml", tmp_path / "ext.geojson", vertical_datum="ellipsoid")["a"],
    ]
    c0 = cams[0]
    assert c0.focal_px == pytest.approx((1200.0, 1200.0))
    assert c0.principal_point_px == pytest.approx((500 + 10.0, 400 - 20.0))
    assert c0.distortion == {"k1": -0.1, "k2": 0.0, "k3": 0.0, "p1": 0.0, "p2": 0.001}
    for c in cams[1:]:
        np.testing.assert_allclose(c.params, c0.params, rtol=1e-12, atol=1e-9)
    with pytest.raises(FrameCameraError, match="crs="):
        read_orthority_cameras(tmp_path / "int.yaml", tmp_path / "pos.txt", vertical_datum="ellipsoid")
    with pytest.raises(FrameCameraError, match="vertical_datum"):
        read_orthority_cameras(tmp_path / "int.yaml", tmp_path / "ext.csv")
    (tmp_path / "fish.yaml").write_text(INT_YAML.replace("brown", "fisheye"))
    with pytest.raises(FrameCameraError, match="fisheye"):
        read_orthority_cameras(tmp_path / "fish.yaml", tmp_path / "ext.csv", vertical_datum="ellipsoid")


@pytest.mark.realdata
def test_orthority_baviaans_files_agree():
    root = shared_data("orthority_baviaans_aerial_qb2")
    rasterio = pytest.importorskip("rasterio")
    with rasterio.open(root / "ngi" / "3324c_2015_1004_05_0182_RGB.tif") as ds:
        crs = ds.crs
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        kw = dict(vertical_datum="egm2008", allow_geoid_substitute=True)
        csv_ = read_orthority_cameras(root / "io/ngi_int_param.yaml", root / "io/ngi_xyz_opk.csv", **kw)
        gj = read_orthority_cameras(root / "io/ngi_int_param.yaml", root / "io/ngi_ext_param.geojson", **kw)
        txt = read_orthority_cameras(root / "io/ngi_int_param.yaml", root / "ngi/camera_pos_ori.txt", crs=crs, **kw)
    assert sorted(csv_) == sorted(gj) == sorted(txt) and len(txt) == 4
    for name, cam in txt.items():
        assert cam.width == 640 and cam.height == 1152
        assert cam.focal_px == pytest.approx((120 / 0.144, 120 / 0.144))
        np.testing.assert_allclose(gj[name].params, cam.params, rtol=0, atol=1e-9)
        # the CSV is rounded to 1 mm and 0.001°
        np.testing.assert_allclose(csv_[name].position, cam.position, atol=1e-3)
        np.testing.assert_allclose(csv_[name].opk_deg, cam.opk_deg, atol=1e-3)
