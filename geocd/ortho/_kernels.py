"""numba kernels of the orthorectifier, each with a pure-numpy reference.

Conventions
-----------
* Images are ``(bands, rows, cols)`` float32 or float64 with a separate
  ``valid`` uint8 ``(rows, cols)`` mask (any input dtype is cast to float first;
  integers up to 24 bits are exact in float32).
* Image coordinates ``(col, row)`` are continuous with ``(0, 0)`` at the
  upper-left *corner* of the upper-left pixel (geocd/GDAL convention).
* Grid arrays (DSM, ray directions) are indexed ``[i, j]`` = (row, col) with
  cell centres at integer positions for the ray march.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from .._jit import parallel_njit

NEAREST = 0
BILINEAR = 1


# ---------------------------------------------------------------------------------------------
# sampling an image at projected positions
# ---------------------------------------------------------------------------------------------
@parallel_njit()
def sample_image(img, valid, col, row, mode, out, ok):
    """Sample a multi-band image at continuous ``(col, row)``.

    ``mode`` 0 (nearest): the pixel containing the point. ``mode`` 1 (bilinear):
    the four pixel centres around the point; within half a pixel of the image
    border the edge pixel is repeated. A sample is valid when the point lies in
    the image and every pixel it uses (with a non-zero weight) is valid.

    Parameters
    ----------
    img : float32/float64 (B, H, W)
    valid : uint8 (H, W)
    col, row : float64 (h, w), image coordinates relative to ``img``
    mode : int, NEAREST or BILINEAR
    out : (B, h, w) of ``img``'s dtype, written (0 where not ok)
    ok : bool (h, w), written
    """
    B, H, W = img.shape
    h, w = col.shape
    for i in prange(h):
        for j in range(w):
            c = col[i, j]
            r = row[i, j]
            good = c >= 0.0 and r >= 0.0 and c < W and r < H  # False for NaN
            if good and mode == NEAREST:
                jj = int(c)
                ii = int(r)
                if valid[ii, jj] == 0:
                    good = False
                else:
                    for b in range(B):
                        out[b, i, j] = img[b, ii, jj]
            elif good:
                x = min(max(c - 0.5, 0.0), W - 1.0)
                y = min(max(r - 0.5, 0.0), H - 1.0)
                j0 = min(int(x), W - 1)
                i0 = min(int(y), H - 1)
                fx = x - j0
                fy = y - i0
                j1 = min(j0 + 1, W - 1)
                i1 = min(i0 + 1, H - 1)
                w00 = (1.0 - fx) * (1.0 - fy)
                w01 = fx * (1.0 - fy)
                w10 = (1.0 - fx) * fy
                w11 = fx * fy
                if (
                    (w00 > 0.0 and valid[i0, j0] == 0)
                    or (w01 > 0.0 and valid[i0, j1] == 0)
                    or (w10 > 0.0 and valid[i1, j0] == 0)
                    or (w11 > 0.0 and valid[i1, j1] == 0)
                ):
                    good = False
                else:
                    for b in range(B):
                        v = 0.0
                        if w00 > 0.0:
                            v += w00 * img[b, i0, j0]
                        if w01 > 0.0:
                            v += w01 * img[b, i0, j1]
                        if w10 > 0.0:
                            v += w10 * img[b, i1, j0]
                        if w11 > 0.0:
                            v += w11 * img[b, i1, j1]
                        out[b, i, j] = v
            ok[i, j] = good
            if not good:
                for b in range(B):
                    out[b, i, j] = 0.0


def sample_image_ref(
    img: np.ndarray, valid: np.ndarray, col: np.ndarray, row: np.ndarray, mode: int
) -> tuple[np.ndarray, np.ndarray]:
    """numpy reference of :func:`sample_image` → (out, ok)."""
    B, H, W = img.shape
    inside = (col >= 0) & (row >= 0) & (col < W) & (row < H)
    c = np.where(inside, col, 0.0)
    r = np.where(inside, row, 0.0)
    if mode == NEAREST:
        jj = np.minimum(c.astype(np.int64), W - 1)
        ii = np.minimum(r.astype(np.int64), H - 1)
        ok = inside & (valid[ii, jj] > 0)
        out = img[:, ii, jj]
    else:
        x = np.clip(c - 0.5, 0.0, W - 1.0)
        y = np.clip(r - 0.5, 0.0, H - 1.0)
        j0 = np.minimum(x.astype(np.int64), W - 1)
        i0 = np.minimum(y.astype(np.int64), H - 1)
        fx, fy = x - j0, y - i0
        j1, i1 = np.minimum(j0 + 1, W - 1), np.minimum(i0 + 1, H - 1)
        ws = [((1 - fx) * (1 - fy), i0, j0), (fx * (1 - fy), i0, j1), ((1 - fx) * fy, i1, j0), (fx * fy, i1, j1)]
        ok = inside.copy()
        out = np.zeros((B,) + col.shape, np.float64)
        for wk, ik, jk in ws:
            ok &= ~((wk > 0) & (valid[ik, jk] == 0))
            out += np.where(wk > 0, wk, 0.0)[None] * img[:, ik, jk]
    out = np.where(ok[None], out, 0.0).astype(img.dtype)
    return out, ok


# ---------------------------------------------------------------------------------------------
# true-ortho visibility: march up the line of sight through the DSM
# ---------------------------------------------------------------------------------------------
@njit(cache=True, inline="always")
def _dsm_at(dsm, y, x):
    """Bilinear DSM height at array position (row y, col x), centres at integers; NaN outside/NaN."""
    H, W = dsm.shape
    if not (x >= 0.0 and y >= 0.0 and x <= W - 1 and y <= H - 1):
        return np.nan
    j0 = min(int(x), W - 2) if W > 1 else 0
    i0 = min(int(y), H - 2) if H > 1 else 0
    fx = x - j0
    fy = y - i0
    j1 = min(j0 + 1, W - 1)
    i1 = min(i0 + 1, H - 1)
    return (dsm[i0, j0] * (1.0 - fx) + dsm[i0, j1] * fx) * (1.0 - fy) + (
        dsm[i1, j0] * (1.0 - fx) + dsm[i1, j1] * fx
    ) * fy


@parallel_njit()
def occlusion_march(dsm, ray_j, ray_i, tol_m, step_cells, out):
    """Cells whose line of sight to the camera passes below the DSM (hidden: true-ortho occlusion).

    From each cell centre at its DSM height ``z0`` the ray climbs towards the
    camera, moving ``(ray_j, ray_i)`` grid cells per metre of height. It is
    sampled every ``step_cells`` cells of horizontal distance until it rises above
    the highest DSM height; the cell is hidden when at some sample the DSM
    (bilinear; NaN samples are skipped) is more than ``tol_m`` above the ray. A
    ray that leaves the array is assumed free (give the tile a margin, see
    :func:`geocd.ortho.occlusion_margin_cells`). Cells with a NaN height or ray
    are not tested (False).

    Parameters
    ----------
    dsm : float64 (H, W), metres
    ray_j, ray_i : float64 (H, W), grid columns / rows per metre of height up the ray
    tol_m : float
    step_cells : float, > 0
    out : bool (H, W), written
    """
    H, W = dsm.shape
    zmax = -np.inf
    for i in range(H):
        for j in range(W):
            if dsm[i, j] > zmax:
                zmax = dsm[i, j]
    for i in prange(H):
        for j in range(W):
            out[i, j] = False
            z0 = dsm[i, j]
            vj = ray_j[i, j]
            vi = ray_i[i, j]
            if not (np.isfinite(z0) and np.isfinite(vj) and np.isfinite(vi)):
                continue
            d = np.sqrt(vj * vj + vi * vi)  # cells per metre of height
            if d < 1e-12:
                continue
            tmax = (zmax - tol_m - z0) * d  # beyond this the ray clears every surface
            uj = vj / d
            ui = vi / d
            t = step_cells
            while t <= tmax:
                x = j + uj * t
                y = i + ui * t
                if x < 0.0 or y < 0.0 or x > W - 1 or y > H - 1:
                    break
                zs = _dsm_at(dsm, y, x)
                if zs > z0 + t / d + tol_m:  # False for NaN
                    out[i, j] = True
                    break
                t += step_cells


def occlusion_march_ref(
    dsm: np.ndarray, ray_j: np.ndarray, ray_i: np.ndarray, tol_m: float, step_cells: float
) -> np.ndarray:
    """numpy reference of :func:`occlusion_march` (all cells advance together, one step at a time)."""
    H, W = dsm.shape
    zmax = np.nanmax(dsm)
    ii, jj = np.mgrid[0:H, 0:W].astype(np.float64)
    d = np.hypot(ray_j, ray_i)
    test = np.isfinite(dsm) & np.isfinite(d) & (d >= 1e-12)
    dd = np.where(test, d, 1.0)
    uj, ui = np.where(test, ray_j, 0.0) / dd, np.where(test, ray_i, 0.0) / dd
    tmax = np.where(test, (zmax - tol_m - np.where(test, dsm, 0.0)) * dd, -1.0)
    out = np.zeros((H, W), bool)
    active = test.copy()
    n = 1
    while True:
        t = n * step_cells
        active &= t <= tmax
        if not active.any():
            break
        x = jj + uj * t
        y = ii + ui * t
        inside = (x >= 0) & (y >= 0) & (x <= W - 1) & (y <= H - 1)
        active &= inside
        xs, ys = np.where(active, x, 0.0), np.where(active, y, 0.0)
        j0 = np.minimum(xs.astype(np.int64), max(W - 2, 0))
        i0 = np.minimum(ys.astype(np.int64), max(H - 2, 0))
        fx, fy = xs - j0, ys - i0
        j1, i1 = np.minimum(j0 + 1, W - 1), np.minimum(i0 + 1, H - 1)
        zs = (dsm[i0, j0] * (1 - fx) + dsm[i0, j1] * fx) * (1 - fy) + (dsm[i1, j0] * (1 - fx) + dsm[i1, j1] * fx) * fy
        with np.errstate(invalid="ignore"):
            hit = active & (zs > np.where(test, dsm, 0.0) + t / dd + tol_m)
        out |= hit
        active &= ~hit
        n += 1
    return out
