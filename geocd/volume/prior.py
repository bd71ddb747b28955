"""A DEM prior for the occlusion density (a geocd extension; the paper starts from a constant α).

With few views (a handful of satellite passes and aerial frames, rather than the
paper's 25–175 images), the online update is ambiguous over homogeneous
surfaces: free space above a uniform roof or lawn explains the pixels as well as
the surface does, and early, greedy updates grow spurious floating density. The
manifest's prior DEM (terrain, no buildings) removes most of that ambiguity:

* cells within ``ground_band_m`` of the DEM are refined to the finest level and
  their occlusion probabilities encode "the ground surface lies somewhere in
  ``[z_dem - b, z_dem + b]``, uniformly" (``b = ground_band_m``): a viewer from
  above is stopped by the surface at height ``z`` with the surface-height CDF
  ``F``, so the visibility from above is ``V(z) = F(z)`` and a cell spanning
  ``[z0, z1]`` gets ``P = 1 - F(z0) / F(z1)`` (capped at ``ground_p_max`` so it
  stays learnable). The median visible surface — where ``V`` falls to 0.5, the
  model's height map — is then the DEM itself (exact when the DEM height is on a
  cell face, within a few centimetres otherwise, as α is constant per cell);
* cells more than ``max_object_m`` above it start nearly empty (``air_p``);
* everything else (where buildings and trees may be, and below the band) keeps
  the uninformative ``p_init``.

Every cell stays learnable: the prior only sets where the update starts.

A symmetric band of equal probabilities (each cell within ``b`` of the DEM at
the same ``P``) puts the median surface above the DEM, by about
``b + cell/2`` for ``P = 0.3`` (+0.53 m on the towns with 0.5 m cells): the
first cells of the band seen from above already stop half the rays. Views a
few degrees off nadir cannot correct that (0.5 m of height moves a point by
0.1–0.2 px in them), so the model kept the offset after training.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import ConfigError
from ..geodesy import AOIGrid
from .scene import VolumeModel


@dataclass(frozen=True)
class DEMPrior:
    """Parameters of :func:`seed_from_dem` (see the module docstring)."""

    ground_band_m: float = 0.5
    ground_band_top_m: float = 0.0
    ground_p_max: float = 0.9
    max_object_m: float = 25.0
    air_p: float = 1e-3

    def __post_init__(self) -> None:
        if not (self.ground_band_m > 0):
            raise ConfigError(f"ground_band_m must be positive, got {self.ground_band_m}")
        if not (0.0 < self.ground_p_max < 1.0):
            raise ConfigError(f"ground_p_max must be in (0, 1), got {self.ground_p_max}")
        if not (0.0 < self.air_p < 1.0):
            raise ConfigError(f"air_p must be in (0, 1), got {self.air_p}")


def band_occlusion(
    z_lo: np.ndarray, z_hi: np.ndarray, band_lo: np.ndarray, band_hi: np.ndarray, p_max: float
) -> np.ndarray:
    """Occlusion probability of cells ``[z_lo, z_hi]`` under a surface uniform in ``[band_lo, band_hi]``.

    ``P = 1 - F(z_lo) / F(z_hi)`` with ``F`` the CDF of the surface height (the visibility
    from above at height ``z`` is ``F(z)``), capped at ``p_max``; 0 where the cell is above
    the band, NaN where it is entirely below it. All heights in one frame (m); arrays broadcast.
    """
    width = np.maximum(np.asarray(band_hi, dtype=np.float64) - band_lo, 1e-9)
    f_lo = np.clip((z_lo - band_lo) / width, 0.0, 1.0)
    f_hi = np.clip((z_hi - band_lo) / width, 0.0, 1.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        p = np.where(f_hi > 0, 1.0 - f_lo / f_hi, np.nan)
    return np.minimum(p, p_max)


def _leaf_heights(model: VolumeModel, dem_m: np.ndarray, grid: AOIGrid):
    from .baseline import sample_grid
    from .relight import node_boxes

    centers, sizes = node_boxes(model)
    leaves = np.nonzero(model.child < 0)[0]
    fr = model.geometry.frame
    c = centers[leaves]
    lon, lat, _ = fr.from_enu(c[:, 0], c[:, 1], np.zeros(len(leaves)))
    h_dem = sample_grid(dem_m, grid, lon, lat)
    z_dem = h_dem - fr.h0  # ENU up of the DEM surface (curvature < 1 cm over an AOI)
    return leaves, c[:, 2], sizes[leaves], z_dem


def seed_from_dem(
    model: VolumeModel,
    dem_m: np.ndarray,
    grid: AOIGrid,
    prior: DEMPrior | None = None,
    *,
    roof_m: np.ndarray | None = None,
) -> dict:
    """Refine the ground band and set the initial α from the DEM (in place; call on a fresh model).

    Parameters
    ----------
    dem_m : float (rows, cols) ellipsoidal heights on ``grid`` (NaN = unknown: cells there keep ``p_init``)
    roof_m : float (rows, cols) on ``grid``, optional
        Ellipsoidal roof heights of known buildings (NaN elsewhere; see
        :func:`footprint_roof_heights`). Where finite, the first surface seen from
        above is the roof, not the bare ground: the band ends at the roof and the
        cells below it (the building's interior, the hidden ground) keep ``p_init``.

    Returns
    -------
    dict with the numbers of ground, air and refined cells.
    """
    from .refine import split_leaves

    prior = prior or DEMPrior()
    if roof_m is not None:
        roof = np.asarray(roof_m, dtype=np.float64)
        dem_m = np.where(np.isfinite(roof), roof, dem_m)
    g = model.geometry
    f = g.finest_cell_m
    split_total = 0
    for _ in range(g.max_depth + 1):
        leaves, z, size, z_dem = _leaf_heights(model, dem_m, grid)
        near = np.isfinite(z_dem) & (np.abs(z - z_dem) <= 0.5 * size + prior.ground_band_m)
        n = split_leaves(model, leaves[near])
        split_total += n
        if n == 0:
            break
    leaves, z, size, z_dem = _leaf_heights(model, dem_m, grid)
    known = np.isfinite(z_dem)
    p_band = band_occlusion(
        z - 0.5 * size, z + 0.5 * size, z_dem - prior.ground_band_m, z_dem + prior.ground_band_top_m, prior.ground_p_max
    )
    ground = known & np.isfinite(p_band) & (p_band > model.params.p_init)
    air = known & (z - 0.5 * size > z_dem + prior.max_object_m)
    # α is a density: the cell's probability over its own size (band cells are finest cells after the split)
    model.alpha[leaves[ground]] = (-np.log1p(-p_band[ground]) / size[ground]).astype(model.alpha.dtype)
    model.alpha[leaves[air]] = -math.log1p(-prior.air_p) / f
    return {"ground_cells": int(ground.sum()), "air_cells": int(air.sum()), "leaves_split": int(split_total)}


def footprint_roof_heights(
    views: list,
    labels: np.ndarray,
    dem_m: np.ndarray,
    grid: AOIGrid,
    *,
    max_height_m: float = 25.0,
    step_m: float = 0.5,
    min_cells: int = 8,
) -> dict:
    """Roof height of each footprint from the training views, by a plane sweep of the whole footprint.

    Over a uniform roof the per-cell update cannot tell the roof from the ground below it
    (every cell on a pixel's ray explains the roof's colour equally well); only the roof's
    outline constrains its height. Here the outline is the footprint's: the footprint's cells,
    lifted to ``DEM + h``, are projected into every view, and ``h`` is chosen where the views
    agree best: the mean, over pairs of views, of the correlation (zero-mean, unit-variance
    over the footprint) of their intensities at those cells. At a wrong height each view
    shifts the outline by a different parallax and brings in ground, walls or shadow on a
    different side; at the true height all see the same roof. ``h = 0`` is a candidate: a
    footprint whose building is not there keeps the ground.

    Parameters
    ----------
    views : objects with ``intensity`` (rows, cols) and ``camera`` (the training views)
    labels : int (rows, cols) on ``grid``, 0 outside footprints, k > 0 inside footprint k
    dem_m : float (rows, cols) ellipsoidal ground heights on ``grid``
    max_height_m, step_m : the heights tried above the DEM, ``0, step, ..., max_height_m``

    Returns
    -------
    dict: ``height_m`` (n_labels + 1,) the chosen height above the DEM per label (NaN: fewer than
    two views see the whole footprint, or fewer than ``min_cells`` cells; index 0 unused), ``score`` (n_labels + 1,) the correlation there,
    ``curve`` (n_heights, n_labels + 1) and ``heights_m``.
    """
    from scipy.ndimage import map_coordinates

    from ..geodesy import to_lonlat

    lab = np.asarray(labels)
    rr, cc = np.nonzero((lab > 0) & np.isfinite(dem_m))
    k = lab[rr, cc].astype(np.int64)
    n_lab = int(lab.max()) + 1
    x, y = grid.xy()
    lon, lat = to_lonlat(x[rr, cc], y[rr, cc], grid.crs)
    heights = np.arange(0.0, max_height_m + 0.5 * step_m, step_m)
    curve = np.full((heights.size, n_lab), np.nan)
    nv = len(views)
    if nv < 2 or k.size == 0:
        return {
            "height_m": np.full(n_lab, np.nan),
            "score": np.full(n_lab, np.nan),
            "curve": curve,
            "heights_m": heights,
        }
    imgs = [
        (np.where(np.isfinite(v.intensity), v.intensity, 0.0), np.isfinite(v.intensity).astype(float)) for v in views
    ]
    total = np.bincount(k, minlength=n_lab).astype(float)

    def sample(h: float) -> np.ndarray:
        zs = np.full((nv, k.size), np.nan)
        for iv, v in enumerate(views):
            col, row = v.camera.project(lon, lat, dem_m[rr, cc] + h)
            val = map_coordinates(imgs[iv][0], [row - 0.5, col - 0.5], order=1, mode="constant", cval=0.0)
            ok = map_coordinates(imgs[iv][1], [row - 0.5, col - 0.5], order=1, mode="constant", cval=0.0) > 0.99
            zs[iv] = np.where(ok & np.isfinite(col), val, np.nan)
        return zs

    # a view takes part for a footprint when it sees the whole footprint at the lowest and highest height
    use = np.ones((nv, n_lab), dtype=bool)
    for h in (heights[0], heights[-1]):
        seen = np.isfinite(sample(h))
        for iv in range(nv):
            use[iv] &= np.bincount(k, seen[iv], minlength=n_lab) >= total
    n_views = use.sum(axis=0).astype(float)
    for ih, h in enumerate(heights):
        z = sample(h)
        with np.errstate(invalid="ignore", divide="ignore"):
            for iv in range(nv):  # standardise each view over each footprint; views not taking part give 0
                ok = np.isfinite(z[iv])
                n = np.bincount(k[ok], minlength=n_lab).astype(float)
                m1 = np.bincount(k[ok], z[iv][ok], minlength=n_lab) / n
                m2 = np.bincount(k[ok], z[iv][ok] ** 2, minlength=n_lab) / n
                sd = np.sqrt(np.maximum(m2 - m1**2, 0.0))
                zi = (z[iv] - m1[k]) / np.maximum(sd[k], 1e-6)
                z[iv] = np.where(ok & use[iv][k], zi, 0.0)
            s = z.sum(axis=0)
            q = (z**2).sum(axis=0)
            pair = (np.bincount(k, s**2, minlength=n_lab) - np.bincount(k, q, minlength=n_lab)) / (
                n_views * (n_views - 1) * total
            )
        pair[(total < min_cells) | (n_views < 2)] = np.nan
        curve[ih] = pair
    best = np.full(n_lab, np.nan)
    score = np.full(n_lab, np.nan)
    has = np.any(np.isfinite(curve), axis=0)
    idx = np.nanargmax(np.where(np.isfinite(curve[:, has]), curve[:, has], -np.inf), axis=0)
    best[has] = heights[idx]
    score[has] = curve[idx, np.nonzero(has)[0]]
    best[0] = score[0] = np.nan
    return {"height_m": best, "score": score, "curve": curve, "heights_m": heights}


def roof_surface(
    views: list,
    footprints_mask: np.ndarray,
    dem_m: np.ndarray,
    grid: AOIGrid,
    prior: DEMPrior | None = None,
    *,
    step_m: float = 0.5,
) -> tuple[np.ndarray, dict]:
    """Ellipsoidal roof heights on ``grid`` for :func:`seed_from_dem` (NaN outside footprints or where no
    roof was found), from a footprint mask and the training views (:func:`footprint_roof_heights`; each
    connected part of the mask is one footprint; ``step_m``: the model's finest cell)."""
    from scipy.ndimage import label

    prior = prior or DEMPrior()
    lab, n = label(np.asarray(footprints_mask, dtype=bool))
    r = footprint_roof_heights(views, lab, dem_m, grid, max_height_m=prior.max_object_m, step_m=step_m)
    h = r["height_m"]
    h = np.where(h > 0, h, np.nan)  # h = 0: the views agree best on the ground
    roof = np.where(lab > 0, dem_m + h[lab], np.nan)
    return roof, {
        "footprints": int(n),
        "roofs": int(np.isfinite(h[1:]).sum()),
        "height_m": h[1:],
        "score": r["score"][1:],
    }
