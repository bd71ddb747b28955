"""Real before/after: the whole example run on the Kahramanmaraş Pléiades pairs (docs/kahramanmaras.md)."""

import json

import geopandas as gpd
import numpy as np
import pytest

from tests.conftest import REPO, shared_data

pytestmark = [pytest.mark.realdata, pytest.mark.slow]


@pytest.fixture(scope="module")
def kahra_run(tmp_path_factory):
    shared_data("cnes_picanteo_kahramanmaras", "post_event_img2.tif")
    from geocd.pipeline import RunConfig, run

    ex = REPO / "examples" / "kahramanmaras"
    out = tmp_path_factory.mktemp("kahra")
    res = run(ex / "scene.yaml", out_dir=out, config=RunConfig(model_path=str(ex / "marseille_urban_model.json")))
    return out, res


def test_layers_and_orientation(kahra_run):
    out, res = kahra_run
    s = json.loads((out / "run_summary.json").read_text())
    assert s["orientation"]["applied"] is True
    assert s["orientation"]["after"]["cross_epoch"]["median_px"] < 0.3
    for name in ("sc_change.tif", "sc_change_mask.tif", "sc_changes.gpkg", "sc_ground_model.tif",
                 "orientation/orientation.json", "orientation/scene.oriented.yaml"):
        assert (out / name).exists(), name
    dmg = gpd.read_file(out / "sc_changes.gpkg", layer="building_damage")
    assert {"class", "confidence_pct", "height_before_m", "height_after_m", "volume_lost_m3",
            "volume_sigma_m3"} <= set(dmg.columns)
    assert set(dmg["confidence_pct"].unique()) <= {0.0, 90.0, 95.0, 99.0}


def test_headline_figures(kahra_run):
    """Measured: 194 objects, 18 collapsed, 15 partly collapsed; 13.8 % of observed cells flagged at 99 % (90 %:
    14.9 %), 9.7 % of the cells outside changed buildings (90 %: 10.8 %) — the transfer shortfall of the
    Marseille model, reported."""
    out, res = kahra_run
    from geocd.change.dsm_buildings import stable_false_alarms

    dmg = gpd.read_file(out / "sc_changes.gpkg", layer="building_damage")
    cls = dmg["class"].value_counts()
    assert 150 <= len(dmg) <= 240
    assert 12 <= cls.get("collapsed", 0) <= 24
    collapsed = dmg[dmg["class"] == "collapsed"]
    assert (collapsed["height_after_m"] < collapsed["height_before_m"]).all()
    assert (collapsed["confidence_pct"] == 99.0).all()
    r = res["result"]
    flagged = float((r.changed_at(99.0) != 0)[r.observed].mean())
    assert 0.130 < flagged < 0.1455        # 90 % map: 0.149
    fa = stable_false_alarms(r.confidence, r.observed, dmg, res["grid"])
    assert 0.090 < fa["99"] < 0.104        # 90 %: 0.108
    assert fa["90"] > fa["99"]
