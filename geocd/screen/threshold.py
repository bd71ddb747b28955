"""Where the screen's threshold comes from — never from the pair it is scored on.

* **No-change pair** (:func:`threshold_from_nochange`): the dissimilarities of a pair known
  to hold no change (two views of one date, or a control pair) are the null distribution;
  the threshold is its ``100 − false_alarm_pct`` percentile, then Otsu's split of the
  screened pair's values above it (:func:`split_above`): the null bounds what noise does,
  the split separates cells that changed from cells a change merely touches (the coarse
  grid's halo). The screen's confidence that a cell changed is the percentile of its
  value in the null (:class:`NullDistribution`).
* **Labelled pairs** (:func:`threshold_best_f1`): the threshold of the best pooled F1 on
  pairs with truth masks (other pairs than the one screened).
* **Fixed**: a number the user gives.

:func:`f1_scores` scores a change mask against a truth mask.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from ..errors import ConfigError, EmptyDataError

THRESHOLD_RULES = ("nochange", "labelled", "fixed")


@dataclass(frozen=True)
class NullDistribution:
    """Sorted dissimilarities of a no-change pair (a sample of at most ``max_n``)."""

    values: np.ndarray
    source: str = ""

    @classmethod
    def from_values(cls, d: np.ndarray, source: str = "", max_n: int = 200_000, seed: int = 0) -> "NullDistribution":
        v = np.asarray(d, np.float64).ravel()
        v = v[np.isfinite(v)]
        if v.size < 100:
            raise EmptyDataError(
                f"the no-change pair {source or ''} has {v.size} valid values; at least 100 are "
                "needed for a threshold (is the pair on the same grid and overlapping?)"
            )
        if v.size > max_n:
            v = np.random.default_rng(seed).choice(v, max_n, replace=False)
        return cls(np.sort(v).astype(np.float32), source)

    def threshold(self, false_alarm_pct: float) -> float:
        if not 0 < false_alarm_pct < 50:
            raise ConfigError(f"false_alarm_pct must be between 0 and 50 (percent), got {false_alarm_pct}")
        return float(np.quantile(self.values, 1 - false_alarm_pct / 100.0))

    def confidence_pct(self, d: np.ndarray) -> np.ndarray:
        """Percent of the no-change values below ``d`` (NaN stays NaN)."""
        d = np.asarray(d, np.float64)
        out = 100.0 * np.searchsorted(self.values, np.where(np.isfinite(d), d, 0.0), side="left") / self.values.size
        return np.where(np.isfinite(d), out, np.nan).astype(np.float32)

    def to_dict(self) -> dict:
        q = np.quantile(self.values, [0.5, 0.9, 0.95, 0.99, 0.999])
        return {
            "source": self.source,
            "n": int(self.values.size),
            "quantiles": {k: round(float(v), 4) for k, v in zip(("50", "90", "95", "99", "99.9"), q)},
        }


def threshold_from_nochange(
    d_nochange: np.ndarray, false_alarm_pct: float = 1.0, source: str = "", d_test: np.ndarray | None = None
) -> float:
    """The ``100 − false_alarm_pct`` percentile of a no-change pair's dissimilarities; with ``d_test``,
    raised to Otsu's split of the screened pair's values above it (:func:`split_above`)."""
    t = NullDistribution.from_values(d_nochange, source).threshold(false_alarm_pct)
    return split_above(d_test, t) if d_test is not None else t


def split_above(d_test: np.ndarray, t_null: float, min_n: int = 50) -> float:
    """Otsu's split of the screened values above the null threshold (never below it).

    The null threshold bounds what noise does; the values above it mix cells that changed over
    most of their area with cells a change merely touches (the coarse grid's halo, spread to the
    pixels and to whole superpixels). Otsu's two-class split of those values keeps the first
    group: data-derived, no constant tuned on a truth.
    """
    from skimage.filters import threshold_otsu

    v = np.asarray(d_test, np.float64).ravel()
    v = v[np.isfinite(v) & (v > t_null)]
    if v.size < min_n or np.ptp(v) <= 0:
        return float(t_null)
    return float(max(t_null, threshold_otsu(v)))


def f1_scores(changed: np.ndarray, truth: np.ndarray, valid: np.ndarray | None = None) -> dict[str, float]:
    """Pixel precision, recall, F1 and counts of a change mask against truth (on valid cells)."""
    c = np.asarray(changed, bool)
    t = np.asarray(truth, bool)
    v = np.ones_like(c) if valid is None else np.asarray(valid, bool)
    tp = int(np.sum(c & t & v))
    fp = int(np.sum(c & ~t & v))
    fn = int(np.sum(~c & t & v))
    p = tp / (tp + fp) if tp + fp else 0.0
    r = tp / (tp + fn) if tp + fn else 0.0
    f = 2 * p * r / (p + r) if p + r else 0.0
    return {"precision": round(p, 4), "recall": round(r, 4), "f1": round(f, 4), "tp": tp, "fp": fp, "fn": fn}


def f1_curve(ds: Sequence[np.ndarray], truths: Sequence[np.ndarray], thresholds: np.ndarray) -> np.ndarray:
    """Pooled F1 over pairs at each threshold (``changed = d > t``; NaN cells left out)."""
    tp = np.zeros(len(thresholds))
    fp = np.zeros(len(thresholds))
    fn = np.zeros(len(thresholds))
    for d, t in zip(ds, truths):
        d = np.asarray(d, np.float64).ravel()
        t = np.asarray(t, bool).ravel()
        ok = np.isfinite(d)
        d, t = d[ok], t[ok]
        pos = np.sort(d[t])
        neg = np.sort(d[~t])
        n_pos_above = pos.size - np.searchsorted(pos, thresholds, side="right")
        n_neg_above = neg.size - np.searchsorted(neg, thresholds, side="right")
        tp += n_pos_above
        fp += n_neg_above
        fn += pos.size - n_pos_above
    with np.errstate(invalid="ignore", divide="ignore"):
        f = np.where(2 * tp + fp + fn > 0, 2 * tp / (2 * tp + fp + fn), 0.0)
    return f


def threshold_best_f1(ds: Sequence[np.ndarray], truths: Sequence[np.ndarray], n: int = 400) -> tuple[float, float]:
    """The threshold of the best pooled F1 over labelled pairs; returns (threshold, F1 there)."""
    if not ds:
        raise ConfigError("threshold_best_f1 needs at least one labelled pair")
    hi = max(float(np.nanmax(d)) if np.isfinite(d).any() else 0.0 for d in ds)
    ts = np.linspace(0.0, max(hi, 1e-6), n)
    f = f1_curve(ds, truths, ts)
    k = int(np.argmax(f))
    return float(ts[k]), float(f[k])
