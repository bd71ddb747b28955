"""The probabilistic model of chapter 5 (eqs. 5.2, 5.5–5.11) in the log domain, and σ estimation (§5.3.5).

Notation (thesis): at a reference pixel, hypotheses d = 1..n along its ray;
``s_d`` the patch dissimilarity between two images of the *depth epoch* (t),
``s'_d`` between two images of the *other epoch* (t'); c = 1: the scene depth
changed at the pixel.

* depth density (5.2): ``p(d) ∝ exp(−s_d/σ)``; several pairs of the depth epoch
  are independent observations: ``p(d) ∝ exp(−Σ_k s^k_d / σ)``;
* observation models (5.9–5.10): ``p(s'|δ'=1) = e^{−s'/σ'}/σ'`` (half-Laplace),
  ``p(s'|δ'=0) = U = 1/S`` (uniform over the dissimilarity range S);
* per hypothesis (5.8 with Table 5.1 and the approximation of 5.11):
  ``p(s'_d|c=0) = p(d) p(s'|δ'=1) + (1 − p(d)) U`` and ``p(s'_d|c=1) ≈ U``;
* posterior (5.5–5.7): ``logit p(c=1|s') = logit p(c=1) − Σ_pairs Σ_d log[p(s'_d|c=0)/U]``.

Every product over d is a sum of logs (float64), so n = 128 or 4096 hypotheses
never underflow, which a literal implementation of (5.7) does (tested).

σ estimation (§5.3.5): the histogram of ``s̃ = min_d s_d`` over the scene
stands for correctly matched points; a half-Laplace (exponential) density is
fitted to it by maximum likelihood after trimming the values above a high
quantile, so occlusions and specular points in the tail do not inflate σ (the thesis picked σ = 1.5 by
eye for 8-bit street images; here images are normalized to 0–255 first and σ is
measured per scene).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from ..errors import ConfigError, ProcessingError
from . import _kernels as K
from .params import ProbChangeParams


# ---------------------------------------------------------------------------------------------
# σ and S from the data
# ---------------------------------------------------------------------------------------------
def fit_half_laplace(samples: np.ndarray, quantile: float = 0.95) -> float:
    """σ of ``p(s) = e^{−s/σ}/σ`` fitted to the ``samples`` ≤ their ``quantile`` (§5.3.5).

    The maximum-likelihood σ of a half-Laplace (exponential) sample is its mean.
    Values above the quantile (occlusions, specular spots, untextured borders)
    are trimmed first, and the trimmed mean is divided by its known ratio to σ
    for an exponential trimmed at its own q-quantile,
    ``c(q) = 1 + (1 − q) ln(1 − q) / q`` (0.842 at q = 0.95), so exponential data
    give σ back without bias. The truncated-exponential likelihood itself is
    *not* maximized: as the thesis notes (Fig. 5.10), the histogram of
    min_d s_d peaks above 0 (noise and the min over d), and for such a histogram
    that MLE runs off to σ → ∞.

    Parameters
    ----------
    samples : array of dissimilarities (NaN ignored), e.g. min_d s_d of many pixels
    quantile : float in [0.5, 1]

    Raises
    ------
    ProcessingError
        Fewer than 50 finite samples (nothing to fit: the images do not overlap enough).
    """
    s = np.asarray(samples, np.float64)
    s = s[np.isfinite(s) & (s >= 0)]
    if s.size < 50:
        raise ProcessingError(
            f"only {s.size} patch dissimilarities to estimate σ from (≥ 50 needed): the images of "
            "the epoch hardly overlap over the area; check the AOI/key frame or give sigma "
            "explicitly"
        )
    c = 1.0
    if quantile < 1.0:
        s = s[s <= np.quantile(s, quantile)]
        c = 1.0 + (1.0 - quantile) * math.log(1.0 - quantile) / quantile
    return float(max(s.mean() / c, 1e-3))


def uniform_range(samples: np.ndarray, quantile: float = 0.99) -> float:
    """Width S of the uniform density of mismatched dissimilarities: a high quantile of all s'."""
    s = np.asarray(samples, np.float64)
    s = s[np.isfinite(s)]
    if s.size < 50:
        raise ProcessingError(
            "too few patch dissimilarities to estimate the uniform range; give uniform_range explicitly"
        )
    return float(max(np.quantile(s, quantile), 1e-3))


@dataclass(frozen=True)
class NoiseModel:
    """σ (depth epoch), σ' (other epoch) and the uniform range S, with where they came from.

    For the symmetric test the roles swap: the other epoch's σ' shapes its depth
    density and σ the first epoch's observations (each epoch keeps its own σ).
    """

    sigma: float
    sigma_prime: float
    s_range: float
    s_range_prime: float
    source: str = "given"
    n_samples: int = 0

    def to_dict(self) -> dict:
        return {
            "sigma": self.sigma,
            "sigma_prime": self.sigma_prime,
            "uniform_range": self.s_range,
            "uniform_range_prime": self.s_range_prime,
            "source": self.source,
            "n_samples": self.n_samples,
        }


# ---------------------------------------------------------------------------------------------
# array API (numpy in / numpy out)
# ---------------------------------------------------------------------------------------------
def _volume(v: np.ndarray, name: str) -> np.ndarray:
    a = np.asarray(v)
    if a.ndim == 3:
        a = a[None]
    if a.ndim != 4:
        raise ConfigError(f"{name} must be (pairs, n, rows, cols) or (n, rows, cols), got shape {a.shape}")
    return np.ascontiguousarray(a, np.float32)


def depth_log_prob(
    s_depth: np.ndarray, sigma: float, s_range: float = 1.0, none_prior: float = 0.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """log p(d) (eq. 5.2) from one or several pairs of the depth epoch.

    Parameters
    ----------
    s_depth : float (pairs, n, rows, cols) or (n, rows, cols); NaN = not observed
    sigma : σ on the same scale as ``s_depth``
    s_range : S, width of the uniform density of mismatched dissimilarities (only matters with
        ``none_prior`` > 0)
    none_prior : π∅, prior probability that no hypothesis is the surface (0: the thesis, p(d) sums to 1)

    Returns
    -------
    logp : float32 (n, rows, cols), −inf for hypotheses no pair observes
    k_map : int32 (rows, cols), the most probable hypothesis (−1 where none is observed)
    log_none : float32 (rows, cols), log p(∅) (−inf when π∅ = 0)
    """
    if not (sigma > 0 and math.isfinite(sigma)):
        raise ConfigError(f"σ must be positive and finite, got {sigma}")
    if not 0.0 <= none_prior < 1.0:
        raise ConfigError(f"none_prior must be in [0, 1), got {none_prior}")
    v = _volume(s_depth, "s_depth")
    P, n, h, w = v.shape
    out = np.empty((n, h, w), np.float32)
    kb = np.empty((h, w), np.int32)
    ln = np.empty((h, w), np.float32)
    K.depth_logprob(
        v,
        1.0 / float(sigma),
        math.log(float(s_range) / float(sigma)),
        math.log(none_prior) if none_prior > 0 else -math.inf,
        math.log1p(-none_prior),
        out,
        kb,
        ln,
    )
    return out, kb, ln


def change_log_likelihood_ratio(
    logp: np.ndarray, s_obs: np.ndarray, sigma_prime: float, s_range: float, outlier_fraction: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """``Σ_pairs Σ_d log[p(s'_d|c=0)/p(s'_d|c=1)]`` (eqs. 5.7–5.11), float64.

    Parameters
    ----------
    logp : float32 (n, rows, cols), from :func:`depth_log_prob`
    s_obs : float (pairs, n, rows, cols) or (n, rows, cols): s' of the other epoch (NaN = not observed)
    sigma_prime : σ'
    s_range : S, width of the uniform density of mismatched dissimilarities
    outlier_fraction : ε of the occlusion-robust variant (0: the thesis)

    Returns
    -------
    llr : float64 (rows, cols) — positive: evidence for "no change"
    coverage : float32 (rows, cols) — fraction of the depth probability mass the pairs observe (0–1)
    """
    if not (sigma_prime > 0 and s_range > 0):
        raise ConfigError(f"σ' and S must be positive, got {sigma_prime}, {s_range}")
    lp = np.ascontiguousarray(logp, np.float32)
    v = _volume(s_obs, "s_obs")
    if v.shape[1:] != lp.shape:
        raise ConfigError(f"s_obs {v.shape[1:]} and logp {lp.shape} must have the same (n, rows, cols)")
    n, h, w = lp.shape
    llr = np.empty((h, w), np.float64)
    cov = np.empty((h, w), np.float32)
    eps = float(outlier_fraction)
    log_eps = math.log(eps) if eps > 0 else -math.inf
    K.change_llr(
        lp,
        v,
        1.0 / float(sigma_prime),
        math.log(float(s_range) / float(sigma_prime)),
        log_eps,
        math.log1p(-eps),
        llr,
        cov,
    )
    return llr, cov


def posterior_change(llr: np.ndarray, prior_change: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """p(c = 1 | s'_1..s'_n) (eq. 5.5) and its log-odds from the log-likelihood ratio.

    Returns
    -------
    prob : float32, log_odds : float32 (natural log of p/(1 − p))
    """
    if not 0.0 < prior_change < 1.0:
        raise ConfigError(f"prior p(c=1) must be in (0, 1), got {prior_change}")
    lo = math.log(prior_change) - math.log1p(-prior_change) - np.asarray(llr, np.float64)
    with np.errstate(over="ignore"):
        prob = 0.5 * (1.0 + np.tanh(0.5 * lo))  # logistic, stable for any |lo|
    return prob.astype(np.float32), lo.astype(np.float32)


def change_probability_direct(
    s_depth: np.ndarray, s_obs: np.ndarray, sigma: float, sigma_prime: float, s_range: float, prior_change: float = 0.5
) -> np.ndarray:
    """A literal, probability-domain evaluation of eqs. 5.2–5.11 for ONE pair per epoch (reference only).

    Products over d are computed as products, so they underflow for long rays
    (this is what the log-domain implementation avoids); used by the tests.

    Parameters
    ----------
    s_depth, s_obs : float (n, ...) dissimilarities along the rays
    """
    s = np.asarray(s_depth, np.float64)
    sp = np.asarray(s_obs, np.float64)
    e = np.exp(-s / sigma)
    p = e / e.sum(axis=0)
    U = 1.0 / s_range
    L = np.exp(-sp / sigma_prime) / sigma_prime
    p_c0 = np.prod(p * L + (1 - p) * U, axis=0)  # p(s'_1..n | c=0)   (5.7b with 5.8)
    p_c1 = np.prod(np.full_like(p, U), axis=0)  # p(s'_1..n | c=1)   (5.7a with 5.11)
    num = p_c1 * prior_change
    return num / (num + p_c0 * (1 - prior_change))


# ---------------------------------------------------------------------------------------------
# per-tile evaluation shared by the key-frame and object-space variants
# ---------------------------------------------------------------------------------------------
@dataclass
class TileEvidence:
    """Dissimilarity volumes of one tile: ``s_a`` (depth-epoch pairs) and ``s_b`` (other-epoch pairs)."""

    s_a: np.ndarray  # float32 (PA, n, h, w)
    s_b: np.ndarray  # float32 (PB, n, h, w)
    k0: int = 0  # index of the first hypothesis (object space: plane index)
    extra: Any = None  # variant-specific data (key frame: hypothesis heights on the lattice)
    s_b_obs: np.ndarray | None = None  # s_b as observations of A's depth (visibility-masked); None: s_b
    s_a_obs: np.ndarray | None = None  # s_a as observations of B's depth (symmetric test); None: s_a


@dataclass
class TileResult:
    """Per-pixel outputs of one tile (float32 unless noted)."""

    prob: np.ndarray
    log_odds: np.ndarray
    coverage: np.ndarray
    k_a: np.ndarray  # int32, MAP hypothesis of the depth epoch (−1: none)
    k_b: np.ndarray  # int32, MAP hypothesis of the other epoch
    llr_ab: np.ndarray  # float64
    llr_ba: np.ndarray | None = None


def evaluate_tile(ev: TileEvidence, noise: NoiseModel, params: ProbChangeParams) -> TileResult:
    """Depth densities, log-likelihood ratios and the posterior on one tile (both epochs' MAP too)."""
    logp_a, k_a, none_a = depth_log_prob(ev.s_a, noise.sigma, noise.s_range, params.no_depth_prior)
    logp_b, k_b, none_b = depth_log_prob(ev.s_b, noise.sigma_prime, noise.s_range_prime, params.no_depth_prior)
    obs_b = ev.s_b if ev.s_b_obs is None else ev.s_b_obs
    obs_a = ev.s_a if ev.s_a_obs is None else ev.s_a_obs
    llr_ab, cov = change_log_likelihood_ratio(
        logp_a, obs_b, noise.sigma_prime, noise.s_range_prime, params.outlier_fraction
    )
    # coverage: the share of the depth epoch's probability (with "no consistent depth") the other epoch observes
    cov = cov * (1.0 - np.exp(none_a))
    llr = llr_ab
    llr_ba = None
    if params.symmetric:
        llr_ba, cov_b = change_log_likelihood_ratio(logp_b, obs_a, noise.sigma, noise.s_range, params.outlier_fraction)
        llr = llr_ab + llr_ba
        cov = np.maximum(cov, cov_b * (1.0 - np.exp(none_b)))
    prob, lo = posterior_change(llr, params.prior_change)
    return TileResult(prob, lo, cov, k_a, k_b, llr_ab, llr_ba)


def pair_minima(vol: np.ndarray) -> np.ndarray:
    """min_d s_d per pair and pixel (the s̃ of §5.3.5), NaN where a pair observes nothing: (P, h, w)."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanmin(vol, axis=1)


def estimate_noise_model(
    samples_a_min: Sequence[np.ndarray],
    samples_b_min: Sequence[np.ndarray],
    samples_a_all: Sequence[np.ndarray],
    samples_b_all: Sequence[np.ndarray],
    params: ProbChangeParams,
) -> NoiseModel:
    """σ, σ' (§5.3.5) and S, S' from sampled dissimilarities (parameters given explicitly win)."""
    cat = lambda xs: np.concatenate([np.asarray(x, np.float64).ravel() for x in xs]) if xs else np.empty(0)  # noqa: E731
    a_min, b_min = cat(samples_a_min), cat(samples_b_min)
    sig = params.sigma if params.sigma is not None else fit_half_laplace(a_min, params.sigma_fit_quantile)
    sigp = params.sigma_prime if params.sigma_prime is not None else fit_half_laplace(b_min, params.sigma_fit_quantile)
    if params.uniform_range is not None:
        S = Sp = float(params.uniform_range)
    else:
        S = uniform_range(cat(samples_a_all), params.uniform_quantile)
        Sp = uniform_range(cat(samples_b_all), params.uniform_quantile)
    given = params.sigma is not None and params.sigma_prime is not None and params.uniform_range is not None
    return NoiseModel(
        float(sig),
        float(sigp),
        float(S),
        float(Sp),
        "given" if given else "estimated (§5.3.5)",
        int(np.isfinite(a_min).sum() + np.isfinite(b_min).sum()),
    )


def subsample(values: np.ndarray, max_n: int, rng: np.random.Generator) -> np.ndarray:
    """Finite values, at most ``max_n`` of them (uniform random draws with replacement)."""
    v = np.asarray(values).ravel()
    if v.size > 4 * max_n:  # thin first (cheap), then drop NaN
        v = v[rng.integers(0, v.size, 4 * max_n)]
    v = v[np.isfinite(v)]
    if v.size > max_n:
        v = v[rng.integers(0, v.size, max_n)]
    return v
