"""The ARD GP: sparse DTC prediction against the exact GP, batching, hyperparameters, integration on a grid."""

from __future__ import annotations

import numpy as np
import pytest

from geocd.errors import ConfigError, EmptyDataError
from geocd.landcover.gp import GPHyper, GPParams, SparseGP, choose_inducing, exact_gp, fit_hyperparameters, integrate


def _hyper(d=3):
    return GPHyper(
        length_scales=np.array([0.8, 1.5, 3.0][:d]),
        signal_var=0.09,
        noise_var=0.004,
        x_mean=np.zeros(d),
        x_std=np.ones(d),
        y_mean=0.4,
        names=[f"x{i}" for i in range(d)],
    )


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


def test_marginal_likelihood_fit_matches_scikit_learn():
    """Our L-BFGS-B fit of the product kernel reaches scikit-learn's optimum (same objective)."""
    from sklearn.gaussian_process import GaussianProcessRegressor
    from sklearn.gaussian_process.kernels import RBF, ConstantKernel, WhiteKernel

    X, y = _data(120, seed=3)
    h = fit_hyperparameters(X, y, GPParams(n_fit=120, kernel="product"))
    Xs, ys = (X - h.x_mean) / h.x_std, (y - h.y_mean) / y.std()
    k = ConstantKernel(0.5) * RBF(np.ones(3), (1e-2, 1e3)) + WhiteKernel(0.1, (1e-5, 1e1))
    g = GaussianProcessRegressor(k, n_restarts_optimizer=2, random_state=0).fit(Xs, ys)
    ours = h.log_marginal_likelihood
    assert ours >= g.log_marginal_likelihood_value_ - 0.05
    np.testing.assert_allclose(
        g.log_marginal_likelihood(np.log(np.r_[h.signal_var / y.var(), h.length_scales, h.noise_var / y.var()])),
        ours,
        atol=1e-6,
    )


def test_nll_gradient_is_exact():
    from scipy.optimize import check_grad

    from geocd.landcover.gp import _nll

    X, y = _data(40, seed=4)
    y = (y - y.mean()) / y.std()
    th = np.log(np.array([0.7, 1.3, 2.0, 0.3, 0.4, 0.05]))
    err = check_grad(lambda t: _nll(t, X, y, [[0, 1], [2]])[0], lambda t: _nll(t, X, y, [[0, 1], [2]])[1], th)
    assert err < 1e-4 * max(1.0, np.abs(_nll(th, X, y, [[0, 1], [2]])[1]).max())


def _additive_hyper():
    return GPHyper(
        length_scales=np.array([0.5, 0.5, 0.3]),
        signal_var=0.09,
        noise_var=0.002,
        x_mean=np.zeros(3),
        x_std=np.ones(3),
        y_mean=0.5,
        names=["x", "y", "coarse"],
        groups=[[0, 1], [2]],
        signal_vars=[0.03, 0.06],
    )


def test_additive_sparse_with_all_points_is_exact():
    X, y = _data(250, seed=5)
    Xs = np.random.default_rng(6).uniform(-2.5, 2.5, (100, 3))
    h = _additive_hyper()
    m1, s1 = exact_gp(X, y, Xs, h)
    m2, s2 = SparseGP(h, X).fit(X, y, batch=50).predict(Xs, batch=30)
    np.testing.assert_allclose(m2, m1, atol=1e-3)
    np.testing.assert_allclose(s2, s1, atol=2e-3)


def test_additive_kernel_carries_appearance_far_away():
    """Far from every observation the product kernel forgets the coarse input; the additive one does not."""
    rng = np.random.default_rng(7)
    X = rng.uniform(0, 1, (200, 3))
    y = (X[:, 2] > 0.5) + 0.3 * np.sin(12.0 * X[:, 0])  # appearance + a local spatial pattern
    far = np.array([[20.0, 20.0, 0.9], [20.0, 20.0, 0.1]])
    for kernel, expect_split in (("additive", True), ("product", False)):
        h = fit_hyperparameters(X, y, GPParams(n_fit=200, kernel=kernel), names=["x", "y", "coarse"])
        m, _ = exact_gp(X, y, far, h)
        assert (m[0] - m[1] > 0.5) == expect_split, (kernel, m)


def test_fit_once_predict_per_window_equals_whole_grid():
    from geocd.landcover.gp import fit_integrator, predict_window

    n = 30
    yy, xx = np.mgrid[0:n, 0:n].astype(float)
    c = np.sin(xx / 4.0) * np.cos(yy / 5.0)
    det = np.where(yy < 12, c + 0.5, np.nan)
    inputs = {"x": xx, "y": yy, "coarse": c}
    gp, _ = fit_integrator(det, inputs, GPParams(n_fit=150, n_inducing=60))
    m, s, so = predict_window(gp, inputs)
    win = {k: v[10:25, 5:20] for k, v in inputs.items()}
    mw, sw, _ = predict_window(gp, win, batch=17)
    np.testing.assert_allclose(mw, m[10:25, 5:20], atol=1e-6)
    np.testing.assert_allclose(sw, s[10:25, 5:20], atol=1e-6)
    with pytest.raises(ConfigError, match="differ"):
        predict_window(gp, {"y": yy, "x": xx, "coarse": c})


def test_heldout_calibration_scales_sigma():
    """Misspecified noise: the held-out scale brings the ±1σ coverage of new observations near 68 %."""
    rng = np.random.default_rng(3)
    n = 40
    yy, xx = np.mgrid[0:n, 0:n].astype(float)
    c = np.sin(xx / 5.0) + np.cos(yy / 7.0)
    target = c + 0.3 * rng.standard_t(3, c.shape)  # heavy-tailed noise
    det = np.where(rng.random(c.shape) < 0.6, target, np.nan)
    res = integrate(det, {"x": xx, "y": yy, "coarse": c}, GPParams(n_fit=200, n_inducing=80, calibrate_folds=4))
    cal = res.report["calibration"]
    assert cal["folds"] == 4 and cal["held_out_cells"] == int(np.isfinite(det).sum())
    new = ~np.isfinite(det)
    err = np.abs(target[new] - res.mean[new])
    assert abs(np.mean(err <= res.sd_cal[new]) - 0.683) < 0.08
    with pytest.raises(ConfigError):
        GPParams(calibrate_folds=1)
