"""The octree under a turned sun on a generated 300 m town (docs/volume.md, "Shadows cast from a DSM").

The town is generated in the fixture (seed 11, suns 81° of azimuth apart); its own file so that pytest-xdist
runs it beside the 120 m town of test_town_volume.py."""

from __future__ import annotations

import pytest

# subarea_aucs_by_shadow trains on epoch A but its holdout A_sat3 and scores the epoch-B satellite views
TRAINED = ["A_sat1", "A_sat2", "A_sat4", "A_air1", "A_air2", "A_air3"]
SCORED = ["B_sat1", "B_sat2", "B_sat3"]


@pytest.fixture(scope="module")
def town_sun_turned(tmp_path_factory):
    """A 300 m town under suns 81° of azimuth apart (136°/47° on A, 217°/48° on B): ``geocd synth --params``
    with seed 11 and these dates (docs/volume.md, "Shadows cast from a DSM")."""
    from geocd.synth.generate import SynthParams, generate

    out = tmp_path_factory.mktemp("volume_town_sun") / "town_seed11"
    # the views the evaluation reads (its holdout A_sat3 is never read), each the image a full run writes, and the
    # change masks of the scored epoch-B views only
    generate(
        SynthParams(seed=11, date_a="2023-04-12T10:00:00", date_b="2024-09-03T13:30:00"),
        out,
        only_views=TRAINED + SCORED,
        mask_views=SCORED,
    )
    return out


@pytest.mark.slow
def test_shadows_cast_from_a_dsm_lift_the_octree_under_a_turned_sun(town_sun_turned):
    """On a 120 m sub-area (B_sat1-3 pooled, 187,683 pixels, 2.7 % changed), measured: with the shadows of the
    model's own density plain eq. 27 0.759 / 3x3 0.772; with the shadows cast from epoch A's DSM (the truth DSM
    here, so that the test needs no stereo; geocd stereo's gives 0.798 / 0.810, docs/volume.md)
    0.798 / 0.809; Carlotto 0.822, DEM warp 0.607. Pinned at +-0.01, and the DSM's gain at >= 0.025 on both."""
    from geocd.volume.evaluate import subarea_aucs_by_shadow

    bounds = (374290.0, 4824254.0, 374410.0, 4824374.0)
    # one model (training does not depend on the shadow DSM), detected with both shadows
    own, dsm = subarea_aucs_by_shadow(
        str(town_sun_turned),
        bounds,
        [None, str(town_sun_turned / "truth" / "dsm_A.tif")],
        log=lambda *a, **k: None,
    )
    assert own["n_pixels"] > 150_000 and 0.02 < own["changed_fraction"] < 0.04, own
    assert own["3-D octree (relit)"] == pytest.approx(0.759, abs=0.01), own
    assert own["3-D octree 3×3 (relit)"] == pytest.approx(0.772, abs=0.01), own
    assert dsm["3-D octree (relit)"] == pytest.approx(0.798, abs=0.01), dsm
    assert dsm["3-D octree 3×3 (relit)"] == pytest.approx(0.809, abs=0.01), dsm
    assert dsm["2-D Carlotto joint histogram"] == pytest.approx(0.822, abs=0.01), dsm
    for k in ("3-D octree (relit)", "3-D octree 3×3 (relit)"):
        assert dsm[k] - own[k] >= 0.025, (k, own, dsm)
