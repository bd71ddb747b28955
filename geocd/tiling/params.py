"""How a scene is tiled and scheduled (:class:`TilingParams`), and the deterministic subsample of whole-scene
statistics (:func:`keep_cells`): shared by every tiled method."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import ConfigError
from ..params import ParamsMixin


# ------------------------------------------------------------------------------------------
# parameters
# ------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class TilingParams(ParamsMixin):
    """How a scene is tiled and scheduled (see :mod:`geocd.tiling`; where the defaults come from: docs/tiling.md).

    Attributes
    ----------
    tile_size : cells per tile side
    scheduler : sync | threads | processes | auto | a dask.distributed scheduler address
    n_workers, memory_limit : of the local cluster (default: one worker per core, 80 % of
        the machine's memory shared out)
    sample_cells : whole-scene statistics use every cell of grids up to this size, a fixed
        subsample of this many cells beyond
    exact_grid_cells : correlated sums on the whole grid up to this size, on a coarse grid beyond
    coarse_cells : size of that coarse grid
    patch_radius : cells around each co-registration fit cell gathered for its interpolation
    keep_work : keep the work folder (per-tile results) after a successful run
    """

    _kind = "tiling"

    tile_size: int = 1024
    scheduler: str = "auto"
    n_workers: int | None = None
    memory_limit: str | None = None
    sample_cells: int = 8_000_000
    exact_grid_cells: int = 4_000_000
    coarse_cells: int = 1_000_000
    patch_radius: int = 4
    keep_work: bool = False

    def __post_init__(self) -> None:
        if self.tile_size < 64:
            raise ConfigError(f"tile_size must be at least 64 cells, got {self.tile_size}")
        if self.sample_cells < 10_000 or self.coarse_cells < 1_000:
            raise ConfigError("sample_cells ≥ 10 000 and coarse_cells ≥ 1 000 are required")
        if self.patch_radius < 2:
            raise ConfigError("patch_radius must be ≥ 2")


# ------------------------------------------------------------------------------------------
# deterministic subsample
# ------------------------------------------------------------------------------------------
def keep_cells(rows: np.ndarray, cols: np.ndarray, width: int, fraction: float) -> np.ndarray:
    """bool: the cells a whole-scene statistic keeps at ``fraction`` (a hash of the cell index:
    the same cells whatever the tiling, scheduler or order)."""
    if fraction >= 1.0:
        return np.ones(np.shape(rows), bool)
    with np.errstate(over="ignore"):
        z = np.asarray(rows, np.uint64) * np.uint64(width) + np.asarray(cols, np.uint64) + np.uint64(0x9E3779B97F4A7C15)
        z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        z = z ^ (z >> np.uint64(31))
    return (z >> np.uint64(11)).astype(np.float64) * (1.0 / 9007199254740992.0) < fraction
