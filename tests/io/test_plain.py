"""Plain image pairs on a local grid (``--pixel-size``): geocd.io.plain and the two doors that use it."""

from __future__ import annotations

import json

import numpy as np
import pytest
import rasterio
from click.testing import CliRunner
from PIL import Image

from geocd.cli import main
from geocd.errors import ConfigError
from geocd.io.plain import LOCAL_IMAGE_CRS_WKT, is_georeferenced, plain_image_vrt, plain_images_on_a_grid


def _png(path, shape=(48, 64), seed=0, square=None):
    rng = np.random.default_rng(seed)
    a = (rng.random(shape + (3,)) * 60 + 80).astype(np.uint8)
    if square is not None:
        r, c, n = square
        a[r : r + n, c : c + n] = 230
    Image.fromarray(a).save(path)
    return path


@pytest.mark.filterwarnings("ignore::rasterio.errors.NotGeoreferencedWarning")  # the raw PNG, opened to compare
def test_a_vrt_puts_the_pixels_on_a_local_metric_grid(tmp_path):
    src = _png(tmp_path / "a.png")
    assert not is_georeferenced(src)
    vrt = plain_image_vrt(src, 0.3, tmp_path)
    with rasterio.open(vrt) as ds, rasterio.open(src) as raw:
        assert (ds.width, ds.height, ds.count) == (64, 48, 3)
        assert ds.transform == rasterio.Affine(0.3, 0, 0, 0, -0.3, 48 * 0.3)  # lower-left corner at (0, 0)
        assert ds.crs is not None and ds.crs.to_wkt().startswith('LOCAL_CS["geocd image grid')
        np.testing.assert_array_equal(ds.read(), raw.read())
    assert "metre" in LOCAL_IMAGE_CRS_WKT


def test_refusals(tmp_path):
    a, b = _png(tmp_path / "a.png"), _png(tmp_path / "b.png", shape=(40, 64))
    with pytest.raises(ConfigError, match="must have one size"):
        plain_images_on_a_grid([a, b], 0.5, tmp_path)
    with pytest.raises(ConfigError, match="> 0"):
        plain_image_vrt(a, 0.0, tmp_path)
    geo = tmp_path / "geo.tif"
    with rasterio.open(
        geo, "w", driver="GTiff", width=8, height=8, count=1, dtype="uint8", crs="EPSG:32631",
        transform=rasterio.Affine(0.5, 0, 500000, 0, -0.5, 4800000),
    ) as ds:  # fmt: skip
        ds.write(np.zeros((1, 8, 8), np.uint8))
    assert is_georeferenced(geo)
    with pytest.raises(ConfigError, match="leave --pixel-size out"):
        plain_image_vrt(geo, 0.5, tmp_path)


def test_same_stem_in_two_folders_gets_two_vrts(tmp_path):
    (tmp_path / "A").mkdir()
    (tmp_path / "B").mkdir()
    a, b = _png(tmp_path / "A" / "x.png", seed=1), _png(tmp_path / "B" / "x.png", seed=2)
    va, vb = plain_images_on_a_grid([a, b], 0.5, tmp_path)
    assert va != vb


def test_geocd_screen_on_a_plain_pair(tmp_path):
    a = _png(tmp_path / "a.png", shape=(96, 96), seed=3)
    b = _png(tmp_path / "b.png", shape=(96, 96), seed=3, square=(30, 30, 30))  # a bright new roof
    out = tmp_path / "out"
    args = ["--progress", "none", "screen", str(a), str(b), "--feature", "patch", "--cell", "8"]
    r = CliRunner().invoke(main, args + ["--threshold", "0.5", "--out", str(out)])
    assert r.exit_code == 2 and "no georeference" not in r.output and "--pixel-size" in r.output, r.output
    r = CliRunner().invoke(main, args + ["--threshold", "0.5", "--pixel-size", "0.5", "--out", str(out)])
    assert r.exit_code == 0, r.output
    with rasterio.open(out / "screen_dissimilarity.tif") as ds:
        assert ds.crs.to_wkt().startswith('LOCAL_CS["geocd image grid') and ds.transform.a == 0.5
        d = ds.read(1)
    assert np.nanmean(d[32:58, 32:58]) > np.nanmean(d[70:, 70:])  # the new roof stands out


def test_the_screen_of_two_rasters_says_it_needs_a_rule_before_reading_them(tmp_path):
    a, b = _png(tmp_path / "a.png"), _png(tmp_path / "b.png")
    r = CliRunner().invoke(main, ["--progress", "none", "screen", str(a), str(b), "--pixel-size", "0.5"])
    assert r.exit_code == 2 and "needs a threshold rule" in r.output, r.output
    assert not (tmp_path / "geocd_out").exists()


def test_geocd_mpp_on_a_plain_pair_and_its_refusals(tmp_path):
    a = _png(tmp_path / "a.png", shape=(80, 80), seed=4)
    b = _png(tmp_path / "b.png", shape=(80, 80), seed=4, square=(20, 20, 24))
    out = tmp_path / "mpp"
    base = ["--progress", "none", "mpp", "--image-a", str(a), "--image-b", str(b), "--out", str(out)]
    r = CliRunner().invoke(main, base + ["--pixel-size", "0.5", "--max-iter", "20"])
    assert r.exit_code == 0, r.output
    with rasterio.open(out / "mpp_buildings.tif") as ds:
        assert ds.crs.to_wkt().startswith('LOCAL_CS["geocd image grid') and ds.shape == (80, 80)
    assert json.loads((out / "mpp_summary.json").read_text())
    r = CliRunner().invoke(main, ["--progress", "none", "mpp", "sample_aoi", "--pixel-size", "0.5"])
    assert r.exit_code == 2 and "--pixel-size is for two plain images" in r.output, r.output
