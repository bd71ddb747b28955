"""The full run (geocd run): configuration tree, input checks, and end-to-end on simulated scenes."""

import json

import numpy as np
import pytest
import yaml

from geocd.errors import ConfigError
from geocd.pipeline import RunConfig, pick_epochs, run


def test_config_round_trip(tmp_path):
    cfg = RunConfig()
    d = cfg.to_dict()
    assert d["stereo"]["window"] == 7 and d["change"]["combine"] == "majority" and d["pairs"] == "same-kind"
    p = tmp_path / "cfg.json"
    p.write_text(json.dumps(d, default=list))
    back = RunConfig.load(p)
    assert json.loads(json.dumps(back.to_dict(), default=list)) == json.loads(json.dumps(d, default=list))
    with pytest.raises(ConfigError, match="unknown run configuration keys"):
        RunConfig.from_dict({"stereo": {}, "colour": 1})
    with pytest.raises(ConfigError, match="unknown stereo parameters"):
        RunConfig.from_dict({"stereo": {"windw": 5}})


def _manifest(tmp_path, n_a, n_b):
    (tmp_path / "img").mkdir()
    eps = []
    for name, n in (("A", n_a), ("B", n_b)):
        imgs = []
        for i in range(n):
            f = tmp_path / "img" / f"{name}{i}.tif"
            f.write_bytes(b"")
            imgs.append(f"img/{f.name}")
        eps.append({"name": name, "date": f"202{len(eps)}-01-01", "images": imgs})
    p = tmp_path / "scene.yaml"
    p.write_text(yaml.safe_dump({"epochs": eps}))
    return p


def test_epoch_with_one_image_is_a_clear_error(tmp_path):
    p = _manifest(tmp_path, 3, 1)
    with pytest.raises(ConfigError, match="epoch 'B' has 1 image"):
        run(p, out_dir=tmp_path / "out")
    assert not (tmp_path / "out" / "sc_change.tif").exists()


def test_pick_epochs(tmp_path):
    from geocd.io.manifest import load_manifest

    m = load_manifest(_manifest(tmp_path, 2, 2))
    a, b = pick_epochs(m)
    assert (a.name, b.name) == ("A", "B")
    with pytest.raises(ConfigError, match="two different epochs"):
        pick_epochs(m, "A", "A")


@pytest.mark.slow
def test_run_on_a_tiny_scene(tmp_path):
    import pyogrio
    import rasterio

    from geocd.synth.generate import SynthParams, generate

    scene = tmp_path / "scene"
    generate(SynthParams.tiny(seed=3, n_sat_a=3), scene)  # 3 satellite views: 3 pair-DEMs to learn from
    res = run(scene, out_dir=tmp_path / "out")
    out = res["outputs"]
    for k in ("change", "change_mask"):
        with rasterio.open(out[k]) as ds:
            assert ds.crs is not None and ds.width > 50
    assert {"changes", "buildings", "curves", "layer_styles"} <= {n for n, _ in pyogrio.list_layers(out["changes"])}
    cfg = RunConfig.load(out["config"])
    assert cfg.to_dict()["region_confidence"] == 99.0
    s = json.loads(out["summary"].read_text())
    assert s["epoch_a"] == "A" and s["model"]["learned_here"]


@pytest.mark.slow
@pytest.mark.realdata
def test_sample_aoi_end_to_end(tmp_path, sample_aoi):
    """issue 5's targets on the committed sample: building F1 ≥ 0.9 at 99%, false alarms ≲ 1% of static cells."""
    from shapely.geometry import box

    from geocd.change.buildings import score_buildings
    from geocd.change.metrics import binary_scores
    from geocd.io.raster import read_on_grid
    from geocd.io.vector import read_footprints

    res = run(sample_aoi, out_dir=tmp_path / "out")
    grid = res["grid"]
    truth = read_on_grid(sample_aoi / "truth" / "change_mask.tif", grid) > 0.5
    r = res["result"]
    s = binary_scores(r.changed_at(99) != 0, truth, r.observed)
    assert s["false_alarm_rate"] < 0.015, s
    assert s["recall"] > 0.45, s
    b = res["buildings"]  # epoch-A footprints (the manifest's) + new buildings detected in the change map
    assert set(b.loc[b["source"] == "footprint", "building_id"]) == set(
        read_footprints(sample_aoi / "truth" / "footprints_A.gpkg")["building_id"])
    fps = read_footprints(sample_aoi / "truth" / "footprints_all.gpkg", crs=grid.crs)
    sb = score_buildings(b, fps, aoi=box(*grid.bounds))
    assert sb["f1"] >= 0.9, sb
