"""sample_aoi's Table 2 row through `geocd mpp`'s own pipeline (orthos and stereo DSMs made by it): docs/mpp.md,
"The DSM's surface median". Both DSMs are pinned: the default (each cell's own match, surface median 1) and geocd
stereo's product DSM (a median over the matching window), whose difference is the largest effect on these
figures measured so far."""

from __future__ import annotations

import warnings

import geopandas as gpd
import pytest

from geocd.mpp.evaluate import rect_masks, sample_truth, table2
from geocd.mpp.pipeline import dsm_smoothing, run_mpp_manifest
from geocd.stereo.params import StereoParams


@pytest.mark.slow
@pytest.mark.parametrize("stereo, want", [
    (None, {"DP": 0.820, "HO": 3, "FO": 9, "HV": 2, "FV": 12}),            # geocd mpp's default: no surface median
    ("window", {"DP": 0.686, "HO": 11, "FO": 3, "HV": 3, "FV": 4}),        # geocd stereo's product DSM
], ids=["default", "window-median"])
def test_sample_aoi_table2_through_geocd_mpp(sample_aoi, tmp_path, stereo, want):
    sp = None if stereo is None else StereoParams()   # StereoParams(): surface median over the matching window
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        r = run_mpp_manifest(sample_aoi, out_dir=tmp_path / "mpp", stereo_params=sp)
    det, grid = r["detection"], r["grid"]
    assert r["params"].height == "and" and r["params"].edge_fit == "joint" and r["params"].seed == 0
    objs, t1, t2 = sample_truth(gpd.read_file(sample_aoi / "truth" / "footprints_all.gpkg"), grid)
    t = table2(rect_masks(det.result.rects, det.result.xi, grid.shape), objs, t1, t2)
    assert (t["objects"], t["changes"]) == (30, 5)
    assert t["DP"] == pytest.approx(want["DP"], abs=0.015), t
    for k in ("HO", "FO", "HV", "FV"):
        assert abs(t[k] - want[k]) <= 2, (k, t)
    assert (tmp_path / "mpp" / "mpp" / "mpp_buildings.gpkg").is_file()
    # the DSMs say which surface median made them (what geocd mpp --dsm-a/--dsm-b warns about)
    assert dsm_smoothing(tmp_path / "mpp" / "ortho" / "A" / "dsm_A.tif") == (1 if stereo is None else 7)
