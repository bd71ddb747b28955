"""Stereo tile by tile on sample_aoi: the same accuracy as the untiled match (stated tolerance)."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from geocd.demdiff.tiled import TilingParams
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
    ep["images"] = [dict(i, path=str(sample_aoi / i["path"])) for i in ep["images"] if i["name"] in ("B_sat1", "B_sat3")]
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
    from geocd.stereo.pipeline import default_aoi_grid, load_epoch_images

    m = load_manifest(sample_aoi / "scene.yaml")
    ims = load_epoch_images(m, m.epoch("B"))
    g = default_aoi_grid(m, {"B": ims}, dem_median=200.0)
    cams = [ims[0].camera, ims[2].camera]
    m1 = stereo_margin_cells(g, cams, 190.0, 230.0, StereoParams())
    m2 = stereo_margin_cells(g, cams, 190.0, 290.0, StereoParams())
    m3 = stereo_margin_cells(g, cams, 190.0, 230.0, StereoParams(window=11))
    assert m2 > m1 and m3 > m1 and m1 > StereoParams().radius
