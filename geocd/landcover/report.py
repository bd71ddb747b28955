"""The thesis's ablation as a report: what each data source adds, scored against a truth map.

Scores follow the thesis (ch. 6.3.2): precision–recall curves and F1 at recall
0.5, for the coarse image alone (every cell), the detailed views alone (the
cells they observe), and GP integrations with growing input sets (every cell,
and the unobserved cells separately: the cells only the GP can fill). The
calibration of the GP's σ is the fraction of truth values inside ±1σ / ±2σ of
the predictive mean on the unobserved cells (68 % / 95 % for a calibrated
Gaussian).
"""

from __future__ import annotations

import numpy as np

from ..errors import EmptyDataError
from .gp import GPParams, GPResult, integrate

#: the thesis's ablation: input sets of the GP (names of :data:`geocd.landcover.pipeline.INPUTS`), and the
#: kernel (None: the one in the GP parameters)
ABLATION = {
    "GP: detailed + xy": (("xy",), None),
    "GP: detailed + coarse + xy": (("xy", "coarse"), None),
    "GP, thesis product kernel: detailed + coarse + xy + DEM + buildings": (
        ("xy", "coarse", "dem", "buildings"),
        "product",
    ),
    "GP: detailed + coarse + xy + DEM + buildings": (("xy", "coarse", "dem", "buildings"), None),
}


def f1_at_recall(truth: np.ndarray, score: np.ndarray, recall: float = 0.5) -> dict:
    """Interpolated precision at ``recall`` (best precision among thresholds reaching it), its F1, and the
    average precision; ``truth`` boolean, ``score`` any monotone score (NaN cells dropped)."""
    from sklearn.metrics import average_precision_score, precision_recall_curve

    t = np.asarray(truth, bool).ravel()
    s = np.asarray(score, np.float64).ravel()
    ok = np.isfinite(s)
    t, s = t[ok], s[ok]
    if t.size == 0 or t.all() or not t.any():
        return {"cells": int(t.size), "note": "needs cells of both classes"}
    p, r, _ = precision_recall_curve(t, s)
    prec = float(np.max(p[r >= recall]))
    return {
        "precision_at_recall": round(prec, 4),
        "f1_at_recall": round(2 * prec * recall / (prec + recall), 4),
        "average_precision": round(float(average_precision_score(t, s)), 4),
        "cells": int(t.size),
        "positive_rate": round(float(t.mean()), 4),
    }


def sigma_calibration(truth: np.ndarray, res: GPResult, cells: np.ndarray) -> dict:
    """Fraction of ``truth`` (e.g. a vegetated fraction per cell) within ±1σ / ±2σ of the GP mean on ``cells``."""
    ok = cells & np.isfinite(res.mean) & np.isfinite(truth)
    if not ok.any():
        return {"cells": 0}
    err = np.abs(truth[ok] - res.mean[ok])
    out: dict = {"cells": int(ok.sum()), "rmse": round(float(np.sqrt(np.mean(err**2))), 4)}
    sds = [("sigma", res.sd[ok]), ("sigma_obs", res.sd_obs[ok])]
    if res.sd_cal is not None:
        sds.append(("sigma_calibrated", res.sd_cal[ok]))
    for name, sd in sds:
        out[name] = {
            "inside_1sigma": round(float(np.mean(err <= sd)), 4),
            "inside_2sigma": round(float(np.mean(err <= 2 * sd)), 4),
            "median": round(float(np.median(sd)), 4),
        }
    return out


def ablation(
    detailed: np.ndarray,
    coarse: np.ndarray | None,
    inputs_for,
    truth: np.ndarray,
    truth_value: np.ndarray | None = None,
    exclude: np.ndarray | None = None,
    params: GPParams = GPParams(),
    configs: dict | None = None,
) -> tuple[dict, dict]:
    """Run the ablation.

    Parameters
    ----------
    detailed : float (rows, cols), the detailed views' probability (NaN = unobserved)
    coarse : float (rows, cols) or None, the coarse full-cover probability
    inputs_for : callable(tuple of input names) → dict of GP input arrays
    configs : mapping name → (input names, kernel or None); default :data:`ABLATION`
    truth : bool (rows, cols), the condition; ``truth_value`` float (rows, cols), optional, the
        continuous truth for the σ calibration (default: ``truth`` as 0/1)
    exclude : bool (rows, cols), optional, cells never scored (e.g. training labels)

    Returns
    -------
    scores : dict, results : dict name → GPResult
    """
    t = np.asarray(truth, bool)
    ev = np.ones(t.shape, bool) if exclude is None else ~np.asarray(exclude, bool)
    obs = np.isfinite(detailed)
    if not (obs & ev).any():
        raise EmptyDataError("the detailed views observe no scored cell")
    scores: dict = {"observed_fraction": round(float(obs.mean()), 4)}
    if coarse is not None:
        scores["coarse alone (all cells)"] = f1_at_recall(t[ev], coarse[ev])
        if (ev & ~obs).any():
            scores["coarse alone (unobserved cells)"] = f1_at_recall(t[ev & ~obs], coarse[ev & ~obs])
    scores["detailed alone (observed cells)"] = f1_at_recall(t[ev & obs], detailed[ev & obs])
    configs = (
        configs
        if configs is not None
        else {k: v for k, v in ABLATION.items() if coarse is not None or "coarse" not in v[0]}
    )
    results: dict = {}
    for name, (use, kernel) in configs.items():
        p = params if kernel is None else params.replace(kernel=kernel)
        res = integrate(detailed, inputs_for(use), p)
        results[name] = res
        scores[f"{name} (all cells)"] = f1_at_recall(t[ev], res.mean[ev])
        if (ev & ~obs).any():
            scores[f"{name} (unobserved cells)"] = f1_at_recall(t[ev & ~obs], res.mean[ev & ~obs])
    last = results[list(configs)[-1]]
    tv = t.astype(np.float64) if truth_value is None else np.asarray(truth_value, np.float64)
    scores["sigma_calibration_unobserved"] = sigma_calibration(tv, last, ev & ~obs)
    scores["hyperparameters"] = {n: r.hyper.to_dict() for n, r in results.items()}
    return scores, results


def pr_figure(path, curves: dict, scores: dict, title: str = "") -> None:
    """PR curves and F1 at recall 0.5 (bars) — the thesis's figure 6.13 layout."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from sklearn.metrics import precision_recall_curve

    fig, ax = plt.subplots(1, 2, figsize=(13, 5.5), gridspec_kw={"width_ratios": [1, 1.3]})
    for name, (y, s) in curves.items():
        ok = np.isfinite(s)
        if ok.sum() and y[ok].any() and not y[ok].all():
            p, r, _ = precision_recall_curve(y[ok], s[ok])
            ax[0].plot(r, p, label=name)
    ax[0].axvline(0.5, color="k", lw=0.5, ls=":")
    ax[0].set_xlabel("recall")
    ax[0].set_ylabel("precision")
    ax[0].set_title(title, fontsize=8, wrap=True)
    ax[0].legend(fontsize=7, loc="lower left")
    names = [n for n, v in scores.items() if isinstance(v, dict) and "f1_at_recall" in v]
    ap = [scores[n]["average_precision"] for n in names]
    ax[1].barh(range(len(names)), ap, color="tab:green")
    for i, n in enumerate(names):
        ax[1].text(ap[i], i, f" AP {ap[i]:.3f} · F1@R.5 {scores[n]['f1_at_recall']:.3f}", va="center", fontsize=7)
    ax[1].set_yticks(range(len(names)))
    ax[1].set_yticklabels([n.replace(" (", "\n(") for n in names], fontsize=6)
    ax[1].invert_yaxis()
    ax[1].set_xlabel("average precision (label: AP and F1 at recall 0.5)")
    ax[1].set_xlim(max(0.0, min(ap) - 0.05) if ap else 0, 1.08)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)
