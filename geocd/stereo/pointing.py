"""Relative pointing correction of a pair (cross-epipolar bias), estimated in object space.

Satellite RPCs carry pointing errors of a few pixels; what matters for
matching is the *relative* error between the two images. Its component along
the epipolar direction is indistinguishable from a constant height offset (it
shifts the whole pair-DEM vertically — harmless for change detection, which
compares heights of the same pair geometry class), but its component *across*
the epipolar direction ("y-parallax") makes the two windows never line up at
any height, and a 2–3 px y-parallax is enough to ruin matching on fine texture
(s2p and CARS correct it with sparse matches for the same reason).

Estimate: warp both images onto the grid at an approximate surface; tile the
grid into patches; find each patch's 2-D shift between the two warped images
(normalized cross-correlation, sub-cell peak). A height error moves the content
along ``d = A_a − A_b`` (ground metres per metre of height, with
``A_n = (∂u_n/∂(x,y))⁻¹ ∂u_n/∂z`` the relief displacement of image n), so the
median of the shifts' components across ``d`` is the relative pointing error.
It is applied to image b as a constant image-space shift
``β = ∂u_b/∂(x,y) · s⊥`` (pixels), i.e. in the camera's own pixel frame.
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from .._fft import fftconvolve
from ..camera import Camera
from ..geodesy import AOIGrid
from .sweep import ImageChip


def _jacobians(
    cam: Camera, grid: AOIGrid, x: float, y: float, h: float, d: float = 1.0
) -> tuple[np.ndarray, np.ndarray]:
    """∂u/∂(x, y) (2×2, px per m) and ∂u/∂z (2,) at one ground point."""
    pr = cam.ground_projector(np.array([x, x + d, x]), np.array([y, y, y + d]), grid.crs)
    c, r = pr.project(np.full(3, h))
    Jxy = np.array([[c[1] - c[0], c[2] - c[0]], [r[1] - r[0], r[2] - r[0]]]) / d
    dc, dr = cam.ground_projector(np.array([x]), np.array([y]), grid.crs).dproj_dh(np.array([h]))
    return Jxy, np.array([float(dc[0]), float(dr[0])])


def _ncc_shift(a: np.ndarray, b: np.ndarray, max_shift: int) -> tuple[float, float, float]:
    """Shift (drow, dcol) such that b[i + drow, j + dcol] ≈ a[i, j] over the patch, and its NCC peak.

    ``a`` is (P, P), ``b`` is (P + 2M, P + 2M) centred on it. NaN = invalid.
    """
    M = max_shift
    ta = np.where(np.isfinite(a), a, np.nan)
    ta = ta - np.nanmean(ta)
    ta = np.nan_to_num(ta)
    na = np.sqrt(np.sum(ta * ta))
    if na <= 0:
        return np.nan, np.nan, np.nan
    bb = np.nan_to_num(b - np.nanmean(b))
    num = fftconvolve(bb, ta[::-1, ::-1], "valid")  # (2M+1, 2M+1)
    ones = np.ones_like(ta)
    s1 = fftconvolve(bb, ones, "valid")
    s2 = fftconvolve(bb * bb, ones, "valid")
    var = np.maximum(s2 - s1 * s1 / ones.size, 1e-9)
    ncc = num / (na * np.sqrt(var))
    i, j = np.unravel_index(np.argmax(ncc), ncc.shape)
    peak = float(ncc[i, j])
    if i in (0, 2 * M) or j in (0, 2 * M):
        return np.nan, np.nan, peak

    def sub(cm, c0, cp):
        den = cm - 2 * c0 + cp
        return 0.5 * (cm - cp) / den if den < 0 else 0.0

    di = sub(ncc[i - 1, j], ncc[i, j], ncc[i + 1, j])
    dj = sub(ncc[i, j - 1], ncc[i, j], ncc[i, j + 1])
    return float(i + di - M), float(j + dj - M), peak


def relative_pointing(
    grid: AOIGrid,
    chips: Sequence[ImageChip],
    cameras: Sequence[Camera],
    surface_m: np.ndarray,
    *,
    patch: int = 48,
    max_shift: int = 12,
    min_peak: float = 0.5,
    min_patches: int = 4,
) -> dict[str, Any]:
    """Relative pointing error of image b against image a, across the epipolar direction.

    Parameters
    ----------
    grid : AOIGrid (projected, metres)
    chips, cameras : the pair (a, b)
    surface_m : float (rows, cols), approximate ellipsoidal heights on ``grid``
        (a coarse match or a prior DEM; errors of a few metres only move content
        along the epipolar direction, which the estimate ignores)
    patch, max_shift : patch side and search radius, in cells

    Returns
    -------
    dict with ``dcol``, ``drow`` (the shift to add to camera b's image coordinates,
    pixels), ``cross_px`` (its size), ``n_patches``, ``spread_px`` (MAD of the
    patches' cross components, pixels), ``applied`` (False when too few patches
    agreed: then dcol = drow = 0).
    """
    from .sweep import PlaneSweep, HeightSearch

    H, W = grid.shape
    z = np.where(np.isfinite(surface_m), surface_m, np.nanmedian(surface_m))
    sw = PlaneSweep(grid, list(chips[:2]), list(cameras[:2]), HeightSearch.uniform(grid.shape, 0.0, 1.0, 1.0))
    wa, wb = sw.warp_at(z)
    xc, yc = grid.xy(np.array([H // 2]), np.array([W // 2]))
    h0 = float(np.nanmedian(z))
    Ja_xy, Ja = _jacobians(cameras[0], grid, float(xc[0]), float(yc[0]), h0)
    Jb_xy, Jb = _jacobians(cameras[1], grid, float(xc[0]), float(yc[0]), h0)
    d = np.linalg.solve(Ja_xy, Ja) - np.linalg.solve(Jb_xy, Jb)  # ground m per m of height
    out = {"dcol": 0.0, "drow": 0.0, "cross_px": 0.0, "n_patches": 0, "spread_px": float("nan"), "applied": False}
    nd = np.linalg.norm(d)
    if not nd > 1e-9:
        return out
    dperp = np.array([-d[1], d[0]]) / nd  # unit, ground (x east, y north)
    px, py = grid.posting
    M = max_shift
    vals = []
    for r0 in range(M, H - patch - M + 1, patch):
        for c0 in range(M, W - patch - M + 1, patch):
            a = wa[r0 : r0 + patch, c0 : c0 + patch]
            b = wb[r0 - M : r0 + patch + M, c0 - M : c0 + patch + M]
            if np.isfinite(a).mean() < 0.9 or np.isfinite(b).mean() < 0.9:
                continue
            dr, dc, peak = _ncc_shift(a, b, M)
            if not (np.isfinite(dr) and peak >= min_peak):
                continue
            s = np.array([dc * px, -dr * py])  # ground metres
            vals.append(float(s @ dperp))
    out["n_patches"] = len(vals)
    if len(vals) < min_patches:
        return out
    v = np.asarray(vals)
    s_perp = float(np.median(v))
    beta = Jb_xy @ (s_perp * dperp)  # pixels of image b
    rho_b = float(np.sqrt(abs(np.linalg.det(Jb_xy))))
    out.update(
        dcol=float(beta[0]),
        drow=float(beta[1]),
        cross_px=float(np.hypot(*beta)),
        spread_px=float(1.4826 * np.median(np.abs(v - s_perp)) * rho_b),
        applied=True,
    )
    return out
