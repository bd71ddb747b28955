"""Uncertainty of DEM differences, learned on stable terrain (Hugonnet et al. 2022 recipe).

1. **Heteroscedasticity** — the per-cell error grows with slope and curvature. The
   stable cells are binned by slope × a second predictor (maximum curvature by
   default, or roughness); the NMAD of dh in each bin is fitted by
   ``σ² = c0 + c1 tan²α + c2 q²`` (non-negative coefficients, weighted by the bin
   counts): a parametric model that extrapolates sanely to the steep slopes that
   stable terrain rarely has (a growing lava dome). The binned table is kept.
2. **Spatial correlation** — the standardized residuals z = (dh − median)/σ(cell)
   (re-scaled so that their NMAD is 1, and winsorized at ±``clip_z`` so a few
   blunders do not dominate) give an empirical variogram over *all* pairs of stable
   cells, computed exactly with FFTs (Marcotte 1996), binned by distance; it is
   fitted by a nugget + a sum of two spherical models (short and long range).
3. **Area averages and volumes** — for a set R of N cells, with C(d) the fitted
   covariance of z (C(0) = total sill),

       Var(Σ_R dh) = Σ_i Σ_j σ_i σ_j C(d_ij),

   evaluated exactly for the whole set by FFT autocorrelation of σ·1_R. The number
   of effective samples is ``n_eff = (Σ σ_i)² C(0) / Var(Σ dh)`` (N for uncorrelated
   errors, 1 for fully correlated ones), so that σ(mean dh) = σ̄ sqrt(C(0)/n_eff) as
   in xDEM; the volume σ is cell area × sqrt(Var(Σ dh)).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .._fft import fftconvolve
from ..errors import ConfigError, EmptyDataError
from .stable import nmad


# ------------------------------------------------------------------------------------------
# heteroscedasticity
# ------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ErrorParams:
    """Parameters of the error model (heteroscedasticity + variogram)."""

    predictor: str = "max_curvature"  # or "roughness_m", or "none" (slope only)
    slope_bins: int = 8
    predictor_bins: int = 4
    min_bin_cells: int = 30
    clip_z: float = 4.0
    variogram_bins: int = 30
    max_lag_m: float | None = None
    max_fft_cells: int = 4_000_000
    n_components: int = 2

    def __post_init__(self) -> None:
        if self.predictor not in ("max_curvature", "roughness_m", "none"):
            raise ConfigError(f"predictor must be max_curvature, roughness_m or none, got {self.predictor!r}")
        if self.n_components not in (1, 2):
            raise ConfigError("n_components must be 1 or 2")


@dataclass(frozen=True)
class ErrorModel:
    """σ(dh) per cell: ``sqrt(c0 + c1 tan²(slope) + c2 q²)`` × ``scale``.

    Attributes
    ----------
    coef : (c0, c1, c2) in m², m², m²/(q unit)²
    predictor : name of q ("max_curvature", "roughness_m" or "none")
    scale : NMAD of the standardized stable residuals with the raw model (≈ 1); folded in
    table : list of dict(slope_lo_deg, slope_hi_deg, q_lo, q_hi, n, nmad_m, model_m)
    """

    coef: tuple[float, float, float]
    predictor: str
    scale: float = 1.0
    table: tuple[dict, ...] = field(default_factory=tuple)

    def sigma(self, slope_rad: np.ndarray, q: np.ndarray | None = None) -> np.ndarray:
        """Per-cell 1σ (m) of dh; NaN where the predictors are NaN."""
        t2 = np.tan(np.asarray(slope_rad, np.float64)) ** 2
        v = self.coef[0] + self.coef[1] * t2
        if self.predictor != "none" and q is not None:
            v = v + self.coef[2] * np.asarray(q, np.float64) ** 2
        return (np.sqrt(v) * self.scale).astype(np.float32)

    def to_dict(self) -> dict[str, Any]:
        return {"coef": list(self.coef), "predictor": self.predictor, "scale": self.scale, "table": list(self.table)}


def _quantile_edges(v: np.ndarray, n: int) -> np.ndarray:
    e = np.unique(np.quantile(v, np.linspace(0, 1, n + 1)))
    if e.size < 2:
        e = np.array([v.min(), v.min() + 1e-9])
    e[-1] = np.nextafter(e[-1], np.inf)
    return e


def fit_error_model(
    dh_m: np.ndarray,
    stable: np.ndarray,
    slope_rad: np.ndarray,
    q: np.ndarray | None = None,
    params: ErrorParams = ErrorParams(),
) -> ErrorModel:
    """Learn σ(slope, q) from the stable cells (see module docstring).

    Raises
    ------
    EmptyDataError when there are fewer than 10 usable stable cells.
    """
    from scipy.optimize import nnls

    use_q = params.predictor != "none" and q is not None
    m = np.asarray(stable, bool) & np.isfinite(dh_m) & np.isfinite(slope_rad)
    if use_q:
        m &= np.isfinite(q)
    if m.sum() < 10:
        raise EmptyDataError(
            f"only {int(m.sum())} stable cells with slope: too few to learn the error model; "
            "give a larger stable-terrain mask"
        )
    d = np.asarray(dh_m, np.float64)[m]
    d = d - np.median(d)
    s = np.asarray(slope_rad, np.float64)[m]
    qq = np.asarray(q, np.float64)[m] if use_q else np.zeros_like(s)
    se = _quantile_edges(s, params.slope_bins)
    qe = _quantile_edges(qq, params.predictor_bins) if use_q else np.array([-np.inf, np.inf])
    si = np.clip(np.searchsorted(se, s, side="right") - 1, 0, se.size - 2)
    qi = np.clip(np.searchsorted(qe, qq, side="right") - 1, 0, qe.size - 2)
    rows, feats, w = [], [], []
    for a in range(se.size - 1):
        for b in range(qe.size - 1):
            sel = (si == a) & (qi == b)
            n = int(sel.sum())
            if n < params.min_bin_cells:
                continue
            nm = nmad(d[sel])
            t2 = float(np.median(np.tan(s[sel]) ** 2))
            q2 = float(np.median(qq[sel] ** 2)) if use_q else 0.0
            rows.append(
                {
                    "slope_lo_deg": math.degrees(se[a]),
                    "slope_hi_deg": math.degrees(se[a + 1]),
                    "q_lo": float(qe[b]) if use_q else float("nan"),
                    "q_hi": float(qe[b + 1]) if use_q else float("nan"),
                    "n": n,
                    "nmad_m": nm,
                }
            )
            feats.append((1.0, t2, q2))
            w.append(math.sqrt(n))
    if len(rows) >= 3:
        X = np.asarray(feats) * np.asarray(w)[:, None]
        y = np.asarray([r["nmad_m"] ** 2 for r in rows]) * np.asarray(w)
        if not use_q:
            X = X[:, :2]
        coef, _ = nnls(X, y)
        coef = np.append(coef, 0.0) if not use_q else coef
        if coef[0] <= 0:
            coef[0] = max(1e-6, 0.01 * nmad(d) ** 2)
    else:
        coef = np.array([max(nmad(d) ** 2, 1e-12), 0.0, 0.0])
    raw = ErrorModel((float(coef[0]), float(coef[1]), float(coef[2])), params.predictor if use_q else "none")
    sig = raw.sigma(s, qq if use_q else None).astype(np.float64)
    scale = nmad(d / sig)
    if not (np.isfinite(scale) and scale > 0):
        scale = 1.0
    for r, f in zip(rows, feats):
        r["model_m"] = float(math.sqrt(coef[0] + coef[1] * f[1] + coef[2] * f[2]) * scale)
    return ErrorModel(raw.coef, raw.predictor, float(scale), tuple(rows))


# ------------------------------------------------------------------------------------------
# variogram
# ------------------------------------------------------------------------------------------
def _fft_autocorr(a: np.ndarray, b: np.ndarray | None = None) -> np.ndarray:
    """Full cross-correlation c[l] = Σ_x a[x] b[x + l] for every lag l, centred (shape 2h−1, 2w−1)."""
    from scipy import fft

    h, w = a.shape
    sh = (fft.next_fast_len(2 * h - 1, real=True), fft.next_fast_len(2 * w - 1, real=True))
    fa = fft.rfft2(a, sh)
    fb = fa if b is None else fft.rfft2(b, sh)
    c = fft.irfft2(np.conj(fa) * fb, sh)
    # lags 0..h-1 then negative lags at the end
    c = np.roll(np.roll(c, h - 1, axis=0), w - 1, axis=1)
    return c[: 2 * h - 1, : 2 * w - 1]


def _lag_distance(shape_full: tuple[int, int], posting_xy_m: tuple[float, float]) -> np.ndarray:
    H, W = shape_full
    h, w = (H + 1) // 2, (W + 1) // 2
    ly = (np.arange(H) - (h - 1)) * posting_xy_m[1]
    lx = (np.arange(W) - (w - 1)) * posting_xy_m[0]
    return np.hypot(ly[:, None], lx[None, :])


def variogram_fft(
    values: np.ndarray, mask: np.ndarray, posting_xy_m: tuple[float, float], edges_m: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Exact empirical semivariogram of all pairs of masked cells, by FFT (Marcotte 1996).

    Returns (gamma, pair counts) per distance bin (each unordered pair counted once).
    """
    m = np.asarray(mask, bool) & np.isfinite(values)
    r, c = np.nonzero(m)
    if r.size < 2:
        nb = len(edges_m) - 1
        return np.full(nb, np.nan), np.zeros(nb, np.int64)
    sl = (slice(r.min(), r.max() + 1), slice(c.min(), c.max() + 1))
    mm = m[sl].astype(np.float64)
    ms = m[sl]
    z = np.where(ms, values[sl], 0.0).astype(np.float64)
    z = np.where(ms, z - z[ms].mean(), 0.0)
    n = _fft_autocorr(mm)
    z1 = _fft_autocorr(mm, z * z)  # Σ m(x) m(x+l) z(x+l)²
    z2 = _fft_autocorr(z * z, mm)  # Σ m(x) z(x)² m(x+l)
    zz = _fft_autocorr(z)  # Σ z(x) z(x+l)
    sq = z1 + z2 - 2.0 * zz  # Σ m m (z(x+l) − z(x))²
    dist = _lag_distance(n.shape, posting_xy_m)
    cnt = np.rint(n).astype(np.int64)
    edges = np.asarray(edges_m, np.float64)
    idx = np.searchsorted(edges, dist, side="right") - 1
    ok = (idx >= 0) & (idx < edges.size - 1) & (cnt > 0) & (dist > 0)
    nb = edges.size - 1
    counts = np.bincount(idx[ok], weights=cnt[ok], minlength=nb)
    sums = np.bincount(idx[ok], weights=np.maximum(sq[ok], 0.0), minlength=nb)
    with np.errstate(invalid="ignore", divide="ignore"):
        gamma = np.where(counts > 0, 0.5 * sums / np.maximum(counts, 1), np.nan)
    # every unordered pair appears at lag l and −l
    return gamma, (counts // 2).astype(np.int64)


def default_lag_edges(posting_m: float, max_lag_m: float, n_log: int = 30) -> np.ndarray:
    """Bin edges: one bin per pixel step up to 8 px, then log-spaced up to ``max_lag_m``."""
    lin = (np.arange(0, 9) + 0.5) * posting_m
    lin[0] = 0.5 * posting_m
    if max_lag_m <= lin[-1] * 1.2:
        return lin[lin <= max(max_lag_m, lin[1])]
    lg = np.geomspace(lin[-1], max_lag_m, n_log + 1)[1:]
    return np.concatenate([lin, lg])


def spherical(d: np.ndarray, range_m: float, sill: float) -> np.ndarray:
    """Spherical variogram component (0 at d = 0, ``sill`` beyond ``range_m``)."""
    x = np.minimum(np.asarray(d, np.float64) / max(range_m, 1e-12), 1.0)
    return sill * (1.5 * x - 0.5 * x**3)


@dataclass(frozen=True)
class VariogramModel:
    """Nugget + sum of spherical components, for standardized residuals.

    Attributes
    ----------
    nugget : float
    ranges_m, sills : tuple of floats (same length), ranges increasing
    lags_m, gamma, counts : the empirical variogram it was fitted to
    """

    nugget: float
    ranges_m: tuple[float, ...]
    sills: tuple[float, ...]
    lags_m: tuple[float, ...] = ()
    gamma: tuple[float, ...] = ()
    counts: tuple[int, ...] = ()

    @property
    def total_sill(self) -> float:
        return float(self.nugget + sum(self.sills))

    def semivariance(self, d: np.ndarray) -> np.ndarray:
        d = np.asarray(d, np.float64)
        g = np.where(d > 0, self.nugget, 0.0)
        for r, s in zip(self.ranges_m, self.sills):
            g = g + spherical(d, r, s)
        return g

    def covariance(self, d: np.ndarray) -> np.ndarray:
        """C(d) = total sill − γ(d); C(0) = total sill."""
        return self.total_sill - self.semivariance(d)

    def correlation(self, d: np.ndarray) -> np.ndarray:
        return self.covariance(d) / self.total_sill

    def to_dict(self) -> dict[str, Any]:
        return {
            "nugget": self.nugget,
            "ranges_m": list(self.ranges_m),
            "sills": list(self.sills),
            "lags_m": list(self.lags_m),
            "gamma": list(self.gamma),
            "counts": list(self.counts),
        }


def fit_variogram(
    lags_m: np.ndarray, gamma: np.ndarray, counts: np.ndarray, n_components: int = 2, max_range_m: float | None = None
) -> VariogramModel:
    """Weighted least-squares fit of nugget + 1 or 2 spherical components.

    Weights ∝ sqrt(pair count); ranges are constrained to (0, max_range_m] and ordered.
    """
    from scipy.optimize import curve_fit

    ok = np.isfinite(gamma) & (counts > 0)
    x = np.asarray(lags_m, np.float64)[ok]
    y = np.asarray(gamma, np.float64)[ok]
    cnt = np.asarray(counts, np.float64)[ok]
    if x.size < 3:
        raise EmptyDataError("too few lags with pairs to fit a variogram; the stable terrain is too small")
    rmax = float(max_range_m or x.max())
    sill = float(np.median(y[-max(3, x.size // 4) :]))
    first = float(y[0])
    sig = 1.0 / np.sqrt(cnt)

    def f1(d, n0, r1, s1):
        return np.where(d > 0, n0, 0) + spherical(d, r1, s1)

    def f2(d, n0, r1, s1, dr, s2):
        return np.where(d > 0, n0, 0) + spherical(d, r1, s1) + spherical(d, r1 + dr, s2)

    best = None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            p1, _ = curve_fit(
                f1,
                x,
                y,
                p0=[max(first * 0.3, 1e-6), min(5 * x[0], rmax), max(sill * 0.7, 1e-6)],
                sigma=sig,
                bounds=([0, 1e-6, 0], [np.inf, rmax, np.inf]),
                maxfev=20000,
            )
            best = VariogramModel(float(p1[0]), (float(p1[1]),), (float(p1[2]),))
            cost1 = float(np.sum(((f1(x, *p1) - y) / sig) ** 2))
        except (RuntimeError, ValueError):
            cost1 = np.inf
        if n_components == 2:
            try:
                p0 = [
                    max(first * 0.3, 1e-6),
                    min(3 * x[0], rmax / 4),
                    max(sill * 0.5, 1e-6),
                    rmax / 3,
                    max(sill * 0.3, 1e-6),
                ]
                p2, _ = curve_fit(
                    f2,
                    x,
                    y,
                    p0=p0,
                    sigma=sig,
                    bounds=([0, 1e-6, 0, 1e-6, 0], [np.inf, rmax, np.inf, rmax, np.inf]),
                    maxfev=40000,
                )
                cost2 = float(np.sum(((f2(x, *p2) - y) / sig) ** 2))
                if cost2 < cost1 * 0.98 or best is None:
                    r2 = min(p2[1] + p2[3], rmax)
                    best = VariogramModel(float(p2[0]), (float(p2[1]), float(r2)), (float(p2[2]), float(p2[4])))
            except (RuntimeError, ValueError):
                pass
    if best is None:
        best = VariogramModel(max(sill, 1e-12), (float(x[0]),), (0.0,))
    return VariogramModel(
        best.nugget,
        best.ranges_m,
        best.sills,
        tuple(map(float, lags_m)),
        tuple(float(g) for g in gamma),
        tuple(int(c) for c in counts),
    )


def standardized_residuals(
    dh_m: np.ndarray, sigma_m: np.ndarray, stable: np.ndarray, clip_z: float = 4.0
) -> np.ndarray:
    """z = (dh − median_stable)/σ, NaN outside stable cells, winsorized at ±clip_z."""
    m = np.asarray(stable, bool) & np.isfinite(dh_m) & np.isfinite(sigma_m) & (sigma_m > 0)
    z = np.full(np.shape(dh_m), np.nan)
    if not m.any():
        return z
    med = np.median(np.asarray(dh_m)[m])
    z[m] = (np.asarray(dh_m, np.float64)[m] - med) / np.asarray(sigma_m, np.float64)[m]
    return np.clip(z, -clip_z, clip_z)


@dataclass(frozen=True)
class VariogramPlan:
    """Which grids :func:`empirical_variogram` computes on (so that a tiled run gathers only those).

    Attributes
    ----------
    edges : distance bin edges (m)
    bbox : (row0, col0, rows, cols) of the finite cells' bounding box in the whole grid
    step : 1 = the whole box; > 1 = long lags on the box decimated by ``step`` and short lags
        on ``window`` (row0, col0, rows, cols, in the whole grid)
    """

    edges: np.ndarray
    bbox: tuple[int, int, int, int]
    step: int
    window: tuple[int, int, int, int] | None


def variogram_plan(
    bbox: tuple[int, int, int, int], posting_xy_m: tuple[float, float], params: ErrorParams = ErrorParams()
) -> VariogramPlan:
    """The :class:`VariogramPlan` for finite cells in ``bbox`` (row0, col0, rows, cols)."""
    r0, c0, hh, ww = bbox
    pm = 0.5 * (posting_xy_m[0] + posting_xy_m[1])
    diag = math.hypot(hh * posting_xy_m[1], ww * posting_xy_m[0])
    max_lag = params.max_lag_m or 0.5 * diag
    edges = default_lag_edges(pm, max_lag, params.variogram_bins)
    step = 1
    while (hh // step) * (ww // step) * 4 > params.max_fft_cells:
        step += 1
    win = None
    if step > 1:
        side = int(math.sqrt(params.max_fft_cells / 4))
        wr0 = max(0, hh // 2 - side // 2)
        wc0 = max(0, ww // 2 - side // 2)
        win = (r0 + wr0, c0 + wc0, min(side, hh - wr0), min(side, ww - wc0))
    return VariogramPlan(edges, (r0, c0, hh, ww), step, win)


def variogram_from_plan(
    plan: VariogramPlan,
    posting_xy_m: tuple[float, float],
    box: np.ndarray | None = None,
    sub: np.ndarray | None = None,
    window: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The binned variogram from the plan's grids: ``box`` (step 1), or ``sub`` (the box
    decimated by ``step``) and ``window``. Returns (lag centres m, gamma, pair counts)."""
    edges = plan.edges
    if plan.step == 1:
        g, n = variogram_fft(box, np.isfinite(box), posting_xy_m, edges)
    else:
        step = plan.step
        pm = 0.5 * (posting_xy_m[0] + posting_xy_m[1])
        # fine lags on a central window, long lags on a decimated grid
        g_long, n_long = variogram_fft(sub, np.isfinite(sub), (posting_xy_m[0] * step, posting_xy_m[1] * step), edges)
        g_short, n_short = variogram_fft(window, np.isfinite(window), posting_xy_m, edges)
        short = edges[1:] <= step * pm * 4
        g = np.where(short & (n_short > 0), g_short, g_long)
        n = np.where(short & (n_short > 0), n_short, n_long)
    centres = 0.5 * (edges[:-1] + edges[1:])
    return centres, g, n


def empirical_variogram(
    z: np.ndarray, posting_xy_m: tuple[float, float], params: ErrorParams = ErrorParams()
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Binned empirical variogram of the finite cells of ``z`` (FFT over their bounding box).

    For very large boxes (> ``max_fft_cells``) the grid is decimated by an integer factor
    first (the short lags are then estimated on the finest level only up to the factor).
    Returns (lag centres m, gamma, pair counts).
    """
    m = np.isfinite(z)
    r, c = np.nonzero(m)
    if r.size < 10:
        raise EmptyDataError("fewer than 10 stable cells: cannot estimate a variogram")
    plan = variogram_plan(
        (int(r.min()), int(c.min()), int(r.max() - r.min() + 1), int(c.max() - c.min() + 1)), posting_xy_m, params
    )
    r0, c0, hh, ww = plan.bbox
    zz = z[r0 : r0 + hh, c0 : c0 + ww]
    if plan.step == 1:
        return variogram_from_plan(plan, posting_xy_m, box=zz)
    wr0, wc0, wh, wwd = plan.window
    return variogram_from_plan(
        plan, posting_xy_m, sub=zz[:: plan.step, :: plan.step], window=z[wr0 : wr0 + wh, wc0 : wc0 + wwd]
    )


# ------------------------------------------------------------------------------------------
# correlated sums, effective samples, volume σ
# ------------------------------------------------------------------------------------------
def correlated_sum_variance(
    sigma_m: np.ndarray, mask: np.ndarray, model: VariogramModel, posting_xy_m: tuple[float, float]
) -> float:
    """Var(Σ_{i∈R} dh_i) = Σ_i Σ_j σ_i σ_j C(d_ij) over the cells of ``mask`` (exact, FFT)."""
    m = np.asarray(mask, bool) & np.isfinite(sigma_m)
    r, c = np.nonzero(m)
    if r.size == 0:
        return 0.0
    sl = (slice(r.min(), r.max() + 1), slice(c.min(), c.max() + 1))
    return _window_variance(np.where(m[sl], sigma_m[sl], 0.0), model, posting_xy_m)


def _window_variance(w: np.ndarray, model: VariogramModel, posting_xy_m: tuple[float, float]) -> float:
    """Σ_x Σ_y w(x) w(y) C(|x − y|) for a weight window w (σ inside the set, 0 outside)."""
    w = np.asarray(w, np.float64)
    if w.size == 1:
        return float(w.flat[0] ** 2 * model.total_sill)
    if w.size <= 64:
        r, c = np.nonzero(w)
        x = c * posting_xy_m[0]
        y = r * posting_xy_m[1]
        v = w[r, c]
        d = np.hypot(x[:, None] - x[None, :], y[:, None] - y[None, :])
        return float(max(np.sum(v[:, None] * v[None, :] * model.covariance(d)), 0.0))
    ac = _fft_autocorr(w)
    cov = model.covariance(_lag_distance(ac.shape, posting_xy_m))
    return float(max(np.sum(ac * cov), 0.0))


def correlated_sum_variance_ref(
    sigma_m: np.ndarray, mask: np.ndarray, model: VariogramModel, posting_xy_m: tuple[float, float]
) -> float:
    """Brute-force double sum (reference for tests; small masks only)."""
    m = np.asarray(mask, bool) & np.isfinite(sigma_m)
    r, c = np.nonzero(m)
    x = c * posting_xy_m[0]
    y = r * posting_xy_m[1]
    s = np.asarray(sigma_m, np.float64)[r, c]
    d = np.hypot(x[:, None] - x[None, :], y[:, None] - y[None, :])
    return float(np.sum(s[:, None] * s[None, :] * model.covariance(d)))


def n_effective(
    sigma_m: np.ndarray, mask: np.ndarray, model: VariogramModel, posting_xy_m: tuple[float, float]
) -> float:
    """Number of effective samples of the cells in ``mask`` (N when uncorrelated, 1 when fully correlated)."""
    m = np.asarray(mask, bool) & np.isfinite(sigma_m)
    var = correlated_sum_variance(sigma_m, m, model, posting_xy_m)
    if var <= 0:
        return float("nan")
    return float(np.sum(np.asarray(sigma_m, np.float64)[m]) ** 2 * model.total_sill / var)


@dataclass(frozen=True)
class Uncertainty:
    """Everything needed to put an honest σ on dh sums over any set of cells.

    The dh were centred on the stable terrain S (the vertical co-registration), so the
    error of Σ_R dh is Σ_R e − N_R · mean_S(e), whose variance is

        Var(Σ_R e) + N_R² Var(mean_S e) − 2 (N_R / N_S) Σ_{i∈R} σ_i K_i,

    with K_i = Σ_{j∈S} σ_j C(d_ij) precomputed for every cell (``k_field``, one FFT
    convolution). Without ``k_field`` the cross term is dropped (conservative). A median
    offset left on stable terrain (``offset_m``: the DEMs were not vertically co-registered)
    is a systematic error of N_R × offset on the sum and is added in quadrature.
    """

    error_model: ErrorModel
    variogram: VariogramModel
    sigma_m: np.ndarray  # per-cell 1σ (m), float32 (rows, cols)
    posting_xy_m: tuple[float, float]
    bias_sigma_m: float = 0.0  # σ of the stable-terrain mean
    n_eff_stable: float = float("nan")
    n_stable: int = 0
    k_field: np.ndarray | None = None  # Σ_{j∈S} σ_j C(d_ij), float64 (rows, cols)
    offset_m: float = 0.0  # median dh left on stable terrain (not removed): systematic

    def with_offset(self, offset_m: float) -> "Uncertainty":
        from dataclasses import replace

        return replace(self, offset_m=float(offset_m) if np.isfinite(offset_m) else 0.0)

    def _variance(self, w: np.ndarray, k: np.ndarray | None, include_bias: bool) -> float:
        var = _window_variance(w, self.variogram, self.posting_xy_m)
        if include_bias and self.n_stable:
            n = float(np.count_nonzero(w))
            var += (n * self.bias_sigma_m) ** 2
            if k is not None:
                var -= 2.0 * n / self.n_stable * float(np.sum(w * k))
            var = max(var, 0.0) + (n * self.offset_m) ** 2
        return max(var, 0.0)

    def sum_sigma_m(self, mask: np.ndarray, include_bias: bool = True) -> float:
        """1σ of Σ dh over ``mask`` (m)."""
        m = np.asarray(mask, bool) & np.isfinite(self.sigma_m)
        r, c = np.nonzero(m)
        if r.size == 0:
            return 0.0
        sl = (slice(r.min(), r.max() + 1), slice(c.min(), c.max() + 1))
        return self._window_sigma(m[sl], sl, include_bias)

    def _window_sigma(self, m: np.ndarray, sl: tuple[slice, slice], include_bias: bool) -> float:
        sig = self.sigma_m[sl]
        m = np.asarray(m, bool) & np.isfinite(sig)
        w = np.where(m, sig, 0.0).astype(np.float64)
        k = None if self.k_field is None else self.k_field[sl]
        return float(math.sqrt(self._variance(w, k, include_bias)))

    def volume_sigma_m3(self, mask: np.ndarray, cell_area_m2: float, include_bias: bool = True) -> float:
        """1σ of the volume Σ dh × cell area over ``mask`` (m³)."""
        return self.sum_sigma_m(mask, include_bias) * cell_area_m2

    def mean_sigma_m(self, mask: np.ndarray, include_bias: bool = True) -> float:
        n = int(np.sum(np.asarray(mask, bool) & np.isfinite(self.sigma_m)))
        return self.sum_sigma_m(mask, include_bias) / n if n else float("nan")

    def n_effective(self, mask: np.ndarray) -> float:
        return n_effective(self.sigma_m, mask, self.variogram, self.posting_xy_m)

    def volume_sigma_fn(self, cell_area_m2: float, include_bias: bool = True) -> "VolumeSigma":
        """A callable ``f(mask) → σ_V`` (m³) for :func:`geocd.change.regions.change_regions`."""
        return VolumeSigma(self, cell_area_m2, include_bias)

    def to_dict(self) -> dict[str, Any]:
        return {
            "error_model": self.error_model.to_dict(),
            "variogram": self.variogram.to_dict(),
            "bias_sigma_m": self.bias_sigma_m,
            "n_eff_stable": self.n_eff_stable,
        }


class VolumeSigma:
    """σ of the volume over a cell set: ``f(mask)``, and ``f.windowed(mask_window, slices)``
    for a set given by its bounding window (no full-grid scan: fast for many small regions)."""

    def __init__(self, unc: Uncertainty, cell_area_m2: float, include_bias: bool = True):
        self.unc = unc
        self.cell_area_m2 = float(cell_area_m2)
        self.include_bias = include_bias

    def __call__(self, mask: np.ndarray) -> float:
        return self.unc.volume_sigma_m3(mask, self.cell_area_m2, self.include_bias)

    def windowed(self, mask_window: np.ndarray, slices: tuple[slice, slice]) -> float:
        return self.unc._window_sigma(mask_window, slices, self.include_bias) * self.cell_area_m2


def estimate_uncertainty(
    dh_m: np.ndarray,
    stable: np.ndarray,
    slope_rad: np.ndarray,
    q: np.ndarray | None,
    posting_xy_m: tuple[float, float],
    params: ErrorParams = ErrorParams(),
) -> Uncertainty:
    """Heteroscedastic error model + variogram + stable-mean σ from the stable cells."""
    em = fit_error_model(dh_m, stable, slope_rad, q, params)
    sigma = em.sigma(slope_rad, q if em.predictor != "none" else None)
    # cells without a slope (edges, next to nodata) get the median σ of their neighbourhood's model: use c0
    fill = float(math.sqrt(em.coef[0]) * em.scale)
    sigma = np.where(np.isfinite(sigma), sigma, np.where(np.isfinite(dh_m), fill, np.nan)).astype(np.float32)
    z = standardized_residuals(dh_m, sigma, stable, params.clip_z)
    lags, g, n = empirical_variogram(z, posting_xy_m, params)
    r, c = np.nonzero(np.isfinite(z))
    ext = math.hypot((r.max() - r.min() + 1) * posting_xy_m[1], (c.max() - c.min() + 1) * posting_xy_m[0])
    vg = fit_variogram(lags, g, n, params.n_components, max_range_m=ext)
    st = np.isfinite(z)
    w = np.where(st, sigma, 0.0).astype(np.float64)
    k = _k_field(w, vg, posting_xy_m)
    var_sum = float(max(np.sum(w * k), 0.0))
    nst = int(st.sum())
    bias = math.sqrt(var_sum) / nst if nst else float("nan")
    neff = float(np.sum(w) ** 2 * vg.total_sill / var_sum) if var_sum > 0 else float("nan")
    return Uncertainty(em, vg, sigma, (float(posting_xy_m[0]), float(posting_xy_m[1])), bias, neff, nst, k)


def _k_field(w: np.ndarray, model: VariogramModel, posting_xy_m: tuple[float, float]) -> np.ndarray:
    """K(x) = Σ_j w_j C(|x − x_j|) on the whole grid (FFT convolution with the covariance kernel)."""
    h, wd = w.shape
    cov = model.covariance(_lag_distance((2 * h - 1, 2 * wd - 1), posting_xy_m))
    return fftconvolve(w, cov, "same")
