"""Camera rays in the volume's ENU frame, for any camera of the camera protocol.

A pixel's ray is the line through its ground points at two ellipsoidal heights
(``camera.localize`` above the volume top and below its bottom), expressed in
the model's :class:`~geocd.geodesy.LocalFrame`. That works the same for RPC,
pushbroom and frame cameras (never branch on the camera kind); over a volume
tens of metres high the line of sight of every model in geocd is straight to far
below a millimetre. Rays start at the upper point and point downwards.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..errors import CameraError, NoOverlapError
from .scene import VolumeGeometry

#: heights above the volume top and below its bottom where rays are localized (m)
RAY_MARGIN_M = 2.0


def pixel_rays(
    camera: Any, geometry: VolumeGeometry, cols: np.ndarray, rows: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Rays through image points ``(col, row)`` (continuous pixels, GDAL convention).

    Parameters
    ----------
    camera : geocd.camera.Camera
    geometry : VolumeGeometry
    cols, rows : ndarray, same shape (N,) — pass pixel centres (``j + 0.5``, ``i + 0.5``).

    Returns
    -------
    orig : (N, 3) float64, ENU m — the point at the upper height (NaN where the camera
        cannot localize the pixel).
    dirs : (N, 3) float64 — unit directions, downwards.
    """
    fr = geometry.frame
    z0, z1 = geometry.z_range_enu
    h_top = fr.h0 + z1 + RAY_MARGIN_M
    h_bot = fr.h0 + z0 - RAY_MARGIN_M
    cols = np.asarray(cols, dtype=np.float64).ravel()
    rows = np.asarray(rows, dtype=np.float64).ravel()
    with np.errstate(all="ignore"):
        lon1, lat1 = camera.localize(cols, rows, np.full(cols.shape, h_top))
        lon0, lat0 = camera.localize(cols, rows, np.full(cols.shape, h_bot))
        a = np.stack(fr.to_enu(lon1, lat1, np.full(cols.shape, h_top)), axis=-1)
        b = np.stack(fr.to_enu(lon0, lat0, np.full(cols.shape, h_bot)), axis=-1)
        d = b - a
        nrm = np.linalg.norm(d, axis=-1, keepdims=True)
        d = d / nrm
    bad = ~(np.all(np.isfinite(a), axis=-1) & np.all(np.isfinite(d), axis=-1))
    a[bad] = np.nan
    d[bad] = np.nan
    return np.ascontiguousarray(a), np.ascontiguousarray(d)


def image_rays(
    camera: Any, geometry: VolumeGeometry, row0: int, row1: int, width: int, stride: int = 1, supersample: int = 1
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Rays of the pixel centres of image rows ``row0:row1`` (every ``stride``-th pixel).

    With ``supersample = k > 1``, each pixel gets k×k rays on a regular sub-pixel
    grid (for octree cells smaller than a pixel's footprint).

    Returns ``orig, dirs`` (N, 3) and the integer ``rows, cols`` (N,) of the pixels.
    """
    rr = np.arange(row0, row1, stride)
    cc = np.arange(0, width, stride)
    R, C = np.meshgrid(rr, cc, indexing="ij")
    R, C = R.ravel(), C.ravel()
    k = max(int(supersample), 1)
    if k == 1:
        o, d = pixel_rays(camera, geometry, C + 0.5, R + 0.5)
        return o, d, R, C
    off = (np.arange(k) + 0.5) / k
    dr, dc = np.meshgrid(off, off, indexing="ij")
    Rs = (R[:, None] + dr.ravel()[None, :]).ravel()
    Cs = (C[:, None] + dc.ravel()[None, :]).ravel()
    o, d = pixel_rays(camera, geometry, Cs, Rs)
    return o, d, np.repeat(R, k * k), np.repeat(C, k * k)


def check_camera_sees_volume(
    camera: Any, geometry: VolumeGeometry, width: int, height: int, name: str = "the image"
) -> None:
    """Clear errors for a camera that gives no rays (NaN parameters) or misses the volume.

    Raises
    ------
    CameraError
        When not one pixel of a coarse grid can be localized (e.g. NaN parameters).
    NoOverlapError
        When no ray of the image crosses the volume box.
    """
    n = 24
    cc = np.linspace(0.5, width - 0.5, n)
    rr = np.linspace(0.5, height - 0.5, n)
    C, R = np.meshgrid(cc, rr)
    try:
        o, d = pixel_rays(camera, geometry, C.ravel(), R.ravel())
    except (ValueError, ArithmeticError, FloatingPointError) as exc:
        raise CameraError(f"the camera of {name} cannot localize its pixels ({exc}); check its parameters") from exc
    ok = np.all(np.isfinite(o), axis=1) & np.all(np.isfinite(d), axis=1)
    if not ok.any():
        raise CameraError(
            f"the camera of {name} gives no finite viewing ray (NaN or degenerate parameters?); check the camera "
            "file (RPC coefficients, frame position/orientation)"
        )
    lo, hi = geometry.box_lo, geometry.box_hi
    hit = _rays_hit_box(o[ok], d[ok], lo, hi)
    if not hit.any():
        # the grid may skip a small volume: test the volume's corners projected into the image
        if not _box_projects_into_image(camera, geometry, width, height):
            raise NoOverlapError(
                f"{name} does not see the volume (no viewing ray crosses the model's box "
                f"{np.round(lo, 1).tolist()}–{np.round(hi, 1).tolist()} m ENU); check that the image covers the "
                "model's AOI and that its camera is right"
            )


def _rays_hit_box(o: np.ndarray, d: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        ta = (lo - o) * inv
        tb = (hi - o) * inv
    tmin = np.nanmax(np.minimum(ta, tb), axis=1)
    tmax = np.nanmin(np.maximum(ta, tb), axis=1)
    return tmax > np.maximum(tmin, 0.0)


def _box_projects_into_image(camera: Any, geometry: VolumeGeometry, width: int, height: int) -> bool:
    lo, hi = geometry.box_lo, geometry.box_hi
    g = np.linspace(0, 1, 5)
    X, Y, Z = np.meshgrid(lo[0] + g * (hi[0] - lo[0]), lo[1] + g * (hi[1] - lo[1]), [lo[2], hi[2]])
    lon, lat, h = geometry.frame.from_enu(X.ravel(), Y.ravel(), Z.ravel())
    with np.errstate(all="ignore"):
        c, r = camera.project(lon, lat, h)
    ok = np.isfinite(c) & np.isfinite(r) & (c >= 0) & (c <= width) & (r >= 0) & (r <= height)
    return bool(ok.any())


def vertical_rays(geometry: VolumeGeometry, e: np.ndarray, n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rays straight down (ENU −up) from just above the volume top at ENU points (e, n)."""
    e = np.asarray(e, dtype=np.float64).ravel()
    n = np.asarray(n, dtype=np.float64).ravel()
    top = geometry.box_hi[2] + 1.0
    o = np.stack([e, n, np.full(e.shape, top)], axis=-1)
    d = np.zeros_like(o)
    d[:, 2] = -1.0
    return o, d


__all__ = ["pixel_rays", "image_rays", "check_camera_sees_volume", "vertical_rays", "NoOverlapError"]
