"""A small synthetic town with two epochs and known changes.

Coordinates
-----------
The scene lives in *map space*: ``(x, y)`` metres relative to an origin
``(E0, N0)`` in a WGS84 / UTM CRS, and ``z`` = **ellipsoidal** height in metres.
Walls stand along fixed ``(x, y)`` (true verticals), flat roofs sit at a constant
ellipsoidal height, and the truth rasters (DSM, DEM) are exact samples of the
surface on the UTM grid. :class:`SceneFrame` converts between map space,
geodetic coordinates and the local East-North-Up frame the physical satellite
model uses (a cubic polynomial ENU → map space, fitted once and checked to
< 1e-6 m over the scene box).

Content
-------
* terrain: a smooth height field (plane + Gaussian bumps) on a 0.5 m grid,
  rendered with bilinear interpolation (the truth DEM samples it exactly);
* streets: a rotated grid of straight roads with sidewalks and lane markings
  (albedo only, they follow the terrain);
* buildings: built from footprint polygons (unions of rectangles): houses with
  gabled roofs, flat-roofed blocks and L-shaped buildings, several storeys;
* trees: ellipsoidal crowns; cars: body + cabin boxes;
* two epochs A and B with known changes (:class:`Change`): new, demolished,
  raised and lowered buildings, moved cars, changed trees, and non-3-D changes
  (repainted roofs, vegetation season) that a method must *not* report.

Everything is drawn from one ``numpy.random.Generator`` seeded by
:attr:`TownParams.seed`, so the same parameters give the same town.
"""

from __future__ import annotations

import functools
import math
from dataclasses import asdict, dataclass, field, replace
from typing import Any

import numpy as np

from ..errors import ConfigError
from ..geodesy import LocalFrame, as_crs, from_lonlat, to_lonlat, utm_crs_for

# materials (shared with the kernels)
M_GRASS, M_ASPHALT, M_PAVEMENT, M_SOIL, M_ROOF_FLAT, M_ROOF_TILE, M_WALL, M_CAR, M_GLASS, M_TREE, M_MARKING = range(11)

#: kinds of renderable objects
K_POLY, K_ELLIPSOID = 0, 1
#: object classes (for hit ids and change classes)
C_TERRAIN, C_BUILDING, C_CAR, C_TREE = 0, 1, 2, 3

STOREY_M = 3.0

CHANGE_TYPES = ("new", "demolished", "raised", "lowered", "cars", "trees", "repaint", "season")


# ------------------------------------------------------------------------------------------
# frames
# ------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class SceneFrame:
    """Map space of the scene: UTM ``(E0 + x, N0 + y)`` and ellipsoidal ``z``.

    Parameters
    ----------
    epsg : int
        WGS84 / UTM zone EPSG code.
    e0, n0 : float
        Map coordinates of the scene origin (the AOI centre).
    lon0, lat0, h0 : float
        The same origin in geodetic coordinates (ENU origin of the sensors).
    """

    epsg: int
    e0: float
    n0: float
    lon0: float
    lat0: float
    h0: float

    @classmethod
    def at(cls, lon: float, lat: float, h0: float) -> "SceneFrame":
        crs = utm_crs_for(lon, lat)
        e, n = from_lonlat(lon, lat, crs)
        e0, n0 = float(np.round(e / 2.0) * 2.0), float(np.round(n / 2.0) * 2.0)  # even metres
        lon0, lat0 = to_lonlat(e0, n0, crs)
        return cls(int(crs.to_epsg()), e0, n0, float(lon0), float(lat0), float(h0))

    @property
    def crs(self):
        return as_crs(f"EPSG:{self.epsg}")

    @property
    def enu(self) -> LocalFrame:
        return LocalFrame(self.lon0, self.lat0, self.h0)

    def to_lonlat(self, x: Any, y: Any) -> tuple[np.ndarray, np.ndarray]:
        return to_lonlat(np.asarray(x, float) + self.e0, np.asarray(y, float) + self.n0, self.crs)

    def from_lonlat(self, lon: Any, lat: Any) -> tuple[np.ndarray, np.ndarray]:
        e, n = from_lonlat(lon, lat, self.crs)
        return e - self.e0, n - self.n0

    def enu_to_map_exact(self, e: Any, n: Any, u: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        lon, lat, h = self.enu.from_enu(e, n, u)
        x, y = self.from_lonlat(lon, lat)
        return x, y, h

    def map_to_enu(self, x: Any, y: Any, z: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        lon, lat = self.to_lonlat(x, y)
        return self.enu.to_enu(lon, lat, z)

    @functools.cached_property
    def _poly(self) -> tuple[np.ndarray, np.ndarray, float]:
        """Cubic polynomial ENU → map fitted over ±2 km, −300..+1000 m (coefficients, scale)."""
        s = 2000.0
        g = np.linspace(-1.0, 1.0, 9)
        e, n, u = (a.ravel() for a in np.meshgrid(g * s, g * s, np.linspace(-300.0, 1000.0, 7), indexing="ij"))
        x, y, z = self.enu_to_map_exact(e, n, u)
        T = _cubic_terms(e / s, n / s, u / s)
        coef, *_ = np.linalg.lstsq(T.T, np.stack([x, y, z - self.h0]).T, rcond=None)
        return coef, np.array([s]), float(self.h0)

    def enu_to_map(self, e: Any, n: Any, u: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """ENU → map space with the fitted cubic (error < 1e-6 m within ±2 km, −300..1000 m)."""
        coef, s, h0 = self._poly
        e, n, u = np.broadcast_arrays(np.asarray(e, float), np.asarray(n, float), np.asarray(u, float))
        T = _cubic_terms(e.ravel() / s[0], n.ravel() / s[0], u.ravel() / s[0])
        out = T.T @ coef
        return (out[:, 0].reshape(e.shape), out[:, 1].reshape(e.shape), (out[:, 2] + h0).reshape(e.shape))

    def to_dict(self) -> dict:
        return asdict(self)


def _cubic_terms(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    one = np.ones_like(a)
    return np.stack(
        [
            one,
            a,
            b,
            c,
            a * a,
            b * b,
            c * c,
            a * b,
            a * c,
            b * c,
            a**3,
            b**3,
            c**3,
            a * a * b,
            a * a * c,
            b * b * a,
            b * b * c,
            c * c * a,
            c * c * b,
            a * b * c,
        ]
    )


# ------------------------------------------------------------------------------------------
# scene content
# ------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Rect:
    """An oriented rectangle: centre (x, y), half length along ``angle``, half width across."""

    cx: float
    cy: float
    half_len: float
    half_wid: float
    angle: float  # radians, direction of the length axis from +x (east) counter-clockwise

    @property
    def axes(self) -> tuple[np.ndarray, np.ndarray]:
        u = np.array([math.cos(self.angle), math.sin(self.angle)])
        return u, np.array([-u[1], u[0]])

    def corners(self) -> np.ndarray:
        u, v = self.axes
        c = np.array([self.cx, self.cy])
        L, W = self.half_len, self.half_wid
        return np.array([c - L * u - W * v, c + L * u - W * v, c + L * u + W * v, c - L * u + W * v])

    def polygon(self):
        from shapely.geometry import Polygon

        return Polygon(self.corners())

    def ridge(self) -> tuple[np.ndarray, float, float]:
        """Gable geometry: unit vector along the ridge (the longer axis), half length along it, half span across."""
        u, v = self.axes
        if self.half_len >= self.half_wid:
            return u, self.half_len, self.half_wid
        return v, self.half_wid, self.half_len


@dataclass(frozen=True)
class Lot(Rect):
    """A building lot; ``front`` (±1) says on which side of its width axis the street is."""

    front: int = 1


@dataclass(frozen=True)
class Building:
    """A building extruded from its footprint (union of rectangles).

    ``ground_m`` is the ellipsoidal height of the ground floor (highest terrain
    under the footprint); eaves are ``storeys * STOREY_M`` above it; a gabled
    roof adds ``rise_m`` at the ridge (along each part's length axis).
    """

    building_id: int
    parts: tuple[Rect, ...]
    storeys: int
    roof: str  # "flat" | "gabled"
    rise_m: float
    ground_m: float
    roof_rgb: tuple[float, float, float]
    wall_rgb: tuple[float, float, float]
    kind: str = "house"  # house | block | lshape

    @property
    def eave_m(self) -> float:
        return self.ground_m + self.storeys * STOREY_M

    @property
    def top_m(self) -> float:
        return self.eave_m + (self.rise_m if self.roof == "gabled" else 0.0)

    def polygon(self):
        from shapely.ops import unary_union

        return unary_union([p.polygon() for p in self.parts])

    def corners_3d(self) -> np.ndarray:
        """(N, 3) roof corners (eave corners of every part, ridge ends of gabled parts) in map space."""
        pts = []
        for p in self.parts:
            for c in p.corners():
                pts.append([c[0], c[1], self.eave_m])
            if self.roof == "gabled":
                u, half, _ = p.ridge()
                for s in (-1, 1):
                    pts.append([p.cx + s * half * u[0], p.cy + s * half * u[1], self.top_m])
        return np.array(pts)


@dataclass(frozen=True)
class Car:
    car_id: int
    body: Rect
    ground_m: float
    rgb: tuple[float, float, float]
    height_m: float = 1.5


@dataclass(frozen=True)
class Tree:
    tree_id: int
    cx: float
    cy: float
    crown_r: float
    crown_rz: float
    trunk_m: float  # crown bottom above ground
    ground_m: float
    tint: float = 1.0

    @property
    def crown_cz(self) -> float:
        return self.ground_m + self.trunk_m + self.crown_rz

    @property
    def top_m(self) -> float:
        return self.crown_cz + self.crown_rz


@dataclass(frozen=True)
class Street:
    x0: float
    y0: float
    x1: float
    y1: float
    half_width: float
    sidewalk_m: float = 2.0


@dataclass(frozen=True)
class Patch:
    """A ground patch with its own material (soil of a demolished lot, a paved yard)."""

    rect: Rect
    material: int


@dataclass(frozen=True)
class Terrain:
    """Bilinear height field: node (i, j) at (x0 + j*step, y0 + i*step), ellipsoidal metres."""

    x0: float
    y0: float
    step: float
    height_m: np.ndarray  # (ny, nx) float64, row i increases with y (south → north)

    def at(self, x: Any, y: Any) -> np.ndarray:
        """Bilinear height (same formula as the kernel), clamped at the edges."""
        x = np.asarray(x, float)
        y = np.asarray(y, float)
        ny, nx = self.height_m.shape
        fj = np.clip((x - self.x0) / self.step, 0.0, nx - 1.000001)
        fi = np.clip((y - self.y0) / self.step, 0.0, ny - 1.000001)
        j = np.floor(fj).astype(int)
        i = np.floor(fi).astype(int)
        a = fj - j
        b = fi - i
        H = self.height_m
        return (
            (1 - a) * (1 - b) * H[i, j]
            + a * (1 - b) * H[i, j + 1]
            + (1 - a) * b * H[i + 1, j]
            + a * b * H[i + 1, j + 1]
        )


@dataclass(frozen=True)
class Epoch:
    """What stands in the scene at one date."""

    name: str
    buildings: tuple[Building, ...]
    cars: tuple[Car, ...]
    trees: tuple[Tree, ...]
    patches: tuple[Patch, ...]
    vegetation_rgb: tuple[float, float, float]  # multiplies grass and tree albedo (season)
    grass_rgb: tuple[float, float, float]
    vegetation_nir: tuple[float, float] = (0.35, 0.40)  # near-infrared albedo of grass and trees


@dataclass(frozen=True)
class Change:
    """One known change between epochs A and B."""

    kind: str  # new | demolished | raised | lowered | car_removed | car_added | car_moved | tree_removed |
    #            tree_added | repaint | season
    object_id: int
    is_3d: bool
    dz_m: float = 0.0
    note: str = ""

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class TownParams:
    """Parameters of :func:`build_town`.

    Attributes
    ----------
    seed : int
    size_m : float
        Side of the square AOI (metres).
    margin_m : float
        Scene content extends this far beyond the AOI (what oblique views see).
    center_lon, center_lat : float
        Geodetic centre (sets the UTM zone).
    base_height_m : float
        Ellipsoidal height of the terrain at the centre.
    relief_m : float
        Typical amplitude of the rolling terrain.
    n_buildings : int or None
        Buildings standing in epoch A inside the AOI (None: 32 per 300 m × 300 m).
    n_new, n_demolished, n_raised, n_lowered : int
        Building changes (limited by what fits in small scenes).
    n_cars_moved, n_trees_changed, n_repainted : int
    season : bool
        Vegetation colour differs between epochs.
    changes : tuple of str
        Which change types are enabled (subset of :data:`CHANGE_TYPES`).
    """

    seed: int = 0
    size_m: float = 300.0
    margin_m: float = 40.0
    center_lon: float = 1.4440
    center_lat: float = 43.5620
    base_height_m: float = 196.0
    relief_m: float = 4.0
    n_buildings: int | None = None
    n_new: int = 3
    n_demolished: int = 2
    n_raised: int = 2
    n_lowered: int = 1
    n_cars_moved: int = 4
    n_trees_changed: int = 2
    n_repainted: int = 2
    season: bool = True
    changes: tuple[str, ...] = CHANGE_TYPES

    def __post_init__(self) -> None:
        if not (16.0 <= self.size_m <= 2000.0):
            raise ConfigError(f"scene size_m must be within 16..2000 m, got {self.size_m}")
        bad = set(self.changes) - set(CHANGE_TYPES)
        if bad:
            raise ConfigError(f"unknown change types {sorted(bad)}; choose from {list(CHANGE_TYPES)}")
        for k in ("n_new", "n_demolished", "n_raised", "n_lowered", "n_cars_moved", "n_trees_changed", "n_repainted"):
            if getattr(self, k) < 0:
                raise ConfigError(f"{k} must be ≥ 0")


@dataclass(frozen=True)
class Town:
    """The whole synthetic scene: frame, terrain, streets, two epochs and their changes."""

    params: TownParams
    frame: SceneFrame
    aoi: tuple[float, float, float, float]  # (xmin, ymin, xmax, ymax) map space
    extent: tuple[float, float, float, float]
    terrain: Terrain
    streets: tuple[Street, ...]
    epochs: dict = field(default_factory=dict)  # name → Epoch
    changes: tuple[Change, ...] = ()

    @property
    def aoi_bounds_utm(self) -> tuple[float, float, float, float]:
        x0, y0, x1, y1 = self.aoi
        return (x0 + self.frame.e0, y0 + self.frame.n0, x1 + self.frame.e0, y1 + self.frame.n0)

    def height_range(self) -> tuple[float, float]:
        """(min terrain, max object top) over the whole scene, ellipsoidal metres."""
        lo = float(self.terrain.height_m.min())
        hi = float(self.terrain.height_m.max())
        for ep in self.epochs.values():
            for b in ep.buildings:
                hi = max(hi, b.top_m)
            for t in ep.trees:
                hi = max(hi, t.top_m)
        return lo, hi

    def aoi_height_range(self) -> tuple[float, float]:
        x0, y0, x1, y1 = self.aoi
        xs = np.linspace(x0, x1, 61)
        X, Y = np.meshgrid(xs, np.linspace(y0, y1, 61))
        h = self.terrain.at(X, Y)
        return float(h.min()), max(float(h.max()), self.height_range()[1])


# ------------------------------------------------------------------------------------------
# generation
# ------------------------------------------------------------------------------------------
_ROOF_COLOURS = [
    (0.62, 0.30, 0.22),
    (0.55, 0.26, 0.20),
    (0.40, 0.40, 0.42),
    (0.30, 0.31, 0.34),
    (0.70, 0.68, 0.62),
    (0.50, 0.47, 0.44),
    (0.25, 0.22, 0.22),
    (0.58, 0.52, 0.40),
]
_WALL_COLOURS = [(0.78, 0.74, 0.66), (0.85, 0.82, 0.76), (0.70, 0.62, 0.52), (0.66, 0.66, 0.66), (0.80, 0.70, 0.60)]
_CAR_COLOURS = [
    (0.80, 0.80, 0.82),
    (0.08, 0.08, 0.09),
    (0.55, 0.08, 0.07),
    (0.12, 0.20, 0.45),
    (0.45, 0.46, 0.48),
    (0.85, 0.85, 0.80),
    (0.20, 0.30, 0.22),
]


def _terrain(rng: np.random.Generator, extent, step: float, relief: float, base: float) -> Terrain:
    x0, y0, x1, y1 = extent
    nx = int(math.ceil((x1 - x0) / step)) + 1
    ny = int(math.ceil((y1 - y0) / step)) + 1
    xs = x0 + step * np.arange(nx)
    ys = y0 + step * np.arange(ny)
    X, Y = np.meshgrid(xs, ys)
    gx, gy = rng.normal(0, 0.012, 2)
    H = base + gx * X + gy * Y
    size = max(x1 - x0, y1 - y0)
    for _ in range(6):
        cx, cy = rng.uniform(x0, x1), rng.uniform(y0, y1)
        s = rng.uniform(0.25, 0.6) * size
        a = rng.normal(0.0, relief)
        H = H + a * np.exp(-((X - cx) ** 2 + (Y - cy) ** 2) / (2 * s * s))
    H = H - (np.interp(0.0, xs, H[int(np.argmin(np.abs(ys))), :]) - base)  # centre at base height
    return Terrain(float(x0), float(y0), step, H)


def _street_grid(rng, extent, angle: float, spacing_u: float, spacing_v: float) -> tuple[list[Street], tuple]:
    """Streets along u (angle) and v, as segments covering the extent; returns streets and lattice info."""
    x0, y0, x1, y1 = extent
    R = math.hypot(x1 - x0, y1 - y0)
    u = np.array([math.cos(angle), math.sin(angle)])
    v = np.array([-u[1], u[0]])
    off_u = rng.uniform(0, spacing_u)
    off_v = rng.uniform(0, spacing_v)
    streets = []
    hw = 4.0
    # streets of constant v-coordinate (running along u)
    k0 = int(math.floor((-R - off_v) / spacing_v))
    vs = [off_v + k * spacing_v for k in range(k0, k0 + int(2 * R / spacing_v) + 3)]
    k0 = int(math.floor((-R - off_u) / spacing_u))
    us = [off_u + k * spacing_u for k in range(k0, k0 + int(2 * R / spacing_u) + 3)]
    for vv in vs:
        a, b = vv * v - R * u, vv * v + R * u
        streets.append(Street(a[0], a[1], b[0], b[1], hw))
    for uu in us:
        a, b = uu * u - R * v, uu * u + R * v
        streets.append(Street(a[0], a[1], b[0], b[1], hw))
    return streets, (u, v, us, vs)


def _inside(poly, box) -> bool:
    from shapely.geometry import box as sbox

    return sbox(*box).contains(poly)


def build_town(p: TownParams) -> Town:
    """Generate the town (both epochs and the list of changes) from ``p``.

    Deterministic: the same parameters give the same town.
    """
    from shapely.geometry import Point
    from shapely.geometry import box as sbox
    from shapely.strtree import STRtree  # noqa: F401  (kept simple: counts are small)

    rng = np.random.default_rng(np.random.SeedSequence([p.seed, 0x5EED]))
    half = p.size_m / 2.0
    aoi = (-half, -half, half, half)
    m = p.margin_m
    extent = (-half - m, -half - m, half + m, half + m)
    frame = SceneFrame.at(p.center_lon, p.center_lat, p.base_height_m)
    terrain = _terrain(
        rng, (extent[0] - 40, extent[1] - 40, extent[2] + 40, extent[3] + 40), 0.5, p.relief_m, p.base_height_m
    )

    # --- streets and lots -------------------------------------------------------------------
    angle = math.radians(rng.uniform(8.0, 25.0))
    spacing_u, spacing_v = rng.uniform(95, 115), rng.uniform(62, 72)
    streets, (u, v, us, vs) = _street_grid(rng, extent, angle, spacing_u, spacing_v)
    hw, sw = 4.0, 2.0
    road_union = None
    from shapely.ops import unary_union

    road_polys = []
    for s in streets:
        from shapely.geometry import LineString

        road_polys.append(LineString([(s.x0, s.y0), (s.x1, s.y1)]).buffer(s.half_width + s.sidewalk_m, cap_style=2))
    road_union = unary_union(road_polys)
    lots: list[Rect] = []
    for i in range(len(us) - 1):
        for j in range(len(vs) - 1):
            ua, ub = us[i] + hw + sw + 1.0, us[i + 1] - hw - sw - 1.0
            va, vb = vs[j] + hw + sw + 1.0, vs[j + 1] - hw - sw - 1.0
            depth = (vb - va) / 2.0
            for row_lo, row_hi, front in ((va, va + depth, -1), (va + depth, vb, 1)):
                uu = ua
                while uu < ub - 10.0:
                    w = rng.uniform(17.0, 26.0)
                    w = min(w, ub - uu)
                    cu, cv = uu + w / 2.0, 0.5 * (row_lo + row_hi)
                    c = cu * u + cv * v
                    lots.append(Lot(float(c[0]), float(c[1]), w / 2.0, (row_hi - row_lo) / 2.0, angle, front))
                    uu += w
    ext_box = sbox(*extent)
    lots = [lt for lt in lots if ext_box.contains(lt.polygon())]
    rng.shuffle(lots)
    aoi_box = sbox(*aoi)
    inner_box = sbox(aoi[0] + 3, aoi[1] + 3, aoi[2] - 3, aoi[3] - 3)

    # --- buildings on lots --------------------------------------------------------------------
    def make_building(bid: int, lot: Rect, kind: str | None = None) -> Building:
        k = kind or rng.choice(["house", "house", "block", "lshape"], p=[0.35, 0.2, 0.25, 0.2])
        Lmax, Wmax = lot.half_len - 2.0, lot.half_wid - 2.5
        uax, vax = lot.axes
        # front setback: the building sits toward one side of the lot's depth
        if k == "house":
            L = min(rng.uniform(4.0, 6.5), Lmax)
            W = min(rng.uniform(3.6, 5.0), Wmax)
            along = rng.random() < 0.7
            off = rng.uniform(-1.0, 1.0) * max(Wmax - W, 0.0)
            c = np.array([lot.cx, lot.cy]) + off * vax + rng.uniform(-1, 1) * max(Lmax - L, 0) * 0.5 * uax
            if along:
                parts = (Rect(float(c[0]), float(c[1]), L, W, lot.angle),)
            else:
                parts = (
                    (Rect(float(c[0]), float(c[1]), L, W, lot.angle + math.pi / 2),)
                    if W <= Lmax and L <= Wmax
                    else (Rect(float(c[0]), float(c[1]), L, W, lot.angle),)
                )
            storeys = int(rng.integers(1, 3))
            roof, rise = "gabled", float(rng.uniform(2.2, 3.6))
        elif k == "block":
            L = min(rng.uniform(6.0, 11.0), Lmax)
            W = min(rng.uniform(4.5, 7.0), Wmax)
            c = np.array([lot.cx, lot.cy]) + rng.uniform(-0.5, 0.5) * max(Wmax - W, 0) * vax
            parts = (Rect(float(c[0]), float(c[1]), L, W, lot.angle),)
            storeys = int(rng.integers(3, 7))
            roof, rise = "flat", 0.0
        else:  # L-shape: main wing + perpendicular wing
            L = min(rng.uniform(6.0, 9.5), Lmax)
            W = min(rng.uniform(3.5, 4.5), Wmax)
            c = np.array([lot.cx, lot.cy])
            main = Rect(float(c[0]), float(c[1]), L, W, lot.angle)
            ext = max(1.5, min(rng.uniform(3.0, 6.0), Wmax - W))
            ww = rng.uniform(min(3.0, 0.4 * L), min(4.0, 0.5 * L))
            side = 1 if rng.random() < 0.5 else -1
            end = 1 if rng.random() < 0.5 else -1
            wl = (W + ext) / 2.0  # wing spans v in [0, W + ext] on one side: overlaps the main wing
            wc = c + end * (L - ww) * uax + side * wl * vax
            wing = Rect(float(wc[0]), float(wc[1]), ww, wl, lot.angle)
            parts = (main, wing)
            storeys = int(rng.integers(2, 4))
            roof, rise = "flat", 0.0
        poly = unary_union([q.polygon() for q in parts])
        xs, ys = np.asarray(poly.exterior.xy)
        gx, gy = np.meshgrid(np.linspace(xs.min(), xs.max(), 9), np.linspace(ys.min(), ys.max(), 9))
        ground = float(terrain.at(gx, gy).max()) + 0.15
        roof_rgb = _ROOF_COLOURS[int(rng.integers(len(_ROOF_COLOURS)))]
        if roof == "gabled" and rng.random() < 0.7:
            roof_rgb = _ROOF_COLOURS[int(rng.integers(2))]
        wall_rgb = _WALL_COLOURS[int(rng.integers(len(_WALL_COLOURS)))]
        jitter = rng.uniform(0.92, 1.08, 3)
        roof_rgb = tuple(float(min(0.95, c_ * j)) for c_, j in zip(roof_rgb, jitter))
        return Building(bid, parts, storeys, roof, rise, ground, roof_rgb, tuple(map(float, wall_rgb)), k)

    def access(b: Building, lot: Lot) -> tuple[list[Patch], list[Rect]]:
        """Driveway (houses) or car park (other buildings) between the building and the street."""
        uax, vax = lot.axes
        c = np.array([lot.cx, lot.cy])
        pts = np.concatenate([q.corners() for q in b.parts]) - c
        us, vs = pts @ uax, pts @ vax
        if lot.front > 0:
            v0, v1 = float(vs.max()), lot.half_wid + 1.2
        else:
            v0, v1 = -lot.half_wid - 1.2, float(vs.min())
        if v1 - v0 < 2.0:
            return [], []
        if b.kind == "house":
            u_mid, half_u, mat = float(us.max()) - 1.6, 1.5, M_PAVEMENT
        else:
            u_mid, half_u, mat = 0.5 * float(us.min() + us.max()), 0.5 * float(us.max() - us.min()), M_ASPHALT
        cc = c + u_mid * uax + 0.5 * (v0 + v1) * vax
        pr = Rect(float(cc[0]), float(cc[1]), half_u, 0.5 * (v1 - v0), lot.angle)
        spots = []
        if mat == M_ASPHALT and v1 - v0 > 6.0:
            for k in range(int(rng.integers(0, 3))):
                uu = u_mid - half_u + 1.6 + k * 2.8
                if uu > u_mid + half_u - 1.2:
                    break
                cs = c + uu * uax + 0.5 * (v0 + v1) * vax
                spots.append(Rect(float(cs[0]), float(cs[1]), 2.25, 0.9, lot.angle + math.pi / 2))
        return [Patch(pr, mat)], spots

    area_ratio = (p.size_m / 300.0) ** 2
    n_target = p.n_buildings if p.n_buildings is not None else max(2, int(round(32 * area_ratio)))
    buildings: list[Building] = []
    used_lots: list[Rect] = []
    free_lots: list[Rect] = []
    patches_a: list[Patch] = []
    parking: list[Rect] = []
    n_in = 0
    # margin lots: fill with the same density so the views look continuous
    lots_in = [lt for lt in lots if aoi_box.intersects(lt.polygon())]
    lots_out = [lt for lt in lots if not aoi_box.intersects(lt.polygon())]
    want_new = p.n_new if "new" in p.changes else 0
    density = min(1.0, (n_target + 0.0) / max(len(lots_in) - want_new, 1))
    bid = 1
    for lt in lots_in:
        fits_inside = inner_box.contains(lt.polygon())
        if n_in < n_target and (len(lots_in) - len(used_lots) - len(free_lots) > want_new or not fits_inside):
            b = make_building(bid, lt)
            if b.polygon().intersects(aoi_box):
                buildings.append(b)
                pa, sp = access(b, lt)
                patches_a += pa
                parking += sp
                used_lots.append(lt)
                bid += 1
                n_in += 1
                continue
        free_lots.append(lt)
    for lt in lots_out:
        if rng.random() < density:
            b = make_building(bid, lt)
            buildings.append(b)
            pa, sp = access(b, lt)
            patches_a += pa
            parking += sp
            bid += 1
    # --- trees ---------------------------------------------------------------------------------
    occupied = unary_union(
        [b.polygon().buffer(1.5) for b in buildings]
        + [road_union.buffer(-sw + 0.5)]
        + [q.rect.polygon().buffer(0.5) for q in patches_a]
    )
    trees: list[Tree] = []
    n_trees = int(round(140 * ((p.size_m + 2 * m) / 380.0) ** 2))
    tid = 1
    attempts = 0
    while len(trees) < n_trees and attempts < n_trees * 40:
        attempts += 1
        if trees and rng.random() < 0.5:  # garden groups: next to an existing tree
            t0 = trees[int(rng.integers(len(trees)))]
            a = rng.uniform(0, 2 * math.pi)
            dd = t0.crown_r + rng.uniform(2.5, 6.0)
            x, y = t0.cx + dd * math.cos(a), t0.cy + dd * math.sin(a)
            if not (extent[0] + 3 < x < extent[2] - 3 and extent[1] + 3 < y < extent[3] - 3):
                continue
        else:
            x, y = rng.uniform(extent[0] + 3, extent[2] - 3), rng.uniform(extent[1] + 3, extent[3] - 3)
        r = float(rng.uniform(1.6, 3.6))
        disk = Point(x, y).buffer(r)
        if occupied.intersects(disk):
            continue
        if any(math.hypot(t.cx - x, t.cy - y) < t.crown_r + r + 0.5 for t in trees):
            continue
        rz = float(r * rng.uniform(0.9, 1.4))
        trees.append(
            Tree(
                tid,
                float(x),
                float(y),
                r,
                rz,
                float(rng.uniform(1.5, 3.5)),
                float(terrain.at(x, y)),
                float(rng.uniform(0.85, 1.15)),
            )
        )
        tid += 1
    # --- cars: parked along the kerbs ----------------------------------------------------------
    cars: list[Car] = []
    n_cars = int(round(22 * ((p.size_m + 2 * m) / 380.0) ** 2))
    cid = 1
    attempts = 0
    seg_len = [math.hypot(s.x1 - s.x0, s.y1 - s.y0) for s in streets]
    while len(cars) < n_cars and attempts < n_cars * 50:
        attempts += 1
        k = int(rng.integers(len(streets)))
        s = streets[k]
        t = rng.uniform(0, 1)
        d = np.array([s.x1 - s.x0, s.y1 - s.y0]) / seg_len[k]
        nrm = np.array([-d[1], d[0]])
        side = 1 if rng.random() < 0.5 else -1
        c = np.array([s.x0, s.y0]) + t * seg_len[k] * d + side * (s.half_width - 1.3) * nrm
        if not (extent[0] + 3 < c[0] < extent[2] - 3 and extent[1] + 3 < c[1] < extent[3] - 3):
            continue
        ang = math.atan2(d[1], d[0])
        body = Rect(float(c[0]), float(c[1]), 2.25, 0.9, ang)
        poly = body.polygon()
        # not across an intersection, not on another car
        inter = sum(1 for q in road_polys if q.intersects(poly.buffer(3.0)))
        if inter > 1:
            continue
        if any(poly.buffer(0.6).intersects(cc.body.polygon()) for cc in cars):
            continue
        col = _CAR_COLOURS[int(rng.integers(len(_CAR_COLOURS)))]
        cars.append(Car(cid, body, float(terrain.at(c[0], c[1])), tuple(map(float, col))))
        cid += 1

    for spot in parking:
        if any(spot.polygon().buffer(0.4).intersects(cc.body.polygon()) for cc in cars):
            continue
        col = _CAR_COLOURS[int(rng.integers(len(_CAR_COLOURS)))]
        cars.append(Car(cid, spot, float(terrain.at(spot.cx, spot.cy)), tuple(map(float, col))))
        cid += 1
    grass_a = (0.30, 0.34, 0.16)  # late summer, dry
    veg_a = (1.0, 0.92, 0.80)
    epoch_a = Epoch("A", tuple(buildings), tuple(cars), tuple(trees), tuple(patches_a), veg_a, grass_a, (0.30, 0.38))

    # --- changes for epoch B ---------------------------------------------------------------------
    changes: list[Change] = []
    b_list = list(buildings)
    cand = [b for b in buildings if inner_box.contains(b.polygon())]
    rng.shuffle(cand)
    taken: set[int] = set()

    def pick(pred, n):
        out = []
        for b in cand:
            if len(out) >= n:
                break
            if b.building_id in taken or not pred(b):
                continue
            out.append(b)
            taken.add(b.building_id)
        return out

    patches_b: list[Patch] = list(patches_a)
    if "demolished" in p.changes:
        for b in pick(lambda b: True, p.n_demolished):
            b_list = [x for x in b_list if x.building_id != b.building_id]
            changes.append(Change("demolished", b.building_id, True, -(b.top_m - b.ground_m)))
            for part in b.parts:
                patches_b.insert(
                    0, Patch(Rect(part.cx, part.cy, part.half_len + 0.8, part.half_wid + 0.8, part.angle), M_SOIL)
                )
    if "raised" in p.changes:
        for b in pick(lambda b: b.storeys <= 5, p.n_raised):
            k = int(rng.integers(1, 3))
            nb = replace(b, storeys=b.storeys + k)
            b_list = [nb if x.building_id == b.building_id else x for x in b_list]
            changes.append(Change("raised", b.building_id, True, k * STOREY_M, f"+{k} storeys"))
    if "lowered" in p.changes:
        for b in pick(lambda b: b.storeys >= 2, p.n_lowered):
            k = int(rng.integers(1, b.storeys))
            k = max(1, min(k, 2))
            nb = replace(b, storeys=b.storeys - k)
            b_list = [nb if x.building_id == b.building_id else x for x in b_list]
            changes.append(Change("lowered", b.building_id, True, -k * STOREY_M, f"-{k} storeys"))
    if "repaint" in p.changes:
        for b in pick(lambda b: True, p.n_repainted):
            old = np.array(b.roof_rgb)
            new = tuple(float(v) for v in np.clip(0.95 - old * 0.9 + rng.uniform(-0.05, 0.05, 3), 0.08, 0.9))
            nb = replace(b, roof_rgb=new)
            b_list = [nb if x.building_id == b.building_id else x for x in b_list]
            changes.append(Change("repaint", b.building_id, False, 0.0, "roof repainted"))
    trees_b = list(trees)
    if "new" in p.changes:
        new_sites = [lt for lt in free_lots if inner_box.contains(lt.polygon())]
        n_made = 0
        for lt in new_sites:
            if n_made >= p.n_new:
                break
            nb = make_building(bid, lt, kind=["block", "house", "lshape"][n_made % 3])
            poly = nb.polygon()
            if not inner_box.contains(poly):
                continue
            # clear trees on the construction site (recorded as changes too)
            for t in list(trees_b):
                if Point(t.cx, t.cy).buffer(t.crown_r).intersects(poly.buffer(1.0)):
                    trees_b.remove(t)
                    changes.append(Change("tree_removed", t.tree_id, True, -(t.top_m - t.ground_m), "site clearance"))
            b_list.append(nb)
            patches_b += access(nb, lt)[0]
            changes.append(Change("new", bid, True, nb.top_m - nb.ground_m))
            bid += 1
            n_made += 1
    cars_b = list(cars)
    if "cars" in p.changes and cars:
        in_cars = [c for c in cars if inner_box.contains(c.body.polygon())]
        rng.shuffle(in_cars)
        k = min(p.n_cars_moved, len(in_cars))
        for i, c in enumerate(in_cars[:k]):
            if i % 3 == 0:
                cars_b.remove(c)
                changes.append(Change("car_removed", c.car_id, True, -c.height_m))
            elif i % 3 == 1:
                # moved along the kerb by one or two car lengths
                u_ = np.array([math.cos(c.body.angle), math.sin(c.body.angle)])
                d = rng.choice([-1, 1]) * rng.uniform(5.5, 9.0)
                nc = np.array([c.body.cx, c.body.cy]) + d * u_
                body = replace(c.body, cx=float(nc[0]), cy=float(nc[1]))
                if any(
                    body.polygon().buffer(0.4).intersects(o.body.polygon()) for o in cars_b if o.car_id != c.car_id
                ) or any(body.polygon().buffer(0.5).intersects(bb.polygon()) for bb in b_list):
                    cars_b.remove(c)
                    changes.append(Change("car_removed", c.car_id, True, -c.height_m))
                    continue
                cars_b[cars_b.index(c)] = replace(c, body=body, ground_m=float(terrain.at(nc[0], nc[1])))
                changes.append(Change("car_moved", c.car_id, True, c.height_m, f"moved {d:+.1f} m"))
            else:
                # replaced by another car of another colour at the same place
                col = _CAR_COLOURS[(int(rng.integers(len(_CAR_COLOURS))))]
                cars_b[cars_b.index(c)] = replace(
                    c,
                    car_id=cid,
                    rgb=tuple(map(float, col)),
                    body=replace(
                        c.body, cx=c.body.cx + 0.6 * math.cos(c.body.angle), cy=c.body.cy + 0.6 * math.sin(c.body.angle)
                    ),
                )
                changes.append(Change("car_replaced", cid, True, 0.0, f"car {c.car_id} replaced by {cid}"))
                cid += 1
    if "trees" in p.changes:
        in_trees = [t for t in trees_b if inner_box.contains(Point(t.cx, t.cy).buffer(t.crown_r + 1))]
        rng.shuffle(in_trees)
        n_rm = (p.n_trees_changed + 1) // 2
        for t in in_trees[:n_rm]:
            trees_b.remove(t)
            changes.append(Change("tree_removed", t.tree_id, True, -(t.top_m - t.ground_m), "felled"))
        # planted / grown trees
        occupied_b = unary_union([b.polygon().buffer(1.5) for b in b_list] + [road_union.buffer(-sw + 0.5)])
        n_add = p.n_trees_changed - n_rm
        attempts = 0
        while n_add > 0 and attempts < 2000:
            attempts += 1
            x, y = rng.uniform(aoi[0] + 8, aoi[2] - 8), rng.uniform(aoi[1] + 8, aoi[3] - 8)
            r = float(rng.uniform(2.5, 3.5))
            disk = Point(x, y).buffer(r)
            if occupied_b.intersects(disk) or any(
                math.hypot(t.cx - x, t.cy - y) < t.crown_r + r + 1.0 for t in trees_b + list(trees)
            ):
                continue
            nt = Tree(tid, float(x), float(y), r, r * 1.2, 2.5, float(terrain.at(x, y)), 1.0)
            trees_b.append(nt)
            changes.append(Change("tree_added", tid, True, nt.top_m - nt.ground_m, "planted (grown)"))
            tid += 1
            n_add -= 1
    if p.season and "season" in p.changes:
        grass_b, veg_b, nir_b = (0.20, 0.36, 0.12), (0.80, 1.05, 0.75), (0.44, 0.42)  # spring green
        changes.append(Change("season", 0, False, 0.0, "vegetation colour (late summer → spring)"))
    else:
        grass_b, veg_b, nir_b = grass_a, veg_a, epoch_a.vegetation_nir
    epoch_b = Epoch("B", tuple(b_list), tuple(cars_b), tuple(trees_b), tuple(patches_b), veg_b, grass_b, nir_b)
    return Town(p, frame, aoi, extent, terrain, tuple(streets), {"A": epoch_a, "B": epoch_b}, tuple(changes))


def building_status(town: Town) -> dict[str, dict[int, str]]:
    """Per epoch, building_id → status in {new, demolished, raised, lowered, unchanged}."""
    by_id = {c.object_id: c.kind for c in town.changes if c.kind in ("new", "demolished", "raised", "lowered")}
    out: dict[str, dict[int, str]] = {}
    for name, ep in town.epochs.items():
        out[name] = {b.building_id: by_id.get(b.building_id, "unchanged") for b in ep.buildings}
    return out
