"""Self-consistency significance test (Leclerc, Luong & Fua; Heller, Leclerc & Luong, SRI).

Stage 1 learns, from reconstructions of a *static* scene, how much two
reconstructions of the same surface disagree as a function of the match score;
stage 2 calls a cross-epoch difference a change only where it exceeds that
disagreement at a chosen confidence.

Quantities (per grid cell, for two pair-DEMs p and q on the same grid):

* normalized difference ``Δ̃ = (z_q − z_p) / sqrt(g_p⁻² + g_q⁻²)`` where ``g`` is
  the pair's disparity per metre of height (px/m) — one unit of Δ̃ is one pixel
  of disparity;
* score ``max(s_p, s_q)`` (MDL score, lower = better match).

The learned :class:`SelfConsistencyModel` keeps the full 2-D histogram
(score × |Δ̃|, log-spaced |Δ̃| bins), so curves for any confidence can be
recomputed from a saved model; curves are made non-decreasing in score
(isotonic regression weighted by bin counts) and thin bins are merged.

**Vertical alignment.** RPC biases that the matcher's pointing correction cannot
see (their along-epipolar part) shift each pair-DEM vertically by a constant:
metres between the pairs of the real Pléiades triplet, i.e. most of a pixel of
disparity. Before comparing, every reconstruction is therefore shifted by the
median height difference to a reference over their common, well-matched cells
(``align="vertical"``, the default; the median ignores a minority of changed
cells). The reference is the given DEM when an epoch is a DEM; else every pair of
reconstructions is compared and the offsets are their least-squares fit (zero
mean), so results do not depend on the order in which reconstructions are given. This also removes a real, uniform change of
the whole AOI (e.g. subsidence); use ``align="none"`` where that matters.

A DEM standing for an epoch (LiDAR, last year's product) is a "pair-DEM" with
``g = ∞`` (no disparity error) and no score: Δ̃ then carries only the stereo
side's uncertainty. This is an approximation — it treats the given DEM as exact
— and is documented as such in the products.
"""

from __future__ import annotations

import datetime as _dt
import itertools
import json
import os
import warnings
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Iterable, Protocol, Sequence

import numpy as np

from .errors import ConfigError, GridError, ProcessingError
from .progress import Progress, ensure_progress
from .stereo.surface import nanmedian_stack

ALIGN_MODES = ("vertical", "none")

#: log-spaced |Δ̃| histogram edges (pixels of disparity) used for every model
DTILDE_EDGES = np.concatenate([[0.0], np.logspace(-3, 3, 241)])


class PairDEMLike(Protocol):
    """What the consistency test needs from a reconstruction (see geocd.stereo.PairDEM)."""

    z_m: np.ndarray
    score: np.ndarray
    g_px_per_m: np.ndarray
    valid: np.ndarray
    grid: Any
    name: str


@dataclass
class DEMAsEpoch:
    """A given DEM used as one epoch's reconstruction (g = ∞: treated as exact).

    Its score is NaN; in a match pair the stereo side's score is used.
    """

    z_m: np.ndarray
    grid: Any
    name: str = "dem"

    @property
    def valid(self) -> np.ndarray:
        return np.isfinite(self.z_m)

    @property
    def g_px_per_m(self) -> np.ndarray:
        return np.full(self.z_m.shape, np.inf, dtype=np.float32)

    @property
    def score(self) -> np.ndarray:
        return np.full(self.z_m.shape, np.nan, dtype=np.float32)


@dataclass(frozen=True)
class ConsistencyParams:
    """Parameters of stage 1.

    Attributes
    ----------
    confidences : tuple of float
        Confidence levels (percent) for which curves are extracted.
    n_score_bins : int
        Number of equal-count score bins (fewer when data are thin).
    min_bin_count : int
        Minimum match pairs per score bin; thinner bins are merged.
    align : {"vertical", "none"}
        Remove each reconstruction's constant vertical offset, fitted to all pairwise offsets
        within the group (see the module notes).
    cluster_confidence : float
        Cells changed at this per-cell level (percent) form the candidate regions whose combined
        evidence the region test weighs (docs/self_consistency.md: 95 % chosen among 90/95/99 on
        three towns, checked on a fourth).
    min_region_cells : int, optional
        Minimum mapping unit in grid cells. None: derived from the reconstructions — the
        ground footprint of one matching window (window² cells at the grid posting), the area
        over which one height measurement averages; 1 when no reconstruction says its window.
    """

    confidences: tuple[float, ...] = (90.0, 95.0, 99.0)
    n_score_bins: int = 24
    min_bin_count: int = 200
    align: str = "vertical"
    cluster_confidence: float = 95.0
    min_region_cells: int | None = None

    def __post_init__(self) -> None:
        if self.align not in ALIGN_MODES:
            raise ConfigError(f"align must be one of {ALIGN_MODES}, got {self.align!r}")
        if not 0 < self.cluster_confidence < 100:
            raise ConfigError(f"cluster_confidence is a percentage in (0, 100), got {self.cluster_confidence}")
        if self.min_region_cells is not None and self.min_region_cells < 1:
            raise ConfigError(f"min_region_cells must be ≥ 1 (or None: derived), got {self.min_region_cells}")


def window_cells(recs: Iterable[PairDEMLike]) -> int:
    """Grid cells covered by the largest matching window among the reconstructions (1 if none says).

    A pair-DEM's height at a cell is measured from a window of ``window`` × ``window`` pixels;
    geocd's grid posting is the images' ground sampling distance by default, so one measurement
    averages over about window² cells — the smallest area a change can be told apart from
    a matching error (the minimum mapping unit).
    """
    w = 1
    for r in recs:
        meta = getattr(r, "meta", None) or {}
        win = (meta.get("params") or {}).get("window") if isinstance(meta, dict) else None
        if win:
            w = max(w, int(win))
    return w * w


def match_pairs(p: PairDEMLike, q: PairDEMLike) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Common-xy match pairs of two reconstructions on the same grid.

    Returns
    -------
    dtilde : float32 (rows, cols)
        (z_q − z_p) / sqrt(g_p⁻² + g_q⁻²), pixels of disparity (NaN where not both valid).
    score : float32 (rows, cols)
        max(s_p, s_q) (the finite one when a side has no score).
    dz_m : float32 (rows, cols)
        z_q − z_p, metres.
    both : bool (rows, cols)
        Cells valid in both.
    """
    if p.z_m.shape != q.z_m.shape:
        raise GridError(
            f"reconstructions {p.name!r} {p.z_m.shape} and {q.name!r} {q.z_m.shape} are on different grids; "
            "resample them onto one AOI grid first"
        )
    if getattr(p, "grid", None) is not None and getattr(q, "grid", None) is not None:
        if hasattr(p.grid, "same_as") and not p.grid.same_as(q.grid):
            raise GridError(
                f"reconstructions {p.name!r} and {q.name!r} are not on the same AOI grid; "
                "resample one onto the other (geocd.io.raster.reproject_array)"
            )
    gp = np.asarray(p.g_px_per_m, np.float64)
    gq = np.asarray(q.g_px_per_m, np.float64)
    both = np.asarray(p.valid, bool) & np.asarray(q.valid, bool) & np.isfinite(p.z_m) & np.isfinite(q.z_m)
    both &= (gp > 0) & (gq > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = np.sqrt(1.0 / gp**2 + 1.0 / gq**2)
        dz = np.asarray(q.z_m, np.float64) - np.asarray(p.z_m, np.float64)
        dt = dz / denom
    both &= np.isfinite(dt)
    sp = np.asarray(p.score, np.float64)
    sq = np.asarray(q.score, np.float64)
    score = np.fmax(sp, sq)  # fmax ignores a NaN side (a DEM standing for an epoch)
    both &= np.isfinite(score)
    dt = np.where(both, dt, np.nan).astype(np.float32)
    return dt, np.where(both, score, np.nan).astype(np.float32), np.where(both, dz, np.nan).astype(np.float32), both


class _Shifted:
    """A reconstruction seen through a constant vertical shift (nothing copied but z)."""

    def __init__(self, rec: PairDEMLike, offset_m: float):
        self._rec = rec
        self.offset_m = float(offset_m)
        self.z_m = (np.asarray(rec.z_m, np.float32) - np.float32(offset_m)).astype(np.float32)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._rec, name)


def vertical_offset(rec: PairDEMLike, ref: PairDEMLike, min_cells: int = 100) -> float:
    """Median z_rec − z_ref over common valid cells, the better-scored half of them when scores exist.

    Returns 0 when the two share fewer than ``min_cells`` cells.
    """
    both = np.asarray(rec.valid, bool) & np.asarray(ref.valid, bool) & np.isfinite(rec.z_m) & np.isfinite(ref.z_m)
    if both.sum() < min_cells:
        return 0.0
    dz = (np.asarray(rec.z_m, np.float64) - np.asarray(ref.z_m, np.float64))[both]
    sc = np.fmax(np.asarray(rec.score, np.float64), np.asarray(ref.score, np.float64))[both]
    if np.isfinite(sc).sum() >= 2 * min_cells:
        good = np.isfinite(sc) & (sc <= np.nanmedian(sc))
        dz = dz[good]
    return float(np.median(dz))


def vertical_offsets(
    recs: Sequence[PairDEMLike], reference: PairDEMLike | None = None, mode: str = "vertical"
) -> dict[str, float]:
    """Each reconstruction's constant vertical offset to a common reference (a whole-scene statistic).

    Parameters
    ----------
    recs : reconstructions on one grid (their order does not matter)
    reference : optional reconstruction to align to; default: a :class:`DEMAsEpoch` among
        ``recs`` if any (a DEM is the absolute reference), else all of them: each offset is the
        least-squares fit of the pairwise offsets (:func:`vertical_offset` of every pair), i.e.
        the mean of its offsets to the others, and the offsets sum to zero. The result depends
        only on the set of reconstructions, not on their order.
    mode : "vertical" or "none" (all offsets 0)

    Returns
    -------
    {name: offset (m) to subtract from its heights}
    """
    if mode not in ALIGN_MODES:
        raise ConfigError(f"align must be one of {ALIGN_MODES}, got {mode!r}")
    recs = list(recs)
    names = [r.name for r in recs]
    if len(set(names)) != len(names):
        raise ConfigError(f"reconstructions must have distinct names to be aligned, got {names}")
    if mode == "none" or len(recs) < 2:
        return {r.name: 0.0 for r in recs}
    if reference is None:
        dems = sorted((r for r in recs if isinstance(r, DEMAsEpoch)), key=lambda r: r.name)
        reference = dems[0] if dems else None
    if reference is not None:
        return {r.name: (0.0 if r is reference else vertical_offset(r, reference)) for r in recs}
    # least squares on all pairwise offsets: o_r − o_q = d(r, q) ⇒ o_r = mean_q d(r, q) (zero mean);
    # d is antisymmetric and the sums run in name order, so the result is exactly order-free
    recs = sorted(recs, key=lambda r: r.name)
    n = len(recs)
    d = np.zeros((n, n))
    for i, j in itertools.combinations(range(n), 2):
        d[i, j] = vertical_offset(recs[i], recs[j])
        d[j, i] = -d[i, j]
    return {r.name: float(np.sum(d[i]) / n) for i, r in enumerate(recs)}


def apply_offsets(recs: Sequence[PairDEMLike], offsets: dict[str, float]) -> list:
    """The reconstructions seen through their vertical offsets (per-cell work; nothing copied but z)."""
    out = []
    for r in recs:
        if r.name not in offsets:
            raise ConfigError(f"no vertical offset for reconstruction {r.name!r}; known: {sorted(offsets)}")
        off = float(offsets[r.name])
        out.append(r if off == 0.0 else _Shifted(r, off))
    return out


def align_reconstructions(
    recs: Sequence[PairDEMLike], reference: PairDEMLike | None = None, mode: str = "vertical"
) -> tuple[list, dict[str, float]]:
    """Shift reconstructions onto a common vertical reference (see :func:`vertical_offsets`).

    Returns
    -------
    aligned : list of reconstructions (same order), offsets : {name: offset removed, m}
    """
    offsets = vertical_offsets(recs, reference, mode)
    return apply_offsets(recs, offsets), offsets


# ----------------------------------------------------------------------------------------
# Transfer calibration: a scene-class model made to fit the data it is applied to
# ----------------------------------------------------------------------------------------
CALIBRATION_MODES = ("auto", "pair", "none")

#: bins of the local slope (dimensionless, |∇z|) in which the calibration compares medians
_SLOPE_EDGES = np.array([0.0, 0.1, 0.2, 0.35, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0, 5.0, 8.0, np.inf])


def local_slope(z_m: np.ndarray, posting_m: float) -> np.ndarray:
    """|∇z| (m per m) from the one-sided differences that exist (NaN-tolerant); 0 where no neighbour is valid.

    Per axis the slope is the mean of the backward and forward differences available at the cell,
    so a cell beside a gap (an occlusion, often at a building edge) still gets its slope.
    """
    z = np.asarray(z_m, np.float64)
    comps = []
    for ax in (0, 1):
        d = np.diff(z, axis=ax) / float(posting_m)
        pad = [(0, 0), (0, 0)]
        pad[ax] = (1, 0)
        back = np.pad(d, pad, constant_values=np.nan)
        pad[ax] = (0, 1)
        fwd = np.pad(d, pad, constant_values=np.nan)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            comps.append(np.nanmean(np.stack([back, fwd]), axis=0))
    return np.nan_to_num(np.hypot(*comps), nan=0.0)


@dataclass(frozen=True)
class PairCalibration:
    """How much more (or less) the tested reconstructions disagree than the scene-class model says.

    A model learned on one scene (e.g. the Marseille Pléiades triplet) is applied to another pair of
    epochs; the two can differ in how well they match (other images, B/H, sun, season). The
    calibration keeps the model's *shape* — its |Δ̃| distribution per score bin — and fits its
    *scale* to the data under test, plus the misregistration term of steep cells:

    ``m_tot(score, slope) = sqrt((scale · m50(score))² + (slope · edge_sigma_m / mpu)²)``

    where ``m50`` is the model's median |Δ̃| at the score, ``slope`` the larger local |∇z| of the two
    reconstructions, ``mpu`` the metres per unit of Δ̃ and ``edge_sigma_m`` the horizontal
    disagreement of the two surfaces (metres; a surface shifted by δ differs by |∇z|·δ). The
    test then reads the model at ``Δ̃ · m50 / m_tot``.

    Attributes
    ----------
    scale : float
        The data's median disagreement over the model's at the same score (1: the model fits).
    edge_sigma_m : float
        Median-equivalent horizontal disagreement of the two epochs' surfaces (m).
    n_cells : int
        Observed cells the fit used (after trimming the cells the first fit calls changed).
    n_bins : int
        (score × slope) bins with enough cells.
    trimmed_fraction : float
        Share of the observed cells left out of the second fit (p < 0.01 under the first).
    ref_scale, ref_edge_sigma_m : float
        The same law fitted to the model's own static comparisons when it was learned
        (:attr:`SelfConsistencyModel.reference_law`; 1 and 0 for models saved without it). The
        inflation is relative to it, so a model applied to data like its own is left as it is.
    """

    scale: float
    edge_sigma_m: float
    n_cells: int = 0
    n_bins: int = 0
    trimmed_fraction: float = 0.0
    ref_scale: float = 1.0
    ref_edge_sigma_m: float = 0.0

    def to_dict(self) -> dict:
        return {k: (round(v, 4) if isinstance(v, float) else v) for k, v in asdict(self).items()}

    def inflation(
        self, model: "SelfConsistencyModel", score: np.ndarray, slope: np.ndarray, metres_per_unit: np.ndarray
    ) -> np.ndarray:
        """m_tot / m_ref per cell: how much wider the static disagreement is here than where the model was learned."""
        m50 = model.threshold(score, 50.0)
        g = np.asarray(slope, np.float64) / metres_per_unit
        with np.errstate(divide="ignore", invalid="ignore"):
            mtot = np.sqrt((self.scale * m50) ** 2 + (g * self.edge_sigma_m) ** 2)
            mref = np.sqrt((self.ref_scale * m50) ** 2 + (g * self.ref_edge_sigma_m) ** 2)
            return np.where((mref > 0) & np.isfinite(mtot), mtot / mref, self.scale / self.ref_scale)

    def effective_dtilde(
        self,
        model: "SelfConsistencyModel",
        dtilde: np.ndarray,
        score: np.ndarray,
        slope: np.ndarray,
        metres_per_unit: np.ndarray,
    ) -> np.ndarray:
        """Δ̃ rescaled onto the model's own scale: Δ̃ · m50 / m_tot (see the class notes)."""
        return np.asarray(dtilde, np.float64) / self.inflation(model, score, slope, metres_per_unit)


def fit_pair_calibration(
    model: "SelfConsistencyModel",
    dtilde: np.ndarray,
    score: np.ndarray,
    slope: np.ndarray,
    metres_per_unit: np.ndarray,
    min_bin_cells: int = 200,
    max_cells: int = 2_000_000,
    fit_edge: bool = True,
    reference: bool = True,
) -> PairCalibration:
    """Fit :class:`PairCalibration` to cross-epoch comparisons, tolerant of a changed minority.

    In bins of (the model's score bins × local slope) the median |Δ̃| of the data is compared with
    the calibrated model's median; ``scale`` and ``edge_sigma_m`` minimise the (soft-L1, count-weighted)
    log ratio. Medians ignore a changed minority, and the fit is repeated once without the cells the
    first fit calls changed at 99 % (p < 0.01): what is left is the static majority. A changed
    majority would be read as disagreement (a conservative bias: fewer cells flagged).

    Parameters
    ----------
    model : the scene-class model
    dtilde, score, slope, metres_per_unit : 1-D float arrays of the observed cells (all comparisons pooled)
    min_bin_cells : bins with fewer cells are ignored
    max_cells : a deterministic subsample beyond this many cells (every k-th)
    fit_edge : False: the scale alone (``edge_sigma_m`` = 0), e.g. when no slope is known
    reference : relative to the model's :attr:`~SelfConsistencyModel.reference_law` (False: to the
        bare model, scale 1 and no slope term — how the reference law itself is fitted)

    Raises
    ------
    ProcessingError
        When fewer than two bins hold enough cells (too little data to calibrate).
    """
    from scipy.optimize import least_squares

    a = np.abs(np.asarray(dtilde, np.float64))
    sc = np.asarray(score, np.float64)
    g = np.asarray(slope, np.float64)
    mpu = np.asarray(metres_per_unit, np.float64)
    ok = np.isfinite(a) & np.isfinite(sc) & np.isfinite(g) & np.isfinite(mpu) & (mpu > 0)
    a, sc, g, mpu = a[ok], sc[ok], g[ok], mpu[ok]
    if a.size > max_cells:
        step = int(np.ceil(a.size / max_cells))
        a, sc, g, mpu = a[::step], sc[::step], g[::step], mpu[::step]
    m50 = model.threshold(sc, 50.0)
    sb = np.clip(np.searchsorted(model.score_edges, sc, side="right") - 1, 0, len(model.score_edges) - 2)
    gb = np.searchsorted(_SLOPE_EDGES, g, side="right") - 1
    key = sb * len(_SLOPE_EDGES) + gb

    def fit(keep: np.ndarray) -> tuple[np.ndarray, int]:
        # the cells grouped by bin once (sorted by key): each bin's medians from its own slice
        order = np.argsort(key[keep], kind="stable")
        k = key[keep][order]
        cols = [v[keep][order] for v in (a, m50, g, mpu)]
        starts = np.r_[0, np.flatnonzero(np.diff(k)) + 1]
        ends = np.r_[starts[1:], k.size]
        rows = []
        for i0, i1 in zip(starts, ends):
            if i1 - i0 < min_bin_cells:
                continue
            rows.append((*(np.median(c[i0:i1]) for c in cols), i1 - i0))
        if len(rows) < 2:
            raise ProcessingError(
                f"too few observed cells to calibrate the model to these data ({int(keep.sum())} "
                "cells); use calibration='none' or a larger AOI"
            )
        R = np.asarray(rows, np.float64)
        R = R[(R[:, 0] > 0) & (R[:, 1] > 0)]
        w = np.sqrt(R[:, 4] / R[:, 4].mean())
        # the slope term is identifiable only when the bins span more than one slope bin
        edge = fit_edge and np.unique(np.searchsorted(_SLOPE_EDGES, R[:, 2], side="right")).size > 1

        def resid(x):
            e = x[1] if edge else 0.0
            pred = np.sqrt((x[0] * R[:, 1]) ** 2 + (R[:, 2] * e / R[:, 3]) ** 2)
            return (np.log(pred) - np.log(R[:, 0])) * w

        sol = least_squares(resid, [1.0, 0.1], bounds=([1e-3, 0.0], [1e3, 1e2]), loss="soft_l1", f_scale=0.1)
        return np.array([sol.x[0], sol.x[1] if edge else 0.0]), len(R)

    law = model.reference_law if reference else {}
    ref = {
        "ref_scale": float(law.get("scale", 1.0)),
        "ref_edge_sigma_m": float(law.get("edge_sigma_m", 0.0)) if fit_edge else 0.0,
    }
    keep = np.ones(a.size, bool)
    x, nb = fit(keep)
    cal = PairCalibration(float(x[0]), float(x[1]), **ref)
    p = model.pvalue(cal.effective_dtilde(model, a, sc, g, mpu), sc)
    keep = p >= 0.01
    x, nb = fit(keep)
    return PairCalibration(
        float(x[0]),
        float(x[1]),
        n_cells=int(keep.sum()),
        n_bins=int(nb),
        trimmed_fraction=float(1.0 - keep.mean()),
        **ref,
    )


def model_learned_on(model: "SelfConsistencyModel", recs: Sequence[PairDEMLike]) -> bool:
    """Whether the model's static comparisons involve any of these reconstructions (learned on these data)."""
    names = {r.name for r in recs}
    comps = model.provenance.get("comparisons") or []
    return any(part.strip() in names for c in comps for part in str(c).split(" vs "))


def _quantile_from_hist(counts: np.ndarray, edges: np.ndarray, q: float) -> float:
    """q-quantile (0..1) of a histogram, linear inside the bin."""
    total = counts.sum()
    if total == 0:
        return float("nan")
    c = np.cumsum(counts)
    target = q * total
    k = int(np.searchsorted(c, target, side="left"))
    k = min(k, len(counts) - 1)
    prev = c[k - 1] if k > 0 else 0.0
    frac = (target - prev) / counts[k] if counts[k] > 0 else 0.0
    return float(edges[k] + frac * (edges[k + 1] - edges[k]))


def _isotonic(y: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Non-decreasing weighted least-squares fit of ``y`` (B,) with weights ``w`` (B,) (pool-adjacent-violators).

    Entries with a non-finite value or no weight take the line between the fitted neighbours (the end values
    beyond the first and last), as scikit-learn's ``IsotonicRegression(out_of_bounds="clip")`` predicts them;
    the fit equals it to rounding. A few dozen bins: a plain loop, and no scikit-learn import (2 s of start-up).
    """
    ok = np.isfinite(y) & (w > 0)
    out = np.full(y.shape, np.nan)
    idx = np.flatnonzero(ok)
    if idx.size == 0:
        return out
    sum_wy: list[float] = []  # one block per run of pooled entries: weighted sum, weight, length
    sum_w: list[float] = []
    size: list[int] = []
    for v, wt in zip(y[idx].tolist(), w[idx].tolist()):
        swy, sw, n = v * wt, wt, 1
        while size and sum_wy[-1] / sum_w[-1] > swy / sw:  # the block before lies above: pool them
            swy += sum_wy.pop()
            sw += sum_w.pop()
            n += size.pop()
        sum_wy.append(swy)
        sum_w.append(sw)
        size.append(n)
    fit = np.repeat(np.array(sum_wy) / np.array(sum_w), size)
    out[:] = np.interp(np.arange(len(y), dtype=np.float64), idx.astype(np.float64), fit)
    return out


@dataclass
class SelfConsistencyModel:
    """Significance curves for one scene class, with the data behind them.

    Attributes
    ----------
    score_edges : (B+1,) float
        Score bin edges (equal-count bins of the training scores).
    hist : (B, D) int64
        Counts of match pairs per score bin and |Δ̃| bin (:data:`DTILDE_EDGES`).
    curves : dict[str, list[float]]
        "99" → per-bin |Δ̃| threshold (pixels), isotonic in score.
    raw_curves : dict[str, list[float]]
        The per-bin quantiles before smoothing (for plots and audit).
    provenance : dict
        sensor, gsd_m, scene_class, dates, images, created, geocd version, ...
    region_null : dict
        The region test's null, learned on the same static comparisons: ``cluster_confidence``
        (percent), ``min_region_cells``, ``comparisons`` and, per comparison, ``masses``: the
        evidence of each of its candidate regions (at least ``min_region_cells``). Empty for
        models saved before the region test existed (then only the per-cell test is available).
    reference_law : dict
        The transfer calibration's law (:class:`PairCalibration`) fitted to the model's own static
        comparisons: ``scale``, ``edge_sigma_m``, ``n_cells``. A transferred model is calibrated
        relative to it. Empty for models saved without it (then relative to scale 1, no slope term).
    """

    score_edges: np.ndarray
    hist: np.ndarray
    curves: dict[str, list[float]] = field(default_factory=dict)
    raw_curves: dict[str, list[float]] = field(default_factory=dict)
    provenance: dict = field(default_factory=dict)
    region_null: dict = field(default_factory=dict)
    reference_law: dict = field(default_factory=dict)

    def survival(self) -> np.ndarray:
        """(B, D+1) P(|Δ̃| > edge_k | score bin b), made non-decreasing in score (isotonic per edge)."""
        cached = self.__dict__.get("_survival")
        if cached is not None:
            return cached
        h = self.hist.astype(np.float64)
        n = np.maximum(h.sum(axis=1, keepdims=True), 1.0)
        surv = np.concatenate([np.ones((h.shape[0], 1)), 1.0 - np.cumsum(h, axis=1) / n], axis=1)
        w = self.bin_counts.astype(float)
        if h.shape[0] > 1:
            surv = np.stack([_isotonic(surv[:, k], w) for k in range(surv.shape[1])], axis=1)
        surv = np.clip(surv, 0.0, 1.0)
        self.__dict__["_survival"] = surv
        return surv

    def pvalue(self, dtilde: np.ndarray, score: np.ndarray) -> np.ndarray:
        """P(|Δ̃| ≥ observed | score) in a static scene: the per-comparison p-value of each cell.

        From the learned histogram (linear between |Δ̃| edges, the score's bin), never below
        1/(n_bin + 1) — nothing is rarer than the rarest thing seen. NaN where an input is NaN.
        """
        surv = self.survival()
        a = np.abs(np.asarray(dtilde, np.float64))
        sc = np.asarray(score, np.float64)
        ok = np.isfinite(a) & np.isfinite(sc)
        b = np.clip(np.searchsorted(self.score_edges, np.where(ok, sc, 0.0), side="right") - 1, 0, surv.shape[0] - 1)
        a0 = np.where(ok, np.minimum(a, DTILDE_EDGES[-1]), 0.0)
        k = np.clip(np.searchsorted(DTILDE_EDGES, a0, side="right") - 1, 0, len(DTILDE_EDGES) - 2)
        e0, e1 = DTILDE_EDGES[k], DTILDE_EDGES[k + 1]
        f = np.clip((a0 - e0) / (e1 - e0), 0.0, 1.0)
        p = surv[b, k] * (1.0 - f) + surv[b, k + 1] * f
        floor = 1.0 / (self.bin_counts.astype(np.float64) + 1.0)
        return np.where(ok, np.maximum(p, floor[b]), np.nan)

    def sigma_dtilde(self, score: np.ndarray) -> np.ndarray:
        """1σ-equivalent disagreement |Δ̃| (pixels) at each score: the 68.27 % curve."""
        return self.threshold(score, 68.27)

    @property
    def has_region_test(self) -> bool:
        return "masses" in self.region_null

    def region_confidence(self, mass: np.ndarray) -> np.ndarray:
        """Confidence (percent) of regions with this evidence.

        For each static comparison, the share of its candidate regions that carry less evidence;
        the confidence is the median of these shares over the comparisons — what a typical
        comparison of the static scene says, as the majority vote combines the comparisons of a
        cell (a comparison without any region counts as 100 %). A region stronger than the
        strongest region of most static comparisons gets 100 %.
        """
        if not self.has_region_test:
            raise ConfigError(
                "this self-consistency model has no region null distribution (saved by an older geocd); "
                "re-learn it with `geocd consistency`, or use the per-cell test (significance='cell')"
            )
        return null_region_confidence(self.region_null["masses"], mass)

    @property
    def bin_counts(self) -> np.ndarray:
        return self.hist.sum(axis=1)

    @property
    def score_centres(self) -> np.ndarray:
        e = self.score_edges
        return 0.5 * (e[:-1] + e[1:])

    @property
    def confidences(self) -> list[float]:
        return sorted(float(k) for k in self.curves)

    def compute_curve(self, confidence: float) -> tuple[np.ndarray, np.ndarray]:
        """(raw, smoothed) per-bin thresholds for ``confidence`` percent."""
        if not (0.0 < confidence < 100.0):
            raise ConfigError(f"confidence must be in (0, 100) percent, got {confidence}")
        raw = np.array(
            [_quantile_from_hist(self.hist[b], DTILDE_EDGES, confidence / 100.0) for b in range(self.hist.shape[0])]
        )
        return raw, _isotonic(raw, self.bin_counts.astype(float))

    def add_confidence(self, confidence: float) -> None:
        raw, smooth = self.compute_curve(confidence)
        key = _ckey(confidence)
        self.raw_curves[key] = raw.tolist()
        self.curves[key] = smooth.tolist()

    def threshold(self, score: np.ndarray, confidence: float) -> np.ndarray:
        """|Δ̃| threshold (pixels) at ``confidence`` for each score.

        Piecewise-linear in score between bin centres; constant beyond the first
        and last centre (no extrapolation beyond what was learned).
        """
        key = _ckey(confidence)
        if key not in self.curves:
            self.add_confidence(confidence)
        curve = np.asarray(self.curves[key], float)
        x = self.score_centres
        ok = np.isfinite(curve)
        s = np.asarray(score, float)
        out = np.interp(s, x[ok], curve[ok])
        return np.where(np.isfinite(s), out, np.nan)

    # --- persistence ---------------------------------------------------------------
    def to_dict(self) -> dict:
        return {
            "geocd_self_consistency_model": 1,
            "score_edges": self.score_edges.tolist(),
            "dtilde_edges": DTILDE_EDGES.tolist(),
            "hist": self.hist.tolist(),
            "bin_counts": self.bin_counts.tolist(),
            "curves": self.curves,
            "raw_curves": self.raw_curves,
            "provenance": self.provenance,
            "region_null": self.region_null,
            "reference_law": self.reference_law,
        }

    @classmethod
    def from_dict(cls, d: dict) -> "SelfConsistencyModel":
        """The model of :meth:`to_dict`'s form, every field checked (a damaged model is a :class:`ConfigError`)."""
        if d.get("geocd_self_consistency_model") != 1:
            raise ConfigError(
                "not a geocd self-consistency model (missing 'geocd_self_consistency_model': 1); "
                "create one with `geocd consistency`"
            )
        f = _checked_model_fields(d)
        if not np.allclose(f["dtilde_edges"], DTILDE_EDGES):
            raise ConfigError("the model was saved with different |Δ̃| bins; re-learn it with this geocd version")
        return cls(
            f["score_edges"],
            f["hist"],
            f["curves"],
            f["raw_curves"],
            f["provenance"],
            f["region_null"],
            f["reference_law"],
        )

    def save(self, path: os.PathLike | str) -> Path:
        from .io.atomic import write_text_atomic

        return write_text_atomic(path, json.dumps(self.to_dict(), indent=1))

    @classmethod
    def load(cls, path: os.PathLike | str) -> "SelfConsistencyModel":
        from .errors import InputFileNotFoundError

        p = Path(path)
        if not p.exists():
            raise InputFileNotFoundError(
                f"self-consistency model {p} does not exist; create one with `geocd consistency`"
            )
        try:
            d = json.loads(p.read_text(encoding="utf-8"))
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise ConfigError(
                f"{p} is not a self-consistency model (not valid JSON text: {exc}); give the JSON "
                "written by `geocd consistency` or a run"
            ) from exc
        if not isinstance(d, dict):
            raise ConfigError(
                f"{p} is not a self-consistency model (a JSON {type(d).__name__}); give the JSON "
                "written by `geocd consistency` or a run"
            )
        try:
            return cls.from_dict(d)
        except ConfigError as exc:
            raise ConfigError(f"{p}: {exc}") from None

    def curves_table(self):
        """pandas DataFrame: one row per score bin (edges, centre, count, raw and smoothed curves)."""
        import pandas as pd

        d: dict[str, Any] = {
            "score_lo": self.score_edges[:-1],
            "score_hi": self.score_edges[1:],
            "score_centre": self.score_centres,
            "n_pairs": self.bin_counts,
        }
        for k in sorted(self.curves, key=float):
            d[f"q{k}_raw"] = self.raw_curves.get(k, [np.nan] * len(self.score_centres))
            d[f"q{k}"] = self.curves[k]
        return pd.DataFrame(d)


def _ckey(confidence: float) -> str:
    return f"{float(confidence):g}"


def _equal_count_edges(scores: np.ndarray, n_bins: int, min_count: int) -> np.ndarray:
    n = scores.size
    nb = int(max(1, min(n_bins, n // max(min_count, 1))))
    qs = np.quantile(scores, np.linspace(0, 1, nb + 1))
    edges = np.unique(qs)
    if edges.size < 2:
        edges = np.array([scores.min() - 1e-6, scores.max() + 1e-6])
    edges[0] = -np.inf if False else edges[0]
    return edges.astype(float)


def comparisons_within(recs: Sequence[PairDEMLike]) -> list[tuple[PairDEMLike, PairDEMLike]]:
    """All unordered pairs of reconstructions (stage 1: same epoch)."""
    return list(itertools.combinations(recs, 2))


def learn_self_consistency(
    groups: Sequence[Sequence[PairDEMLike]],
    params: ConsistencyParams = ConsistencyParams(),
    provenance: dict | None = None,
    progress: Progress | None = None,
) -> SelfConsistencyModel:
    """Stage 1: learn the self-consistency distribution from static-scene reconstructions.

    Parameters
    ----------
    groups : sequence of sequences of pair-DEMs
        Each group is one epoch (or one scene) of the same class; all pairs of
        reconstructions *within* a group are compared (3 images → 3 pair-DEMs → 3
        comparisons). Groups are pooled.
    params : ConsistencyParams
    provenance : dict, optional
        Sensor, GSD, scene class, dates... stored in the model.

    Raises
    ------
    ProcessingError
        When fewer than two reconstructions exist in every group (no comparison
        possible): give a scene-class model instead (learned on another scene).
    """
    prog = ensure_progress(progress)
    offsets: dict[str, float] = {}
    aligned_groups = []
    empty = [r.name for g in groups for r in g if not np.any(r.valid)]
    if empty:
        warnings.warn(
            f"reconstructions with no valid cell left out of the self-consistency model: {', '.join(empty)}",
            UserWarning,
            stacklevel=2,
        )
    for g in groups:
        g = sorted((r for r in g if np.any(r.valid)), key=lambda r: r.name)
        ag, off = align_reconstructions(g, mode=params.align)
        aligned_groups.append(ag)
        offsets.update(off)
    comps = [c for g in aligned_groups for c in comparisons_within(g)]
    if not comps:
        raise ProcessingError(
            "self-consistency needs at least two reconstructions of the same static scene (an epoch with 3 images "
            "gives 3 pair-DEMs); with one pair per epoch, pass a scene-class model learned on another scene "
            "(geocd change --model MODEL.json)"
            + (f"; these had no valid cell at all: {', '.join(empty)}" if empty else "")
        )
    dts, scs = [], []
    for i, (p, q) in enumerate(comps):
        dt, sc, _, both = match_pairs(p, q)
        dts.append(np.abs(dt[both]))
        scs.append(sc[both])
        prog((i + 1) / len(comps), f"comparison {p.name} vs {q.name}")
    adt = np.concatenate(dts)
    sc = np.concatenate(scs)
    if adt.size < params.min_bin_count:
        raise ProcessingError(
            f"only {adt.size} common-xy match pairs between same-epoch reconstructions (need ≥ {params.min_bin_count}); "
            "the pair-DEMs barely overlap — enlarge the AOI or lower min_bin_count"
        )
    edges = _equal_count_edges(sc, params.n_score_bins, params.min_bin_count)
    hist, _, _ = np.histogram2d(sc, np.minimum(adt, DTILDE_EDGES[-1] * 0.999999), bins=[edges, DTILDE_EDGES])
    prov = dict(provenance or {})
    prov.setdefault("created", _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"))
    prov.setdefault("comparisons", [f"{p.name} vs {q.name}" for p, q in comps])
    prov.setdefault("n_match_pairs", int(adt.size))
    prov.setdefault(
        "alignment", {"mode": params.align, "vertical_offsets_m": {k: round(v, 4) for k, v in offsets.items()}}
    )
    from . import __version__

    prov.setdefault("geocd_version", __version__)
    model = SelfConsistencyModel(edges, hist.astype(np.int64), provenance=prov)
    for c in params.confidences:
        model.add_confidence(c)
    # the region test's null: candidate regions of the same static comparisons and their evidence
    mmu = params.min_region_cells or window_cells(r for g in aligned_groups for r in g)
    alpha0 = 1.0 - params.cluster_confidence / 100.0
    masses = []
    for p, q in comps:
        dt, sc, _, both = match_pairs(p, q)
        pv = np.where(both, model.pvalue(dt, sc), 1.0)
        _, mass, _ = candidate_regions(pv, np.sign(np.nan_to_num(dt)).astype(np.int8), alpha0, mmu)
        masses.append(sorted(float(f"{v:.5g}") for v in mass))
    model.region_null = {
        "cluster_confidence": float(params.cluster_confidence),
        "min_region_cells": int(mmu),
        "comparisons": [f"{p.name} vs {q.name}" for p, q in comps],
        "masses": masses,
        "n_regions": int(sum(len(v) for v in masses)),
    }
    model.reference_law = reference_law(model, comps)
    return model


def _comparison_arrays(p: PairDEMLike, q: PairDEMLike, posting_m: float | None, slopes: dict | None = None):
    """Δ̃, score, Δz, both, metres per unit of Δ̃ and the slope of the surface common to both (min of the two).

    ``slopes``: {id(pair-DEM): its local slope}, filled here, when the caller compares each pair-DEM several
    times (its slope is computed once)."""
    dt, sc, dz, both = match_pairs(p, q)
    with np.errstate(divide="ignore", invalid="ignore"):
        mpu = np.sqrt(1.0 / np.asarray(p.g_px_per_m, np.float64) ** 2 + 1.0 / np.asarray(q.g_px_per_m, np.float64) ** 2)
    mpu = np.broadcast_to(mpu, dt.shape)
    if posting_m:
        if slopes is None:
            slopes = {}
        for r in (p, q):
            if id(r) not in slopes:
                slopes[id(r)] = local_slope(r.z_m, posting_m)
        slope = np.fmin(slopes[id(p)], slopes[id(q)])
    else:
        slope = np.zeros(dt.shape)
    return dt, sc, dz, both, mpu, slope


def reference_law(model: "SelfConsistencyModel", comps: Sequence[tuple[PairDEMLike, PairDEMLike]]) -> dict:
    """The calibration law fitted to the model's own static comparisons ({} when it cannot be fitted)."""
    posting = getattr(getattr(comps[0][0], "grid", None), "posting_m", None) if comps else None
    slopes: dict = {}  # each pair-DEM's slope once (it is in several comparisons); comps keeps them alive
    arrays = [_comparison_arrays(p, q, posting, slopes) for p, q in comps]
    try:
        cal = fit_pair_calibration(
            model,
            *(np.concatenate([a[k][a[3]] for a in arrays]) for k in (0, 1, 5, 4)),
            fit_edge=bool(posting),
            reference=False,
        )
    except ProcessingError:
        return {}
    return {
        "scale": round(cal.scale, 5),
        "edge_sigma_m": round(cal.edge_sigma_m, 5),
        "n_cells": cal.n_cells,
        "slope": "min of the two surfaces' local |grad z|" if posting else "none (no grid posting)",
    }


def _damaged(what: str) -> ConfigError:
    return ConfigError(
        f"damaged self-consistency model: {what}; re-learn it with `geocd consistency` (or a "
        "`geocd run` that writes one)"
    )


def _number_array(d: dict, key: str, ndim: int, *, allow_nan: bool = False) -> np.ndarray:
    if key not in d:
        raise _damaged(f"'{key}' is missing")
    try:
        a = np.asarray(d[key], dtype=np.float64)
    except (TypeError, ValueError):
        raise _damaged(f"'{key}' holds something other than numbers") from None
    if a.ndim != ndim:
        raise _damaged(f"'{key}' has {a.ndim} dimension(s), expected {ndim}")
    if np.isinf(a).any() or (not allow_nan and np.isnan(a).any()):
        raise _damaged(f"'{key}' holds non-finite values")
    return a


def _checked_model_fields(d: dict) -> dict:
    """The fields of a saved model as arrays and dicts, checked for shape, range and order."""
    score_edges = _number_array(d, "score_edges", 1)
    if score_edges.size < 2 or not np.all(np.diff(score_edges) > 0):
        raise _damaged("'score_edges' must be two or more increasing numbers")
    dtilde = _number_array(d, "dtilde_edges", 1)
    hist = _number_array(d, "hist", 2)
    if hist.shape != (score_edges.size - 1, dtilde.size - 1):
        raise _damaged(
            f"'hist' has shape {hist.shape}, expected {(score_edges.size - 1, dtilde.size - 1)} (score bins × |Δ̃| bins)"
        )
    if (hist < 0).any() or (hist != np.round(hist)).any() or hist.max(initial=0) > 2**62:
        raise _damaged("'hist' must hold counts (whole numbers ≥ 0)")
    if hist.sum() == 0:
        raise _damaged("'hist' is empty (no comparison was learned)")
    out: dict[str, Any] = {"score_edges": score_edges, "dtilde_edges": dtilde, "hist": hist.astype(np.int64)}
    for key in ("curves", "raw_curves"):
        v = d.get(key, {})
        if not isinstance(v, dict):
            raise _damaged(f"'{key}' is not a mapping of confidence → thresholds")
        curves = {}
        for k, c in v.items():
            try:
                conf = float(k)
            except (TypeError, ValueError):
                raise _damaged(f"'{key}' has a key {str(k)[:20]!r} that is not a confidence in percent") from None
            if not 0.0 < conf < 100.0:
                raise _damaged(f"'{key}' has a confidence {conf:g} outside (0, 100) percent")
            arr = _number_array(
                {k: [np.nan if x is None else x for x in c] if isinstance(c, list) else c}, k, 1, allow_nan=True
            )
            if arr.size != hist.shape[0] or (arr[np.isfinite(arr)] < 0).any():
                raise _damaged(f"'{key}[{k}]' must hold one threshold ≥ 0 per score bin ({hist.shape[0]})")
            curves[k] = list(c)
        out[key] = curves
    for key in ("provenance", "region_null", "reference_law"):
        v = d.get(key, {})
        if not isinstance(v, dict):
            raise _damaged(f"'{key}' is not a mapping")
        out[key] = dict(v)
    rn = out["region_null"]
    if rn:
        masses = rn.get("masses")
        if not isinstance(masses, list) or not all(isinstance(m, list) for m in masses):
            raise _damaged("'region_null.masses' must be one list of region evidence per static comparison")
        for m in masses:
            a = _number_array({"masses": m}, "masses", 1)
            if (a < 0).any() or (np.diff(a) < 0).any():
                raise _damaged("'region_null.masses' must hold sorted evidence values ≥ 0")
        for key, lo, hi in (("cluster_confidence", 0.0, 100.0), ("min_region_cells", 1.0, 1e9)):
            try:
                x = float(rn.get(key, lo if key == "min_region_cells" else 50.0))
            except (TypeError, ValueError):
                raise _damaged(f"'region_null.{key}' is not a number") from None
            if not (np.isfinite(x) and lo <= x <= hi and (key != "cluster_confidence" or 0.0 < x < 100.0)):
                raise _damaged(f"'region_null.{key}' is {x:g}, outside [{lo:g}, {hi:g}]")
    law = out["reference_law"]
    for key in ("scale", "edge_sigma_m"):
        if key in law:
            try:
                x = float(law[key])
            except (TypeError, ValueError):
                raise _damaged(f"'reference_law.{key}' is not a number") from None
            if not np.isfinite(x) or x < 0 or (key == "scale" and x == 0):
                raise _damaged(
                    f"'reference_law.{key}' is {x:g}: a {'scale > 0' if key == 'scale' else 'σ ≥ 0'} is expected"
                )
    return out


def null_region_confidence(null_masses: Sequence[Sequence[float]], mass: np.ndarray) -> np.ndarray:
    """Confidence (percent) of regions with evidence ``mass`` against null regions' evidence.

    ``null_masses``: one sorted list of evidence per null sample (a static comparison, a
    simulated noise field set). Per sample, the share of its null regions with less evidence;
    the confidence is the median share over the samples (a sample without any region counts as
    100 %).
    """
    m = np.atleast_1d(np.asarray(mass, float))
    shares = []
    for ms in null_masses:
        ms = np.asarray(ms, float)
        shares.append(np.searchsorted(ms, m, side="left") / ms.size if ms.size else np.ones(m.shape))
    if not shares:
        return np.full(m.shape, 100.0)
    return 100.0 * np.median(np.stack(shares), axis=0)


def cluster_evidence(pvalue: np.ndarray, alpha0: float) -> np.ndarray:
    """Each cell's evidence beyond the cluster-forming level: log(α0/p) where p < α0, else 0."""
    p = np.asarray(pvalue, np.float64)
    cand = np.isfinite(p) & (p < alpha0)
    return np.where(cand, np.log(alpha0 / np.maximum(np.where(cand, p, 1.0), 1e-300)), 0.0)


def candidate_regions(
    pvalue: np.ndarray, sign: np.ndarray, alpha0: float, min_cells: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Candidate change regions and their combined evidence.

    8-connected groups of same-sign cells with p < ``alpha0``, of at least ``min_cells``
    cells. A region's evidence is its cluster mass Σ log(α0/p_i) (each cell's evidence
    beyond the cluster-forming level, summed; large when many cells agree or a few are
    extreme). Same function for the static comparisons (the null) and the cross-epoch test.

    Parameters
    ----------
    pvalue : float (rows, cols); 1 or NaN where nothing was observed
    sign : int8 (rows, cols), the sign of the difference
    alpha0 : cluster-forming p-value
    min_cells : minimum mapping unit (cells)

    Returns
    -------
    labels : int32 (rows, cols), 0 outside kept regions, 1..n (raised regions first)
    mass : float (n,), the evidence of region i + 1
    region_sign : int8 (n,)
    """
    from scipy import ndimage

    p = np.asarray(pvalue, np.float64)
    cand = np.isfinite(p) & (p < alpha0)
    ev = cluster_evidence(p, alpha0)
    labels = np.zeros(p.shape, np.int32)
    masses, signs = [], []
    n_total = 0
    for sgn in (1, -1):
        lab, n = ndimage.label(cand & (np.asarray(sign) == sgn), structure=np.ones((3, 3), bool))
        if n == 0:
            continue
        size = np.bincount(lab.ravel(), minlength=n + 1)
        mass = np.bincount(lab.ravel(), weights=ev.ravel(), minlength=n + 1)
        keep = np.nonzero(size >= min_cells)[0]
        keep = keep[keep > 0]
        if keep.size == 0:
            continue
        remap = np.zeros(n + 1, np.int32)
        remap[keep] = np.arange(n_total + 1, n_total + keep.size + 1, dtype=np.int32)
        labels = np.where(remap[lab] > 0, remap[lab], labels)
        masses.append(mass[keep])
        signs.append(np.full(keep.size, sgn, np.int8))
        n_total += keep.size
    if not masses:
        return labels, np.zeros(0), np.zeros(0, np.int8)
    return labels, np.concatenate(masses), np.concatenate(signs)


# ----------------------------------------------------------------------------------------
# Stage 2
# ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ChangeParams:
    """Parameters of stage 2.

    Attributes
    ----------
    confidences : tuple of float
        Levels (percent) reported in summaries (``changed_at``); the confidence itself is continuous.
    combine : {"majority", "all", "any"}
        How several cross-epoch comparisons of a cell are combined: a cell is
        changed at level s when more than half ("majority"), all, or any of its
        observed comparisons exceed their significance level s, with a consistent sign
        (the sign of the median Δz). Its per-cell p-value is the matching order statistic
        of the comparisons' p-values.
    significance : {"region", "cell"}
        "region" (default): cells changed at the model's cluster-forming level form candidate
        regions; a region's confidence is how much of the static scene's candidate regions carry
        less combined evidence (:meth:`SelfConsistencyModel.region_confidence`), and every cell
        of the region gets it. "cell": the SRI per-cell test — each cell's own highest level, then regions
        smaller than the minimum mapping unit dropped.
    min_region_cells : int, optional
        Minimum mapping unit (cells). None: the model's (region test) or the footprint of one
        matching window of the reconstructions (:func:`window_cells`).
    align : {"vertical", "none"}
        Shift every reconstruction of both epochs onto one vertical reference (a DEM
        epoch if given, else the least-squares fit of all their pairwise offsets) before testing.
    calibration : {"auto", "pair", "none"}
        "pair": fit the model's scale and a slope × misregistration term to the cross-epoch
        comparisons themselves (:func:`fit_pair_calibration`, robust to a changed minority) — for
        a model learned on another scene. "none": use the model as learned. "auto" (default):
        "pair" when the model was learned on other reconstructions than those tested
        (:func:`model_learned_on`), else "none".
    """

    confidences: tuple[float, ...] = (90.0, 95.0, 99.0)
    combine: str = "majority"
    significance: str = "region"
    min_region_cells: int | None = None
    align: str = "vertical"
    calibration: str = "auto"

    def __post_init__(self) -> None:
        if self.align not in ALIGN_MODES:
            raise ConfigError(f"align must be one of {ALIGN_MODES}, got {self.align!r}")
        if self.min_region_cells is not None and self.min_region_cells < 1:
            raise ConfigError(f"min_region_cells must be ≥ 1 (or None: derived), got {self.min_region_cells}")
        if self.combine not in ("majority", "all", "any"):
            raise ConfigError(f"combine must be majority, all or any, got {self.combine!r}")
        if self.calibration not in CALIBRATION_MODES:
            raise ConfigError(f"calibration must be one of {CALIBRATION_MODES}, got {self.calibration!r}")
        if self.significance not in ("region", "cell"):
            raise ConfigError(f"significance must be 'region' or 'cell', got {self.significance!r}")
        for c in self.confidences:
            if not 0 < c < 100:
                raise ConfigError(f"confidence levels are percentages in (0, 100), got {c}")


@dataclass
class ChangeResult:
    """Per-cell result of the cross-epoch test (all arrays on the AOI grid).

    Attributes
    ----------
    dz_m : float32, median z_B − z_A over comparisons (NaN where unobserved)
    dtilde : float32, median Δ̃ (pixels of disparity)
    score : float32, max score over comparisons
    confidence : float32, confidence (percent) that the cell changed: its region's (region test) or
        its own highest level (cell test); 0 if in no region / unchanged, NaN if unobserved
    change : int8, changed at the lowest of ``confidences``: +1 raised, −1 lowered, 0 unchanged,
        :data:`CHANGE_NODATA` unobserved
    n_comparisons : int16, number of cross-epoch comparisons observed at the cell
    cell_confidence : float32, 100 × (1 − the cell's combined p-value): the per-cell evidence alone
    dz_sigma_m : float32, 1σ of dz from the error model (the 68.27 % disagreement at the cell's
        scores, in metres; median over comparisons)
    min_region_cells : int, the minimum mapping unit used (cells)
    significance : "region" or "cell"
    p_value : float64, the cell's combined p-value (what the region test clusters; tiled runs merge
        regions across tiles from it)
    calibration : PairCalibration or None, the transfer calibration applied (None: the model as learned)
    """

    dz_m: np.ndarray
    dtilde: np.ndarray
    score: np.ndarray
    confidence: np.ndarray
    change: np.ndarray
    n_comparisons: np.ndarray
    grid: Any = None
    confidences: tuple[float, ...] = ()
    comparisons: list[str] = field(default_factory=list)
    vertical_offsets_m: dict[str, float] = field(default_factory=dict)
    cell_confidence: np.ndarray | None = None
    dz_sigma_m: np.ndarray | None = None
    min_region_cells: int = 1
    significance: str = "cell"
    p_value: np.ndarray | None = None
    calibration: PairCalibration | None = None

    @property
    def observed(self) -> np.ndarray:
        return self.n_comparisons > 0

    def changed_at(self, confidence: float) -> np.ndarray:
        """Signed change mask at ``confidence`` percent.

        int8 (rows, cols): +1 raised, −1 lowered, 0 unchanged, :data:`CHANGE_NODATA` where no
        comparison observed the cell (so building statistics can tell "unchanged" from "unseen").
        """
        c = np.nan_to_num(self.confidence, nan=0.0)
        out = np.where(c >= confidence, np.sign(np.nan_to_num(self.dz_m)), 0).astype(np.int8)
        out[~self.observed] = CHANGE_NODATA
        return out


CHANGE_NODATA = -128
#: change-mask code of a cell the 3-D test did not examine (a tiered run: the screen did not flag its tile)
NOT_EXAMINED = -127


def combine_pvalues(pvalues: np.ndarray, signs: np.ndarray, sign: np.ndarray, combine: str = "majority") -> np.ndarray:
    """Per-cell p-value of several comparisons voting with a consistent sign (per-cell work).

    Parameters
    ----------
    pvalues : float (n, rows, cols), NaN where comparison k does not observe the cell
    signs : int8 (n, rows, cols), the sign of each comparison's difference
    sign : int8 (rows, cols), the sign tested (the median difference's)
    combine : "majority" (the (⌊m/2⌋+1)-th smallest of the m observed p-values, comparisons of
        the other sign counting as 1), "all" (the largest) or "any" (the smallest)

    Returns
    -------
    float (rows, cols): the cell is changed at level s exactly when p < 1 − s/100 under the rule;
    1 where nothing was observed or the sign is 0.
    """
    P = np.asarray(pvalues, np.float64)
    obs = np.isfinite(P)
    nobs = obs.sum(axis=0)
    pa = np.where(obs, np.where(np.asarray(signs) == np.asarray(sign)[None], P, 1.0), np.inf)
    pa.sort(axis=0)
    if combine == "majority":
        k = nobs // 2
    elif combine == "all":
        k = nobs - 1
    else:
        k = np.zeros_like(nobs)
    out = np.take_along_axis(pa, np.clip(k, 0, P.shape[0] - 1)[None], axis=0)[0]
    return np.where((nobs > 0) & (np.asarray(sign) != 0) & np.isfinite(out), out, 1.0)


def change_test(
    epoch_a: Sequence[PairDEMLike],
    epoch_b: Sequence[PairDEMLike],
    model: SelfConsistencyModel,
    params: ChangeParams = ChangeParams(),
    progress: Progress | None = None,
    offsets: dict[str, float] | None = None,
    calibration: PairCalibration | None = None,
) -> ChangeResult:
    """Stage 2: test every cross-epoch comparison against the static scene's disagreement.

    For each pair (p from epoch A, q from epoch B) and each cell valid in both, the
    comparison's p-value is how rarely two reconstructions of a static scene disagree by
    |Δ̃| or more at that score (:meth:`SelfConsistencyModel.pvalue`). Comparisons are
    combined per cell by ``params.combine`` with a consistent sign (the sign of the median
    Δz). With ``significance="region"`` the cells beyond the model's cluster-forming level
    form regions whose combined evidence is ranked against the static scene's regions;
    with ``"cell"`` each cell stands alone (highest level of ``params.confidences`` whose
    curve it exceeds). Regions smaller than the minimum mapping unit are never reported.
    The result does not depend on the order of the reconstructions.

    Parameters
    ----------
    epoch_a, epoch_b : reconstructions (pair-DEMs, :class:`DEMAsEpoch`) on one grid
    model : the significance curves and region null (a whole-scene or scene-class statistic)
    offsets : {name: m}, optional
        Vertical offsets to remove (:func:`vertical_offsets`, a whole-scene statistic). Give
        them when the arrays are a tile of a larger scene, so every tile uses the same ones;
        default: computed here from the arrays given (``params.align``). The region step
        (:func:`candidate_regions`) needs whole regions: tile with an overlap wider than the
        largest region, or run it on the mosaic of ``cell_confidence``.
    calibration : PairCalibration, optional
        A transfer calibration to apply (a whole-scene statistic, like ``offsets``); default:
        fitted here when ``params.calibration`` asks for it.
    """
    prog = ensure_progress(progress)
    if not epoch_a or not epoch_b:
        raise ProcessingError("the change test needs at least one reconstruction (pair-DEM or DEM) per epoch")
    significance = params.significance
    if significance == "region" and not model.has_region_test:
        warnings.warn(
            "the self-consistency model has no region null (saved by an older geocd): using the per-cell "
            "test; re-learn the model for the region test",
            UserWarning,
            stacklevel=2,
        )
        significance = "cell"
    epoch_a = sorted(epoch_a, key=lambda r: r.name)  # a deterministic order for the comparisons' names
    epoch_b = sorted(epoch_b, key=lambda r: r.name)
    na = len(epoch_a)
    if offsets is None:
        offsets = vertical_offsets(list(epoch_a) + list(epoch_b), mode=params.align)
    aligned = apply_offsets(list(epoch_a) + list(epoch_b), offsets)
    epoch_a, epoch_b = aligned[:na], aligned[na:]
    if params.min_region_cells is not None:
        mmu = int(params.min_region_cells)
    elif significance == "region":
        mmu = int(model.region_null.get("min_region_cells", 1))
    else:
        mmu = window_cells(aligned)
    shape = epoch_a[0].z_m.shape
    comps = [(p, q) for p in epoch_a for q in epoch_b]
    levels = sorted(params.confidences)
    n = len(comps)
    mode = params.calibration
    if mode == "auto":
        mode = "none" if model_learned_on(model, aligned) else "pair"
    # without a grid posting there is no slope: the calibration fits the scale alone
    posting = getattr(getattr(epoch_a[0], "grid", None), "posting_m", None)
    need_slope = calibration is not None or mode == "pair"
    slopes: dict = {}  # each pair-DEM's slope once (it is in several comparisons); comps keeps them alive
    per_comp = [_comparison_arrays(p, q, posting if need_slope else None, slopes) for p, q in comps]
    if calibration is None and mode == "pair":
        calibration = fit_pair_calibration(
            model, *(np.concatenate([c[k][c[3]] for c in per_comp]) for k in (0, 1, 5, 4)), fit_edge=bool(posting)
        )
    dz_stack = np.full((n, *shape), np.nan, np.float32)
    dt_stack = np.full((n, *shape), np.nan, np.float32)
    dte_stack = np.full((n, *shape), np.nan, np.float32)
    pv_stack = np.full((n, *shape), np.nan, np.float32)
    sig_stack = np.full((n, *shape), np.nan, np.float32)
    score = np.full(shape, np.nan, np.float32)
    for k, ((p, q), (dt, sc, dz, both, metres_per_unit, slope)) in enumerate(zip(comps, per_comp)):
        dz_stack[k] = dz
        dt_stack[k] = dt
        score = np.fmax(score, sc)
        sig = model.sigma_dtilde(sc)
        dte = dt
        if calibration is not None:
            infl = calibration.inflation(model, sc, slope, metres_per_unit)
            dte = dt / infl
            sig = sig * infl
        dte_stack[k] = dte
        pv_stack[k] = np.where(both, model.pvalue(dte, sc), np.nan)
        sig_stack[k] = np.where(both, sig * metres_per_unit, np.nan)
        prog((k + 1) / n, f"comparison {p.name} vs {q.name}")
    nobs = np.sum(np.isfinite(dt_stack), axis=0).astype(np.int16)
    observed = nobs > 0
    dz_med = nanmedian_stack(dz_stack)
    dt_med = nanmedian_stack(dt_stack)
    sig_med = nanmedian_stack(sig_stack)
    sign = np.sign(np.nan_to_num(dz_med)).astype(np.int8)
    signs = np.sign(np.nan_to_num(dz_stack)).astype(np.int8)
    p_cell = combine_pvalues(pv_stack, signs, sign, params.combine)
    cell_conf = np.where(observed, 100.0 * (1.0 - p_cell), np.nan).astype(np.float32)
    conf = np.where(observed, 0.0, np.nan).astype(np.float32)
    if significance == "region":
        alpha0 = 1.0 - float(model.region_null["cluster_confidence"]) / 100.0
        labels, mass, _ = candidate_regions(np.where(observed, p_cell, 1.0), sign, alpha0, mmu)
        if mass.size:
            rconf = np.concatenate([[0.0], model.region_confidence(mass)]).astype(np.float32)
            conf = np.where(observed, rconf[labels], np.nan).astype(np.float32)
    else:
        for lev in levels:
            hit = np.zeros(shape, bool)
            votes = np.zeros(shape, np.int16)
            for k, (p, q) in enumerate(comps):
                thr = model.threshold(_score_of(p, q), lev)
                votes += (np.isfinite(dte_stack[k]) & (np.abs(dte_stack[k]) > thr) & (signs[k] == sign)).astype(
                    np.int16
                )
            if params.combine == "majority":
                hit = votes * 2 > nobs
            elif params.combine == "all":
                hit = (votes == nobs) & observed
            else:
                hit = votes > 0
            hit &= observed & (sign != 0)
            if mmu > 1:
                hit = _drop_small(hit, sign, mmu)
            conf = np.where(hit, np.float32(lev), conf)
    change = np.where(observed, np.where(np.nan_to_num(conf) >= levels[0], sign, 0), CHANGE_NODATA).astype(np.int8)
    return ChangeResult(
        dz_med.astype(np.float32),
        dt_med.astype(np.float32),
        score,
        conf,
        change,
        nobs,
        grid=getattr(epoch_a[0], "grid", None),
        confidences=tuple(levels),
        comparisons=[f"{p.name} vs {q.name}" for p, q in comps],
        vertical_offsets_m=offsets,
        cell_confidence=cell_conf,
        dz_sigma_m=sig_med.astype(np.float32),
        min_region_cells=mmu,
        significance=significance,
        p_value=p_cell,
        calibration=calibration,
    )


def _score_of(p: PairDEMLike, q: PairDEMLike) -> np.ndarray:
    """max(s_p, s_q), the finite side when one has no score (a DEM epoch)."""
    return np.fmax(np.asarray(p.score, np.float64), np.asarray(q.score, np.float64))


def _drop_small(hit: np.ndarray, sign: np.ndarray, min_cells: int) -> np.ndarray:
    """Remove 8-connected groups of same-sign hits smaller than ``min_cells``."""
    from scipy import ndimage

    out = np.zeros_like(hit)
    for s in (1, -1):
        lab, n = ndimage.label(hit & (sign == s), structure=np.ones((3, 3), bool))
        if n == 0:
            continue
        size = np.bincount(lab.ravel())
        keep = size >= min_cells
        keep[0] = False
        out |= keep[lab]
    return out


def naive_threshold(
    epoch_a: Sequence[PairDEMLike],
    epoch_b: Sequence[PairDEMLike],
    threshold: float,
    units: str = "dtilde",
    combine: str = "majority",
    min_region_cells: int = 4,
    align: str = "vertical",
) -> np.ndarray:
    """The baseline the SRI paper compares against (its Fig. 1 c, d): |Δ̃| (or |Δz|) > threshold.

    Comparisons are combined and small groups dropped exactly as in :func:`change_test`,
    so the two differ only in the threshold. ``units``: "dtilde" (pixels of disparity) or "m".
    Returns a signed change mask (+1/−1/0, :data:`CHANGE_NODATA` unobserved).
    """
    na = len(epoch_a)
    aligned, _ = align_reconstructions(list(epoch_a) + list(epoch_b), mode=align)
    epoch_a, epoch_b = aligned[:na], aligned[na:]
    comps = [(p, q) for p in epoch_a for q in epoch_b]
    shape = epoch_a[0].z_m.shape
    votes = np.zeros(shape, np.int16)
    nobs = np.zeros(shape, np.int16)
    dzs = []
    for p, q in comps:
        dt, _, dz, both = match_pairs(p, q)
        v = np.abs(dt if units == "dtilde" else dz)
        votes += (both & (v > threshold)).astype(np.int16)
        nobs += both
        dzs.append(dz)
    dz_med = nanmedian_stack(np.stack(dzs))
    if combine == "majority":
        hit = votes * 2 > nobs
    elif combine == "all":
        hit = (votes == nobs) & (nobs > 0)
    else:
        hit = votes > 0
    sign = np.sign(np.nan_to_num(dz_med)).astype(np.int8)
    hit &= (nobs > 0) & (sign != 0)
    if min_region_cells > 1:
        hit = _drop_small(hit, sign, min_region_cells)
    out = np.where(hit, sign, 0).astype(np.int8)
    return np.where(nobs > 0, out, CHANGE_NODATA).astype(np.int8)
