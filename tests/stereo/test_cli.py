"""``geocd stereo MANIFEST`` on the synthetic pair written as GeoTIFFs with RPC tags."""

import json

import numpy as np
import pytest
import rasterio
import yaml
from click.testing import CliRunner

from geocd.cli import main
from geocd.io.raster import write_image
from geocd.stereo import BANDS, read_pair_dem


@pytest.fixture
def scene_dir(tmp_path, scene):
    for img, cam, name in zip(scene.images, scene.cameras, scene.names):
        write_image(tmp_path / f"{name}.tif", img, rpc=cam, nbits=11 if img.dtype == np.uint16 else None)
    l, b, r, t = scene.grid.bounds
    m = {
        "geocd_manifest": 1,
        "name": "synthetic",
        "aoi": {"crs": scene.grid.crs.to_string(), "bounds": [l, b, r, t], "posting_m": scene.grid.posting_m},
        "epochs": [{"name": "A", "images": [f"{n}.tif" for n in scene.names]}],
    }
    (tmp_path / "scene.yaml").write_text(yaml.safe_dump(m))
    return tmp_path


def test_cli_writes_pair_dems(scene_dir, scene):
    res = CliRunner().invoke(
        main,
        [
            "--progress",
            "json",
            "stereo",
            str(scene_dir / "scene.yaml"),
            "--out",
            str(scene_dir / "out"),
            "--height-range",
            "180",
            "230",
        ],
    )
    assert res.exit_code == 0, res.output
    lines = [json.loads(x) for x in res.stderr.splitlines() if x.startswith("{")] if hasattr(res, "stderr") else []
    p = scene_dir / "out" / "stereo" / "A" / "img_a__img_b.tif"
    assert p.is_file()
    with rasterio.open(p) as ds:
        assert ds.descriptions == BANDS
    pd = read_pair_dem(p)
    assert pd.grid.same_as(scene.grid)
    assert np.median(np.abs(pd.z_m - scene.truth)[pd.valid]) < 0.2
    if lines:
        assert any(x["type"] == "progress" for x in lines) and lines[-1]["type"] == "result"


def test_cli_errors_are_one_line(scene_dir):
    res = CliRunner().invoke(main, ["stereo", str(scene_dir / "scene.yaml"), "--epoch", "nope"])
    assert res.exit_code != 0
    assert "epoch 'nope' is not in the manifest" in res.output
    assert "Traceback" not in res.output
    res = CliRunner().invoke(main, ["stereo", str(scene_dir / "scene.yaml"), "--window", "4"])
    assert res.exit_code != 0 and "odd" in res.output


@pytest.mark.parametrize("height_range, warned", [(("180", "230"), False), (("150", "192"), True)])
def test_cli_warns_of_a_low_completeness(scene_dir, height_range, warned):
    """A pair-DEM whose heights lie outside the searched range holds few heights: a warning on screen and in the
    summary naming the pair, the share and the flags; a good pair-DEM none."""
    res = CliRunner().invoke(
        main,
        [
            "stereo",
            "--json",
            str(scene_dir / "scene.yaml"),
            "--out",
            str(scene_dir / "out"),
            "--height-range",
            *height_range,
        ],
    )
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout)
    w = doc["summary"]["pair_warnings"]
    if warned:
        assert len(w) == 1 and "A/img_a__img_b" in w[0] and "below 70%" in w[0] and "range_limit" in w[0]
        assert any("completeness" in x for x in doc["warnings"])
    else:
        assert w == [] and not any("completeness" in x for x in doc["warnings"])
