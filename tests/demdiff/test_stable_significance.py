import numpy as np
import pytest

from geocd.demdiff import (
    StableParams,
    auto_stable_mask,
    change_sign,
    fit_significance,
    nmad,
    significance_map,
    stable_terrain,
)
from geocd.errors import ConfigError, EmptyDataError

from .synthetic import grid


def test_nmad_of_gaussian():
    x = np.random.default_rng(0).normal(scale=2.0, size=200_000)
    assert nmad(x) == pytest.approx(2.0, rel=0.01)
    assert np.isnan(nmad(np.array([np.nan])))


def test_auto_stable_excludes_coherent_change_but_keeps_isolated_outliers():
    rng = np.random.default_rng(1)
    dh = rng.normal(scale=0.5, size=(100, 100))
    dh[30:50, 30:50] += 10.0  # a coherent change
    dh[80, 80] = 9.0  # an isolated blunder: part of the error distribution
    m, info = auto_stable_mask(dh)
    assert not m[30:50, 30:50].any() and not m[29, 30]  # change and its 1-cell buffer excluded
    assert m[80, 80]
    assert info.nmad_m == pytest.approx(0.5, rel=0.1) and info.n_cells > 8500


def test_auto_stable_reports_when_everything_changed():
    rng = np.random.default_rng(2)
    dh = np.linspace(0, 200, 10000).reshape(100, 100) + rng.normal(size=(100, 100))
    m, info = auto_stable_mask(dh)
    assert not m.any() and "no stable terrain" in " ".join(info.notes)


def test_user_mask_and_footprints():
    g = grid(40, 40)
    dh = np.zeros(g.shape)
    valid = np.ones(g.shape, bool)
    user = np.zeros(g.shape, bool)
    user[:20] = True
    m, info = stable_terrain(dh, valid, g, user_mask=user)
    assert m.sum() == 800 and info.source.startswith("user")
    m2, _ = stable_terrain(dh, valid, g, user_mask=user, mask_is="unstable")
    assert m2.sum() == 800 and not m2[:20].any()
    from shapely.geometry import box
    import geopandas as gpd

    l, b, r, t = g.bounds
    fp = gpd.GeoDataFrame(geometry=[box(l + 100, t - 100, l + 150, t - 50)], crs=g.crs)
    m3, info3 = stable_terrain(dh, valid, g, footprints=fp)
    assert not m3[5:10, 10:15].any() and not m3[4, 9] and m3.sum() > 1400


def test_all_nan_stable_mask_is_an_error():
    g = grid(30, 30)
    dh = np.full(g.shape, np.nan)
    dh[:, 15:] = 0.0
    user = np.zeros(g.shape, bool)
    user[:, :10] = True  # only cells without data
    with pytest.raises(EmptyDataError, match="none of them holds valid heights"):
        stable_terrain(dh, np.isfinite(dh), g, user_mask=user)
    with pytest.raises(ConfigError):
        StableParams(max_slope_deg=0)


def test_significance_from_stable_distribution():
    rng = np.random.default_rng(3)
    dh = rng.standard_t(5, size=(100, 100))
    sig = np.ones(dh.shape)
    st = np.ones(dh.shape, bool)
    st[:10] = False
    dh[:10, :10] = 25.0
    model = fit_significance(dh, sig, st)
    z, conf = significance_map(dh, sig, model)
    # on stable terrain the confidence is uniform: ~5% of cells reach 0.95
    frac = np.mean(conf[st] >= 0.95)
    assert 0.04 < frac < 0.06
    assert np.all(conf[:10, :10] > 0.999)
    thr = model.threshold_z(0.95)
    assert np.all((conf >= 0.95) == (np.abs(z) > thr))
    s = change_sign(dh, conf, 0.99, model.center_m)
    assert np.all(s[:10, :10] == 1)
    s2 = change_sign(dh, conf, 0.99, model.center_m, observed=~np.eye(100, dtype=bool), nodata=-128)
    assert s2[5, 5] == -128 and s2[5, 6] == 1
    curves = model.curves(type("EM", (), {"sigma": lambda self, s, q: np.ones_like(s)})())
    assert curves["0.99"][0] > curves["0.9"][0]


def test_significance_needs_stable_cells():
    with pytest.raises(EmptyDataError):
        fit_significance(np.zeros((3, 3)), np.ones((3, 3)), np.ones((3, 3), bool))
