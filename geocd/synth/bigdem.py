"""A large DEM pair with known changes, made fast and tile by tile (for scale tests).

:func:`make_dem_pair` writes a DEM A and a DEM B of ``size`` × ``size`` cells in a few
minutes for 20 000 × 20 000 cells, with bounded memory (it runs on :mod:`geocd.tiling`):

* **Terrain** — ``base_m`` plus a sum of value-noise octaves (3000 m down to 30 m, 120 m down
  to 1 m of relief: slopes in every direction, up to ~35°), evaluated at each cell centre from
  the cell's map coordinates, so any window is the same whatever the tiling.
* **B = A moved** by ``shift_m`` = (east, north, up) — the exact shift a co-registration
  must find — **plus changes**: raised and lowered boxes (buildings built or demolished,
  4–30 m), paraboloid mounds and pits (landslide deposits, excavations, 3–40 m), and
  voids (NaN holes, as in stereo DEMs).
* **DEM errors** — per DEM, correlated value noise (``err_corr_m`` at ``err_scale_m``) and
  white noise (``err_white_m``), hashed from the cell index.

Truth: ``truth_dh.tif`` (the change in B's frame, 0 elsewhere; NaN in voids),
``objects.gpkg`` (one row per change with its volume on the grid, as if alone: overlapping
changes add up) and ``truth.json`` (totals from the truth raster).
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
from affine import Affine

from ..errors import ConfigError
from ..geodesy import AOIGrid
from ..progress import Progress
from . import _kernels as K

KINDS = {0: "box", 1: "mound", 2: "void"}
SCALES_M = np.array([3000.0, 1200.0, 500.0, 200.0, 80.0, 30.0])
AMPS_M = np.array([120.0, 50.0, 20.0, 8.0, 3.0, 1.0])


@dataclass(frozen=True)
class DEMPairParams:
    """Parameters of :func:`make_dem_pair` (sizes in cells, lengths in metres)."""

    size: int = 20000
    posting_m: float = 1.0
    seed: int = 0
    shift_m: tuple[float, float, float] = (1.3, -0.7, 0.5)
    changes_per_km2: float = 6.0
    voids_per_km2: float = 0.3
    err_scale_m: float = 30.0
    err_corr_m: float = 0.2
    err_white_m: float = 0.1
    base_m: float = 800.0
    crs: str = "EPSG:32631"
    x0: float = 400000.0
    y0: float = 4900000.0

    def __post_init__(self) -> None:
        if self.size < 16 or self.posting_m <= 0:
            raise ConfigError(f"size ≥ 16 cells and a positive posting are required, got {self.size}, {self.posting_m}")

    def grid(self) -> AOIGrid:
        p = self.posting_m
        return AOIGrid(self.crs, Affine(p, 0.0, self.x0, 0.0, -p, self.y0), self.size, self.size)


def make_objects(p: DEMPairParams) -> np.ndarray:
    """The changes (rows: kind, cx, cy, a, b, h) drawn from ``p.seed``."""
    rng = np.random.default_rng(p.seed + 17)
    side_km = p.size * p.posting_m / 1000.0
    n = int(round(p.changes_per_km2 * side_km**2))
    nv = int(round(p.voids_per_km2 * side_km**2))
    L = p.size * p.posting_m
    rows = []
    margin = 60.0 * p.posting_m
    for _ in range(n):
        cx = p.x0 + rng.uniform(margin, L - margin)
        cy = p.y0 - rng.uniform(margin, L - margin)
        if rng.uniform() < 0.6:
            a, b = rng.uniform(4, 25, size=2) * p.posting_m
            h = rng.choice([-1.0, 1.0]) * rng.uniform(4, 30)
            rows.append((0, cx, cy, a, b, h))
        else:
            a = rng.uniform(6, 40) * p.posting_m
            h = rng.choice([-1.0, 1.0]) * rng.uniform(3, 40)
            rows.append((1, cx, cy, a, a, h))
    for _ in range(nv):
        cx = p.x0 + rng.uniform(margin, L - margin)
        cy = p.y0 - rng.uniform(margin, L - margin)
        a = rng.uniform(5, 30) * p.posting_m
        rows.append((2, cx, cy, a, a, 0.0))
    return np.asarray(rows, np.float64).reshape(-1, 6)


def dem_window(p: DEMPairParams, which: str, window: tuple[int, int, int, int], objects: np.ndarray) -> np.ndarray:
    """float32 heights of DEM ``which`` ("a", "b" or "truth": the change alone) on ``window``
    (row0, col0, h, w) of ``p.grid()``; ``objects`` are the changes (:func:`make_objects`)."""
    r0, c0, h, w = window
    out = np.empty((h, w), np.float64)
    none = np.zeros((0, 6))
    nil = np.zeros(0)
    g = (p.x0, p.y0, p.posting_m, r0, c0, h, w)
    if which == "a":
        K.dem_window(*g, 0.0, 0.0, 0.0, p.seed, SCALES_M, AMPS_M, p.err_scale_m, p.err_corr_m, p.err_white_m, none, out)
    elif which == "b":
        de, dn, dz = p.shift_m
        K.dem_window(*g, de, dn, dz, p.seed, SCALES_M, AMPS_M, p.err_scale_m, 0.0, 0.0, objects, out)
        err = np.empty((h, w), np.float64)
        # B's errors are its own (another seed)
        K.dem_window(*g, 0.0, 0.0, 0.0, p.seed + 5000, nil, nil, p.err_scale_m, p.err_corr_m, p.err_white_m, none, err)
        out += err
    elif which == "truth":
        K.dem_window(*g, 0.0, 0.0, 0.0, p.seed, nil, nil, 1.0, 0.0, 0.0, objects, out)
    else:
        raise ConfigError(f"which must be 'a', 'b' or 'truth', got {which!r}")
    if which != "truth":
        out += p.base_m
    return out.astype(np.float32)


def dem_window_ref(p: DEMPairParams, which: str, window: tuple[int, int, int, int], objects: np.ndarray) -> np.ndarray:
    """Pure-numpy reference of :func:`dem_window`."""
    r0, c0, h, w = window
    rr, cc = np.mgrid[r0 : r0 + h, c0 : c0 + w]
    x = p.x0 + (cc + 0.5) * p.posting_m
    y = p.y0 - (rr + 0.5) * p.posting_m

    def terrain(xs, ys):
        z = np.zeros(xs.shape)
        for k, (s, a) in enumerate(zip(SCALES_M, AMPS_M)):
            z += a * (2.0 * K.vnoise_ref(xs / s, ys / s, np.full(xs.shape, 0.5), p.seed + k) - 1.0)
        return z

    def errors(seed):
        e = p.err_corr_m * (
            2.0 * K.vnoise_ref(x / p.err_scale_m, y / p.err_scale_m, np.full(x.shape, 0.5), seed + 1000) - 1.0
        )
        u1 = K._hash3_ref(rr, cc, 1, seed + 2000)
        u2 = K._hash3_ref(rr, cc, 2, seed + 2000)
        return e + p.err_white_m * np.sqrt(-2.0 * np.log(1.0 - u1)) * np.cos(2.0 * np.pi * u2)

    def changes(z):
        z = z.copy()
        for kind, cx, cy, a, b, hh in objects:
            if kind == 0:
                z += np.where((np.abs(x - cx) <= a) & (np.abs(y - cy) <= b), hh, 0.0)
            else:
                q = ((x - cx) ** 2 + (y - cy) ** 2) / (a * a)
                if kind == 1:
                    z += np.where(q < 1.0, hh * (1.0 - q), 0.0)
                else:
                    z[q < 1.0] = np.nan
        return z

    if which == "a":
        return (terrain(x, y) + errors(p.seed) + p.base_m).astype(np.float32)
    de, dn, dz = p.shift_m
    if which == "b":
        return (changes(terrain(x - de, y - dn) + dz) + errors(p.seed + 5000) + p.base_m).astype(np.float32)
    return changes(np.zeros(x.shape)).astype(np.float32)


def _pair_tile(arrays, ctx):
    p, objects = ctx.params
    r0, c0, h, w = ctx.tile.core
    from ..tiling import TileOutput

    sel = _objects_near(objects, p, ctx.tile.core)
    t = dem_window(p, "truth", (r0, c0, h, w), sel)
    fin = np.isfinite(t)
    small = {
        "changed_cells": int(np.count_nonzero(fin & (t != 0))),
        "void_cells": int(np.count_nonzero(~fin)),
        "raised": float(np.sum(t[fin & (t > 0)], dtype=np.float64)),
        "lowered": float(np.sum(t[fin & (t < 0)], dtype=np.float64)),
    }
    return TileOutput(
        arrays={"a": dem_window(p, "a", (r0, c0, h, w), sel), "b": dem_window(p, "b", (r0, c0, h, w), sel), "truth": t},
        small=small,
    )


def _objects_near(objects: np.ndarray, p: DEMPairParams, window) -> np.ndarray:
    r0, c0, h, w = window
    if objects.size == 0:
        return objects
    ext = np.maximum(objects[:, 3], objects[:, 4]) + 2 * p.posting_m
    xl = p.x0 + c0 * p.posting_m
    xr = p.x0 + (c0 + w) * p.posting_m
    yt = p.y0 - r0 * p.posting_m
    yb = p.y0 - (r0 + h) * p.posting_m
    keep = (
        (objects[:, 1] + ext >= xl)
        & (objects[:, 1] - ext <= xr)
        & (objects[:, 2] + ext >= yb)
        & (objects[:, 2] - ext <= yt)
    )
    return np.ascontiguousarray(objects[keep])


def object_volumes(p: DEMPairParams, objects: np.ndarray) -> list[dict[str, Any]]:
    """Per change: kind, centre, size, height, cells and exact volume on the grid (m³)."""
    out = []
    g = p.grid()
    for k, o in enumerate(objects):
        ext = max(o[3], o[4]) + 2 * p.posting_m
        c0 = max(int(math.floor((o[1] - ext - p.x0) / p.posting_m)), 0)
        c1 = min(int(math.ceil((o[1] + ext - p.x0) / p.posting_m)), g.width)
        r0 = max(int(math.floor((p.y0 - o[2] - ext) / p.posting_m)), 0)
        r1 = min(int(math.ceil((p.y0 - o[2] + ext) / p.posting_m)), g.height)
        t = dem_window(p, "truth", (r0, c0, r1 - r0, c1 - c0), o[None, :])
        fin = np.isfinite(t)
        nz = fin & (t != 0)
        out.append(
            {
                "change_id": k + 1,
                "kind": KINDS[int(o[0])],
                "cx": float(o[1]),
                "cy": float(o[2]),
                "a_m": float(o[3]),
                "b_m": float(o[4]),
                "height_m": float(o[5]),
                "n_cells": int(nz.sum()),
                "void_cells": int((~fin).sum()),
                "volume_m3": float(np.sum(t[nz], dtype=np.float64) * p.posting_m**2),
                "bounds": (float(o[1] - o[3]), float(o[2] - o[4]), float(o[1] + o[3]), float(o[2] + o[4])),
            }
        )
    return out


def make_dem_pair(
    out_dir: os.PathLike | str,
    params: DEMPairParams = DEMPairParams(),
    *,
    tile_size: int = 2048,
    scheduler: Any = "auto",
    progress: Progress | None = None,
) -> dict[str, Path]:
    """Write ``dem_a.tif``, ``dem_b.tif``, ``truth_dh.tif`` (COGs), ``objects.gpkg`` and ``truth.json``.

    Returns name → path.
    """
    import geopandas as gpd
    from shapely.geometry import Point, box

    from ..io.atomic import write_text_atomic
    from ..io.vector import write_gpkg
    from ..tiling import RasterProduct, remove_work, run_tiled

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    p = params
    g = p.grid()
    objects = make_objects(p)
    tags = {"generator": "geocd.synth.bigdem", "params": json.dumps(asdict(p))}
    prods = {
        "dem_a": RasterProduct(str(out / "dem_a.tif"), ("a",), tags=tags | {"epoch": "A"}, descriptions=("height_m",)),
        "dem_b": RasterProduct(str(out / "dem_b.tif"), ("b",), tags=tags | {"epoch": "B"}, descriptions=("height_m",)),
        "truth_dh": RasterProduct(str(out / "truth_dh.tif"), ("truth",), tags=tags, descriptions=("dh_m",)),
    }
    run = run_tiled(
        _pair_tile,
        g,
        {},
        tile_size=tile_size,
        params=(p, objects),
        out=out,
        stage="bigdem",
        products=prods,
        scheduler=scheduler,
        progress=progress,
    )
    vols = object_volumes(p, objects)
    geoms = [box(*v["bounds"]) if v["kind"] == "box" else Point(v["cx"], v["cy"]).buffer(v["a_m"], 32) for v in vols]
    gdf = gpd.GeoDataFrame([{k: v for k, v in d.items() if k != "bounds"} for d in vols], geometry=geoms, crs=g.crs)
    paths = dict(run.products)
    paths["objects"] = write_gpkg(out / "objects.gpkg", {"changes": gdf})
    ch = [v for v in vols if v["kind"] != "void"]
    tot = {k: sum(s[k] for _, s in run.smalls()) for k in ("changed_cells", "void_cells", "raised", "lowered")}
    cell = p.posting_m**2
    # totals from the truth raster (overlapping changes counted once, voids excluded)
    truth = {
        "params": asdict(p),
        "grid": g.to_dict(),
        "n_changes": len(ch),
        "n_voids": len(vols) - len(ch),
        "changed_cells": int(tot["changed_cells"]),
        "void_cells": int(tot["void_cells"]),
        "volume_raised_m3": tot["raised"] * cell,
        "volume_lowered_m3": tot["lowered"] * cell,
        "wall_s": run.wall_s,
    }
    paths["truth"] = write_text_atomic(out / "truth.json", json.dumps(truth, indent=1))
    remove_work(out)
    return paths
