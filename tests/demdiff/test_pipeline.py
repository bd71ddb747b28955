import datetime as dt

import numpy as np
import pytest
from affine import Affine

from geocd.demdiff import DEMDiffParams, Epoch, align_dems, dem_difference, dem_time_series, survey_footprint
from geocd.errors import EmptyDataError, NoOverlapError, VerticalDatumError
from geocd.geodesy import AOIGrid
from geocd.io.raster import DEM

from .synthetic import grid, pair


@pytest.mark.slow
def test_known_shift_and_volume_recovered():
    a, b, info = pair((7.0, -4.0, 1.5), noise_m=0.4, bump_m=30.0, bump_radius_px=14)
    r = dem_difference(a, b, epoch_a="A", epoch_b="B")
    assert r.status == "ok" and r.coreg.status == "ok"
    np.testing.assert_allclose(r.coreg.shift_m, (-7.0, 4.0, -1.5), atol=0.4)
    s = r.summary
    v, sv = s["volume_changed_m3"], s["volume_changed_sigma_m3"]
    assert sv > 0
    # the changed cells hold the bump (its flat fringe below noise is missed): within 3σ + 3% of truth
    assert abs(v - info["volume_m3"]) < 3 * sv + 0.03 * info["volume_m3"], (v, sv, info["volume_m3"])
    assert s["stable_nmad_m"] < 1.0
    # one raised region over the bump, with the shared schema
    reg = r.regions
    assert list(reg.columns[:12]) == [
        "region_id",
        "method",
        "epoch_a",
        "epoch_b",
        "sign",
        "n_cells",
        "area_m2",
        "mean_dz_m",
        "max_dz_m",
        "volume_m3",
        "volume_sigma_m3",
        "confidence",
    ]
    big = reg.sort_values("n_cells").iloc[-1]
    assert big["sign"] == 1 and big["confidence"] > 0.99 and big["max_dz_m"] > 25
    assert r.changed[info["bump"]].mean() > 0.7


@pytest.mark.slow
def test_null_pair_has_few_false_changes():
    a, b, _ = pair((3.0, 3.0, 0.0), noise_m=0.5, seed=7)
    r = dem_difference(a, b, params=DEMDiffParams(confidence=99.0, min_region_cells=4))
    # white noise: at 99% ~1% of cells pass, 4-cell 8-connected clusters of them are rare
    assert r.changed.mean() < 0.005
    assert r.summary["stable_nmad_m"] == pytest.approx(0.5 * np.sqrt(2), rel=0.3)


def test_dems_that_do_not_overlap():
    a, _, _ = pair()
    g2 = grid(x0=700000.0)
    b = DEM(a.height_m.copy(), g2, None, "far")
    with pytest.raises(NoOverlapError, match="do not overlap"):
        dem_difference(a, b)


def test_unknown_vs_declared_vertical_datum():
    a, b, _ = pair()
    b.vertical_datum = "egm96"
    with pytest.raises(VerticalDatumError, match="will not guess"):
        dem_difference(a, b)


def test_missing_geoid_grid_is_a_clear_error(monkeypatch):
    import geocd.geodesy as geo

    a, b, _ = pair()
    a.vertical_datum = "ellipsoid"
    b.vertical_datum = "egm2008"
    monkeypatch.setattr(geo, "find_geoid_grid", lambda model: None)
    with pytest.raises(VerticalDatumError, match="geoid grid"):
        dem_difference(a, b)


def test_datums_converted_when_the_grid_exists():
    import geocd.geodesy as geo

    if geo.find_geoid_grid("egm96") is None:
        pytest.skip("EGM96 grid not installed")
    a, b, _ = pair(noise_m=0.0)
    b.vertical_datum = "egm96"
    a.vertical_datum = "ellipsoid"
    pair_ = align_dems(a, b)
    lon, lat = a.grid.lonlat()
    n = geo.geoid_undulation(lon, lat, "egm96")
    np.testing.assert_allclose(pair_.height_b_m - b.height_m, n, atol=1e-3)
    assert pair_.vertical_datum == "ellipsoid" and pair_.notes


def test_no_stable_terrain_is_reported_not_invented():
    a, _, _ = pair()
    g = a.grid
    rr = np.mgrid[0 : g.height, 0 : g.width][0]
    b = DEM((a.height_m + 2.0 * rr).astype(np.float32), g, None, "B")  # everything changed, smoothly
    r = dem_difference(a, b)
    assert r.status == "no_stable_terrain"
    assert r.coreg.shift_m == (0.0, 0.0, 0.0)
    assert np.isnan(r.summary["volume_changed_sigma_m3"]) and len(r.regions) == 0
    assert any("no stable terrain" in n or "no usable stable terrain" in n for n in r.notes)


def test_user_mask_with_no_valid_cells_is_an_error():
    a, b, _ = pair()
    b.height_m[:, :40] = np.nan
    m = np.zeros(a.grid.shape, bool)
    m[:, :30] = True
    with pytest.raises(EmptyDataError):
        dem_difference(a, b, stable_mask=m)


def test_geographic_grid_uses_metric_posting():
    g = AOIGrid("EPSG:4326", Affine(1 / 1200, 0, 40.0, 0, -1 / 1200, 40.0), 150, 150)
    a, b, _ = pair((0.0, 0.0, 0.0), g=g, noise_m=0.3)
    # terrain() is in map units (degrees here): rebuild metric-looking relief
    x, y = g.xy()
    za = 1000 + 300 * np.sin(x * 300) * np.cos(y * 250)
    a = DEM(za.astype(np.float32), g)
    zb = np.roll(za, 2, axis=1)  # B = A moved 2 px east
    b = DEM(zb.astype(np.float32), g)
    r = dem_difference(a, b)
    px = r.coreg.shift_px
    assert px[0] == pytest.approx(-2.0, abs=0.1) and abs(px[1]) < 0.1
    assert 60 < r.posting_xy_m[0] < 80 and 90 < r.posting_xy_m[1] < 95


@pytest.mark.slow
def test_time_series_over_common_survey_areas():
    g = grid(100, 100)
    base, _, _ = pair(g=g, noise_m=0.0)
    rng = np.random.default_rng(0)
    eps = []
    rr, cc = np.mgrid[0:100, 0:100]
    # a compact dome: each survey keeps a wide stable ring (the sub-threshold tails of smooth change
    # otherwise bias the stable median, a documented limitation of automatic stable terrain)
    dome = np.exp(-((rr - 50) ** 2 + (cc - 50) ** 2) / (2 * 5**2))
    for k, (amp, half) in enumerate([(10, 30), (20, 35), (35, 40)]):
        h = base.height_m + amp * dome
        surveyed = (np.abs(rr - 50) < half) & (np.abs(cc - 50) < half)
        merged = np.where(surveyed, h + rng.normal(scale=0.3, size=h.shape), base.height_m)
        eps.append(Epoch(f"e{k}", dt.date(2005, 1 + 3 * k, 1), DEM(merged.astype(np.float32), g)))
    fp = survey_footprint(eps[0].dem.height_m, base.height_m)
    assert fp.sum() == pytest.approx(60 * 59, rel=0.05)
    ts = dem_time_series(eps, base=Epoch("base", None, base))
    rows = [r for r in ts.table if r["kind"] == "interval"]
    cell = g.cell_area_m2
    true_12 = 10 * dome[fp].sum() * cell
    assert abs(rows[0]["volume_net_m3"] - true_12) < 3 * rows[0]["volume_net_sigma_m3"] + 0.03 * true_12
    assert rows[1]["cumulative_net_m3"] == pytest.approx(rows[0]["volume_net_m3"] + rows[1]["volume_net_m3"])
    vb = [r for r in ts.table if r["kind"] == "vs_base"]
    assert len(vb) == 3 and vb[-1]["volume_net_m3"] == pytest.approx(35 * dome.sum() * cell, rel=0.05)
    assert all(np.isfinite(r["volume_net_sigma_m3"]) for r in rows)
