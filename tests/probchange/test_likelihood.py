"""The model of chapter 5: log-domain implementation vs a literal one, σ estimation, hypotheses along rays."""

import math

import numpy as np
import pytest

from geocd.errors import ConfigError, ProcessingError
from geocd.probchange import (
    ProbChangeParams,
    change_log_likelihood_ratio,
    change_probability_direct,
    depth_log_prob,
    fit_half_laplace,
    posterior_change,
    ray_hypotheses,
)


def _rays(rng, n, m=50):
    s = rng.uniform(20, 60, (n, m))
    s[rng.integers(0, n, m), np.arange(m)] = rng.uniform(0, 5, m)  # a good match somewhere
    sp = rng.uniform(0, 60, (n, m))
    return s, sp


@pytest.mark.parametrize("prior", [0.1, 0.5, 0.9])
def test_log_domain_equals_literal_equations(prior):
    """eqs. 5.2-5.11 evaluated literally (products over d) agree with the log-domain implementation."""
    rng = np.random.default_rng(0)
    n = 24
    s, sp = _rays(rng, n)
    sigma, sigp, S = 3.0, 4.0, 70.0
    direct = change_probability_direct(s, sp, sigma, sigp, S, prior)
    logp, _, _ = depth_log_prob(s[:, :, None], sigma)
    llr, cov = change_log_likelihood_ratio(logp, sp[:, :, None], sigp, S)
    prob, _ = posterior_change(llr, prior)
    np.testing.assert_allclose(prob[:, 0], direct, rtol=1e-5, atol=1e-6)
    assert np.allclose(cov, 1.0)


def test_no_underflow_for_long_rays():
    """With n = 4096 hypotheses the literal products underflow (0/0); the log domain stays exact."""
    rng = np.random.default_rng(1)
    n = 4096
    s, sp = _rays(rng, n, m=20)
    sigma, sigp, S = 1.5, 1.5, 255.0
    with np.errstate(all="ignore"):
        direct = change_probability_direct(s, sp, sigma, sigp, S, 0.5)
    assert not np.all(np.isfinite(direct))
    logp, _, _ = depth_log_prob(s[:, :, None], sigma)
    llr, _ = change_log_likelihood_ratio(logp, sp[:, :, None], sigp, S)
    prob, lo = posterior_change(llr, 0.5)
    assert np.all(np.isfinite(prob)) and np.all(np.isfinite(lo))
    # reference: the same equations with every product taken as a float64 sum of logs (scipy logsumexp)
    from scipy.special import logsumexp

    lp = -s / sigma - logsumexp(-s / sigma, axis=0)
    logr = np.log(S / sigp) - sp / sigp
    term = np.logaddexp(lp + logr, np.log(-np.expm1(lp)))
    np.testing.assert_allclose(llr[:, 0], term.sum(axis=0), rtol=1e-5, atol=1e-5)


def test_certain_depth_gives_the_closed_form():
    """p(d) one-hot at d*: p(c=1) = π / (π + (1−π) L(s'_{d*})/U)."""
    n = 10
    s = np.full((n, 1, 1), 200.0)
    s[3] = 0.0
    sp = np.full((n, 1, 1), 7.0)
    sigma, S = 2.0, 100.0
    logp, k, _ = depth_log_prob(s, sigma)
    assert k[0, 0] == 3
    llr, _ = change_log_likelihood_ratio(logp, sp, sigma, S)
    prob, _ = posterior_change(llr, 0.3)
    r = (S / sigma) * math.exp(-7.0 / sigma)
    assert prob[0, 0] == pytest.approx(0.3 / (0.3 + 0.7 * r), rel=1e-4)


def test_no_depth_hypothesis_takes_the_mass_of_bad_matches():
    n = 32
    good = np.full((2, n, 1, 1), 60.0)
    good[:, 10] = 2.0
    bad = np.full((2, n, 1, 1), 60.0)
    bad[:, 10] = 30.0
    for vol, expect_none in ((good, False), (bad, True)):
        logp, _, ln = depth_log_prob(vol, 4.0, 120.0, none_prior=0.1)
        p_none = float(np.exp(ln[0, 0]))
        assert (p_none > 0.9) == expect_none
        assert np.exp(logp[:, 0, 0].astype(float)).sum() + p_none == pytest.approx(1.0, abs=1e-5)


def test_posterior_is_monotonic_in_the_prior_and_neutral_without_evidence():
    llr = np.array([-3.0, 0.0, 2.0])
    last = np.zeros(3)
    for prior in np.linspace(0.1, 0.9, 9):
        p, _ = posterior_change(llr, prior)
        assert np.all(p > last)
        last = p
    assert posterior_change(np.zeros(1), 0.5)[0][0] == pytest.approx(0.5)
    assert posterior_change(np.array([-1e6, 1e6]), 0.5)[0].tolist() == [1.0, 0.0]


def test_fit_half_laplace_recovers_sigma():
    rng = np.random.default_rng(2)
    for sigma in (1.5, 4.0, 9.0):
        x = rng.exponential(sigma, 200_000)
        assert fit_half_laplace(x, 0.95) == pytest.approx(sigma, rel=0.02)
        assert fit_half_laplace(x, 1.0) == pytest.approx(sigma, rel=0.02)
        x[:5000] = rng.uniform(50, 200, 5000)  # 2.5 % occlusion outliers in the tail
        assert fit_half_laplace(x, 0.95) == pytest.approx(sigma, rel=0.10)  # the plain mean is off by > 30 %
        assert np.mean(x) > 1.3 * sigma
    with pytest.raises(ProcessingError, match="overlap"):
        fit_half_laplace(np.full(10, np.nan))


def test_params_validation():
    with pytest.raises(ConfigError, match="prior"):
        ProbChangeParams(prior_change=1.0)
    with pytest.raises(ConfigError, match="odd"):
        ProbChangeParams(window=4)
    with pytest.raises(ConfigError, match="unknown"):
        ProbChangeParams.from_dict({"sigmaa": 1})
    p = ProbChangeParams.robust(prior_change=0.3)
    assert p.visibility and p.pairs == "all" and p.prior_change == 0.3
    assert ProbChangeParams.from_dict(p.to_dict()) == p


# ---------------------------------------------------------------------------------------------
# hypotheses along rays: inverse depth for frame cameras, height for RPC views, one code path
# ---------------------------------------------------------------------------------------------
def test_rpc_rays_get_height_bins():
    from scene import affine_rpc

    key = affine_rpc(0.5, (0.0, 0.02), 200, 200)
    other = affine_rpc(0.5, (0.55, 0.05), 200, 200)
    col, row = np.array([50.5, 120.5]), np.array([80.5, 30.5])
    H = ray_hypotheses(key, [other], col, row, 190.0, 230.0, 128)
    assert H.shape == (128, 2)
    np.testing.assert_allclose(np.diff(H, axis=0), 40.0 / 127, rtol=1e-6)


def test_frame_rays_get_inverse_depth_bins():
    from scene import H0, frame_camera

    # a rectified pair: nadir, same orientation, base along x
    key = frame_camera(0.0, 0.0, 300, 300, altitude_m=150.0, opk=(0.0, 0.0, 0.0))
    other = frame_camera(20.0, 0.0, 300, 300, altitude_m=150.0, opk=(0.0, 0.0, 0.0))
    col, row = np.array([150.0, 40.5, 260.5]), np.array([150.0, 60.5, 250.5])
    H = ray_hypotheses(key, [other], col, row, H0 - 5.0, H0 + 40.0, 64, n_knots=257)
    zc = H0 + 150.0
    # depth along the optical axis = camera height − point height (nadir camera)
    inv_depth = 1.0 / (zc - H)
    step = np.diff(inv_depth, axis=0)
    assert np.max(np.abs(step / step.mean(axis=0) - 1.0)) < 2e-3
    # and not uniform in height
    assert np.max(np.abs(np.diff(H, axis=0) / np.diff(H, axis=0).mean(axis=0) - 1.0)) > 0.2
