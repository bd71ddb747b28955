"""Automatic tie points between all images of all epochs, found on orthos at a reference height.

Every image is resampled onto the AOI grid at one ellipsoidal height ``h0`` through its own
camera (an "ortho at h0"). A ground point at height ``h`` then appears in the ortho of image
``k`` displaced by ``(h − h0)·a_k`` (``a_k``: the relief displacement of image k, ortho pixels per
metre), plus the image's pointing bias. Between two orthos the displacement of a point is
therefore ``(h − h0)(a_o − a_r) + bias``: along the *epipolar direction* ``a_o − a_r`` it carries
the point's height, across it only the relative bias — a constant over a small scene. That is
the geometric test that rejects false matches.

Matching: the strongest Harris corner of each block of the reference ortho (the first image
of the first epoch) is a candidate; a coarse pass on 2 m orthos finds the bias of every other
image (median over many patches, robust to the relief), a fine pass matches each candidate by
normalized cross-correlation (sub-pixel parabola), keeps it when the match back from the other
ortho returns to it within a pixel, and when its displacement across the epipolar direction
agrees with the others'. Each candidate with at least one match is a *track*: one ground point
seen by several images; its observations are image coordinates in each image's own pixel frame
(exact: the ortho was sampled through that image's camera at h0).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
from scipy.ndimage import map_coordinates
from skimage.feature import corner_harris

from ..camera import Camera
from ..geodesy import AOIGrid, to_lonlat
from ..progress import Progress, ensure_progress
from ._kernels import ncc_at_offsets
from .params import OrientationParams


@dataclass
class OrthoView:
    """One image resampled onto the AOI grid at height ``h0_m`` (NaN where the image does not reach)."""

    name: str
    epoch: str
    camera: Camera
    ortho: np.ndarray
    relief_px_per_m: np.ndarray  # (2,) displacement (drow, dcol) in ortho pixels per metre above h0


@dataclass
class TiePoints:
    """Tie-point observations: ``colrow[k]`` is where track ``track[k]`` is seen in image ``image[k]``.

    Attributes
    ----------
    names, epochs : per image
    image, track : (n_obs,) int
    colrow : (n_obs, 2) float64, image pixels (col, row) in each image's own frame
    xy0 : (n_tracks, 2) float64, map coordinates (grid CRS) of each track in the reference ortho
    h0_m : float, the reference height the orthos were made at
    ncc : (n_obs,) float, NCC peak of the match (1 for the reference observation)
    """

    names: list[str]
    epochs: list[str]
    image: np.ndarray
    track: np.ndarray
    colrow: np.ndarray
    xy0: np.ndarray
    h0_m: float
    crs: object
    ncc: np.ndarray
    pair_stats: dict = field(default_factory=dict)

    @property
    def n_tracks(self) -> int:
        return int(self.xy0.shape[0])

    def subset(self, keep_obs: np.ndarray) -> "TiePoints":
        """The observations where ``keep_obs``; tracks left with fewer than two observations are dropped."""
        keep = np.asarray(keep_obs, bool).copy()
        counts = np.bincount(self.track[keep], minlength=self.n_tracks)
        keep &= counts[self.track] >= 2
        used = np.unique(self.track[keep])
        remap = -np.ones(self.n_tracks, dtype=np.int64)
        remap[used] = np.arange(used.size)
        return TiePoints(
            self.names,
            self.epochs,
            self.image[keep],
            remap[self.track[keep]],
            self.colrow[keep],
            self.xy0[used],
            self.h0_m,
            self.crs,
            self.ncc[keep],
            self.pair_stats,
        )


def ortho_at_height(image: np.ndarray, col0: int, row0: int, camera: Camera, grid: AOIGrid, h_m: float) -> np.ndarray:
    """Resample an image window (upper-left pixel at ``(col0, row0)`` of the image) onto ``grid`` at height ``h_m``.

    Returns float32 (rows, cols), NaN where the grid projects outside the window.
    """
    x, y = grid.xy()
    c, r = camera.ground_projector(x, y, grid.crs).project(np.float64(h_m))
    out = map_coordinates(
        np.asarray(image, dtype=np.float32), [r - 0.5 - row0, c - 0.5 - col0], order=1, cval=np.nan, prefilter=False
    )
    return out.astype(np.float32)


def relief_displacement(camera: Camera, grid: AOIGrid, h_m: float) -> np.ndarray:
    """(drow, dcol) in ortho pixels per metre: where a point ``dh`` above ``h_m`` appears in the ortho at ``h_m``.

    Uses ``J⁻¹ ∂u/∂h`` at the grid centre (``J`` = ∂(col,row)/∂(x,y)).
    """
    l, b, r, t = grid.bounds
    x, y, d = 0.5 * (l + r), 0.5 * (b + t), 1.0
    pr = camera.ground_projector(np.array([x, x + d, x]), np.array([y, y, y + d]), grid.crs)
    c, rw = pr.project(np.full(3, h_m))
    J = np.array([[c[1] - c[0], c[2] - c[0]], [rw[1] - rw[0], rw[2] - rw[0]]]) / d
    dc, dr = camera.ground_projector(np.array([x]), np.array([y]), grid.crs).dproj_dh(np.array([h_m]))
    # the ortho pixel X' shows at h0 what X shows at h0 + dh: J (X' − X) = ∂u/∂h · dh
    axy = np.linalg.solve(J, np.array([float(dc[0]), float(dr[0])]))  # metres (x, y) per metre of height
    return np.array([-axy[1], axy[0]]) / grid.posting_m


def _fill(a: np.ndarray) -> np.ndarray:
    v = np.isfinite(a)
    return np.where(v, a, np.nanmean(a) if v.any() else 0.0).astype(np.float32)


def _downsample(a: np.ndarray, f: int) -> np.ndarray:
    if f <= 1:
        return a
    h, w = (a.shape[0] // f) * f, (a.shape[1] // f) * f
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanmean(a[:h, :w].reshape(h // f, f, w // f, f), axis=(1, 3)).astype(np.float32)


def corner_candidates(ortho: np.ndarray, block: int, border: int, rel: float = 0.01) -> np.ndarray:
    """(n, 2) int (row, col): the strongest Harris corner of each ``block`` × ``block`` cell of the ortho."""
    R = corner_harris(_fill(ortho), sigma=1.5)
    R[~np.isfinite(ortho)] = 0.0
    H, W = R.shape
    R[:border] = 0
    R[-border:] = 0
    R[:, :border] = 0
    R[:, -border:] = 0
    thr = rel * float(np.percentile(R[R > 0], 99)) if np.any(R > 0) else np.inf
    out = []
    for i in range(0, H, block):
        for j in range(0, W, block):
            sub = R[i : i + block, j : j + block]
            k = int(np.argmax(sub))
            a, b = divmod(k, sub.shape[1])
            if sub[a, b] > thr:
                out.append((i + a, j + b))
    return np.asarray(out, dtype=np.int64).reshape(-1, 2)


def square_offsets(half: int) -> np.ndarray:
    """(m, 2) int64 offsets (drow, dcol) of a (2·half+1)² square."""
    r = np.arange(-half, half + 1)
    R, C = np.meshgrid(r, r, indexing="ij")
    return np.column_stack([R.ravel(), C.ravel()]).astype(np.int64)


def band_offsets(along: np.ndarray, along_half: float, cross_half: float) -> np.ndarray:
    """(m, 2) int64 offsets within ``along_half`` px along the unit vector ``along`` and ``cross_half`` across it."""
    half = int(math.ceil(max(along_half, cross_half)))
    sq = square_offsets(half).astype(np.float64)
    u = np.asarray(along, dtype=np.float64)
    n = np.array([-u[1], u[0]])
    keep = (np.abs(sq @ u) <= along_half) & (np.abs(sq @ n) <= cross_half)
    return sq[keep].astype(np.int64)


def match_points(
    ref: np.ndarray, oth: np.ndarray, pts: np.ndarray, centres: np.ndarray, offsets: np.ndarray, P: int
) -> np.ndarray:
    """(n, 3) sub-pixel (row, col, ncc) of each point's best match (NaN rows where none); numba kernel."""
    if len(pts) == 0:
        return np.zeros((0, 3))
    return ncc_at_offsets(
        np.ascontiguousarray(ref, dtype=np.float32),
        np.ascontiguousarray(oth, dtype=np.float32),
        np.ascontiguousarray(pts, dtype=np.int64),
        np.ascontiguousarray(centres, dtype=np.int64),
        np.ascontiguousarray(offsets, dtype=np.int64),
        int(P),
    )


def _epipolar_frame(e: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    n = float(np.hypot(*e))
    if n < 1e-6:
        return np.array([1.0, 0.0]), np.array([0.0, 1.0]), 0.0
    u = e / n
    return u, np.array([-u[1], u[0]]), n


def _coarse_offset(ref: OrthoView, oth: OrthoView, posting_m: float, params: OrientationParams) -> np.ndarray | None:
    """Median displacement (drow, dcol) in full-resolution ortho pixels from a 2 m pass (None if it fails)."""
    f = max(1, int(round(2.0 / posting_m)))
    a, b = _downsample(ref.ortho, f), _downsample(oth.ortho, f)
    P = 8
    S = int(math.ceil(params.max_offset_m / (posting_m * f)))
    cands = corner_candidates(a, block=16, border=P + 1)
    m = match_points(a, b, cands, cands, square_offsets(S), P)
    ok = np.isfinite(m[:, 0]) & (m[:, 2] >= params.min_ncc)
    if ok.sum() < 5:
        return None
    d = (m[ok, :2] - cands[ok]) * f
    u, n, norm = _epipolar_frame(oth.relief_px_per_m - ref.relief_px_per_m)
    cross, along = d @ n, d @ u
    c0 = np.median(cross)
    ok = np.abs(cross - c0) <= 2.0 * f
    if ok.sum() < 5:
        return None
    a0 = np.median(along[ok]) if norm > 0 else np.median(along)
    c0 = np.median(cross[ok])
    return c0 * n + a0 * u


def find_tie_points(
    views: Sequence[OrthoView],
    grid: AOIGrid,
    h0_m: float,
    params: OrientationParams = OrientationParams(),
    progress: Progress | None = None,
) -> TiePoints:
    """Tie points between the first view and every other (see the module docstring).

    Parameters
    ----------
    views : orthos of every image at ``h0_m`` on ``grid`` (the first is the reference)
    """
    prog = ensure_progress(progress)
    ref = views[0]
    P = params.patch_px
    cands = corner_candidates(ref.ortho, block=params.block_px, border=P + 2)
    n_c = len(cands)
    pos = {0: cands.astype(np.float64)}
    ncc = {0: np.ones(n_c)}
    pair_stats: dict = {}
    for k, oth in enumerate(views[1:], start=1):
        prog((k - 1) / max(len(views) - 1, 1), f"tie points {ref.name} ↔ {oth.name}")
        d0 = _coarse_offset(ref, oth, grid.posting_m, params)
        if d0 is None:
            pair_stats[oth.name] = {"coarse_offset_px": None, "matches": 0, "inliers": 0}
            pos[k], ncc[k] = np.full((n_c, 2), np.nan), np.full(n_c, np.nan)
            continue
        u, nrm, norm = _epipolar_frame(oth.relief_px_per_m - ref.relief_px_per_m)
        offs = band_offsets(u, norm * params.height_span_m + 3.0, 3.0)
        centres = np.rint(cands + d0).astype(np.int64)
        fw = match_points(ref.ortho, oth.ortho, cands, centres, offs, P)
        good = np.isfinite(fw[:, 0]) & (fw[:, 2] >= params.min_ncc)
        # the match back from the other ortho must return to the candidate within a pixel
        back_from = np.rint(np.where(good[:, None], fw[:, :2], 0)).astype(np.int64)
        bw = match_points(oth.ortho, ref.ortho, back_from, cands, square_offsets(2), P)
        back = bw[:, :2] + (fw[:, :2] - back_from)
        good &= np.isfinite(bw[:, 0]) & (np.hypot(back[:, 0] - cands[:, 0], back[:, 1] - cands[:, 1]) <= 1.0)
        found = np.where(good[:, None], fw[:, :2], np.nan)
        peak = np.where(good, fw[:, 2], np.nan)
        ok = np.isfinite(found[:, 0])
        d = found - cands
        cross = d @ nrm
        along = d @ u
        keep = ok.copy()
        if ok.sum() >= 3:
            c0 = np.median(cross[ok])
            mad = 1.4826 * np.median(np.abs(cross[ok] - c0))
            keep &= np.abs(cross - c0) <= max(3.0 * mad, 1.0)
            if norm < 1e-6:  # the same direction of view: the along component is constant too
                a0 = np.median(along[ok])
                mad_a = 1.4826 * np.median(np.abs(along[ok] - a0))
                keep &= np.abs(along - a0) <= max(3.0 * mad_a, 1.0)
        found[~keep] = np.nan
        peak[~keep] = np.nan
        pair_stats[oth.name] = {
            "coarse_offset_px": [round(float(v), 2) for v in d0],
            "matches": int(ok.sum()),
            "inliers": int(keep.sum()),
            "epipolar_px_per_m": round(norm, 4),
        }
        pos[k], ncc[k] = found, peak
    prog(1.0, "tie points done")
    # tracks: candidates matched in at least one other view
    matched = np.zeros(n_c, dtype=bool)
    for k in range(1, len(views)):
        matched |= np.isfinite(pos[k][:, 0])
    track_ids = -np.ones(n_c, dtype=np.int64)
    track_ids[matched] = np.arange(int(matched.sum()))
    T = grid.transform
    images, tracks, colrow, peaks = [], [], [], []
    for k, v in enumerate(views):
        p = pos[k]
        sel = matched & np.isfinite(p[:, 0])
        if not sel.any():
            continue
        rows, cols = p[sel, 0], p[sel, 1]
        x = T.c + (cols + 0.5) * T.a + (rows + 0.5) * T.b
        y = T.f + (cols + 0.5) * T.d + (rows + 0.5) * T.e
        lon, lat = to_lonlat(x, y, grid.crs)
        c, r = v.camera.project(lon, lat, np.full(lon.shape, h0_m))
        images.append(np.full(sel.sum(), k))
        tracks.append(track_ids[sel])
        colrow.append(np.column_stack([c, r]))
        peaks.append(ncc[k][sel])
    r0, c0 = cands[matched, 0].astype(float), cands[matched, 1].astype(float)
    xy0 = np.column_stack([T.c + (c0 + 0.5) * T.a + (r0 + 0.5) * T.b, T.f + (c0 + 0.5) * T.d + (r0 + 0.5) * T.e])

    def cat(xs, shape):
        return np.concatenate(xs) if xs else np.zeros(shape)

    return TiePoints(
        names=[v.name for v in views],
        epochs=[v.epoch for v in views],
        image=cat(images, (0,)).astype(np.int64),
        track=cat(tracks, (0,)).astype(np.int64),
        colrow=cat(colrow, (0, 2)),
        xy0=xy0.reshape(-1, 2),
        h0_m=float(h0_m),
        crs=grid.crs,
        ncc=cat(peaks, (0,)),
        pair_stats=pair_stats,
    )
