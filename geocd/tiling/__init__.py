"""Tiled processing of whole scenes on Dask: bounded memory, resumable, one laptop or a cluster.

One layer for every raster method. A method is a function of a tile's arrays::

    from geocd.tiling import RasterSource, RasterProduct, TileOutput, run_tiled

    def slope_tile(arrays, ctx):                  # arrays: name → float32 (read window)
        s = slope(arrays["dem"])                  # needs 1 cell of context
        return TileOutput(arrays={"slope": s},    # read-window (or core) arrays; the core is kept
                          small=np.nansum(s[ctx.core]))   # a partial result for a reduction

    run = run_tiled(slope_tile, grid, {"dem": RasterSource("dem.tif", dem=True)},
                    overlap_cells=1, tile_size=1024, out="out", stage="slope",
                    products={"slope": RasterProduct("out/slope.tif", bands=("slope",))},
                    scheduler="auto", progress=progress)
    total = sum(s for _, s in run.smalls())       # whole-scene reduction over tiles

What the layer guarantees:

* **Declared overlap.** Every method states the context it needs (``overlap_cells``, or
  :func:`overlap_cells` from metres). Tiles read their core plus that overlap (clipped at
  the grid's edge, never padded) and keep only their core: a method whose context fits
  in its declared overlap gives the same cells tiled as on the whole grid.
* **Lazy windows.** Inputs are sources read by window on the worker that runs the tile
  (:class:`RasterSource`: rasterio windows, a GDAL warped VRT when the file is on another
  grid); a later pass reads an earlier pass's arrays (``run.source(name)``).
* **One writer.** Tile results come back to the client, which alone writes them to the
  work folder; products are assembled into a tiled GeoTIFF and written as COGs with
  :func:`geocd.io.raster.write_cog`'s conventions, through a hidden temporary file and a
  rename (nothing partial is ever visible under the product's name).
* **Vectors.** A tile's objects are kept when their centre lies in its core (an object
  belongs to the tile holding its centre); ``run.vectors()`` merges them. Objects larger
  than the overlap need a cross-tile merge (:mod:`geocd.tiling.regions` for connected
  regions of a raster).
* **Reductions.** ``small`` results (sums, histograms, samples) come back per tile for
  whole-scene statistics (``run.smalls()``).
* **Dask as the engine.** ``scheduler``: ``sync`` | ``threads`` | ``processes`` | ``auto``
  (a ``distributed.LocalCluster`` sized to the machine, a memory limit per worker) | the
  address of a running ``dask.distributed`` scheduler. A bounded number of tiles is in
  flight (``as_completed``); progress is reported per tile through geocd's progress
  callback, and a cancel (the callback raising CancelledError) stops in-flight tiles.
* **Resume.** Finished tiles are journalled under ``out/.geocd-work/<stage>-<key>/`` with a
  hash of the pass's parameters, inputs and tiling: a killed run restarted with the same
  command redoes only the unfinished tiles and gives the same result; a changed command
  starts afresh. :func:`remove_work` deletes the work folder after a successful run.
"""

from __future__ import annotations

import shutil
from pathlib import Path

from .engine import LOCAL_KINDS, SCHEDULER_HELP, Engine, open_engine, parse_memory, usable_cores
from .grid import Tile, TileGrid, overlap_cells
from .run import TileContext, TiledRun, TileOutput, run_tiled, work_root
from .sources import ArraySource, RasterSource
from .store import WORK_DIR, StoreSource, TileStore, make_key
from .writer import RasterProduct, overview_factors, write_product


def remove_work(out: str | Path) -> None:
    """Delete the hidden work folder of a finished run writing into ``out``."""
    shutil.rmtree(Path(out) / WORK_DIR, ignore_errors=True)


__all__ = [
    "ArraySource",
    "Engine",
    "LOCAL_KINDS",
    "RasterProduct",
    "RasterSource",
    "SCHEDULER_HELP",
    "StoreSource",
    "Tile",
    "TileContext",
    "TileGrid",
    "TileOutput",
    "TileStore",
    "TiledRun",
    "WORK_DIR",
    "make_key",
    "open_engine",
    "overlap_cells",
    "overview_factors",
    "parse_memory",
    "remove_work",
    "run_tiled",
    "usable_cores",
    "work_root",
    "write_product",
]
