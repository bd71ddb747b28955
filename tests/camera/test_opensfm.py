"""OpenSfM / ODM reconstruction.json import: conventions checked against OpenSfM's own formulas."""

from __future__ import annotations

import json

import numpy as np
import pytest

from geocd.errors import FrameCameraError
from geocd.geodesy import transformer
from geocd.io.opensfm import read_opensfm_cameras, rodrigues, topocentric_to

REF = (7.4312, 46.9480, 610.0)  # lon, lat, ellipsoidal h


def opensfm_project(cam: dict, shot: dict, X: np.ndarray) -> np.ndarray:
    """OpenSfM's projection (pixel centres at integers), written from its documentation."""
    r = rodrigues(shot["rotation"])
    xc = (r @ X.T).T + np.asarray(shot["translation"])
    x, y = xc[:, 0] / xc[:, 2], xc[:, 1] / xc[:, 2]
    r2 = x * x + y * y
    size = max(cam["width"], cam["height"])
    if cam["projection_type"] == "perspective":
        d = 1 + cam["k1"] * r2 + cam["k2"] * r2**2
        u, v = cam["focal"] * d * x, cam["focal"] * d * y
    else:
        rad = 1 + cam["k1"] * r2 + cam["k2"] * r2**2 + cam["k3"] * r2**3
        xd = x * rad + 2 * cam["p1"] * x * y + cam["p2"] * (r2 + 2 * x * x)
        yd = y * rad + cam["p1"] * (r2 + 2 * y * y) + 2 * cam["p2"] * x * y
        u, v = cam["focal_x"] * xd + cam["c_x"], cam["focal_y"] * yd + cam["c_y"]
    # normalized → pixels: p = n · size − 0.5 + width / 2 (OpenSfM's pixel centres are integers)
    return np.column_stack([u * size - 0.5 + cam["width"] / 2.0, v * size - 0.5 + cam["height"] / 2.0])


def _reconstruction(tmp_path, with_ref=True):
    cams = {
        "v2 dji fc6310 4864 3648 brown 0.6666": {
            "projection_type": "brown",
            "width": 4864,
            "height": 3648,
            "focal_x": 0.67,
            "focal_y": 0.668,
            "c_x": 0.004,
            "c_y": -0.003,
            "k1": -0.26,
            "k2": 0.09,
            "k3": -0.01,
            "p1": 0.001,
            "p2": -0.0005,
        },
        "perspective cam": {
            "projection_type": "perspective",
            "width": 4000,
            "height": 3000,
            "focal": 0.85,
            "k1": -0.05,
            "k2": 0.01,
        },
    }
    shots = {}
    rng = np.random.default_rng(4)
    for k, cid in enumerate(["v2 dji fc6310 4864 3648 brown 0.6666"] * 2 + ["perspective cam"]):
        # cameras ~80 m up, looking down (camera z axis towards −up), tilted a little
        rot = (
            np.diag([1.0, -1.0, -1.0])
            @ rodrigues([rng.normal(0, 0.05), rng.normal(0, 0.05), 0.0])
            @ rodrigues([0.0, 0.0, rng.uniform(-np.pi, np.pi)])
        )
        centre = np.array([rng.uniform(-200, 200), rng.uniform(-200, 200), 80.0 + rng.uniform(-5, 5)])
        from scipy.spatial.transform import Rotation

        rv = Rotation.from_matrix(rot).as_rotvec()
        shots[f"DJI_{k:04d}.JPG"] = {"camera": cid, "rotation": rv.tolist(), "translation": (-rot @ centre).tolist()}
    doc = {"cameras": cams, "shots": shots}
    if with_ref:
        doc["reference_lla"] = {"longitude": REF[0], "latitude": REF[1], "altitude": REF[2]}
    p = tmp_path / "reconstruction.json"
    p.write_text(json.dumps([doc]))
    return p, doc


def test_opensfm_cameras_project_as_opensfm_does(tmp_path):
    p, doc = _reconstruction(tmp_path)
    cams = read_opensfm_cameras(p)
    assert sorted(cams) == sorted(doc["shots"])
    rng = np.random.default_rng(0)
    for name, shot in doc["shots"].items():
        cam = doc["cameras"][shot["camera"]]
        fc = cams[name]
        # ground points seen by this shot, in topocentric metres
        r = rodrigues(shot["rotation"])
        centre = -r.T @ np.asarray(shot["translation"])
        X = np.column_stack(
            [centre[0] + rng.uniform(-30, 30, 200), centre[1] + rng.uniform(-30, 30, 200), rng.uniform(-10, 20, 200)]
        )
        ref_px = opensfm_project(cam, shot, X)
        gx, gy, h = topocentric_to(fc.crs, X[:, 0], X[:, 1], X[:, 2], REF)
        lon, lat = transformer(fc.crs, "EPSG:4326").transform(gx, gy)
        col, row = fc.project(lon, lat, h)
        # geocd's corner convention is OpenSfM's pixel + 0.5; the local transverse Mercator is ~Cartesian
        # near the reference (mm; in UTM the 0.9996 scale factor alone costs ~0.6 px here)
        err = np.hypot(col - 0.5 - ref_px[:, 0], row - 0.5 - ref_px[:, 1])
        assert np.nanmax(err) < 0.3, (name, np.nanmax(err))  # 0.3 px = 7 mm at 80 m
        assert np.isfinite(err).mean() > 0.95


def test_opensfm_reference_beside_and_errors(tmp_path):
    p, doc = _reconstruction(tmp_path, with_ref=False)
    with pytest.raises(FrameCameraError, match="reference_lla"):
        read_opensfm_cameras(p)
    (tmp_path / "reference_lla.json").write_text(
        json.dumps({"latitude": REF[1], "longitude": REF[0], "altitude": REF[2]})
    )
    assert len(read_opensfm_cameras(p)) == 3
    doc["cameras"]["perspective cam"]["projection_type"] = "fisheye"
    p.write_text(json.dumps([doc]))
    with pytest.raises(FrameCameraError, match="fisheye"):
        read_opensfm_cameras(p)
