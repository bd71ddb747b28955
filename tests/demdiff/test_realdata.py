"""Real-data checks: Mount St Helens (USGS OFR 2008-1169) and the demcompare known shift."""

import numpy as np
import pytest

from geocd.demdiff import DEMDiffParams, dem_difference, nuth_kaab, survey_footprint, metric_posting
from geocd.io.raster import read_dem

from ..conftest import shared_data

pytestmark = pytest.mark.realdata


def _msh(a, b):
    from geocd.io.e00 import read_e00_dem

    base = read_e00_dem(shared_data("usgs_msh_dome_dems", "raw_e00", "1_msh00_83.e00"))
    da = read_dem(shared_data("usgs_msh_dome_dems", "geotiff_utm10n", f"{a}.tif"))
    db = read_dem(shared_data("usgs_msh_dome_dems", "geotiff_utm10n", f"{b}.tif"))
    obs = survey_footprint(da.height_m, base.height_m) & survey_footprint(db.height_m, base.height_m)
    return da, db, obs


def test_msh_26_27():
    da, db, obs = _msh(26, 27)
    assert obs.sum() == 22251
    # the headline of docs/demdiff.md compares with xDEM on the same changed cells: region test off
    r = dem_difference(da, db, observed=obs, epoch_a="26", epoch_b="27", params=DEMDiffParams(region_test="off"))
    s = r.summary
    assert r.status == "ok"
    # the Nuth–Kääb fit is well constrained and agrees with xDEM 0.2.3 given geocd's stable mask ((+0.78, +1.54,
    # +3.55) m, bench/bench_demdiff.py) within 2σ, but moving B does not lower the stable NMAD: not applied
    e, n, z = r.coreg.fitted_shift_m
    se, sn, sz = r.coreg.shift_sigma_m
    assert abs(e - 0.78) < 2 * se and abs(n - 1.54) < 2 * sn and abs(z - 3.55) < 3 * sz + 0.2
    assert r.coreg.status == "not_improving" and r.coreg.applied == "vertical"
    assert abs(s.get("fitted_shift_volume_effect_sigma", 0.0)) < 1.0
    assert 2.0 < s["stable_nmad_m"] < 3.5
    assert 0.15e6 < s["changed_area_m2"] < 0.6e6
    assert s["volume_changed_m3"] > 0 and 0.05e6 < s["volume_changed_sigma_m3"] < 0.6e6
    # the headline of docs/demdiff.md: +1.889 ± 0.249 Mm³ (a tenth of its own σ as the tolerance)
    assert s["volume_changed_m3"] == pytest.approx(1.889e6, abs=0.025e6)
    assert s["volume_changed_sigma_m3"] == pytest.approx(0.249e6, abs=0.01e6)
    assert s["stable_nmad_m"] == pytest.approx(2.415, abs=0.05)
    # dome growth: the largest raised region has tens of metres of change
    up = r.regions[r.regions.sign == 1]
    assert up.max_dz_m.max() > 20
    # the default region test (noise null from the fitted variogram) drops 59 of the 69 regions
    # (500 of 3,889 cells, mostly lowered noise): +1.994 ± 0.237 Mm³ (+0.42σ), 10 regions
    d = dem_difference(da, db, observed=obs, epoch_a="26", epoch_b="27")
    rt = d.summary["region_test"]
    assert rt["regions_tested"] == 69 and rt["regions_dropped"] == 59 and len(d.regions) == 10
    assert d.summary["volume_changed_m3"] == pytest.approx(1.994e6, abs=0.025e6)
    assert d.summary["volume_changed_sigma_m3"] == pytest.approx(0.237e6, abs=0.01e6)
    assert d.regions.max_dz_m.max() == up.max_dz_m.max()


def test_msh_2_27_no_stable_terrain_and_underconstrained_mask():
    da, db, obs = _msh(2, 27)
    r = dem_difference(da, db, observed=obs)
    assert r.status == "no_stable_terrain" and r.coreg.shift_m == (0.0, 0.0, 0.0)
    # the README's whole-process row (`geocd demdiff 2.tif 27.tif --base …`): net +20.551 Mm³ over the common area
    assert r.summary["volume_net_observed_m3"] == pytest.approx(20.551e6, abs=0.05e6)
    # a user mask of the 93 cells with |dh| < 5 m: xDEM's Nuth–Kääb fits 79 of them and applies the shift;
    # geocd reports the fit as under-constrained and does not move the DEM horizontally
    dh = db.height_m.astype(float) - da.height_m
    st = obs & (np.abs(dh) < 5)
    assert st.sum() == 93
    r2 = dem_difference(da, db, observed=obs, stable_mask=st)
    assert r2.coreg.status == "underconstrained" and r2.coreg.applied == "vertical"
    assert r2.status == "uncertainty_indicative"
    assert r2.summary["volume_net_observed_m3"] > 15e6


def test_demcompare_known_shift():
    ref = read_dem(shared_data("cnes_demcompare_srtm", "srtm_ref.tif"))
    sec = read_dem(shared_data("cnes_demcompare_srtm", "srtm_blurred_and_shifted.tif"))
    from geocd.demdiff import align_dems

    pair = align_dems(ref, sec)
    post = metric_posting(pair.grid)
    st = pair.valid
    _, c = nuth_kaab(pair.height_a_m, pair.height_b_m, st, post)
    px = c.shift_px
    # demcompare's reference output: offsets 3 px (x) and 5 px (y), i.e. the secondary DEM's origin moves
    # 3 px east and 5 px south (gdal_translate bounds ulx 40.0025, uly 39.99583)
    assert c.status == "ok"
    assert abs(px[0] - 3.0) < 0.2 and abs(px[1] + 5.0) < 0.2
    # after alignment the two DEMs agree to a few metres (the blur remains)
    assert c.nmad_after_m < 5.0 < c.nmad_before_m
