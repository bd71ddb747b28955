import math

import numpy as np
import pytest

from geocd.demdiff import (
    ErrorParams,
    VariogramModel,
    correlated_sum_variance,
    estimate_uncertainty,
    fit_error_model,
    fit_variogram,
    n_effective,
)
from geocd.demdiff._kernels import terrain_attributes
from geocd.demdiff.uncertainty import correlated_sum_variance_ref, default_lag_edges, variogram_fft
from geocd.errors import EmptyDataError

from .synthetic import correlated_noise, grid, terrain

POST = (10.0, 10.0)
MODEL = VariogramModel(0.2, (30.0, 200.0), (0.5, 0.3))


def test_fft_double_sum_equals_brute_force():
    rng = np.random.default_rng(1)
    sig = rng.uniform(0.5, 2.0, size=(17, 23))
    mask = rng.random(sig.shape) > 0.4
    a = correlated_sum_variance(sig, mask, MODEL, POST)
    b = correlated_sum_variance_ref(sig, mask, MODEL, POST)
    assert a == pytest.approx(b, rel=1e-9)


def test_effective_samples_limits():
    sig = np.ones((20, 20))
    m = np.ones(sig.shape, bool)
    white = VariogramModel(1.0, (10.0,), (0.0,))
    assert n_effective(sig, m, white, POST) == pytest.approx(400, rel=1e-6)
    rigid = VariogramModel(0.0, (1e7,), (1.0,))
    assert n_effective(sig, m, rigid, POST) == pytest.approx(1.0, rel=1e-3)
    mid = n_effective(sig, m, MODEL, POST)
    assert 1 < mid < 400


def test_variogram_fit_recovers_a_spherical_model():
    # exact model values → the fit returns them
    lags = default_lag_edges(10.0, 1500.0)
    c = 0.5 * (lags[1:] + lags[:-1])
    g = MODEL.semivariance(c)
    fit = fit_variogram(c, g, np.full(c.size, 1000))
    assert fit.total_sill == pytest.approx(MODEL.total_sill, rel=0.02)
    assert fit.semivariance(np.array([15.0, 60.0, 150.0])) == pytest.approx(
        MODEL.semivariance(np.array([15.0, 60.0, 150.0])), rel=0.05
    )


def test_variogram_of_simulated_correlated_noise():
    rng = np.random.default_rng(2)
    z = correlated_noise((150, 150), 1.0, 3.0, rng)  # Gaussian covariance, ~1/e at 2·3 px = 60 m
    m = np.ones(z.shape, bool)
    edges = default_lag_edges(10.0, 700.0)
    g, n = variogram_fft(z, m, POST, edges)
    c = 0.5 * (edges[1:] + edges[:-1])
    fit = fit_variogram(c, g, n)
    # short lags correlated, long lags not
    assert fit.correlation(np.array([10.0]))[0] > 0.7
    assert fit.correlation(np.array([250.0]))[0] < 0.2
    assert fit.total_sill == pytest.approx(1.0, rel=0.25)


@pytest.mark.parametrize("corr_px", [1.5, 4.0])
def test_sum_sigma_is_calibrated_on_correlated_noise(corr_px):
    """Predicted σ of a regional mean vs its spread over many noise realizations."""
    shape = (120, 120)
    slope = np.zeros(shape, np.float32)
    region = np.zeros(shape, bool)
    region[40:70, 50:80] = True
    stable = ~region
    rng = np.random.default_rng(11)
    means_raw, means_centred = [], []
    for _ in range(80):
        e = correlated_noise(shape, 1.0, corr_px, rng, white=0.3)
        means_raw.append(e[region].mean())
        means_centred.append(e[region].mean() - e[stable].mean())
    e = correlated_noise(shape, 1.0, corr_px, rng, white=0.3)
    unc = estimate_uncertainty(e, stable, slope, None, POST, ErrorParams(predictor="none"))
    n = region.sum()
    pred_raw = unc.sum_sigma_m(region, include_bias=False) / n
    pred_centred = unc.sum_sigma_m(region, include_bias=True) / n
    assert 0.6 < pred_raw / np.std(means_raw) < 1.6, (pred_raw, np.std(means_raw))
    assert 0.6 < pred_centred / np.std(means_centred) < 1.6, (pred_centred, np.std(means_centred))
    # the naive independent-cells σ would be far too small
    assert unc.sigma_m[region].mean() / math.sqrt(n) < 0.7 * np.std(means_raw)


def test_heteroscedastic_model_learns_slope_dependence():
    g = grid(200, 200)
    x, y = g.xy()
    h = terrain(x, y, g.bounds)
    att = terrain_attributes(h, POST)
    s = att["slope_rad"].astype(float)
    rng = np.random.default_rng(4)
    true_sig = np.sqrt(0.5**2 + (3.0 * np.tan(np.nan_to_num(s))) ** 2)
    dh = rng.normal(size=h.shape) * true_sig
    em = fit_error_model(dh, np.isfinite(s), s, None, ErrorParams(predictor="none"))
    for deg in (3.0, 15.0, 30.0):
        t = math.radians(deg)
        assert em.sigma(np.array([t]))[0] == pytest.approx(math.sqrt(0.25 + (3 * math.tan(t)) ** 2), rel=0.2)
    assert len(em.table) >= 3


def test_error_model_needs_stable_cells():
    with pytest.raises(EmptyDataError):
        fit_error_model(np.zeros((5, 5)), np.zeros((5, 5), bool), np.zeros((5, 5)))
