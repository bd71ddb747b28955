"""Gaussian-process integration of sparse detailed observations over a whole grid (arrays in, arrays out).

Sakurada's thesis (ch. 6.2.3) regresses the per-cell probability seen in the
detailed views, ``y``, on cell inputs ``x = (x, y, DEM height, coarse-image
probability, building occupancy)`` with the ARD squared-exponential kernel

    k(x_p, x_q) = σ_f² exp(−½ Σ_d (x_pd − x_qd)² / l_d²) + σ_n² δ_pq,

one length scale ``l_d`` per input (the thesis's diagonal ``W``). An exact GP
costs O(n³) time and O(n²) memory (10⁴ cells: 0.8 GB for K alone), so:

1. **Hyperparameters** (``l_d``, ``σ_f``, ``σ_n``) are fitted by exact GP
   regression on a random subsample of the observed cells: the log marginal
   likelihood and its analytic gradient, maximised by L-BFGS-B (the same
   objective as scikit-learn's ``GaussianProcessRegressor``, which has no
   additive kernel over input subsets; tested against it).
2. **Prediction** uses *all* observed cells through ``m`` inducing points
   ``Z`` (k-means centres in the kernel's scaled input space) — the DTC/SoR
   approximation in the numerically stable form of Titsias (2009) / GPflow's
   SGPR: with ``L = chol(K_mm)``, ``A = L⁻¹K_mn/σ_n``, ``B = I + AAᵀ``,
   ``L_B = chol(B)``, ``c = L_B⁻¹ L⁻¹ K_mn y / σ_n²``,

       mean_* = (L_B⁻¹ L⁻¹ K_m*)ᵀ c
       var_*  = σ_f² − |L⁻¹ K_m*|² + |L_B⁻¹ L⁻¹ K_m*|²      (latent f; + σ_n² for a new observation)

   ``AAᵀ`` and ``K_mn y`` are accumulated over batches of cells, and prediction
   runs in batches too, so memory is O(m² + m·batch) whatever the number of
   cells (10⁶ cells: see ``bench/bench_gp.py``). With ``Z`` = the training
   inputs the approximation is the exact GP (tested).

**Kernels.** ``product`` is the thesis's kernel above. With it, two cells are
alike only when they are close in *every* input, position included, so a cell
far from all detailed views falls back to the prior mean whatever the coarse
image says there. ``additive`` (the default) sums two ARD squared exponentials,
one over the position (x, y) and one over the other inputs:
``k = σ_s² exp(−½|Δxy/l_xy|²) + σ_a² exp(−½|Δa/l_a|²)``, so cells that look
alike in the coarse image, sit at a similar height and have a similar building
occupancy share their value at any distance, and nearby cells share a local
correction (measured on sample_aoi: docs/landcover.md).

Inputs are standardised (zero mean, unit variance over the observed cells) and
the target is centred and scaled; the results are returned in the target's units.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.linalg import cho_solve, cholesky, solve_triangular

from ..errors import ConfigError, EmptyDataError, ProcessingError
from ..params import ParamsMixin
from ..progress import ensure_progress

#: jitter added to K_mm's diagonal, relative to σ_f²
JITTER = 1e-6
KERNELS = ("product", "additive")
#: inputs that form the spatial component of the additive kernel
SPATIAL = ("x", "y")


@dataclass(frozen=True)
class GPParams(ParamsMixin):
    """How the GP is fitted and evaluated.

    Attributes
    ----------
    n_fit : int
        Observed cells (random subsample) for the exact-GP hyperparameter fit.
    n_inducing : int
        Inducing points of the sparse prediction (capped by the number of observed cells).
    batch : int
        Cells per batch in the accumulation and the prediction (memory ~ 8·n_inducing·batch bytes × 3).
    restarts : int
        Extra random restarts of the marginal-likelihood optimiser.
    max_train : int or None
        At most this many observed cells enter the sparse fit (random subsample; None = all).
    kernel : "product" or "additive"
        product: one ARD squared exponential over every input (the thesis's eq. 6.3); additive: an ARD
        squared exponential over the cell position (x, y) plus another over the other inputs, so cells far
        from every observation still share what looks alike (see the module docstring).
    calibrate_folds : int
        0: no calibration. k ≥ 2: the observed cells are split into k spatial blocks (k-means of x, y); the GP
        (same hyperparameters) is refitted without each block and predicts it, and σ_obs is scaled so that 68.3 %
        of the held-out standardised residuals fall within ±1σ (``sd_cal``). Held-out *blocks* mimic the
        extrapolation to unobserved areas; the scale comes from the data, never from a truth map.
    seed : int
    """

    _kind = "GP"

    n_fit: int = 1000
    n_inducing: int = 400
    batch: int = 20000
    restarts: int = 0
    max_train: int | None = None
    kernel: str = "additive"
    calibrate_folds: int = 0
    seed: int = 0

    def __post_init__(self) -> None:
        if self.kernel not in KERNELS:
            raise ConfigError(f"GP kernel must be one of {KERNELS}, got {self.kernel!r}")
        if self.n_fit < 10:
            raise ConfigError(f"n_fit must be at least 10 cells, got {self.n_fit}")
        if self.n_inducing < 1:
            raise ConfigError(f"n_inducing must be positive, got {self.n_inducing}")
        if self.batch < 1:
            raise ConfigError(f"batch must be positive, got {self.batch}")
        if self.calibrate_folds == 1 or self.calibrate_folds < 0:
            raise ConfigError(f"calibrate_folds must be 0 (off) or at least 2, got {self.calibrate_folds}")
        if self.restarts < 0:
            raise ConfigError(f"restarts must be ≥ 0, got {self.restarts}")


@dataclass
class GPHyper:
    """ARD squared-exponential hyperparameters in standardised units, and the standardisation.

    ``length_scales`` are in units of each input's standard deviation; :meth:`length_scales_units`
    gives them in the inputs' own units. ``signal_var`` and ``noise_var`` are in the target's units².
    """

    length_scales: np.ndarray
    signal_var: float
    noise_var: float
    x_mean: np.ndarray
    x_std: np.ndarray
    y_mean: float
    names: list = field(default_factory=list)
    log_marginal_likelihood: float = float("nan")
    #: kernel components: input indices of each (None = one component over every input, variance signal_var)
    groups: list | None = None
    #: signal variance of each component (target units²)
    signal_vars: list | None = None

    def components(self) -> list[tuple[np.ndarray, float]]:
        """(input indices, signal variance) of each summed squared-exponential component."""
        if self.groups is None:
            return [(np.arange(len(self.length_scales)), float(self.signal_var))]
        return [(np.asarray(g, int), float(v)) for g, v in zip(self.groups, self.signal_vars)]

    @property
    def prior_var(self) -> float:
        """k(x, x): the latent prior variance."""
        return float(sum(v for _, v in self.components()))

    def kernel(self, A: np.ndarray, B: np.ndarray) -> np.ndarray:
        """Kernel matrix between already-scaled rows A (p, d) and B (q, d) → (p, q)."""
        comps = self.components()
        out = None
        for g, v in comps:
            k = _sqexp(A[:, g] if len(comps) > 1 else A, B[:, g] if len(comps) > 1 else B, v)
            out = k if out is None else out + k
        return out

    def length_scales_units(self) -> np.ndarray:
        return self.length_scales * self.x_std

    def scale(self, X: np.ndarray) -> np.ndarray:
        """Inputs → standardised, length-scale-divided coordinates (the kernel's metric)."""
        return (np.asarray(X, np.float64) - self.x_mean) / (self.x_std * self.length_scales)

    def to_dict(self) -> dict:
        comps = [
            {"inputs": [self.names[i] if i < len(self.names) else f"x{i}" for i in g], "signal_sd": float(np.sqrt(v))}
            for g, v in self.components()
        ]
        return {
            "inputs": list(self.names),
            "components": comps,
            "length_scales": {n: float(v) for n, v in zip(self.names, self.length_scales_units())},
            "length_scales_std_units": {n: float(v) for n, v in zip(self.names, self.length_scales)},
            "signal_sd": float(np.sqrt(self.prior_var)),
            "noise_sd": float(np.sqrt(self.noise_var)),
            "mean": float(self.y_mean),
            "log_marginal_likelihood": float(self.log_marginal_likelihood),
        }


def _check_xy(X: np.ndarray, y: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray | None]:
    X = np.asarray(X, np.float64)
    if X.ndim != 2:
        raise ConfigError(f"GP inputs must be (n, d), got shape {X.shape}")
    if not np.all(np.isfinite(X)):
        raise ConfigError("GP inputs contain NaN or infinite values; drop those cells first")
    if y is not None:
        y = np.asarray(y, np.float64).ravel()
        if y.shape[0] != X.shape[0]:
            raise ConfigError(f"{X.shape[0]} input rows but {y.shape[0]} targets")
        if not np.all(np.isfinite(y)):
            raise ConfigError("GP targets contain NaN; use observed cells only")
    return X, y


def fit_hyperparameters(
    X: np.ndarray, y: np.ndarray, params: GPParams = GPParams(), names: list | None = None
) -> GPHyper:
    """Exact-GP marginal-likelihood fit of the kernel on a random subsample of (X, y).

    Parameters
    ----------
    X : (n, d) inputs of the observed cells; y : (n,) targets
    names : input names; with ``params.kernel == "additive"`` the inputs named in :data:`SPATIAL` form the
        spatial component (when there are none, or nothing else, the kernel is a single component).
    """
    X, y = _check_xy(X, y)
    n, d = X.shape
    if n < max(10, d + 2):
        raise EmptyDataError(
            f"only {n} observed cells for a GP with {d} inputs; the detailed views must observe "
            "more of the area (or use a finer grid)"
        )
    names = list(names) if names is not None else [f"x{i}" for i in range(d)]
    x_mean = X.mean(axis=0)
    x_std = X.std(axis=0)
    const = x_std <= 1e-12
    x_std = np.where(const, 1.0, x_std)
    y_mean = float(y.mean())
    y_sd = float(y.std()) or 1.0
    rng = np.random.default_rng(params.seed)
    idx = rng.choice(n, min(n, params.n_fit), replace=False)
    Xs = (X[idx] - x_mean) / x_std
    ys = (y[idx] - y_mean) / y_sd
    spatial = [i for i, nm in enumerate(names) if nm in SPATIAL]
    other = [i for i in range(d) if i not in spatial]
    groups = [spatial, other] if params.kernel == "additive" and spatial and other else [list(range(d))]
    ls, sv, nv, lml = _fit_ml(Xs, ys, groups, params.restarts, rng)
    ls = np.where(const, 1e3, ls)  # a constant input carries no information
    sv = [v * y_sd**2 for v in sv]
    return GPHyper(
        length_scales=ls,
        signal_var=float(sum(sv)),
        noise_var=float(nv) * y_sd**2,
        x_mean=x_mean,
        x_std=x_std,
        y_mean=y_mean,
        names=names,
        log_marginal_likelihood=float(lml),
        groups=groups if len(groups) > 1 else None,
        signal_vars=sv if len(groups) > 1 else None,
    )


#: bounds of the log hyperparameters (standardised inputs and target)
_LOG_LS = (np.log(1e-2), np.log(1e3))
_LOG_SV = (np.log(1e-4), np.log(1e2))
_LOG_NV = (np.log(1e-5), np.log(1e1))


def _nll(theta: np.ndarray, X: np.ndarray, y: np.ndarray, groups: list) -> tuple[float, np.ndarray]:
    """Negative log marginal likelihood of a sum of ARD squared exponentials + noise, and its gradient.

    ``theta`` = log length scales (d), log signal variances (one per group), log noise variance.
    """
    n, d = X.shape
    G = len(groups)
    ls = np.exp(theta[:d])
    sv = np.exp(theta[d : d + G])
    nv = float(np.exp(theta[-1]))
    S = X / ls
    comps = []
    K = np.zeros((n, n))
    for g, v in zip(groups, sv):
        kg = _sqexp(S[:, g], S[:, g], v)
        comps.append(kg)
        K += kg
    K[np.diag_indices(n)] += nv
    try:
        L = cholesky(K, lower=True)
    except np.linalg.LinAlgError:
        return 1e25, np.zeros_like(theta)
    alpha = cho_solve((L, True), y)
    nll = 0.5 * y @ alpha + np.log(np.diag(L)).sum() + 0.5 * n * np.log(2 * np.pi)
    W = np.outer(alpha, alpha) - cho_solve((L, True), np.eye(n))  # ααᵀ − K⁻¹
    grad = np.zeros_like(theta)
    for gi, (g, kg) in enumerate(zip(groups, comps)):
        Wk = W * kg
        grad[d + gi] = -0.5 * Wk.sum()
        for i in g:
            diff2 = (S[:, i, None] - S[None, :, i]) ** 2
            grad[i] = -0.5 * (Wk * diff2).sum()
    grad[-1] = -0.5 * nv * np.trace(W)
    return float(nll), grad


def _fit_ml(X: np.ndarray, y: np.ndarray, groups: list, restarts: int, rng) -> tuple:
    """Maximise the marginal likelihood (L-BFGS-B, analytic gradient) from a default start + random restarts."""
    from scipy.optimize import minimize

    d = X.shape[1]
    G = len(groups)
    bounds = [_LOG_LS] * d + [_LOG_SV] * G + [_LOG_NV]
    starts = [np.concatenate([np.zeros(d), np.full(G, np.log(0.5 / G)), [np.log(0.1)]])]
    for _ in range(restarts):
        starts.append(np.array([rng.uniform(lo, hi) for lo, hi in bounds]))
    best = None
    for t0 in starts:
        r = minimize(_nll, t0, args=(X, y, groups), jac=True, method="L-BFGS-B", bounds=bounds)
        if best is None or r.fun < best.fun:
            best = r
    th = best.x
    return np.exp(th[:d]), list(np.exp(th[d : d + G])), float(np.exp(th[-1])), -float(best.fun)


def _sqexp(A: np.ndarray, B: np.ndarray, signal_var: float) -> np.ndarray:
    """σ_f² exp(−½|a − b|²) for already-scaled rows of A (p, d) and B (q, d) → (p, q)."""
    d2 = (A * A).sum(1)[:, None] + (B * B).sum(1)[None, :] - 2.0 * (A @ B.T)
    np.maximum(d2, 0.0, out=d2)
    return signal_var * np.exp(-0.5 * d2)


def choose_inducing(X: np.ndarray, hyper: GPHyper, m: int, seed: int = 0, max_kmeans: int = 100_000) -> np.ndarray:
    """``m`` inducing inputs: k-means centres of the cells in the kernel's scaled space (returned unscaled)."""
    from sklearn.cluster import MiniBatchKMeans

    X = np.asarray(X, np.float64)
    n = X.shape[0]
    if m >= n:
        return X.copy()
    rng = np.random.default_rng(seed)
    sub = X[rng.choice(n, min(n, max_kmeans), replace=False)]
    S = hyper.scale(sub)
    km = MiniBatchKMeans(n_clusters=m, random_state=seed, n_init=3, batch_size=max(1024, 4 * m))
    km.fit(S)
    C = km.cluster_centers_
    return C * (hyper.x_std * hyper.length_scales) + hyper.x_mean


class SparseGP:
    """DTC/SoR sparse GP with fixed hyperparameters (see the module docstring).

    Parameters
    ----------
    hyper : GPHyper
    Z : (m, d) inducing inputs (in the inputs' units)
    """

    def __init__(self, hyper: GPHyper, Z: np.ndarray):
        self.hyper = hyper
        self.Zs = hyper.scale(Z)
        m = self.Zs.shape[0]
        Kmm = hyper.kernel(self.Zs, self.Zs)
        Kmm[np.diag_indices(m)] += JITTER * hyper.prior_var
        try:
            self.L = cholesky(Kmm, lower=True)
        except np.linalg.LinAlgError as exc:  # pragma: no cover - jitter makes this rare
            raise ProcessingError("the inducing-point covariance is singular; use fewer inducing points") from exc
        self.LB = None
        self.c = None
        self.n_train = 0

    def fit(self, X: np.ndarray, y: np.ndarray, batch: int = 20000, progress=None) -> "SparseGP":
        """Accumulate ``AAᵀ = Σ_batches (L⁻¹K_mb)(L⁻¹K_mb)ᵀ / σ_n²`` and ``L⁻¹K_mn y`` over the training cells.

        Whitening each batch before the product keeps ``AAᵀ`` a Gram matrix (positive semi-definite in floating
        point too), however ill-conditioned ``K_mm`` is.
        """
        X, y = _check_xy(X, y)
        prog = ensure_progress(progress)
        h = self.hyper
        m = self.Zs.shape[0]
        AAT = np.zeros((m, m))
        r = np.zeros(m)
        n = X.shape[0]
        yc = y - h.y_mean
        for s in range(0, n, batch):
            T = solve_triangular(self.L, h.kernel(self.Zs, h.scale(X[s : s + batch])), lower=True)
            AAT += T @ T.T
            r += T @ yc[s : s + batch]
            prog(min(1.0, (s + batch) / n), f"sparse GP: {min(n, s + batch)}/{n} training cells")
        B = AAT / h.noise_var + np.eye(m)
        self.LB = cholesky(0.5 * (B + B.T), lower=True)
        self.c = solve_triangular(self.LB, r, lower=True) / h.noise_var
        self.n_train = n
        return self

    def predict(self, X: np.ndarray, batch: int = 20000, progress=None) -> tuple[np.ndarray, np.ndarray]:
        """Predictive mean and latent standard deviation at X (n, d), in batches.

        Returns
        -------
        mean, sd_f : float64 (n,); the sd of a new noisy observation is ``sqrt(sd_f² + noise_var)``.
        """
        if self.c is None:
            raise ProcessingError("SparseGP.predict before fit")
        X, _ = _check_xy(X)
        prog = ensure_progress(progress)
        h = self.hyper
        n = X.shape[0]
        mean = np.empty(n)
        var = np.empty(n)
        for s in range(0, n, batch):
            Kms = h.kernel(self.Zs, h.scale(X[s : s + batch]))
            t1 = solve_triangular(self.L, Kms, lower=True)
            t2 = solve_triangular(self.LB, t1, lower=True)
            mean[s : s + batch] = t2.T @ self.c + h.y_mean
            var[s : s + batch] = h.prior_var - (t1 * t1).sum(0) + (t2 * t2).sum(0)
            prog(min(1.0, (s + batch) / n), f"sparse GP: {min(n, s + batch)}/{n} cells predicted")
        return mean, np.sqrt(np.maximum(var, 0.0))


def exact_gp(
    X: np.ndarray, y: np.ndarray, Xs: np.ndarray, hyper: GPHyper, batch: int = 5000
) -> tuple[np.ndarray, np.ndarray]:
    """Exact GP prediction with fixed hyperparameters (numpy/scipy Cholesky; O(n²) memory, O(n³) time).

    The reference the sparse approximation is checked and benchmarked against.
    Returns mean and latent sd at ``Xs``.
    """
    X, y = _check_xy(X, y)
    Xs, _ = _check_xy(Xs)
    S = hyper.scale(X)
    K = hyper.kernel(S, S)
    K[np.diag_indices(K.shape[0])] += hyper.noise_var
    L = cholesky(K, lower=True, overwrite_a=True)
    del K
    alpha = cho_solve((L, True), y - hyper.y_mean)
    mean = np.empty(Xs.shape[0])
    var = np.empty(Xs.shape[0])
    for s in range(0, Xs.shape[0], batch):
        Ks = hyper.kernel(S, hyper.scale(Xs[s : s + batch]))
        mean[s : s + batch] = Ks.T @ alpha + hyper.y_mean
        v = solve_triangular(L, Ks, lower=True)
        var[s : s + batch] = hyper.prior_var - (v * v).sum(0)
    return mean, np.sqrt(np.maximum(var, 0.0))


@dataclass
class GPResult:
    """A GP integration on a grid.

    Attributes
    ----------
    mean : float32 (rows, cols), predictive mean (target units; NaN where an input is missing)
    sd : float32 (rows, cols), predictive sd of the latent value
    sd_obs : float32 (rows, cols), predictive sd of a new observation (latent ⊕ noise)
    hyper : GPHyper
    report : dict (sizes, timings)
    sd_cal : float32 (rows, cols) or None, ``sd_obs`` × the held-out calibration scale (``calibrate_folds``)
    """

    mean: np.ndarray
    sd: np.ndarray
    sd_obs: np.ndarray
    hyper: GPHyper
    report: dict
    sd_cal: np.ndarray | None = None


def _stack(inputs: dict, shape: tuple | None = None) -> tuple[list, np.ndarray, np.ndarray]:
    names = list(inputs)
    stack = [np.asarray(inputs[k], np.float64) for k in names]
    shape = shape if shape is not None else stack[0].shape
    for k, a in zip(names, stack):
        if a.shape != shape:
            raise ConfigError(f"GP input {k!r} has shape {a.shape}, expected {shape}")
    have = np.all([np.isfinite(a) for a in stack], axis=0)
    return names, stack, have


def fit_integrator(
    target: np.ndarray, inputs: dict, params: GPParams = GPParams(), progress=None
) -> tuple[SparseGP, dict]:
    """Fit the GP on the observed cells of one grid (or window): hyperparameters, inducing points, DTC terms.

    Returns the fitted :class:`SparseGP` (its ``hyper.names`` are the input names, in order) and a report.
    Predict any window of the same inputs with :func:`predict_window` (tiling: fit once, predict per tile).
    """
    import time

    prog = ensure_progress(progress)
    if not inputs:
        raise ConfigError("the GP needs at least one input (e.g. the cells' x, y)")
    t = np.asarray(target, np.float64)
    names, stack, have = _stack(inputs, t.shape)
    obs = have & np.isfinite(t)
    n_obs = int(obs.sum())
    if n_obs == 0:
        raise EmptyDataError("no cell is both observed by the detailed views and covered by every input")
    X_obs = np.stack([a[obs] for a in stack], axis=1)
    y_obs = t[obs]
    rep: dict = {"cells": int(t.size), "cells_with_inputs": int(have.sum()), "observed_cells": n_obs}
    t0 = time.perf_counter()
    prog(0.02, f"exact-GP hyperparameters on {min(n_obs, params.n_fit)} of {n_obs} observed cells")
    hyper = fit_hyperparameters(X_obs, y_obs, params, names)
    rep["hyper_fit_s"] = round(time.perf_counter() - t0, 2)
    rng = np.random.default_rng(params.seed + 1)
    if params.max_train is not None and n_obs > params.max_train:
        sel = rng.choice(n_obs, params.max_train, replace=False)
        X_tr, y_tr = X_obs[sel], y_obs[sel]
    else:
        X_tr, y_tr = X_obs, y_obs
    t0 = time.perf_counter()
    Z = choose_inducing(X_tr, hyper, params.n_inducing, params.seed)
    gp = SparseGP(hyper, Z).fit(X_tr, y_tr, params.batch, progress=lambda f, m="": prog(0.3 + 0.3 * (f or 0), m))
    rep["sparse_fit_s"] = round(time.perf_counter() - t0, 2)
    rep["inducing_points"] = int(Z.shape[0])
    rep["training_cells"] = int(X_tr.shape[0])
    rep["hyper"] = hyper.to_dict()
    return gp, rep


def predict_window(
    gp: SparseGP, inputs: dict, batch: int = 20000, progress=None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Predictive mean, latent sd and observation sd (float32 (rows, cols), NaN where an input is missing)
    of a fitted GP on any window of the inputs (same names as the fit)."""
    names, stack, have = _stack(inputs)
    if names != list(gp.hyper.names):
        raise ConfigError(f"inputs {names} differ from the fitted GP's {gp.hyper.names}")
    shape = stack[0].shape
    mean = np.full(shape, np.nan, np.float32)
    sdf = np.full(shape, np.nan, np.float32)
    if have.any():
        mu, sd = gp.predict(np.stack([a[have] for a in stack], axis=1), batch, progress=progress)
        mean[have] = mu
        sdf[have] = sd
    sdo = np.sqrt(sdf.astype(np.float64) ** 2 + gp.hyper.noise_var).astype(np.float32)
    return mean, sdf, sdo


def integrate(target: np.ndarray, inputs: dict, params: GPParams = GPParams(), progress=None) -> GPResult:
    """GP regression of a sparse per-cell target on per-cell inputs, predicted at every cell.

    Parameters
    ----------
    target : float (rows, cols), the detailed views' probability; NaN = unobserved
    inputs : mapping name → float (rows, cols) (e.g. ``x``, ``y``, ``dem``, ``coarse``, ``buildings``);
        cells where any input is NaN get no prediction
    params : GPParams

    Returns
    -------
    GPResult
    """
    import time

    prog = ensure_progress(progress)
    gp, rep = fit_integrator(target, inputs, params, progress=lambda f, m="": prog(0.6 * (f or 0), m))
    t0 = time.perf_counter()
    mean, sdf, sdo = predict_window(gp, inputs, params.batch, progress=lambda f, m="": prog(0.6 + 0.4 * (f or 0), m))
    rep["predict_s"] = round(time.perf_counter() - t0, 2)
    sd_cal = None
    if params.calibrate_folds:
        scale, cal = heldout_sigma_scale(target, inputs, gp.hyper, params)
        rep["calibration"] = cal
        sd_cal = (sdo * scale).astype(np.float32)
    return GPResult(mean=mean, sd=sdf, sd_obs=sdo, hyper=gp.hyper, report=rep, sd_cal=sd_cal)


def heldout_sigma_scale(target: np.ndarray, inputs: dict, hyper: GPHyper, params: GPParams) -> tuple[float, dict]:
    """Scale of σ_obs from spatial-block cross-validation of the observed cells (see ``GPParams.calibrate_folds``).

    Returns the scale and a report (folds, held-out cells, coverage of ±1σ/±2σ before and after scaling).
    """
    from sklearn.cluster import KMeans

    t = np.asarray(target, np.float64)
    names, stack, have = _stack(inputs, t.shape)
    obs = have & np.isfinite(t)
    X = np.stack([a[obs] for a in stack], axis=1)
    y = t[obs]
    rows, cols = np.nonzero(obs)
    k = int(params.calibrate_folds)
    rng = np.random.default_rng(params.seed + 7)
    pts = np.column_stack([rows, cols]).astype(float)
    sub = pts[rng.choice(len(pts), min(len(pts), 20000), replace=False)]
    km = KMeans(n_clusters=k, n_init=3, random_state=params.seed).fit(sub)
    fold = km.predict(pts)
    z = []
    for f in range(k):
        te = fold == f
        tr = ~te
        if te.sum() == 0 or tr.sum() < 10:
            continue
        Xtr, ytr = X[tr], y[tr]
        if params.max_train is not None and len(ytr) > params.max_train:
            sel = rng.choice(len(ytr), params.max_train, replace=False)
            Xtr, ytr = Xtr[sel], ytr[sel]
        Z = choose_inducing(Xtr, hyper, params.n_inducing, params.seed)
        gp = SparseGP(hyper, Z).fit(Xtr, ytr, params.batch)
        mu, sd = gp.predict(X[te], params.batch)
        z.append((y[te] - mu) / np.sqrt(sd**2 + hyper.noise_var))
    if not z:
        return 1.0, {"note": "too few observed cells to calibrate"}
    az = np.abs(np.concatenate(z))
    scale = float(max(np.quantile(az, 0.6827), 1e-6))
    return scale, {
        "folds": k,
        "held_out_cells": int(az.size),
        "scale": round(scale, 4),
        "inside_1sigma_before": round(float(np.mean(az <= 1)), 4),
        "inside_2sigma_before": round(float(np.mean(az <= 2)), 4),
        "inside_2sigma_after": round(float(np.mean(az <= 2 * scale)), 4),
    }
