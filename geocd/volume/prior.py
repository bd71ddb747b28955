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


def band_occlusion(z_lo: np.ndarray, z_hi: np.ndarray, band_lo: np.ndarray, band_hi: np.ndarray,
                   p_max: float) -> np.ndarray:
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


def seed_from_dem(model: VolumeModel, dem_m: np.ndarray, grid: AOIGrid, prior: DEMPrior | None = None) -> dict:
    """Refine the ground band and set the initial α from the DEM (in place; call on a fresh model).

    Parameters
    ----------
    dem_m : float (rows, cols) ellipsoidal heights on ``grid`` (NaN = unknown: cells there keep ``p_init``)

    Returns
    -------
    dict with the numbers of ground, air and refined cells.
    """
    from .refine import split_leaves

    prior = prior or DEMPrior()
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
    p_band = band_occlusion(z - 0.5 * size, z + 0.5 * size, z_dem - prior.ground_band_m,
                            z_dem + prior.ground_band_top_m, prior.ground_p_max)
    ground = known & np.isfinite(p_band) & (p_band > model.params.p_init)
    air = known & (z - 0.5 * size > z_dem + prior.max_object_m)
    # α is a density: the cell's probability over its own size (band cells are finest cells after the split)
    model.alpha[leaves[ground]] = (-np.log1p(-p_band[ground]) / size[ground]).astype(model.alpha.dtype)
    model.alpha[leaves[air]] = -math.log1p(-prior.air_p) / f
    return {"ground_cells": int(ground.sum()), "air_cells": int(air.sum()), "leaves_split": int(split_total)}
