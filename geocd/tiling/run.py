"""``run_tiled``: one pass of a function over the tiles of a grid (see :mod:`geocd.tiling`)."""

from __future__ import annotations

import contextlib
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterator, Mapping

import numpy as np

from ..errors import ConfigError, ProcessingError
from ..geodesy import AOIGrid
from ..progress import Progress, ensure_progress
from .engine import Engine, open_engine
from .grid import Tile, TileGrid
from .store import WORK_DIR, TileStore, make_key
from .writer import RasterProduct, write_product


@dataclass(frozen=True)
class TileContext:
    """What a tile function knows about its tile.

    Attributes
    ----------
    tile : the :class:`~geocd.tiling.grid.Tile` (core and read windows in whole-grid cells)
    grid : the whole grid
    read_grid : the grid of the read window (the arrays the function receives)
    params : the ``params`` given to :func:`run_tiled` (models, constants: anything picklable)
    """

    tile: Tile
    grid: AOIGrid
    read_grid: AOIGrid
    params: Any = None

    @property
    def core(self) -> tuple[slice, slice]:
        """Slices of the tile's core in the read-window arrays."""
        return self.tile.core_in_read

    def crop(self, a: np.ndarray) -> np.ndarray:
        return a[(...,) + self.core]

    @property
    def origin(self) -> tuple[int, int]:
        """(row, col) of the read window's first cell in the whole grid."""
        return self.tile.read[0], self.tile.read[1]

    def global_rows_cols(self) -> tuple[np.ndarray, np.ndarray]:
        """Whole-grid row and column indices (1-D) of the read window's rows and columns."""
        r0, c0, h, w = self.tile.read
        return np.arange(r0, r0 + h), np.arange(c0, c0 + w)

    def core_mask(self) -> np.ndarray:
        """bool (h, w) on the read window: True on the core."""
        m = np.zeros(self.tile.read[2:], bool)
        m[self.core] = True
        return m


@dataclass
class TileOutput:
    """What a tile function returns.

    Attributes
    ----------
    arrays : name → array on the read window or on the core (stored as the core)
    small : anything small and picklable (partial sums, histograms, samples) for a
        reduction over tiles after the pass
    vectors : GeoDataFrame of objects found in the read window; the layer keeps those
        whose centre (centroid) lies in the tile's core — an object belongs to the tile
        holding its centre, so objects seen by two tiles are kept once
    """

    arrays: dict[str, np.ndarray] = field(default_factory=dict)
    small: Any = None
    vectors: Any = None


@dataclass(frozen=True)
class _Job:
    func: Callable
    tile: Tile
    grid: AOIGrid
    inputs: Mapping[str, Any]


def _keep_by_centre(gdf, tile: Tile, grid: AOIGrid):
    if gdf is None or len(gdf) == 0:
        return gdf
    c = gdf.geometry.centroid
    inv = ~grid.transform
    col = inv.a * c.x.to_numpy() + inv.b * c.y.to_numpy() + inv.c
    row = inv.d * c.x.to_numpy() + inv.e * c.y.to_numpy() + inv.f
    # the grid's last row/column own centres on the outer edge
    row = np.minimum(row, grid.height - 1e-9)
    col = np.minimum(col, grid.width - 1e-9)
    r0, c0, h, w = tile.core
    keep = (row >= r0) & (row < r0 + h) & (col >= c0) & (col < c0 + w)
    return gdf[keep]


def _run_tile(job: _Job, params: Any = None) -> TileOutput:
    """Worker side: read the tile's windows, call the function, keep the core and the owned objects."""
    t = job.tile
    arrays = {k: src.read(job.grid, t.read) for k, src in job.inputs.items()}
    r0, c0, h, w = t.read
    ctx = TileContext(t, job.grid, job.grid.subgrid(r0, c0, h, w), params)
    out = job.func(arrays, ctx)
    if out is None:
        out = TileOutput()
    elif isinstance(out, Mapping):
        out = TileOutput(arrays=dict(out))
    elif not isinstance(out, TileOutput):
        raise ProcessingError(f"a tile function returns a TileOutput or a dict of arrays, not {type(out).__name__}")
    core_shape = tuple(t.core[2:])
    read_shape = tuple(t.read[2:])
    kept = {}
    for name, a in out.arrays.items():
        a = np.asarray(a)
        if a.shape[-2:] == read_shape:
            a = a[(...,) + t.core_in_read]
        elif a.shape[-2:] != core_shape:
            raise ProcessingError(
                f"tile array {name!r} has shape {a.shape}; expected the read window "
                f"{read_shape} or the core {core_shape}"
            )
        kept[name] = np.ascontiguousarray(a)
    out.arrays = kept
    out.vectors = _keep_by_centre(out.vectors, t, job.grid)
    return out


@dataclass
class TiledRun:
    """The outcome of :func:`run_tiled`.

    Attributes
    ----------
    store : the pass's :class:`~geocd.tiling.store.TileStore` (per-tile arrays and small results)
    products : product name → COG path
    n_tiles, n_resumed : tiles in the grid, tiles found finished by an earlier (killed) run
    wall_s : seconds
    """

    store: TileStore
    tile_grid: TileGrid
    products: dict[str, Path] = field(default_factory=dict)
    n_tiles: int = 0
    n_resumed: int = 0
    wall_s: float = 0.0

    def smalls(self) -> Iterator[tuple[Tile, Any]]:
        """(tile, small result) for every tile, in tile order."""
        for t in self.tile_grid:
            yield t, self.store.small(t)[0]

    def vectors(self):
        """Every tile's kept objects, merged (GeoDataFrame; None when no tile returned any)."""
        import pandas as pd

        parts = [v for t in self.tile_grid for v in [self.store.small(t)[1]] if v is not None and len(v)]
        if not parts:
            return None
        import geopandas as gpd

        return gpd.GeoDataFrame(pd.concat(parts, ignore_index=True), crs=parts[0].crs)

    def source(self, name: str):
        """A lazy source of array ``name`` for a later pass."""
        return self.store.source(name)

    def read(self, name: str, window: tuple[int, int, int, int] | None = None) -> np.ndarray:
        """Array ``name`` on ``window`` (default: the whole grid — small grids only)."""
        g = self.tile_grid.grid
        return self.store.read(name, window or (0, 0, g.height, g.width))


def work_root(out: str | Path | None) -> Path:
    """The hidden work folder of a run writing into ``out`` (a temporary folder without ``out``)."""
    if out is None:
        return Path(tempfile.mkdtemp(prefix="geocd-work-"))
    return Path(out) / WORK_DIR


def run_tiled(
    func: Callable[[dict, TileContext], Any],
    grid: AOIGrid | TileGrid,
    inputs: Mapping[str, Any],
    *,
    overlap_cells: int = 0,
    tile_size: int | tuple[int, int] = 1024,
    params: Any = None,
    out: str | Path | None = None,
    work: str | Path | None = None,
    stage: str = "tiled",
    key: Any = None,
    products: Mapping[str, RasterProduct] | None = None,
    scheduler: "str | Engine" = "sync",
    n_workers: int | None = None,
    memory_limit: str | int | None = None,
    max_in_flight: int | None = None,
    progress: Progress | None = None,
) -> TiledRun:
    """Run ``func`` on every tile of ``grid`` with ``overlap_cells`` of context; resume finished tiles.

    Parameters
    ----------
    func : ``func(arrays, ctx) → TileOutput | dict of arrays``; ``arrays`` maps each input's
        name to its float32 array on the tile's read window; module-level (picklable)
    grid : the processing grid (or a TileGrid; one with a ``selected`` subset runs only those tiles,
        and the products hold each product's ``fill`` value on the others)
    inputs : name → source (:class:`~geocd.tiling.sources.RasterSource`,
        :class:`~geocd.tiling.sources.ArraySource`, a previous pass's ``TiledRun.source(name)``)
    overlap_cells : the context the method declares (cells on every side)
    params : passed to ``func`` as ``ctx.params`` (whole-scene models, constants); sent to each
        worker once
    out : output folder (the work folder is ``out/.geocd-work``); ``work`` overrides it
    stage, key : the pass's name and whatever else its results depend on; together with
        the function, params, inputs and tiling they make the resume key
    products : name → :class:`~geocd.tiling.writer.RasterProduct`, written as COGs once every tile is done
    scheduler : ``sync`` | ``threads`` | ``processes`` | ``auto`` (``sync`` when one tile is left to do) | a
        scheduler address, or an open Engine
    progress : ``progress(fraction, message)``; may raise CancelledError (in-flight tiles are cancelled)

    Returns
    -------
    TiledRun
    """
    t0 = time.perf_counter()
    prog = ensure_progress(progress)
    tg = (
        grid
        if isinstance(grid, TileGrid)
        else TileGrid(grid, tile_size if not isinstance(tile_size, int) else (tile_size, tile_size), int(overlap_cells))
    )
    if isinstance(grid, TileGrid) and overlap_cells and overlap_cells != grid.overlap:
        tg = grid.with_overlap(int(overlap_cells))
    g = tg.grid
    if not callable(func):
        raise ConfigError("run_tiled needs a function")
    ident = {k: (src.identity() if hasattr(src, "identity") else repr(src)) for k, src in inputs.items()}
    fname = f"{getattr(func, '__module__', '')}.{getattr(func, '__qualname__', repr(func))}"
    sel = sorted(tg.selected) if tg.selected is not None else None
    full_key = make_key(
        stage,
        fname,
        params,
        ident,
        g.to_dict(),
        list(tg.tile_size),
        tg.overlap,
        key,
        *([sel, tg.merge_runs] if sel is not None else []),
    )
    root = Path(work) if work is not None else work_root(out)
    store = TileStore(root, stage, full_key, tg)
    tiles = list(tg)
    todo = [t for t in tiles if not store.done(t)]
    n = len(tiles)
    n_res = n - len(todo)
    done = n_res
    prog(done / n if n else 1.0, f"{stage}: {done}/{n} tiles" + (f" ({n_res} resumed)" if n_res else ""))
    if todo:
        jobs = (_Job(func, t, g, dict(inputs)) for t in todo)
        if isinstance(scheduler, str) and scheduler.strip() == "auto" and len(todo) < 2:
            scheduler = "sync"  # one tile: a cluster would only add its start-up
        with open_engine(scheduler, n_workers=n_workers, memory_limit=memory_limit) as eng:
            it = eng.map_unordered(
                _run_tile, jobs, shared=params, max_in_flight=max_in_flight, key_prefix=f"geocd-{stage}"
            )
            with contextlib.closing(it):
                for job, res in it:
                    store.save(job.tile, res.arrays, (res.small, res.vectors))
                    done += 1
                    prog(done / n, f"{stage}: {done}/{n} tiles")
    run = TiledRun(store, tg, {}, n, n_res)
    for name, spec in (products or {}).items():
        run.products[name] = write_product(store, spec, g, tg)
    run.wall_s = time.perf_counter() - t0
    return run
