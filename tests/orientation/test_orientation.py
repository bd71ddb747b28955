"""Cross-epoch relative orientation: NCC kernel, recovery of known biases, refusal on poor tie points."""

import numpy as np
import pytest
import yaml

from geocd.camera import CorrectedCamera
from geocd.errors import ConfigError, ManifestError
from geocd.geodesy import AOIGrid
from geocd.io.cameras import load_camera
from geocd.io.manifest import load_manifest
from geocd.orientation import OrientationParams, OrientationWarning, orient_images, orient_manifest
from geocd.orientation._kernels import ncc_at_offsets, ncc_at_offsets_ref
from geocd.orientation.adjust import adjust
from geocd.orientation.tiepoints import TiePoints, band_offsets, square_offsets
from geocd.stereo.scene import EpochImage


def test_ncc_kernel_matches_reference():
    rng = np.random.default_rng(3)
    a = rng.normal(size=(120, 130)).astype(np.float32)
    from scipy.ndimage import gaussian_filter, shift

    a = gaussian_filter(a, 1.2).astype(np.float32)
    b = shift(a, (2.3, -1.6), order=3).astype(np.float32)
    b[:5] = np.nan
    pts = rng.integers(15, 100, (40, 2)).astype(np.int64)
    offs = square_offsets(4)
    got = ncc_at_offsets(a, b, pts, pts, offs, 5)
    ref = ncc_at_offsets_ref(a, b, pts, pts, offs, 5)
    assert np.array_equal(np.isnan(got[:, 0]), np.isnan(ref[:, 0]))
    ok = np.isfinite(got[:, 0])
    assert ok.sum() > 30
    assert np.allclose(got[ok], ref[ok], atol=1e-6)
    # sub-pixel displacement recovered
    d = got[ok, :2] - pts[ok]
    assert np.median(np.abs(d[:, 0] - 2.3)) < 0.15 and np.median(np.abs(d[:, 1] + 1.6)) < 0.15


def test_band_offsets_follow_the_direction():
    u = np.array([0.6, 0.8])
    o = band_offsets(u, 10.0, 1.0).astype(float)
    n = np.array([-0.8, 0.6])
    assert np.all(np.abs(o @ n) <= 1.0) and np.all(np.abs(o @ u) <= 10.0)
    assert (np.abs(o @ u) > 8).any()


SHIFTS = {
    "A_sat1": (0.0, 0.0),
    "A_sat2": (0.0, 0.0),
    "A_air1": (1.0, 1.0),
    "B_sat1": (2.0, -1.5),
    "B_sat2": (2.0, -1.5),
}


@pytest.fixture(scope="module")
def biased_images(sample_aoi):
    """sample_aoi's exact cameras, some given a known image-space bias (what the adjustment must undo)."""
    out = []
    for name, (dc, dr) in SHIFTS.items():
        path = sample_aoi / "images" / f"{name}.tif"
        side = path.with_suffix(".camera.json")
        cam = load_camera(path, side if side.exists() else None)
        out.append((name[0], EpochImage(name, path, CorrectedCamera(cam, (dc, dr)) if (dc or dr) else cam)))
    return out


def test_recovers_known_biases_rpc_and_frame(biased_images):
    grid = AOIGrid.from_bounds(374259.0, 4824329.0, 374409.0, 4824479.0, 0.5, "EPSG:32631")
    res = orient_images(biased_images, grid, 205.0, OrientationParams(min_points=10))
    assert res.applied, res.reason
    p = res.corrections
    names = [im.name for _, im in biased_images]
    # corrections undo the biases up to the datum that tie points cannot see: what the corrected cameras still
    # add to the true ones, q_k = p_k + bias_k, must be the image motion of one common ground translation δX
    x, y, h = 374334.0, 4824404.0, 205.0
    J = []
    for _, im in biased_images:
        pr = im.camera.ground_projector(np.array([x, x + 1, x, x]), np.array([y, y, y + 1, y]), grid.crs)
        c, r = pr.project(np.array([h, h, h, h + 1]))
        J.append(np.array([[c[1] - c[0], c[2] - c[0], c[3] - c[0]], [r[1] - r[0], r[2] - r[0], r[3] - r[0]]]))
    q = np.concatenate([p[k] + SHIFTS[name] for k, name in enumerate(names)])
    dX, *_ = np.linalg.lstsq(np.concatenate(J), q, rcond=None)
    assert np.abs(np.concatenate(J) @ dX - q).max() < 0.15, (q, np.concatenate(J) @ dX)
    assert abs(p[:, 0].mean()) < 1e-3 and abs(p[:, 1].mean()) < 1e-3  # gauge: mean held at zero
    rep = res.report
    print(rep["before"], rep["after"], rep.get("held_out"))
    assert rep["before"]["cross_epoch"]["median_px"] > 0.6
    assert rep["after"]["cross_epoch"]["median_px"] < 0.35
    assert rep["held_out"]["cross_epoch"]["median_px"] < 0.4


def test_too_few_or_clustered_tie_points_are_refused(biased_images):
    cams = [im.camera for _, im in biased_images][:3]
    from geocd.geodesy import to_lonlat

    rng = np.random.default_rng(0)
    # every tie point in one 10 m corner of a 150 m AOI
    xy = np.column_stack([374260 + 10 * rng.random(40), 4824330 + 10 * rng.random(40)])
    lon, lat = to_lonlat(xy[:, 0], xy[:, 1], "EPSG:32631")
    obs_img, obs_trk, colrow = [], [], []
    for k, cam in enumerate(cams):
        c, r = cam.project(lon, lat, np.full(40, 205.0))
        obs_img.append(np.full(40, k))
        obs_trk.append(np.arange(40))
        colrow.append(np.column_stack([c, r]) + rng.normal(0, 0.1, (40, 2)))
    tp = TiePoints(
        ["a", "b", "c"],
        ["A", "A", "B"],
        np.concatenate(obs_img),
        np.concatenate(obs_trk),
        np.concatenate(colrow),
        xy,
        205.0,
        "EPSG:32631",
        np.ones(120),
    )
    res = adjust(cams, tp, OrientationParams(), aoi_area_m2=150.0 * 150.0)
    assert not res.applied and "cover" in res.reason
    assert not np.any(res.corrections)
    few = tp.subset(tp.track < 8)
    res = adjust(cams, few, OrientationParams(min_spread=0.0), aoi_area_m2=150.0 * 150.0)
    assert not res.applied and "fewer than 20" in res.reason


def test_manifest_key(tmp_path, sample_aoi):
    doc = yaml.safe_load((sample_aoi / "scene.yaml").read_text())
    assert doc["orientation"] is False  # simulated cameras are exact
    for value, ok in (
        ({"model": "affine"}, True),
        ("auto", True),
        ({"modle": "shift"}, False),
        ({"model": "spline"}, False),
        ("yes please", False),
    ):
        d = dict(doc, orientation=value)
        p = tmp_path / "scene.yaml"
        for k in ("dem", "footprints"):
            d[k] = str(sample_aoi / (d[k]["path"] if isinstance(d[k], dict) else d[k]))
        d["epochs"] = [
            dict(
                e,
                images=[
                    dict(
                        i,
                        path=str(sample_aoi / i["path"]),
                        **({"camera": str(sample_aoi / i["camera"])} if "camera" in i else {}),
                    )
                    for i in e["images"]
                ],
            )
            for e in d["epochs"]
        ]
        d.pop("truth")
        p.write_text(yaml.safe_dump(d))
        if ok:
            load_manifest(p)
        else:
            with pytest.raises((ManifestError, ConfigError)):
                load_manifest(p)


@pytest.mark.slow
def test_exact_cameras_and_refusal_through_the_manifest(tmp_path, sample_aoi):
    """On sample_aoi's exact cameras the corrections stay below the floor (not applied, no warning); asking for
    more tie points than the images give refuses the correction with a warning and says so in the report."""
    import dataclasses
    import warnings

    m0 = load_manifest(sample_aoi / "scene.yaml")
    m = dataclasses.replace(m0, extras={**m0.extras, "orientation": {"enabled": True}})
    with warnings.catch_warnings():
        warnings.simplefilter("error", OrientationWarning)
        m2, rep = orient_manifest(m, out_dir=tmp_path / "a")
    assert m2 is m and rep["status"] == "not needed" and rep["largest_correction_px"] < 0.2
    assert rep["after"]["cross_epoch"]["median_px"] < 0.25
    m = dataclasses.replace(m0, extras={**m0.extras, "orientation": {"enabled": True, "min_points": 100000}})
    with pytest.warns(OrientationWarning, match="not applied"):
        m2, rep = orient_manifest(m, out_dir=tmp_path / "b")
    assert (
        m2 is m and rep["applied"] is False and rep["status"] == "insufficient" and "fewer than 100000" in rep["reason"]
    )
    assert (tmp_path / "b" / "orientation" / "orientation.json").is_file()


def test_schema_lists_every_parameter():
    import dataclasses

    from geocd.io.manifest import ORIENTATION_KEYS

    assert set(ORIENTATION_KEYS) == {f.name for f in dataclasses.fields(OrientationParams)}
