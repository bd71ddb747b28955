"""Connected regions of a change-sign raster across tile seams (union–find over the tiles' borders).

A region larger than any overlap cannot be found by one tile. Each tile labels the
8-connected regions of +1 and of −1 cells of its core (:func:`tile_regions`: per label the
cell count, Σ dz, extreme dz, bounding box, first cell and polygons, plus the labels on
the core's four edges); :func:`merge_regions` joins the labels that touch across a seam
(8-connectivity: edges and corners), adds up their figures and unions their polygons.
The merged regions are what :func:`geocd.change.regions.change_regions` finds on the
whole grid, in the same order (raised first, then lowered; each by decreasing size, ties
by the first cell in row-major order).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import numpy as np

from ..geodesy import AOIGrid
from .grid import Tile, TileGrid

_EIGHT = np.ones((3, 3), dtype=bool)


@dataclass
class TileRegions:
    """The regions of one tile's core (small: sent back to the client).

    ``labels`` is the tile's label raster (int32, +k raised, −k lowered, 0 none; store it as
    a tile array, not with the small results); per-sign arrays are indexed by label − 1.
    """

    tile_index: tuple[int, int]
    core: tuple[int, int, int, int]
    stats: dict[int, dict[str, np.ndarray]] = field(default_factory=dict)
    edges: dict[int, dict[str, np.ndarray]] = field(default_factory=dict)
    polygons: dict[int, list[list[bytes]]] = field(default_factory=dict)
    labels: np.ndarray | None = None


def tile_regions(
    sign: np.ndarray,
    dz_m: np.ndarray,
    tile: Tile,
    grid: AOIGrid,
    *,
    sigma: np.ndarray | None = None,
    confidence: np.ndarray | None = None,
    polygons: bool = True,
    sums: dict[str, np.ndarray] | None = None,
) -> TileRegions:
    """Label the +1 and −1 regions of a tile's core (``sign`` and ``dz_m`` on the core) and summarise them.

    ``sums``: further per-cell values (on the core) summed per region (added up across seams)."""
    from scipy import ndimage

    r0, c0, h, w = tile.core
    out = TileRegions(tile.index, tile.core)
    dz = np.asarray(dz_m, np.float64)
    fin = np.isfinite(dz)
    dzf = np.where(fin, dz, 0.0)
    lin = np.arange(r0, r0 + h, dtype=np.int64)[:, None] * grid.width + np.arange(c0, c0 + w)[None, :]
    core_grid = grid.subgrid(r0, c0, h, w)
    out.labels = np.zeros((h, w), np.int32)
    for s in (1, -1):
        lab, n = ndimage.label(sign == s, structure=_EIGHT)
        if n == 0:
            continue
        out.labels[lab > 0] = s * lab[lab > 0]
        li = lab.ravel()
        k = n + 1
        cnt = np.bincount(li, minlength=k)
        st = {
            "n": cnt[1:].astype(np.int64),
            "sum": np.bincount(li, weights=dzf.ravel(), minlength=k)[1:],
            "nfin": np.bincount(li, weights=fin.ravel().astype(np.float64), minlength=k)[1:].astype(np.int64),
        }
        mx = np.full(k, -np.inf)
        mn = np.full(k, np.inf)
        np.maximum.at(mx, li[fin.ravel()], dz.ravel()[fin.ravel()])
        np.minimum.at(mn, li[fin.ravel()], dz.ravel()[fin.ravel()])
        st["max"] = mx[1:]
        st["min"] = mn[1:]
        first = np.full(k, np.iinfo(np.int64).max)
        np.minimum.at(first, li, lin.ravel())
        st["first"] = first[1:]
        objs = ndimage.find_objects(lab)
        st["bbox"] = np.array(
            [(o[0].start + r0, o[1].start + c0, o[0].stop + r0, o[1].stop + c0) for o in objs], np.int64
        )
        if sigma is not None:
            sg = np.where(np.isfinite(sigma), sigma, 0.0).astype(np.float64)
            st["sum_sigma"] = np.bincount(li, weights=sg.ravel(), minlength=k)[1:]
        if confidence is not None:
            cf = np.asarray(confidence, np.float64)
            st["conf_sum"] = np.bincount(li, weights=np.nan_to_num(cf).ravel(), minlength=k)[1:]
        for key, v in (sums or {}).items():
            st[key] = np.bincount(li, weights=np.asarray(v, np.float64).ravel(), minlength=k)[1:]
        out.stats[s] = st
        out.edges[s] = {
            "top": lab[0].copy(),
            "bottom": lab[-1].copy(),
            "left": lab[:, 0].copy(),
            "right": lab[:, -1].copy(),
        }
        if polygons:
            from rasterio.features import shapes
            from shapely.geometry import shape

            parts: list[list[bytes]] = [[] for _ in range(n)]
            for geom, val in shapes(lab.astype(np.int32), mask=lab > 0, connectivity=8, transform=core_grid.transform):
                parts[int(val) - 1].append(shape(geom).wkb)
            out.polygons[s] = parts
    return out


class _UF:
    def __init__(self, n: int):
        self.p = np.arange(n)

    def find(self, a: int) -> int:
        p = self.p
        while p[a] != a:
            p[a] = p[p[a]]
            a = p[a]
        return a

    def union(self, a: int, b: int) -> None:
        ra, rb = self.find(a), self.find(b)
        if ra != rb:
            if ra < rb:
                self.p[rb] = ra
            else:
                self.p[ra] = rb


class _Members:
    """Per region, its (tile index, sign, local label) pieces — built on demand, not held as Python lists."""

    def __init__(
        self,
        tiles: np.ndarray,
        signs: np.ndarray,
        labels: np.ndarray,
        perm: np.ndarray,
        starts: np.ndarray,
        groups: np.ndarray,
    ):
        self._t, self._s, self._l = tiles, signs, labels
        self._perm, self._starts, self._groups = perm, starts, groups
        #: number of pieces per region
        self.counts = (starts[groups + 1] - starts[groups]).astype(np.int64) if groups.size else np.zeros(0, np.int64)

    def units(self, k: int) -> np.ndarray:
        g = int(self._groups[k])
        return self._perm[self._starts[g] : self._starts[g + 1]]

    def __len__(self) -> int:
        return int(self._groups.size)

    def pieces(self, ks: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(tile index (n, 2), sign, local label) of every piece of regions ``ks``."""
        g = self._groups[np.asarray(ks, np.int64)]
        a, b = self._starts[g], self._starts[g + 1]
        cnt = b - a
        idx = np.repeat(a - np.concatenate([[0], np.cumsum(cnt)[:-1]]), cnt) + np.arange(int(cnt.sum()))
        u = self._perm[idx]
        return self._t[u], self._s[u], self._l[u]

    def __getitem__(self, k: int) -> list:
        return [((int(self._t[u, 0]), int(self._t[u, 1])), int(self._s[u]), int(self._l[u])) for u in self.units(k)]

    def __iter__(self):
        return (self[k] for k in range(len(self)))


class _Geometries:
    """Per region, the union of its pieces' polygons, built on demand (a slice builds a batch, vectorized)."""

    def __init__(self, members: _Members | None, polys: list | None):
        self._m = members
        self._p = polys

    def __len__(self) -> int:
        return len(self._m) if self._m is not None else 0

    def _one(self, k: int):
        from shapely import wkb
        from shapely.ops import unary_union

        if self._p is None:
            return None
        pieces = [wkb.loads(b) for u in self._m.units(k) for b in self._p[u]]
        geom = unary_union(pieces) if len(pieces) > 1 else pieces[0]
        if not geom.is_valid:
            geom = geom.buffer(0)
        return geom

    def batch(self, a: int, b: int) -> np.ndarray:
        """Regions a … b − 1 as an object array of shapely geometries (same as one by one)."""
        import shapely

        b = min(b, len(self))
        out = np.empty(max(b - a, 0), dtype=object)
        if self._p is None or b <= a:
            return out
        single = []
        blobs = []
        for k in range(a, b):
            us = self._m.units(k)
            if us.size == 1 and len(self._p[us[0]]) == 1:
                single.append(k - a)
                blobs.append(self._p[us[0]][0])
            else:
                out[k - a] = self._one(k)
        if single:
            g = shapely.from_wkb(np.array(blobs, dtype=object))
            bad = ~shapely.is_valid(g)
            if bad.any():
                g[bad] = shapely.buffer(g[bad], 0)
            out[np.asarray(single, np.int64)] = g
        return out

    def __getitem__(self, k):
        if isinstance(k, slice):
            a, b, step = k.indices(len(self))
            if step != 1:
                return [self._one(i) for i in range(a, b, step)]
            return list(self.batch(a, b))
        return self._one(int(k))

    def __iter__(self):
        step = 50_000
        for a in range(0, len(self), step):
            yield from self.batch(a, a + step)


@dataclass
class MergedRegions:
    """Regions of the whole grid after the merge (one entry per region, in the layer's order).

    Attributes
    ----------
    sign, n, sum, nfin, extreme, first : per region
    bbox : (row0, col0, row1, col1) per region (exclusive ends)
    geometry : per region, shapely geometries built on demand (None when polygons were not asked);
        ``geometry.batch(a, b)`` builds a range at once
    members : per region, the (tile index, sign, local label) pieces (``members.counts``: how many)
    """

    sign: np.ndarray
    n: np.ndarray
    sum: np.ndarray
    nfin: np.ndarray
    extreme: np.ndarray
    first: np.ndarray
    bbox: np.ndarray
    geometry: Any
    members: Any
    extra: dict[str, np.ndarray] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.n.size)


def merge_regions(parts: Sequence[TileRegions], tile_grid: TileGrid, min_cells: int = 1) -> MergedRegions:
    """Join the tiles' regions across seams (8-connectivity) and order them as the ``changes`` layer.

    Memory: per region a few numbers; the polygons stay the tiles' WKB pieces until
    ``geometry`` builds them (a whole scene has millions of regions).
    """
    by_tile = {p.tile_index: p for p in parts}
    offset: dict[tuple[tuple[int, int], int], int] = {}
    total = 0
    for p in parts:
        for s, st in p.stats.items():
            offset[(p.tile_index, s)] = total
            total += st["n"].size
    uf = _UF(total)

    def join(a: np.ndarray, b: np.ndarray, oa: int, ob: int) -> None:
        # a[i] touches b[i-1], b[i], b[i+1] (two edges facing each other)
        for d in (-1, 0, 1):
            if d < 0:
                x, y = a[1:], b[:-1]
            elif d > 0:
                x, y = a[:-1], b[1:]
            else:
                x, y = a, b
            both = (x > 0) & (y > 0)
            if both.any():
                for u, v in set(zip(x[both].tolist(), y[both].tolist())):
                    uf.union(oa + u - 1, ob + v - 1)

    for (i, j), p in by_tile.items():
        for s in p.edges:
            oa = offset[((i, j), s)]
            e = p.edges[s]
            q = by_tile.get((i, j + 1))
            if q is not None and s in q.edges:
                join(e["right"], q.edges[s]["left"], oa, offset[((i, j + 1), s)])
            q = by_tile.get((i + 1, j))
            if q is not None and s in q.edges:
                join(e["bottom"], q.edges[s]["top"], oa, offset[((i + 1, j), s)])
            q = by_tile.get((i + 1, j + 1))
            if q is not None and s in q.edges and e["bottom"][-1] > 0 and q.edges[s]["top"][0] > 0:
                uf.union(oa + e["bottom"][-1] - 1, offset[((i + 1, j + 1), s)] + q.edges[s]["top"][0] - 1)
            q = by_tile.get((i + 1, j - 1))
            if q is not None and s in q.edges and e["bottom"][0] > 0 and q.edges[s]["top"][-1] > 0:
                uf.union(oa + e["bottom"][0] - 1, offset[((i + 1, j - 1), s)] + q.edges[s]["top"][-1] - 1)
    if total == 0:
        e = np.zeros(0)
        return MergedRegions(
            np.zeros(0, np.int8),
            np.zeros(0, np.int64),
            e,
            np.zeros(0, np.int64),
            e,
            np.zeros(0, np.int64),
            np.zeros((0, 4), np.int64),
            [],
            [],
        )
    # roots of every piece (vectorized path halving until fixed)
    roots = uf.p.copy()
    while True:
        nxt = roots[roots]
        if np.array_equal(nxt, roots):
            break
        roots = nxt
    # per piece: tile, sign, local label (compact arrays)
    u_tile = np.zeros((total, 2), np.int32)
    u_sign = np.zeros(total, np.int8)
    u_lab = np.zeros(total, np.int32)
    cat: dict[str, list] = {k: [] for k in ("n", "sum", "nfin", "max", "min", "first", "bbox")}
    extra_keys: set[str] = set()
    for p in parts:
        for s, st in p.stats.items():
            o = offset[(p.tile_index, s)]
            k_ = st["n"].size
            u_tile[o : o + k_] = p.tile_index
            u_sign[o : o + k_] = s
            u_lab[o : o + k_] = np.arange(1, k_ + 1)
            for k in cat:
                cat[k].append(st[k])
            extra_keys |= {k for k in st if k not in cat}
    a = {k: np.concatenate(v) for k, v in cat.items()}
    ur, inv = np.unique(roots, return_inverse=True)
    inv = inv.ravel()
    m = ur.size
    n = np.bincount(inv, weights=a["n"], minlength=m).astype(np.int64)
    sm = np.bincount(inv, weights=a["sum"], minlength=m)
    nf = np.bincount(inv, weights=a["nfin"], minlength=m).astype(np.int64)
    mx = np.full(m, -np.inf)
    mn = np.full(m, np.inf)
    np.maximum.at(mx, inv, a["max"])
    np.minimum.at(mn, inv, a["min"])
    first = np.full(m, np.iinfo(np.int64).max)
    np.minimum.at(first, inv, a["first"])
    bb = np.zeros((m, 4), np.int64)
    bb[:, :2] = np.iinfo(np.int64).max
    np.minimum.at(bb[:, 0], inv, a["bbox"][:, 0])
    np.minimum.at(bb[:, 1], inv, a["bbox"][:, 1])
    np.maximum.at(bb[:, 2], inv, a["bbox"][:, 2])
    np.maximum.at(bb[:, 3], inv, a["bbox"][:, 3])
    del a
    sgn = u_sign[ur]
    extra = {}
    for k in extra_keys:
        vals = np.concatenate([st[k] for p in parts for s, st in p.stats.items()])
        extra[k] = np.bincount(inv, weights=vals, minlength=m)
    ext = np.where(np.abs(mx) >= np.abs(mn), mx, mn)
    ext = np.where(nf > 0, ext, np.nan)
    keep = n >= max(int(min_cells), 1)
    # order: raised, then lowered; by decreasing size; ties by the first cell (scipy's label order)
    order = np.lexsort((first, -n, -sgn))
    order = order[keep[order]]
    # pieces grouped by region, in piece order within a region
    perm = np.argsort(inv, kind="stable")
    starts = np.searchsorted(inv[perm], np.arange(m + 1))
    members = _Members(u_tile, u_sign, u_lab, perm, starts, order)
    have_polys = all(s in p.polygons for p in parts for s in p.stats)
    polys = [pp for p in parts for s in p.stats for pp in p.polygons[s]] if have_polys else None
    return MergedRegions(
        sgn[order].astype(np.int8),
        n[order],
        sm[order],
        nf[order],
        ext[order],
        first[order],
        bb[order],
        _Geometries(members, polys),
        members,
        {k: v[order] for k, v in extra.items()},
    )


def regions_columns(
    merged: MergedRegions,
    *,
    cell_area_m2: float,
    method: str = "",
    epoch_a: str = "",
    epoch_b: str = "",
    volume_sigma: Callable[[int], float] | None = None,
    confidence: Callable[[int], float] | None = None,
):
    """The attribute columns of the ``changes`` layer (a DataFrame, no geometry)."""
    import math

    import pandas as pd

    from ..change.regions import _gauss_level

    # column arrays, not a record per region: a whole scene has millions of regions
    n = len(merged)
    total = np.asarray(merged.sum, np.float64)
    nfin = np.asarray(merged.nfin, np.int64)
    vol = total * cell_area_m2
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(nfin > 0, total / np.where(nfin > 0, nfin, 1), np.nan)
    vs = np.full(n, np.nan)
    cf = np.full(n, np.nan)
    for k in range(n):
        v = float(volume_sigma(k)) if volume_sigma is not None else float("nan")
        vs[k] = v
        if math.isfinite(v):
            cf[k] = _gauss_level(float(vol[k]), v)
        elif confidence is not None:
            cf[k] = float(confidence(k))
    return pd.DataFrame(
        {
            "region_id": np.arange(1, n + 1, dtype=np.int64),
            "method": method,
            "epoch_a": epoch_a,
            "epoch_b": epoch_b,
            "sign": np.asarray(merged.sign).astype("int64"),
            "n_cells": np.asarray(merged.n).astype("int64"),
            "area_m2": np.asarray(merged.n, np.float64) * cell_area_m2,
            "mean_dz_m": mean,
            "max_dz_m": np.asarray(merged.extreme, np.float64),
            "volume_m3": vol,
            "volume_sigma_m3": vs,
            "confidence": cf,
        }
    )


def regions_layer(
    merged: MergedRegions,
    grid: AOIGrid,
    *,
    cell_area_m2: float,
    method: str = "",
    epoch_a: str = "",
    epoch_b: str = "",
    volume_sigma: Callable[[int], float] | None = None,
    confidence: Callable[[int], float] | None = None,
):
    """The ``changes`` layer (:data:`geocd.change.regions.COLUMNS`) of merged regions.

    ``volume_sigma(k)`` gives region k's volume σ (m³); without it the confidence is
    ``confidence(k)`` (e.g. the median per-cell confidence) or NaN. For millions of regions
    :func:`regions_layer_batches` writes the same layer without holding every polygon.
    """
    import geopandas as gpd

    from ..change.regions import empty_regions

    if len(merged) == 0:
        return empty_regions(grid.crs)
    df = regions_columns(
        merged,
        cell_area_m2=cell_area_m2,
        method=method,
        epoch_a=epoch_a,
        epoch_b=epoch_b,
        volume_sigma=volume_sigma,
        confidence=confidence,
    )
    return gpd.GeoDataFrame(df, geometry=list(merged.geometry), crs=grid.crs)


class RegionBatches:
    """The ``changes`` layer of merged regions as GeoDataFrame batches (for :func:`geocd.io.vector.write_gpkg`).

    Written batch by batch, it is the layer :func:`regions_layer` gives (same rows, order,
    geometries and layer geometry type): ``geometry_type`` comes from a first pass that builds
    each batch's polygons and keeps only their types.
    """

    def __init__(self, merged: MergedRegions, grid: AOIGrid, columns, batch: int = 50_000):
        self.merged = merged
        self.grid = grid
        self.columns = columns
        self.batch = int(batch)
        self._gtype: str | None = None

    def __len__(self) -> int:
        return len(self.merged)

    @property
    def geometry_type(self) -> str:
        """The layer type pyogrio infers for the whole layer (mixed Polygon/MultiPolygon → MultiPolygon)."""
        import shapely

        if self._gtype is None:
            types: set[str] = set()
            for a in range(0, len(self), self.batch):
                g = self.merged.geometry.batch(a, a + self.batch)
                types |= set(shapely.get_type_id(g).tolist())
            names = {3: "Polygon", 6: "MultiPolygon"}
            found = {names.get(t, "Unknown") for t in types}
            self._gtype = (
                found.pop() if len(found) == 1 else ("MultiPolygon" if found <= set(names.values()) else "Unknown")
            )
        return self._gtype

    def __iter__(self):
        import geopandas as gpd

        for a in range(0, len(self), self.batch):
            b = min(a + self.batch, len(self))
            geom = self.merged.geometry.batch(a, b)
            yield gpd.GeoDataFrame(
                self.columns.iloc[a:b].reset_index(drop=True), geometry=list(geom), crs=self.grid.crs
            )


def regions_layer_batches(
    merged: MergedRegions,
    grid: AOIGrid,
    *,
    cell_area_m2: float,
    method: str = "",
    epoch_a: str = "",
    epoch_b: str = "",
    volume_sigma: Callable[[int], float] | None = None,
    confidence: Callable[[int], float] | None = None,
    batch: int = 50_000,
):
    """:func:`regions_layer` as a :class:`RegionBatches` (an empty layer stays a GeoDataFrame)."""
    from ..change.regions import empty_regions

    if len(merged) == 0:
        return empty_regions(grid.crs)
    df = regions_columns(
        merged,
        cell_area_m2=cell_area_m2,
        method=method,
        epoch_a=epoch_a,
        epoch_b=epoch_b,
        volume_sigma=volume_sigma,
        confidence=confidence,
    )
    return RegionBatches(merged, grid, df, batch)


def region_mask_window(
    merged: MergedRegions, k: int, label_reader: Callable[[Tile], np.ndarray], tile_grid: TileGrid
) -> tuple[np.ndarray, tuple[slice, slice]]:
    """Region ``k``'s cells as a bool window over its bounding box, from the tiles' label rasters.

    ``label_reader(tile)`` returns the tile's core label raster (+label for raised, −label for lowered).
    """
    r0, c0, r1, c1 = (int(v) for v in merged.bbox[k])
    out = np.zeros((r1 - r0, c1 - c0), bool)
    by_tile: dict[tuple[int, int], list[int]] = {}
    for ti, s, lab in merged.members[k]:
        by_tile.setdefault(ti, []).append(s * lab)
    for ti, labs in by_tile.items():
        t = tile_grid.tile(*ti)
        tr0, tc0, th, tw = t.core
        a = np.asarray(label_reader(t))
        i0, j0 = max(r0, tr0), max(c0, tc0)
        i1, j1 = min(r1, tr0 + th), min(c1, tc0 + tw)
        if i1 <= i0 or j1 <= j0:
            continue
        sub = a[i0 - tr0 : i1 - tr0, j0 - tc0 : j1 - tc0]
        out[i0 - r0 : i1 - r0, j0 - c0 : j1 - c0] |= np.isin(sub, labs)
    return out, (slice(r0, r1), slice(c0, c1))
