"""The octree model against its 2-D baselines on a sub-area of sample_aoi (a reduced docs/volume.md evaluation)."""

from __future__ import annotations

import pytest

# 120 m x 120 m at the south edge of the AOI (AOI CRS, EPSG:32631)
BOUNDS = (374290.0, 4824254.0, 374410.0, 4824374.0)


@pytest.mark.slow
def test_octree_per_pixel_aucs_on_a_sample_aoi_subarea(sample_aoi):
    """Figures measured on this sub-area (5 passes, A_sat3 held out, B_sat1-3 pooled, seed 0, the DEM prior's
    band ending at the DEM, roof heights from the epoch-A footprints): plain eq. 27 0.864, default 3x3 0.885,
    DEM warp + difference 0.888, Carlotto 0.849 (with the bare-ground prior under the roofs: 0.850, 0.888,
    0.881, 0.844 on slightly other pixels; with the band reaching 1 m above the DEM: 0.841, 0.886, 0.882, 0.845).

    Pins the per-pixel AUCs (a mutation of the detection default, the relighting, the roof prior or the
    baselines moves them by more than the tolerance) and that the plain eq. 27 now beats Carlotto here; the DEM
    warp is level with the 3x3 on this sub-area (it is not on the whole AOI, docs/volume.md).
    """
    from geocd.volume.evaluate import subarea_aucs

    r = subarea_aucs(str(sample_aoi), BOUNDS, log=lambda *a, **k: None)
    plain, nxn = r["3-D octree (relit)"], r["3-D octree 3×3 (relit)"]
    carlotto, warp = r["2-D Carlotto joint histogram"], r["2-D DEM warp + difference"]
    assert r["n_pixels"] > 150_000 and 0.02 < r["changed_fraction"] < 0.06, r
    assert plain == pytest.approx(0.864, abs=0.007), r
    assert nxn == pytest.approx(0.885, abs=0.007), r
    assert carlotto == pytest.approx(0.849, abs=0.007), r
    assert warp == pytest.approx(0.888, abs=0.007), r
    assert plain > carlotto + 0.01 and nxn > plain + 0.015 and nxn > carlotto + 0.03, r
