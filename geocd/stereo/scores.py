"""Match scores: MDL (description length), NCC and the SSD residual.

MDL score (a reconstruction — the published papers' exact formula is not
available; this is the working definition of the project notes and issue 4)
------------------------------------------------------------------------------
For ``k`` windows of ``n`` pixels (here ``k = 2``: the two images warped onto the
grid at the matched height) with noise standard deviation ``σ_n``:

* coding each window on its own costs ``L_ind = Σ_j (n/2) log2(s_j² + σ_n²)`` bits,
  with ``s_j²`` the variance of window ``j``;
* coding them as one match — their mean window ``t`` (variance ``s_t²``) plus the
  residuals — costs ``L_match = (n/2) log2(s_t² + σ_n²) + ((k−1) n/2) log2(v + σ_n²)``
  with ``v`` the residual variance;
* ``score = (L_match − L_ind) / n`` bits per pixel. **Lower is better**: negative
  means the match explains the data (describing the two windows as one surface
  seen twice is shorter than describing them separately).

Choices made here (documented because the formula leaves them open):

* variances are population variances over the window (divide by ``n``);
* the residual is taken after removing each window's mean (a photometric offset
  between the images is not charged), and ``v = RSS / ((k−1) n)`` — the residual
  sum of squares over its ``(k−1) n`` degrees of freedom. For ``k = 2`` with
  variances ``s_a², s_b²`` and covariance ``c``: ``s_t² = (s_a² + s_b² + 2c)/4`` and
  ``v = (s_a² + s_b² − 2c)/2``;
* intensities are on the locally normalized 8-bit scale
  (:mod:`geocd.stereo.photometry`), ``σ_n`` estimated from the images.

* **the score of a match is the worst of its sub-windows**: the matching window
  (7 × 7 cells by default) is cut into 3 × 3-cell sub-windows that tile it
  (``StereoParams.score_subwindow``), each scored with the formula above at the
  matched height, and the largest (worst) is kept
  (:func:`geocd.stereo.subwindow_mdl`). A window whose contrast one surface explains
  but whose other part it does not — it straddles a height step, and its height is
  that of the stronger side ("foreground fattening") — then scores like its
  unexplained part instead of passing for a good match. On sample_aoi this turns the
  score deciles from non-monotonic into rising (docs/stereo.md); the whole-window
  score stays available (``score_subwindow ≥ window``, ``PairDEM.mdl_window``).

Consequences worth knowing: a perfect match of texture ``s`` scores
``½ log2(σ_n²/(s² + σ_n²))`` (very negative for strong texture); a textureless
window scores ≈ 0 (no evidence either way); two independent windows of equal
variance score ≈ −½. The score is a *predictor*: whether it predicts
self-consistency is checked empirically (docs/stereo.md).

NCC is the zero-mean normalized cross-correlation ``c / sqrt(s_a² s_b²)``; the SSD
residual is the mean squared difference of the zero-mean windows
``s_a² + s_b² − 2c`` (8-bit units²).
"""

from __future__ import annotations

import numpy as np


def window_stats(mom: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(n, var_a, var_b, cov) from window moments ``(6, ...)`` (see :mod:`geocd.stereo._kernels`)."""
    n = mom[0]
    with np.errstate(all="ignore"):
        ma = mom[1] / n
        mb = mom[2] / n
        va = np.maximum(mom[3] / n - ma * ma, 0.0)
        vb = np.maximum(mom[4] / n - mb * mb, 0.0)
        cov = mom[5] / n - ma * mb
    return n, va, vb, cov


def mdl_from_stats(var_a: np.ndarray, var_b: np.ndarray, cov: np.ndarray, noise_sigma: float) -> np.ndarray:
    """MDL score (bits per pixel, lower = better) of two windows from their variances and covariance."""
    s2 = float(noise_sigma) ** 2
    va = np.asarray(var_a, np.float64)
    vb = np.asarray(var_b, np.float64)
    c = np.asarray(cov, np.float64)
    st2 = np.maximum((va + vb + 2.0 * c) / 4.0, 0.0)
    v = np.maximum((va + vb - 2.0 * c) / 2.0, 0.0)
    return 0.5 * (np.log2(st2 + s2) + np.log2(v + s2) - np.log2(va + s2) - np.log2(vb + s2))


def ncc_from_stats(var_a: np.ndarray, var_b: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """Zero-mean NCC in [−1, 1]; NaN where a window is flat."""
    with np.errstate(all="ignore"):
        d = np.sqrt(np.asarray(var_a, np.float64) * np.asarray(var_b, np.float64))
        r = np.where(d > 0, np.asarray(cov, np.float64) / d, np.nan)
    return np.clip(r, -1.0, 1.0)


def ssd_from_stats(var_a: np.ndarray, var_b: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """Mean squared difference of the zero-mean windows (8-bit units²)."""
    return np.maximum(
        np.asarray(var_a, np.float64) + np.asarray(var_b, np.float64) - 2.0 * np.asarray(cov, np.float64), 0.0
    )


def mdl_score_ref(windows: np.ndarray, noise_sigma: float) -> float:
    """Direct MDL score of ``k`` windows (``(k, n)`` array, any k ≥ 2), bits per pixel.

    The reference for :func:`mdl_from_stats` (which is the k = 2 case from moments).
    """
    w = np.asarray(windows, np.float64)
    k, n = w.shape
    s2 = float(noise_sigma) ** 2
    L_ind = sum(n / 2.0 * np.log2(w[j].var() + s2) for j in range(k))
    t = w.mean(axis=0)
    resid = (w - w.mean(axis=1, keepdims=True)) - (t - t.mean())
    v = float((resid**2).sum()) / ((k - 1) * n)
    L_match = n / 2.0 * np.log2(t.var() + s2) + (k - 1) * n / 2.0 * np.log2(v + s2)
    return float((L_match - L_ind) / n)


SCORES = ("mdl", "ncc", "ssd")


def score_from_stats(kind: str, var_a, var_b, cov, noise_sigma: float) -> np.ndarray:
    """The score used as ``PairDEM.score`` (lower = better): mdl, 1 − ncc, or ssd."""
    if kind == "mdl":
        return mdl_from_stats(var_a, var_b, cov, noise_sigma)
    if kind == "ncc":
        return 1.0 - ncc_from_stats(var_a, var_b, cov)
    if kind == "ssd":
        return ssd_from_stats(var_a, var_b, cov)
    raise ValueError(f"score must be one of {SCORES}, got {kind!r}")
