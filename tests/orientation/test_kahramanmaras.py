"""Real two-epoch Pléiades case: the cross-epoch residuals the relative orientation reaches (docs/kahramanmaras.md)."""

import warnings

import pytest

from geocd.io.manifest import load_manifest
from geocd.orientation import orient_manifest
from tests.conftest import REPO, shared_data

pytestmark = [pytest.mark.realdata, pytest.mark.slow]


def test_cross_epoch_residuals_before_and_after(tmp_path):
    shared_data("cnes_picanteo_kahramanmaras", "post_event_img2.geom")
    m = load_manifest(REPO / "examples" / "kahramanmaras" / "scene.yaml")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no OrientationWarning: the correction is applied
        m2, rep = orient_manifest(m, out_dir=tmp_path)
    assert rep["applied"] and rep["status"] == "applied"
    # measured: before median 0.59 px / RMS 0.72; after 0.23 / 0.34; held out 0.23 / 0.34 (1714 observations)
    assert rep["before"]["cross_epoch"]["median_px"] > 0.45
    assert rep["after"]["cross_epoch"]["median_px"] < 0.30
    assert rep["after"]["cross_epoch"]["rms_px"] < 0.45
    assert rep["held_out"]["cross_epoch"]["median_px"] < 0.30
    assert rep["after"]["cross_epoch"]["n"] > 1000
    assert 0.5 < rep["largest_correction_px"] < 1.5
    # every image gets its corrected camera, and the oriented manifest is written for later commands
    for e in m2.epochs:
        for im in e.images:
            assert im.camera is not None and im.camera.name.endswith(".camera.json")
    assert (tmp_path / "orientation" / "scene.oriented.yaml").is_file()
    load_manifest(tmp_path / "orientation" / "scene.oriented.yaml")


def test_epochs_that_do_not_overlap_are_a_clear_error(tmp_path):
    """Pre-event images of Kahramanmaraş against Réunion as the 'after' epoch: NoOverlapError before any stereo."""
    import yaml

    from geocd.errors import NoOverlapError
    from geocd.pipeline import run

    d = shared_data("cnes_picanteo_kahramanmaras")
    reu = shared_data("s2p_pleiades", "input_pair")
    doc = {
        "geocd_manifest": 1,
        "epochs": [
            {"name": "pre", "images": [str(d / "pre_event_img1.tif"), str(d / "pre_event_img2.tif")]},
            {"name": "post", "images": [str(reu / "img_01.tif"), str(reu / "img_02.tif")]},
        ],
    }
    p = tmp_path / "scene.yaml"
    p.write_text(yaml.safe_dump(doc))
    with pytest.raises(NoOverlapError, match="do not overlap on the ground"):
        run(p, out_dir=tmp_path / "out")
