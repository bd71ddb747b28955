"""Tiered change detection: the 2-D screen first, the 3-D methods only where it flags (``geocd run --screen``).

1. The screen runs on the manifest's views projected on the terrain DEM (no stereo needed):
   :func:`geocd.screen.pipeline.run_screen_manifest` on the run's AOI grid, threshold from a
   within-epoch no-change pair.
2. The grid is cut into square tiles (``tile_cells``); a tile is flagged when it holds changed
   screen cells of a region of at least ``min_region_m2``.
3. Flagged tiles that touch (8-connectivity) form groups; each group's bounding box, grown by
   ``margin_cells`` (the stereo matcher's and the change test's context), is matched with
   :func:`geocd.stereo.run_stereo` on that window only. The pair-DEMs are pasted onto the
   whole grid (cells outside every window: not observed) and the run goes on as usual
   (self-consistency baseline, change test, layers).

What the screen misses is lost to the 3-D test: ``run_summary.json`` reports the flagged
fraction and the time of each stage; ``bench/bench_screen.py`` compares with a full run.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Any

import numpy as np

from ..geodesy import AOIGrid
from ..progress import Progress, ensure_progress, sub_progress


@dataclasses.dataclass(frozen=True)
class Flagged:
    """Tiles the screen flagged and the windows the 3-D stage runs on."""

    tile_cells: int
    tiles: np.ndarray                       # bool (tile rows, tile cols)
    windows: list[tuple[int, int, int, int]]  # (row0, col0, height, width) on the grid

    @property
    def tile_fraction(self) -> float:
        return float(self.tiles.mean()) if self.tiles.size else 0.0

    def window_fraction(self, shape: tuple[int, int]) -> float:
        m = np.zeros(shape, bool)
        for r0, c0, h, w in self.windows:
            m[r0:r0 + h, c0:c0 + w] = True
        return float(m.mean())


def flag_tiles(changed: np.ndarray, tile_cells: int, margin_cells: int, min_cells: int = 1) -> Flagged:
    """Tiles holding ≥ ``min_cells`` changed cells; windows = bounding boxes of touching flagged tiles + margin."""
    from scipy import ndimage

    H, W = changed.shape
    nr, nc = -(-H // tile_cells), -(-W // tile_cells)
    pad = np.zeros((nr * tile_cells, nc * tile_cells), bool)
    pad[:H, :W] = changed
    counts = pad.reshape(nr, tile_cells, nc, tile_cells).sum(axis=(1, 3))
    tiles = counts >= max(int(min_cells), 1)
    lab, n = ndimage.label(tiles, structure=np.ones((3, 3), bool))
    wins = []
    for sl in ndimage.find_objects(lab):
        r0 = max(0, sl[0].start * tile_cells - margin_cells)
        c0 = max(0, sl[1].start * tile_cells - margin_cells)
        r1 = min(H, sl[0].stop * tile_cells + margin_cells)
        c1 = min(W, sl[1].stop * tile_cells + margin_cells)
        wins.append((r0, c0, r1 - r0, c1 - c0))
    return Flagged(tile_cells, tiles, wins)


def _paste(parts: list[tuple[Any, tuple[int, int, int, int]]], grid: AOIGrid):
    """Pair-DEMs of windows → one pair-DEM on the whole grid (not observed outside the windows)."""
    from ..stereo.products import PairDEM

    first = parts[0][0]
    H, W = grid.shape

    def full(name, fill, dtype):
        if getattr(first, name) is None:
            return None
        a = np.full((H, W), fill, dtype)
        for p, (r0, c0, h, w) in parts:
            a[r0:r0 + h, c0:c0 + w] = getattr(p, name)
        return a

    return PairDEM(z_m=full("z_m", np.nan, np.float32), score=full("score", np.nan, np.float32),
                   g_px_per_m=full("g_px_per_m", np.nan, np.float32), valid=full("valid", False, bool), grid=grid,
                   name=first.name, camera_names=first.camera_names, ncc=full("ncc", np.nan, np.float32),
                   ssd=full("ssd", np.nan, np.float32), flags=full("flags", 255, np.uint8),
                   z_raw_m=full("z_raw_m", np.nan, np.float32), mdl_window=full("mdl_window", np.nan, np.float32),
                   epoch=first.epoch, meta={**first.meta, "screened_windows": [list(w) for _, w in parts]})


def run_stereo_screened(manifest, *, out: Path, stereo_params, screen_params, epochs: list[str], pairs: str,
                        posting_m: float | None = None, epoch_a: str | None = None, epoch_b: str | None = None,
                        tile_cells: int = 128, margin_cells: int | None = None, min_region_m2: float = 4.0,
                        progress: Progress | None = None) -> dict[str, Any]:
    """The screen, then geocd stereo on the flagged windows only; returns run_stereo's dict + ``screen`` info."""
    from ..io.raster import read_dem
    from ..stereo.pipeline import default_aoi_grid, load_epoch_images, run_stereo
    from ..stereo.products import write_pair_dem
    from ..stereo.pipeline import pair_path
    from .pipeline import run_screen_manifest

    prog = ensure_progress(progress)
    m = manifest
    images = {e: load_epoch_images(m, m.epoch(e)) for e in epochs}
    dem_median = None
    if m.dem is not None:
        dem_median = float(np.nanmedian(read_dem(m.dem.path, vertical_datum=m.dem.vertical_datum)
                                        .to_ellipsoidal().height_m))
    grid = default_aoi_grid(m, images, posting_m=posting_m, dem_median=dem_median, params=stereo_params)
    t0 = time.perf_counter()
    sc = run_screen_manifest(m, out=out / "screen", params=screen_params, grid=grid, epoch_a=epoch_a,
                             epoch_b=epoch_b, progress=sub_progress(prog, 0.0, 0.2, "screen: "))
    t_screen = time.perf_counter() - t0
    sr = sc["run"]
    changed = sr.valid & np.isfinite(sr.dissimilarity) & (sr.dissimilarity > sc["threshold"])
    from scipy import ndimage

    lab, n = ndimage.label(changed, structure=np.ones((3, 3), bool))
    if n:
        sizes = np.bincount(lab.ravel())
        keep = sizes >= max(1, int(np.ceil(min_region_m2 / grid.cell_area_m2)))
        keep[0] = False
        changed = keep[lab]
    if margin_cells is None:  # the matcher's window and the change test's neighbourhood, with room to spare
        margin_cells = int(4 * stereo_params.window + 16)
    fl = flag_tiles(changed, tile_cells, margin_cells)
    t1 = time.perf_counter()
    parts: dict[str, list] = {}
    outputs: dict[str, Path] = {}
    for k, (r0, c0, h, w) in enumerate(fl.windows):
        sub = grid.subgrid(r0, c0, h, w)
        st = run_stereo(m, epochs=epochs, out_dir=out / ".screened" / f"w{k:03d}", params=stereo_params, grid=sub,
                        keep_arrays=True, pairs=pairs, orient=False,
                        progress=sub_progress(prog, 0.2 + 0.8 * k / max(len(fl.windows), 1),
                                              0.2 + 0.8 * (k + 1) / max(len(fl.windows), 1), f"stereo window {k + 1}: "))
        for key, pd in st["pairs"].items():
            parts.setdefault(key, []).append((pd, (r0, c0, h, w)))
    t_3d = time.perf_counter() - t1
    kept = {}
    for key, ps in parts.items():
        pd = _paste(ps, grid)
        e, ab = key.split("/", 1)
        a, b = ab.split("__", 1)
        outputs[key] = write_pair_dem(pair_path(out, e, a, b), pd, tags={"screened_windows": str(fl.windows)})
        kept[key] = pd
    import shutil

    shutil.rmtree(out / ".screened", ignore_errors=True)
    info = {"threshold": round(float(sc["threshold"]), 4), "rule": sc["rule"], "feature": screen_params.feature.label,
            "pair": list(sc["pair"]), "tile_cells": tile_cells, "margin_cells": margin_cells,
            "flagged_tiles": int(fl.tiles.sum()), "tiles": int(fl.tiles.size),
            "flagged_tile_fraction": round(fl.tile_fraction, 4), "windows": [list(w) for w in fl.windows],
            "stereo_cell_fraction": round(fl.window_fraction(grid.shape), 4),
            "screen_seconds": round(t_screen, 2), "stereo_seconds": round(t_3d, 2)}
    prog(1.0, "screened stereo done")
    return {"outputs": outputs, "grid": grid, "pairs": kept, "screen": info,
            "screen_outputs": {f"screen:{k}": v for k, v in sc["outputs"].items() if not k.startswith("view:")}}
