"""Every camera, whatever file it comes from (--camera, a manifest's camera:, a sidecar), passes the checks
of its kind: an implausible RPC or frame camera is refused, a garbled RPC sidecar is an error naming it."""

from __future__ import annotations

import json

import numpy as np
import pytest

from geocd.camera import RPCModel
from geocd.errors import FrameCameraError, RPCParseError
from geocd.io.cameras import load_camera, read_camera_file
from geocd.io.frame import read_frame_sidecar
from geocd.io.rpc import check_rpc_plausible, find_rpc_sidecar, load_rpc_for_image
from tests.camera.test_rpc import synthetic_rpc
from tests.io.test_rpc_readers import write_tif


@pytest.fixture(scope="module")
def model() -> RPCModel:
    return synthetic_rpc(seed=7)


def _rpc_json(model: RPCModel, path, **override):
    d = model.to_dict()
    d.update(override)
    path.write_text(json.dumps(d))
    return path


@pytest.mark.parametrize(
    "field, value, needle",
    [
        ("lat_scale", 1e308, "LAT_SCALE=1e+308 is outside"),
        ("lon_scale", 500.0, "LONG_SCALE=500 is outside"),
        ("lat_off", 95.0, "LAT_OFF=95 is not a latitude"),
        ("line_scale", -540.0, "LINE_SCALE=-540 is negative"),
        ("samp_scale", 1e9, "SAMP_SCALE=1e+09 is outside"),
        ("height_scale", -500.0, "HEIGHT_SCALE=-500 is negative"),
    ],
)
def test_explicit_geocd_rpc_json_is_checked(model, tmp_path, field, value, needle):
    p = _rpc_json(model, tmp_path / "x.rpc.json", **{field: value})
    with pytest.raises(RPCParseError, match="implausible RPC") as ei:
        read_camera_file(p)
    assert needle in str(ei.value) and str(p) in str(ei.value)
    image = write_tif(None, tmp_path / "img.tif")
    with pytest.raises(RPCParseError, match=needle.split("=")[0]):
        load_camera(image, p)


def test_negative_lat_scale_stays_accepted(model):
    """Planet's L1A/L1B RPCs have LAT_SCALE < 0 (the sign is in the coefficients)."""
    m = model.replace(lat_scale=-model.lat_scale, line_num=model.line_num, samp_num=model.samp_num)
    assert check_rpc_plausible(m) is m


def test_corrupt_rpc_json_sidecar_is_an_error(model, tmp_path):
    image = write_tif(None, tmp_path / "s.tif")
    side = tmp_path / "s.rpc.json"
    side.write_text('{"kind": "rpc", "line_num": [1, 2')
    assert find_rpc_sidecar(image) == side
    with pytest.raises(RPCParseError, match="not valid JSON") as ei:
        load_rpc_for_image(image)
    assert str(side) in str(ei.value)
    _rpc_json(model, side, lat_scale=1e308)
    with pytest.raises(RPCParseError, match="LAT_SCALE"):
        load_camera(image)


def test_generic_json_next_to_an_image_is_still_skipped(tmp_path):
    image = write_tif(None, tmp_path / "s.tif")
    (tmp_path / "s.json").write_text('{"name": "not an rpc"}')
    assert find_rpc_sidecar(image) is None


def test_camera_file_with_duplicate_keys(model, tmp_path):
    d = json.dumps(model.to_dict())
    p = tmp_path / "dup.rpc.json"
    p.write_text(d[:-1] + ', "lat_off": 1.0}')
    with pytest.raises(RPCParseError, match="duplicate key 'lat_off'"):
        read_camera_file(p)


FRAME = {
    "kind": "frame",
    "crs": "EPSG:32631",
    "width": 400,
    "height": 300,
    "focal_px": 1000.0,
    "position": [500000.0, 4000000.0, 1500.0],
    "opk_deg": [0.0, 0.0, 0.0],
    "vertical_datum": "ellipsoid",
}


@pytest.mark.parametrize(
    "field, value, needle",
    [
        ("width", 10**400, "'width'=1000"),
        ("width", 10**7, "whole number of pixels in 1..1000000"),
        ("height", True, "'height'=True"),
        ("focal_px", 10**400, "'focal_px'"),
        ("position", [1e300, 0.0, 0.0], "out of range"),
        ("opk_deg", [0.0, 1e12, 0.0], "out of range"),
    ],
)
def test_frame_sidecar_out_of_range(tmp_path, field, value, needle):
    p = tmp_path / "a.camera.json"
    p.write_text(json.dumps({**FRAME, field: value}))
    with pytest.raises(FrameCameraError) as ei:
        read_frame_sidecar(p)
    assert needle in str(ei.value) and str(p) in str(ei.value)
    assert len(str(ei.value)) < 600
    with pytest.raises(FrameCameraError):
        read_camera_file(p)


def test_frame_sidecar_in_range_loads(tmp_path):
    p = tmp_path / "a.camera.json"
    p.write_text(json.dumps(FRAME))
    cam = read_frame_sidecar(p)
    assert (cam.width, cam.height) == (400, 300) and np.isclose(cam.focal_px[0], 1000.0)
