"""Plots of the self-consistency method (to merge into geocd.change.plots)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path) -> Path:
    from ..io.atomic import atomic_path

    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=130, bbox_inches="tight", format="png")
    _plt().close(fig)
    return Path(path)


def plot_scatter_curves(model, path: os.PathLike | str, title: str = "Self-consistency distribution") -> Path:
    """The score × |Δ̃| 2-D histogram with the significance curves (as the SRI paper's figures)."""
    from matplotlib.colors import LogNorm

    from ..consistency import DTILDE_EDGES

    plt = _plt()
    fig, ax = plt.subplots(figsize=(7, 4.8))
    e = model.score_edges
    d = DTILDE_EDGES.copy()
    d[0] = 1e-3
    h = model.hist.astype(float)
    # density per score bin (bins have equal counts by construction, except thin tails)
    h = h / np.maximum(h.sum(axis=1, keepdims=True), 1)
    m = ax.pcolormesh(e, d, np.ma.masked_equal(h.T, 0), norm=LogNorm(vmin=1e-4, vmax=h.max()), cmap="Greys", shading="flat")
    fig.colorbar(m, ax=ax, label="fraction of match pairs in score bin")
    colours = {"90": "#1a9641", "95": "#fdae61", "99": "#d7191c"}
    x = model.score_centres
    for k in sorted(model.curves, key=float):
        c = colours.get(k, None)
        ax.plot(x, model.curves[k], "-", color=c, lw=2, label=f"{k}% curve")
        if k in model.raw_curves:
            ax.plot(x, model.raw_curves[k], ".", color=c, ms=4)
    ax.set_yscale("log")
    ax.set_ylim(1e-2, max(10.0, np.nanmax([np.nanmax(v) for v in model.curves.values()]) * 2))
    ax.set_xlabel("max MDL score of the two matches (bits/pixel, lower = better)")
    ax.set_ylabel("|Δ̃| (pixels of disparity)")
    n = int(model.bin_counts.sum())
    ax.set_title(f"{title} ({n:,} match pairs)")
    ax.legend(loc="upper left")
    return _save(fig, path)


def plot_change_quicklook(dz_m: np.ndarray, sign: np.ndarray, grid, path: os.PathLike | str, title: str = "",
                          vmax: float | None = None) -> Path:
    """Δz map (diverging colours) with changed cells outlined."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6.5, 6))
    l, b, r, t = grid.bounds
    v = vmax or float(np.nanpercentile(np.abs(dz_m), 99)) if np.isfinite(dz_m).any() else 1.0
    v = max(v, 1.0)
    im = ax.imshow(dz_m, cmap="RdBu_r", vmin=-v, vmax=v, extent=(l, r, b, t), interpolation="nearest")
    fig.colorbar(im, ax=ax, shrink=0.8, label="Δz (m), B − A")
    if np.any(sign != 0):
        ax.contour(np.where(sign > 0, 1.0, 0.0), levels=[0.5], colors="darkred", linewidths=0.8,
                   extent=(l, r, t, b), origin="upper")
        ax.contour(np.where(sign < 0, 1.0, 0.0), levels=[0.5], colors="navy", linewidths=0.8,
                   extent=(l, r, t, b), origin="upper")
    ax.set_title(title, fontsize=9)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.ticklabel_format(useOffset=False, style="plain")
    return _save(fig, path)
