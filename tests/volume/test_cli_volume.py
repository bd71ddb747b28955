"""``geocd volume update|detect|render`` on the toy town written to disk as a scene folder."""

from __future__ import annotations

import json

import numpy as np
import pytest
import rasterio
import yaml
from click.testing import CliRunner

from geocd.cli import main
from geocd.io.frame import write_frame_sidecar
from geocd.io.raster import write_cog, write_image

from . import toyscene as T


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("toy_scene")
    (root / "images").mkdir()
    toy = T.make_toy(size=48)
    sun = {"SUN_AZIMUTH": "135.0", "SUN_ELEVATION": "60.0"}
    imgs_a = []
    for i, (c, im) in enumerate(zip(toy.cameras[:6], toy.images[:6])):
        p = root / "images" / f"A_{i}.tif"
        write_image(p, np.round(im * 255).astype(np.uint8)[None], tags=sun)
        write_frame_sidecar(p, c)
        imgs_a.append({"path": f"images/A_{i}.tif"})
    pb = root / "images" / "B_test.tif"
    write_image(pb, np.round(toy.test_image_b * 255).astype(np.uint8)[None], tags=sun)
    write_frame_sidecar(pb, toy.test_camera)
    grid = T.aoi_grid(1.0)
    write_cog(root / "dem.tif", np.full(grid.shape, T.H0, dtype=np.float32), grid)
    man = {
        "geocd_manifest": 1,
        "name": "toy",
        "aoi": {"crs": T.CRS, "bounds": list(grid.bounds), "posting_m": 0.5},
        "dem": {"path": "dem.tif", "vertical_datum": "ellipsoid"},
        "epochs": [{"name": "A", "images": imgs_a}, {"name": "B", "images": [{"path": "images/B_test.tif"}]}],
    }
    (root / "scene.yaml").write_text(yaml.safe_dump(man), encoding="utf-8")
    return root


def test_update_detect_render(scene, tmp_path):
    r = CliRunner()
    model = tmp_path / "model"
    res = r.invoke(
        main,
        [
            "--progress",
            "none",
            "volume",
            "update",
            str(model),
            "--manifest",
            str(scene / "scene.yaml"),
            "--passes",
            "2",
            "--above",
            "10",
        ],
    )
    assert res.exit_code == 0, res.output
    meta = json.loads((model / "model.json").read_text())
    assert meta["geometry"]["crs"] == T.CRS
    assert len(meta["history"]) == 12 and meta["sun_bins"][0][:2] == [135.0, 60.0]
    out = tmp_path / "det"
    res = r.invoke(
        main,
        [
            "--progress",
            "json",
            "volume",
            "detect",
            str(model),
            str(scene / "images" / "B_test.tif"),
            "--out",
            str(out),
            "--neighborhood",
            "3",
        ],
    )
    assert res.exit_code == 0, res.output
    with rasterio.open(out / "B_test_change_prob.tif") as ds:
        assert ds.count == 3 and ds.descriptions[0] == "change_probability"
        p = ds.read(1)
    assert np.nanmax(p) <= 1.0 and np.isfinite(p).mean() > 0.3
    with rasterio.open(out / "B_test_change_prob_ortho.tif") as ds:
        assert ds.crs.to_epsg() == 32632
    summary = json.loads((out / "B_test_change.json").read_text())
    assert summary["sun_bin"] == 0
    # under another sun, with the shadows cast from a DSM of epoch A (the flat DEM here: nothing is shaded)
    res = r.invoke(
        main,
        [
            "--progress",
            "none",
            "volume",
            "detect",
            str(model),
            str(scene / "images" / "B_test.tif"),
            "--out",
            str(tmp_path / "det_dsm"),
            "--sun",
            "160",
            "30",
            "--shadow-dsm",
            str(scene / "dem.tif"),
        ],
    )
    assert res.exit_code == 0, res.output
    relit = json.loads((tmp_path / "det_dsm" / "B_test_change.json").read_text())["relight"]
    assert relit["shadows"] == "DSM" and relit["class_fraction"]["lit>lit"] == 1.0, relit
    res = r.invoke(
        main,
        [
            "--progress",
            "none",
            "volume",
            "render",
            str(model),
            "--image",
            str(scene / "images" / "A_0.tif"),
            "--height-map",
            "--out",
            str(tmp_path / "ren"),
        ],
    )
    assert res.exit_code == 0, res.output
    with rasterio.open(tmp_path / "ren" / "expected_height_map.tif") as ds:
        h = ds.read(1)
    assert abs(np.nanmedian(h) - T.H0) < 1.0  # mostly ground
    assert (tmp_path / "ren" / "A_0_expected.tif").is_file()
    # incremental update of the saved model
    res = r.invoke(
        main,
        [
            "--progress",
            "none",
            "volume",
            "update",
            str(model),
            "--image",
            str(scene / "images" / "A_0.tif"),
            "--passes",
            "1",
        ],
    )
    assert res.exit_code == 0, res.output
    assert len(json.loads((model / "model.json").read_text())["history"]) == 13


def test_cli_errors_are_one_line(scene, tmp_path):
    r = CliRunner()
    model = tmp_path / "model"
    res = r.invoke(
        main,
        [
            "--progress",
            "none",
            "volume",
            "update",
            str(model),
            "--manifest",
            str(scene / "scene.yaml"),
            "--passes",
            "1",
            "--above",
            "10",
            "--exclude",
            "A_1",
            "--exclude",
            "A_2",
            "--exclude",
            "A_3",
            "--exclude",
            "A_4",
            "--exclude",
            "A_5",
        ],
    )
    assert res.exit_code == 0, res.output
    # the same model with a manifest in another CRS
    man = yaml.safe_load((scene / "scene.yaml").read_text())
    man["aoi"]["crs"] = "EPSG:32633"
    other = scene / "other.yaml"
    other.write_text(yaml.safe_dump(man), encoding="utf-8")
    res = r.invoke(main, ["--progress", "none", "volume", "update", str(model), "--manifest", str(other)])
    assert res.exit_code == 2
    assert "was built in" in res.output and "Traceback" not in res.output
    # no model there and nothing to define one
    res = r.invoke(
        main,
        [
            "--progress",
            "none",
            "volume",
            "update",
            str(tmp_path / "none"),
            "--image",
            str(scene / "images" / "A_0.tif"),
        ],
    )
    assert res.exit_code == 2 and "holds no model" in res.output
    # a folder that is not a model
    res = r.invoke(
        main,
        [
            "--progress",
            "none",
            "volume",
            "detect",
            str(scene / "images"),
            str(scene / "images" / "B_test.tif"),
            "--out",
            str(tmp_path / "x"),
        ],
    )
    assert res.exit_code == 2 and "no volume model" in res.output


def test_update_with_roofs_from_footprints(scene, tmp_path):
    """``--footprints``: the manifest's footprints give the boxes' roof heights (the log says how many)."""
    import geopandas as gpd
    from shapely.geometry import box

    from geocd.geodesy import from_lonlat

    polys = []
    for e0, e1, n0, n1, _h, _c in T.BOXES_A:
        lon, lat, _ = T.FRAME.from_enu(np.array([e0, e1]), np.array([n0, n1]), np.zeros(2))
        x, y = from_lonlat(lon, lat, T.CRS)
        polys.append(box(float(x[0]), float(y[0]), float(x[1]), float(y[1])))
    root = tmp_path / "scene_fp"
    import shutil

    shutil.copytree(scene, root)
    gpd.GeoDataFrame(geometry=polys, crs=T.CRS).to_file(root / "footprints.gpkg", driver="GPKG")
    man = yaml.safe_load((root / "scene.yaml").read_text())
    man["footprints"] = "footprints.gpkg"
    (root / "scene.yaml").write_text(yaml.safe_dump(man), encoding="utf-8")
    res = CliRunner().invoke(
        main,
        [
            "volume",
            "update",
            str(tmp_path / "m"),
            "--manifest",
            str(root / "scene.yaml"),
            "--passes",
            "1",
            "--above",
            "10",
            "--footprints",
        ],
    )
    assert res.exit_code == 0, res.output
    assert "roof heights from the footprints: 3 of 3 footprints" in res.output, res.output
