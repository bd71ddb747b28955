"""DEM-vs-DEM change with co-registration and honest uncertainty.

One place for DEM differencing (docs/demdiff.md has the method notes and results):

* :func:`align_dems` — one grid, one vertical datum (explicit resampling; clear errors);
* :func:`nuth_kaab` — Nuth & Kääb (2011) co-registration with convergence, jackknife σ and
  under-constrained detection (:class:`CoregParams`, :class:`CoregResult`);
* :func:`stable_terrain` — user mask, footprints, or automatic (:class:`StableParams`);
* :func:`estimate_uncertainty` — heteroscedastic σ(slope, curvature), variogram (short + long
  range), effective samples, volume σ (:class:`ErrorParams`, :class:`Uncertainty`);
* :func:`fit_significance` — per-cell confidence from the stable-terrain distribution;
* :func:`dem_difference` — the whole pair pipeline (:class:`DEMDiffParams`, :class:`DEMDiffResult`);
* :func:`dem_time_series` — per-interval and cumulative volumes over common survey areas;
* :func:`write_demdiff_products` — rasters, ``changes``/``buildings`` layers, PNG, JSON report.
"""

from __future__ import annotations

from .align import AlignedPair, align_dems, crop_to_overlap, metric_posting
from .coreg import CoregParams, CoregResult, apply_shift, nuth_kaab
from .pipeline import CHANGE_NODATA, DEMDiffParams, DEMDiffResult, dem_difference, summary_table
from .significance import SignificanceModel, change_sign, fit_significance, significance_map
from .stable import StableInfo, StableParams, auto_stable_mask, mask_from_user, nmad, stable_terrain
from .timeseries import Epoch, TimeSeriesResult, dem_time_series, survey_footprint
from .uncertainty import (
    ErrorModel,
    ErrorParams,
    Uncertainty,
    VariogramModel,
    correlated_sum_variance,
    empirical_variogram,
    estimate_uncertainty,
    fit_error_model,
    fit_variogram,
    n_effective,
    variogram_fft,
)


def write_demdiff_products(*args, **kwargs):
    """See :func:`geocd.demdiff.products.write_demdiff_products` (imported lazily)."""
    from .products import write_demdiff_products as _w

    return _w(*args, **kwargs)


__all__ = [
    "AlignedPair",
    "align_dems",
    "crop_to_overlap",
    "metric_posting",
    "CoregParams",
    "CoregResult",
    "apply_shift",
    "nuth_kaab",
    "CHANGE_NODATA",
    "DEMDiffParams",
    "DEMDiffResult",
    "dem_difference",
    "summary_table",
    "SignificanceModel",
    "change_sign",
    "fit_significance",
    "significance_map",
    "StableInfo",
    "StableParams",
    "auto_stable_mask",
    "mask_from_user",
    "nmad",
    "stable_terrain",
    "Epoch",
    "TimeSeriesResult",
    "dem_time_series",
    "survey_footprint",
    "ErrorModel",
    "ErrorParams",
    "Uncertainty",
    "VariogramModel",
    "correlated_sum_variance",
    "empirical_variogram",
    "estimate_uncertainty",
    "fit_error_model",
    "fit_variogram",
    "n_effective",
    "variogram_fft",
    "write_demdiff_products",
]
