"""Per-cell significance of dh against the stable-terrain distribution.

The DEM-only analogue of the self-consistency curves: on stable terrain, the
standardized residual ``z = (dh − m)/σ(slope, q)`` (σ from the heteroscedastic
error model, m the stable median) has an empirical distribution that holds every
error source the two DEMs really have, heavy tails included. A cell is *changed at
confidence s* when |z| exceeds the s-quantile of |z| on stable terrain; its
*confidence* is the empirical CDF of |z_stable| at its own |z| (0–1). Because σ
depends on slope and curvature, the threshold in metres is conditioned on them:
``threshold_s(cell) = q_s(|z|) × σ(cell)``. :meth:`SignificanceModel.curves` tabulates
those thresholds against slope for plots and reports.

No Gaussian assumption is made for the cells; the region-level test in
:mod:`geocd.change.regions` uses the variogram-based volume σ instead (sums of many
correlated cells are close to Gaussian).

**Minimum mapping unit from the noise** (:func:`noise_region_null`, :func:`noise_region_filter`).
A region of changed cells is itself a statistic: correlated noise makes clusters of cells
that each pass the cell test. A region's combined evidence is its cluster mass Σ log(α/p_i)
(p_i = 1 − the cell's confidence, α = 1 − the map's level; the self-consistency change
test's region evidence, :func:`geocd.consistency.candidate_regions`). Its null is the masses
of the regions that noise alone forms under the same cell test: fields of standardized
residuals simulated with the fitted variogram's correlation (a Gaussian copula: under no
change each cell's confidence is uniform, and neighbours are dependent as the stable terrain's
z are). A region is kept when its mass exceeds the share ``level`` of the noise regions'
masses (:func:`geocd.consistency.null_region_confidence`) — nothing in it is a constant chosen
on a scene; the unit grows with the correlation range and with the level.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ..consistency import candidate_regions, cluster_evidence, null_region_confidence
from ..errors import EmptyDataError


@dataclass(frozen=True)
class SignificanceModel:
    """Empirical distribution of |z| on stable terrain.

    Attributes
    ----------
    abs_z_sorted : float64 (n,), sorted |z| of the stable cells
    center_m : the stable median removed before standardizing
    """

    abs_z_sorted: np.ndarray
    center_m: float

    @property
    def n(self) -> int:
        return int(self.abs_z_sorted.size)

    def confidence_of_z(self, z: np.ndarray) -> np.ndarray:
        """Empirical CDF of |z_stable| at |z| (NaN → NaN), in [0, 1)."""
        a = np.abs(np.asarray(z, np.float64))
        out = np.full(a.shape, np.nan)
        ok = np.isfinite(a)
        # fraction of stable cells with |z_stable| < |z| (strict: ties do not count as exceeded)
        out[ok] = np.searchsorted(self.abs_z_sorted, a[ok], side="left") / (self.n + 1.0)
        return out

    def threshold_z(self, level: float) -> float:
        """|z| above which a cell is changed at ``level`` (0–1)."""
        if not 0 < level < 1:
            raise ValueError(f"confidence level must be in (0, 1), got {level}")
        k = int(np.ceil(level * (self.n + 1.0))) - 1
        if k >= self.n:
            return float("inf")
        return float(self.abs_z_sorted[max(k, 0)])

    def max_level(self) -> float:
        """The highest confidence this stable sample can support (n/(n+1))."""
        return self.n / (self.n + 1.0)

    def curves(self, error_model, levels=(0.9, 0.95, 0.99), slopes_deg=None, q: float = 0.0) -> dict[str, Any]:
        """Threshold |dh| (m) vs slope for each level, at predictor value ``q``."""
        s = np.arange(0, 61, 5.0) if slopes_deg is None else np.asarray(slopes_deg, float)
        sig = error_model.sigma(np.radians(s), np.full(s.shape, q))
        return {"slope_deg": s.tolist(), **{f"{lv:g}": (self.threshold_z(lv) * sig).tolist() for lv in levels}}

    def to_dict(self) -> dict[str, Any]:
        qs = [0.5, 0.68, 0.9, 0.95, 0.99, 0.999]
        return {
            "n_stable": self.n,
            "center_m": self.center_m,
            "abs_z_quantiles": {f"{q:g}": self.threshold_z(q) for q in qs if q < self.max_level()},
        }


def fit_significance(dh_m: np.ndarray, sigma_m: np.ndarray, stable: np.ndarray) -> SignificanceModel:
    """The stable-terrain |z| distribution (needs ≥ 20 stable cells)."""
    m = np.asarray(stable, bool) & np.isfinite(dh_m) & np.isfinite(sigma_m) & (sigma_m > 0)
    if m.sum() < 20:
        raise EmptyDataError(f"only {int(m.sum())} stable cells: too few to test significance")
    d = np.asarray(dh_m, np.float64)[m]
    c = float(np.median(d))
    z = np.sort(np.abs((d - c) / np.asarray(sigma_m, np.float64)[m]))
    return SignificanceModel(z, c)


def significance_map(dh_m: np.ndarray, sigma_m: np.ndarray, model: SignificanceModel) -> tuple[np.ndarray, np.ndarray]:
    """Per-cell standardized residual z and confidence (0–1, NaN where dh or σ is NaN)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        z = (np.asarray(dh_m, np.float64) - model.center_m) / np.asarray(sigma_m, np.float64)
    return z.astype(np.float32), model.confidence_of_z(z).astype(np.float32)


def change_sign(
    dh_m: np.ndarray,
    confidence: np.ndarray,
    level: float,
    center_m: float = 0.0,
    observed: np.ndarray | None = None,
    nodata: int | None = None,
) -> np.ndarray:
    """int8 +1 raised / −1 lowered / 0 unchanged at ``level``; ``nodata`` (e.g. −128) where not observed.

    ``nodata=None`` writes 0 there (the form :func:`geocd.change.regions.change_regions` takes).
    """
    conf = np.nan_to_num(np.asarray(confidence, np.float64), nan=0.0)
    d = np.nan_to_num(np.asarray(dh_m, np.float64) - center_m, nan=0.0)
    s = np.where(conf >= level, np.sign(d), 0).astype(np.int8)
    if observed is not None and nodata is not None:
        s = np.where(observed, s, np.int8(nodata)).astype(np.int8)
    return s


def _torus_spectrum(vg, posting_xy_m: tuple[float, float], size: int) -> np.ndarray:
    """The circulant embedding's eigenvalues (rfft2 of the correlation on a 2·size torus), clipped at 0."""
    m = 2 * size
    i = np.minimum(np.arange(m), m - np.arange(m))
    d = np.hypot(i[None, :] * float(posting_xy_m[0]), i[:, None] * float(posting_xy_m[1]))
    lam = np.fft.rfft2(vg.correlation(d)).real
    return np.maximum(lam, 0.0)  # circulant embedding: ranges beyond the torus clip a little


def _torus_field(
    vg, posting_xy_m: tuple[float, float], size: int, rng: np.random.Generator, lam: np.ndarray | None = None
) -> np.ndarray:
    """One ``size``² field of unit variance with the variogram's correlation (FFT on a 2·size torus).

    ``lam``: :func:`_torus_spectrum` of the same arguments, when the caller draws many fields.
    """
    m = 2 * size
    if lam is None:
        lam = _torus_spectrum(vg, posting_xy_m, size)
    w = np.fft.rfft2(rng.standard_normal((m, m)))
    f = np.fft.irfft2(np.sqrt(lam) * w, s=(m, m))[:size, :size]
    return f / np.sqrt(np.mean(lam))


def noise_region_null(
    vg,
    posting_xy_m: tuple[float, float],
    level_pct: float,
    min_cells: int = 1,
    *,
    size: int = 512,
    min_regions: int = 2000,
    max_fields: int = 48,
    seed: int = 0,
) -> np.ndarray:
    """Sorted cluster masses of the regions noise alone forms at ``level_pct`` (see module docstring).

    Parameters
    ----------
    vg : :class:`geocd.demdiff.uncertainty.VariogramModel` of the standardized residuals
    posting_xy_m : cell size (x, y) in metres
    level_pct : the map's confidence (percent); cells with p = 1 − confidence < 1 − level form regions
    min_cells : regions smaller than this are not regions (the map's ``min_region_cells``: the null is
        the regions the map would report)
    size : side of each simulated field (cells); fields are simulated until ``min_regions`` null
        regions or ``max_fields`` fields (fixed seed: the same model gives the same null)

    The null depends on these arguments only; the last few are kept (a process that differences
    several DEM pairs with the same error model simulates it once). The array returned is read-only.
    """
    key = (
        float(vg.nugget),
        tuple(map(float, vg.ranges_m)),
        tuple(map(float, vg.sills)),
        float(posting_xy_m[0]),
        float(posting_xy_m[1]),
        float(level_pct),
        int(min_cells),
        int(size),
        int(min_regions),
        int(max_fields),
        int(seed),
    )
    hit = _NULL_CACHE.get(key)
    if hit is not None:
        return hit
    from scipy.special import erfc

    alpha = 1.0 - float(level_pct) / 100.0
    rng = np.random.default_rng(seed)
    lam = _torus_spectrum(vg, posting_xy_m, int(size))
    masses: list[np.ndarray] = []
    n = 0
    for _ in range(int(max_fields)):
        g = _torus_field(vg, posting_xy_m, int(size), rng, lam)
        pv = erfc(np.abs(g) / np.sqrt(2.0))
        _, mass, _ = candidate_regions(pv, np.sign(g).astype(np.int8), alpha, int(min_cells))
        masses.append(mass)
        n += mass.size
        if n >= min_regions:
            break
    out = np.sort(np.concatenate(masses)) if masses else np.zeros(0)
    out.flags.writeable = False
    if len(_NULL_CACHE) >= 8:
        _NULL_CACHE.pop(next(iter(_NULL_CACHE)))
    _NULL_CACHE[key] = out
    return out


#: the last few region nulls (see :func:`noise_region_null`)
_NULL_CACHE: dict[tuple, np.ndarray] = {}


def noise_region_filter(
    sign: np.ndarray, confidence_pct: np.ndarray, level_pct: float, null_masses: np.ndarray, min_cells: int = 1
) -> tuple[np.ndarray, dict[str, Any]]:
    """Drop the regions of ``sign`` whose combined evidence noise alone reaches (see module docstring).

    Parameters
    ----------
    sign : int8 (rows, cols) +1/−1/0, the cell test's changed cells (0 where not observed)
    confidence_pct : float (rows, cols), each cell's confidence (percent)
    null_masses : sorted masses from :func:`noise_region_null`

    Returns
    -------
    sign : the same with the cells of non-significant regions set to 0
    info : regions tested / dropped, cells dropped, the mass a region needs
    """
    from scipy import ndimage

    alpha = 1.0 - float(level_pct) / 100.0
    ev = cluster_evidence(1.0 - np.asarray(confidence_pct, np.float64) / 100.0, alpha)
    out = np.asarray(sign, np.int8).copy()
    tested = dropped = dropped_cells = 0
    for s in (1, -1):
        lab, n = ndimage.label(out == s, structure=np.ones((3, 3), bool))
        if n == 0:
            continue
        size = np.bincount(lab.ravel(), minlength=n + 1)
        mass = np.bincount(lab.ravel(), weights=ev.ravel(), minlength=n + 1)
        big = size >= max(int(min_cells), 1)
        big[0] = False
        drop = big & (region_noise_confidence(mass, null_masses) < float(level_pct))
        if not resolvable(null_masses, level_pct):
            drop[:] = False
        tested += int(big.sum())
        dropped += int(drop.sum())
        dropped_cells += int(size[drop].sum())
        out[drop[lab]] = 0
    return out, {
        "regions_tested": tested,
        "regions_dropped": dropped,
        "cells_dropped": dropped_cells,
        "null_regions": int(np.asarray(null_masses).size),
        "mass_needed": noise_mass_needed(null_masses, level_pct),
    }


def resolvable(null_masses: np.ndarray, level_pct: float) -> bool:
    """Enough noise regions to tell the ``level_pct`` share of them (else noise seldom forms regions of
    the mapping unit's size, and every region is kept)."""
    return np.asarray(null_masses).size * (1.0 - float(level_pct) / 100.0) >= 1.0


def region_noise_confidence(mass: np.ndarray, null_masses: np.ndarray) -> np.ndarray:
    """Confidence (percent) of regions with cluster mass ``mass`` against the noise regions."""
    return null_region_confidence([null_masses], mass)


def noise_mass_needed(null_masses: np.ndarray, level_pct: float) -> float:
    """The smallest cluster mass a region needs to be kept at ``level_pct``."""
    ms = np.asarray(null_masses, float)
    if not resolvable(ms, level_pct):
        return float("nan")
    k = int(np.ceil(float(level_pct) / 100.0 * ms.size))
    return float(ms[k - 1]) if k <= ms.size else float("inf")
