"""Building extraction and change from two orthoimages: arrays in, rectangles out.

:func:`detect` runs one of the measured variants:

* ``"ED"`` — the paper's joint model (both dates and ξ in one energy, texture-change term);
* ``"SD"`` — sequential detection: each image alone, then compared (the paper's baseline);
* ``"EV"`` — edge-only verification: the joint model whose object energy is the gradient term only
  (colour and shadow still shape the birth maps);

and, with DSMs, geocd's height-aware joint model (``params.height="and"``) and the 3-D change prior
(``params.gamma_3d > 0`` with ``change_prior``).

Everything works on one AOI window; :func:`context_m` is the margin a tile needs (the largest rectangle
plus its rings and the orientation window) so that tiles can be processed independently.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..errors import ConfigError, GridError
from ..progress import Progress, ensure_progress, sub_progress
from .features import (
    ImageFeatures,
    fill_roof_holes,
    dsm_ground,
    height_similarity,
    image_features,
    side_max_from_dsm,
    texture_change,
)
from .model import BOTH, ONLY_1, ONLY_2, EnergyModel, MPPResult, optimize, sd_combine
from .params import MPPParams

METHODS = ("ED", "SD", "EV")
#: above this share of cells standing ``min_height_m`` over the ground on both dates, no rectangle can be a
#: raised block with lower surroundings: the detection is refused before the annealing. On the Kahramanmaraş
#: DSMs one opening wider than every building left 96 % / 99 % of the cells raised and the whole annealing
#: placed no rectangle; the terrain filter leaves 54 % / 61 % there (docs/mpp.md)
RAISED_MAX = 0.9


@dataclass
class Detection:
    """Result of :func:`detect`.

    Attributes
    ----------
    result : MPPResult (for SD: rectangles of both single-date runs, compared)
    method : str
    features : the two ImageFeatures
    b0 : texture-change threshold (Bhattacharyya), NaN for SD
    thresholds : per image {"d_gradient", "D_gradient", "prototypes"}
    notes : what was dropped or assumed (grey image, no shadows, resampling, ...)
    """

    result: MPPResult
    method: str
    features: tuple
    b0: float = float("nan")
    thresholds: list = field(default_factory=list)
    notes: list = field(default_factory=list)


def context_m(params: MPPParams = MPPParams()) -> float:
    """Margin (m) a tile needs on each side: half the largest rectangle's diagonal, its outer rings and half
    the orientation window (objects centred in the tile core see all their data)."""
    return (
        0.5 * math.sqrt(2.0) * params.side_max_m
        + max(params.ring_m, params.shadow_ring_m)
        + params.edge_width_m
        + 0.5 * params.window
    )


def _check(a: np.ndarray, b: np.ndarray) -> None:
    sa = np.shape(a)[-2:]
    sb = np.shape(b)[-2:]
    if sa != sb:
        raise GridError(
            f"the two images are on different grids ({sa[0]}×{sa[1]} and {sb[0]}×{sb[1]} cells); "
            "orthorectify both onto one AOI grid (geocd ortho) or resample one onto the other's grid"
        )


def detect(
    image_a: np.ndarray,
    image_b: np.ndarray,
    posting_m: float,
    params: MPPParams = MPPParams(),
    *,
    method: str = "ED",
    valid_a: np.ndarray | None = None,
    valid_b: np.ndarray | None = None,
    dsm_a: np.ndarray | None = None,
    dsm_b: np.ndarray | None = None,
    ground_m: np.ndarray | None = None,
    filled_a: np.ndarray | None = None,
    filled_b: np.ndarray | None = None,
    change_prior: np.ndarray | None = None,
    progress: Progress | None = None,
) -> Detection:
    """Buildings of two dates and their changes from two images on one grid.

    Parameters
    ----------
    image_a, image_b : (rows, cols) or (bands, rows, cols), any dtype; earlier and later image
    posting_m : grid posting (m)
    method : "ED", "SD" or "EV" (see the module docstring)
    valid_a, valid_b : bool (rows, cols), observed cells (e.g. an orthoimage's mask)
    dsm_a, dsm_b, ground_m : heights (m) for ``params.height == "and"``; without ``ground_m`` the terrain is
        estimated from each DSM. A hole of a DSM (NaN, or a cell of ``filled_a`` / ``filled_b``) enclosed by
        cells standing above ``min_height_m`` takes their height, one half on such cells becomes NaN
        (:func:`features.fill_roof_holes`)
    filled_a, filled_b : bool (rows, cols), optional: cells whose height the DSM's producer interpolated (geocd
        ortho's ``filled`` band, the terrain put into the stereo's holes)
    change_prior : 3-D change evidence in [0, 1] (e.g. the self-consistency confidence / 100), used with
        ``params.gamma_3d > 0``
    """
    if method not in METHODS:
        raise ConfigError(f"method must be one of {METHODS}, got {method!r}")
    _check(image_a, image_b)
    if not (posting_m > 0):
        raise ConfigError(f"posting must be positive, got {posting_m}")
    prog = ensure_progress(progress)
    if method == "EV":
        params = params.replace(prototypes="gradient")
    use_h = params.height != "off"
    notes: list[str] = []
    if use_h and (dsm_a is None or dsm_b is None):
        raise ConfigError("the height term needs a DSM of each date (dsm_a, dsm_b); give them or set height='off'")
    if params.gamma_3d > 0 and change_prior is None:
        raise ConfigError("gamma_3d > 0 needs a 3-D change map (change_prior)")
    prog(0.0, "features")
    if use_h:
        shape = np.shape(image_a)[-2:]
        for what, arr in (
            ("DSM A", dsm_a),
            ("DSM B", dsm_b),
            ("ground", ground_m),
            ("filled A", filled_a),
            ("filled B", filled_b),
        ):
            if arr is not None and np.shape(arr) != shape:
                raise ConfigError(
                    f"{what} shape {np.shape(arr)} does not match the images {shape}; put both on the grid"
                )
        grounds, dsms, filled = [], [], []
        for d, fl in ((dsm_a, filled_a), (dsm_b, filled_b)):
            d = np.asarray(d, np.float64)
            g = ground_m if ground_m is not None else dsm_ground(d, posting_m)
            d, roof, unknown = fill_roof_holes(d, g, params.min_height_m, fl)
            grounds.append(g)
            dsms.append(d)
            filled.append((int(roof.sum()), int(unknown.sum())))
        dsm_a, dsm_b = dsms
        if any(sum(x) for x in filled):
            notes.append(
                "DSM holes (no height, or the terrain its producer put there) inside raised surfaces, "
                "roofs the stereo could not match, take the surface's height: "
                f"{filled[0][0]} cells on date A, {filled[1][0]} on date B; holes half on a raised "
                f"surface, half beside it, are unknown: {filled[0][1]} and {filled[1][1]} cells"
            )
    if use_h and params.side_max_from_dsm:
        found = []
        for d, g in zip((dsm_a, dsm_b), grounds):
            with np.errstate(invalid="ignore"):
                found.append(side_max_from_dsm(d - g, posting_m, params))
        smax = max([x for x in found if np.isfinite(x)], default=params.side_max_m)
        if smax > params.side_max_m:
            notes.append(
                f"largest rectangle side {smax:.1f} m: 0.9 quantile of the raised segments' long sides "
                f"(instead of {params.side_max_m:g} m)"
            )
            params = params.replace(side_max_m=round(smax, 1))
    fa = image_features(
        image_a, posting_m, params, valid=valid_a, dsm_m=dsm_a if use_h else None, ground_m=ground_m if use_h else None
    )
    fb = image_features(
        image_b, posting_m, params, valid=valid_b, dsm_m=dsm_b if use_h else None, ground_m=ground_m if use_h else None
    )
    for tag, f in (("image A", fa), ("image B", fb)):
        notes += [f"{tag}: {n}" for n in f.notes]
    flat = [tag for tag, f in (("image A", fa), ("image B", fb)) if not f.birth.any()]
    if flat:
        notes.append(
            f"{' and '.join(flat)}: no gradient at all (flat): no building can be seen there"
            + (
                ""
                if len(flat) == 2
                else "; every building of the other date will read as a change "
                "(check for cloud, nodata or a wrong band)"
            )
        )
    raised = _raised_shares(params, (fa, fb))
    if len(raised) == 2 and min(raised) > RAISED_MAX:
        raise ConfigError(
            f"{min(raised):.0%}–{max(raised):.0%} of the cells stand more than {params.min_height_m:g} m above the "
            "ground on both dates, so no rectangle can be a raised block with lower surroundings: the ground is "
            "too low (give the terrain DEM with --ground, or the manifest's dem) or the DSMs are not of this "
            "place; --height off detects from the images alone"
        )
    b0 = float("nan")
    if method == "SD":
        ma = EnergyModel([fa], posting_m, params)
        mb = EnergyModel([fb], posting_m, params.replace(seed=params.seed + 1))
        ra = optimize(ma, params, progress=sub_progress(prog, 0.1, 0.55, "date A: "))
        rb = optimize(mb, params.replace(seed=params.seed + 1), progress=sub_progress(prog, 0.55, 1.0, "date B: "))
        rects, xi = sd_combine(ra, rb, fa.grey.shape)
        notes += [f"date A: {n}" for n in ra.notes] + [f"date B: {n}" for n in rb.notes]
        res = _sd_result(ra, rb, rects, xi)
        thr = [_thr(t) for t in (ma.terms[0], mb.terms[0])]
    else:
        _, B, b0 = texture_change(fa, fb)
        ev = params.change_evidence
        if ev != "texture" and (fa.ndsm is None or fb.ndsm is None):
            notes.append("change evidence (ξ): the texture alone (no DSMs)")
        elif ev != "texture":
            Bh = height_similarity(fa, fb, params.min_height_m, B)
            B = Bh if ev == "height" else (0.5 * (B + Bh)).astype(np.float32)
            standing = f"a cell changed when it stands over {params.min_height_m:g} m above the ground on one date only"
            notes.append(
                f"change evidence (ξ): the DSMs: {standing}"
                if ev == "height"
                else f"change evidence (ξ): the mean of the DSMs' and the texture's: {standing} "
                "(or the orientation texture differs)"
            )
        model = EnergyModel(
            [fa, fb], posting_m, params, similarity=B, change_prior=change_prior if params.gamma_3d > 0 else None
        )
        res = optimize(model, params, progress=sub_progress(prog, 0.1, 1.0))
        notes += res.notes
        thr = [_thr(t) for t in model.terms]
    if len(res) == 0 and not flat:
        notes.append(_why_empty(params, (fa, fb)))
    if not res.converged:
        notes.append(
            f"multiple birth and death stopped at the iteration cap ({params.max_iter}) before the "
            "convergence test passed"
        )
    prog(1.0, f"{len(res)} rectangles")
    return Detection(res, method, (fa, fb), b0, thr, notes)


def _raised_shares(params: MPPParams, feats) -> list[float]:
    """Per date with a DSM: the share of its valid cells standing more than ``min_height_m`` above the ground."""
    raised = []
    for f in feats:
        if f.ndsm is not None:
            ok = np.isfinite(f.ndsm) & f.valid
            if ok.any():
                raised.append(float(np.mean(f.ndsm[ok] > params.min_height_m)))
    return raised


def _why_empty(params: MPPParams, feats) -> str:
    """A note for a run that found nothing on images that do have edges (an implausible answer)."""
    raised = _raised_shares(params, feats)
    if raised and max(raised) > 0.5:
        return (
            f"no building found: {max(raised):.0%} of the cells stand more than {params.min_height_m:g} m above "
            "the ground estimated from the DSM, so no rectangle is a raised block with lower surroundings "
            "(dense blocks larger than the largest rectangle, or a ground model that is too low: give the "
            "terrain DEM, or try without the height term)"
        )
    return (
        f"no building found: no rectangle of {params.side_min_m:g}–{params.side_max_m:g} m fits the image "
        "cues; check the side bounds against the buildings' size"
    )


def _thr(term) -> dict[str, Any]:
    return {
        "d_gradient": round(term.d_gradient, 4),
        "D_gradient": round(term.D_gradient, 4),
        "prototypes": " | ".join(" + ".join(p) for p in term.prototypes),
    }


def _sd_result(ra: MPPResult, rb: MPPResult, rects: np.ndarray, xi: np.ndarray) -> MPPResult:
    """One MPPResult from the two single-date runs (energies, φ and confidences carried over)."""
    n1 = len(ra)
    keep_b = len(rects) - n1
    sel_b = np.zeros(len(rb), bool)
    if keep_b:
        # sd_combine appends the kept date-2 rectangles in order
        idx = [k for k in range(len(rb)) if any(np.array_equal(rb.rects[k], r) for r in rects[n1:])]
        sel_b[idx] = True
    energy = np.concatenate([ra.energy, rb.energy[sel_b]])
    phi = np.full((len(rects), 2), np.nan)
    phi[:n1, 0] = ra.phi[:, 0]
    phi[n1:, 1] = rb.phi[sel_b, 0]
    conf = np.concatenate([ra.confidence, rb.confidence[sel_b]])
    return MPPResult(
        rects=rects,
        xi=xi.astype(np.int8),
        energy=energy,
        phi=phi,
        confidence=conf,
        xi_confidence=np.full(len(rects), np.nan),
        iterations=max(ra.iterations, rb.iterations),
        converged=ra.converged and rb.converged,
        births=ra.births + rb.births,
        energy_total=ra.energy_total + rb.energy_total,
    )


__all__ = ["BOTH", "ONLY_1", "ONLY_2", "METHODS", "Detection", "context_m", "detect", "ImageFeatures"]
