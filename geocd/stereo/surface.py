"""The matched surface after the validity tests: a median along the surface, and narrow holes filled (flagged).

Arrays in, arrays out (heights in metres on the AOI grid, NaN = no height).
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from typing import Any

import numpy as np
from scipy import ndimage

from ..errors import ConfigError
from . import _kernels as K


def surface_median(z_m: np.ndarray, size: int) -> np.ndarray:
    """Replace each finite height by the median of the finite heights in the ``size`` × ``size`` cells around it.

    Parameters
    ----------
    z_m : float (rows, cols), m; NaN where there is no (valid) height
    size : odd window side in cells (1 = unchanged)

    Returns
    -------
    float64 (rows, cols), NaN exactly where ``z_m`` is NaN.
    """
    if size < 1 or size % 2 == 0:
        raise ConfigError(f"the surface median needs an odd window of cells, got {size}")
    z = np.ascontiguousarray(z_m, np.float64)
    if size == 1:
        return z.copy()
    out = np.empty_like(z)
    K.valid_median(z, size // 2, out)
    return out


def narrow_holes(valid: np.ndarray, radius: int) -> np.ndarray:
    """Invalid cells of the holes that lie wholly within ``radius`` cells of valid cells.

    A hole is a 4-connected component of invalid cells that does not touch the grid's border
    (an open edge is not a hole); it is narrow when none of its cells is more than ``radius``
    cells (chessboard distance) from a valid cell — with ``radius`` the matching window's
    radius, every cell of such a hole lies inside the matching windows of valid cells.

    Parameters
    ----------
    valid : bool (rows, cols)
    radius : int ≥ 0, cells

    Returns
    -------
    bool (rows, cols): the cells to fill.
    """
    valid = np.asarray(valid, bool)
    holes = ~valid
    if radius < 1 or not holes.any() or not valid.any():
        return np.zeros(valid.shape, bool)
    lab, n = ndimage.label(holes)
    dist = ndimage.distance_transform_cdt(holes, metric="chessboard")
    far = np.asarray(ndimage.maximum(dist, lab, index=np.arange(1, n + 1)))
    ok = np.zeros(n + 1, bool)
    ok[1:] = far <= radius
    edge = np.unique(np.concatenate([lab[0], lab[-1], lab[:, 0], lab[:, -1]]))
    ok[edge] = False
    ok[0] = False
    return ok[lab]


def fill_narrow_holes(z_m: np.ndarray, valid: np.ndarray, radius: int) -> tuple[np.ndarray, np.ndarray]:
    """Heights for the narrow holes (:func:`narrow_holes`) by inverse-distance interpolation of the valid heights.

    The interpolation is GDAL's (``rasterio.fill.fillnodata``, no smoothing; CARS fills its DSM with it),
    searching ``2·radius + 1`` cells; holes it cannot reach stay empty.

    Returns
    -------
    z : float64 (rows, cols), ``z_m`` on valid cells, interpolated heights on filled cells, NaN elsewhere
    filled : bool (rows, cols)
    """
    from rasterio.fill import fillnodata

    valid = np.asarray(valid, bool) & np.isfinite(z_m)
    z = np.where(valid, z_m, np.nan).astype(np.float64)
    target = narrow_holes(valid, radius)
    if not target.any():
        return z, target
    # Cells the search does not reach keep their source value: a sentinel no interpolation of heights can give
    # tells them apart in one pass (only cells under ``mask`` feed the interpolation).
    sentinel = np.float32(np.finfo(np.float32).min)
    src = np.where(valid, z, sentinel).astype(np.float32)
    f = fillnodata(src, mask=valid.astype(np.uint8), max_search_distance=float(2 * radius + 1), smoothing_iterations=0)
    got = f != sentinel
    filled = target & got
    z[filled] = f[filled]
    return z, filled


def nanmedian_stack(stack: np.ndarray) -> np.ndarray:
    """Median over axis 0 ignoring NaN, NaN where a cell has no value: ``np.nanmedian(stack, axis=0)``, same values.

    numpy's ``nanmedian`` along a short axis goes through masked arrays (about 0.5 s per 400 k cells of a
    few layers) and warns once per all-NaN cell in a Python loop. Here each cell's values are sorted (NaN
    last) and the middle one, or the mean of the middle two, is taken as numpy takes it: ``(low + high) / 2``
    in the stack's dtype.

    Parameters
    ----------
    stack : float (n, rows, cols)

    Returns
    -------
    float (rows, cols), the dtype ``np.nanmedian`` gives
    """
    a = np.asarray(stack)
    if a.dtype.kind != "f" or a.ndim < 1 or a.shape[0] == 0:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            return np.nanmedian(a, axis=0)
    n = a.shape[0]
    s = np.sort(a.reshape(n, -1).T, axis=1)  # (cells, n): each cell's values ascending, NaN last
    count = n - np.isnan(s).sum(axis=1)
    high = count // 2
    low = np.where(count % 2 == 1, high, high - 1)
    cells = np.arange(s.shape[0])
    with np.errstate(invalid="ignore", over="ignore"):
        out = (s[cells, np.maximum(low, 0)] + s[cells, np.minimum(high, n - 1)]) / a.dtype.type(2)
    out[count == 0] = np.nan
    return out.reshape(a.shape[1:])


def epoch_surface(pair_dems: Sequence[Any]) -> np.ndarray:
    """One surface per epoch from its pair-DEMs: the median of their valid heights, NaN where none has one.

    Parameters
    ----------
    pair_dems : objects with ``z_m`` (float (rows, cols), m) and ``valid`` (bool (rows, cols)) on one grid

    Returns
    -------
    float32 (rows, cols), m
    """
    return nanmedian_stack(np.stack([np.where(p.valid, p.z_m, np.nan) for p in pair_dems])).astype(np.float32)
