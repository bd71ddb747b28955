"""Manifest → products (GeoTIFF on the grid and in key-frame geometry, GeoPackage changes layer) and the CLI."""

import json

import numpy as np
import pytest
from click.testing import CliRunner
from scene import make_scene

from geocd.cli import main


@pytest.fixture(scope="module")
def manifest(tmp_path_factory):
    import yaml

    from geocd.io.raster import write_cog, write_image

    sc = make_scene(kind="rpc", size_m=36.0)
    root = tmp_path_factory.mktemp("pc_scene")
    (root / "images").mkdir()
    epochs = []
    for e in ("A", "B"):
        ims = []
        for img, cam, name in zip(sc.images[e], sc.cameras[e], sc.names[e]):
            write_image(root / "images" / f"{name}.tif", img, rpc=cam, nbits=11)
            ims.append({"path": f"images/{name}.tif", "name": name})
        epochs.append({"name": e, "date": "2020-01-01" if e == "A" else "2021-01-01", "images": ims})
    write_cog(root / "change_mask.tif", sc.truth.astype(np.uint8), sc.grid, dtype="uint8")
    doc = {
        "geocd_manifest": 1,
        "name": "pc_tiny",
        "aoi": {"crs": sc.grid.crs.to_string(), "bounds": list(sc.grid.bounds), "posting_m": 0.5},
        "epochs": epochs,
        "output": "out",
    }
    (root / "scene.yaml").write_text(yaml.safe_dump(doc), encoding="utf-8")
    return root, sc


@pytest.mark.slow
def test_cli_objectspace_products(manifest, tmp_path):
    import pyogrio
    import rasterio

    from geocd.change.metrics import binary_scores

    root, sc = manifest
    out = tmp_path / "o"
    res = CliRunner().invoke(
        main,
        [
            "--progress",
            "json",
            "probchange",
            str(root / "scene.yaml"),
            "--out",
            str(out),
            "--bins",
            "48",
            "--height-range",
            "196",
            "214",
        ],
    )
    assert res.exit_code == 0, res.output
    assert '"type": "result"' in res.output
    with rasterio.open(out / "probchange_probability.tif") as ds:
        assert ds.descriptions[:3] == ("probability", "log_odds", "coverage")
        assert ds.crs is not None and ds.tags()["method"] == "probchange"
        p = ds.read(1)
    with rasterio.open(out / "probchange_change_mask.tif") as ds:
        mask = ds.read(1)
        assert ds.nodata == -128
    assert (out / "probchange_probability.qml").exists() and (out / "probchange_change_mask.qml").exists()
    assert set(np.unique(mask)) <= {-128, -1, 0, 1}
    assert binary_scores(np.isin(mask, (-1, 1)), sc.truth)["f1"] > 0.6
    assert np.nanmax(p) <= 1.0 and np.nanmin(p) >= 0.0
    layers = [name for name, _ in pyogrio.list_layers(out / "probchange_changes.gpkg")]
    assert "changes" in layers and "layer_styles" in layers
    gdf = pyogrio.read_dataframe(out / "probchange_changes.gpkg", layer="changes")
    assert len(gdf) >= 2 and set(gdf["method"]) == {"probchange"}
    assert {"region_id", "sign", "area_m2", "confidence", "epoch_a", "epoch_b"} <= set(gdf.columns)
    summary = json.loads((out / "probchange_summary.json").read_text())
    assert summary["variant"] == "objectspace" and summary["noise_model"]["sigma"] > 0


@pytest.mark.slow
def test_cli_keyframe_products(manifest, tmp_path):
    import rasterio

    from geocd.io.cameras import load_camera

    root, sc = manifest
    out = tmp_path / "k"
    res = CliRunner().invoke(
        main,
        [
            "--progress",
            "none",
            "probchange",
            str(root / "scene.yaml"),
            "--variant",
            "keyframe",
            "--key",
            "B1",
            "--model",
            "thesis",
            "--out",
            str(out),
            "--bins",
            "48",
            "--height-range",
            "196",
            "214",
        ],
    )
    assert res.exit_code == 0, res.output
    kf = out / "probchange_keyframe_B1.tif"
    with rasterio.open(kf) as ds:
        assert ds.count == 4 and ds.rpcs is not None  # the key camera, cropped to the window
        tags = ds.tags()
        prob = ds.read(1)
    assert tags["key_image"] == "B1"
    cam = load_camera(kf, out / "probchange_keyframe_B1.camera.json")
    full = load_camera(root / "images" / "B1.tif")
    c0, r0 = int(tags["key_window_col0"]), int(tags["key_window_row0"])
    lon, lat = full.localize(np.array([c0 + 10.5]), np.array([r0 + 7.5]), np.array([205.0]))
    c, r = cam.project(lon, lat, np.array([205.0]))
    assert abs(c[0] - 10.5) < 1e-6 and abs(r[0] - 7.5) < 1e-6
    assert np.isfinite(prob).mean() > 0.5
    summary = json.loads((out / "probchange_summary.json").read_text())
    assert summary["depth_epoch"] == "B" and summary["key_frame"] == "B1"


@pytest.mark.slow
def test_cli_single_image_epoch_one_line_error(manifest, tmp_path):
    root, _ = manifest
    res = CliRunner().invoke(
        main,
        [
            "--progress",
            "none",
            "probchange",
            str(root / "scene.yaml"),
            "--image-b",
            "B2",
            "--out",
            str(tmp_path),
            "--height-range",
            "196",
            "214",
        ],
    )
    assert res.exit_code != 0
    assert "epoch 'B' has 1 image" in res.output and "Traceback" not in res.output
    res = CliRunner().invoke(
        main,
        [
            "--progress",
            "none",
            "probchange",
            str(root / "scene.yaml"),
            "--image-a",
            "A1",
            "--image-a",
            "A9",
            "--out",
            str(tmp_path),
        ],
    )
    assert res.exit_code != 0 and "are not in epoch 'A'" in res.output
