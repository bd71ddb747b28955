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
    """

    confidences: tuple[float, ...] = (90.0, 95.0, 99.0)
    n_score_bins: int = 24
    min_bin_count: int = 200
    align: str = "vertical"

    def __post_init__(self) -> None:
        if self.align not in ALIGN_MODES:
            raise ConfigError(f"align must be one of {ALIGN_MODES}, got {self.align!r}")


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
        raise GridError(f"reconstructions {p.name!r} {p.z_m.shape} and {q.name!r} {q.z_m.shape} are on different grids; "
                        "resample them onto one AOI grid first")
    if getattr(p, "grid", None) is not None and getattr(q, "grid", None) is not None:
        if hasattr(p.grid, "same_as") and not p.grid.same_as(q.grid):
            raise GridError(f"reconstructions {p.name!r} and {q.name!r} are not on the same AOI grid; "
                            "resample one onto the other (geocd.io.raster.reproject_array)")
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
    both = (np.asarray(rec.valid, bool) & np.asarray(ref.valid, bool) & np.isfinite(rec.z_m) & np.isfinite(ref.z_m))
    if both.sum() < min_cells:
        return 0.0
    dz = (np.asarray(rec.z_m, np.float64) - np.asarray(ref.z_m, np.float64))[both]
    sc = np.fmax(np.asarray(rec.score, np.float64), np.asarray(ref.score, np.float64))[both]
    if np.isfinite(sc).sum() >= 2 * min_cells:
        good = np.isfinite(sc) & (sc <= np.nanmedian(sc))
        dz = dz[good]
    return float(np.median(dz))


def vertical_offsets(recs: Sequence[PairDEMLike], reference: PairDEMLike | None = None,
                     mode: str = "vertical") -> dict[str, float]:
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


def align_reconstructions(recs: Sequence[PairDEMLike], reference: PairDEMLike | None = None,
                          mode: str = "vertical") -> tuple[list, dict[str, float]]:
    """Shift reconstructions onto a common vertical reference (see :func:`vertical_offsets`).

    Returns
    -------
    aligned : list of reconstructions (same order), offsets : {name: offset removed, m}
    """
    offsets = vertical_offsets(recs, reference, mode)
    return apply_offsets(recs, offsets), offsets


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
    """Non-decreasing weighted least-squares fit (pool-adjacent-violators)."""
    from sklearn.isotonic import IsotonicRegression

    ok = np.isfinite(y) & (w > 0)
    out = np.full_like(y, np.nan, dtype=np.float64)
    if ok.sum() == 0:
        return out
    x = np.arange(len(y), dtype=float)
    ir = IsotonicRegression(increasing=True, out_of_bounds="clip")
    ir.fit(x[ok], y[ok], sample_weight=w[ok])
    out[:] = ir.predict(x)
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
    """

    score_edges: np.ndarray
    hist: np.ndarray
    curves: dict[str, list[float]] = field(default_factory=dict)
    raw_curves: dict[str, list[float]] = field(default_factory=dict)
    provenance: dict = field(default_factory=dict)

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
        raw = np.array([_quantile_from_hist(self.hist[b], DTILDE_EDGES, confidence / 100.0)
                        for b in range(self.hist.shape[0])])
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
        }

    @classmethod
    def from_dict(cls, d: dict) -> "SelfConsistencyModel":
        if d.get("geocd_self_consistency_model") != 1:
            raise ConfigError("not a geocd self-consistency model (missing 'geocd_self_consistency_model': 1); "
                              "create one with `geocd consistency`")
        if not np.allclose(np.asarray(d["dtilde_edges"]), DTILDE_EDGES):
            raise ConfigError("the model was saved with different |Δ̃| bins; re-learn it with this geocd version")
        return cls(np.asarray(d["score_edges"], float), np.asarray(d["hist"], np.int64),
                   {k: list(v) for k, v in d.get("curves", {}).items()},
                   {k: list(v) for k, v in d.get("raw_curves", {}).items()}, dict(d.get("provenance", {})))

    def save(self, path: os.PathLike | str) -> Path:
        from .io.atomic import write_text_atomic

        return write_text_atomic(path, json.dumps(self.to_dict(), indent=1))

    @classmethod
    def load(cls, path: os.PathLike | str) -> "SelfConsistencyModel":
        from .errors import InputFileNotFoundError

        p = Path(path)
        if not p.exists():
            raise InputFileNotFoundError(f"self-consistency model {p} does not exist; create one with `geocd consistency`")
        try:
            d = json.loads(p.read_text(encoding="utf-8"))
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise ConfigError(f"{p} is not a self-consistency model (not valid JSON text: {exc}); give the JSON "
                              "written by `geocd consistency` or a run") from exc
        if not isinstance(d, dict):
            raise ConfigError(f"{p} is not a self-consistency model (a JSON {type(d).__name__}); give the JSON "
                              "written by `geocd consistency` or a run")
        return cls.from_dict(d)

    def curves_table(self):
        """pandas DataFrame: one row per score bin (edges, centre, count, raw and smoothed curves)."""
        import pandas as pd

        d: dict[str, Any] = {"score_lo": self.score_edges[:-1], "score_hi": self.score_edges[1:],
                             "score_centre": self.score_centres, "n_pairs": self.bin_counts}
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


def learn_self_consistency(groups: Sequence[Sequence[PairDEMLike]], params: ConsistencyParams = ConsistencyParams(),
                           provenance: dict | None = None, progress: Progress | None = None) -> SelfConsistencyModel:
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
        warnings.warn(f"reconstructions with no valid cell left out of the self-consistency model: {', '.join(empty)}",
                      UserWarning, stacklevel=2)
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
    prov.setdefault("alignment", {"mode": params.align, "vertical_offsets_m": {k: round(v, 4) for k, v in offsets.items()}})
    from . import __version__

    prov.setdefault("geocd_version", __version__)
    model = SelfConsistencyModel(edges, hist.astype(np.int64), provenance=prov)
    for c in params.confidences:
        model.add_confidence(c)
    return model


# ----------------------------------------------------------------------------------------
# Stage 2
# ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ChangeParams:
    """Parameters of stage 2.

    Attributes
    ----------
    confidences : tuple of float
        Levels (percent) tested; the products report the highest level at which a cell is changed.
    combine : {"majority", "all", "any"}
        How several cross-epoch comparisons of a cell are combined: a cell is
        changed at level s when more than half ("majority"), all, or any of its
        observed comparisons exceed the curve at s, with a consistent sign.
    min_region_cells : int
        Changed cells in 8-connected groups (per sign) smaller than this are not
        reported at that level (default 4 cells = 1 m² at 0.5 m, the same minimum
        as the ``changes`` polygons and the simulator's truth mask).
    align : {"vertical", "none"}
        Shift every reconstruction of both epochs onto one vertical reference (a DEM
        epoch if given, else the least-squares fit of all their pairwise offsets) before testing.
    """

    confidences: tuple[float, ...] = (90.0, 95.0, 99.0)
    combine: str = "majority"
    min_region_cells: int = 4
    align: str = "vertical"

    def __post_init__(self) -> None:
        if self.align not in ALIGN_MODES:
            raise ConfigError(f"align must be one of {ALIGN_MODES}, got {self.align!r}")
        if self.min_region_cells < 1:
            raise ConfigError(f"min_region_cells must be ≥ 1, got {self.min_region_cells}")
        if self.combine not in ("majority", "all", "any"):
            raise ConfigError(f"combine must be majority, all or any, got {self.combine!r}")
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
    confidence : float32, highest confidence level (percent) at which the cell is changed, 0 if unchanged,
        NaN if unobserved
    change : int8, +1 raised, −1 lowered, 0 unchanged, :data:`CHANGE_NODATA` unobserved
    n_comparisons : int16, number of cross-epoch comparisons observed at the cell
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


def change_test(epoch_a: Sequence[PairDEMLike], epoch_b: Sequence[PairDEMLike], model: SelfConsistencyModel,
                params: ChangeParams = ChangeParams(), progress: Progress | None = None,
                offsets: dict[str, float] | None = None) -> ChangeResult:
    """Stage 2: test every cross-epoch comparison against the significance curves.

    For each pair (p from epoch A, q from epoch B) and each cell valid in both:
    changed at level s when |Δ̃| > curve_s(max score). Comparisons are combined
    per cell by ``params.combine`` with a consistent sign (the sign of the median
    Δz); the reported confidence is the highest level at which the combined test
    says "changed". The result does not depend on the order of the reconstructions.

    Parameters
    ----------
    epoch_a, epoch_b : reconstructions (pair-DEMs, :class:`DEMAsEpoch`) on one grid
    model : the significance curves (a whole-scene or scene-class statistic)
    offsets : {name: m}, optional
        Vertical offsets to remove (:func:`vertical_offsets`, a whole-scene statistic). Give
        them when the arrays are a tile of a larger scene, so every tile uses the same ones;
        default: computed here from the arrays given (``params.align``).
    """
    prog = ensure_progress(progress)
    if not epoch_a or not epoch_b:
        raise ProcessingError("the change test needs at least one reconstruction (pair-DEM or DEM) per epoch")
    epoch_a = sorted(epoch_a, key=lambda r: r.name)  # a deterministic order for the comparisons' names
    epoch_b = sorted(epoch_b, key=lambda r: r.name)
    na = len(epoch_a)
    if offsets is None:
        offsets = vertical_offsets(list(epoch_a) + list(epoch_b), mode=params.align)
    aligned = apply_offsets(list(epoch_a) + list(epoch_b), offsets)
    epoch_a, epoch_b = aligned[:na], aligned[na:]
    shape = epoch_a[0].z_m.shape
    comps = [(p, q) for p in epoch_a for q in epoch_b]
    levels = sorted(params.confidences)
    n = len(comps)
    dz_stack = np.full((n, *shape), np.nan, np.float32)
    dt_stack = np.full((n, *shape), np.nan, np.float32)
    score = np.full(shape, np.nan, np.float32)
    exceed = np.zeros((len(levels), n, *shape), dtype=np.int8)  # +1/-1 exceed with sign, 0 not
    for k, (p, q) in enumerate(comps):
        dt, sc, dz, both = match_pairs(p, q)
        dz_stack[k] = dz
        dt_stack[k] = dt
        score = np.fmax(score, sc)
        for li, lev in enumerate(levels):
            thr = model.threshold(sc, lev)
            ex = both & (np.abs(dt) > thr)
            exceed[li, k] = np.where(ex, np.sign(dz), 0).astype(np.int8)
        prog((k + 1) / n, f"comparison {p.name} vs {q.name}")
    nobs = np.sum(np.isfinite(dt_stack), axis=0).astype(np.int16)
    observed = nobs > 0
    with np.errstate(all="ignore"):
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            dz_med = np.nanmedian(dz_stack, axis=0)
            dt_med = np.nanmedian(dt_stack, axis=0)
    sign = np.sign(np.nan_to_num(dz_med)).astype(np.int8)
    conf = np.where(observed, 0.0, np.nan).astype(np.float32)
    for li, lev in enumerate(levels):
        agree = np.sum(exceed[li] == sign[None], axis=0) * (sign != 0)
        if params.combine == "majority":
            hit = agree * 2 > nobs
        elif params.combine == "all":
            hit = (agree == nobs) & observed
        else:
            hit = agree > 0
        hit &= observed
        if params.min_region_cells > 1:
            hit = _drop_small(hit, sign, params.min_region_cells)
        conf = np.where(hit, np.float32(lev), conf)
    change = np.where(observed, np.where(conf > 0, sign, 0), CHANGE_NODATA).astype(np.int8)
    return ChangeResult(dz_med.astype(np.float32), dt_med.astype(np.float32), score, conf, change, nobs,
                        grid=getattr(epoch_a[0], "grid", None), confidences=tuple(levels),
                        comparisons=[f"{p.name} vs {q.name}" for p, q in comps], vertical_offsets_m=offsets)


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


def naive_threshold(epoch_a: Sequence[PairDEMLike], epoch_b: Sequence[PairDEMLike], threshold: float,
                    units: str = "dtilde", combine: str = "majority", min_region_cells: int = 4,
                    align: str = "vertical") -> np.ndarray:
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
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        dz_med = np.nanmedian(np.stack(dzs), axis=0)
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
