"""Volume change through a sequence of DEMs, each interval only over its common surveyed area.

For epochs 0..n−1 (sorted by date) :func:`dem_time_series` runs
:func:`~geocd.demdiff.pipeline.dem_difference` on every consecutive pair
(k−1 → k) and, when a ``base`` DEM is given, every epoch against the base
(base → k). Per interval it records the *net* volume change over the area both
epochs surveyed, Σ dh × cell area, with its variogram-based σ (random + stable-mean
terms), and the volume of the significantly changed cells.

* **chained** cumulative volume: the sum of the interval volumes; σ adds in quadrature
  (an approximation: consecutive intervals share a DEM, so their errors are partly
  anti-correlated and the quadrature sum is conservative). When consecutive surveys
  cover different areas, the chain misses the change outside each common area.
* **base-referenced** volume: Σ (epoch k − base) over epoch k's survey area, the way
  dome volumes are usually reported against a pre-eruption surface (not co-registered
  by default, see ``base_params``; σ only where stable terrain is found).

**Survey footprints of merged DEMs.** Some archives (the Mount St Helens set)
store each epoch as the base DEM with the epoch's survey pasted over its own
footprint. A cell then belongs to epoch k's survey where it differs from the base
(:func:`survey_footprint`); pass ``base`` and ``merged_with_base=True`` to restrict
each comparison to the footprints both epochs share.
"""

from __future__ import annotations

import datetime as _dt
import math
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from ..errors import ConfigError
from ..io.raster import DEM
from ..progress import Progress, ensure_progress, sub_progress
from .align import align_dems
from .pipeline import DEMDiffParams, DEMDiffResult, dem_difference


def survey_footprint(height_m: np.ndarray, base_height_m: np.ndarray, tol_m: float = 1e-3) -> np.ndarray:
    """Cells where a merged DEM differs from its base by more than ``tol_m`` (its own survey)."""
    h = np.asarray(height_m, np.float64)
    b = np.asarray(base_height_m, np.float64)
    if h.shape != b.shape:
        raise ConfigError(f"DEM {h.shape} and base {b.shape} must be on the same grid to find survey footprints")
    return np.isfinite(h) & (~np.isfinite(b) | (np.abs(h - b) > tol_m))


@dataclass(frozen=True)
class Epoch:
    """One DEM of a series."""

    name: str
    date: _dt.date | None
    dem: DEM


@dataclass
class TimeSeriesResult:
    """Per-interval and cumulative volumes.

    Attributes
    ----------
    table : list of dict rows (one per consecutive interval, then one per base → epoch when a base is given)
    intervals : DEMDiffResult per consecutive interval (arrays dropped when ``keep_arrays`` was False)
    """

    table: list[dict[str, Any]]
    intervals: list[DEMDiffResult] = field(default_factory=list)
    vs_base: list[DEMDiffResult] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    def frame(self):
        import pandas as pd

        return pd.DataFrame(self.table)


def _row(kind: str, a: Epoch, b: Epoch, r: DEMDiffResult | None, err: str = "") -> dict[str, Any]:
    row: dict[str, Any] = {
        "kind": kind,
        "epoch_a": a.name,
        "epoch_b": b.name,
        "date_a": a.date.isoformat() if a.date else "",
        "date_b": b.date.isoformat() if b.date else "",
    }
    if r is None:
        row.update(status=f"failed: {err}")
        return row
    s = r.summary
    row.update(
        status=s["status"],
        coreg_status=s["coreg_status"],
        coreg_applied=s["coreg_applied"],
        shift_e_m=s["shift_applied_m"][0],
        shift_n_m=s["shift_applied_m"][1],
        shift_z_m=s["shift_applied_m"][2],
        n_stable=s["n_stable"],
        stable_nmad_m=s["stable_nmad_m"],
        observed_area_m2=s["observed_area_m2"],
        volume_net_m3=s["volume_net_observed_m3"],
        volume_net_sigma_m3=s["volume_net_observed_sigma_m3"],
        changed_area_m2=s["changed_area_m2"],
        volume_changed_m3=s["volume_changed_m3"],
        volume_changed_sigma_m3=s["volume_changed_sigma_m3"],
        volume_raised_m3=s["volume_raised_m3"],
        volume_lowered_m3=s["volume_lowered_m3"],
    )
    return row


def _light(r: DEMDiffResult) -> DEMDiffResult:
    """Drop the big arrays of a result (keep summary, coreg, models)."""
    for k in ("height_a_m", "height_b_m", "dh_raw_m", "z"):
        setattr(r, k, None)
    return r


def dem_time_series(
    epochs: Sequence[Epoch],
    *,
    base: Epoch | None = None,
    merged_with_base: bool = True,
    params: DEMDiffParams = DEMDiffParams(),
    base_params: DEMDiffParams | None = None,
    stable_mask: Any = None,
    mask_is: str = "stable",
    keep_arrays: bool = False,
    progress: Progress | None = None,
) -> TimeSeriesResult:
    """Volume change through a series of DEMs (see module docstring).

    Parameters
    ----------
    epochs : at least two :class:`Epoch` (sorted by date here when all have dates)
    base : optional base DEM (e.g. the pre-eruption surface); with ``merged_with_base`` each
        epoch's survey footprint is where it differs from the base
    base_params : parameters of the base → epoch comparisons; default ``params`` without
        co-registration (a base surveyed years earlier rarely shares enough stable terrain
        with a survey footprint for a trustworthy fit, and a vertical-only correction from
        a doubtful stable set moves the volume by more than it fixes)
    keep_arrays : keep the per-cell arrays of every interval (memory: ~10 arrays per interval)
    """
    prog = ensure_progress(progress)
    from dataclasses import replace

    bparams = base_params if base_params is not None else replace(params, coregister=False)
    eps = list(epochs)
    if len(eps) < 2:
        raise ConfigError("a time series needs at least two DEMs")
    if all(e.date is not None for e in eps):
        eps.sort(key=lambda e: e.date)
    notes: list[str] = []
    grid = eps[0].dem.grid
    fps: dict[str, np.ndarray] = {}
    base_h = None
    if base is not None:
        base_h = align_dems(eps[0].dem, base.dem, grid, crop=False).height_b_m

    def footprint(e: Epoch) -> np.ndarray | None:
        if base_h is None or not merged_with_base:
            return None
        if e.name not in fps:
            h = align_dems(eps[0].dem, e.dem, grid, crop=False).height_b_m
            fps[e.name] = survey_footprint(h, base_h)
        return fps[e.name]

    jobs: list[tuple[str, Epoch, Epoch]] = [("interval", eps[k - 1], eps[k]) for k in range(1, len(eps))]
    if base is not None:
        jobs += [("vs_base", base, e) for e in eps]
    table, intervals, vs_base = [], [], []
    from ..errors import GeoCDError

    for j, (kind, a, b) in enumerate(jobs):
        sub = sub_progress(prog, j / len(jobs), (j + 1) / len(jobs), f"{a.name} → {b.name}: ")
        fa = footprint(a) if kind == "interval" else None
        fb = footprint(b)
        obs = None
        if fb is not None:
            obs = fb if fa is None else (fa & fb)
            if not obs.any():
                table.append(_row(kind, a, b, None, "the two surveys share no cell"))
                notes.append(f"{a.name} → {b.name}: the surveys share no cell; skipped")
                continue
        try:
            pair = align_dems(a.dem, b.dem, grid, resampling=params.resampling, crop=False)
            r = dem_difference(
                pair,
                observed=obs,
                stable_mask=stable_mask,
                mask_is=mask_is,
                params=params if kind == "interval" else bparams,
                epoch_a=a.name,
                epoch_b=b.name,
                progress=sub,
            )
        except GeoCDError as exc:
            table.append(_row(kind, a, b, None, str(exc)))
            notes.append(f"{a.name} → {b.name}: {exc}")
            continue
        table.append(_row(kind, a, b, r))
        notes.extend(f"{a.name} → {b.name}: {w}" for w in r.warnings)
        if not keep_arrays:
            r = _light(r)
        (intervals if kind == "interval" else vs_base).append(r)
    _cumulate(table)
    return TimeSeriesResult(table, intervals, vs_base, notes)


def _cumulate(table: list[dict[str, Any]]) -> None:
    """Add chained cumulative volume ± σ to the interval rows (in date order)."""
    cum, var = 0.0, 0.0
    for row in table:
        if row["kind"] != "interval":
            continue
        v = row.get("volume_net_m3", float("nan"))
        s = row.get("volume_net_sigma_m3", float("nan"))
        if v is not None and math.isfinite(v):
            cum += v
        if s is not None and math.isfinite(s):
            var += s * s
        row["cumulative_net_m3"] = cum
        row["cumulative_net_sigma_m3"] = math.sqrt(var)
