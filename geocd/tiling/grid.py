"""Cutting an AOI grid into tiles that carry the overlap a method declares."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Iterator

import numpy as np

from ..errors import ConfigError
from ..geodesy import AOIGrid


def overlap_cells(grid: AOIGrid | None = None, *, cells: int | None = None, metres: float | None = None) -> int:
    """The overlap a method needs, in cells: ``cells`` as given, or ``metres`` rounded up to whole cells.

    Parameters
    ----------
    grid : AOIGrid, needed with ``metres`` (its posting converts metres to cells; the
        coarser axis is used so that the context covers ``metres`` in both directions)
    cells, metres : give one (or both: the larger wins)
    """
    need = 0
    if cells is not None:
        if cells < 0:
            raise ConfigError(f"an overlap cannot be negative, got {cells} cells")
        need = int(cells)
    if metres is not None:
        if metres < 0:
            raise ConfigError(f"an overlap cannot be negative, got {metres} m")
        if grid is None:
            raise ConfigError("an overlap in metres needs the grid (its posting converts metres to cells)")
        post = min(grid.posting)
        need = max(need, int(math.ceil(metres / post - 1e-9)))
    return need


@dataclass(frozen=True)
class Tile:
    """One tile: a core window that it owns and a read window (core + overlap, clipped to the grid).

    All windows are (row0, col0, height, width) in cells of the whole grid.
    """

    index: tuple[int, int]
    core: tuple[int, int, int, int]
    read: tuple[int, int, int, int]

    @property
    def name(self) -> str:
        return f"r{self.index[0]:04d}_c{self.index[1]:04d}"

    @property
    def core_in_read(self) -> tuple[slice, slice]:
        """Slices of the core inside arrays of the read window."""
        r0, c0, h, w = self.core
        R0, C0, _, _ = self.read
        return (slice(r0 - R0, r0 - R0 + h), slice(c0 - C0, c0 - C0 + w))

    @property
    def core_slices(self) -> tuple[slice, slice]:
        """Slices of the core in whole-grid arrays."""
        r0, c0, h, w = self.core
        return (slice(r0, r0 + h), slice(c0, c0 + w))

    @property
    def read_slices(self) -> tuple[slice, slice]:
        r0, c0, h, w = self.read
        return (slice(r0, r0 + h), slice(c0, c0 + w))

    @property
    def n_cells(self) -> int:
        return self.core[2] * self.core[3]


@dataclass(frozen=True)
class TileGrid:
    """An AOI grid cut into ``tile_size`` tiles with ``overlap`` cells of context on every side.

    Tiles are enumerated row by row. The overlap is clipped at the grid's edges, so a
    method sees exactly the grid's own border there (never padding): a per-cell method
    whose context fits in the overlap gives on every core cell what it gives on the
    whole grid.

    ``selected`` (optional) restricts a pass to some tiles — bool (tile rows, tile cols), or
    an iterable of (i, j): iterating the grid (``for t in tg``, ``len(tg)``) yields only those;
    :meth:`all_tiles` yields every tile. The writer fills the cores of the other tiles with
    each product's ``fill`` value (e.g. "not examined"), and reading a stored array there
    gives that fill, so a pass over a subset still makes whole-grid products.

    ``merge_runs`` (with a selection): consecutive selected tiles of a tile row are processed as one
    unit (a :class:`Tile` whose core spans the run, named by its first tile), so their shared edges
    need no overlap of their own — a method with a wide context reads ``(n·t + 2o) × (t + 2o)``
    cells for a run of n tiles instead of n times ``(t + 2o)²``. Only selected tiles' cores are ever
    inside a unit's core.
    """

    grid: AOIGrid
    tile_size: tuple[int, int] = (1024, 1024)
    overlap: int = 0
    selected: frozenset | None = None
    merge_runs: bool = False

    def __post_init__(self) -> None:
        ts = self.tile_size
        if isinstance(ts, int):
            object.__setattr__(self, "tile_size", (int(ts), int(ts)))
        th, tw = self.tile_size
        if th < 1 or tw < 1:
            raise ConfigError(f"tile size must be positive, got {self.tile_size}")
        if self.overlap < 0:
            raise ConfigError(f"overlap must be ≥ 0, got {self.overlap}")
        sel = self.selected
        if sel is not None and not isinstance(sel, frozenset):
            a = np.asarray(sel) if not isinstance(sel, (set, list, tuple)) else None
            if a is not None and a.dtype == bool:
                if a.shape != self.shape:
                    raise ConfigError(f"the tile selection has shape {a.shape}; the tiling has {self.shape} tiles")
                sel = frozenset((int(i), int(j)) for i, j in zip(*np.nonzero(a)))
            else:
                sel = frozenset((int(i), int(j)) for i, j in sel)
            object.__setattr__(self, "selected", sel)
        if self.selected is not None:
            bad = [ij for ij in self.selected if not (0 <= ij[0] < self.shape[0] and 0 <= ij[1] < self.shape[1])]
            if bad:
                raise ConfigError(f"selected tiles {sorted(bad)[:5]} are outside the {self.shape} tiles of the grid")

    @property
    def shape(self) -> tuple[int, int]:
        """(tile rows, tile cols)."""
        th, tw = self.tile_size
        return (-(-self.grid.height // th), -(-self.grid.width // tw))

    def __len__(self) -> int:
        if self.selected is not None:
            return len(self.units()) if self.merge_runs else len(self.selected)
        a, b = self.shape
        return a * b

    def is_selected(self, tile: Tile) -> bool:
        """Whether a pass over this tiling processes ``tile`` (every tile when nothing is selected)."""
        return self.selected is None or tuple(tile.index) in self.selected

    def selection_mask(self) -> np.ndarray:
        """bool (tile rows, tile cols): the tiles a pass processes."""
        m = np.ones(self.shape, bool)
        if self.selected is not None:
            m[:] = False
            for i, j in self.selected:
                m[i, j] = True
        return m

    def all_tiles(self) -> Iterator[Tile]:
        """Every tile of the grid, selected or not, row by row."""
        a, b = self.shape
        for i in range(a):
            for j in range(b):
                yield self.tile(i, j)

    def tile(self, i: int, j: int) -> Tile:
        th, tw = self.tile_size
        H, W = self.grid.shape
        r0, c0 = i * th, j * tw
        h, w = min(th, H - r0), min(tw, W - c0)
        o = self.overlap
        R0, C0 = max(0, r0 - o), max(0, c0 - o)
        R1, C1 = min(H, r0 + h + o), min(W, c0 + w + o)
        return Tile((i, j), (r0, c0, h, w), (R0, C0, R1 - R0, C1 - C0))

    def units(self) -> list[Tile]:
        """The units a pass processes: the selected tiles, or their runs along tile rows (``merge_runs``)."""
        if self.selected is None or not self.merge_runs:
            return [t for t in self.all_tiles() if self.selected is None or t.index in self.selected]
        th, tw = self.tile_size
        H, W = self.grid.shape
        o = self.overlap
        out = []
        for i in range(self.shape[0]):
            j = 0
            while j < self.shape[1]:
                if (i, j) not in self.selected:
                    j += 1
                    continue
                j0 = j
                while j < self.shape[1] and (i, j) in self.selected:
                    j += 1
                r0, c0 = i * th, j0 * tw
                h, w = min(th, H - r0), min(j * tw, W) - c0
                R0, C0 = max(0, r0 - o), max(0, c0 - o)
                R1, C1 = min(H, r0 + h + o), min(W, c0 + w + o)
                out.append(Tile((i, j0), (r0, c0, h, w), (R0, C0, R1 - R0, C1 - C0)))
        return out

    def __iter__(self) -> Iterator[Tile]:
        yield from self.units()

    def units_in(self, window: tuple[int, int, int, int]) -> list[Tile]:
        """Processed units whose core intersects ``window`` (row0, col0, height, width)."""
        r0, c0, h, w = window
        if self.selected is None or not self.merge_runs:
            return [t for t in self.tiles_in(window) if self.is_selected(t)]
        return [
            t
            for t in self.units()
            if t.core[0] < r0 + h and r0 < t.core[0] + t.core[2] and t.core[1] < c0 + w and c0 < t.core[1] + t.core[3]
        ]

    def tiles_in(self, window: tuple[int, int, int, int]) -> Iterator[Tile]:
        """Tiles whose core intersects ``window`` (row0, col0, height, width), selected or not."""
        th, tw = self.tile_size
        r0, c0, h, w = window
        if h <= 0 or w <= 0:
            return
        for i in range(max(0, r0 // th), min(self.shape[0], (r0 + h - 1) // th + 1)):
            for j in range(max(0, c0 // tw), min(self.shape[1], (c0 + w - 1) // tw + 1)):
                yield self.tile(i, j)

    def with_overlap(self, overlap: int) -> "TileGrid":
        return TileGrid(self.grid, self.tile_size, int(overlap), self.selected, self.merge_runs)

    def with_selection(self, selected, merge_runs: bool = False) -> "TileGrid":
        """The same tiling restricted to ``selected`` (bool (tile rows, tile cols) or (i, j) pairs; None: all)."""
        return TileGrid(self.grid, self.tile_size, self.overlap, selected, merge_runs)

    def read_grid(self, tile: Tile) -> AOIGrid:
        """The AOI grid of a tile's read window."""
        r0, c0, h, w = tile.read
        return self.grid.subgrid(r0, c0, h, w)

    def core_grid(self, tile: Tile) -> AOIGrid:
        r0, c0, h, w = tile.core
        return self.grid.subgrid(r0, c0, h, w)
