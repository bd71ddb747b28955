"""True orthorectification: geometry, occlusion, dtypes, probability maps, files and the CLI."""

from __future__ import annotations

import numpy as np
import pytest
import rasterio

from geocd.camera import FrameCamera
from geocd.errors import ConfigError, GridError
from geocd.geodesy import AOIGrid
from geocd.ortho import (
    NO_HEIGHT,
    OCCLUDED,
    OUTSIDE_IMAGE,
    SEEN,
    OrthoParams,
    fill_dsm_holes,
    occlusion_margin_cells,
    orthorectify,
    view_geometry,
)

CRS = "EPSG:32631"
X0, Y0 = 374200.0, 4824300.0


def _scene():
    """100 m × 100 m at 1 m, flat ground at 100 m with a 20 m × 20 m, 10 m high block in the middle;
    a nadir-pointing pinhole 1000 m above the ground and 1000 m west of the scene: a 45° view from the west."""
    grid = AOIGrid.from_bounds(X0, Y0, X0 + 100, Y0 + 100, 1.0, CRS)
    dsm = np.full(grid.shape, 100.0)
    dsm[40:60, 40:60] = 110.0
    cam = FrameCamera(
        width=2600,
        height=600,
        focal_px=1000.0,
        position=(X0 + 50 - 1000.0, Y0 + 50, 1100.0),
        opk_deg=(0, 0, 0),
        crs=CRS,
        vertical_datum="ellipsoid",
        principal_point_px=(1300.0, 300.0),
    )
    return grid, dsm, cam


def _exact_hidden(grid, dsm, cam):
    """Ground cells whose segment to the camera crosses the block (slab test)."""
    x, y = grid.xy()
    C = np.array(cam.position)
    hidden = np.zeros(grid.shape, bool)
    lo = np.array([X0 + 40, Y0 + 40, 100.0])
    hi = np.array([X0 + 60, Y0 + 60, 110.0])
    for i in range(grid.height):
        for j in range(grid.width):
            if dsm[i, j] > 100:
                continue
            P = np.array([x[i, j], y[i, j], 100.0])
            d = C - P
            t0, t1 = 1e-9, 1.0
            for k in range(3):
                if abs(d[k]) < 1e-12:
                    if not (lo[k] <= P[k] <= hi[k]):
                        t0, t1 = 1, 0
                    continue
                a, b = (lo[k] - P[k]) / d[k], (hi[k] - P[k]) / d[k]
                t0, t1 = max(t0, min(a, b)), min(t1, max(a, b))
            hidden[i, j] = t0 < t1
    return hidden


def test_occlusion_matches_exact_geometry():
    grid, dsm, cam = _scene()
    img = np.ones((cam.height, cam.width), np.uint8)
    # the ray must pass more than the tolerance below a surface to be blocked: an exact DSM, a small tolerance
    r = orthorectify(img, cam, grid, dsm, params=OrthoParams(occlusion_tol_m=0.1))
    assert r.occlusion_tol_m == 0.1
    truth = _exact_hidden(grid, dsm, cam)
    occ = r.status == OCCLUDED
    # ~10 m × 20 m hidden strip east of the block
    assert 180 <= truth.sum() <= 230
    assert (occ == truth).mean() > 0.995
    assert (occ & truth).sum() >= 0.93 * truth.sum()
    assert (occ & ~truth).sum() <= 0.05 * truth.sum()
    # 45° from the west: the ray climbs westward one cell per metre
    g = r.geometry
    assert abs(float(np.median(g.view_zenith_deg)) - 45.0) < 3.0
    assert abs(float(np.median(g.view_azimuth_deg)) - 270.0) < 2.0
    assert np.all(r.observed == (r.status == SEEN))
    assert occlusion_margin_cells(dsm, g) >= 10
    # the default tolerance (0.5 m for an exact DSM) gives up the last 0.5 m of the strip: 9 of 10 columns
    rd = orthorectify(img, cam, grid, dsm)
    assert rd.occlusion_tol_m == 0.5
    assert 0.85 * truth.sum() <= (rd.status == OCCLUDED).sum() <= truth.sum()


def test_classic_ortho_smears_and_true_ortho_does_not():
    grid, dsm, cam = _scene()
    # the image of a bright block on dark ground, rendered by projecting the DSM surface densely
    img = np.zeros((cam.height, cam.width), np.float32)
    r_geo = orthorectify(
        np.zeros((cam.height, cam.width), np.float32), cam, grid, dsm, params=OrthoParams(occlusion=False)
    )
    roof = dsm > 100
    c, rr = r_geo.geometry.col[roof], r_geo.geometry.row[roof]
    cc, rc = np.meshgrid(np.arange(cam.width) + 0.5, np.arange(cam.height) + 0.5)
    box = (cc >= c.min() - 0.5) & (cc <= c.max() + 0.5) & (rc >= rr.min() - 0.5) & (rc <= rr.max() + 0.5)
    img[box] = 1.0
    classic = orthorectify(img, cam, grid, dsm, params=OrthoParams(occlusion=False, antialias=False))
    true = orthorectify(img, cam, grid, dsm, params=OrthoParams(antialias=False))
    hidden = true.status == OCCLUDED
    assert hidden.sum() > 150
    assert np.nanmean(classic.values[0][hidden]) > 0.9  # the roof smeared onto the street behind it
    assert np.all(np.isnan(true.values[0][hidden]))
    ground = ~roof & ~hidden
    ground[38:62, 38:75] = False  # keep clear of the roof edge blur
    assert np.nanmax(true.values[0][ground]) < 0.05


def test_sampling_follows_the_pixel_corner_convention():
    grid, dsm, cam = _scene()
    cc, _ = np.meshgrid(np.arange(cam.width) + 0.5, np.arange(cam.height) + 0.5)
    r = orthorectify(cc, cam, grid, dsm, params=OrthoParams(occlusion=False))
    ok = r.observed
    assert ok.mean() > 0.99
    np.testing.assert_allclose(r.values[0][ok], r.geometry.col[ok], atol=1e-9)
    # a window of the image with its offset gives the same values
    win = cc[100:500, 1800:2500]
    rw = orthorectify(win, cam, grid, dsm, col0=1800, row0=100, params=OrthoParams(occlusion=False))
    both = rw.observed & ok
    assert both.mean() > 0.95
    np.testing.assert_allclose(rw.values[0][both], r.values[0][both], atol=1e-9)


def test_dtypes_bands_and_probability_maps():
    grid, dsm, cam = _scene()
    rng = np.random.default_rng(0)
    u16 = rng.integers(0, 2047, (2, cam.height, cam.width)).astype(np.uint16)
    r = orthorectify(u16, cam, grid, dsm)
    assert r.values.dtype == np.uint16 and r.values.shape == (2,) + grid.shape
    assert np.all(r.values[:, ~r.observed] == 0)
    # class probabilities (float64, 3 classes summing to 1) stay probabilities
    p = rng.random((3, cam.height, cam.width))
    p /= p.sum(axis=0)
    rp = orthorectify(p, cam, grid, dsm)
    assert rp.values.dtype == np.float64
    s = rp.values.sum(axis=0)
    np.testing.assert_allclose(s[rp.observed], 1.0, atol=1e-9)
    assert np.all(np.isnan(rp.values[:, ~rp.observed]))
    assert set(rp.weights) >= {"view_zenith_deg", "incidence_deg", "px_per_cell", "cos_incidence"}
    # labels with nearest sampling keep their values
    lab = rng.integers(1, 5, (cam.height, cam.width)).astype(np.uint8)
    rl = orthorectify(lab, cam, grid, dsm, params=OrthoParams(resampling="nearest"))
    assert set(np.unique(rl.values[0][rl.observed])) <= {1, 2, 3, 4}
    # the same geometry can be reused for another array of the same image
    g = view_geometry(cam, grid, dsm)
    rg = orthorectify(p, cam, grid, dsm, geometry=g)
    np.testing.assert_array_equal(rg.status, rp.status)


def test_nodata_heights_image_and_bad_inputs():
    grid, dsm, cam = _scene()
    d = dsm.copy()
    d[:5, :] = np.nan
    img = np.ones((cam.height, cam.width), np.float32)
    valid = np.ones(img.shape, bool)
    r0 = orthorectify(img, cam, grid, d)
    valid[:, : int(np.nanmax(r0.geometry.col)) - 20] = False  # most of the image is nodata
    r = orthorectify(img, cam, grid, d, valid=valid)
    assert np.all(r.status[:5] == NO_HEIGHT)
    assert (r.status == OUTSIDE_IMAGE).sum() > 0.5 * r.status.size
    filled, hole = fill_dsm_holes(d)
    assert hole[:5].all() and np.all(filled[:5] == 100.0)
    with pytest.raises(GridError):
        orthorectify(img, cam, grid, dsm[:50])
    with pytest.raises(ConfigError):
        OrthoParams(resampling="cubic")


def test_fill_dsm_holes_uses_the_low_side():
    d = np.full((20, 20), 100.0)
    d[5:15, 5:10] = 112.0
    d[5:15, 10:13] = np.nan  # a hole between a roof and the ground
    filled, hole = fill_dsm_holes(d)
    assert np.all(filled[hole] == 100.0)
    prior = np.full((20, 20), 99.0)
    filled2, _ = fill_dsm_holes(d, prior)
    assert np.all(filled2[hole] == 99.0)


@pytest.mark.slow
def test_cli_single_image_and_manifest(tmp_path, sample_aoi):
    from click.testing import CliRunner

    from geocd.cli import main

    r = CliRunner().invoke(
        main,
        [
            "--progress",
            "none",
            "ortho",
            str(sample_aoi / "images" / "B_sat2.tif"),
            "--dsm",
            str(sample_aoi / "truth" / "dsm_B.tif"),
            "--out",
            str(tmp_path / "b2.tif"),
            "--view-bands",
        ],
    )
    assert r.exit_code == 0, r.output
    with rasterio.open(tmp_path / "b2.tif") as ds:
        assert ds.dtypes[0] == "uint16" and ds.count == 1
        m = ds.read_masks(1)
        assert 0.01 < (m == 0).mean() < 0.04  # occluded cells are masked
        assert ds.driver == "GTiff" and ds.tags(ns="IMAGE_STRUCTURE").get("LAYOUT") == "COG"
    with rasterio.open(tmp_path / "b2_status.tif") as ds:
        st = ds.read(1)
        assert np.array_equal(st == OCCLUDED, m == 0)
    with rasterio.open(tmp_path / "b2_view.tif") as ds:
        assert ds.descriptions[0] == "view_zenith_deg"
    assert (tmp_path / "b2.qml").exists() and (tmp_path / "b2_status.qml").exists()
    # manifest mode, one image, a given DSM per epoch (no stereo run)
    r = CliRunner().invoke(
        main,
        [
            "--progress",
            "none",
            "ortho",
            str(sample_aoi / "scene.yaml"),
            "--image",
            "A_air2",
            "--dsm",
            f"A={sample_aoi / 'truth' / 'dsm_A.tif'}",
            "--out",
            str(tmp_path / "run"),
        ],
    )
    assert r.exit_code == 0, r.output
    with rasterio.open(tmp_path / "run" / "ortho" / "A" / "A_air2.tif") as ds:
        assert ds.count == 3 and ds.dtypes[0] == "uint8"
    # refusing to overwrite, and a missing DSM
    r = CliRunner().invoke(
        main,
        [
            "--progress",
            "none",
            "ortho",
            str(sample_aoi / "images" / "B_sat2.tif"),
            "--dsm",
            str(sample_aoi / "truth" / "dsm_B.tif"),
            "--out",
            str(tmp_path / "b2.tif"),
            "--no-overwrite",
        ],
    )
    assert r.exit_code != 0 and "exist" in r.output
    r = CliRunner().invoke(main, ["--progress", "none", "ortho", str(sample_aoi / "images" / "B_sat2.tif")])
    assert r.exit_code != 0 and "--dsm" in r.output


def test_manifest_run_on_given_pair_dems(tmp_path, sample_aoi):
    """An epoch's pair-DEMs from an earlier stereo run make its DSM without matching: their median, the largest
    surface median they name in its tag; pair-DEMs on another grid are refused before any ortho."""
    from geocd.io.raster import read_dem
    from geocd.ortho.pipeline import run_ortho
    from geocd.stereo.params import StereoParams
    from geocd.stereo.products import PairDEM

    truth = read_dem(sample_aoi / "truth" / "dsm_A.tif")
    grid, z = truth.grid, truth.height_m.astype(np.float32)
    rng = np.random.default_rng(0)

    def pair(dz, k, g=grid, zz=z):
        valid = rng.random(zz.shape) > 0.2
        return PairDEM(
            z_m=np.where(valid, zz + dz, np.nan).astype(np.float32),
            score=np.zeros(zz.shape, np.float32),
            g_px_per_m=np.ones(zz.shape, np.float32),
            valid=valid,
            grid=g,
            name=f"p{k}",
            meta={"params": StereoParams(surface_median=k).to_dict()},
        )

    pds = [pair(-1.0, 1), pair(0.0, 7), pair(2.0, 1)]
    got = run_ortho(sample_aoi, epochs=["A"], images=["A_air2"], out_dir=tmp_path, grid=grid, pair_dems={"A": pds})
    want = np.nanmedian(np.stack([np.where(p.valid, p.z_m, np.nan) for p in pds]), axis=0)
    with rasterio.open(got["outputs"]["A/dsm"]) as ds:
        h, filled = ds.read(1), ds.read(2) > 0.5
        assert ds.tags()["surface_median_cells"] == "7"
    has = np.isfinite(want)
    assert np.array_equal(filled, ~has) and np.array_equal(h[has], want[has].astype(np.float32))
    assert got["dsm_source"]["A"] == "geocd stereo: median of 3 given pair-DEMs" and "A/A_air2" in got["results"]
    crop = AOIGrid.from_bounds(*grid.bounds[:2], grid.bounds[2] - 10.0, grid.bounds[3], grid.posting_m, grid.crs)
    with pytest.raises(GridError, match="not the run's"):
        run_ortho(
            sample_aoi,
            epochs=["A"],
            images=["A_air2"],
            out_dir=tmp_path / "x",
            grid=grid,
            pair_dems={"A": [pair(0.0, 1, crop, z[:, :-20])]},
        )
    assert not (tmp_path / "x" / "ortho").exists()
