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
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

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
        return {"slope_deg": s.tolist(),
                **{f"{lv:g}": (self.threshold_z(lv) * sig).tolist() for lv in levels}}

    def to_dict(self) -> dict[str, Any]:
        qs = [0.5, 0.68, 0.9, 0.95, 0.99, 0.999]
        return {"n_stable": self.n, "center_m": self.center_m,
                "abs_z_quantiles": {f"{q:g}": self.threshold_z(q) for q in qs if q < self.max_level()}}


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


def change_sign(dh_m: np.ndarray, confidence: np.ndarray, level: float, center_m: float = 0.0,
                observed: np.ndarray | None = None, nodata: int | None = None) -> np.ndarray:
    """int8 +1 raised / −1 lowered / 0 unchanged at ``level``; ``nodata`` (e.g. −128) where not observed.

    ``nodata=None`` writes 0 there (the form :func:`geocd.change.regions.change_regions` takes).
    """
    conf = np.nan_to_num(np.asarray(confidence, np.float64), nan=0.0)
    d = np.nan_to_num(np.asarray(dh_m, np.float64) - center_m, nan=0.0)
    s = np.where(conf >= level, np.sign(d), 0).astype(np.int8)
    if observed is not None and nodata is not None:
        s = np.where(observed, s, np.int8(nodata)).astype(np.int8)
    return s
