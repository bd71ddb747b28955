"""The object-space height sweep: reusable warping machinery.

A :class:`PlaneSweep` walks the AOI grid tile by tile (tiles with margins, so
memory stays bounded for any AOI) and, for every horizontal plane ``k`` of
height ``origin + k·step`` that the tile's cells search, warps every image onto
the tile's cells (bilinear). Any per-height cost can plug in::

    sweep = PlaneSweep(grid, chips, cameras, search, tile_size=256, margin=2)
    for tile in sweep.tiles():
        kmin, kmax = sweep.kmin(tile), sweep.kmax(tile)   # each cell's own plane range
        for sl in sweep.slices(tile):        # sl.k, sl.height_m, sl.stack (N, h, w)
            cost_k = my_cost(sl.stack)       # NaN in the stack = outside the image / nodata
            ...
        keep results on tile.core (= tile.inner inside the tile's arrays)

For each camera ``camera.ground_projector(x, y, grid.crs)`` is built once per
tile and only ``.project(h)`` runs per height, so RPC and frame cameras go
through the same code (never a branch on the camera kind). The stack array is
reused between slices: copy what you keep.

Heights are ellipsoidal metres. All cells share the planes (fronto-parallel
windows never mix heights) but each cell searches only its own range
``[lo_m, hi_m]`` (:class:`HeightSearch`), e.g. a prior DEM ± margin, and a tile
sweeps only the planes its cells need.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Iterator, Sequence

import numpy as np

from ..camera import Camera
from ..errors import EmptyDataError, GridError
from ..geodesy import AOIGrid
from ..progress import Progress, ensure_progress
from . import _kernels as K
from .photometry import box_blur_nan, estimate_noise_sigma, local_normalize, to_gray


# ---------------------------------------------------------------------------------------------
# images
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ImageChip:
    """A normalized gray image window ready for warping.

    Attributes
    ----------
    data : float32 (rows, cols)
        Locally normalized gray levels (0–255 scale), NaN where invalid.
    col0, row0 : int
        Position of ``data[0, 0]`` in the full image the camera describes (pixels),
        so camera coordinates ``(col, row)`` sample ``data`` at
        ``(col + shift[0] − col0, row + shift[1] − row0)``.
    name : str
    noise_sigma : float
        Noise standard deviation on the normalized scale (estimated).
    shift : (float, float)
        Pointing correction added to the camera's image coordinates (pixels), e.g. the
        relative pointing error of a pair (:func:`geocd.stereo.pointing.relative_pointing`).
    """

    data: np.ndarray
    col0: int = 0
    row0: int = 0
    name: str = ""
    noise_sigma: float = float("nan")
    shift: tuple[float, float] = (0.0, 0.0)

    @property
    def origin(self) -> tuple[float, float]:
        """Camera coordinates of ``data``'s upper-left corner (``col0 − shift``, ``row0 − shift``)."""
        return (self.col0 - float(self.shift[0]), self.row0 - float(self.shift[1]))

    def shifted(self, dcol: float, drow: float) -> "ImageChip":
        """The chip with an extra pointing correction (pixels)."""
        return replace(self, shift=(float(self.shift[0]) + dcol, float(self.shift[1]) + drow))

    @property
    def shape(self) -> tuple[int, int]:
        return self.data.shape

    @property
    def box(self) -> tuple[int, int, int, int]:
        """(col0, row0, col1, row1) in full-image pixels (without the pointing shift)."""
        return (self.col0, self.row0, self.col0 + self.data.shape[1], self.row0 + self.data.shape[0])

    def warp(self, col: np.ndarray, row: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """Bilinear samples at full-image coordinates (pixel-corner convention); NaN outside/invalid."""
        c0, r0 = self.origin
        c = np.asarray(col, np.float64) - c0
        r = np.asarray(row, np.float64) - r0
        if c.ndim == 2 and out is not None:
            K.warp_bilinear(self.data, np.ascontiguousarray(c), np.ascontiguousarray(r), out)
            return out
        shape = c.shape
        o = np.empty((1, c.size), np.float32)
        K.warp_bilinear(self.data, np.ascontiguousarray(c.reshape(1, -1)), np.ascontiguousarray(r.reshape(1, -1)), o)
        o = o.reshape(shape)
        if out is not None:
            out[...] = o
            return out
        return o

    def blurred(self, size: int) -> "ImageChip":
        """The chip box-blurred over ``size`` pixels (anti-aliasing for a coarser grid)."""
        if size <= 1:
            return self
        return replace(self, data=box_blur_nan(self.data, int(size)))


def prepare_chip(
    data: np.ndarray,
    valid: np.ndarray | None = None,
    *,
    col0: int = 0,
    row0: int = 0,
    name: str = "",
    block_px: int = 256,
) -> ImageChip:
    """Gray, locally normalized chip from raw image data (any dtype, 1 or more bands).

    Parameters
    ----------
    data : (rows, cols) or (bands, rows, cols)
    valid : bool (rows, cols), optional
    col0, row0 : position of ``data`` in the full image (for windows read from a large image)

    Raises
    ------
    EmptyDataError
        When no pixel is valid.
    """
    g = to_gray(data, valid)
    if not np.isfinite(g).any():
        raise EmptyDataError(
            f"image {name or ''} is entirely nodata over the area to match; check its nodata "
            "value and that it covers the AOI"
        )
    norm = local_normalize(g, block_px=block_px)
    sigma = estimate_noise_sigma(norm)
    return ImageChip(np.ascontiguousarray(norm, np.float32), int(col0), int(row0), name, sigma)


# ---------------------------------------------------------------------------------------------
# height hypotheses
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class HeightSearch:
    """Horizontal height planes ``origin_m + k · step_m`` and the range each cell searches.

    Every cell is tested on the same planes (windows are fronto-parallel, so a
    window never mixes heights), but only for ``kmin ≤ k ≤ kmax`` — its own
    ``[lo_m, hi_m]``. A tile sweeps the indices its cells need, so the cost
    follows the local relief, not the whole scene's.

    Attributes
    ----------
    lo_m, hi_m : float64 (rows, cols), ellipsoidal metres (NaN = do not search)
    step_m : float
    origin_m : float, height of plane k = 0 (default: the lowest ``lo_m``)
    """

    lo_m: np.ndarray
    hi_m: np.ndarray
    step_m: float
    origin_m: float = float("nan")

    def __post_init__(self) -> None:
        if self.lo_m.shape != self.hi_m.shape:
            raise GridError("height search lo and hi must have the same shape")
        if not (self.step_m > 0 and math.isfinite(self.step_m)):
            raise GridError(f"height step must be positive, got {self.step_m}")
        if not math.isfinite(self.origin_m):
            lo = self.lo_m[np.isfinite(self.lo_m)]
            object.__setattr__(self, "origin_m", float(lo.min()) if lo.size else 0.0)

    @classmethod
    def uniform(cls, shape: tuple[int, int], lo_m: float, hi_m: float, step_m: float) -> "HeightSearch":
        return cls(np.full(shape, float(lo_m)), np.full(shape, float(hi_m)), float(step_m))

    @property
    def shape(self) -> tuple[int, int]:
        return self.lo_m.shape

    def kmin(self) -> np.ndarray:
        """int32 (rows, cols): first plane index of each cell."""
        ok = np.isfinite(self.lo_m) & np.isfinite(self.hi_m)
        k = np.ceil((np.where(ok, self.lo_m, self.origin_m) - self.origin_m) / self.step_m - 1e-9)
        return np.where(ok, k, 0).astype(np.int32)

    def kmax(self) -> np.ndarray:
        """int32 (rows, cols): last plane index of each cell (−1 where not searched)."""
        ok = np.isfinite(self.lo_m) & np.isfinite(self.hi_m)
        k = np.floor((np.where(ok, self.hi_m, self.origin_m) - self.origin_m) / self.step_m + 1e-9)
        k = np.maximum(k, self.kmin())
        return np.where(ok, k, -1).astype(np.int32)

    def n_planes(self) -> int:
        """Planes from the origin to the highest searched one."""
        return int(self.kmax().max()) + 1

    def height(self, k: int | float | np.ndarray) -> np.ndarray | float:
        """Height (m) of plane index ``k`` (fractional indices allowed)."""
        return self.origin_m + np.asarray(k, np.float64) * self.step_m


# ---------------------------------------------------------------------------------------------
# tiles
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Tile:
    """A tile of the grid: ``core`` cells (results) inside ``outer`` (core + margin, clipped).

    ``core`` and ``outer`` are (row slice, col slice) in the grid; ``inner`` is
    the core inside the outer window's arrays.
    """

    index: int
    count: int
    core: tuple[slice, slice]
    outer: tuple[slice, slice]
    inner: tuple[slice, slice]

    @property
    def outer_shape(self) -> tuple[int, int]:
        return (self.outer[0].stop - self.outer[0].start, self.outer[1].stop - self.outer[1].start)

    @property
    def core_cells(self) -> int:
        return (self.core[0].stop - self.core[0].start) * (self.core[1].stop - self.core[1].start)


def iter_tiles(shape: tuple[int, int], tile_size: int, margin: int) -> list[Tile]:
    """Tiles of ``tile_size`` cells with ``margin`` cells of context on each side."""
    H, W = shape
    rows = list(range(0, H, tile_size))
    cols = list(range(0, W, tile_size))
    out = []
    n = len(rows) * len(cols)
    for r0 in rows:
        for c0 in cols:
            r1, c1 = min(r0 + tile_size, H), min(c0 + tile_size, W)
            R0, C0 = max(r0 - margin, 0), max(c0 - margin, 0)
            R1, C1 = min(r1 + margin, H), min(c1 + margin, W)
            out.append(
                Tile(
                    len(out),
                    n,
                    (slice(r0, r1), slice(c0, c1)),
                    (slice(R0, R1), slice(C0, C1)),
                    (slice(r0 - R0, r1 - R0), slice(c0 - C0, c1 - C0)),
                )
            )
    return out


def _tile(index: int, count: int, shape: tuple[int, int], r0: int, r1: int, c0: int, c1: int, margin: int) -> Tile:
    H, W = shape
    R0, C0 = max(r0 - margin, 0), max(c0 - margin, 0)
    R1, C1 = min(r1 + margin, H), min(c1 + margin, W)
    return Tile(
        index,
        count,
        (slice(r0, r1), slice(c0, c1)),
        (slice(R0, R1), slice(C0, C1)),
        (slice(r0 - R0, r1 - R0), slice(c0 - C0, c1 - C0)),
    )


def adaptive_tiles(
    shape: tuple[int, int], tile_size: int, margin: int, kmin: np.ndarray, kmax: np.ndarray, min_size: int = 16
) -> list[Tile]:
    """Tiles of at most ``tile_size`` cells, split further where that cuts the planes swept.

    A tile sweeps every plane any of its cells needs (window sums need the neighbours at
    the same plane), so one cell with a wide range — a coarse match that failed, a steep
    slope — makes the whole tile sweep it: the work then grows with the AOI's relief, not
    with what each cell needs. A tile is cut in four (down to ``min_size`` cells) when its
    quarters' swept cells × planes, margins included, are under ¾ of its own.
    """
    H, W = shape
    ok = kmax >= 0

    def cost(r0: int, r1: int, c0: int, c1: int) -> float:
        m = ok[r0:r1, c0:c1]
        if not m.any():
            return 0.0
        planes = int(kmax[r0:r1, c0:c1][m].max()) - int(kmin[r0:r1, c0:c1][m].min()) + 1
        return float((min(r1 + margin, H) - max(r0 - margin, 0)) * (min(c1 + margin, W) - max(c0 - margin, 0)) * planes)

    boxes = []

    def visit(r0: int, r1: int, c0: int, c1: int) -> None:
        if r1 - r0 >= 2 * min_size and c1 - c0 >= 2 * min_size:
            rm, cm = (r0 + r1) // 2, (c0 + c1) // 2
            kids = [(r0, rm, c0, cm), (r0, rm, cm, c1), (rm, r1, c0, cm), (rm, r1, cm, c1)]
            if sum(cost(*k) for k in kids) < 0.75 * cost(r0, r1, c0, c1):
                for k in kids:
                    visit(*k)
                return
        boxes.append((r0, r1, c0, c1))

    for r0 in range(0, H, tile_size):
        for c0 in range(0, W, tile_size):
            visit(r0, min(r0 + tile_size, H), c0, min(c0 + tile_size, W))
    return [_tile(i, len(boxes), shape, *b, margin) for i, b in enumerate(boxes)]


@dataclass
class SweepSlice:
    """One height index of one tile: every image warped onto the tile's outer cells.

    Attributes
    ----------
    k : int, plane index
    height_m : float, the plane's ellipsoidal height (m)
    stack : float32 (N, h, w), image n warped onto the cells (NaN = outside / nodata);
        reused for the next slice — copy what you keep
    tile : Tile
    """

    k: int
    height_m: float
    stack: np.ndarray
    tile: Tile


class PlaneSweep:
    """Warp N images onto an AOI grid for every height hypothesis, tile by tile.

    Parameters
    ----------
    grid : AOIGrid
    chips : sequence of ImageChip (normalized images)
    cameras : sequence of Camera, one per chip
    search : HeightSearch on ``grid``
    tile_size : int, tile side in cells
    margin : int, context cells around each tile (e.g. the window radius)
    interp_tol_px : float
        Cameras are evaluated exactly every few planes and projections are
        interpolated linearly in between when that stays within this many pixels
        (checked per tile at both ends of its range; 0 = project every plane).
    lonlat : (lon, lat) arrays of the grid's cell centres, optional
        Computed once here when not given (one CRS transform for the whole sweep).
    adaptive : bool
        Split tiles where their cells' height ranges differ (:func:`adaptive_tiles`), so the
        planes swept follow each cell's own range (default); False: a regular grid of tiles.
    """

    def __init__(
        self,
        grid: AOIGrid,
        chips: Sequence[ImageChip],
        cameras: Sequence[Camera],
        search: HeightSearch,
        *,
        tile_size: int = 256,
        margin: int = 0,
        interp_tol_px: float = 0.01,
        lonlat: tuple[np.ndarray, np.ndarray] | None = None,
        adaptive: bool = True,
    ):
        if len(chips) != len(cameras) or not chips:
            raise ValueError("PlaneSweep needs one camera per image chip, and at least one")
        if search.shape != grid.shape:
            raise GridError(f"height search shape {search.shape} differs from the grid {grid.shape}")
        self.grid = grid
        self.chips = list(chips)
        self.cameras = list(cameras)
        self.search = search
        self.tile_size = int(tile_size)
        self.margin = int(margin)
        self.interp_tol_px = float(interp_tol_px)
        self._kmin = search.kmin()
        self._kmax = search.kmax()
        self._tiles = (
            adaptive_tiles(grid.shape, self.tile_size, self.margin, self._kmin, self._kmax)
            if adaptive
            else iter_tiles(grid.shape, self.tile_size, self.margin)
        )
        if lonlat is None:
            lonlat = grid.lonlat()
        if lonlat[0].shape != grid.shape:
            raise GridError(f"lon/lat arrays {lonlat[0].shape} do not match the grid {grid.shape}")
        self._lonlat = lonlat

    def tiles(self) -> list[Tile]:
        return list(self._tiles)

    def kmin(self, tile: Tile) -> np.ndarray:
        """int32 first plane index of the tile's outer cells."""
        return np.ascontiguousarray(self._kmin[tile.outer])

    def kmax(self, tile: Tile) -> np.ndarray:
        """int32 last plane index of the tile's outer cells (−1: not searched)."""
        return np.ascontiguousarray(self._kmax[tile.outer])

    def k_range(self, tile: Tile) -> tuple[int, int]:
        """[start, stop) of the plane indices the tile's core cells need (empty when none)."""
        kmax = self._kmax[tile.core]
        ok = kmax >= 0
        if not ok.any():
            return (0, 0)
        return int(self._kmin[tile.core][ok].min()), int(kmax[ok].max()) + 1

    def n_evaluations(self) -> int:
        """Cell × plane evaluations of the whole sweep (core cells, for benchmarks)."""
        n = 0
        for t in self._tiles:
            k0, k1 = self.k_range(t)
            n += t.core_cells * max(k1 - k0, 0)
        return int(n)

    def projectors(self, tile: Tile) -> list:
        """Ground projectors of the tile's outer cell centres, one per camera."""
        lon, lat = (a[tile.outer] for a in self._lonlat)
        return [cam.ground_projector(lon, lat, None) for cam in self.cameras]

    def interval(self, projs: list, k0: int, k1: int) -> int:
        """Planes between exact projections so linear interpolation errs < interp_tol_px."""
        if self.interp_tol_px <= 0 or k1 - k0 < 3:
            return 1
        for m in (16, 8, 4, 2):
            if 2 * m > k1 - k0 + m:
                continue
            ok = True
            for ka in (k0, max(k0, k1 - 1 - m)):
                ha, hm, hb = (float(self.search.height(ka + d)) for d in (0, m / 2, m))
                for pr in projs:
                    ca, ra = pr.project(ha)
                    cm, rm = pr.project(hm)
                    cb, rb = pr.project(hb)
                    dev = np.abs(np.concatenate([np.ravel(0.5 * (ca + cb) - cm), np.ravel(0.5 * (ra + rb) - rm)]))
                    dev = dev[np.isfinite(dev)]
                    err = float(dev.max()) if dev.size else 0.0  # nowhere in an image: nothing to interpolate
                    if not err < self.interp_tol_px:
                        ok = False
                        break
                if not ok:
                    break
            if ok:
                return m
        return 1

    def slices(self, tile: Tile, k_range: tuple[int, int] | None = None) -> Iterator[SweepSlice]:
        """Yield the tile's warped stack for each plane index (default: :meth:`k_range`)."""
        projs = self.projectors(tile)
        k0, k1 = k_range if k_range is not None else self.k_range(tile)
        stack = np.empty((len(self.chips), *tile.outer_shape), np.float32)
        m = self.interval(projs, k0, k1)
        knots: dict[int, list] = {}

        def exact(kk: int) -> list:
            if kk not in knots:
                h = float(self.search.height(kk))
                knots[kk] = [tuple(np.ascontiguousarray(v, np.float64) for v in pr.project(h)) for pr in projs]
                for old in [q for q in knots if q < kk - m]:
                    del knots[old]
            return knots[kk]

        for k in range(k0, k1):
            ka = k0 + ((k - k0) // m) * m
            t = (k - ka) / m
            A = exact(ka)
            B = exact(ka + m) if m > 1 else A
            for n, chip in enumerate(self.chips):
                c0, r0 = chip.origin
                K.warp_bilinear_lerp(chip.data, A[n][0], A[n][1], B[n][0], B[n][1], t, c0, r0, stack[n])
            yield SweepSlice(k, float(self.search.height(k)), stack, tile)

    def warp_at(self, height_m: np.ndarray) -> np.ndarray:
        """Every image warped onto the whole grid at given per-cell heights: float32 (N, rows, cols)."""
        lon, lat = self._lonlat
        out = np.empty((len(self.chips), *self.grid.shape), np.float32)
        for n, (chip, cam) in enumerate(zip(self.chips, self.cameras)):
            col, row = cam.ground_projector(lon, lat, None).project(height_m)
            chip.warp(col, row, out=out[n])
        return out


def window_mean(x: np.ndarray, radius: int) -> tuple[np.ndarray, np.ndarray]:
    """Mean of the finite values of ``x`` over ``(2·radius+1)²`` windows and their count.

    O(cells) whatever the window (running sums, numba): the building block of any
    per-height window cost plugged into a :class:`PlaneSweep` (e.g. the mean absolute
    difference of two warped images: ``window_mean(abs(a − b), 2)``).

    Returns
    -------
    mean : float64 (h, w), NaN where the window holds no finite value
    count : float64 (h, w)
    """
    a = np.ascontiguousarray(x)
    if a.dtype not in (np.float32, np.float64):
        a = a.astype(np.float64)
    out = np.empty(a.shape)
    cnt = np.empty(a.shape)
    K.box_mean(a, int(radius), out, cnt, np.empty((2, *a.shape)))
    return out, cnt


def sweep_progress(progress: Progress | None, tile: Tile, k: int, n_k: int, prefix: str = "") -> None:
    """Report the fraction of a sweep done (between heights and tiles)."""
    p = ensure_progress(progress)
    frac = (tile.index + (k / max(n_k, 1))) / max(tile.count, 1)
    p(frac, f"{prefix}tile {tile.index + 1}/{tile.count} height {k}/{n_k}")


# ---------------------------------------------------------------------------------------------
# geometry on the grid
# ---------------------------------------------------------------------------------------------
def sample_cells(shape: tuple[int, int], n: int = 24) -> tuple[np.ndarray, np.ndarray]:
    """(rows, cols) of about n×n cells spread over a grid, borders included."""
    H, W = shape
    r = np.unique(np.linspace(0, H - 1, min(n, H)).round().astype(int))
    c = np.unique(np.linspace(0, W - 1, min(n, W)).round().astype(int))
    R, C = np.meshgrid(r, c, indexing="ij")
    return R.ravel(), C.ravel()


def image_sampling_px_per_m(
    camera: Camera, grid: AOIGrid, rows: np.ndarray, cols: np.ndarray, height_m: np.ndarray | float, d_m: float = 1.0
) -> np.ndarray:
    """Image pixels per ground metre at grid cells: sqrt(|det ∂(col,row)/∂(x,y)|) (x, y metres)."""
    x, y = grid.xy(rows, cols)
    h = np.broadcast_to(np.asarray(height_m, float), x.shape)
    pr = camera.ground_projector(np.concatenate([x, x + d_m, x]), np.concatenate([y, y, y + d_m]), grid.crs)
    c, r = pr.project(np.concatenate([h, h, h]))
    n = x.size
    dcx, drx = (c[n : 2 * n] - c[:n]) / d_m, (r[n : 2 * n] - r[:n]) / d_m
    dcy, dry = (c[2 * n :] - c[:n]) / d_m, (r[2 * n :] - r[:n]) / d_m
    return np.sqrt(np.abs(dcx * dry - dcy * drx))


def grid_metres_per_unit(grid: AOIGrid) -> float:
    """Metres per CRS unit of the grid (1 for projected CRSs in metres)."""
    try:
        u = grid.crs.axis_info[0].unit_conversion_factor
        return float(u) if u else 1.0
    except (IndexError, AttributeError):  # pragma: no cover
        return 1.0


def chip_valid_at(chip: ImageChip, col: np.ndarray, row: np.ndarray) -> np.ndarray:
    """Whether full-image points fall on valid pixels of a chip (bilinear support)."""
    v = chip.warp(col, row)
    return np.isfinite(v)


def coarse_grid(grid: AOIGrid, factor: int) -> AOIGrid:
    """The grid ``factor`` times coarser, aligned on the same upper-left corner."""
    from affine import Affine

    if factor == 1:
        return grid
    return AOIGrid(grid.crs, grid.transform @ Affine.scale(factor), -(-grid.width // factor), -(-grid.height // factor))


def upsample_nearest(a: np.ndarray, factor: int, shape: tuple[int, int]) -> np.ndarray:
    """Coarse-grid array → fine grid (each fine cell takes the coarse cell containing it)."""
    if factor == 1:
        return a
    r = np.minimum(np.arange(shape[0]) // factor, a.shape[0] - 1)
    c = np.minimum(np.arange(shape[1]) // factor, a.shape[1] - 1)
    return a[np.ix_(r, c)]
