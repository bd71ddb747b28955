"""DEM-vs-DEM change for one pair: align → stable terrain → co-register → uncertainty → significance → regions.

Steps of :func:`dem_difference` (arrays in, arrays out; files only in the CLI):

1. :func:`~geocd.demdiff.align.align_dems` puts B on A's grid and datum (or takes an
   :class:`~geocd.demdiff.align.AlignedPair`); ``observed`` restricts the comparison
   (e.g. the survey area both epochs share).
2. Nuth & Kääb co-registration of B onto A: with a user mask, on its stable cells;
   otherwise twice — pass 1 on every valid cell (the aspect-bin medians are robust to
   a minority of changed cells), pass 2 on the automatic stable terrain of the
   pass-1-aligned dh (``nmad_factor`` × ``coreg_stable_factor``), started from the
   pass-1 shift.
3. The final stable terrain is selected on the co-registered dh (or taken from the
   user mask), and the error model (σ per cell, variogram, stable-mean σ) is learned
   on it.
4. Each cell's confidence (percent) is the stable-terrain ECDF of its |z|; cells at
   ``confidence`` percent or above are changed; 8-connected regions of at least
   ``min_region_cells`` cells become the ``changes`` layer with volume ± σ.

Without stable terrain the result says so (``status``), no shift is invented, σ and
confidence are NaN, and only a fixed ``fallback_threshold_m`` (if given) makes
regions.

Degenerate stable terrain: when most stable cells hold the *same* height in both DEMs
(they share data: both pasted on a common base DEM, one filled from the other), or the
stable NMAD is within a few float32 rounding steps of zero, the error model measures
nothing. σ and the confidence are still computed but the result's ``status`` is
``"degenerate_stable_terrain"`` and ``warnings`` says what to do (``--base``,
``--stable-mask``) instead of reporting ``NMAD 0.00 m`` as a fact.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from ..errors import ConfigError, EmptyDataError
from ..geodesy import AOIGrid
from ..io.raster import DEM
from ..progress import Progress, ensure_progress, sub_progress
from ._kernels import terrain_attributes
from .align import AlignedPair, align_dems
from .coreg import CoregParams, CoregResult, apply_shift, nuth_kaab
from .significance import (
    SignificanceModel,
    change_sign,
    fit_significance,
    noise_region_filter,
    noise_region_null,
    significance_map,
)
from .stable import StableInfo, StableParams, nmad, stable_terrain
from .uncertainty import ErrorParams, Uncertainty, estimate_uncertainty

CHANGE_NODATA = -128


@dataclass(frozen=True)
class DEMDiffParams:
    """Parameters of :func:`dem_difference`."""

    coreg: CoregParams = CoregParams()
    stable: StableParams = StableParams()
    error: ErrorParams = ErrorParams()
    coregister: bool = True
    coreg_stable_factor: float = 1.0
    confidence: float = 95.0
    min_region_cells: int = 4
    #: region test: "noise" keeps a region only when its combined evidence (cluster mass) exceeds what
    #: ``confidence`` % of the regions formed by noise alone reach (the error model's σ and variogram:
    #: :func:`geocd.demdiff.significance.noise_region_null`); "off": every region of ≥ min_region_cells.
    #: Without stable terrain (no σ, no variogram) there is no test and every region is kept.
    region_test: str = "noise"
    resampling: str = "bilinear"
    fallback_threshold_m: float | None = None
    min_stable_cells: int = 50
    reliable_stable_cells: int = 300
    reliable_stable_blocks: int = 6
    #: stable terrain is degenerate when at least this share of its cells is identical in both DEMs ...
    max_identical_fraction: float = 0.5
    #: ... or its NMAD is at most this many float32 rounding steps of the heights (storage precision)
    nmad_floor_ulps: float = 10.0

    def __post_init__(self) -> None:
        if 0 < self.confidence < 1:
            raise ConfigError(
                f"confidence is a percentage: did you mean {100 * self.confidence:g}? "
                f"(got {self.confidence:g}; 95 means 95 %)"
            )
        if not 50 <= self.confidence < 100:
            raise ConfigError(f"confidence {self.confidence:g} is outside [50, 100): give a percentage such as 95")
        if not 0 < self.max_identical_fraction <= 1:
            raise ConfigError("max_identical_fraction must be in (0, 1]")
        if self.min_region_cells < 1:
            raise ConfigError("min_region_cells must be ≥ 1")
        if self.region_test not in ("noise", "off"):
            raise ConfigError(f"region_test must be 'noise' or 'off', got {self.region_test!r}")


@dataclass
class DEMDiffResult:
    """Per-cell products and summary of one DEM pair (arrays on ``grid``).

    Attributes
    ----------
    dh_m : float32, B(co-registered) − A, NaN outside the observed common area
    dh_raw_m : float32, B − A before co-registration
    sigma_m : float32, per-cell 1σ of dh (NaN when unknown)
    z : float32, standardized residual (dh − stable median)/σ
    confidence : float32, percent 0–100 (NaN unobserved or unknown)
    sign : int8, +1/−1/0 in kept regions, CHANGE_NODATA (−128) where not observed
    stable : bool, final stable terrain
    status : "ok", "uncertainty_indicative" (σ from too few / too clustered stable cells),
        "degenerate_stable_terrain" (stable cells identical in both DEMs or NMAD ≈ 0: σ is not an error
        estimate) or "no_stable_terrain" (σ and confidence unknown)
    level : the confidence (percent) at which cells are called changed
    warnings : what makes the figures not credible, and what to do
    summary : dict of the headline figures (see :func:`summary_table`)
    """

    grid: AOIGrid
    posting_xy_m: tuple[float, float]
    height_a_m: np.ndarray
    height_b_m: np.ndarray
    dh_m: np.ndarray
    dh_raw_m: np.ndarray
    observed: np.ndarray
    stable: np.ndarray
    stable_info: StableInfo
    coreg: CoregResult
    uncertainty: Uncertainty | None
    significance: SignificanceModel | None
    sigma_m: np.ndarray
    z: np.ndarray
    confidence: np.ndarray
    sign: np.ndarray
    regions: Any
    epoch_a: str = "A"
    epoch_b: str = "B"
    level: float = 95.0
    status: str = "ok"
    notes: list[str] = field(default_factory=list)
    summary: dict[str, Any] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)

    @property
    def changed(self) -> np.ndarray:
        return (self.sign == 1) | (self.sign == -1)

    def to_dict(self) -> dict[str, Any]:
        d = {
            "epoch_a": self.epoch_a,
            "epoch_b": self.epoch_b,
            "status": self.status,
            "confidence_level_pct": self.level,
            "grid": self.grid.to_dict(),
            "posting_xy_m": list(self.posting_xy_m),
            "notes": list(self.notes),
            "warnings": list(self.warnings),
            "summary": self.summary,
            "stable": self.stable_info.to_dict(),
            "coreg": self.coreg.to_dict(),
        }
        if self.uncertainty is not None:
            d["uncertainty"] = self.uncertainty.to_dict()
        if self.significance is not None:
            d["significance"] = self.significance.to_dict()
        return d


def _as_pair(dem_a, dem_b, grid, resampling) -> AlignedPair:
    if isinstance(dem_a, AlignedPair):
        return dem_a
    if isinstance(dem_a, DEM) and isinstance(dem_b, DEM):
        return align_dems(dem_a, dem_b, grid, resampling=resampling)
    raise ConfigError("dem_difference takes two geocd.io.raster.DEM objects (or an AlignedPair)")


def dem_difference(
    dem_a: DEM | AlignedPair,
    dem_b: DEM | None = None,
    *,
    grid: AOIGrid | None = None,
    observed: np.ndarray | None = None,
    stable_mask: Any = None,
    mask_is: str = "stable",
    footprints: Any = None,
    params: DEMDiffParams = DEMDiffParams(),
    epoch_a: str = "A",
    epoch_b: str = "B",
    method: str = "demdiff",
    progress: Progress | None = None,
) -> DEMDiffResult:
    """Change between two DEMs with co-registration and honest uncertainty (see module docstring).

    Parameters
    ----------
    dem_a, dem_b : DEM (A = reference/earlier, B = later), or an AlignedPair as ``dem_a``
    grid : optional target grid (default: A's grid cropped to the overlap)
    observed : bool array on the target grid, optional: compare only these cells
    stable_mask : optional user mask (array, polygons or path); see :func:`~geocd.demdiff.stable.stable_terrain`
    footprints : optional building polygons (excluded from stable terrain; attributed in products)

    Raises
    ------
    NoOverlapError, VerticalDatumError, EmptyDataError (e.g. a user stable mask with no valid cell)
    """
    t0 = time.perf_counter()
    prog = ensure_progress(progress)
    p = params
    pair = _as_pair(dem_a, dem_b, grid, p.resampling)
    g = pair.grid
    post = pair.posting_xy_m
    A = pair.height_a_m.astype(np.float64)
    B = pair.height_b_m.astype(np.float64)
    valid = pair.valid
    if observed is not None:
        ob = np.asarray(observed, bool)
        if ob.shape != g.shape:
            raise ConfigError(f"observed mask {ob.shape} does not match the grid {g.shape}")
        valid = valid & ob
    if not valid.any():
        raise EmptyDataError("no cell is observed in both DEMs (check the observed/survey masks)")
    notes = list(pair.notes)
    prog(0.02, "terrain attributes")
    terr = terrain_attributes(A, post)
    slope = terr["slope_rad"]
    q = terr.get(p.error.predictor) if p.error.predictor != "none" else None
    dh_raw = np.where(valid, B - A, np.nan)

    # --- co-registration -------------------------------------------------------------------------
    loose = replace(p.stable, nmad_factor=p.stable.nmad_factor * p.coreg_stable_factor)
    Bv = np.where(valid, B, np.nan) if observed is not None else B
    if not p.coregister:
        creg = nuth_kaab(A, B, valid, post, replace(p.coreg, horizontal=False, vertical=False, tilt=False))[1]
        Bc = B
    elif stable_mask is not None:
        st0, _ = stable_terrain(
            dh_raw,
            valid,
            g,
            user_mask=stable_mask,
            mask_is=mask_is,
            footprints=footprints,
            slope_rad=slope,
            params=loose,
        )
        Bc, creg = nuth_kaab(A, Bv, st0, post, p.coreg, progress=sub_progress(prog, 0.05, 0.4, "co-registration: "))
    else:
        st_all, _ = stable_terrain(dh_raw, valid, g, user_mask=valid, footprints=footprints, params=loose)
        B1, c1 = nuth_kaab(A, Bv, st_all, post, p.coreg, progress=sub_progress(prog, 0.05, 0.2, "co-registration 1: "))
        trusted1 = c1.status == "ok"
        dh1 = np.where(valid, (B1 if trusted1 else Bv) - A, np.nan)
        st0, _ = stable_terrain(dh1, valid & np.isfinite(dh1), g, footprints=footprints, slope_rad=slope, params=loose)
        init = c1.fitted_shift_m[:2] if trusted1 else (0.0, 0.0)
        Bc, creg = nuth_kaab(
            A,
            Bv,
            st0,
            post,
            p.coreg,
            progress=sub_progress(prog, 0.2, 0.4, "co-registration 2: "),
            initial_shift_m=init,
        )
    Bc = np.asarray(Bc, np.float64)
    if creg.status != "ok":
        notes.append(creg.summary())
    dh = np.where(valid, Bc - A, np.nan)
    obs = valid & np.isfinite(dh)

    # --- final stable terrain ------------------------------------------------------------------
    prog(0.45, "stable terrain")
    st, info = stable_terrain(
        dh, obs, g, user_mask=stable_mask, mask_is=mask_is, footprints=footprints, slope_rad=slope, params=p.stable
    )
    res = finish_difference(
        g,
        post,
        A,
        B,
        Bc,
        dh,
        dh_raw,
        obs,
        st,
        info,
        creg,
        slope,
        q,
        notes,
        p,
        epoch_a=epoch_a,
        epoch_b=epoch_b,
        method=method,
        progress=prog,
    )
    res.summary["wall_s"] = time.perf_counter() - t0
    prog(1.0, "done")
    return res


def finish_difference(
    g: AOIGrid,
    post: tuple[float, float],
    A: np.ndarray,
    B: np.ndarray,
    Bc: np.ndarray,
    dh: np.ndarray,
    dh_raw: np.ndarray,
    obs: np.ndarray,
    st: np.ndarray,
    info: StableInfo,
    creg: CoregResult,
    slope: np.ndarray,
    q: np.ndarray | None,
    notes: list[str],
    p: DEMDiffParams,
    *,
    epoch_a: str = "A",
    epoch_b: str = "B",
    method: str = "demdiff",
    progress: Progress | None = None,
) -> DEMDiffResult:
    """The steps of :func:`dem_difference` after the final stable terrain (whole grids; float64 A, B
    as read, Bc co-registered, dh = Bc − A on ``obs``): error model, significance, change map,
    regions and the summary (without ``wall_s``)."""
    prog = ensure_progress(progress)
    notes.extend(info.notes)
    status = "ok"
    unc = None
    sig_model = None
    sigma = np.full(g.shape, np.nan, np.float32)
    z = np.full(g.shape, np.nan, np.float32)
    conf = np.full(g.shape, np.nan, np.float32)
    center = 0.0
    if info.n_cells < p.min_stable_cells:
        status = "no_stable_terrain"
        notes.append(
            f"no usable stable terrain ({info.n_cells} cells, at least {p.min_stable_cells} needed): "
            "no co-registration shift was invented, and σ and confidence are unknown; give a stable-terrain "
            "mask (--stable-mask) to test significance"
        )
    else:
        prog(0.5, "error model and variogram")
        rs_, cs_ = np.nonzero(st)
        nblk = len(np.unique((rs_ // p.coreg.block_px) * (g.width // p.coreg.block_px + 1) + cs_ // p.coreg.block_px))
        if info.n_cells < p.reliable_stable_cells or nblk < p.reliable_stable_blocks:
            status = "uncertainty_indicative"
            notes.append(
                f"σ learned from only {info.n_cells} stable cells in {nblk} blocks of {p.coreg.block_px} px "
                f"(reliable from {p.reliable_stable_cells} cells in {p.reliable_stable_blocks} blocks): "
                "the error model and variogram are indicative only"
            )
        unc = estimate_uncertainty(dh, st, slope, q, post, p.error)
        sigma = np.where(obs, unc.sigma_m, np.nan).astype(np.float32)
        sig_model = fit_significance(dh, sigma, st)
        # a vertical offset the co-registration did not remove stays in every sum: count it
        unc = unc.with_offset(sig_model.center_m)
        center = sig_model.center_m
        z, conf = significance_map(dh, sigma, sig_model)
        conf = (100.0 * conf).astype(np.float32)
        if p.confidence > 100.0 * sig_model.max_level():
            notes.append(
                f"{sig_model.n} stable cells support confidences up to {100 * sig_model.max_level():.2f}% "
                f"only; nothing can be significant at {p.confidence:g}%"
            )
    warns: list[str] = []
    degenerate = {}
    if info.n_cells >= p.min_stable_cells:
        degenerate, warn = degenerate_stable_terrain(A, B, dh, st, p)
        if warn:
            status = "degenerate_stable_terrain"
            warns.append(warn)

    # --- change map and regions ------------------------------------------------------------------
    prog(0.8, "changed regions")
    from ..change.regions import change_regions

    if sig_model is not None:
        raw_sign = change_sign(dh, conf / 100.0, p.confidence / 100.0, center)
    elif p.fallback_threshold_m is not None:
        raw_sign = np.where(np.abs(np.nan_to_num(dh)) > p.fallback_threshold_m, np.sign(np.nan_to_num(dh)), 0).astype(
            np.int8
        )
        notes.append(f"changed cells from the fixed threshold |dh| > {p.fallback_threshold_m} m (no significance test)")
    else:
        raw_sign = np.zeros(g.shape, np.int8)
    raw_sign = np.where(obs, raw_sign, 0).astype(np.int8)
    region_info = None
    if p.region_test == "noise" and sig_model is not None and unc is not None:
        null = region_null_of(unc.variogram, post, p.confidence, p.min_region_cells)
        raw_sign, region_info = noise_region_filter(raw_sign, conf, p.confidence, null, p.min_region_cells)
    cell = float(post[0] * post[1])
    vfn = unc.volume_sigma_fn(cell) if unc is not None else None
    # per-cell confidence in percent, as change_regions takes it
    regions = change_regions(
        raw_sign,
        dh,
        g,
        confidence=conf if sig_model is not None else None,
        volume_sigma_fn=vfn,
        method=method,
        epoch_a=epoch_a,
        epoch_b=epoch_b,
        min_cells=p.min_region_cells,
        cell_area_m2=cell,
    )
    sign = _sign_in_regions(raw_sign, p.min_region_cells)
    sign = np.where(obs, sign, CHANGE_NODATA).astype(np.int8)

    res = DEMDiffResult(
        g,
        post,
        A.astype(np.float32),
        Bc.astype(np.float32),
        dh.astype(np.float32),
        dh_raw.astype(np.float32),
        obs,
        st,
        info,
        creg,
        unc,
        sig_model,
        sigma,
        z,
        conf,
        sign,
        regions,
        epoch_a,
        epoch_b,
        p.confidence,
        status,
        notes,
        warnings=warns,
    )
    res.summary = _summary(res, B, p)
    res.summary.update(degenerate)
    if region_info is not None:
        res.summary["region_test"] = region_info
    return res


def region_null_of(vg, posting_xy_m, level_pct: float, min_cells: int) -> np.ndarray:
    """The noise regions' masses for the region test (the regions of ≥ ``min_cells`` the cell test makes in noise)."""
    return noise_region_null(vg, (float(posting_xy_m[0]), float(posting_xy_m[1])), level_pct, min_cells)


def degenerate_stable_terrain(
    height_a_m: np.ndarray,
    height_b_m: np.ndarray,
    dh_m: np.ndarray,
    stable: np.ndarray,
    params: DEMDiffParams = DEMDiffParams(),
) -> tuple[dict[str, float], str | None]:
    """Is the stable terrain degenerate (identical heights, NMAD ≈ 0)? → (figures, warning or None).

    Parameters
    ----------
    height_a_m, height_b_m : (rows, cols) the two DEMs on one grid, before co-registration (m)
    dh_m : (rows, cols) the co-registered difference (m)
    stable : (rows, cols) bool, the stable terrain

    Two independently made DEMs never agree to the last bit on most of their stable cells, and their
    difference has an NMAD far above the float32 rounding of the heights (``nmad_floor_ulps`` steps of
    ``np.spacing(float32(max |h|))``, ≈ 2 mm at 2,000 m). When either happens the DEMs share data (a common
    base DEM, a fill, a copy) or are noise-free synthetics, and σ measures nothing.
    """
    st = np.asarray(stable, bool)
    n = int(st.sum())
    if n == 0:
        return {}, None
    ident = int(np.count_nonzero(st & (height_a_m == height_b_m)))
    v = dh_m[st]
    v = v[np.isfinite(v)]
    nm = nmad(v) if v.size else float("nan")
    hmax = float(np.nanmax(np.abs(height_a_m[st]))) if np.isfinite(height_a_m[st]).any() else 0.0
    return degenerate_message(n, ident, nm, hmax, params)


def degenerate_message(
    n: int, identical: int, nmad_m: float, hmax_m: float, params: DEMDiffParams = DEMDiffParams()
) -> tuple[dict[str, float], str | None]:
    """:func:`degenerate_stable_terrain` from its counts: ``n`` stable cells, ``identical`` of them with the
    same height in both DEMs, their dh NMAD and the largest |height| (for the float32 rounding floor)."""
    if n == 0:
        return {}, None
    frac = identical / n
    nm = nmad_m
    floor = float(params.nmad_floor_ulps * np.spacing(np.float32(max(hmax_m, 1.0))))
    figures = {"stable_identical_fraction": round(frac, 5), "stable_nmad_floor_m": floor}
    if frac < params.max_identical_fraction and not (nm <= floor):
        return figures, None
    what = (
        f"{100 * frac:.1f}% of the {n} stable cells have exactly the same height in both DEMs"
        if frac >= params.max_identical_fraction
        else f"the stable terrain's NMAD is {nm:.2g} m"
    )
    msg = (
        f"degenerate stable terrain: {what} (NMAD {nm:.2g} m): the DEMs share data there (e.g. both were merged "
        "onto a common base DEM, or one was filled from the other) or are noise-free, so σ, the confidence and "
        "the volume ± σ are not an error estimate. If the DEMs were merged onto a base DEM, give it (--base "
        "BASE; QGIS: 'Base DEM') to compare only where both epochs were surveyed; otherwise give stable terrain "
        "where the DEMs are independent (--stable-mask)."
    )
    return figures, msg


def _sign_in_regions(sign: np.ndarray, min_cells: int) -> np.ndarray:
    from scipy import ndimage

    out = np.zeros(sign.shape, np.int8)
    for s in (1, -1):
        lab, n = ndimage.label(sign == s, structure=np.ones((3, 3), bool))
        if n == 0:
            continue
        sizes = np.bincount(lab.ravel(), minlength=n + 1)
        big = sizes >= min_cells
        big[0] = False
        out[big[lab]] = s
    return out


def _summary(res: DEMDiffResult, B_raw: np.ndarray, p: DEMDiffParams) -> dict[str, Any]:
    """Headline figures: shift, stable NMAD, changed area, volumes ± σ (m, m², m³)."""
    cell = float(res.posting_xy_m[0] * res.posting_xy_m[1])
    dh = res.dh_m.astype(np.float64)
    obs = res.observed
    ch = res.changed
    s: dict[str, Any] = {
        "epoch_a": res.epoch_a,
        "epoch_b": res.epoch_b,
        "status": res.status,
        "coreg_status": res.coreg.status,
        "coreg_applied": res.coreg.applied,
        "shift_applied_m": list(res.coreg.shift_m),
        "shift_fitted_m": list(res.coreg.fitted_shift_m),
        "shift_sigma_m": list(res.coreg.shift_sigma_m),
        "coreg_n_fit": res.coreg.n_fit,
        "n_observed": int(obs.sum()),
        "observed_area_m2": float(obs.sum() * cell),
        "n_stable": int(res.stable.sum()),
        "stable_median_m": float(np.median(dh[res.stable])) if res.stable.any() else float("nan"),
        "stable_nmad_m": nmad(dh[res.stable]) if res.stable.any() else float("nan"),
        "stable_nmad_before_coreg_m": res.coreg.nmad_before_m,
        "changed_cells": int(ch.sum()),
        "changed_area_m2": float(ch.sum() * cell),
        "raised_area_m2": float((res.sign == 1).sum() * cell),
        "lowered_area_m2": float((res.sign == -1).sum() * cell),
        "volume_changed_m3": float(np.nansum(dh[ch]) * cell),
        "volume_raised_m3": float(np.nansum(dh[res.sign == 1]) * cell),
        "volume_lowered_m3": float(np.nansum(dh[res.sign == -1]) * cell),
        "volume_net_observed_m3": float(np.nansum(dh[obs]) * cell),
    }
    nan = float("nan")
    s.update(
        volume_changed_sigma_m3=nan,
        volume_changed_sigma_random_m3=nan,
        volume_net_observed_sigma_m3=nan,
        n_eff_changed=nan,
        variogram_ranges_m=[],
        variogram_sills=[],
        variogram_nugget=nan,
        bias_sigma_m=nan,
    )
    u = res.uncertainty
    if u is not None:
        s["variogram_ranges_m"] = list(u.variogram.ranges_m)
        s["variogram_sills"] = list(u.variogram.sills)
        s["variogram_nugget"] = u.variogram.nugget
        s["bias_sigma_m"] = u.bias_sigma_m
        s["n_eff_stable"] = u.n_eff_stable
        s["error_model_coef"] = list(u.error_model.coef)
        s["error_model_scale"] = u.error_model.scale
        s["volume_net_observed_sigma_m3"] = u.volume_sigma_m3(obs, cell)
        if ch.any():
            s["volume_changed_sigma_m3"] = u.volume_sigma_m3(ch, cell)
            s["volume_changed_sigma_random_m3"] = u.volume_sigma_m3(ch, cell, include_bias=False)
            s["n_eff_changed"] = u.n_effective(ch)
    # what the fitted (not applied) horizontal shift would have done to the changed volume
    c = res.coreg
    fe, fn, fz = c.fitted_shift_m
    if (fe or fn) and c.applied in ("vertical", "none") and ch.any():
        Bf = apply_shift(B_raw, (fe, fn, fz), res.posting_xy_m, resampling=p.coreg.resampling).astype(np.float64)
        dhf = np.where(obs, Bf - res.height_a_m, np.nan)
        vf = float(np.nansum(dhf[ch]) * cell)
        s["volume_changed_if_fitted_shift_applied_m3"] = vf
        sv = s["volume_changed_sigma_m3"]
        s["fitted_shift_volume_effect_sigma"] = (vf - s["volume_changed_m3"]) / sv if sv and math.isfinite(sv) else nan
    return s


def summary_table(results) -> list[dict[str, Any]]:
    """One flat row per result (for CSV/GeoPackage tables)."""
    rows = []
    for r in results:
        s = r.summary
        e, n, z = s["shift_applied_m"]
        fe, fn, fz = s["shift_fitted_m"]
        se, sn, sz = s["shift_sigma_m"]
        rows.append(
            {
                "epoch_a": r.epoch_a,
                "epoch_b": r.epoch_b,
                "status": s["status"],
                "coreg_status": s["coreg_status"],
                "coreg_applied": s["coreg_applied"],
                "shift_e_m": e,
                "shift_n_m": n,
                "shift_z_m": z,
                "fitted_e_m": fe,
                "fitted_n_m": fn,
                "fitted_z_m": fz,
                "sigma_e_m": se,
                "sigma_n_m": sn,
                "sigma_z_m": sz,
                "n_stable": s["n_stable"],
                "stable_nmad_m": s["stable_nmad_m"],
                "observed_area_m2": s["observed_area_m2"],
                "changed_area_m2": s["changed_area_m2"],
                "volume_changed_m3": s["volume_changed_m3"],
                "volume_changed_sigma_m3": s["volume_changed_sigma_m3"],
                "volume_net_observed_m3": s["volume_net_observed_m3"],
                "volume_net_observed_sigma_m3": s["volume_net_observed_sigma_m3"],
            }
        )
    return rows
