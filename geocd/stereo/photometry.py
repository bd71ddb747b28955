"""Photometry for matching: gray levels, local 8-bit normalization, noise, anti-aliasing.

Inputs may be 8-bit, 11/12-bit in uint16, float, single band or RGB/multi-band.
Every image is reduced to one float32 gray band (mean over bands, NaN where
invalid) and then *locally normalized* as in the SRI paper's Appendix B: over
small regions the dynamic range is much smaller than over the whole image, so
each region's pixel-value range is mapped onto 0–255. Here the regions are
blocks of ``block_px`` pixels; their low/high percentiles are interpolated
bilinearly between block centres (no seams) and the stretch is limited so flat
regions do not turn noise into texture. Values stay floating point (no
quantization); the matching cost (NCC) is invariant to gain and offset anyway —
the normalization gives the noise level σ_n and the MDL/SSD scores a common
8-bit scale across sensors.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from ..errors import EmptyDataError


def to_gray(data: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
    """One float32 gray band from ``(rows, cols)`` or ``(bands, rows, cols)``; NaN where invalid.

    Parameters
    ----------
    data : array, any numeric dtype
    valid : bool (rows, cols), optional; non-finite samples are always invalid
    """
    a = np.asarray(data)
    if a.ndim == 3:
        g = a.astype(np.float32).mean(axis=0)
    elif a.ndim == 2:
        g = a.astype(np.float32, copy=True)
    else:
        raise EmptyDataError(f"an image must be 2-D (rows, cols) or 3-D (bands, rows, cols), got shape {a.shape}")
    if valid is not None:
        g[~np.asarray(valid, bool)] = np.nan
    g[~np.isfinite(g)] = np.nan
    return g


def local_normalize(
    gray: np.ndarray, block_px: int = 256, percentiles: tuple[float, float] = (0.5, 99.5), max_stretch: float = 4.0
) -> np.ndarray:
    """Map each region's pixel-value range to 0–255 (SRI Appendix B), smoothly.

    Parameters
    ----------
    gray : float32 (rows, cols), NaN = invalid
    block_px : int
        Region size in pixels (the paper uses 512×512 regions of IKONOS images).
    percentiles : (low, high)
        Robust range of a region.
    max_stretch : float
        A region's range is at least ``1/max_stretch`` of the whole image's range,
        so textureless regions are not stretched into noise.

    Returns
    -------
    float32 (rows, cols) in [0, 255], NaN where invalid.

    Raises
    ------
    EmptyDataError
        When the image has no valid pixel.
    """
    ok = np.isfinite(gray)
    if not ok.any():
        raise EmptyDataError(
            "the image has no valid pixel over the area to match; check its nodata value and that it covers the AOI"
        )
    g_lo, g_hi = np.percentile(gray[ok], percentiles)
    g_rng = max(float(g_hi - g_lo), 1e-6)
    H, W = gray.shape
    nb_r = max(1, int(round(H / block_px)))
    nb_c = max(1, int(round(W / block_px)))
    lo = np.full((nb_r, nb_c), np.nan)
    hi = np.full((nb_r, nb_c), np.nan)
    re = np.linspace(0, H, nb_r + 1).astype(int)
    ce = np.linspace(0, W, nb_c + 1).astype(int)
    for bi in range(nb_r):
        for bj in range(nb_c):
            blk = gray[re[bi] : re[bi + 1], ce[bj] : ce[bj + 1]]
            v = blk[np.isfinite(blk)]
            if v.size >= 64:
                lo[bi, bj], hi[bi, bj] = np.percentile(v, percentiles)
    # blocks without data take the whole image's range
    lo = np.where(np.isfinite(lo), lo, g_lo)
    hi = np.where(np.isfinite(hi), hi, g_hi)
    mid = 0.5 * (lo + hi)
    half = np.maximum(0.5 * (hi - lo), 0.5 * g_rng / max_stretch)
    lo, hi = mid - half, mid + half
    if nb_r == 1 and nb_c == 1:
        lo_f = np.full(gray.shape, lo[0, 0])
        hi_f = np.full(gray.shape, hi[0, 0])
    else:
        # block centres at (re[i]+re[i+1])/2; interpolate in block-index space
        rr = (np.arange(H) + 0.5) / (H / nb_r) - 0.5
        cc = (np.arange(W) + 0.5) / (W / nb_c) - 0.5
        R, C = np.meshgrid(np.clip(rr, 0, nb_r - 1), np.clip(cc, 0, nb_c - 1), indexing="ij")
        lo_f = ndimage.map_coordinates(lo, [R, C], order=1, mode="nearest")
        hi_f = ndimage.map_coordinates(hi, [R, C], order=1, mode="nearest")
    out = (gray - lo_f) * (255.0 / (hi_f - lo_f))
    out = np.clip(out, 0.0, 255.0).astype(np.float32)
    out[~ok] = np.nan
    return out


def estimate_noise_sigma(img: np.ndarray, block: int = 32, quantile: float = 25.0) -> float:
    """Robust noise standard deviation of an image (Immerkær's mask, per block, flattest blocks).

    The mask ``[[1,−2,1],[−2,4,−2],[1,−2,1]]`` cancels planar image structure; in each
    ``block``×``block`` block the median absolute response divided by 0.6745·6 estimates
    σ, inflated by whatever texture the block has. The ``quantile``-th percentile over
    blocks keeps the flattest ones (pure noise reads about 4 % low). Falls back on the
    whole image's median when there are fewer than 4 full blocks.
    """
    a = np.asarray(img, np.float64)
    k = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], float)
    ok = np.isfinite(a)
    resp = np.abs(ndimage.convolve(np.where(ok, a, 0.0), k, mode="nearest"))
    ok3 = ndimage.minimum_filter(ok.astype(np.uint8), size=3, mode="constant", cval=0) > 0
    H, W = a.shape
    est = []
    for i in range(0, H - block + 1, block):
        for j in range(0, W - block + 1, block):
            m = ok3[i : i + block, j : j + block]
            if m.mean() > 0.9:
                est.append(np.median(resp[i : i + block, j : j + block][m]))
    if len(est) >= 4:
        return float(np.percentile(est, quantile) / 0.6745 / 6.0)
    v = resp[ok3]
    if v.size < 16:
        return float("nan")
    return float(np.median(v) / 0.6745 / 6.0)


def box_blur_nan(img: np.ndarray, size: int) -> np.ndarray:
    """Normalized box blur that ignores NaN (anti-aliasing before sampling a coarser grid).

    Even sizes are rounded up to the next odd size: an even box is not centred and
    would shift the image by half a pixel. A pixel stays NaN when it was NaN (the
    valid support does not grow).
    """
    if size <= 1:
        return img
    size = int(size) | 1
    ok = np.isfinite(img)
    num = ndimage.uniform_filter(np.where(ok, img, 0.0).astype(np.float64), size=size, mode="nearest")
    den = ndimage.uniform_filter(ok.astype(np.float64), size=size, mode="nearest")
    with np.errstate(invalid="ignore", divide="ignore"):
        out = (num / den).astype(np.float32)
    out[~ok] = np.nan
    return out
