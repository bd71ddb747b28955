"""The check behind sample_aoi's Table 2 rows through `geocd mpp`'s own pipeline (orthos and stereo DSMs made by
it; docs/mpp.md, "The DSM's surface median"), one row per test file: test_sample_aoi.py (the default DSMs, each
cell's own match) and test_sample_aoi_window.py (geocd stereo's product DSM, a median over the matching window)."""

from __future__ import annotations

import warnings

import geopandas as gpd
import pytest

from geocd.mpp.evaluate import rect_masks, sample_truth, table2
from geocd.mpp.pipeline import dsm_smoothing, run_mpp_manifest
from geocd.stereo.params import StereoParams, change_stereo_params


def check_table2(sample_aoi, tmp_path, stereo, want, want_drop, pair_dems=None):
    """``want``: the scoring with the five buildings the border cuts in the truth masks (the default);
    ``want_drop``: with them left out, the scoring of the earlier figures. ``pair_dems``: the epochs' pair-DEMs
    of geocd mpp's default stereo, made earlier (tests/sample_aoi_cache.py), instead of matching here."""
    sp = None if stereo is None else StereoParams()  # StereoParams(): surface median over the matching window
    if pair_dems is not None:
        # the very pair-DEMs geocd mpp's default stereo makes: its parameters (run_ortho checks the grid)
        assert stereo is None
        assert all(
            StereoParams.from_dict(p.meta["params"]) == change_stereo_params() for v in pair_dems.values() for p in v
        )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        r = run_mpp_manifest(sample_aoi, out_dir=tmp_path / "mpp", stereo_params=sp, pair_dems=pair_dems)
    det, grid = r["detection"], r["grid"]
    assert r["params"].height == "and" and r["params"].edge_fit == "joint" and r["params"].seed == 0
    footprints = gpd.read_file(sample_aoi / "truth" / "footprints_all.gpkg")
    masks = rect_masks(det.result.rects, det.result.xi, grid.shape)
    objs, t1, t2 = sample_truth(footprints, grid)
    t = table2(masks, objs, t1, t2)
    assert (t["objects"], t["changes"]) == (30, 5)
    assert sum(not o["scored"] for o in objs) == 5
    assert t["DP"] == pytest.approx(want["DP"], abs=0.01), t
    assert t["DP_precision"] == pytest.approx(want["DP_precision"], abs=0.01), t
    for k in ("HO", "FO", "HV", "FV"):
        assert abs(t[k] - want[k]) <= 2, (k, t)
    objs_d, d1, d2 = sample_truth(footprints, grid, cut_buildings="drop")
    td = table2(masks, objs_d, d1, d2)
    assert td["DP"] == pytest.approx(want_drop["DP"], abs=0.01), td
    assert abs(td["FO"] - want_drop["FO"]) <= 2, td
    # a pinned gap between the two scorings: a detection on a cut building is not false pixels
    assert t["DP_precision"] - td["DP_precision"] == pytest.approx(want["DP_precision_gain"], abs=0.005), (t, td)
    assert (tmp_path / "mpp" / "mpp" / "mpp_buildings.gpkg").is_file()
    # the DSMs say which surface median made them (what geocd mpp --dsm-a/--dsm-b warns about)
    assert dsm_smoothing(tmp_path / "mpp" / "ortho" / "A" / "dsm_A.tif") == (1 if stereo is None else 7)
    # the terrain geocd ortho put into the stereo's holes on roofs is given back to the roofs
    assert any("inside raised surfaces" in n for n in det.notes), det.notes
