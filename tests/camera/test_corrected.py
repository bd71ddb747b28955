"""CorrectedCamera: any camera composed with an image-space affine."""

import json

import numpy as np
import pytest

from geocd.camera import CorrectedCamera, camera_from_dict
from geocd.errors import CameraError
from geocd.io.cameras import load_camera


@pytest.fixture(scope="module")
def rpc(sample_aoi):
    return load_camera(sample_aoi / "images" / "A_sat1.tif")


@pytest.fixture(scope="module")
def frame(sample_aoi):
    return load_camera(sample_aoi / "images" / "A_air1.tif")


def _ground(cam):
    c, r = np.meshgrid(np.linspace(50, cam.width - 50, 5), np.linspace(50, cam.height - 50, 5))
    lon, lat = cam.localize(c.ravel(), r.ravel(), np.full(c.size, 210.0))
    return lon, lat, np.full(c.size, 210.0)


@pytest.mark.parametrize("which", ["rpc", "frame"])
@pytest.mark.parametrize("linear", [None, [[1.0e-3, -2.0e-3], [0.5e-3, 1.5e-3]]])
def test_project_localize_dproj(which, linear, request):
    base = request.getfixturevalue(which)
    cam = CorrectedCamera(base, (2.5, -1.25), linear)
    lon, lat, h = _ground(base)
    c0, r0 = base.project(lon, lat, h)
    c, r = cam.project(lon, lat, h)
    M = np.zeros((2, 2)) if linear is None else np.asarray(linear)
    u0 = np.array([base.width / 2, base.height / 2])
    d = np.column_stack([c0, r0]) - u0
    expect = np.column_stack([c0, r0]) + [2.5, -1.25] + d @ M.T
    assert np.allclose(np.column_stack([c, r]), expect, atol=1e-9)
    lon2, lat2 = cam.localize(c, r, h)
    assert np.allclose(lon2, lon, atol=1e-10) and np.allclose(lat2, lat, atol=1e-10)
    dc, dr = cam.dproj_dh(lon, lat, h)
    c1, r1 = cam.project(lon, lat, h + 0.5)
    cm, rm = cam.project(lon, lat, h - 0.5)
    assert np.allclose(dc, c1 - cm, atol=1e-6) and np.allclose(dr, r1 - rm, atol=1e-6)
    # the prepared projector agrees with the plain projection
    pr = cam.ground_projector(lon, lat)
    pc, prr = pr.project(h)
    assert np.allclose(pc, c, atol=1e-9) and np.allclose(prr, r, atol=1e-9)
    back = camera_from_dict(json.loads(json.dumps(cam.to_dict())))
    bc, br = back.project(lon, lat, h)
    assert np.allclose(bc, c, atol=1e-9) and np.allclose(br, r, atol=1e-9)
    assert cam.sensor_kind == base.kind


def test_crop_and_rpc_export(rpc):
    cam = CorrectedCamera(rpc, (1.5, -0.75))
    lon, lat, h = _ground(rpc)
    c, r = cam.project(lon, lat, h)
    crop = cam.cropped(100, 40, 200, 200)
    cc, rc = crop.project(lon, lat, h)
    assert np.allclose(cc, c - 100, atol=1e-9) and np.allclose(rc, r - 40, atol=1e-9)
    folded = cam.to_rasterio()  # a shift folds into the RPC offsets exactly
    assert folded.samp_off == pytest.approx(rpc.samp_off + 1.5)
    assert folded.line_off == pytest.approx(rpc.line_off - 0.75)
    aff = CorrectedCamera(rpc, (1.5, -0.75), [[1e-3, 0], [0, 0]])
    assert not hasattr(aff, "to_rasterio")


def test_frame_has_no_crop(frame):
    assert hasattr(frame, "cropped") == hasattr(CorrectedCamera(frame), "cropped")


def test_bad_corrections(rpc):
    with pytest.raises(CameraError, match="NaN"):
        CorrectedCamera(rpc, (np.nan, 0))
    with pytest.raises(CameraError, match="singular"):
        CorrectedCamera(rpc, (0, 0), [[-1, 0], [0, -1]])
    with pytest.raises(CameraError, match="lacks 'base'"):
        camera_from_dict({"kind": "corrected"})
