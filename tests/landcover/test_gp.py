"""The ARD GP: sparse DTC prediction against the exact GP, batching, hyperparameters, integration on a grid."""

from __future__ import annotations

import numpy as np
import pytest

from geocd.errors import ConfigError, EmptyDataError
from geocd.landcover.gp import GPHyper, GPParams, SparseGP, choose_inducing, exact_gp, fit_hyperparameters, integrate


def _hyper(d=3):
    return GPHyper(length_scales=np.array([0.8, 1.5, 3.0][:d]), signal_var=0.09, noise_var=0.004,
                   x_mean=np.zeros(d), x_std=np.ones(d), y_mean=0.4, names=[f"x{i}" for i in range(d)])


def _data(n=300, d=3, seed=0):
    rng = np.random.default_rng(seed)
    X = rng.uniform(-2, 2, (n, d))
    y = 0.4 + 0.3 * np.sin(1.5 * X[:, 0]) + 0.1 * X[:, 1] + 0.05 * rng.normal(size=n)
    return X, y


def test_sparse_with_all_points_is_exact():
    X, y = _data()
    Xs = np.random.default_rng(1).uniform(-2.5, 2.5, (200, 3))
    h = _hyper()
    m1, s1 = exact_gp(X, y, Xs, h)
    m2, s2 = SparseGP(h, X).fit(X, y, batch=64).predict(Xs, batch=37)
    np.testing.assert_allclose(m2, m1, atol=2e-4)
    np.testing.assert_allclose(s2, s1, atol=2e-3)


def test_exact_gp_reference_formula():
    """exact_gp against the textbook k*ᵀ(K + σn²I)⁻¹y with a dense solve."""
    X, y = _data(60)
    Xs = X[:7] + 0.1
    h = _hyper()
    S, Ss = h.scale(X), h.scale(Xs)
    k = lambda A, B: h.signal_var * np.exp(-0.5 * ((A[:, None, :] - B[None]) ** 2).sum(-1))  # noqa: E731
    K = k(S, S) + h.noise_var * np.eye(60)
    Ks = k(S, Ss)
    mean = Ks.T @ np.linalg.solve(K, y - h.y_mean) + h.y_mean
    var = h.signal_var - np.einsum("ij,ij->j", Ks, np.linalg.solve(K, Ks))
    m, s = exact_gp(X, y, Xs, h)
    np.testing.assert_allclose(m, mean, atol=1e-9)
    np.testing.assert_allclose(s, np.sqrt(var), atol=1e-7)


def test_sparse_with_few_inducing_points_is_close():
    X, y = _data(2000)
    Xs = np.random.default_rng(2).uniform(-2, 2, (300, 3))
    h = _hyper()
    m1, s1 = exact_gp(X, y, Xs, h)
    Z = choose_inducing(X, h, 150)
    m2, s2 = SparseGP(h, Z).fit(X, y).predict(Xs)
    assert np.sqrt(np.mean((m1 - m2) ** 2)) < 0.01
    assert np.median(s2) >= np.median(s1) * 0.9  # DTC does not become overconfident here


def test_far_from_data_reverts_to_prior():
    X, y = _data(200)
    h = _hyper()
    m, s = SparseGP(h, choose_inducing(X, h, 50)).fit(X, y).predict(np.array([[50.0, 50.0, 50.0]]))
    assert m[0] == pytest.approx(h.y_mean, abs=1e-6)
    assert s[0] == pytest.approx(np.sqrt(h.signal_var), rel=1e-3)


def test_hyperparameters_find_the_irrelevant_input():
    rng = np.random.default_rng(0)
    X = rng.uniform(0, 10, (150, 2))
    y = np.sin(X[:, 0]) + 0.05 * rng.normal(size=150)
    h = fit_hyperparameters(X, y, GPParams(n_fit=150), names=["useful", "noise"])
    ls = h.length_scales_units()
    assert ls[1] > 10 * ls[0]
    assert 0.01 < np.sqrt(h.noise_var) < 0.2


def test_integrate_on_a_grid():
    n = 40
    yy, xx = np.mgrid[0:n, 0:n].astype(float)
    truth = (np.sin(xx / 3.0) * np.sin(yy / 4.0) > 0).astype(float)
    coarse = np.clip(truth + np.random.default_rng(0).normal(0, 0.25, truth.shape), 0, 1)
    det = np.where(xx < 20, truth, np.nan)  # the detailed views see the left half
    dem = np.full((n, n), 10.0)
    dem[0, 0] = np.nan  # no height: no prediction there
    res = integrate(det, {"x": xx, "y": yy, "coarse": coarse, "dem": dem}, GPParams(n_fit=300, n_inducing=100))
    assert np.isnan(res.mean[0, 0]) and np.isfinite(res.mean[1:, 1:]).all()
    right = xx >= 20
    acc = np.mean((res.mean[right] > 0.5) == (truth[right] > 0.5))
    assert acc > 0.85, acc
    assert (res.sd_obs >= res.sd)[np.isfinite(res.sd)].all()
    assert res.report["observed_cells"] == 20 * n - 1
    assert set(res.hyper.to_dict()["length_scales"]) == {"x", "y", "coarse", "dem"}


def test_integrate_bad_inputs():
    a = np.full((5, 5), np.nan)
    with pytest.raises(EmptyDataError, match="no cell is both observed"):
        integrate(a, {"x": np.zeros((5, 5))})
    with pytest.raises(ConfigError, match="at least one input"):
        integrate(np.zeros((5, 5)), {})
    with pytest.raises(ConfigError, match="shape"):
        integrate(np.zeros((5, 5)), {"x": np.zeros((4, 5))})
    with pytest.raises(ConfigError):
        GPParams(n_inducing=0)
