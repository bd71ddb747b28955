"""Stable terrain: where the two DEMs should agree.

Three sources, combined by :func:`stable_terrain`:

1. a **user mask** (raster or polygons; by default non-zero / inside = stable,
   ``mask_is="unstable"`` flips it, e.g. for glacier or landslide outlines);
2. **footprints** (buildings) and other known-unstable polygons: excluded, with a
   buffer of ``StableParams.footprint_buffer_cells``;
3. **automatic** (when no user mask is given): every valid cell with slope ≤
   ``max_slope_deg``, minus *coherent* change. Candidate change cells are those with
   |dh − median| > ``nmad_factor`` × NMAD; candidates that form 8-connected groups of at
   least ``min_region_cells`` cells, plus a ``dilate_cells`` buffer, are removed
   (optionally grown first into the connected cells beyond ``grow_factor`` × NMAD:
   hysteresis that also removes the sub-threshold tails of smooth change; off by
   default because with spatially correlated errors it percolates through the noise
   and truncates the error distribution, which makes σ too small); the median and NMAD are re-estimated on the remaining cells and the
   selection repeats until it no longer changes (``max_iterations``). When the
   selected cells still have an NMAD above ``max_nmad_m`` (default 10 m: more than
   DEM errors plausibly reach on unchanged terrain) there is no stable population
   (most of the area changed): the mask comes back empty and the info says so.

Isolated large residuals are *kept*: they are part of the error distribution the
significance test needs (dropping every cell beyond 3 NMAD would truncate the tails
and make the test over-confident). The automatic mask still depends on dh, so it is
recomputed after co-registration.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..errors import ConfigError, EmptyDataError

_EIGHT = np.ones((3, 3), dtype=bool)


def nmad(values: np.ndarray) -> float:
    """Normalized median absolute deviation (1.4826 × median |x − median x|) of finite values."""
    v = np.asarray(values, np.float64)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return float("nan")
    return float(1.4826 * np.median(np.abs(v - np.median(v))))


@dataclass(frozen=True)
class StableParams:
    """Parameters of the automatic stable-terrain selection."""

    max_slope_deg: float = 60.0
    nmad_factor: float = 3.0
    grow_factor: float | None = None
    min_threshold_m: float = 0.0
    min_region_cells: int = 5
    dilate_cells: int = 1
    max_iterations: int = 8
    footprint_buffer_cells: int = 1
    max_nmad_m: float | None = 10.0

    def __post_init__(self) -> None:
        if not (0 < self.max_slope_deg <= 90):
            raise ConfigError(f"max_slope_deg must be in (0, 90], got {self.max_slope_deg}")
        if self.nmad_factor <= 0:
            raise ConfigError(f"nmad_factor must be positive, got {self.nmad_factor}")
        if self.min_region_cells < 1 or self.dilate_cells < 0 or self.max_iterations < 1:
            raise ConfigError("min_region_cells ≥ 1, dilate_cells ≥ 0 and max_iterations ≥ 1 are required")


@dataclass(frozen=True)
class StableInfo:
    """How a stable mask was obtained (for reports)."""

    source: str
    n_cells: int
    iterations: int = 0
    median_m: float = float("nan")
    nmad_m: float = float("nan")
    excluded_change_cells: int = 0
    notes: tuple[str, ...] = field(default_factory=tuple)

    def to_dict(self) -> dict[str, Any]:
        return {
            "source": self.source,
            "n_cells": self.n_cells,
            "iterations": self.iterations,
            "median_m": self.median_m,
            "nmad_m": self.nmad_m,
            "excluded_change_cells": self.excluded_change_cells,
            "notes": list(self.notes),
        }


def coherent_change(
    dh_m: np.ndarray,
    valid: np.ndarray,
    center_m: float,
    threshold_m: float,
    min_region_cells: int,
    dilate_cells: int,
    grow_threshold_m: float | None = None,
) -> np.ndarray:
    """Cells of coherent change around ``center_m``.

    Groups (8-connected) of at least ``min_region_cells`` cells with |dh − center| >
    ``threshold_m`` are the seeds; they grow (hysteresis) into connected cells with
    |dh − center| > ``grow_threshold_m`` (the sub-threshold tails of smooth change), and
    are dilated by ``dilate_cells``.
    """
    from scipy import ndimage

    a = np.abs(np.nan_to_num(dh_m - center_m, nan=0.0))
    cand = valid & (a > threshold_m)
    if not cand.any():
        return cand
    lab, n = ndimage.label(cand, structure=_EIGHT)
    sizes = np.bincount(lab.ravel(), minlength=n + 1)
    big = sizes >= min_region_cells
    big[0] = False
    out = big[lab]
    if grow_threshold_m is not None and grow_threshold_m < threshold_m and out.any():
        weak = valid & (a > grow_threshold_m)
        lab2, _ = ndimage.label(weak | out, structure=_EIGHT)
        keep = np.unique(lab2[out])
        keep = keep[keep > 0]
        out = np.isin(lab2, keep) & (weak | out)
    if dilate_cells > 0 and out.any():
        out = ndimage.binary_dilation(out, structure=_EIGHT, iterations=dilate_cells)
    return out


def auto_stable_mask(
    dh_m: np.ndarray,
    valid: np.ndarray | None = None,
    slope_rad: np.ndarray | None = None,
    exclude: np.ndarray | None = None,
    params: StableParams = StableParams(),
) -> tuple[np.ndarray, StableInfo]:
    """Automatic stable terrain (see module docstring).

    Parameters
    ----------
    dh_m : float (rows, cols), B − A (NaN = not observed in both)
    valid : bool (rows, cols), optional; default finite dh
    slope_rad : float (rows, cols), optional; cells steeper than ``max_slope_deg`` are excluded
    exclude : bool (rows, cols), optional known-unstable cells (footprints, user outlines)

    Returns
    -------
    mask : bool (rows, cols)
    info : StableInfo (an empty mask is returned, not raised: the caller decides)
    """
    dh = np.asarray(dh_m, np.float64)
    ok = np.isfinite(dh) if valid is None else (np.asarray(valid, bool) & np.isfinite(dh))
    base = ok.copy()
    if slope_rad is not None:
        s = np.asarray(slope_rad)
        base &= np.isfinite(s) & (s <= np.radians(params.max_slope_deg))
    if exclude is not None:
        base &= ~np.asarray(exclude, bool)
    data = _GridStable(dh, ok, base, params)
    state, info = select_stable(data, params)
    if state == REJECTED:
        return np.zeros_like(base), info
    return data.mask, info


#: the state of a rejected selection (no stable population)
REJECTED = "rejected"


class _GridStable:
    """:func:`select_stable`'s access to whole grids."""

    def __init__(self, dh: np.ndarray, ok: np.ndarray, base: np.ndarray, params: StableParams):
        self.dh, self.ok, self.base, self.params = dh, ok, base, params
        self.mask = base.copy()
        self.n_base = int(base.sum())

    def initial(self) -> tuple[np.ndarray, int]:
        return self.dh[self.mask], int(self.mask.sum())

    def step(self, state: tuple[float, float, float | None]) -> tuple[np.ndarray, int, int, int]:
        med, thr, grow = state
        p = self.params
        change = coherent_change(self.dh, self.ok, med, thr, p.min_region_cells, p.dilate_cells, grow)
        new = self.base & ~change
        excluded = int((self.base & change).sum())
        toggled = int(np.count_nonzero(new != self.mask))
        self.mask = new
        return self.dh[new], int(new.sum()), excluded, toggled


def stable_state_mask(
    dh_m: np.ndarray, ok: np.ndarray, base: np.ndarray, state: Any, params: StableParams = StableParams()
) -> np.ndarray:
    """The stable mask that :func:`select_stable`'s ``state`` stands for, on any window.

    ``None`` = every base cell; :data:`REJECTED` = none; ``(median, threshold, grow threshold)``
    = base cells outside the coherent change around that median. On a tile whose read
    window has :func:`stable_overlap` cells of context, its core equals the whole grid's.
    """
    if state is None:
        return np.asarray(base, bool).copy()
    if state == REJECTED:
        return np.zeros(np.shape(base), bool)
    med, thr, grow = state
    change = coherent_change(
        np.asarray(dh_m, np.float64), ok, med, thr, params.min_region_cells, params.dilate_cells, grow
    )
    return np.asarray(base, bool) & ~change


def stable_overlap(params: StableParams = StableParams()) -> int:
    """Cells of context a tile needs for :func:`stable_state_mask` to equal the whole grid's on its core.

    A cell is in a coherent group of at least k cells exactly when its group restricted to
    the (2k − 1)² window around it has k cells; the dilation adds its own radius. The
    hysteresis growth (``grow_factor``) is not local and cannot be tiled.
    """
    if params.grow_factor is not None:
        raise ConfigError(
            "the automatic stable terrain with grow_factor (hysteresis) cannot be computed tile by "
            "tile; leave grow_factor unset for tiled runs"
        )
    return int(params.min_region_cells - 1 + params.dilate_cells)


def select_stable(data, params: StableParams = StableParams()) -> tuple[Any, StableInfo]:
    """The iteration of the automatic stable terrain on any data access (see module docstring).

    Parameters
    ----------
    data : an object with ``n_base`` (candidate cells), ``initial() → (dh values over the
        candidates, their number)`` and ``step(state) → (dh values over the new mask, its
        number of cells, excluded change cells, cells toggled since the previous mask)``,
        where ``state = (median, threshold, grow threshold or None)`` defines the new mask
        (:func:`stable_state_mask`). The values may be a subsample; counts are exact.

    Returns
    -------
    state : None (all candidates), ``(median, threshold, grow)`` or :data:`REJECTED`
    info : StableInfo
    """
    vals, n_cur = data.initial()
    state: Any = None
    notes: list[str] = []
    med = nm = float("nan")
    excluded = 0
    it = 0
    for it in range(1, params.max_iterations + 1):
        if n_cur < 3:
            break
        med = float(np.median(vals))
        nm = nmad(vals)
        thr = max(params.nmad_factor * nm, params.min_threshold_m)
        if not np.isfinite(thr) or thr <= 0:
            break
        state = (med, thr, params.grow_factor * nm if params.grow_factor else None)
        vals, n_cur, excluded, toggled = data.step(state)
        if toggled <= 0.001 * max(int(data.n_base), 1):
            break
    else:
        notes.append(f"automatic stable terrain did not settle in {params.max_iterations} iterations")
    if n_cur >= 3:
        med = float(np.median(vals))
        nm = nmad(vals)
    if params.max_nmad_m is not None and np.isfinite(nm) and nm > params.max_nmad_m:
        notes.append(
            f"no stable terrain found: the least-changed population of cells still has an NMAD of {nm:.1f} m "
            f"(> {params.max_nmad_m:g} m, the most DEM errors can plausibly reach on unchanged terrain), "
            "so most of the common area changed; give a stable-terrain mask"
        )
        return REJECTED, StableInfo("automatic (rejected)", 0, it, med, nm, excluded, tuple(notes))
    return state, StableInfo("automatic", int(n_cur), it, med, nm, excluded, tuple(notes))


def mask_from_user(mask: Any, grid, *, mask_is: str = "stable") -> np.ndarray:
    """A user's stable/unstable mask on ``grid`` → bool "stable" array.

    Parameters
    ----------
    mask : bool/number array on the grid, a GeoDataFrame of polygons, or a path to a
        raster (non-zero = inside) or vector file (inside polygons)
    mask_is : "stable" (inside = stable) or "unstable" (inside = unstable, e.g. glaciers)
    """
    if mask_is not in ("stable", "unstable"):
        raise ConfigError(f"mask_is must be 'stable' or 'unstable', got {mask_is!r}")
    inside = _inside(mask, grid)
    return inside if mask_is == "stable" else ~inside


def _inside(mask: Any, grid) -> np.ndarray:
    import os
    from pathlib import Path

    if isinstance(mask, np.ndarray):
        if mask.shape != grid.shape:
            raise ConfigError(f"mask shape {mask.shape} does not match the grid {grid.shape}; resample it first")
        m = np.asarray(mask)
        return (m != 0) & (np.isfinite(m) if m.dtype.kind == "f" else True)
    if hasattr(mask, "geometry"):
        from ..io.vector import polygons_to_mask

        return polygons_to_mask(mask, grid).astype(bool)
    if isinstance(mask, (str, os.PathLike)):
        p = Path(mask)
        from ..errors import InputFileNotFoundError

        if not p.exists():
            raise InputFileNotFoundError(f"mask file {p} does not exist; check the path")
        if p.suffix.lower() in (".gpkg", ".geojson", ".json", ".shp", ".fgb", ".kml", ".gml"):
            from ..io.vector import polygons_to_mask, read_footprints

            return polygons_to_mask(read_footprints(p, crs=grid.crs), grid).astype(bool)
        from ..io.raster import _open, reproject_band

        with _open(p) as ds:
            if ds.crs is None:
                from ..errors import CRSError

                raise CRSError(f"mask raster {p} has no CRS; assign one before using it as a mask")
            m = reproject_band(ds, 1, grid, "nearest")
        return np.isfinite(m) & (m != 0)
    raise ConfigError(f"cannot use {type(mask).__name__} as a mask; give an array, polygons or a file path")


def buffered(mask: np.ndarray, cells: int) -> np.ndarray:
    """Dilate a bool mask by ``cells`` (8-connectivity)."""
    from scipy import ndimage

    m = np.asarray(mask, bool)
    if cells <= 0 or not m.any():
        return m
    return ndimage.binary_dilation(m, structure=_EIGHT, iterations=cells)


def stable_terrain(
    dh_m: np.ndarray,
    valid: np.ndarray,
    grid=None,
    *,
    user_mask: Any = None,
    mask_is: str = "stable",
    footprints: Any = None,
    slope_rad: np.ndarray | None = None,
    params: StableParams = StableParams(),
) -> tuple[np.ndarray, StableInfo]:
    """Stable terrain from a user mask, footprints and/or the automatic selection.

    With a user mask, the stable cells are the mask's stable cells that are valid and
    outside footprints (no automatic filtering: the user decides). Without one, the
    automatic selection runs on the valid cells outside footprints.

    Raises
    ------
    EmptyDataError
        when a user mask leaves no valid cell (e.g. it covers only nodata).
    """
    valid = np.asarray(valid, bool) & np.isfinite(dh_m)
    exclude = None
    notes: list[str] = []
    if footprints is not None:
        if grid is None:
            raise ConfigError("footprints need the grid to be rasterized")
        fp = _inside(footprints, grid)
        exclude = buffered(fp, params.footprint_buffer_cells)
        notes.append(f"footprints excluded ({int(fp.sum())} cells + {params.footprint_buffer_cells}-cell buffer)")
    if user_mask is not None:
        if grid is None and not isinstance(user_mask, np.ndarray):
            raise ConfigError("a vector or file mask needs the grid to be rasterized")
        st = (
            mask_from_user(user_mask, grid, mask_is=mask_is)
            if grid is not None
            else (np.asarray(user_mask) != 0 if mask_is == "stable" else np.asarray(user_mask) == 0)
        )
        n_user = int(st.sum())
        st = st & valid
        if exclude is not None:
            st &= ~exclude
        if not st.any():
            raise EmptyDataError(
                f"the stable-terrain mask selects {n_user} cells but none of them holds valid heights in both DEMs "
                "(all NaN); check that the mask covers the DEMs' common area, or omit it to select stable terrain "
                "automatically"
            )
        dh = np.asarray(dh_m, np.float64)[st]
        return st, StableInfo(
            f"user mask ({mask_is})", int(st.sum()), 0, float(np.median(dh)), nmad(dh), 0, tuple(notes)
        )
    m, info = auto_stable_mask(dh_m, valid, slope_rad, exclude, params)
    if notes:
        info = StableInfo(
            info.source,
            info.n_cells,
            info.iterations,
            info.median_m,
            info.nmad_m,
            info.excluded_change_cells,
            tuple(notes) + info.notes,
        )
    return m, info
