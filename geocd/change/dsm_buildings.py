"""Buildings without a footprint layer: building objects from a DSM, and their damage class.

For a city without a cadastre (disaster response), the pre-event DSM itself says where the buildings were:

1. **Ground model** (:func:`ground_model`): the progressive morphological filter of :mod:`geocd.terrain` on the
   gap-filled DSM.
2. **Building mask**: height above the ground ``≥ min_height_m`` (one storey); tree-like objects are dropped
   (``tree_rule``, :class:`DSMBuildingParams`). The default, ``"plane"``: an object is a tree when the median of
   its cells' best-of-nine 3 × 3 plane residual exceeds 7.5 cm (or the 75th percentile of that residual on
   the DSM's ground, if higher). A roof facet — flat or pitched — leaves the matcher's smoothed noise there,
   a crown its relief. Measured (docs/kahramanmaras.md, "The tree rule"): on the generated towns it finds
   62–77 % of the buildings (no tree rule: 68–83 %; the former ``"roughness"`` rule, relative to the
   ground's roughness, 0–6 %: the synthetic ground is 2–6 cm smooth), and on Kahramanmaraş it drops 9 of
   the 32 pre-event and 1 of the 21 post-event by-eye buildings the roughness rule dropped, and 41 of 60 /
   25 of 32 by-eye trees (roughness: all of them). ``"roughness"`` and ``"planarity"`` (the roof-planarity
   cue of :mod:`geocd.mpp`) remain as options. Only cells with a stereo height count.
3. **Objects** (:func:`building_objects`): touching blocks are split by a watershed of the distance
   transform (markers: its regional maxima above ``split_h_m``); objects smaller than ``min_area_m2`` dropped.
   Buildings wall to wall stay one object there; with a change test, :func:`building_layer` cuts every
   building-sized part of an object that changed with one sign out of it (:func:`split_changed_parts`), so a
   cleared building in a block is a building of its own, and joins a raised part to the new building of the
   later DSM it touches: one building per building where the change says where one ends.
4. **Outlines**: each object's raster outline, simplified (Douglas–Peucker at one posting) and replaced by
   its minimum rotated rectangle when that covers it well (rectangularity ≥ ``rect_min``).

:func:`classify_damage` then labels every building — from the DSM or from any OGR footprint layer — with
the per-cell result of a change test (the self-consistency test's ``ChangeResult``), in the one schema of
every building layer (:mod:`geocd.change.building_layer`):

* ``unobserved`` — too little of it observed in both epochs (as :mod:`geocd.change.buildings`);
* ``collapsed`` — mostly lowered (≥ ``min_changed`` of its observed cells at the report level) and its
  height after is at most ``collapse_ratio`` of the height before (or below one storey);
* ``partly collapsed`` — lowered cells cover ``min_changed`` … ``most`` of it and it is not collapsed (with
  ``changed_part``, off by default, a lowered part of at least the change map's mapping unit is enough: the
  changed-part rule of :mod:`geocd.change.buildings`; a part the plane tree rule calls vegetation on the DSM
  before — after, for a raised part — does not count);
* ``lowered`` — lowered over most (≥ ``most``) of it, standing above ``collapse_ratio`` of its height;
* ``new`` — mostly raised and at ground level before; ``raised`` — mostly raised otherwise;
* ``unchanged`` — otherwise.

Every building carries the confidence (percent, the team's convention) at which it changed — the highest
tested level at which its changed fraction reaches ``min_changed`` or it holds a changed part; 0 for a building
not changed at the report level, empty (NaN) for an unobserved one —, its heights above the ground before and
after (medians), Δz and the volume change ± σ. σ comes from the self-consistency model: a cell's σ(Δz) is its
68.3 % curve value (pixels of disparity, at its score) times its pixel-to-metre factor |Δz/Δ̃|; cells within one
matching window are treated as fully correlated, windows as independent. :func:`footprint_layer` adds to given
footprints the new buildings of the change map that stand outside all of them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from scipy import ndimage as ndi

from ..errors import ConfigError
from ..mpp.features import planar_cells, plane_residual
from ..terrain import fill_gaps
from ..terrain import ground_model as terrain_ground
from .building_layer import (
    CHANGED,
    CLASSES,
    NOT_OBSERVED,
    SOURCE_CHANGE_MAP,
    SOURCE_FOOTPRINTS,
    code_unobserved,
    empty_layer,
    footprints_with_ids,
    order_columns,
)
from .buildings import BuildingParams, classify_buildings, largest_parts

#: the building layer's classes (:data:`geocd.change.building_layer.CLASSES`)
DAMAGE_CLASSES = CLASSES
#: how :func:`building_objects` tells a tree from a building (see :class:`DSMBuildingParams`)
TREE_RULES = ("plane", "roughness", "planarity", "off")


@dataclass(frozen=True)
class DSMBuildingParams:
    """Building extraction from a DSM and damage classification (lengths in metres, areas in m²).

    ``tree_rule`` — which raised objects are trees, not buildings:

    * ``"plane"`` (default): the object's median best-of-nine plane residual (:func:`best_plane_residual`:
      each cell's best 3 × 3 plane fit among the nine that contain it, RMS residual along the normal) exceeds
      the threshold :func:`tree_threshold_m` — ``tree_residual_m`` (0.075 m), raised to the 75th percentile of
      the same residual on the DSM's ground cells when that is higher (a DSM noisier than the ones the
      threshold was measured on: an object as planar as most of the ground is not called a tree). A roof
      facet, flat or pitched, leaves the matcher's smoothed noise; a crown leaves its relief. The 0.075 m is a
      measured constant, not derived from a noise model: the equal-error point (buildings dropped = trees
      kept) of the per-object medians on the development set lies at 0.0725–0.075 m (sample_aoi and towns
      1–2, both epochs, truth; the Kahramanmaraş pre-event DSM, labels by eye), all DSMs of geocd's matcher
      at 0.5 m; held out: town 3 and the post-event DSM (docs/kahramanmaras.md, "The plane-residual tree
      rule") — for the 0.075 m only: the ground-percentile raise was added with those DSMs' figures in view.
      Other matchers or postings: measure it again (``bench/diag_dsm_tree_rule.py``);
    * ``"roughness"``: the object's median local roughness (:func:`roughness`) exceeds
      ``roughness_factor`` × the median roughness of the ground cells (the former default; on DSMs whose
      ground is much smoother than their roofs — generated towns — it drops every building);
    * ``"planarity"``: under half of its cells (with a height) lie on a planar 3 × 3 patch —
      :func:`geocd.mpp.features.planar_cells`: best of the nine plane fits containing the cell, residual along
      the normal, tolerance from the DSM's own low cells (median + 3 robust σ of their residuals); the ½ is
      the marked-point-process detector's rule for a roof's core. A pitched roof is planar per facet, a
      tree crown is not — on DSMs sharp enough to show it (see docs/kahramanmaras.md: not on that scene's);
    * ``"off"``: every raised object ≥ ``min_area_m2`` is kept.

    ``split_changed`` (on): with a change test, building-sized changed parts of epoch A's objects become
    buildings of their own and raised ones join the new building of epoch B they touch
    (:func:`split_changed_parts`); off: whole objects only (the layer as it was before the cut).

    ``split_steps`` (off): objects are also split where their surface steps by a storey
    (:func:`split_height_steps`). Measured with the cut of changed parts on (docs/kahramanmaras.md): on
    Kahramanmaraş 253 → 381 objects (unobserved 20 → 43: slivers along walls) and one of the 79 buildings
    marked unchanged lost — split off its block, it fell to the tree rule, and the new building beside it
    became its nearest object; on the generated towns it finds one more new building (town 3) and changes
    nothing else. Off until the pieces it makes pass the tree rule as their block did.
    """

    max_building_m: float = 60.0
    slope: float = 0.15
    dh0_m: float = 0.5
    dh_max_m: float = 5.0
    ground_block_m: float = 10.0
    min_height_m: float = 3.0
    roughness_factor: float = 2.5
    tree_rule: str = "plane"
    tree_residual_m: float = 0.075
    min_area_m2: float = 40.0
    split_h_m: float = 1.0
    rect_min: float = 0.8
    collapse_ratio: float = 0.3
    most: float = 0.6
    min_changed: float = 0.15
    min_observed: float = 0.3
    correlation_m: float = 3.5
    changed_part: bool = False
    split_changed: bool = True
    split_steps: bool = False

    def __post_init__(self):
        if self.tree_rule not in TREE_RULES:
            raise ConfigError(f"tree_rule {self.tree_rule!r} is not one of {TREE_RULES}: choose one of them")
        if not self.tree_residual_m > 0:
            raise ConfigError(f"tree_residual_m must be > 0 (m), got {self.tree_residual_m}")


def ground_model(
    dsm: np.ndarray, posting_m: float, params: DSMBuildingParams = DSMBuildingParams()
) -> tuple[np.ndarray, np.ndarray]:
    """The ground under a DSM (:func:`geocd.terrain.ground_model` with the extraction's ground constants).

    Returns
    -------
    dtm : float32 (rows, cols), the ground height (m, same datum as the DSM)
    ground : bool (rows, cols), cells classified as ground (valid DSM cells only)
    """
    return terrain_ground(dsm, posting_m, params)


def roughness(z: np.ndarray, posting_m: float) -> np.ndarray:
    """Local roughness (m): std of the surface minus its 3 × 3 mean over a 2 m window."""
    zf = fill_gaps(z)
    hp = zf - ndi.uniform_filter(zf, 3)
    k = max(3, int(round(2.0 / posting_m)) | 1)
    return np.sqrt(np.maximum(ndi.uniform_filter(hp * hp, k), 0.0)).astype(np.float32)


def best_plane_residual(z: np.ndarray, posting_m: float) -> np.ndarray:
    """Best-of-nine plane residual (m): for each cell, the smallest RMS residual (along the plane's normal) of
    the nine 3 × 3 plane fits that contain it (:func:`geocd.mpp.features.plane_residual`). A cell on a roof
    ridge or a facet's border lies in a window of its facet; NaN where no window has a height in every cell."""
    res = plane_residual(z, posting_m)
    best = ndi.grey_erosion(np.where(np.isfinite(res), res, np.inf), size=3, mode="nearest")
    return np.where(np.isfinite(best), best, np.nan).astype(np.float32)


def tree_threshold_m(best: np.ndarray, ground: np.ndarray, params: DSMBuildingParams = DSMBuildingParams()) -> float:
    """The ``"plane"`` rule's threshold (m) on an object's median best-of-nine residual: ``tree_residual_m``,
    or the 75th percentile of ``best`` over the ``ground`` cells when that is higher."""
    g = ground & np.isfinite(best)
    q75 = float(np.percentile(best[g], 75)) if g.sum() >= 100 else 0.0
    return max(params.tree_residual_m, q75)


def building_objects(
    dsm: np.ndarray,
    dtm: np.ndarray,
    posting_m: float,
    params: DSMBuildingParams = DSMBuildingParams(),
    ground: np.ndarray | None = None,
) -> np.ndarray:
    """int32 labels (0 = none) of building objects in a DSM over a ground model (``ground``: its ground cells)."""
    from skimage.morphology import h_maxima
    from skimage.segmentation import watershed

    ndsm = fill_gaps(dsm) - dtm
    mask = ndsm >= params.min_height_m
    mask = ndi.binary_opening(mask, structure=np.ones((3, 3), bool), iterations=max(1, int(round(1.0 / posting_m))))
    mask = ndi.binary_fill_holes(mask)
    dist = ndi.distance_transform_edt(mask) * posting_m
    markers, _ = ndi.label(h_maxima(dist, params.split_h_m))
    labels = watershed(-dist, markers, mask=mask)
    if params.split_steps:
        labels = split_height_steps(
            labels, fill_gaps(dsm), posting_m, params.min_height_m, int(math.ceil(params.min_area_m2 / posting_m**2))
        )
    n = int(labels.max())
    if n == 0:
        return labels.astype(np.int32)
    sizes = np.bincount(labels.ravel(), minlength=n + 1)
    drop = np.zeros(n + 1, bool)
    drop[1:] = sizes[1:] * posting_m * posting_m < params.min_area_m2
    drop[1:] |= tree_objects(dsm, dtm, labels, posting_m, params, ground=ground)
    labels[drop[labels]] = 0
    # renumber 1..n
    u = np.unique(labels)
    u = u[u > 0]
    lut = np.zeros(labels.max() + 1, dtype=np.int32)
    lut[u] = np.arange(1, u.size + 1)
    return lut[labels]


def split_height_steps(
    labels: np.ndarray, z_m: np.ndarray, posting_m: float, step_m: float, min_cells: int
) -> np.ndarray:
    """Split objects where their surface steps by a storey or more: buildings of different heights wall to wall.

    Inside each object the surface (gap-filled, 3 × 3 median) is cut into plateaus: seeds are the cells less
    steep than 45° (a roof facet; a wall between two roofs is steeper), grown over the object by a watershed of
    the slope. Neighbouring plateaus whose median heights differ by less than ``step_m`` join (the facets of a
    pitched roof, a roof and its parapet), and a plateau smaller than ``min_cells`` joins the neighbour closest
    in height; what is left is one object per height level.

    Parameters
    ----------
    labels : int (rows, cols), objects 1 … n, 0 elsewhere
    z_m : float (rows, cols), the surface (m, no NaN)
    step_m : the least height step between two buildings (m; the extraction's storey, ``min_height_m``)
    min_cells : the least building (cells)

    Returns
    -------
    int32 (rows, cols), objects 1 … m (m ≥ n), 0 elsewhere.
    """
    from skimage.segmentation import watershed

    labels = np.asarray(labels, np.int32)
    inside = labels > 0
    if not inside.any():
        return labels
    zs = ndi.median_filter(np.asarray(z_m, np.float64), size=3)
    gy, gx = np.gradient(zs, posting_m)
    slope = np.hypot(gx, gy)
    eight = np.ones((3, 3), bool)
    seeds, _ = ndi.label(inside & (slope < 1.0), structure=eight)
    regions = watershed(slope, seeds, mask=inside)
    # a region never spans two objects
    key = regions.astype(np.int64) * (int(labels.max()) + 1) + labels
    _, inv = np.unique(np.where(inside, key, -1), return_inverse=True)
    regions = inv.reshape(labels.shape).astype(np.int32)  # 0 = outside (the key -1 sorts first)
    n = int(regions.max())
    if n <= 1:
        return labels
    idx = np.arange(1, n + 1)
    med = np.concatenate([[np.nan], np.asarray(ndi.median(zs, regions, idx), float)])
    size = np.bincount(regions.ravel(), minlength=n + 1).astype(np.int64)
    obj = np.zeros(n + 1, np.int64)
    obj[regions.ravel()] = labels.ravel()
    pairs = set()
    for a, b in ((regions[:, :-1], regions[:, 1:]), (regions[:-1, :], regions[1:, :])):
        d = (a != b) & (a > 0) & (b > 0)
        pairs.update(zip(a[d].tolist(), b[d].tolist()))
    pairs = [(i, j) for i, j in pairs if obj[i] == obj[j]]
    parent = np.arange(n + 1)

    def find(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for i, j in sorted(pairs, key=lambda p: abs(med[p[0]] - med[p[1]])):
        if abs(med[i] - med[j]) < step_m:
            ri, rj = find(i), find(j)
            if ri != rj:
                parent[rj] = ri
    for _ in range(3):  # plateaus smaller than a building join the neighbour closest in height
        root = np.array([find(i) for i in range(n + 1)])
        total = np.bincount(root, weights=size, minlength=n + 1)
        moved = False
        for i, j in sorted(pairs, key=lambda p: abs(med[p[0]] - med[p[1]])):
            ri, rj = find(i), find(j)
            if ri != rj and (total[ri] < min_cells or total[rj] < min_cells):
                parent[rj] = ri
                total[ri] += total[rj]
                total[rj] = total[ri]
                moved = True
        if not moved:
            break
    root = np.array([find(i) for i in range(n + 1)])
    out = np.zeros(labels.shape, np.int32)
    _, ids = np.unique(root[regions[inside]], return_inverse=True)
    out[inside] = ids.ravel() + 1
    return out


def plane_rule(
    dsm: np.ndarray,
    dtm: np.ndarray,
    posting_m: float,
    params: DSMBuildingParams = DSMBuildingParams(),
    ground: np.ndarray | None = None,
) -> tuple[np.ndarray, float]:
    """The ``"plane"`` tree rule's cell figure and threshold on a DSM: (best-of-nine plane residual (rows, cols)
    in m, :func:`tree_threshold_m` from the DSM's ground cells). An object (or a changed part) whose median
    figure exceeds the threshold is a tree. ``ground``: ground cells (default: within ``dh0_m`` + 0.5 m of
    ``dtm``)."""
    has_z = np.isfinite(dsm)
    zf = fill_gaps(dsm)
    if ground is None:
        ground = has_z & (np.abs(zf - dtm) < params.dh0_m + 0.5)
    best = best_plane_residual(dsm, posting_m)
    return best, tree_threshold_m(best, ground & has_z & (zf - dtm < params.min_height_m), params)


def tree_objects(
    dsm: np.ndarray,
    dtm: np.ndarray,
    labels: np.ndarray,
    posting_m: float,
    params: DSMBuildingParams = DSMBuildingParams(),
    ground: np.ndarray | None = None,
) -> np.ndarray:
    """bool (n,): which of the objects ``labels`` (1 … n) ``params.tree_rule`` calls a tree (see
    :class:`DSMBuildingParams`). Only cells with a stereo height count; an object without any is a tree."""
    n = int(labels.max())
    idx = np.arange(1, n + 1)
    has_z = np.isfinite(dsm)
    if n == 0 or params.tree_rule == "off":
        return np.zeros(n, bool)
    if params.tree_rule == "planarity":
        planar, _ = planar_cells(dsm, fill_gaps(dsm) - dtm, has_z, params.min_height_m, posting_m)
        known = np.isfinite(planar)
        n_known = np.asarray(ndi.sum(known, labels, idx))
        n_planar = np.asarray(ndi.sum(np.where(known, planar, 0.0), labels, idx))
        return ~(n_planar >= 0.5 * np.maximum(n_known, 1)) | (n_known == 0)
    if ground is None:
        ground = has_z & (np.abs(fill_gaps(dsm) - dtm) < params.dh0_m + 0.5)
    if params.tree_rule == "plane":
        best, thr = plane_rule(dsm, dtm, posting_m, params, ground)
        known = np.isfinite(best)
        lab_b = np.where(known, labels, 0)
        med = np.asarray(ndi.median(np.where(known, best, 0.0), lab_b, idx), dtype=float)
        med = np.where(np.bincount(lab_b.ravel(), minlength=n + 1)[1:] > 0, med, np.inf)
        return med > thr
    rough = roughness(dsm, posting_m)
    g = ground & has_z
    floor = float(np.median(rough[g])) if g.any() else float(np.median(rough))
    lab_z = np.where(has_z, labels, 0)
    med_rough = (
        np.array([np.median(v) if v.size else np.inf for v in (rough[lab_z == i] for i in idx)])
        if n < 5000
        else np.asarray(ndi.median(rough, lab_z, index=idx))
    )
    med_rough = np.where(np.bincount(lab_z.ravel(), minlength=n + 1)[1:] > 0, med_rough, np.inf)
    return med_rough > params.roughness_factor * floor


def tree_cells(dsm: np.ndarray, posting_m: float, params: DSMBuildingParams = DSMBuildingParams()) -> np.ndarray:
    """Cells of the objects of a DSM that ``params.tree_rule`` drops as trees.

    The objects are those of :func:`buildings_from_dsm` before the tree rule (≥ ``min_height_m`` above the
    DSM's own ground model, ≥ ``min_area_m2``); the ones the rule calls trees are returned as a mask — what a
    damage layer built from this DSM leaves out as vegetation (felled, planted or standing trees).

    Parameters
    ----------
    dsm : (rows, cols) float, heights in metres (NaN: no height)
    posting_m : grid posting in metres

    Returns
    -------
    bool (rows, cols); all False with ``tree_rule="off"``.
    """
    dtm, ground = ground_model(dsm, posting_m, params)
    labels = building_objects(dsm, dtm, posting_m, replace(params, tree_rule="off"), ground=ground)
    is_tree = np.concatenate([[False], tree_objects(dsm, dtm, labels, posting_m, params, ground=ground)])
    return is_tree[labels]


def outlines(labels: np.ndarray, grid, params: DSMBuildingParams = DSMBuildingParams()):
    """Regularised polygons of labelled objects: GeoDataFrame (building_id, rectangularity, geometry)."""
    import geopandas as gpd
    from rasterio.features import shapes
    from shapely import STRtree
    from shapely.geometry import shape
    from shapely.ops import unary_union

    polys: dict[int, list] = {}
    for geom, val in shapes(labels.astype(np.int32), mask=labels > 0, transform=grid.transform):
        polys.setdefault(int(val), []).append(shape(geom))
    keys = sorted(polys)
    raw = []
    for k in keys:
        g = unary_union(polys[k]).buffer(0)
        if g.geom_type == "MultiPolygon":
            g = max(g.geoms, key=lambda p: p.area)
        raw.append(g)
    tree = STRtree(raw)
    cell = grid.posting_m * grid.posting_m
    rows = []
    for i, k in enumerate(keys):
        g = raw[i].simplify(grid.posting_m, preserve_topology=True)
        rect = g.minimum_rotated_rectangle
        rectangularity = g.area / rect.area if rect.area > 0 else 0.0
        # the rectangle, unless it reaches over a neighbouring object (touching buildings stay apart)
        if rectangularity >= params.rect_min and not any(
            rect.intersection(raw[j]).area > cell for j in tree.query(rect) if j != i
        ):
            g = rect
        rows.append({"building_id": k, "rectangularity": round(float(rectangularity), 3), "geometry": g})
    return (
        gpd.GeoDataFrame(rows, geometry="geometry", crs=grid.crs)
        if rows
        else gpd.GeoDataFrame({"building_id": [], "rectangularity": []}, geometry=[], crs=grid.crs)
    )


def buildings_from_dsm(dsm: np.ndarray, grid, params: DSMBuildingParams = DSMBuildingParams()):
    """Building polygons, the ground model and the object labels from a DSM on ``grid``.

    Returns
    -------
    (GeoDataFrame of regularised building outlines, dtm float32, labels int32)
    """
    dtm, ground = ground_model(dsm, grid.posting_m, params)
    labels = building_objects(dsm, dtm, grid.posting_m, params, ground=ground)
    return outlines(labels, grid, params), dtm, labels


def split_changed_parts(
    labels: np.ndarray,
    change_report: np.ndarray,
    change_low: np.ndarray,
    posting_m: float,
    params: DSMBuildingParams = DSMBuildingParams(),
    keep=None,
) -> tuple[np.ndarray, int]:
    """One building per building: the changed parts of DSM objects become objects of their own.

    A DSM object can hold several buildings (a block the distance watershed does not split). When one of them
    is cleared or built, the object's changed share is small (a 300 m² cleared plot in a 5,000 m² block is
    6 %) and the object would be called unchanged. Here every 8-connected part of an object that changed with
    one sign at the reported level (``change_report``) and covers at least a building (``min_area_m2``) is cut
    out of it: grown over the object's cells changed with the same sign at the lowest tested level
    (``change_low``; a building's edges change less surely than its middle), holes filled. What is left of the
    object keeps its label when it still covers ``min_area_m2`` (each such connected remainder is an object;
    a block cut in two by a cleared building gives two); smaller leftovers join the part they touch. A part the
    ``keep`` test rejects (e.g. a felled tree) stays in its object. The constants are the extraction's own
    (``min_area_m2``), nothing new.

    Parameters
    ----------
    labels : int (rows, cols), objects 1 … n (:func:`building_objects`), 0 elsewhere
    change_report, change_low : int (rows, cols), +1 raised / −1 lowered at the reported and at the lowest tested
        level (any other value: not changed)
    keep : callable ``(sign, rows, cols) -> bool``, optional (:func:`geocd.change.buildings.largest_parts`)

    Returns
    -------
    labels : int32 (rows, cols), the objects after the cuts (the cut parts numbered after the others)
    parts : dict {label: +1 raised / −1 lowered} of the parts cut out
    """
    labels = np.asarray(labels, np.int32)
    n = int(labels.max())
    if n == 0:
        return labels, {}
    min_cells = max(1, int(math.ceil(params.min_area_m2 / (posting_m * posting_m))))
    eight = np.ones((3, 3), bool)
    out = labels.copy()
    nxt = n + 1
    cut: dict[int, int] = {}
    for i, sl in enumerate(ndi.find_objects(labels, max_label=n)):
        if sl is None:
            continue
        k = i + 1
        inside = labels[sl] == k
        if inside.sum() < 2 * min_cells:  # no room for a part and a remainder
            continue
        parts = np.zeros(inside.shape, np.int32)
        signs = {}
        for s in (1, -1):
            core, nc = ndi.label(inside & (change_report[sl] == s), structure=eight)
            if not nc:
                continue
            sizes = np.bincount(core.ravel())[1:]
            if not (sizes >= min_cells).any():
                continue
            grown, _ = ndi.label(inside & ((change_low[sl] == s) | (change_report[sl] == s)), structure=eight)
            for j in np.nonzero(sizes >= min_cells)[0]:
                g = np.unique(grown[core == j + 1])
                part = ndi.binary_fill_holes(np.isin(grown, g[g > 0])) & inside & (parts == 0)
                if part.sum() < min_cells:
                    continue
                if keep is not None:
                    rr, cc = np.nonzero(part)
                    if not keep(s, rr + sl[0].start, cc + sl[1].start):
                        continue
                parts[part] = len(signs) + 1
                signs[len(signs) + 1] = s
        if not signs:
            continue
        rest, nr = ndi.label(inside & (parts == 0))
        rest_sizes = np.bincount(rest.ravel(), minlength=nr + 1)
        big = [r for r in range(1, nr + 1) if rest_sizes[r] >= min_cells]
        if not big:  # the whole object changed: it stays one object
            continue
        local = np.where(inside, k, 0).astype(np.int32)
        for r in big[1:]:  # each building-sized remainder its own object; the first keeps the label
            local[rest == r] = nxt
            nxt += 1
        for p, sign in signs.items():
            local[parts == p] = nxt
            cut[nxt] = sign
            nxt += 1
        # leftovers smaller than a building join the nearest part or remainder
        small = inside & (parts == 0) & ~np.isin(rest, big)
        if small.any():
            _, (ri, ci) = ndi.distance_transform_edt(~(inside & ~small), return_indices=True)
            local[small] = local[ri[small], ci[small]]
        out[sl][inside] = local[inside]
    return out, cut


def dsm_objects(dsm: np.ndarray, posting_m: float, params: DSMBuildingParams = DSMBuildingParams()) -> np.ndarray:
    """int32 (rows, cols): the building objects of a DSM over its own ground model (:func:`building_objects`)."""
    dtm, ground = ground_model(dsm, posting_m, params)
    return building_objects(dsm, dtm, posting_m, params, ground=ground)


def _join_raised_parts(
    lab_a: np.ndarray,
    lab_new: np.ndarray,
    raised_report: np.ndarray,
    raised_low: np.ndarray,
    min_cells: int,
) -> tuple[np.ndarray, np.ndarray]:
    """A new building seen partly over an epoch-A object is one building: the cells of A's objects raised at the
    lowest tested level (``raised_low``), connected (8-neighbours) to a cell raised at the reported level
    (``raised_report``) and touching a new part of B (:func:`new_parts`), join that new part, whatever their
    size; an A object left with fewer than ``min_cells`` cells that touches a new part joins it too. Returns the
    two label rasters (copies)."""
    lab_a, lab_new = lab_a.copy(), lab_new.copy()
    if not lab_new.any():
        return lab_a, lab_new
    eight = np.ones((3, 3), bool)
    comp, nc = ndi.label((lab_a > 0) & (raised_low | raised_report), structure=eight)
    if nc:
        idx = np.arange(1, nc + 1)
        near_new = ndi.grey_dilation(lab_new, footprint=eight)
        sure = np.asarray(ndi.maximum(raised_report, comp, idx)) > 0
        to = np.where(sure, np.asarray(ndi.maximum(near_new, comp, idx)), 0).astype(np.int32)
        dest = np.concatenate([[0], to])[comp]
        lab_new = np.where(dest > 0, dest, lab_new)
        lab_a = np.where(dest > 0, 0, lab_a)
    n = int(lab_a.max())
    if n:
        idx = np.arange(1, n + 1)
        sizes = np.bincount(lab_a.ravel(), minlength=n + 1)[1:]
        near_new = ndi.grey_dilation(lab_new, footprint=eight)
        to = np.where((sizes > 0) & (sizes < min_cells), np.asarray(ndi.maximum(near_new, lab_a, idx)), 0)
        dest = np.concatenate([[0], to]).astype(np.int32)[lab_a]
        lab_new = np.where(dest > 0, dest, lab_new)
        lab_a = np.where(dest > 0, 0, lab_a)
    return lab_a, lab_new


def _stack_labels(lab_a: np.ndarray, lab_new: np.ndarray) -> tuple[np.ndarray, int]:
    """One raster of both: A's objects renumbered 1 … n_a, then B's new parts n_a + 1 …; returns (labels, n_a)."""
    out = np.zeros(lab_a.shape, np.int32)
    n_a = 0
    for lab in (lab_a, lab_new):
        u = np.unique(lab)
        u = u[u > 0]
        lut = np.zeros(int(lab.max()) + 1, np.int32)
        lut[u] = np.arange(n_a + 1, n_a + 1 + u.size)
        out = np.where(lab > 0, lut[lab], out)
        n_a = n_a + u.size if lab is lab_a else n_a
    return out, n_a


def new_parts(
    z_a: np.ndarray,
    z_b: np.ndarray,
    dtm: np.ndarray,
    labels_b: np.ndarray,
    posting_m: float,
    params: DSMBuildingParams = DSMBuildingParams(),
    labels_a: np.ndarray | None = None,
) -> np.ndarray:
    """Parts of epoch B's building objects that stand where epoch A's surface was at ground level.

    A building built between the dates is an object of the later DSM on cells that stand at least
    ``min_height_m`` above the ground model in B and less than that in A (and lie outside epoch A's objects,
    ``labels_a``); both heights over the same ground model (B's objects come from B's own). Judged per cell,
    not per object: an object of B that joins a new building to standing ones (a block the watershed
    does not split) still yields the new part. The parts are opened like the objects themselves
    (one metre), and those smaller than ``min_area_m2`` dropped — the extraction's own constants, nothing
    new. Cells without a height count by the nearest height of their epoch (as :func:`building_objects`).

    Parameters
    ----------
    z_a, z_b : float (rows, cols), the two epochs' surfaces (m; NaN where unobserved)
    dtm : float (rows, cols), the ground model (m)
    labels_b : int (rows, cols), epoch B's building objects (:func:`building_objects`)
    posting_m : the grid's posting (m)
    labels_a : int (rows, cols), optional, epoch A's building objects

    Returns
    -------
    int32 (rows, cols): the new parts 1 … n, 0 elsewhere.
    """
    ha = fill_gaps(z_a) - dtm
    hb = fill_gaps(z_b) - dtm
    part = (np.asarray(labels_b) > 0) & (ha < params.min_height_m) & (hb >= params.min_height_m)
    if labels_a is not None:
        part &= np.asarray(labels_a) == 0
    part = ndi.binary_opening(part, structure=np.ones((3, 3), bool), iterations=max(1, int(round(1.0 / posting_m))))
    lab, n = ndi.label(part)
    if n:
        sizes = np.bincount(lab.ravel(), minlength=n + 1)
        small = sizes * posting_m * posting_m < params.min_area_m2
        small[0] = True
        lab[small[lab]] = 0
        u = np.unique(lab)
        u = u[u > 0]
        lut = np.zeros(n + 1, np.int32)
        lut[u] = np.arange(1, u.size + 1)
        lab = lut[lab]
    return lab.astype(np.int32)


def new_objects(
    z_a: np.ndarray,
    z_b: np.ndarray,
    dtm: np.ndarray,
    labels_b: np.ndarray,
    grid,
    params: DSMBuildingParams = DSMBuildingParams(),
    labels_a: np.ndarray | None = None,
):
    """The outlines (:func:`outlines`) of :func:`new_parts`: GeoDataFrame, one row per new part."""
    return outlines(new_parts(z_a, z_b, dtm, labels_b, grid.posting_m, params, labels_a), grid, params)


def _sigma_dz(result, model) -> np.ndarray:
    """Per-cell 1-σ of Δz (m) from the model's 68.3 % curve and the cell's |Δz/Δ̃|."""
    q = 68.27
    if q not in model.confidences:
        model.add_confidence(q)
    thr = model.threshold(np.nan_to_num(result.score, nan=np.nanmax(result.score)), q)
    with np.errstate(invalid="ignore", divide="ignore"):
        k = np.abs(result.dz_m / result.dtilde)
    k = np.where(np.isfinite(k) & (np.abs(result.dtilde) > 1e-3), k, np.nan)
    med_k = np.nanmedian(k) if np.isfinite(k).any() else np.nan
    k = np.where(np.isfinite(k), k, med_k)
    return (thr * k).astype(np.float32)


def _not_a_tree(z_a: np.ndarray, z_b: np.ndarray, dtm: np.ndarray, posting_m: float, params: DSMBuildingParams):
    """The changed-part rule's test that a part is not vegetation: with the ``"plane"`` tree rule, a lowered
    part whose pre-event surface (a raised part: post-event) the rule would call a tree — its cells' median
    best-of-nine plane residual above the rule's threshold on that DSM — does not count (a felled or planted
    tree inside a building object's outline is not building damage). Other tree rules: every part counts."""
    if params.tree_rule != "plane":
        return None
    fig = {-1: plane_rule(z_a, dtm, posting_m, params), 1: plane_rule(z_b, dtm, posting_m, params)}

    def keep(sign, rows, cols) -> bool:
        best, thr = fig[sign]
        v = best[rows, cols]
        v = v[np.isfinite(v)]
        return bool(v.size) and float(np.median(v)) <= thr

    return keep


def classify_damage(
    buildings,
    result,
    grid,
    *,
    z_a: np.ndarray,
    z_b: np.ndarray,
    dtm: np.ndarray | None = None,
    model=None,
    report_confidence: float = 99.0,
    params: DSMBuildingParams = DSMBuildingParams(),
    id_field: str | None = None,
    building_params: BuildingParams | None = None,
    sigma_dz_m: np.ndarray | None = None,
):
    """The building layer (:mod:`geocd.change.building_layer`): class, confidence (percent), heights and volume ± σ
    of every building.

    Parameters
    ----------
    buildings : GeoDataFrame of polygons (from :func:`buildings_from_dsm` or any OGR footprint layer); its
        ``source`` column, if any, is kept (default :data:`~geocd.change.building_layer.SOURCE_FOOTPRINTS`)
    result : geocd.consistency.ChangeResult on ``grid``, or any object with ``dz_m``, ``observed``,
        ``confidences``, ``changed_at(level)`` and ``min_region_cells`` (:class:`LevelMasks`)
    z_a, z_b : float (rows, cols), the two epochs' surfaces (m)
    dtm : float (rows, cols), optional
        Ground model (m) for the heights above ground and the ground-level tests; None: the median of a
        ``ring_m`` ring around each building (outside every building), per epoch.
    model : SelfConsistencyModel, optional (for σ of the volume)
    building_params : BuildingParams, optional
        The footprint rules' parameters (``min_observed``, ``min_changed``, ``min_inside``, ``ground_tol_m``,
        ``ring_m``, ``changed_part``); default: ``params``' ``min_observed``, ``min_changed`` and ``changed_part``.
    sigma_dz_m : float (rows, cols), optional
        Per-cell 1σ of Δz (m) for the volume's σ instead of the model's.

    Returns
    -------
    GeoDataFrame with the columns of :data:`geocd.change.building_layer.NAMES` (+ the source's attributes as
    ``src_*``), geometry.
    """
    import geopandas as gpd
    import pandas as pd
    from rasterio.features import rasterize

    from ..consistency import CHANGE_NODATA

    gdf = buildings.to_crs(grid.crs).reset_index(drop=True)
    if not len(gdf):
        return empty_layer(grid.crs)
    observed = np.asarray(result.observed, bool)
    levels = sorted(result.confidences)
    if report_confidence not in levels:
        raise ValueError(f"report confidence {report_confidence} is not a tested level {levels}")
    cm = np.where(observed, result.changed_at(report_confidence), CHANGE_NODATA).astype(np.int16)
    bp = building_params or BuildingParams(
        min_observed=params.min_observed, min_changed=params.min_changed, changed_part=params.changed_part
    )
    mmu = int(result.min_region_cells)
    keep = _not_a_tree(z_a, z_b, dtm, grid.posting_m, params) if (bp.changed_part and dtm is not None) else None
    base = classify_buildings(
        gdf,
        cm,
        result.dz_m,
        grid,
        z_a=z_a,
        z_b=z_b,
        dem_m=dtm,
        params=bp,
        id_field=id_field,
        confidence_level=report_confidence,
        detect_new=False,
        min_part_cells=mmu,
        part_keep=keep,
    )
    labels = rasterize(
        [(g, i + 1) for i, g in enumerate(gdf.geometry)],
        out_shape=grid.shape,
        transform=grid.transform,
        fill=0,
        dtype="int32",
    )
    n = len(gdf)
    idx = np.arange(1, n + 1)
    # highest tested level at which the building is changed
    conf = np.zeros(n)
    n_obs = ndi.sum(observed, labels, idx)
    for c in levels:
        signed = np.where(observed, result.changed_at(c), 0)
        frac = np.asarray(ndi.sum((signed == 1) | (signed == -1), labels, idx)) / np.maximum(n_obs, 1)
        hit = frac >= bp.min_changed
        if bp.changed_part:
            hit |= largest_parts(signed, labels, n, keep=keep)[0] >= mmu
        conf = np.where(hit, c, conf)
    if sigma_dz_m is not None:
        sig = np.asarray(sigma_dz_m, np.float32)
    else:
        sig = _sigma_dz(result, model) if model is not None else None
    cell = grid.cell_area_m2
    corr = max(1, int(round(params.correlation_m / grid.posting_m)))
    ring = max(1, int(round(bp.ring_m / grid.posting_m)))
    za, zb = np.asarray(z_a, float), np.asarray(z_b, float)
    if dtm is not None:
        ha, hb = za - dtm, zb - dtm
    out_rows = []
    slices = ndi.find_objects(labels, max_label=n)
    empty = (slice(0, 0), slice(0, 0))
    for i in range(n):
        sl = slices[i] or empty
        inside = labels[sl] == (i + 1)
        b = base.iloc[i]
        obs = inside & observed[sl]
        if dtm is not None:
            h_before, h_after = _median(ha[sl][inside]), _median(hb[sl][inside])
        else:
            h_before, h_after = _ring_heights(labels, i + 1, sl, ring, za, zb)
        dz = result.dz_m[sl][obs]
        n_in = int(inside.sum())
        # volume: observed cells' Δz, the unobserved cells of the footprint at the observed mean
        mean_dz = float(np.mean(dz)) if dz.size else np.nan
        vol = float(mean_dz * n_in * cell) if dz.size else np.nan
        vsig = np.nan
        if sig is not None and dz.size:
            rr, cc = np.nonzero(obs)
            blocks = (rr // corr) * (grid.shape[1] // corr + 1) + cc // corr
            s = sig[sl][obs].astype(float)
            s_block = np.bincount(blocks, weights=np.where(np.isfinite(s), s, 0.0))
            # scale to the whole footprint like the volume
            vsig = float(math.sqrt(float(np.sum(s_block**2))) * cell * n_in / max(dz.size, 1))
        cls = str(b["class"])
        rule = str(b.get("rule", ""))
        fl = float(np.nan_to_num(b["frac_lowered"]))
        fr = float(np.nan_to_num(b["frac_raised"]))
        if cls in ("lowered", "demolished"):
            ratio = h_after / h_before if (np.isfinite(h_before) and h_before > 0) else np.nan
            if cls == "demolished" and not np.isfinite(h_after):
                cls = "collapsed"  # at ground level after by the ground test, no height to say otherwise
            elif (np.isfinite(ratio) and ratio <= params.collapse_ratio) or (np.isfinite(h_after) and h_after < 2.5):
                cls = "collapsed"
                rule += (
                    f"; {h_after:.1f} m above ground after vs {h_before:.1f} m before (≤ {params.collapse_ratio:g}×)"
                )
            elif fl < params.most:
                cls = "partly collapsed"
                rule += f"; lowered on {100 * fl:.0f}% of it (< {100 * params.most:g}%)"
            else:
                cls = "lowered"
                rule += f"; lowered on {100 * fl:.0f}% of it, {h_after:.1f} m of {h_before:.1f} m left"
        elif cls == "raised" and np.isfinite(h_before) and h_before < 2.5:
            cls = "new"
            rule += f"; {h_before:.1f} m above ground before"
        c_pct = float(conf[i]) if cls in CHANGED else (np.nan if cls in NOT_OBSERVED else 0.0)
        rec = {
            "building_id": b["building_id"],
            "source": str(gdf["source"].iloc[i]) if "source" in gdf.columns else SOURCE_FOOTPRINTS,
            "class": cls,
            "confidence_pct": c_pct,
            "rule": rule,
            "frac_observed": b["frac_observed"],
            "frac_changed": b["frac_changed"],
            "frac_lowered": fl,
            "frac_raised": fr,
            "height_before_m": round(h_before, 2),
            "height_after_m": round(h_after, 2),
            "mean_dz_m": round(mean_dz, 2) if np.isfinite(mean_dz) else np.nan,
            "volume_change_m3": round(vol, 1) if np.isfinite(vol) else np.nan,
            "volume_sigma_m3": round(vsig, 1) if np.isfinite(vsig) else np.nan,
            "volume_lost_m3": round(max(-vol, 0.0), 1) if np.isfinite(vol) else np.nan,
            "area_m2": round(n_in * cell, 1),
        }
        out_rows.append(rec)
    out = gpd.GeoDataFrame(pd.DataFrame(out_rows), geometry=gdf.geometry.values, crs=gdf.crs)
    for c in gdf.columns:
        if c not in out.columns and c != gdf.geometry.name:
            out[f"src_{c}"] = gdf[c].values
    return order_columns(code_unobserved(out))


def _median(v: np.ndarray) -> float:
    v = v[np.isfinite(v)]
    return float(np.median(v)) if v.size else np.nan


def _ring_heights(labels: np.ndarray, k: int, sl, ring: int, z_a: np.ndarray, z_b: np.ndarray) -> tuple[float, float]:
    """Building ``k``'s median height in each epoch above the median of a ``ring``-cell ring around it (outside
    every building), on the window ``sl`` grown by the ring."""
    if sl[0].stop <= sl[0].start:
        return np.nan, np.nan
    H, W = labels.shape
    g = (
        slice(max(0, sl[0].start - ring - 1), min(H, sl[0].stop + ring + 1)),
        slice(max(0, sl[1].start - ring - 1), min(W, sl[1].stop + ring + 1)),
    )
    lab = labels[g]
    inside = lab == k
    around = ndi.binary_dilation(inside, iterations=ring) & (lab == 0)
    out = []
    for z in (z_a, z_b):
        zz = z[g]
        out.append(_median(zz[inside]) - _median(zz[around]))
    return out[0], out[1]


@dataclass(frozen=True)
class LevelMasks:
    """A change test seen by :func:`classify_damage` through its signed change masks, one per tested level.

    For methods without a :class:`~geocd.consistency.ChangeResult` (``geocd demdiff``): ``masks`` maps a level
    (percent) to an int8 mask (+1 raised, −1 lowered, 0 unchanged, any other value unobserved).
    """

    dz_m: np.ndarray
    masks: dict
    min_region_cells: int = 1

    @property
    def confidences(self) -> tuple:
        return tuple(sorted(self.masks))

    @property
    def observed(self) -> np.ndarray:
        m = np.asarray(next(iter(self.masks.values())))
        return (m >= -1) & (m <= 1)

    def changed_at(self, level: float) -> np.ndarray:
        return self.masks[level]


def footprint_layer(
    footprints,
    result,
    grid,
    *,
    z_a: np.ndarray,
    z_b: np.ndarray,
    dtm: np.ndarray | None = None,
    model=None,
    report_confidence: float = 99.0,
    params: DSMBuildingParams = DSMBuildingParams(),
    building_params: BuildingParams | None = None,
    id_field: str | None = None,
    detect_new: bool = True,
    sigma_dz_m: np.ndarray | None = None,
):
    """The building layer of footprints: every footprint, and the new buildings of the later epoch that stand
    outside every footprint, classified by :func:`classify_damage`.

    Footprints are those of the earlier date at best, so a building built since is found in the change map
    (:func:`geocd.change.buildings.detect_new_buildings`: a raised region at the reported level outside every
    footprint, at ground level before, of at least ``min_changed`` × the median footprint area); its ``source``
    is :data:`~geocd.change.building_layer.SOURCE_CHANGE_MAP` and its ``building_id`` −1, −2, … by decreasing area.

    Parameters
    ----------
    footprints : GeoDataFrame of polygons (any CRS)
    id_field : the footprints' id attribute (default: their 1-based row)
    detect_new : add the new buildings of the change map
    (others: as :func:`classify_damage`)

    Returns
    -------
    GeoDataFrame: the building layer (footprints first, in their order, then the new buildings).
    """
    import geopandas as gpd
    import pandas as pd
    from rasterio.features import rasterize

    from .buildings import detect_new_buildings

    fp = footprints_with_ids(footprints, grid.crs, id_field)
    fp.insert(1, "source", SOURCE_FOOTPRINTS)
    bp = building_params or BuildingParams(
        min_observed=params.min_observed, min_changed=params.min_changed, changed_part=params.changed_part
    )
    new = ()
    if detect_new and len(fp):
        any_fp = (
            rasterize(
                [(g, 1) for g in fp.geometry], out_shape=grid.shape, transform=grid.transform, fill=0, dtype="uint8"
            )
            > 0
        )
        new = detect_new_buildings(
            result.changed_at(report_confidence),
            result.dz_m,
            grid,
            z_a=z_a,
            z_b=z_b,
            footprint_mask=any_fp,
            min_area_m2=bp.min_changed * float(np.median(fp.geometry.area)),
            params=bp,
            confidence_level=report_confidence,
        )
    kw = dict(
        z_a=z_a,
        z_b=z_b,
        dtm=dtm,
        model=model,
        report_confidence=report_confidence,
        params=params,
        id_field="building_id",
        building_params=bp,
        sigma_dz_m=sigma_dz_m,
    )
    if not (detect_new and len(new)):
        return classify_damage(fp, result, grid, **kw)
    new = gpd.GeoDataFrame(
        {"building_id": new["building_id"].to_numpy(), "source": SOURCE_CHANGE_MAP},
        geometry=new.geometry.values,
        crs=new.crs,
    ).to_crs(fp.crs)
    both = gpd.GeoDataFrame(pd.concat([fp, new], ignore_index=True), geometry=fp.geometry.name, crs=fp.crs)
    if dtm is not None:
        return classify_damage(both, result, grid, **kw)
    # heights above a ring: a footprint's ring is the footprints' (as the change map's new buildings are found),
    # and a new building's ring leaves the footprints out
    layer = pd.concat(
        [classify_damage(fp, result, grid, **kw), classify_damage(both, result, grid, **kw).iloc[len(fp) :]],
        ignore_index=True,
    )
    return order_columns(gpd.GeoDataFrame(layer, geometry="geometry", crs=fp.crs))


def building_layer(
    footprints,
    result,
    grid,
    *,
    z_a: np.ndarray,
    z_b: np.ndarray,
    model=None,
    report_confidence: float = 99.0,
    epoch_a: str = "A",
    epoch_b: str = "B",
    params: DSMBuildingParams | None = None,
    building_params: BuildingParams | None = None,
):
    """The building layer of a change test (:mod:`geocd.change.building_layer`) and the ground model under it.

    With footprints: every footprint and the new buildings of the change map standing outside all of them
    (:func:`footprint_layer`); without: the building objects of epoch A's DSM, their building-sized changed parts
    cut out into buildings of their own (``params.split_changed``: :func:`split_changed_parts`), plus the parts of
    epoch B's objects that stand where A's surface was ground (new buildings, :func:`new_parts`), joined by the
    raised parts of A's objects they touch. Heights are above the ground model of A's DSM (:func:`ground_model`,
    gaps filled).

    Parameters
    ----------
    footprints : GeoDataFrame or None
    result : geocd.consistency.ChangeResult on ``grid``
    z_a, z_b : float (rows, cols), the epochs' surfaces (m; NaN where unobserved)
    epoch_a, epoch_b : the epochs' names (in the ``source`` of DSM objects)

    Returns
    -------
    (GeoDataFrame, dtm) — the layer (with no row when the DSM holds no building object), or (None, None) when
    an epoch has no height at all or ``report_confidence`` was not tested.
    """
    from .building_layer import source_dsm, source_new_dsm

    params = params or DSMBuildingParams()
    if not (np.isfinite(z_a).any() and np.isfinite(z_b).any()) or report_confidence not in result.confidences:
        return None, None
    if footprints is not None:
        dtm = fill_gaps(ground_model(z_a, grid.posting_m, params)[0])
        id_field = next((c for c in ("building_id", "id", "fid") if c in footprints.columns), None)
        layer = footprint_layer(
            footprints,
            result,
            grid,
            z_a=z_a,
            z_b=z_b,
            dtm=dtm,
            model=model,
            report_confidence=report_confidence,
            params=params,
            building_params=building_params,
            id_field=id_field,
        )
        return layer, dtm
    dtm, ground = ground_model(z_a, grid.posting_m, params)
    lab_a = building_objects(z_a, dtm, grid.posting_m, params, ground=ground)
    # one building per building: an object's building-sized changed parts become objects of their own
    observed = np.asarray(result.observed, bool)
    levels = sorted(result.confidences)
    report = np.where(observed, result.changed_at(report_confidence), 0)
    low = np.where(observed, result.changed_at(levels[0]), 0)
    if params.split_changed:
        lab_a, _ = split_changed_parts(
            lab_a,
            report,
            low,
            grid.posting_m,
            params,
            keep=_not_a_tree(z_a, z_b, fill_gaps(dtm), grid.posting_m, params),
        )
    # new buildings: the parts of B's objects standing where A's surface was ground
    lab_new = new_parts(z_a, z_b, dtm, dsm_objects(z_b, grid.posting_m, params), grid.posting_m, params, lab_a)
    if params.split_changed:  # a new building seen partly over an A object is one building
        min_cells = int(math.ceil(params.min_area_m2 / grid.cell_area_m2))
        lab_a, lab_new = _join_raised_parts(lab_a, lab_new, report == 1, low == 1, min_cells)
    labels, n_a = _stack_labels(lab_a, lab_new)
    bld = outlines(labels, grid, params)
    bld = bld.assign(source=np.where(bld["building_id"] <= n_a, source_dsm(epoch_a), source_new_dsm(epoch_b, epoch_a)))
    dtm = fill_gaps(dtm)
    layer = classify_damage(
        bld,
        result,
        grid,
        z_a=z_a,
        z_b=z_b,
        dtm=dtm,
        model=model,
        params=params,
        report_confidence=report_confidence,
        id_field="building_id",
        building_params=building_params,
    )
    return layer, dtm


def stable_false_alarms(
    confidence: np.ndarray, observed: np.ndarray, damage, grid, *, buffer_m: float = 0.0, levels=(90.0, 95.0, 99.0)
) -> dict:
    """Flagged share of the observed cells outside every changed building (grown by ``buffer_m``).

    ``confidence``: per-cell confidence (percent) of a change test; ``damage``: its building layer.
    Returns {level (str): share, "stable_cells": n, "buffer_m": b}.
    """
    from rasterio.features import rasterize

    changed = damage[damage["class"].isin(CHANGED)]
    geoms = [g.buffer(buffer_m) if buffer_m else g for g in changed.geometry]
    inside = (
        rasterize(
            [(g, 1) for g in geoms], out_shape=grid.shape, transform=grid.transform, fill=0, dtype="uint8"
        ).astype(bool)
        if geoms
        else np.zeros(grid.shape, bool)
    )
    stable = observed & ~inside
    out: dict = {f"{c:g}": round(float((np.nan_to_num(confidence[stable]) >= c).mean()), 5) for c in levels}
    out.update(stable_cells=int(stable.sum()), buffer_m=buffer_m)
    return out
