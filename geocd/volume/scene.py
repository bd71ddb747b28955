"""The volumetric scene: a regular grid of blocks, each a shallow octree, in a local ENU frame.

Layout (flat numpy arrays, one entry per octree *node*, inner nodes included)
----------------------------------------------------------------------------
* ``block_root[bx, by, bz]`` (int32): node index of each block's root cell.
* ``child[node]`` (int32): index of the first of the node's 8 children (they are
  contiguous, octant ``k = ix | iy << 1 | iz << 2``), or ``-1`` for a leaf.
* ``level[node]`` (uint8): depth below the block root (0 = root, the cell edge is
  ``block_size_m / 2**level``).
* ``alpha[node]`` (float32): occlusion density α, 1/m (Crispell et al. §III).
* ``app[node, bin, mode, field]`` (float32): per illumination bin, a mixture of
  up to 3 Gaussians over intensities scaled to [0, 1]; fields are
  ``(mean, sigma, weight, n_obs)`` (:data:`MU`, :data:`SIGMA`, :data:`WEIGHT`,
  :data:`NOBS`); a bin whose weights are all 0 has seen nothing yet and is
  treated as a uniform density.

Only leaves carry live values; an inner node keeps the values it had when it was
split (cheap, and it keeps refinement a pure append). A *fixed grid* is the same
structure with every block refined to ``max_depth`` and refinement switched off,
so the octree/grid comparison uses one code path.

Illumination bins (Pollard et al.): each image's sun position selects the bin of
the nearest known sun direction within ``sun_bin_tolerance_deg``; a new bin is
opened otherwise (up to ``n_bins``).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from ..errors import ConfigError, CRSError, NoOverlapError
from ..geodesy import AOIGrid, LocalFrame, as_crs

MU, SIGMA, WEIGHT, NOBS = 0, 1, 2, 3
N_MODES = 3
N_FIELDS = 4


@dataclass(frozen=True)
class VolumeParams:
    """Parameters of the model and of its online update.

    Attributes
    ----------
    p_init : float
        Prior occlusion probability of one finest cell; α starts at
        ``-ln(1 - p_init) / finest_cell_m`` everywhere (the density does not
        depend on the cell size).
    refine : bool
        Adaptive refinement (eq. 26) after each update; False with
        ``init_depth == max_depth`` gives the fixed-grid model.
    coarsen : bool
        With ``refine``, merge sibling leaves back into their parent after each
        update when none would be split at the parent's size with half the
        threshold (:func:`geocd.volume.refine.coarsen_model`; not in the paper).
    refine_threshold : float
        Split a leaf when ``1 - exp(-ℓ_max α) > refine_threshold`` with
        ``ℓ_max`` the cell diagonal.
    alpha_min, alpha_max : float
        Clamps of α (1/m) after each update.
    sigma_init, sigma_min : float
        Standard deviation of a new mixture mode, and its floor (intensity in [0, 1]).
    match_sigmas : float
        An observation matches a mode within this many standard deviations.
    min_obs_weight : float
        Appearance is updated only where the mean visibility of the cell's
        segments exceeds this.
    appearance_prior_weight : float
        Weight ``w0`` of the uniform density blended into each cell's mixture:
        ``(N p_mog + w0) / (N + w0)`` with ``N`` the cell's total visibility-weighted
        observations (1 ≈ one clear view); 0 gives the plain mixture.
    n_bins : int
        Number of illumination bins (sun positions) the model can hold.
    sun_bin_tolerance_deg : float
        A sun direction within this angle of a bin's joins it.
    """

    p_init: float = 0.01
    refine: bool = True
    coarsen: bool = True
    refine_threshold: float = 0.3
    alpha_min: float = 1e-4
    alpha_max: float = 200.0
    sigma_init: float = 0.1
    sigma_min: float = 0.03
    match_sigmas: float = 2.5
    min_obs_weight: float = 1e-3
    appearance_prior_weight: float = 1.0
    n_bins: int = 2
    sun_bin_tolerance_deg: float = 12.0

    def __post_init__(self) -> None:
        if not (0.0 < self.p_init < 1.0):
            raise ConfigError(f"p_init must be in (0, 1), got {self.p_init}")
        if not (0.0 < self.refine_threshold < 1.0):
            raise ConfigError(f"refine_threshold must be in (0, 1), got {self.refine_threshold}")
        if not (0.0 < self.alpha_min < self.alpha_max):
            raise ConfigError(f"need 0 < alpha_min < alpha_max, got {self.alpha_min}, {self.alpha_max}")
        if not (0.0 < self.sigma_min <= self.sigma_init):
            raise ConfigError(f"need 0 < sigma_min <= sigma_init, got {self.sigma_min}, {self.sigma_init}")
        if not (1 <= int(self.n_bins) <= 16):
            raise ConfigError(f"n_bins must be between 1 and 16, got {self.n_bins}")

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "VolumeParams":
        known = {f for f in cls.__dataclass_fields__}
        return cls(**{k: v for k, v in d.items() if k in known})


@dataclass(frozen=True)
class VolumeGeometry:
    """Where the volume is: a box of ``n_blocks`` blocks in a local ENU frame.

    Attributes
    ----------
    frame : LocalFrame
        ENU origin (lon0, lat0 degrees, h0 ellipsoidal metres).
    origin_enu : (3,) float
        Lower (west, south, bottom) corner of the box, metres in ``frame``.
    block_size_m : float
        Edge of one block (a root octree cell).
    n_blocks : (3,) int
        Blocks along east, north, up.
    max_depth : int
        Octree levels below a block root; the finest cell edge is
        ``block_size_m / 2**max_depth``.
    crs : str
        CRS of the AOI grid the volume was built for (products are written in it).
    aoi_bounds : (4,) float
        (left, bottom, right, top) of that AOI in ``crs``.
    """

    frame: LocalFrame
    origin_enu: tuple[float, float, float]
    block_size_m: float
    n_blocks: tuple[int, int, int]
    max_depth: int
    crs: str
    aoi_bounds: tuple[float, float, float, float]

    def __post_init__(self) -> None:
        if not (self.block_size_m > 0):
            raise ConfigError(f"block size must be positive, got {self.block_size_m}")
        if not (0 <= int(self.max_depth) <= 6):
            raise ConfigError(f"max_depth must be between 0 and 6 (shallow octrees), got {self.max_depth}")
        if any(int(n) < 1 for n in self.n_blocks):
            raise ConfigError(f"the volume needs at least one block per axis, got {self.n_blocks}")
        object.__setattr__(self, "origin_enu", tuple(float(v) for v in self.origin_enu))
        object.__setattr__(self, "n_blocks", tuple(int(v) for v in self.n_blocks))
        object.__setattr__(self, "aoi_bounds", tuple(float(v) for v in self.aoi_bounds))

    @property
    def finest_cell_m(self) -> float:
        return self.block_size_m / (1 << self.max_depth)

    @property
    def box_lo(self) -> np.ndarray:
        return np.asarray(self.origin_enu, dtype=np.float64)

    @property
    def box_hi(self) -> np.ndarray:
        return self.box_lo + self.block_size_m * np.asarray(self.n_blocks, dtype=np.float64)

    @property
    def z_range_enu(self) -> tuple[float, float]:
        return float(self.box_lo[2]), float(self.box_hi[2])

    def geo_array(self) -> np.ndarray:
        """The float64[8] the kernels take: x0, y0, z0, block size, nbx, nby, nbz, max depth."""
        x0, y0, z0 = self.origin_enu
        nx, ny, nz = self.n_blocks
        return np.array([x0, y0, z0, self.block_size_m, nx, ny, nz, self.max_depth], dtype=np.float64)

    def finest_shape(self) -> tuple[int, int, int]:
        k = 1 << self.max_depth
        return (self.n_blocks[0] * k, self.n_blocks[1] * k, self.n_blocks[2] * k)

    def aoi_grid(self, posting_m: float) -> AOIGrid:
        """A north-up grid over the AOI bounds in the model's CRS."""
        l, b, r, t = self.aoi_bounds
        return AOIGrid.from_bounds(l, b, r, t, posting_m, self.crs)

    def check_crs(self, crs: Any, what: str = "the input") -> None:
        """Raise :class:`CRSError` when ``crs`` is not the CRS the model was built in."""
        c = as_crs(crs)
        mine = as_crs(self.crs)
        if not c.equals(mine, ignore_axis_order=True):
            raise CRSError(
                f"{what} is in {c.to_string()} but the volume model was built in {mine.to_string()} "
                f"(ENU origin lon {self.frame.lon0:.6f}, lat {self.frame.lat0:.6f}); use the model built for this "
                "AOI, or reproject the input to the model's CRS"
            )

    def to_dict(self) -> dict:
        return {
            "frame": self.frame.to_dict(),
            "origin_enu": list(self.origin_enu),
            "block_size_m": self.block_size_m,
            "n_blocks": list(self.n_blocks),
            "max_depth": int(self.max_depth),
            "crs": self.crs,
            "aoi_bounds": list(self.aoi_bounds),
        }

    @classmethod
    def from_dict(cls, d: dict) -> "VolumeGeometry":
        f = d["frame"]
        return cls(
            LocalFrame(float(f["lon0"]), float(f["lat0"]), float(f.get("h0", 0.0))),
            tuple(d["origin_enu"]),
            float(d["block_size_m"]),
            tuple(d["n_blocks"]),
            int(d["max_depth"]),
            str(d["crs"]),
            tuple(d["aoi_bounds"]),
        )


def geometry_for_aoi(
    grid_or_bounds: Any,
    crs: Any = None,
    *,
    z_min_m: float,
    z_max_m: float,
    finest_cell_m: float = 0.5,
    max_depth: int = 4,
    frame: LocalFrame | None = None,
) -> VolumeGeometry:
    """The volume box covering an AOI between two ellipsoidal heights.

    Parameters
    ----------
    grid_or_bounds : AOIGrid or (left, bottom, right, top)
        The AOI; with bounds, give ``crs``.
    z_min_m, z_max_m : float
        Ellipsoidal heights (m) the volume must span (e.g. DEM minimum − 2 m and
        DEM maximum + the tallest expected building).
    finest_cell_m : float
        Edge of the finest octree cell; a block is ``finest_cell_m * 2**max_depth``.
    frame : LocalFrame, optional
        ENU origin; default: the AOI centre at ``z_min_m``.
    """
    from ..geodesy import to_lonlat

    if isinstance(grid_or_bounds, AOIGrid):
        bounds = grid_or_bounds.bounds
        crs = grid_or_bounds.crs
    else:
        bounds = tuple(float(v) for v in grid_or_bounds)
        if crs is None:
            raise CRSError("give the CRS of the AOI bounds (crs=...)")
    crs = as_crs(crs)
    if not (z_max_m > z_min_m):
        raise ConfigError(f"the volume needs z_max_m > z_min_m, got {z_min_m}, {z_max_m}")
    if not (finest_cell_m > 0):
        raise ConfigError(f"finest_cell_m must be positive, got {finest_cell_m}")
    l, b, r, t = bounds
    n = 9
    xs = np.concatenate([np.linspace(l, r, n), np.full(n, r), np.linspace(r, l, n), np.full(n, l)])
    ys = np.concatenate([np.full(n, t), np.linspace(t, b, n), np.full(n, b), np.linspace(b, t, n)])
    lon, lat = to_lonlat(xs, ys, crs)
    if frame is None:
        clon, clat = to_lonlat(0.5 * (l + r), 0.5 * (b + t), crs)
        frame = LocalFrame(float(clon), float(clat), float(z_min_m))
    e, nn, _ = frame.to_enu(lon, lat, np.full(lon.shape, frame.h0))
    bs = finest_cell_m * (1 << max_depth)
    lo = np.array([e.min(), nn.min(), z_min_m - frame.h0 - 0.5 * finest_cell_m])
    hi = np.array([e.max(), nn.max(), z_max_m - frame.h0])
    # snap the box to whole finest cells, then to whole blocks
    lo = np.floor(lo / finest_cell_m) * finest_cell_m
    nb = np.maximum(1, np.ceil((hi - lo) / bs - 1e-9)).astype(int)
    return VolumeGeometry(
        frame,
        tuple(lo),
        bs,
        tuple(int(v) for v in nb),
        int(max_depth),
        crs.to_string() if crs.to_epsg() else crs.to_wkt(),
        tuple(bounds),
    )


@dataclass
class VolumeModel:
    """Occlusion density + appearance on a grid of shallow octrees (see the module docstring).

    Build one with :meth:`create`; update it with :func:`geocd.volume.update_model`.
    """

    geometry: VolumeGeometry
    params: VolumeParams
    block_root: np.ndarray
    child: np.ndarray
    level: np.ndarray
    alpha: np.ndarray
    app: np.ndarray
    sun_bins: list = field(default_factory=list)  # [[azimuth_deg, elevation_deg, n_images], ...]
    history: list = field(default_factory=list)  # one dict per update

    # --- construction ------------------------------------------------------------------------
    @classmethod
    def create(
        cls, geometry: VolumeGeometry, params: VolumeParams | None = None, *, init_depth: int = 0
    ) -> "VolumeModel":
        """A fresh model: every block refined to ``init_depth`` levels, α at its prior.

        ``init_depth = geometry.max_depth`` with ``params.refine = False`` is the fixed grid.
        """
        params = params or VolumeParams()
        d = int(init_depth)
        if not (0 <= d <= geometry.max_depth):
            raise ConfigError(f"init_depth must be between 0 and max_depth={geometry.max_depth}, got {init_depth}")
        nb = int(np.prod(geometry.n_blocks))
        per_block = sum(8**k for k in range(d + 1))
        n = nb * per_block
        est_bytes = n * node_bytes(params.n_bins)
        if est_bytes > 12 * 2**30:
            raise ConfigError(
                f"a volume of {n:,} cells needs {est_bytes / 2**30:.1f} GiB; use a coarser init_depth, a smaller "
                "AOI or a larger finest cell"
            )
        child = np.full(n, -1, dtype=np.int32)
        level = np.zeros(n, dtype=np.uint8)
        # per block, nodes in breadth-first order: root, its 8 children, their 64 children, ...
        base = np.arange(nb, dtype=np.int64) * per_block
        for k in range(d + 1):
            cnt = 8**k
            first = sum(8**j for j in range(k))
            idx = base[:, None] + first + np.arange(cnt)[None, :]
            level[idx.ravel()] = k
            if k < d:
                nxt = sum(8**j for j in range(k + 1))
                child[idx.ravel()] = (base[:, None] + nxt + 8 * np.arange(cnt)[None, :]).ravel()
        block_root = base.astype(np.int32).reshape(geometry.n_blocks)
        a0 = -math.log1p(-params.p_init) / geometry.finest_cell_m
        alpha = np.full(n, a0, dtype=np.float32)
        app = np.zeros((n, int(params.n_bins), N_MODES, N_FIELDS), dtype=np.float32)
        app[..., SIGMA] = params.sigma_init
        return cls(geometry, params, block_root, child, level, alpha, app, [], [])

    # --- sizes -------------------------------------------------------------------------------------
    @property
    def n_nodes(self) -> int:
        return int(self.child.size)

    @property
    def n_leaves(self) -> int:
        return int(np.count_nonzero(self.child < 0))

    def leaf_mask(self) -> np.ndarray:
        return self.child < 0

    def nbytes(self) -> int:
        """Bytes of the model's arrays (what is held in memory and written to disk)."""
        return int(self.block_root.nbytes + self.child.nbytes + self.level.nbytes + self.alpha.nbytes + self.app.nbytes)

    def fixed_grid_nbytes(self) -> int:
        """Bytes a plain regular grid at the finest level would need (leaf data only, no tree)."""
        n = int(np.prod(self.geometry.finest_shape()))
        return n * (4 + self.app.shape[1] * N_MODES * N_FIELDS * 4)

    def size_report(self) -> dict:
        """Cell counts and memory, with the fixed-grid equivalent at the same finest resolution."""
        lv = self.level[self.child < 0]
        counts = np.bincount(lv, minlength=self.geometry.max_depth + 1)
        fg = self.fixed_grid_nbytes()
        return {
            "nodes": self.n_nodes,
            "leaves": self.n_leaves,
            "leaves_per_level": {int(k): int(v) for k, v in enumerate(counts)},
            "finest_cell_m": self.geometry.finest_cell_m,
            "block_size_m": self.geometry.block_size_m,
            "n_blocks": list(self.geometry.n_blocks),
            "bytes": self.nbytes(),
            "fixed_grid_cells": int(np.prod(self.geometry.finest_shape())),
            "fixed_grid_bytes": fg,
            "fixed_grid_ratio": fg / max(self.nbytes(), 1),
        }

    # --- illumination bins -----------------------------------------------------------------------
    def sun_bin(self, sun: tuple[float, float] | None, *, create: bool) -> int:
        """Index of the illumination bin of a sun position (azimuth, elevation degrees).

        ``sun=None`` means "one illumination for every image" (bin 0). With
        ``create``, a sun far from every bin opens a new one; without it the
        nearest bin is returned (``-1`` if there is none).
        """
        if sun is None:
            if not self.sun_bins:
                if not create:
                    return -1
                self.sun_bins.append([float("nan"), float("nan"), 0])
            return 0
        az, el = float(sun[0]), float(sun[1])
        if not (np.isfinite(az) and np.isfinite(el)):
            raise ConfigError(f"sun position must be finite (azimuth, elevation degrees), got {sun}")
        best, best_ang = -1, 1e9
        for i, (baz, bel, _n) in enumerate(self.sun_bins):
            if not np.isfinite(baz):
                ang = 0.0  # a model trained without sun positions: one bin for all
            else:
                ang = _angle_deg(az, el, baz, bel)
            if ang < best_ang:
                best, best_ang = i, ang
        if best >= 0 and (best_ang <= self.params.sun_bin_tolerance_deg or not create):
            return best
        if not create:
            return -1
        if len(self.sun_bins) >= self.params.n_bins:
            raise ConfigError(
                f"the sun position (az {az:.1f}°, el {el:.1f}°) is {best_ang:.1f}° from every illumination bin and all "
                f"{self.params.n_bins} bins are used; build the model with more bins (n_bins) or a larger "
                "sun_bin_tolerance_deg"
            )
        self.sun_bins.append([az, el, 0])
        return len(self.sun_bins) - 1

    def sun_bin_distance_deg(self, sun: tuple[float, float] | None, b: int) -> float:
        if sun is None or b < 0 or not np.isfinite(self.sun_bins[b][0]):
            return 0.0
        return _angle_deg(float(sun[0]), float(sun[1]), self.sun_bins[b][0], self.sun_bins[b][1])

    def trained_bins(self) -> list[int]:
        return [i for i, b in enumerate(self.sun_bins) if b[2] > 0]

    def copy(self) -> "VolumeModel":
        return VolumeModel(
            self.geometry,
            self.params,
            self.block_root.copy(),
            self.child.copy(),
            self.level.copy(),
            self.alpha.copy(),
            self.app.copy(),
            [list(b) for b in self.sun_bins],
            [dict(h) for h in self.history],
        )

    def check_overlap(self, lon: np.ndarray, lat: np.ndarray, what: str) -> None:
        """Raise :class:`NoOverlapError` when no point falls in the volume's footprint."""
        e, n, _ = self.geometry.frame.to_enu(lon, lat, np.full(np.shape(lon), self.geometry.frame.h0))
        lo, hi = self.geometry.box_lo, self.geometry.box_hi
        inside = (e >= lo[0]) & (e <= hi[0]) & (n >= lo[1]) & (n <= hi[1])
        if not np.any(inside):
            raise NoOverlapError(f"{what} does not overlap the volume model's AOI; check the image and the model")


def node_bytes(n_bins: int) -> int:
    """Bytes per octree node: child (int32) + level (uint8) + α (float32) + appearance."""
    return 4 + 1 + 4 + int(n_bins) * N_MODES * N_FIELDS * 4


def _angle_deg(az1: float, el1: float, az2: float, el2: float) -> float:
    def v(az, el):
        a, e = math.radians(az), math.radians(el)
        return np.array([math.sin(a) * math.cos(e), math.cos(a) * math.cos(e), math.sin(e)])

    c = float(np.clip(v(az1, el1) @ v(az2, el2), -1.0, 1.0))
    return math.degrees(math.acos(c))
