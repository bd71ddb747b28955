"""Evaluation against truth: confusion counts, precision/recall/F1, false-alarm rate, ROC/AUC.

Shared by every method so their figures are comparable.
"""

from __future__ import annotations

import numpy as np


def binary_scores(pred: np.ndarray, truth: np.ndarray, valid: np.ndarray | None = None) -> dict:
    """Cell-level scores of a binary prediction.

    Parameters
    ----------
    pred, truth : bool-like arrays (non-zero = change)
    valid : optional bool array; only these cells count (e.g. observed cells)

    Returns
    -------
    dict with tp, fp, fn, tn, precision, recall, f1, false_alarm_rate (fp / (fp + tn):
    the fraction of cells with no change that are flagged), n.
    """
    p = np.asarray(pred) != 0
    t = np.asarray(truth) != 0
    if valid is not None:
        v = np.asarray(valid, bool)
        p, t = p[v], t[v]
    tp = int(np.sum(p & t))
    fp = int(np.sum(p & ~t))
    fn = int(np.sum(~p & t))
    tn = int(np.sum(~p & ~t))
    precision = tp / (tp + fp) if tp + fp else float("nan")
    recall = tp / (tp + fn) if tp + fn else float("nan")
    f1 = 2 * precision * recall / (precision + recall) if tp else 0.0
    return {
        "tp": tp,
        "fp": fp,
        "fn": fn,
        "tn": tn,
        "precision": precision,
        "recall": recall,
        "f1": f1,
        "false_alarm_rate": fp / (fp + tn) if fp + tn else float("nan"),
        "n": int(p.size),
    }


def roc_curve(score: np.ndarray, truth: np.ndarray, valid: np.ndarray | None = None, n_thresholds: int = 512):
    """ROC of a continuous change score (higher = more likely change).

    The same curve and AUC as scikit-learn's ``roc_curve(..., drop_intermediate=True)`` and ``roc_auc_score``,
    bit for bit, from one sort of the scores (scikit-learn sorts twice and validates its inputs each time).

    Parameters
    ----------
    score : float array (any shape), NaN where undefined
    truth : bool-like array of the same shape (non-zero = change)
    valid : optional bool array; only these cells count
    n_thresholds : the curve is thinned to about this many points (the AUC uses every point)

    Returns
    -------
    fpr, tpr, thresholds : 1-D arrays (fpr increasing)
    auc : float (trapezoidal); NaN when only one class is present
    """
    s = np.asarray(score, float)
    t = np.asarray(truth) != 0
    ok = np.isfinite(s)
    if valid is not None:
        ok &= np.asarray(valid, bool)
    s, t = s[ok], t[ok]
    if t.all() or not t.any():
        return np.array([0.0, 1.0]), np.array([0.0, 1.0]), np.array([np.inf, -np.inf]), float("nan")
    from scipy.integrate import trapezoid

    # scores in decreasing order; the order within ties does not change the counts at the thresholds
    order = np.argsort(s, kind="stable")[::-1]
    s, t = s[order], t[order]
    idx = np.r_[np.nonzero(np.diff(s))[0], t.size - 1]  # the last sample of each distinct score
    tps = np.cumsum(t, dtype=np.float64)[idx]
    fps = 1 + idx.astype(np.float64) - tps
    thr = s[idx]
    if fps.size > 2:  # drop the points inside straight runs of the curve (scikit-learn's drop_intermediate)
        keep = np.nonzero(np.r_[True, np.logical_or(np.diff(fps, 2), np.diff(tps, 2)), True])[0]
        fps, tps, thr = fps[keep], tps[keep], thr[keep]
    fpr = np.r_[0.0, fps] / fps[-1]
    tpr = np.r_[0.0, tps] / tps[-1]
    thr = np.r_[np.inf, thr]
    auc = float(trapezoid(tpr, fpr))
    if fpr.size > n_thresholds:
        idx = np.unique(np.linspace(0, fpr.size - 1, n_thresholds).astype(int))
        fpr, tpr, thr = fpr[idx], tpr[idx], thr[idx]
    return fpr, tpr, thr, auc


def best_threshold_f1(score: np.ndarray, truth: np.ndarray, valid: np.ndarray | None = None) -> tuple[float, dict]:
    """The threshold on ``score`` that maximizes F1 (for "best threshold" baselines)."""
    from sklearn.metrics import precision_recall_curve

    s = np.asarray(score, float)
    t = np.asarray(truth) != 0
    ok = np.isfinite(s)
    if valid is not None:
        ok &= np.asarray(valid, bool)
    prec, rec, thr = precision_recall_curve(t[ok], s[ok])
    f1 = np.where(prec + rec > 0, 2 * prec * rec / np.maximum(prec + rec, 1e-12), 0)[:-1]
    k = int(np.argmax(f1))
    best = float(thr[k])
    return best, binary_scores(s >= best, t, ok)
