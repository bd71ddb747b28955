"""Stereo tile by tile on sample_aoi: the same accuracy as the untiled match (stated tolerance)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import rasterio
import yaml

from geocd.tiling.params import TilingParams
from geocd.io.raster import read_dem
from geocd.stereo.pipeline import run_stereo
from geocd.stereo.products import read_pair_dem
from geocd.stereo.tiled import run_stereo_tiled, stereo_margin_cells


def _one_pair_manifest(sample_aoi, tmp_path):
    m = yaml.safe_load((sample_aoi / "scene.yaml").read_text())
    for k in ("dem", "footprints"):
        if isinstance(m.get(k), dict):
            m[k]["path"] = str(sample_aoi / m[k]["path"])
        elif m.get(k):
            m[k] = str(sample_aoi / m[k])
    m.pop("truth", None)
    ep = [e for e in m["epochs"] if e["name"] == "B"][0]
    ep["images"] = [
        dict(i, path=str(sample_aoi / i["path"])) for i in ep["images"] if i["name"] in ("B_sat1", "B_sat3")
    ]
    m["epochs"] = [ep]
    p = tmp_path / "scene.yaml"
    p.write_text(yaml.safe_dump(m))
    return p


@pytest.mark.slow
def test_stereo_tiled_matches_untiled_accuracy(sample_aoi, tmp_path):
    man = _one_pair_manifest(sample_aoi, tmp_path)
    u = run_stereo(man, out_dir=tmp_path / "u")["outputs"]["B/B_sat1__B_sat3"]
    r = run_stereo_tiled(man, out_dir=tmp_path / "t", tiling=TilingParams(tile_size=256, scheduler="sync"))
    t = r["outputs"]["B/B_sat1__B_sat3"]
    assert 40 <= r["margins"]["B/B_sat1__B_sat3"] <= 128
    a, b = read_pair_dem(u), read_pair_dem(t)
    assert b.grid.same_as(a.grid) and b.name == a.name and b.epoch == "B"
    truth = read_dem(sample_aoi / "truth" / "dsm_B.tif", grid=a.grid).height_m
    err = {}
    for k, p in (("u", a), ("t", b)):
        d = (p.z_m - truth)[p.valid & np.isfinite(truth)]
        err[k] = (float(p.valid.mean()), float(np.median(np.abs(d))), float(np.mean(np.abs(d) > 1.0)))
    # measured: completeness 0.9281 vs 0.9279, median |dz| 0.065 vs 0.065 m, > 1 m 5.28 % vs 5.32 %
    assert abs(err["t"][0] - err["u"][0]) < 0.005
    assert abs(err["t"][1] - err["u"][1]) < 0.01
    assert abs(err["t"][2] - err["u"][2]) < 0.005
    both = a.valid & b.valid
    assert np.mean(np.abs(a.z_m - b.z_m)[both] < 0.1) > 0.95


def test_stereo_margin_grows_with_height_range_and_window(sample_aoi):
    from geocd.io.manifest import load_manifest
    from geocd.stereo.params import StereoParams
    from geocd.stereo.scene import default_aoi_grid, load_epoch_images

    m = load_manifest(sample_aoi / "scene.yaml")
    ims = load_epoch_images(m, m.epoch("B"))
    g = default_aoi_grid(m, {"B": ims}, dem_median=200.0)
    cams = [ims[0].camera, ims[2].camera]
    m1 = stereo_margin_cells(g, cams, 190.0, 230.0, StereoParams())
    m2 = stereo_margin_cells(g, cams, 190.0, 290.0, StereoParams())
    m3 = stereo_margin_cells(g, cams, 190.0, 230.0, StereoParams(window=11))
    assert m2 > m1 and m3 > m1 and m1 > StereoParams().radius


@pytest.mark.slow
def test_a_finished_pairs_tiles_go_at_once_and_a_resumed_run_reuses_its_dem(tmp_path):
    """Two pairs (one per epoch) of a tiny generated scene: the run is cancelled half way through the second
    pair. The first pair's DEM is written and its tiles are gone already (not kept until the stage ends);
    the same call again matches only the second pair's remaining tiles, and gives the uninterrupted run's
    products."""
    from geocd.errors import CancelledError
    from geocd.synth.bigstereo import StereoSceneParams, make_stereo_scene
    from geocd.tiling import WORK_DIR

    scene = tmp_path / "scene"
    make_stereo_scene(scene, StereoSceneParams(cells=128, seed=2), block=160, workers=1)
    man = scene / "scene.yaml"
    tiling = TilingParams(tile_size=64, scheduler="sync")
    ref = run_stereo_tiled(man, out_dir=tmp_path / "ref", tiling=tiling)
    assert sorted(ref["outputs"]) == ["A/A_sat1__A_sat2", "B/B_sat1__B_sat2"]
    assert not (tmp_path / "ref" / WORK_DIR).exists()

    out = tmp_path / "run"
    seen = []

    def cancel_in_pair_2(fraction, message=""):
        seen.append(message)
        if message.startswith("pair 2/2 stereo-B") and message.endswith(" 2/4 tiles"):
            work = out / WORK_DIR
            # pair 1's DEM is written, its tile store is gone; pair 2's tiles are journalled
            assert (out / "stereo" / "A" / "A_sat1__A_sat2.tif").exists()
            assert not list(work.glob("stereo-A-*")) and len(list(work.glob("stereo-B-*/*.done.pkl"))) == 2
            raise CancelledError("stop")

    with pytest.raises(CancelledError):
        run_stereo_tiled(man, out_dir=out, tiling=tiling, progress=cancel_in_pair_2)
    assert not (out / "stereo" / "B" / "B_sat1__B_sat2.tif").exists()
    seen.clear()
    res = run_stereo_tiled(man, out_dir=out, tiling=tiling, progress=lambda f, m="": seen.append(m))
    assert any(m.startswith("pair 1/2 resumed") for m in seen)
    assert not any(m.startswith("pair 1/2 stereo-A") for m in seen)  # pair 1 not matched again
    assert any("(2 resumed)" in m for m in seen if m.startswith("pair 2/2"))
    assert res["completeness"] == pytest.approx(ref["completeness"], abs=0)
    for k in ref["outputs"]:
        a, b = read_pair_dem(ref["outputs"][k]), read_pair_dem(res["outputs"][k])
        np.testing.assert_array_equal(a.z_m, b.z_m)
        np.testing.assert_array_equal(a.valid, b.valid)
        np.testing.assert_array_equal(a.score, b.score)
    assert not (out / WORK_DIR).exists()
    # a finished run leaves no journal: the same command again matches anew (nothing silently reused)
    seen.clear()
    run_stereo_tiled(man, out_dir=out, tiling=tiling, progress=lambda f, m="": seen.append(m))
    assert not any("resumed" in m for m in seen)


@pytest.mark.slow
def test_geocd_stereo_tiled_is_the_tiled_run(tmp_path):
    """`geocd stereo --tiled` is the door to :func:`run_stereo_tiled`: the same pair-DEMs, bit for bit; its
    --tile-size is the Dask tile; --no-overwrite (an untiled option) is refused with the reason."""
    from click.testing import CliRunner

    from geocd.cli import main
    from geocd.synth.bigstereo import StereoSceneParams, make_stereo_scene

    scene = tmp_path / "scene"
    make_stereo_scene(scene, StereoSceneParams(cells=128, seed=3), block=160, workers=1)
    man = scene / "scene.yaml"
    ref = run_stereo_tiled(man, out_dir=tmp_path / "ref", tiling=TilingParams(tile_size=64, scheduler="sync"))
    out = tmp_path / "cli"
    r = CliRunner().invoke(
        main,
        [
            "--progress",
            "none",
            "stereo",
            str(man),
            "--tiled",
            "--scheduler",
            "sync",
            "--tile-size",
            "64",
            "--out",
            str(out),
        ],
    )
    assert r.exit_code == 0, r.output
    assert "tiled stereo: margins" in r.output
    for k, p in ref["outputs"].items():
        a, b = read_pair_dem(p), read_pair_dem(out / "stereo" / f"{k}.tif")
        np.testing.assert_array_equal(a.z_m, b.z_m)
        np.testing.assert_array_equal(a.valid, b.valid)
        with rasterio.open(out / "stereo" / f"{k}.tif") as ds:
            assert json.loads(ds.tags()["meta"])["tiled"]["tile_size"] == 64
    r = CliRunner().invoke(main, ["stereo", str(man), "--tiled", "--no-overwrite", "--out", str(tmp_path / "x")])
    assert r.exit_code != 0 and "--no-overwrite is for untiled runs" in r.output
