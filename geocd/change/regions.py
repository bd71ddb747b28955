"""Changed regions: connected groups of changed cells as polygons (the ``changes`` layer).

Shared by every method (DEM differencing, self-consistency, octree), so the layer
has one schema:

=================  =========================================================================
column             meaning
=================  =========================================================================
region_id          1, 2, ... (raised regions first, then lowered; each by decreasing size)
method             the method that produced the change map
epoch_a, epoch_b   the epochs compared (B − A)
sign               +1 raised, −1 lowered (int)
n_cells            number of cells
area_m2            n_cells × cell area
mean_dz_m          mean dz over the region's cells with a finite dz
max_dz_m           the signed dz with the largest |dz|
volume_m3          Σ dz × cell area (cells with a finite dz)
volume_sigma_m3    1σ of volume_m3; NaN when unknown
confidence         percent (99 = 99 %), the level at which the region is significant; NaN when unknown
geometry           Polygon / MultiPolygon in the grid's CRS
=================  =========================================================================

**Input convention.** ``sign`` is an int8 array: +1 raised, −1 lowered, 0 not
changed; any other value (e.g. the −128 nodata of change-mask rasters) counts as
not changed, so a change-mask raster can be passed as is. Regions are 8-connected
components of the +1 cells and of the −1 cells separately.

**σ and confidence.** ``volume_sigma_fn(mask) → σ`` (called with a full-grid bool
mask; when the callable also has ``windowed(mask_window, slices)``, that is used
instead, which avoids full-grid scans for many small regions) (e.g. the variogram-based
:meth:`geocd.demdiff.uncertainty.Uncertainty.volume_sigma_fn`) gives the honest σ of
the region's volume. Without it, a per-cell ``dz_sigma_m`` gives a *conservative*
σ that assumes errors fully correlated inside the region (cell area × Σ σ_i).
Confidence (percent): with a volume σ and ``volume_confidence``, the two-sided Gaussian
level ``100 (2Φ(|V|/σ) − 1)``; else a per-cell confidence array's median over the region
(a method whose test is region-level gives every cell of a region the region's confidence);
else a scalar ``confidence`` as given (the level the map was thresholded at); else NaN.
"""

from __future__ import annotations

import math
from typing import Any, Callable

import numpy as np

COLUMNS = (
    "region_id",
    "method",
    "epoch_a",
    "epoch_b",
    "sign",
    "n_cells",
    "area_m2",
    "mean_dz_m",
    "max_dz_m",
    "volume_m3",
    "volume_sigma_m3",
    "confidence",
)

_EIGHT = np.ones((3, 3), dtype=bool)


def empty_regions(crs: Any = None):
    """An empty ``changes`` layer with the full schema."""
    import geopandas as gpd
    import pandas as pd

    df = pd.DataFrame(
        {
            "region_id": pd.Series(dtype="int64"),
            "method": pd.Series(dtype="str"),
            "epoch_a": pd.Series(dtype="str"),
            "epoch_b": pd.Series(dtype="str"),
            "sign": pd.Series(dtype="int64"),
            "n_cells": pd.Series(dtype="int64"),
            **{c: pd.Series(dtype="float64") for c in COLUMNS[6:]},
        }
    )
    return gpd.GeoDataFrame(df, geometry=gpd.GeoSeries([], crs=crs), crs=crs)


def _cell_area_m2(grid) -> float:
    """Cell area in m² (local scale at the grid centre for geographic grids)."""
    if not grid.crs.is_geographic:
        return float(grid.cell_area_m2)
    a, f = 6378137.0, 1.0 / 298.257223563
    e2 = f * (2 - f)
    l, b, r, t = grid.bounds
    lat = math.radians(0.5 * (b + t))
    w = 1 - e2 * math.sin(lat) ** 2
    n = a / math.sqrt(w)
    mm = a * (1 - e2) / w**1.5
    return float(math.radians(grid.posting[0]) * n * math.cos(lat) * math.radians(grid.posting[1]) * mm)


def _gauss_level(v: float, s: float) -> float:
    if not (math.isfinite(v) and math.isfinite(s)) or s <= 0:
        return float("nan")
    return 100.0 * float(math.erf(abs(v) / s / math.sqrt(2.0)))


def change_regions(
    sign: np.ndarray,
    dz_m: np.ndarray,
    grid,
    *,
    confidence: float | np.ndarray | None = None,
    dz_sigma_m: float | np.ndarray | None = None,
    volume_sigma_fn: Callable[[np.ndarray], float] | None = None,
    method: str = "",
    epoch_a: str = "",
    epoch_b: str = "",
    min_cells: int = 4,
    cell_area_m2: float | None = None,
    volume_confidence: bool = True,
):
    """Connected changed regions as polygons with area, volume ± σ and confidence.

    Parameters
    ----------
    sign : int8 (rows, cols); +1 raised, −1 lowered, anything else not changed
    dz_m : float (rows, cols), B − A (NaN allowed)
    grid : AOIGrid of the arrays
    confidence : optional scalar or per-cell float array, percent (NaN unknown)
    dz_sigma_m : optional scalar or per-cell 1σ of dz (m), used when ``volume_sigma_fn`` is None
    volume_sigma_fn : optional callable(bool mask) → 1σ of the region's volume (m³)
    min_cells : regions smaller than this are dropped
    cell_area_m2 : optional cell area; default the grid's (the local metric area for
        geographic grids)
    volume_confidence : bool
        With a volume σ, the region's confidence is the Gaussian level of |V|/σ_V (a
        volume test); False keeps the given ``confidence`` (the method's own test) and
        reports σ_V only.

    Returns
    -------
    GeoDataFrame in ``grid.crs`` with the columns of :data:`COLUMNS` + geometry
    (empty, with the schema, when nothing changed).
    """
    import geopandas as gpd
    import pandas as pd
    from rasterio.features import shapes
    from scipy import ndimage
    from shapely.geometry import shape
    from shapely.ops import unary_union

    s = np.asarray(sign)
    dz = np.asarray(dz_m, np.float64)
    if s.shape != grid.shape or dz.shape != grid.shape:
        from ..errors import ConfigError

        raise ConfigError(f"sign {s.shape} and dz {dz.shape} must both have the grid's shape {grid.shape}")
    cell = float(cell_area_m2) if cell_area_m2 is not None else _cell_area_m2(grid)
    conf_arr = None
    conf_scalar = float("nan")
    if confidence is not None:
        if np.ndim(confidence) == 0:
            conf_scalar = float(confidence)
        else:
            conf_arr = np.asarray(confidence, np.float64)
    sig_arr = None
    if dz_sigma_m is not None:
        sig_arr = np.broadcast_to(np.asarray(dz_sigma_m, np.float64), grid.shape)
    recs: list[dict] = []
    geoms: list = []
    for sgn in (1, -1):
        lab, n = ndimage.label(s == sgn, structure=_EIGHT)
        if n == 0:
            continue
        sizes = np.bincount(lab.ravel(), minlength=n + 1)
        sizes[0] = 0
        keep_ids = np.nonzero(sizes >= max(int(min_cells), 1))[0]
        if keep_ids.size == 0:
            continue
        keep_ids = keep_ids[np.argsort(-sizes[keep_ids], kind="stable")]
        # one pass of polygonization for all kept regions of this sign
        lab_keep = np.where(np.isin(lab, keep_ids), lab, 0).astype(np.int32)
        parts: dict[int, list] = {}
        for geom, val in shapes(lab_keep, mask=lab_keep > 0, connectivity=8, transform=grid.transform):
            parts.setdefault(int(val), []).append(shape(geom))
        objs = ndimage.find_objects(lab)
        for rid in keep_ids:
            sl = objs[rid - 1]
            m = lab[sl] == rid
            d = dz[sl][m]
            fin = np.isfinite(d)
            vol = float(np.sum(d[fin]) * cell)
            mean = float(np.mean(d[fin])) if fin.any() else float("nan")
            mx = float(d[fin][np.argmax(np.abs(d[fin]))]) if fin.any() else float("nan")
            vs = float("nan")
            if volume_sigma_fn is not None:
                win = getattr(volume_sigma_fn, "windowed", None)
                if win is not None:  # fast path: the set given by its bounding window
                    vs = float(win(m, sl))
                else:
                    full = np.zeros(grid.shape, bool)
                    full[sl] = m
                    vs = float(volume_sigma_fn(full))
            elif sig_arr is not None:
                sg = sig_arr[sl][m]
                vs = float(np.nansum(sg) * cell) if np.isfinite(sg).any() else float("nan")
            if math.isfinite(vs) and volume_confidence:
                cf = _gauss_level(vol, vs)
            elif conf_arr is not None:
                cc = conf_arr[sl][m]
                cc = cc[np.isfinite(cc)]
                cf = float(np.median(cc)) if cc.size else float("nan")
            else:
                cf = conf_scalar
            g = unary_union(parts.get(int(rid), []))
            if not g.is_valid:
                g = g.buffer(0)
            recs.append(
                {
                    "method": method,
                    "epoch_a": epoch_a,
                    "epoch_b": epoch_b,
                    "sign": sgn,
                    "n_cells": int(sizes[rid]),
                    "area_m2": float(sizes[rid] * cell),
                    "mean_dz_m": mean,
                    "max_dz_m": mx,
                    "volume_m3": vol,
                    "volume_sigma_m3": vs,
                    "confidence": cf,
                }
            )
            geoms.append(g)
    if not recs:
        return empty_regions(grid.crs)
    df = pd.DataFrame(recs)
    df.insert(0, "region_id", np.arange(1, len(df) + 1, dtype=np.int64))
    df["sign"] = df["sign"].astype("int64")
    df["n_cells"] = df["n_cells"].astype("int64")
    return gpd.GeoDataFrame(df, geometry=geoms, crs=grid.crs)


def correlated_volume_sigma(dz_sigma_m: np.ndarray, correlation_cells: float, cell_area_m2: float):
    """A ``volume_sigma_fn`` for :func:`change_regions` from a per-cell σ and a correlation area.

    Errors are taken as fully correlated within blocks of ``correlation_cells`` cells and
    independent between blocks (the footprint of one height measurement, e.g. a matching
    window): σ_V = a · σ_rms · √(n · min(n, n_c)) for a region of n cells of area a whose
    per-cell σ have root mean square σ_rms — fully correlated below one block, √n-averaging
    beyond.

    Parameters
    ----------
    dz_sigma_m : float (rows, cols), 1σ of dz per cell (NaN unknown: left out)
    correlation_cells : cells per independent error sample (≥ 1)
    cell_area_m2 : area of one cell

    Returns
    -------
    callable(mask) → σ_V (m³), with ``windowed(mask_window, slices)``
    """
    sig = np.asarray(dz_sigma_m, np.float64)
    nc = max(float(correlation_cells), 1.0)

    def _sigma(s: np.ndarray) -> float:
        s = s[np.isfinite(s)]
        if s.size == 0:
            return float("nan")
        n = s.size
        return float(cell_area_m2 * math.sqrt(float(np.mean(s * s)) * n * min(n, nc)))

    def fn(mask: np.ndarray) -> float:
        return _sigma(sig[np.asarray(mask, bool)])

    fn.windowed = lambda mask_window, slices: _sigma(sig[slices][np.asarray(mask_window, bool)])  # type: ignore[attr-defined]
    return fn
