"""Plots shared by the change methods: height-change maps and volume time series (PNG, atomic)."""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np
from scipy import ndimage as ndi

from .building_layer import CLASSES as DAMAGE_CLASSES


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: os.PathLike | str, dpi: int = 130) -> Path:
    from ..io.atomic import atomic_path

    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, bbox_inches="tight", format="png")
    _plt().close(fig)
    return Path(path)


def hillshade(
    height_m: np.ndarray,
    posting_xy_m: tuple[float, float] = (1.0, 1.0),
    azimuth_deg: float = 315.0,
    altitude_deg: float = 45.0,
) -> np.ndarray:
    """Simple hillshade (0–1) for backdrops."""
    h = np.asarray(height_m, np.float64)
    gy, gx = np.gradient(np.where(np.isfinite(h), h, np.nanmean(h)), posting_xy_m[1], posting_xy_m[0])
    slope = np.pi / 2 - np.arctan(np.hypot(gx, gy))
    aspect = np.arctan2(-gx, gy)
    az, alt = np.radians(azimuth_deg), np.radians(altitude_deg)
    hs = np.sin(alt) * np.sin(slope) + np.cos(alt) * np.cos(slope) * np.cos(az - np.pi / 2 - aspect)
    return np.where(np.isfinite(h), np.clip(hs, 0, 1), np.nan)


def plot_dh_map(
    dz_m: np.ndarray,
    grid,
    path: os.PathLike | str,
    *,
    sign: np.ndarray | None = None,
    backdrop_m: np.ndarray | None = None,
    title: str = "",
    vmax: float | None = None,
    stable: np.ndarray | None = None,
    label: str = "Δh (m), B − A",
    cmap: str = "RdBu_r",
    note: str = "",
    backdrop_posting_xy_m: tuple[float, float] | None = None,
    changed_only: bool = False,
) -> Path:
    """Map of a height change (diverging colours centred on 0) with changed regions outlined.

    Parameters
    ----------
    dz_m : float (rows, cols)
    sign : optional int8 (+1 raised / −1 lowered; other values ignored) → outlines in black
        (raised: solid, lowered: dashed) on a thin white halo, visible on any colour
    backdrop_m : optional DEM drawn as a grey hillshade under the change (its metric cell size
        ``backdrop_posting_xy_m``, default the grid's posting)
    stable : optional bool mask drawn as a light hatch-free tint (stable terrain)
    vmax : colour limit (default: 98th percentile of |dz| over the coloured cells)
    changed_only : colour dz only where ``sign`` is ±1 (the rest: the grey backdrop, or light grey
        where observed), so the reported change, not the reconstruction noise at every height edge,
        carries the colour
    """
    from matplotlib import patheffects
    from matplotlib.lines import Line2D

    plt = _plt()
    fig, ax = plt.subplots(figsize=(6.8, 6.4))
    l, b, r, t = grid.bounds
    ext = (l, r, b, t)
    shown = np.asarray(dz_m, float)
    if changed_only and sign is not None:
        sg = np.asarray(sign)
        shown = np.where((sg == 1) | (sg == -1), shown, np.nan)
    fin = np.isfinite(shown)
    if vmax is None:
        vmax = float(np.nanpercentile(np.abs(shown[fin]), 98)) if fin.any() else 1.0
    vmax = max(float(vmax), 1e-3)
    if backdrop_m is not None:
        hs = hillshade(backdrop_m, backdrop_posting_xy_m or grid.posting)
        ax.imshow(
            hs, cmap="Greys_r", vmin=0, vmax=1, extent=ext, interpolation="nearest", alpha=0.6 if changed_only else 1.0
        )
    elif changed_only:
        ax.imshow(
            np.where(np.isfinite(dz_m), 0.85, np.nan),
            cmap="Greys_r",
            vmin=0,
            vmax=1,
            extent=ext,
            interpolation="nearest",
        )
    im = ax.imshow(
        np.ma.masked_invalid(shown),
        cmap=cmap,
        vmin=-vmax,
        vmax=vmax,
        extent=ext,
        interpolation="nearest",
        alpha=0.85 if (backdrop_m is not None and not changed_only) else 1.0,
    )
    fig.colorbar(im, ax=ax, shrink=0.8, label=label + (" (changed cells)" if changed_only else ""), extend="both")
    if stable is not None and np.any(stable):
        ax.contour(
            np.asarray(stable, float),
            levels=[0.5],
            colors="0.35",
            linewidths=0.4,
            linestyles=":",
            extent=(l, r, b, t),
            origin="upper",
        )
    if sign is not None:
        halo = [patheffects.withStroke(linewidth=2.2, foreground="white")]
        handles = []
        for s, style, name in ((1, "solid", "raised"), (-1, "dashed", "lowered")):
            m = np.asarray(sign) == s
            if m.any():
                cs = ax.contour(
                    m.astype(float),
                    levels=[0.5],
                    colors="black",
                    linewidths=0.9,
                    linestyles=style,
                    extent=(l, r, b, t),
                    origin="upper",
                )
                for coll in getattr(cs, "collections", [cs]):
                    coll.set_path_effects(halo)
                handles.append(Line2D([], [], color="black", lw=0.9, ls=style, label=f"{name} region"))
        if handles:
            ax.legend(handles=handles, loc="upper right", fontsize=7, framealpha=0.8)
    ax.set_title(title, fontsize=9)
    if note:
        ax.text(
            0.01,
            0.01,
            note,
            transform=ax.transAxes,
            fontsize=7,
            va="bottom",
            ha="left",
            bbox={"facecolor": "white", "alpha": 0.8, "edgecolor": "none"},
        )
    geographic = bool(getattr(grid.crs, "is_geographic", False))
    ax.set_xlabel("longitude (°)" if geographic else "easting (m)")
    ax.set_ylabel("latitude (°)" if geographic else "northing (m)")
    ax.ticklabel_format(useOffset=False, style="plain")
    return _save(fig, path)


#: the quick-look's class colours and labels, in the legend's order: the building layer's classes, and the
#: "demolished" of run folders written before the one building layer (a dark red beside "collapsed")
QUICKLOOK_CLASSES = {
    "collapsed": DAMAGE_CLASSES["collapsed"],
    "demolished": ("#a50f15", "demolished"),
    **DAMAGE_CLASSES,
}
#: classes drawn as outlines with a light fill under the changed ones (the rest: filled)
_QUIET_CLASSES = ("unchanged", "unobserved", "not examined")


@dataclass
class QuickLookView:
    """What one of the quick-look's first two panels shows.

    Attributes
    ----------
    image : float (rows, cols), NaN where not seen, optional
        A grey image of the epoch (e.g. an orthoimage of one of its views) covering the grid's bounds, on the
        grid or on a coarser grid of the same bounds; drawn with a 1–99 % stretch.
    surface_m : float (rows, cols) on the grid, NaN where no height, optional
        The epoch's surface; drawn as a hillshade when there is no image.
    label : str
        What the image is (e.g. ``"ortho of pre_event_img1"``); the panel's title says it after the epoch.
    """

    image: np.ndarray | None = None
    surface_m: np.ndarray | None = None
    label: str = ""


def _plain(text: str) -> str:
    """Text matplotlib draws as it is: a ``$`` would start mathtext (slow to parse, and not what was meant)."""
    return str(text).replace("$", r"\$")


def _stretch(a: np.ndarray) -> np.ndarray:
    """Linear 1–99 % stretch to 0–1 (NaN kept)."""
    a = np.asarray(a, np.float64)
    v = a[np.isfinite(a)]
    if not v.size:
        return a
    lo, hi = np.percentile(v, [1, 99])
    return np.clip((a - lo) / max(hi - lo, 1e-9), 0.0, 1.0)


def _view_grey(view: QuickLookView | None, posting_xy_m) -> tuple[np.ndarray | None, str]:
    """The grey array (0–1, NaN = no data) of a view and what it is."""
    if view is None:
        return None, "nothing to show"
    if view.image is not None:
        return _stretch(view.image), view.label or "image"
    if view.surface_m is not None:
        return hillshade(view.surface_m, posting_xy_m), "hillshade of its surface (DSM)"
    return None, "nothing to show"


def _polygon_path(geom):
    """A matplotlib Path of a (multi)polygon, holes included, or None when empty."""
    from matplotlib.path import Path as MPath

    verts, codes = [], []
    for poly in getattr(geom, "geoms", [geom]):
        if poly is None or poly.is_empty or not hasattr(poly, "exterior"):
            continue
        for ring in (poly.exterior, *poly.interiors):
            xy = np.asarray(ring.coords)[:, :2]
            if len(xy) < 3:
                continue
            verts.append(xy)
            codes.append(np.r_[MPath.MOVETO, np.full(len(xy) - 2, MPath.LINETO), MPath.CLOSEPOLY])
    if not verts:
        return None
    return MPath(np.concatenate(verts), np.concatenate(codes).astype(np.uint8))


def _scale_bar(ax, grid) -> None:
    """A scale bar of a round length (about a fifth of the panel) in the lower left corner (projected grids)."""
    if bool(getattr(grid.crs, "is_geographic", False)):
        return
    l, b, r, t = grid.bounds
    width = r - l
    raw = width / 5.0
    mag = 10 ** math.floor(math.log10(raw)) if raw > 0 else 1.0
    length = max(k * mag for k in (1, 2, 5) if k * mag <= raw) if raw >= mag else mag
    x0, y0 = l + 0.04 * width, b + 0.05 * (t - b)
    ax.plot([x0, x0 + length], [y0, y0], color="black", lw=3, solid_capstyle="butt")
    ax.plot([x0, x0 + length], [y0, y0], color="white", lw=1.2, solid_capstyle="butt")
    ax.text(
        x0 + length / 2,
        y0 + 0.015 * (t - b),
        f"{length:g} m",
        ha="center",
        va="bottom",
        fontsize=8,
        bbox={"facecolor": "white", "alpha": 0.7, "edgecolor": "none", "pad": 1},
    )


def change_quicklook_figure(
    grid,
    view_a: QuickLookView | None,
    view_b: QuickLookView | None,
    *,
    buildings=None,
    dz_m: np.ndarray | None = None,
    sign: np.ndarray | None = None,
    regions=None,
    epoch_a: str = "A",
    epoch_b: str = "B",
    confidence: float = 99.0,
    method: str = "self-consistency",
):
    """The quick-look of a change run: epoch A | epoch B | what changed, with a legend that counts it.

    Parameters
    ----------
    grid : AOIGrid
        The grid of every array (and the CRS of ``buildings``).
    view_a, view_b : QuickLookView or None
        What the first two panels show (an image of the epoch, else a hillshade of its surface).
    buildings : GeoDataFrame with a ``class`` column, optional
        The building layer: the third panel draws each building in its class's colour
        (:data:`QUICKLOOK_CLASSES`, i.e. :data:`geocd.change.dsm_buildings.DAMAGE_CLASSES` first) over epoch B,
        and the legend gives the count of each class.
    dz_m, sign : float and int8 (rows, cols), optional
        Without ``buildings``: the third panel colours Δz on the cells whose ``sign`` is ±1 (changed at
        ``confidence``), and the legend counts the raised and lowered regions: those of ``regions`` (the
        ``changes`` layer, :func:`geocd.change.regions.change_regions`: columns ``sign`` and ``area_m2``) when
        given, else the 8-connected parts of ``sign``.
    epoch_a, epoch_b, confidence, method : the title's words (confidence in percent)

    Returns
    -------
    figure : matplotlib Figure (three image axes; a colour bar axis too in the Δz case)
    counts : {legend entry: count}, as the legend writes them (building classes, or ``"raised regions"`` /
        ``"lowered regions"``)
    """
    from matplotlib.collections import PathCollection
    from matplotlib.colors import to_rgba
    from matplotlib.patches import Patch

    plt = _plt()
    l, b, r, t = grid.bounds
    ext = (l, r, b, t)
    aspect = (t - b) / max(r - l, 1e-9)
    panel_w = 5.4
    fig, axes = plt.subplots(
        1, 3, figsize=(3 * panel_w + 2.6, panel_w * min(max(aspect, 0.5), 1.6) + 1.2), layout="constrained"
    )
    posting = grid.posting
    greys = []
    for ax, view, epoch in ((axes[0], view_a, epoch_a), (axes[1], view_b, epoch_b)):
        grey, what = _view_grey(view, posting)
        greys.append(grey)
        cmap = plt.get_cmap("gray").with_extremes(bad="#fbe3c8")
        if grey is not None:
            ax.imshow(np.ma.masked_invalid(grey), cmap=cmap, vmin=0, vmax=1, extent=ext, interpolation="antialiased")
        else:
            ax.text(0.5, 0.5, "no image or surface", ha="center", va="center", transform=ax.transAxes)
        ax.set_title(_plain(f"{epoch}: {what}"), fontsize=10)
    ax = axes[2]
    back = greys[1] if greys[1] is not None else greys[0]
    if back is not None:
        ax.imshow(np.ma.masked_invalid(back), cmap="gray", vmin=-0.6, vmax=1.4, extent=ext, interpolation="antialiased")
    counts: dict[str, int] = {}
    handles = []
    if buildings is not None:
        cls = buildings["class"].astype(str)
        vc = cls.value_counts().to_dict()
        order = [c for c in QUICKLOOK_CLASSES if c in vc] + sorted(c for c in vc if c not in QUICKLOOK_CLASSES)
        # quiet classes first, so the changed buildings are drawn over them
        for c in sorted(order, key=lambda c: c not in _QUIET_CLASSES):
            colour, label = QUICKLOOK_CLASSES.get(c, ("#984ea3", c))
            paths = [p for p in (_polygon_path(g) for g in buildings.geometry[cls == c]) if p is not None]
            quiet = c in _QUIET_CLASSES
            style = {
                "facecolor": to_rgba(colour, 0.3 if quiet else 0.9),
                "edgecolor": "#303030" if quiet else "black",
                "linewidths": 0.5 if quiet else 0.7,
            }
            if paths:
                ax.add_collection(PathCollection(paths, **style))
        for c in order:
            colour, label = QUICKLOOK_CLASSES.get(c, ("#984ea3", c))
            counts[c] = int(vc[c])
            face = to_rgba(colour, 0.3 if c in _QUIET_CLASSES else 0.9)
            handles.append(Patch(facecolor=face, edgecolor="black", lw=0.5, label=_plain(f"{label}: {vc[c]}")))
        title = f"buildings by class ({len(buildings)}), over {epoch_b}"
        legend_title = f"building class at {confidence:g} %"
    else:
        title = f"height change of the cells changed at {confidence:g} %, over {epoch_b}"
        legend_title = f"changed at {confidence:g} %"
        if dz_m is not None and sign is not None:
            sg = np.asarray(sign)
            shown = np.where((sg == 1) | (sg == -1), np.asarray(dz_m, float), np.nan)
            fin = np.isfinite(shown)
            vmax = max(float(np.nanpercentile(np.abs(shown[fin]), 98)) if fin.any() else 1.0, 1e-3)
            cmap = plt.get_cmap("RdBu_r")
            im = ax.imshow(
                np.ma.masked_invalid(shown), cmap=cmap, vmin=-vmax, vmax=vmax, extent=ext, interpolation="nearest"
            )
            cax = ax.inset_axes([0.08, -0.075, 0.84, 0.035])
            cb = fig.colorbar(im, cax=cax, orientation="horizontal", extend="both")
            cb.set_label(_plain(f"height change (m), {epoch_b} − {epoch_a}, changed cells"), fontsize=9)
            eight = np.ones((3, 3), bool)
            for s, name, tone in ((1, "raised", 0.9), (-1, "lowered", 0.1)):
                m = sg == s
                if regions is not None:
                    mine = regions[regions["sign"] == s]
                    n, area = len(mine), float(mine["area_m2"].sum())
                else:
                    n = int(ndi.label(m, structure=eight)[1]) if m.any() else 0
                    area = float(m.sum()) * grid.cell_area_m2
                counts[f"{name} regions"] = n
                handles.append(
                    Patch(
                        facecolor=cmap(tone),
                        edgecolor="black",
                        lw=0.5,
                        label=f"{name}: {n} region{'s' if n != 1 else ''}, {area:,.0f} m²",
                    )
                )
    if handles:
        ax.legend(
            handles=handles,
            title=_plain(legend_title),
            loc="upper left",
            bbox_to_anchor=(1.02, 1.0),
            fontsize=9,
            title_fontsize=9,
            frameon=False,
        )
    else:
        ax.text(
            0.5,
            0.5,
            "no building" if buildings is not None else "no change",
            ha="center",
            va="center",
            transform=ax.transAxes,
            bbox={"facecolor": "white", "alpha": 0.8, "edgecolor": "none"},
        )
    ax.set_title(_plain(title), fontsize=10)
    for a in axes:
        a.set_xlim(l, r)
        a.set_ylim(b, t)
        a.set_aspect("equal")
        a.set_xticks([])
        a.set_yticks([])
    _scale_bar(axes[0], grid)
    fig.suptitle(
        _plain(f"{method}: {epoch_a} → {epoch_b}, change reported at {confidence:g} % confidence"),
        fontsize=12,
    )
    return fig, counts


def plot_change_quicklook(path: os.PathLike | str, grid, view_a, view_b, **kwargs) -> Path:
    """Write :func:`change_quicklook_figure` to a PNG (atomically); keyword arguments as that function's."""
    fig, _ = change_quicklook_figure(grid, view_a, view_b, **kwargs)
    return _save(fig, path, dpi=100)


def plot_volume_series(
    series: Sequence[dict[str, Any]],
    path: os.PathLike | str,
    *,
    title: str = "",
    ylabel: str = "volume (10⁶ m³)",
    scale: float = 1e-6,
    reference: Sequence[dict[str, Any]] = (),
    bars: Sequence[dict[str, Any]] = (),
) -> Path:
    """Volume (or any quantity) vs date with 1σ error bars, for one or more series.

    Parameters
    ----------
    series : list of {"label": str, "dates": [date], "values": [float], "sigmas": [float], "style": "o-" (optional)}
    reference : optional published points, same keys (drawn as black markers)
    bars : optional per-interval quantities, same keys plus "dates_a": drawn as steps on a second axis
    scale : multiply values and σ by this for display (default m³ → 10⁶ m³)
    """
    plt = _plt()
    fig, ax = plt.subplots(figsize=(8, 4.8))
    for sdef in series:
        d = list(sdef["dates"])
        v = np.asarray(sdef["values"], float) * scale
        s = np.asarray(sdef.get("sigmas", np.full(len(d), np.nan)), float) * scale
        ax.errorbar(
            d,
            v,
            yerr=np.where(np.isfinite(s), s, 0.0),
            fmt=sdef.get("style", "o-"),
            ms=4,
            capsize=2.5,
            lw=1.2,
            label=sdef["label"],
        )
    for rdef in reference:
        d = list(rdef["dates"])
        v = np.asarray(rdef["values"], float) * scale
        s = np.asarray(rdef.get("sigmas", np.full(len(d), np.nan)), float) * scale
        ax.errorbar(
            d,
            v,
            yerr=np.where(np.isfinite(s), s, 0.0),
            fmt=rdef.get("style", "ks"),
            ms=5,
            capsize=2.5,
            mfc="none",
            label=rdef["label"],
        )
    if bars:
        ax2 = ax.twinx()
        for bdef in bars:
            da, db = list(bdef["dates_a"]), list(bdef["dates"])
            v = np.asarray(bdef["values"], float) * scale
            for k, (x0, x1) in enumerate(zip(da, db)):
                ax2.fill_between(
                    [x0, x1],
                    [0, 0],
                    [v[k], v[k]],
                    step="pre",
                    color="0.8",
                    alpha=0.6,
                    lw=0,
                    label=bdef["label"] if k == 0 else None,
                )
        ax2.set_ylabel(bars[0].get("ylabel", "per interval (10⁶ m³)"))
        ax2.set_zorder(ax.get_zorder() - 1)
        ax.patch.set_visible(False)
        h2, l2 = ax2.get_legend_handles_labels()
    else:
        h2, l2 = [], []
    h1, l1 = ax.get_legend_handles_labels()
    ax.legend(h1 + h2, l1 + l2, loc="upper left", fontsize=8)
    ax.set_ylabel(ylabel)
    ax.set_title(title, fontsize=10)
    ax.grid(alpha=0.3)
    fig.autofmt_xdate()
    return _save(fig, path)


#: colours of the significance curves, by confidence (percent, as the model's curve keys write it)
CURVE_COLOURS = {"68.27": "#2c7bb6", "90": "#1a9641", "95": "#fdae61", "99": "#d7191c"}
#: colours for curves of other levels, taken in turn (none is in CURVE_COLOURS)
SPARE_CURVE_COLOURS = ("#7b3294", "#e66101", "#01665e", "#c51b7d", "#8c510a", "#4d4d4d")


def curve_colours(keys: Sequence[str]) -> dict[str, str]:
    """A distinct colour for each significance curve (``"68.27"``, ``"90"``...), the usual levels fixed."""
    out = {k: CURVE_COLOURS[k] for k in keys if k in CURVE_COLOURS}
    spare = iter(c for c in SPARE_CURVE_COLOURS if c not in out.values())
    for k in sorted(keys, key=float):
        if k not in out:
            out[k] = next(spare, None) or f"C{len(out) % 10}"
    return out


def scatter_curves_figure(model, title: str = "Self-consistency distribution"):
    """The figure of :func:`plot_scatter_curves` (matplotlib Figure, one Axes then its colour bar)."""
    from matplotlib.colors import LogNorm
    from matplotlib.lines import Line2D

    from ..consistency import DTILDE_EDGES

    plt = _plt()
    fig, ax = plt.subplots(figsize=(7, 4.8))
    e = model.score_edges
    d = DTILDE_EDGES.copy()
    d[0] = 1e-3
    h = model.hist.astype(float)
    # density per score bin (bins have equal counts by construction, except thin tails)
    h = h / np.maximum(h.sum(axis=1, keepdims=True), 1)
    m = ax.pcolormesh(
        e, d, np.ma.masked_equal(h.T, 0), norm=LogNorm(vmin=1e-4, vmax=h.max()), cmap="Greys", shading="flat"
    )
    fig.colorbar(m, ax=ax, label="fraction of match pairs in score bin")
    colours = curve_colours(list(model.curves))
    x = model.score_centres
    handles = []
    for k in sorted(model.curves, key=float):
        c = colours[k]
        ax.plot(x, model.curves[k], "-", color=c, lw=2, gid=f"curve {k}")
        raw = k in model.raw_curves
        if raw:
            ax.plot(x, model.raw_curves[k], "o", color=c, ms=3.5, mec="white", mew=0.4, gid=f"bins {k}")
        # the legend shows the curve as drawn: its smoothed line, its per-bin values as dots of its colour
        handles.append(
            Line2D(
                [], [], color=c, lw=2, marker="o" if raw else None, ms=3.5, mec="white", mew=0.4, label=f"{k}% curve"
            )
        )
    ax.set_yscale("log")
    ax.set_ylim(1e-2, max(10.0, np.nanmax([np.nanmax(v) for v in model.curves.values()]) * 2))
    ax.set_xlabel("max MDL score of the two matches (bits/pixel, lower = better)")
    ax.set_ylabel("|Δ̃| (pixels of disparity)")
    n = int(model.bin_counts.sum())
    ax.set_title(f"{title} ({n:,} match pairs)")
    ax.legend(handles=handles, loc="upper left")
    return fig


def plot_scatter_curves(model, path: os.PathLike | str, title: str = "Self-consistency distribution") -> Path:
    """The score × |Δ̃| 2-D histogram with the significance curves (as the SRI paper's figures): one colour per
    confidence level, its smoothed curve a line, its per-bin values dots of the same colour."""
    return _save(scatter_curves_figure(model, title), path)
