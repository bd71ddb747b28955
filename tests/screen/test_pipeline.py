"""The screen on files: tiles, resampling, products, the command line."""

from __future__ import annotations

import json

import numpy as np
import pytest

from geocd.geodesy import AOIGrid
from geocd.io.raster import write_cog
from geocd.screen import FeatureSpec, ScreenParams
from geocd.screen.pipeline import run_screen_files, screen_rasters

from .scenes import nochange, pair

GRID = AOIGrid.from_bounds(500000.0, 4000000.0, 500000.0 + 0.5 * 256, 4000000.0 + 0.5 * 256, 0.5, "EPSG:32631")


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("screen")
    a, b, truth = pair(size=256, box=(90, 150, 100, 170), rgb=True)
    na, nb = nochange(size=256, seed=3)
    paths = {}
    for k, v in (("a", a), ("nc_a", na), ("nc_b", nb)):
        paths[k] = write_cog(d / f"{k}.tif", (v * 1000).astype(np.uint16), GRID)
    # B on its own grid: a larger extent at another posting (resampled onto A's grid)
    gb = AOIGrid.from_bounds(
        499990.0, 3999990.0, 500000.0 + 0.5 * 256 + 10, 4000000.0 + 0.5 * 256 + 10, 0.4, "EPSG:32631"
    )
    from geocd.io.raster import read_on_grid  # noqa: F401 (the writer below is the reference resampler's inverse)
    from rasterio.warp import Resampling, reproject

    bb = np.zeros((3, *gb.shape), np.float32)
    for k in range(3):
        reproject(
            b[k],
            bb[k],
            src_transform=GRID.transform,
            src_crs=GRID.crs.to_wkt(),
            dst_transform=gb.transform,
            dst_crs=gb.crs.to_wkt(),
            resampling=Resampling.bilinear,
            src_nodata=np.nan,
            dst_nodata=np.nan,
        )
    paths["b"] = write_cog(d / "b.tif", np.nan_to_num(bb * 1000, nan=0).astype(np.uint16), gb)
    paths["truth"] = write_cog(d / "truth.tif", truth.astype(np.uint8), GRID)
    return d, paths, truth


@pytest.mark.slow
def test_tiles_give_the_whole_grid_features_and_nearly_its_superpixels(files):
    d, p, truth = files
    params = ScreenParams(feature=FeatureSpec("randbank", 16))
    whole = screen_rasters(p["a"], p["b"], params=params, tile_size=1024)
    tiled = screen_rasters(p["a"], p["b"], params=params, tile_size=64, out=d / "tiled")
    assert whole.n_tiles == 1 and tiled.n_tiles == 16
    assert tiled.overlap_px % 16 == 0 and tiled.overlap_px >= 16 + RandomBankFeatureContext()
    ok = np.isfinite(whole.grid_dissimilarity)
    assert np.allclose(tiled.grid_dissimilarity[ok], whole.grid_dissimilarity[ok], atol=1e-5)
    # Felzenszwalb's segments depend on the window (its merges are global): values differ near seams, and the
    # decisions at a threshold (Otsu's, on the whole grid) agree on most cells
    from skimage.filters import threshold_otsu

    t = threshold_otsu(whole.dissimilarity[ok])
    agree = ((tiled.dissimilarity > t) == (whole.dissimilarity > t))[ok].mean()
    same = np.isclose(tiled.dissimilarity, whole.dissimilarity, atol=1e-4)[ok].mean()
    print(f"tiled vs whole: equal values {same:.3f}, same decision {agree:.4f}")
    assert agree > 0.98, agree
    assert any("resampled" in n for n in whole.notes)


def RandomBankFeatureContext():
    from geocd.screen import RandomBankFeature

    return RandomBankFeature(16).context_px


@pytest.mark.slow
def test_products_threshold_from_the_nochange_pair(files):
    d, p, truth = files
    out = d / "out"
    res = run_screen_files(
        p["a"],
        p["b"],
        out=out,
        params=ScreenParams(feature=FeatureSpec("patch", 16)),
        nochange=(p["nc_a"], p["nc_b"]),
        tile_size=128,
    )
    o = res["outputs"]
    for k in ("dissimilarity", "change_mask", "changes", "summary"):
        assert o[k].exists(), k
    assert (out / "screen_dissimilarity.qml").exists() and (out / "screen_change_mask.qml").exists()
    s = json.loads(o["summary"].read_text())
    assert "no-change pair" in s["threshold_rule"] and s["null"]["n"] > 1000
    import geopandas as gpd
    import rasterio

    from geocd.change.regions import COLUMNS

    reg = gpd.read_file(o["changes"], layer="changes")
    assert list(reg.columns[:-1]) == list(COLUMNS) and len(reg) >= 1
    assert reg["confidence"].between(99, 100).all()  # percent
    with rasterio.open(o["change_mask"]) as ds:
        m = ds.read(1)
    with rasterio.open(o["dissimilarity"]) as ds:
        assert ds.descriptions == ("dissimilarity", "grid_dissimilarity", "confidence", "excluded")
    changed = m == 1
    tp = (changed & truth).sum()
    f1 = 2 * tp / (changed.sum() + truth.sum())
    assert f1 > 0.8, f1
    # a labelled pair (here: the same pair and truth — the test only checks the plumbing)
    res2 = run_screen_files(
        p["a"],
        p["b"],
        out=d / "out2",
        params=ScreenParams(feature=FeatureSpec("patch", 16)),
        labelled=(p["a"], p["b"], p["truth"]),
        tile_size=256,
    )
    assert "best F1" in res2["rule"] and res2["null"] is None


def test_cli_screen_and_bad_weights(files, tmp_path):
    from click.testing import CliRunner

    from geocd.cli import main
    from geocd.screen.cnn import random_state_dict

    d, p, _ = files
    r = CliRunner().invoke(
        main,
        [
            "--progress",
            "none",
            "screen",
            str(p["a"]),
            str(p["b"]),
            "--nochange",
            str(p["nc_a"]),
            "--nochange",
            str(p["nc_b"]),
            "--out",
            str(tmp_path / "cli"),
            "--json",
        ],
    )
    assert r.exit_code == 0, r.output
    doc = json.loads(r.stdout)
    assert doc["status"] == "ok" and "change_mask" in doc["outputs"]
    assert (tmp_path / "cli" / "geocd_screen.log").exists()
    np.savez(tmp_path / "w.npz", **random_state_dict("vgg16", 0))
    r = CliRunner().invoke(
        main,
        [
            "--progress",
            "none",
            "screen",
            str(p["a"]),
            str(p["b"]),
            "--threshold",
            "0.5",
            "--feature",
            "cnn",
            "--backbone",
            "vgg19",
            "--weights",
            str(tmp_path / "w.npz"),
            "--out",
            str(tmp_path / "cli2"),
        ],
    )
    assert r.exit_code == 2 and "does not fit the vgg19 backbone" in r.output and "vgg16" in r.output
    r = CliRunner().invoke(
        main, ["--progress", "none", "screen", str(p["a"]), str(p["b"]), "--out", str(tmp_path / "cli3")]
    )
    assert r.exit_code == 2 and "threshold rule" in r.output
    r = CliRunner().invoke(
        main, ["--progress", "none", "screen", str(p["a"]), str(p["b"]), "--confidence", "0.99", "--threshold", "1"]
    )
    assert r.exit_code == 2 and "percent" in r.output


@pytest.mark.filterwarnings("ignore::rasterio.errors.NotGeoreferencedWarning")
def test_files_of_other_bands_grids_and_places(files, tmp_path):
    """Bad inputs on files: a grey B against an RGB A on another grid is resampled and compared in grey; a B
    that does not overlap A's grid, or a file without a CRS, is refused with an error naming the problem."""
    from geocd.errors import CRSError, NoOverlapError

    d, p, truth = files
    import rasterio

    with rasterio.open(p["b"]) as ds:
        rgb = ds.read().astype(np.float32)
        gb = AOIGrid.from_raster(ds)
    grey_b = write_cog(tmp_path / "b_grey.tif", rgb.mean(axis=0).astype(np.uint16), gb)
    r = screen_rasters(p["a"], grey_b, params=ScreenParams(feature=FeatureSpec("patch", 16)))
    assert r.dissimilarity.shape == GRID.shape
    assert any("bands" in n and "grey" in n for n in r.notes), r.notes
    assert any("resampled" in n for n in r.notes), r.notes
    ok = np.isfinite(r.dissimilarity)
    assert ok.mean() > 0.9
    # grey vs RGB still finds the new roof: its cells are well above the median
    assert np.nanmedian(r.dissimilarity[truth]) > 2 * np.nanmedian(r.dissimilarity[~truth])
    far = AOIGrid.from_bounds(600000.0, 4000000.0, 600000.0 + 0.5 * 64, 4000000.0 + 0.5 * 64, 0.5, "EPSG:32631")
    elsewhere = write_cog(tmp_path / "far.tif", np.ones((64, 64), np.uint16), far)
    with pytest.raises(NoOverlapError, match="no valid pixels on the grid"):
        screen_rasters(p["a"], elsewhere)
    with rasterio.open(tmp_path / "nocrs.tif", "w", driver="GTiff", width=64, height=64, count=1, dtype="uint16") as ds:
        ds.write(np.ones((1, 64, 64), np.uint16))
    with pytest.raises(CRSError, match="no CRS"):
        screen_rasters(p["a"], tmp_path / "nocrs.tif")


@pytest.mark.slow
def test_views_without_a_dem_sit_on_the_matched_ground_height(sample_aoi):
    """Without a DEM the views go on a plane at the ground height of a coarse match of two views of one epoch
    (a plane at the cameras' mid height can be hundreds of metres off and misplace every view by its parallax)."""
    from geocd.io.manifest import load_manifest
    from geocd.io.raster import read_dem
    from geocd.screen.pipeline import flat_ground_height
    from geocd.stereo.scene import default_aoi_grid, load_epoch_images

    m = load_manifest(sample_aoi)
    vb = load_epoch_images(m, m.epoch("B"))
    va = load_epoch_images(m, m.epoch("A"))
    dem = read_dem(m.dem.path, vertical_datum=m.dem.vertical_datum).to_ellipsoidal().height_m
    grid = default_aoi_grid(m, {"A": va, "B": vb}, dem_median=float(np.nanmedian(dem)))
    names = [("A", va[0]), ("B", vb[0]), ("B", vb[1])]
    h = flat_ground_height(names, grid)
    assert h == pytest.approx(float(np.nanmedian(dem)), abs=3.0)
