"""A DEM prior for the occlusion density (a geocd extension; the paper starts from a constant α).

With few views (a handful of satellite passes and aerial frames, rather than the
paper's 25–175 images), the online update is ambiguous over homogeneous
surfaces: free space above a uniform roof or lawn explains the pixels as well as
the surface does, and early, greedy updates grow spurious floating density. The
manifest's prior DEM (terrain, no buildings) removes most of that ambiguity:

* cells within ``ground_band_m`` of the DEM are refined to the finest level and
  start with a ground occlusion probability ``ground_p`` per finest cell;
* cells more than ``max_object_m`` above it start nearly empty (``air_p``);
* everything else (where buildings and trees may be) keeps the uninformative
  ``p_init``.

Every cell stays learnable: the prior only sets where the update starts.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..geodesy import AOIGrid
from .scene import VolumeModel


@dataclass(frozen=True)
class DEMPrior:
    """Parameters of :func:`seed_from_dem` (see the module docstring)."""

    ground_band_m: float = 0.5
    ground_p: float = 0.3
    max_object_m: float = 25.0
    air_p: float = 1e-3


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
    ground = known & (np.abs(z - z_dem) <= 0.5 * size + prior.ground_band_m)
    air = known & (z - 0.5 * size > z_dem + prior.max_object_m)
    model.alpha[leaves[ground]] = -math.log1p(-prior.ground_p) / f
    model.alpha[leaves[air]] = -math.log1p(-prior.air_p) / f
    return {"ground_cells": int(ground.sum()), "air_cells": int(air.sum()), "leaves_split": int(split_total)}
