"""Co-registration of a DEM onto a reference on stable terrain (Nuth & Kääb 2011).

If DEM B is DEM A displaced horizontally by d = (d_e, d_n) and raised by d_z, then
on terrain of slope α and aspect ψ (azimuth of steepest descent)

    dh = B − A ≈ tan α · (d_e sin ψ + d_n cos ψ) + d_z,

so ``dh / tan α = a cos(b − ψ) + c`` with d_e = a sin b, d_n = a cos b (Nuth & Kääb
2011, eq. 3). Each iteration takes the stable cells, removes the median dh, takes
the median of dh / tan α in aspect bins, fits the three coefficients by linear least
squares (the cosine is linear in a cos b, a sin b, c), moves B by −d and repeats
until the increment is below ``tolerance_px`` (0.001 px, as xDEM). The vertical
shift is then the median
of −dh on all stable cells; an optional plane (``tilt=True``) removes a residual
vertical tilt.

**Convention**: the reported shift ``t = (t_e, t_n, t_z)`` is the translation
applied to B: ``B_aligned(x, y) = B(x − t_e, y − t_n) + t_z`` (the same as xDEM's
``shift_x, shift_y, shift_z``).

**Honesty checks.** A fit is *under-constrained* when too few stable cells carry
slope (``min_cells``), when their aspects do not cover enough of the compass
(``min_octants`` of 8 octants), when the block-jackknife 1σ of the horizontal shift
exceeds ``max_sigma_px`` pixels, or when the iteration does not converge. What
happens then is ``on_underconstrained``: ``"vertical_only"`` (default: keep B's
position, apply only the median vertical offset when at least
``min_vertical_cells`` stable cells exist), ``"apply"`` (apply anyway, as xDEM
does), ``"none"`` (apply nothing) or ``"raise"``. The same action follows when a
well-constrained shift does not lower the stable-terrain NMAD
(``require_improvement``, status ``"not_improving"``): then B is not simply A
translated (systematic DEM errors dominate) and moving it does not help. Without stable terrain nothing is
applied and the status says so: geocd never invents a shift.

**σ of the shift.** Stable cells are grouped in ``block_px`` × ``block_px`` blocks,
the blocks dealt into ``jackknife_groups`` groups, and the Nuth–Kääb bin fit repeated
without each group on the final residuals (delete-a-group jackknife); blocks larger
than the error correlation length make it honest about spatially correlated
errors. As a model check, the least-squares fit of the linearized model
``dh = tan α (e sin ψ + n cos ψ) + z`` is evaluated at the solution: the two
estimators weight slopes differently and agree when B really is A translated; where
they do not (systematic DEM errors that depend on slope and aspect), half their
disagreement (``model_disagreement_m``) is added to the σ in quadrature. Optional
Gauss–Newton steps on the linearized model (``refine_steps``, default 0) replace the
Nuth–Kääb estimate by the least-squares one.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from ..errors import ConfigError, ProcessingError
from ..progress import Progress, ensure_progress
from ._kernels import shift_grid, shift_window, terrain_attributes
from .stable import nmad

UNDERCONSTRAINED_ACTIONS = ("vertical_only", "apply", "none", "raise")


@dataclass(frozen=True)
class CoregParams:
    """Parameters of :func:`nuth_kaab`."""

    max_iterations: int = 30
    tolerance_px: float = 0.001
    aspect_bins: int = 36
    min_bin_cells: int = 8
    min_slope_deg: float = 3.0
    max_slope_deg: float = 70.0
    outlier_nmad: float = 5.0
    min_cells: int = 300
    min_octants: int = 6
    max_sigma_px: float = 0.35
    block_px: int = 16
    min_blocks: int = 6
    resampling: str = "bilinear"
    refine_steps: int = 0
    jackknife_groups: int = 20
    max_fit_cells: int = 200_000
    horizontal: bool = True
    vertical: bool = True
    tilt: bool = False
    on_underconstrained: str = "vertical_only"
    min_vertical_cells: int = 30
    require_improvement: bool = True
    min_improvement: float = 0.0

    def __post_init__(self) -> None:
        if self.on_underconstrained not in UNDERCONSTRAINED_ACTIONS:
            raise ConfigError(
                f"on_underconstrained must be one of {UNDERCONSTRAINED_ACTIONS}, got {self.on_underconstrained!r}"
            )
        if self.resampling not in ("bilinear", "cubic"):
            raise ConfigError(f"resampling must be 'bilinear' or 'cubic', got {self.resampling!r}")
        if self.max_iterations < 1 or self.tolerance_px <= 0 or self.aspect_bins < 8:
            raise ConfigError("max_iterations ≥ 1, tolerance_px > 0 and aspect_bins ≥ 8 are required")
        if not (0 <= self.min_slope_deg < self.max_slope_deg <= 90):
            raise ConfigError("0 ≤ min_slope_deg < max_slope_deg ≤ 90 is required")


@dataclass(frozen=True)
class CoregResult:
    """What co-registration found and what it applied.

    Attributes
    ----------
    shift_m : (east, north, up) translation **applied** to B (zeros when nothing was applied)
    fitted_shift_m : (east, north, up) what the fit found, applied or not
    shift_sigma_m : (east, north, up) 1σ of the fitted shift: block jackknife (+ half the
        Nuth–Kääb / least-squares disagreement for the horizontal components); inf when unknown
    model_disagreement_m : (east, north) least-squares shift still seen at the Nuth–Kääb solution
    tilt : (dz/dx, dz/dy) of the applied vertical plane (m per m), or None
    status : "ok", "underconstrained", "not_improving", "no_stable_terrain", "not_converged" or "disabled"
    applied : "horizontal+vertical", "vertical", "none"
    reasons : why the fit is not trusted (empty when ok)
    """

    shift_m: tuple[float, float, float]
    fitted_shift_m: tuple[float, float, float]
    shift_sigma_m: tuple[float, float, float]
    status: str
    applied: str
    reasons: tuple[str, ...] = ()
    tilt: tuple[float, float] | None = None
    iterations: int = 0
    converged: bool = False
    n_stable: int = 0
    n_fit: int = 0
    octants: int = 0
    n_blocks: int = 0
    median_before_m: float = float("nan")
    nmad_before_m: float = float("nan")
    median_after_m: float = float("nan")
    nmad_after_m: float = float("nan")
    posting_xy_m: tuple[float, float] = (float("nan"), float("nan"))
    model_disagreement_m: tuple[float, float] = (float("nan"), float("nan"))
    history_m: tuple[tuple[float, float], ...] = field(default_factory=tuple)

    @property
    def shift_px(self) -> tuple[float, float]:
        """Applied horizontal shift in pixels (east, north)."""
        return (self.shift_m[0] / self.posting_xy_m[0], self.shift_m[1] / self.posting_xy_m[1])

    @property
    def fitted_shift_px(self) -> tuple[float, float]:
        return (self.fitted_shift_m[0] / self.posting_xy_m[0], self.fitted_shift_m[1] / self.posting_xy_m[1])

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["shift_px"] = self.shift_px
        d["fitted_shift_px"] = self.fitted_shift_px
        return d

    def summary(self) -> str:
        e, n, z = self.fitted_shift_m
        se, sn, sz = self.shift_sigma_m
        s = (
            f"Nuth–Kääb: fitted shift (E {e:+.2f} ± {se:.2f}, N {n:+.2f} ± {sn:.2f}, Z {z:+.2f} ± {sz:.2f}) m "
            f"on {self.n_fit} stable cells ({self.octants}/8 aspect octants), {self.iterations} iterations; "
            f"status {self.status}, applied {self.applied}"
        )
        if self.reasons:
            s += " (" + "; ".join(self.reasons) + ")"
        return s


def apply_shift(
    height_m: np.ndarray,
    shift_m: tuple[float, float, float],
    posting_xy_m: tuple[float, float],
    *,
    tilt: tuple[float, float] | None = None,
    resampling: str = "bilinear",
) -> np.ndarray:
    """Translate a DEM by ``shift_m`` = (east, north, up) metres (and add an optional plane).

    ``out(x, y) = h(x − t_e, y − t_n) + t_z [+ a (x − x_c) + b (y − y_c)]`` on a north-up
    grid with posting ``posting_xy_m``; (x_c, y_c) is the grid centre.
    """
    te, tn, tz = shift_m
    h = np.asarray(height_m, np.float64)
    if te != 0.0 or tn != 0.0:
        h = shift_grid(h, te / posting_xy_m[0], -tn / posting_xy_m[1], resampling)
    out = h + tz
    if tilt is not None:
        out = out + _plane(h.shape, posting_xy_m, tilt)
    return out.astype(np.float32)


def _plane(shape, posting_xy_m, tilt, origin: tuple[int, int] = (0, 0), window_shape=None) -> np.ndarray:
    """``tilt[0]·x + tilt[1]·y`` with (x, y) metres from the centre of a grid of ``shape``, on the
    window of ``window_shape`` cells starting at ``origin`` (the whole grid by default)."""
    nr, nc = shape
    r0, c0 = origin
    wr, wc = window_shape or shape
    x = (np.arange(c0, c0 + wc) - (nc - 1) / 2.0) * posting_xy_m[0]
    y = -(np.arange(r0, r0 + wr) - (nr - 1) / 2.0) * posting_xy_m[1]
    return tilt[0] * x[None, :] + tilt[1] * y[:, None]


def plane_at_cells(rows: np.ndarray, cols: np.ndarray, shape, posting_xy_m, tilt) -> np.ndarray:
    """:func:`_plane` at the cells (rows, cols) of a grid of ``shape`` (the same values)."""
    nr, nc = shape
    x = (cols - (nc - 1) / 2.0) * posting_xy_m[0]
    y = -(rows - (nr - 1) / 2.0) * posting_xy_m[1]
    return tilt[0] * x + tilt[1] * y


def _fit_bins(y: np.ndarray, aspect: np.ndarray, nbins: int, min_cells: int) -> tuple[np.ndarray, int] | None:
    """Least-squares fit of y = A cos ψ + B sin ψ + C to the aspect-bin medians of y."""
    idx = np.minimum((aspect / (2 * math.pi) * nbins).astype(np.int64), nbins - 1)
    order = np.argsort(idx, kind="stable")
    idx_s = idx[order]
    y_s = y[order]
    bounds = np.searchsorted(idx_s, np.arange(nbins + 1))
    med = np.full(nbins, np.nan)
    cnt = np.diff(bounds)
    for k in range(nbins):
        if cnt[k] >= min_cells:
            med[k] = np.median(y_s[bounds[k] : bounds[k + 1]])
    ok = np.isfinite(med)
    if ok.sum() < 4:
        return None
    centre = (np.arange(nbins) + 0.5) * 2 * math.pi / nbins
    X = np.column_stack([np.cos(centre[ok]), np.sin(centre[ok]), np.ones(ok.sum())])
    coef, *_ = np.linalg.lstsq(X, med[ok], rcond=None)
    return coef, int(ok.sum())


def _octants(aspect: np.ndarray, min_cells: int) -> int:
    o = np.minimum((aspect / (2 * math.pi) * 8).astype(np.int64), 7)
    return int(np.sum(np.bincount(o, minlength=8) >= min_cells))


def _jackknife(
    dh: np.ndarray,
    tan_a: np.ndarray,
    aspect: np.ndarray,
    rows: np.ndarray,
    cols: np.ndarray,
    block_px: int,
    min_blocks: int,
) -> tuple[np.ndarray, np.ndarray, int]:
    """Block-jackknife of the linearized shift model; returns (beta, sigma, n_blocks)."""
    X = np.column_stack([tan_a * np.sin(aspect), tan_a * np.cos(aspect), np.ones_like(dh)])
    ncb = int(cols.max()) // block_px + 1 if cols.size else 1
    blk = (rows // block_px) * ncb + (cols // block_px)
    ub, inv = np.unique(blk, return_inverse=True)
    K = ub.size
    xtx = np.zeros((K, 3, 3))
    xty = np.zeros((K, 3))
    for i in range(3):
        xty[:, i] = np.bincount(inv, weights=X[:, i] * dh, minlength=K)
        for j in range(i, 3):
            v = np.bincount(inv, weights=X[:, i] * X[:, j], minlength=K)
            xtx[:, i, j] = v
            xtx[:, j, i] = v
    A = xtx.sum(0)
    b = xty.sum(0)
    try:
        beta = np.linalg.solve(A, b)
    except np.linalg.LinAlgError:
        return np.full(3, np.nan), np.full(3, np.inf), K
    if K < min_blocks:
        return beta, np.full(3, np.inf), K
    loo = np.empty((K, 3))
    for k in range(K):
        try:
            loo[k] = np.linalg.solve(A - xtx[k], b - xty[k])
        except np.linalg.LinAlgError:
            return beta, np.full(3, np.inf), K
    var = (K - 1) / K * np.sum((loo - loo.mean(0)) ** 2, axis=0)
    return beta, np.sqrt(var), K


@dataclass(frozen=True)
class StableCells:
    """Values of the stable cells with heights in both DEMs, in row-major order (a cell table).

    What :func:`coregister_cells` needs from the grids: gathered from whole arrays by
    :func:`nuth_kaab`, or tile by tile by the tiled pipeline. When ``n_total`` exceeds the
    number of rows the table is a deterministic subsample of the stable cells.

    Attributes
    ----------
    rows, cols : int64 (n,), whole-grid indices
    a_m, b_m : float64 (n,), heights of A and B
    slope_rad, aspect_rad : float64 (n,), of A (NaN where the 3×3 window is incomplete)
    shape : (rows, cols) of the whole grid
    n_total : number of stable cells in the whole grid
    """

    rows: np.ndarray
    cols: np.ndarray
    a_m: np.ndarray
    b_m: np.ndarray
    slope_rad: np.ndarray
    aspect_rad: np.ndarray
    shape: tuple[int, int]
    n_total: int


@dataclass(frozen=True)
class CoregPlan:
    """What co-registration applies to B: ``out = B(shifted) + tz − plane`` (float32).

    ``shift_px`` = (columns, rows) of :func:`~geocd.demdiff._kernels.shift_grid` (None: B as
    it is); ``plane`` = (a, b) of ``a·x + b·y`` subtracted (x, y from the whole grid's centre).
    """

    shift_px: tuple[float, float] | None
    tz_m: float
    plane: tuple[float, float] | None
    resampling: str = "bilinear"

    def apply(
        self,
        tba_m: np.ndarray,
        posting_xy_m: tuple[float, float],
        origin: tuple[int, int] = (0, 0),
        full_shape: tuple[int, int] | None = None,
    ) -> np.ndarray:
        """B co-registered (float32) on a window of the grid starting at ``origin`` (whole grid by default).

        A window's cells get exactly the values they get on the whole grid as long as the
        window holds the interpolation support of its cells (see :func:`shift_window`).
        """
        B = np.asarray(tba_m, np.float64)
        shape = full_shape or B.shape
        if self.shift_px is not None:
            if origin == (0, 0) and tuple(shape) == B.shape:
                B = shift_grid(B, self.shift_px[0], self.shift_px[1], self.resampling)
            else:
                B = shift_window(B, origin, shape, self.shift_px[0], self.shift_px[1], self.resampling)
        out = B + self.tz_m
        if self.plane is not None:
            out = out - _plane(shape, posting_xy_m, self.plane, origin, B.shape)
        return out.astype(np.float32)


class GridCoregData:
    """:func:`coregister_cells`' access to two whole grids (what :func:`nuth_kaab` uses)."""

    def __init__(
        self,
        A: np.ndarray,
        B: np.ndarray,
        stable: np.ndarray,
        posting_xy_m: tuple[float, float],
        resampling: str = "bilinear",
    ):
        self.A = A
        self.B = B
        self.resampling = resampling
        rows, cols = np.nonzero(stable)
        terr = terrain_attributes(A, posting_xy_m)
        self.cells = StableCells(
            rows,
            cols,
            A[rows, cols],
            B[rows, cols],
            terr["slope_rad"][rows, cols].astype(np.float64),
            terr["aspect_rad"][rows, cols].astype(np.float64),
            A.shape,
            int(rows.size),
        )

    def sample_b(self, idx: np.ndarray, dcol: float, drow: float) -> np.ndarray:
        """B shifted by (dcol, drow) px at the table's cells ``idx``."""
        Bs = shift_grid(self.B, dcol, drow, self.resampling)
        return Bs[self.cells.rows[idx], self.cells.cols[idx]]

    def shifted_b(self, dcol: float, drow: float) -> np.ndarray:
        """B shifted by (dcol, drow) px at every cell of the table."""
        Bs = shift_grid(self.B, dcol, drow, self.resampling)
        return Bs[self.cells.rows, self.cells.cols]


def nuth_kaab(
    ref_m: np.ndarray,
    tba_m: np.ndarray,
    stable: np.ndarray,
    posting_xy_m: tuple[float, float],
    params: CoregParams = CoregParams(),
    progress: Progress | None = None,
    initial_shift_m: tuple[float, float] = (0.0, 0.0),
) -> tuple[np.ndarray, CoregResult]:
    """Co-register ``tba_m`` (B) onto ``ref_m`` (A) on stable terrain.

    Parameters
    ----------
    ref_m, tba_m : float (rows, cols) on the same north-up grid, NaN = nodata
    stable : bool (rows, cols), stable terrain
    posting_xy_m : (x, y) cell size in metres
    initial_shift_m : (east, north) start of the iteration (e.g. from a previous pass)

    Returns
    -------
    aligned : float32 (rows, cols), B after the applied shift (B itself when nothing was applied)
    result : CoregResult
    """
    A = np.asarray(ref_m, np.float64)
    B = np.asarray(tba_m, np.float64)
    if A.shape != B.shape or np.shape(stable) != A.shape:
        raise ConfigError(f"reference {A.shape}, DEM {B.shape} and stable mask {np.shape(stable)} must share one grid")
    st = np.asarray(stable, bool) & np.isfinite(A) & np.isfinite(B)
    data = GridCoregData(A, B, st, posting_xy_m, params.resampling)
    res, plan = coregister_cells(data, posting_xy_m, params, progress, initial_shift_m)
    return plan.apply(B, posting_xy_m), res


def coregister_cells(
    data,
    posting_xy_m: tuple[float, float],
    params: CoregParams = CoregParams(),
    progress: Progress | None = None,
    initial_shift_m: tuple[float, float] = (0.0, 0.0),
) -> tuple[CoregResult, CoregPlan]:
    """Nuth & Kääb on a table of stable cells (see the module docstring).

    Parameters
    ----------
    data : an object with ``cells`` (:class:`StableCells`), ``sample_b(idx, dcol, drow)`` (B shifted
        by (dcol, drow) px at the table's cells ``idx``) and ``shifted_b(dcol, drow)`` (at every
        cell): :class:`GridCoregData` for whole grids, or a tiled reader

    Returns
    -------
    result : CoregResult
    plan : CoregPlan, what to apply to B
    """
    prog = ensure_progress(progress)
    p = params
    c = data.cells
    shape = tuple(c.shape)
    px, py = float(posting_xy_m[0]), float(posting_xy_m[1])
    n_stable = int(c.n_total)
    n_tab = int(c.rows.size)
    dh0 = c.b_m - c.a_m
    med0 = float(np.median(dh0)) if n_tab else float("nan")
    nm0 = nmad(dh0) if n_tab else float("nan")
    base = dict(n_stable=n_stable, median_before_m=med0, nmad_before_m=nm0, posting_xy_m=(px, py))
    zero = (0.0, 0.0, 0.0)
    inf3 = (math.inf, math.inf, math.inf)
    nothing = CoregPlan(None, 0.0, None, p.resampling)
    if not (p.horizontal or p.vertical or p.tilt):
        return CoregResult(zero, zero, inf3, "disabled", "none", **base, median_after_m=med0, nmad_after_m=nm0), nothing
    if n_stable < max(p.min_vertical_cells, 3):
        reason = (
            f"no stable terrain ({n_stable} stable cells with heights in both DEMs, "
            f"at least {max(p.min_vertical_cells, 3)} needed)"
        )
        if p.on_underconstrained == "raise":
            raise ProcessingError(reason + "; give a stable-terrain mask (--stable-mask) or disable co-registration")
        return CoregResult(
            zero, zero, inf3, "no_stable_terrain", "none", (reason,), **base, median_after_m=med0, nmad_after_m=nm0
        ), nothing

    slope = c.slope_rad
    aspect = c.aspect_rad
    fidx = np.nonzero(
        np.isfinite(slope) & (slope >= math.radians(p.min_slope_deg)) & (slope <= math.radians(p.max_slope_deg))
    )[0]
    if p.max_fit_cells and fidx.size > p.max_fit_cells:
        # a fixed random subsample (as xDEM's): the fit and its jackknife stay fast on large DEMs
        pick = np.sort(np.random.default_rng(0).choice(fidx.size, p.max_fit_cells, replace=False))
        fidx = fidx[pick]
    rows, cols = c.rows[fidx], c.cols[fidx]
    tan_a = np.tan(slope[fidx])
    asp = aspect[fidx]
    a_fit = c.a_m[fidx]
    reasons: list[str] = []
    te, tn = float(initial_shift_m[0]), float(initial_shift_m[1])
    history: list[tuple[float, float]] = []
    converged = False
    it = 0
    n_fit = int(rows.size)
    if p.horizontal and n_fit >= 20:
        bs = c.b_m[fidx]
        for it in range(1, p.max_iterations + 1):
            if te != 0.0 or tn != 0.0:
                bs = data.sample_b(fidx, te / px, -tn / py)
            d = bs - a_fit
            ok = np.isfinite(d)
            if ok.sum() < 20:
                reasons.append("the shifted DEM left the stable cells (shift diverged)")
                break
            dd = d[ok]
            if p.tilt:
                dd = dd - _plane_at(dd, rows[ok], cols[ok], shape, (px, py))
            m = np.median(dd)
            s = nmad(dd)
            keep = np.abs(dd - m) <= max(p.outlier_nmad * s, 1e-6) if s > 0 else np.ones(dd.size, bool)
            y = (dd[keep] - m) / tan_a[ok][keep]
            fit = _fit_bins(y, asp[ok][keep], p.aspect_bins, p.min_bin_cells)
            if fit is None:
                reasons.append("too few aspect bins with enough stable cells for the Nuth–Kääb fit")
                break
            (ca, cb, _), _nb = fit
            # displacement of the current B relative to A: d_n = ca (cos term), d_e = cb (sin term)
            de, dn = float(cb), float(ca)
            te -= de
            tn -= dn
            history.append((te, tn))
            prog(min(0.9, it / p.max_iterations), f"Nuth–Kääb iteration {it}: shift E {te:+.3f} N {tn:+.3f} m")
            if math.hypot(de / px, dn / py) < p.tolerance_px:
                converged = True
                break
            if math.hypot(te / px, tn / py) > 0.25 * min(shape):
                reasons.append("the horizontal shift diverged beyond a quarter of the grid")
                break
        if not converged and not reasons:
            reasons.append(f"no convergence to {p.tolerance_px} px in {p.max_iterations} iterations")
    if p.horizontal and n_fit < p.min_cells:
        reasons.append(
            f"only {n_fit} stable cells with slope in [{p.min_slope_deg}, {p.max_slope_deg}]° "
            f"(at least {p.min_cells} needed)"
        )

    # Gauss–Newton polish on the linearized model (the estimator whose jackknife σ is reported)
    if p.horizontal and converged and n_fit >= 20:
        for _ in range(p.refine_steps):
            bs = data.sample_b(fidx, te / px, -tn / py) if (te or tn) else c.b_m[fidx]
            d = bs - a_fit
            ok = np.isfinite(d)
            if ok.sum() < 20:
                break
            m, s_ = float(np.median(d[ok])), nmad(d[ok])
            keep = ok & (np.abs(np.where(ok, d, m) - m) <= max(p.outlier_nmad * s_, 1e-6))
            X = np.column_stack(
                [tan_a[keep] * np.sin(asp[keep]), tan_a[keep] * np.cos(asp[keep]), np.ones(int(keep.sum()))]
            )
            beta, *_ = np.linalg.lstsq(X, d[keep], rcond=None)
            te -= float(beta[0])
            tn -= float(beta[1])
            history.append((te, tn))
            if math.hypot(beta[0] / px, beta[1] / py) < 0.1 * p.tolerance_px:
                break
    # vertical offset after the horizontal fit
    bh = data.shifted_b(te / px, -tn / py) if (te or tn) else c.b_m
    dh1 = bh - c.a_m
    st1 = np.isfinite(dh1)
    tz = -float(np.median(dh1[st1])) if st1.sum() else 0.0

    # jackknife and coverage diagnostics on the final residuals
    sig = np.full(3, math.inf)
    octs = 0
    nblk = 0
    disagree = (math.nan, math.nan)
    if n_fit:
        d = dh1[fidx] + tz
        ok = np.isfinite(d)
        if p.tilt and ok.sum() >= 10:
            d = np.where(ok, d - _plane_at(np.where(ok, d, 0.0), rows, cols, shape, (px, py), ok), np.nan)
        keep = ok.copy()
        if ok.any():
            s, m = nmad(d[ok]), float(np.median(d[ok]))
            if s > 0:
                keep = ok & (np.abs(np.where(ok, d, m) - m) <= p.outlier_nmad * s)
        octs = _octants(asp[keep], max(p.min_bin_cells, int(0.01 * keep.sum())))
        if keep.sum() >= 10:
            n_fit = int(keep.sum())
            dk = d[keep]
            yk = (dk - np.median(dk)) / tan_a[keep]
            se, sn, nblk = _nk_jackknife(
                yk,
                asp[keep],
                rows[keep],
                cols[keep],
                p.aspect_bins,
                p.min_bin_cells,
                p.block_px,
                p.jackknife_groups,
                p.min_blocks,
            )
            # cross-check: the least-squares shift still seen at the Nuth–Kääb solution. The two estimators
            # weight slopes differently; where the pure-translation model does not hold they disagree,
            # and half the disagreement is added to the σ (honest about model error).
            beta, _, _ = _jackknife(dk, tan_a[keep], asp[keep], rows[keep], cols[keep], p.block_px, 1)
            if np.all(np.isfinite(beta)):
                disagree = (float(beta[0]), float(beta[1]))
                se = math.hypot(se, 0.5 * beta[0])
                sn = math.hypot(sn, 0.5 * beta[1])
            sig[:2] = (se, sn)
    # vertical σ: jackknife over all stable cells (flat ones included)
    sz = _block_sigma_of_median(dh1[st1], c.rows[st1], c.cols[st1], p.block_px, p.min_blocks)
    sig = np.array([sig[0], sig[1], sz])

    if p.horizontal:
        if n_fit < p.min_cells and not any(r.startswith("only ") for r in reasons):
            reasons.append(f"{n_fit} stable cells with usable slope (at least {p.min_cells} needed)")
        if octs < p.min_octants:
            reasons.append(f"stable slopes face only {octs} of 8 aspect octants (at least {p.min_octants} needed)")
        hs = math.hypot(sig[0] / px, sig[1] / py)
        if not math.isfinite(hs):
            reasons.append(
                f"horizontal uncertainty unknown (stable cells in {nblk} blocks of {p.block_px} px, "
                f"at least {p.min_blocks} needed)"
            )
        elif hs > p.max_sigma_px:
            reasons.append(f"horizontal shift 1σ {hs:.2f} px exceeds {p.max_sigma_px} px")
    reasons = list(dict.fromkeys(reasons))
    status = (
        "ok"
        if not reasons
        else (
            "not_converged"
            if (p.horizontal and not converged and len(reasons) == 1 and reasons[0].startswith("no convergence"))
            else "underconstrained"
        )
    )
    # a well-constrained shift must also make the stable terrain agree better (NMAD is blind to the
    # vertical offset, so this compares B moved horizontally with B as it is, on the same cells)
    nm_shift = nm_raw = float("nan")
    if status == "ok" and p.horizontal and p.require_improvement and (te or tn):
        both = st1 & np.isfinite(dh0)
        if both.sum() >= 10:
            d1, d0 = dh1[both], dh0[both]
            if p.tilt:  # compare after removing each one's plane
                rb, cb_ = c.rows[both], c.cols[both]
                d1 = d1 - _plane_at(d1, rb, cb_, shape, (px, py))
                d0 = d0 - _plane_at(d0, rb, cb_, shape, (px, py))
            nm_shift, nm_raw = nmad(d1), nmad(d0)
            if nm_shift > nm_raw * (1.0 - p.min_improvement):
                status = "not_improving"
                reasons.append(
                    f"the horizontal shift does not improve the stable terrain (NMAD {nm_shift:.2f} m with "
                    f"it, {nm_raw:.2f} m without): B is not simply A translated"
                )
    fitted = (te, tn, tz)
    trusted = status == "ok"
    action = p.on_underconstrained
    if not trusted and action == "raise":
        raise ProcessingError(
            "co-registration is under-constrained: "
            + "; ".join(reasons)
            + "; give a better stable-terrain mask or pass on_underconstrained='vertical_only'"
        )
    apply_h = p.horizontal and (trusted or action == "apply")
    apply_v = p.vertical and (trusted or action in ("apply", "vertical_only")) and st1.sum() >= p.min_vertical_cells
    bout = bh if apply_h else c.b_m
    tz_applied = 0.0
    if apply_v:
        tz_applied = -float(np.median((bout - c.a_m)[np.isfinite(bout)])) if apply_h else -med0
    out = bout + tz_applied
    tilt = None
    plane = None
    if p.tilt and (trusted or action == "apply") and n_stable >= max(p.min_vertical_cells, 10):
        dd = out - c.a_m
        fin = np.isfinite(dd)
        plane = _fit_plane_cells(c.rows[fin], c.cols[fin], dd[fin], shape, (px, py))
        out = out - plane_at_cells(c.rows, c.cols, shape, (px, py), plane)
        tilt = (-plane[0], -plane[1])
    applied = (
        "horizontal+vertical"
        if (apply_h and apply_v)
        else ("horizontal" if apply_h else ("vertical" if apply_v else "none"))
    )
    dh_after = out - c.a_m
    sa = np.isfinite(dh_after)
    prog(1.0, "co-registration done")
    res = CoregResult(
        shift_m=(te if apply_h else 0.0, tn if apply_h else 0.0, tz_applied),
        fitted_shift_m=fitted,
        shift_sigma_m=tuple(float(v) for v in sig),
        status=status,
        applied=applied,
        reasons=tuple(reasons),
        tilt=tilt,
        iterations=it,
        converged=converged,
        n_fit=n_fit,
        octants=octs,
        n_blocks=nblk,
        model_disagreement_m=disagree,
        median_after_m=float(np.median(dh_after[sa])) if sa.any() else float("nan"),
        nmad_after_m=nmad(dh_after[sa]) if sa.any() else float("nan"),
        history_m=tuple(history),
        **base,
    )
    shift = (te / px, -tn / py) if (apply_h and (te or tn)) else None
    return res, CoregPlan(shift, tz_applied, plane, p.resampling)


def _nk_jackknife(
    y: np.ndarray,
    aspect: np.ndarray,
    rows: np.ndarray,
    cols: np.ndarray,
    nbins: int,
    min_cells: int,
    block_px: int,
    groups: int,
    min_blocks: int,
) -> tuple[float, float, int]:
    """Delete-a-group block jackknife of the Nuth–Kääb bin fit → 1σ of (d_e, d_n) and the block count.

    Cells are grouped in ``block_px`` blocks; blocks are dealt (seeded shuffle) into ``groups``
    groups; the fit is repeated without each group.
    """
    ncb = int(cols.max()) // block_px + 1
    blk = (rows // block_px) * ncb + (cols // block_px)
    ub, inv = np.unique(blk, return_inverse=True)
    K = ub.size
    if K < min_blocks:
        return math.inf, math.inf, K
    G = min(groups, K)
    perm = np.random.default_rng(12345).permutation(K)
    grp = (perm % G)[inv]
    est = []
    for k in range(G):
        keep = grp != k
        f = _fit_bins(y[keep], aspect[keep], nbins, min_cells)
        if f is None:
            return math.inf, math.inf, K
        est.append((f[0][1], f[0][0]))
    e = np.asarray(est)
    var = (G - 1) / G * np.sum((e - e.mean(0)) ** 2, axis=0)
    return float(math.sqrt(var[0])), float(math.sqrt(var[1])), K


def _block_sigma_of_median(d: np.ndarray, rows: np.ndarray, cols: np.ndarray, block_px: int, min_blocks: int) -> float:
    """Block-jackknife 1σ of the mean, × 1.2533 for the median (a proxy for the median's σ under
    spatially correlated errors)."""
    ok = np.isfinite(d)
    d, rows, cols = d[ok], rows[ok], cols[ok]
    if d.size < 3:
        return math.inf
    s = nmad(d)
    if s > 0:
        keep = np.abs(d - np.median(d)) <= 5 * s
        d, rows, cols = d[keep], rows[keep], cols[keep]
    ncb = int(cols.max()) // block_px + 1
    blk = (rows // block_px) * ncb + (cols // block_px)
    ub, inv = np.unique(blk, return_inverse=True)
    K = ub.size
    if K < min_blocks:
        return math.inf
    sums = np.bincount(inv, weights=d, minlength=K)
    cnt = np.bincount(inv, minlength=K).astype(float)
    tot, n = sums.sum(), cnt.sum()
    loo = (tot - sums) / (n - cnt)
    # × sqrt(π/2): the median's σ relative to the mean's for Gaussian errors
    return float(1.2533 * math.sqrt((K - 1) / K * np.sum((loo - loo.mean()) ** 2)))


def _plane_at(
    d: np.ndarray, rows: np.ndarray, cols: np.ndarray, shape, posting_xy_m, use: np.ndarray | None = None
) -> np.ndarray:
    """A robust plane fitted to values ``d`` at cells (rows, cols), evaluated there (intercept excluded)."""
    nr, nc = shape
    x = (cols - (nc - 1) / 2.0) * posting_xy_m[0]
    y = -(rows - (nr - 1) / 2.0) * posting_xy_m[1]
    keep = np.ones(d.size, bool) if use is None else use.copy()
    coef = np.zeros(3)
    for _ in range(4):
        X = np.column_stack([x[keep], y[keep], np.ones(int(keep.sum()))])
        coef, *_ = np.linalg.lstsq(X, d[keep], rcond=None)
        res = d - (coef[0] * x + coef[1] * y + coef[2])
        s = nmad(res[keep])
        new = np.abs(res - np.median(res[keep])) <= 3 * max(s, 1e-9)
        if use is not None:
            new &= use
        if np.array_equal(new, keep) or new.sum() < 10:
            break
        keep = new
    return coef[0] * x + coef[1] * y


def _fit_plane(dh: np.ndarray, stable: np.ndarray, posting_xy_m) -> tuple[float, float]:
    """Robust (iteratively reweighted, Tukey-like cut at 3 NMAD) plane slope of dh on stable cells."""
    r, c = np.nonzero(stable & np.isfinite(dh))
    return _fit_plane_cells(r, c, dh[r, c], dh.shape, posting_xy_m)


def _fit_plane_cells(r: np.ndarray, c: np.ndarray, z: np.ndarray, shape, posting_xy_m) -> tuple[float, float]:
    """:func:`_fit_plane` on the values ``z`` of the cells (r, c) (row-major order) of a grid of ``shape``."""
    nr, nc = shape
    x = (c - (nc - 1) / 2.0) * posting_xy_m[0]
    y = -(r - (nr - 1) / 2.0) * posting_xy_m[1]
    keep = np.ones(z.size, bool)
    coef = np.zeros(3)
    for _ in range(5):
        X = np.column_stack([x[keep], y[keep], np.ones(keep.sum())])
        coef, *_ = np.linalg.lstsq(X, z[keep], rcond=None)
        res = z - (coef[0] * x + coef[1] * y + coef[2])
        s = nmad(res)
        new = np.abs(res - np.median(res)) <= 3 * max(s, 1e-9)
        if np.array_equal(new, keep) or new.sum() < 10:
            break
        keep = new
    return float(coef[0]), float(coef[1])
