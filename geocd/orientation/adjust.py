"""Bias-compensating bundle adjustment: per-image image-space corrections jointly with the tie points' ground points.

Observation equation (Grodecki & Dial 2003, in image space)::

    u_obs(k, j) = u_k(X_j) + t_k + (M_k / 1000) · (u_k(X_j) − c_k) + ε,      ε ~ N(0, σ² I)

with ``u_k`` the uncorrected camera k, ``X_j = (x, y, h)`` the ground point of track j (grid CRS,
ellipsoidal h), ``t_k`` a shift (px) and ``M_k`` a 2 × 2 linear part in pixels per 1000 pixels
(the affine model; zero in the shift model), ``c_k`` the image centre. Solved by
``scipy.optimize.least_squares`` (trust region, sparse Jacobian, soft-L1 loss), with

* the datum (gauge) freedom removed by holding the mean correction over all images at zero
  (``gauge="mean"``) or the first image fixed (``"first"``), and weak a-priori sigmas on every
  correction for the directions tie points cannot see (absolute height and tilt), as in
  Grodecki & Dial's weighted adjustment;
* outliers (mismatches, points that moved between epochs) removed in rounds: observations whose
  residual exceeds ``reject_k`` robust sigmas (and 1 px) are dropped and the problem solved again.

"Before" residuals come from the same solve with every correction held at zero (the ground points
still adjusted), on the same inlier observations. A k-fold check re-estimates the corrections
without a fifth of the tracks and measures those tracks' residuals (held out), so the "after"
figure is not only a fit residual.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
from scipy import sparse
from scipy.optimize import least_squares

from ..camera import Camera
from ..camera.corrected import CorrectedCamera
from ..geodesy import to_lonlat
from .params import OrientationParams
from .tiepoints import TiePoints

_LIN = 1000.0  # linear part in px per this many px


def _centres(cams: Sequence[Camera]) -> np.ndarray:
    return np.array([[0.5 * (c.width or 0), 0.5 * (c.height or 0)] for c in cams], dtype=np.float64)


def _project(cams: Sequence[Camera], tp: TiePoints, X: np.ndarray) -> np.ndarray:
    """(n_obs, 2) uncorrected projections of the track points ``X`` (n_tracks, 3) into their observing images."""
    P = X[tp.track]
    lon, lat = to_lonlat(P[:, 0], P[:, 1], tp.crs)
    out = np.empty((tp.image.size, 2))
    for k, cam in enumerate(cams):
        sel = tp.image == k
        if sel.any():
            c, r = cam.project(lon[sel], lat[sel], P[sel, 2])
            out[sel, 0], out[sel, 1] = c, r
    return out


def _correct(u: np.ndarray, img: np.ndarray, p: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """u + t + M/1000 (u − c) per observation; ``p`` is (n_img, 2) or (n_img, 6)."""
    out = u + p[img, :2]
    if p.shape[1] == 6:
        d = (u - centres[img]) / _LIN
        out[:, 0] += p[img, 2] * d[:, 0] + p[img, 3] * d[:, 1]
        out[:, 1] += p[img, 4] * d[:, 0] + p[img, 5] * d[:, 1]
    return out


@dataclass
class _Problem:
    cams: Sequence[Camera]
    tp: TiePoints
    n_par: int
    free_params: bool
    prior: np.ndarray  # (n_par,) a-priori sigma per parameter
    gauge: str
    centres: np.ndarray

    @property
    def n_img(self) -> int:
        return len(self.cams)

    def split(self, z: np.ndarray, p_fixed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        nt = self.tp.n_tracks
        X = z[: 3 * nt].reshape(nt, 3)
        p = z[3 * nt :].reshape(self.n_img, self.n_par) if self.free_params else p_fixed
        return X, p

    def residuals(self, z: np.ndarray, p_fixed: np.ndarray) -> np.ndarray:
        X, p = self.split(z, p_fixed)
        u = _project(self.cams, self.tp, X)
        r = (_correct(u, self.tp.image, p, self.centres) - self.tp.colrow).ravel()
        if not self.free_params:
            return r
        return np.concatenate([r, self._prior_rows(p)])

    def _prior_rows(self, p: np.ndarray) -> np.ndarray:
        rows = [(p / self.prior).ravel()]
        if self.gauge == "mean":
            rows.append(p.sum(axis=0) / 1e-3)
        else:
            rows.append(p[0] / 1e-3)
        return np.concatenate(rows)

    def jacobian(self, z: np.ndarray, p_fixed: np.ndarray) -> sparse.csr_matrix:
        X, p = self.split(z, p_fixed)
        tp = self.tp
        n_obs, nt = tp.image.size, tp.n_tracks
        u = _project(self.cams, tp, X)
        step = 0.05
        dU = np.empty((n_obs, 2, 3))
        for a in range(3):
            Xs = X.copy()
            Xs[:, a] += step
            dU[:, :, a] = (_project(self.cams, tp, Xs) - u) / step
        if p.shape[1] == 6:  # (I + M/1000) applied to the point derivatives
            m = p[tp.image, 2:] / _LIN
            g = dU.copy()
            g[:, 0, :] += m[:, 0, None] * dU[:, 0, :] + m[:, 1, None] * dU[:, 1, :]
            g[:, 1, :] += m[:, 2, None] * dU[:, 0, :] + m[:, 3, None] * dU[:, 1, :]
            dU = g
        rows, cols, vals = [], [], []
        obs = np.arange(n_obs)
        for comp in range(2):
            for a in range(3):
                rows.append(2 * obs + comp)
                cols.append(3 * tp.track + a)
                vals.append(dU[:, comp, a])
        n_cols = 3 * nt
        if self.free_params:
            base = 3 * nt
            k = tp.image
            for comp in range(2):
                rows.append(2 * obs + comp)
                cols.append(base + k * self.n_par + comp)
                vals.append(np.ones(n_obs))
            if self.n_par == 6:
                d = (u - self.centres[k]) / _LIN
                for comp, (ia, ib) in enumerate(((2, 3), (4, 5))):
                    for idx, col_d in ((ia, 0), (ib, 1)):
                        rows.append(2 * obs + comp)
                        cols.append(base + k * self.n_par + idx)
                        vals.append(d[:, col_d])
            n_cols += self.n_img * self.n_par
            # prior rows
            r0 = 2 * n_obs
            npar = self.n_img * self.n_par
            rows.append(r0 + np.arange(npar))
            cols.append(base + np.arange(npar))
            vals.append(np.tile(1.0 / self.prior, self.n_img))
            r1 = r0 + npar
            if self.gauge == "mean":
                for j in range(self.n_par):
                    rows.append(np.full(self.n_img, r1 + j))
                    cols.append(base + np.arange(self.n_img) * self.n_par + j)
                    vals.append(np.full(self.n_img, 1e3))
            else:
                rows.append(r1 + np.arange(self.n_par))
                cols.append(base + np.arange(self.n_par))
                vals.append(np.full(self.n_par, 1e3))
            n_rows = r1 + self.n_par
        else:
            n_rows = 2 * n_obs
        return sparse.csr_matrix(
            (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n_rows, n_cols)
        )


def _solve(
    cams,
    tp: TiePoints,
    X0: np.ndarray,
    p0: np.ndarray,
    params: OrientationParams,
    free_params: bool,
    max_nfev: int = 50,
) -> tuple[np.ndarray, np.ndarray]:
    n_par = p0.shape[1]
    prior = np.array([params.prior_shift_px] * 2 + [params.prior_linear_px] * (n_par - 2))
    pr = _Problem(cams, tp, n_par, free_params, prior, params.gauge, _centres(cams))
    z0 = np.concatenate([X0.ravel(), p0.ravel()]) if free_params else X0.ravel()
    res = least_squares(
        pr.residuals,
        z0,
        jac=pr.jacobian,
        args=(p0,),
        method="trf",
        loss="soft_l1",
        f_scale=1.0,
        x_scale="jac",
        tr_solver="lsmr",
        max_nfev=max_nfev,
        xtol=1e-10,
        ftol=1e-10,
    )
    return pr.split(res.x, p0)


def residual_norms(cams, tp: TiePoints, X: np.ndarray, p: np.ndarray) -> np.ndarray:
    """(n_obs,) reprojection residual (px) of every observation."""
    u = _correct(_project(cams, tp, X), tp.image, p, _centres(cams))
    return np.hypot(*(u - tp.colrow).T)


def _stats(r: np.ndarray) -> dict:
    if r.size == 0:
        return {"n": 0}
    return {
        "n": int(r.size),
        "median_px": round(float(np.median(r)), 3),
        "rms_px": round(float(np.sqrt(np.mean(r * r))), 3),
        "p90_px": round(float(np.percentile(r, 90)), 3),
    }


def _cross_epoch_obs(tp: TiePoints) -> np.ndarray:
    """Observations of tracks seen in two or more epochs."""
    ep = np.asarray([tp.epochs[k] for k in tp.image])
    cross = np.zeros(tp.n_tracks, dtype=bool)
    _, inv = np.unique(ep, return_inverse=True)
    first = np.full(tp.n_tracks, -1)
    for t, e in zip(tp.track, inv):
        if first[t] < 0:
            first[t] = e
        elif first[t] != e:
            cross[t] = True
    return cross[tp.track]


@dataclass
class OrientationResult:
    """What the adjustment found.

    Attributes
    ----------
    names, epochs : per image
    corrections : (n_img, 2) shift (Δcol, Δrow) px or (n_img, 6) with the linear part (px per 1000 px)
    applied : bool — False when the tie points were too few or ill-distributed (``reason`` says why)
    report : dict — residuals before/after (all, within-epoch, cross-epoch), held-out check, per image counts
    """

    names: list[str]
    epochs: list[str]
    corrections: np.ndarray
    applied: bool
    reason: str
    report: dict = field(default_factory=dict)
    tie_points: TiePoints | None = None
    inliers: np.ndarray | None = None

    def corrected_cameras(self, cams: Sequence[Camera]) -> list[Camera]:
        """The cameras with their corrections (the cameras themselves when not applied)."""
        if not self.applied:
            return list(cams)
        out = []
        centres = _centres(cams)
        for k, cam in enumerate(cams):
            p = self.corrections[k]
            lin = None if p.size == 2 else np.array([[p[2], p[3]], [p[4], p[5]]]) / _LIN
            out.append(
                CorrectedCamera(
                    cam,
                    p[:2],
                    lin,
                    centres[k],
                    provenance={"method": "tie-point bias compensation", "images": self.names, "image": self.names[k]},
                )
            )
        return out


def _hull_fraction(xy: np.ndarray, area_m2: float) -> float:
    from shapely.geometry import MultiPoint

    if xy.shape[0] < 3 or area_m2 <= 0:
        return 0.0
    return float(MultiPoint([tuple(v) for v in xy]).convex_hull.area / area_m2)


def adjust(
    cams: Sequence[Camera],
    tp: TiePoints,
    params: OrientationParams = OrientationParams(),
    *,
    aoi_area_m2: float,
    folds: int = 5,
    seed: int = 0,
) -> OrientationResult:
    """Estimate per-image corrections from tie points (see the module docstring)."""
    n_img, n_par = len(cams), params.n_params
    zero = np.zeros((n_img, n_par))
    if tp.n_tracks == 0:
        return OrientationResult(
            tp.names,
            tp.epochs,
            zero,
            False,
            "no tie point was found between the images",
            {"tracks": 0, "status": "insufficient"},
            tp,
            np.zeros(0, bool),
        )
    X0 = np.column_stack([tp.xy0, np.full(tp.n_tracks, tp.h0_m)])
    X, _ = _solve(cams, tp, X0, zero, params, free_params=False)
    cur = tp
    p = zero
    keep_all = np.ones(tp.image.size, dtype=bool)
    for _round in range(5):
        X, p = _solve(cams, cur, X, p, params, free_params=True)
        r = residual_norms(cams, cur, X, p)
        sigma = float(np.median(r)) / 1.1774 if r.size else 0.0
        bad = r > max(params.reject_k * sigma, 1.0)
        if not bad.any():
            break
        idx = np.flatnonzero(keep_all)
        keep_all[idx[bad]] = False
        counts = np.bincount(cur.track[~bad], minlength=cur.n_tracks)
        keep_tracks = counts >= 2
        X = X[keep_tracks]
        cur = cur.subset(~bad)
        # subset() also drops observations of tracks left with one observation
        survivors = np.flatnonzero(keep_all)
        counts_all = np.bincount(tp.track[survivors], minlength=tp.n_tracks)
        keep_all[survivors[counts_all[tp.track[survivors]] < 2]] = False
        if cur.n_tracks == 0:
            break
    inl = cur
    # before: the same inliers, corrections held at zero (points adjusted)
    Xb, _ = _solve(cams, inl, X, zero, params, free_params=False)
    r_before = residual_norms(cams, inl, Xb, zero)
    r_after = residual_norms(cams, inl, X, p)
    cross = _cross_epoch_obs(inl)
    report: dict = {
        "model": params.model,
        "gauge": params.gauge,
        "h0_m": round(tp.h0_m, 2),
        "tracks": int(inl.n_tracks),
        "observations": int(inl.image.size),
        "candidates_matched": int(tp.n_tracks),
        "observations_rejected": int(tp.image.size - inl.image.size),
        "before": {
            "all": _stats(r_before),
            "cross_epoch": _stats(r_before[cross]),
            "within_epoch_only_tracks": _stats(r_before[~cross]),
        },
        "after": {
            "all": _stats(r_after),
            "cross_epoch": _stats(r_after[cross]),
            "within_epoch_only_tracks": _stats(r_after[~cross]),
        },
        "pairs": tp.pair_stats,
    }
    # per image counts and spread
    per_image = {}
    reasons = []
    for k, name in enumerate(tp.names):
        sel = inl.image == k
        xy = inl.xy0[inl.track[sel]]
        spread = _hull_fraction(xy, aoi_area_m2)
        per_image[name] = {
            "observations": int(sel.sum()),
            "hull_fraction": round(spread, 3),
            "correction": [round(float(v), 3) for v in p[k]],
            "residual_after": _stats(r_after[sel]),
            "residual_before": _stats(r_before[sel]),
        }
        if sel.sum() < params.min_points:
            reasons.append(f"{name}: {int(sel.sum())} tie-point observations (fewer than {params.min_points})")
        elif spread < params.min_spread:
            reasons.append(
                f"{name}: tie points cover {100 * spread:.0f}% of the AOI (less than {100 * params.min_spread:.0f}%)"
            )
    report["images"] = per_image
    if len(set(tp.epochs)) > 1 and int(np.unique(inl.track[cross]).size) < params.min_points:
        reasons.append(
            f"only {int(np.unique(inl.track[cross]).size)} tie points link the epochs (fewer than {params.min_points})"
        )
    # held-out check: corrections without a fold of tracks, residuals of that fold
    if not reasons and folds >= 2 and inl.n_tracks >= 5 * folds:
        rng = np.random.default_rng(seed)
        fold_of = rng.integers(0, folds, inl.n_tracks)
        held, held_cross = [], []
        for f in range(folds):
            train = fold_of[inl.track] != f
            tr = inl.subset(train)
            kept = np.unique(inl.track[train])
            kept = kept[np.bincount(inl.track[train], minlength=inl.n_tracks)[kept] >= 2]
            _, pf = _solve(cams, tr, X[kept], p, params, free_params=True)
            te = inl.subset(~train)
            used = np.unique(inl.track[~train])
            Xt, _ = _solve(cams, te, X[used], pf, params, free_params=False)
            rt = residual_norms(cams, te, Xt, pf)
            held.append(rt)
            held_cross.append(rt[_cross_epoch_obs(te)])
        report["held_out"] = {
            "folds": folds,
            "all": _stats(np.concatenate(held)),
            "cross_epoch": _stats(np.concatenate(held_cross)),
        }
    status = "insufficient" if reasons else "applied"
    largest = float(np.max(np.hypot(p[:, 0], p[:, 1]))) if p.size else 0.0
    if not reasons and largest < params.min_correction_px:
        status = "not needed"
        reasons.append(
            f"the largest correction, {largest:.2f} px, is below {params.min_correction_px:g} px: "
            "the cameras already agree"
        )
    report["status"] = status
    report["largest_correction_px"] = round(largest, 3)
    applied = status == "applied"
    return OrientationResult(
        tp.names, tp.epochs, p if applied else zero, applied, "; ".join(reasons), report, tp, keep_all
    )
