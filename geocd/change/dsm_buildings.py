"""Buildings without a footprint layer: building objects from a DSM, and their damage class.

For a city without a cadastre (disaster response), the pre-event DSM itself says where the buildings were:

1. **Ground model** (:func:`ground_model`): a progressive morphological filter (Zhang et al. 2003) on the
   gap-filled DSM: openings with square windows of growing size (2.5 … ``max_building_m``); a cell is
   off-ground when it stands above the opening by more than ``dh0 + slope·w`` (bounded by ``dh_max``).
   Ground cells are resampled to ``ground_block_m`` blocks (median) and interpolated back (bilinear over
   filled blocks), which gives a smooth DTM under the buildings; twice, the cells within ``dh0 + 0.5`` m of
   that surface join the ground and it is interpolated again (an opening sits below sloping ground).
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
import warnings
from dataclasses import dataclass, replace

import numpy as np
from scipy import ndimage as ndi

from ..errors import ConfigError
from ..mpp.features import planar_cells, plane_residual
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

    def __post_init__(self):
        if self.tree_rule not in TREE_RULES:
            raise ConfigError(f"tree_rule {self.tree_rule!r} is not one of {TREE_RULES}: choose one of them")
        if not self.tree_residual_m > 0:
            raise ConfigError(f"tree_residual_m must be > 0 (m), got {self.tree_residual_m}")


def fill_gaps(z: np.ndarray) -> np.ndarray:
    """NaN cells take the value of the nearest valid cell."""
    bad = ~np.isfinite(z)
    if not bad.any():
        return z.astype(np.float64)
    if bad.all():
        raise ValueError("the DSM has no valid cell")
    idx = ndi.distance_transform_edt(bad, return_distances=False, return_indices=True)
    return z[tuple(idx)].astype(np.float64)


def ground_model(
    dsm: np.ndarray, posting_m: float, params: DSMBuildingParams = DSMBuildingParams()
) -> tuple[np.ndarray, np.ndarray]:
    """Progressive morphological ground filter.

    Returns
    -------
    dtm : float32 (rows, cols), the ground height (m, same datum as the DSM)
    ground : bool (rows, cols), cells classified as ground (valid DSM cells only)
    """
    z = fill_gaps(dsm)
    valid = np.isfinite(dsm)
    off = np.zeros(z.shape, dtype=bool)
    w = 2.5
    cur = z
    while True:
        k = max(3, int(round(w / posting_m)) | 1)
        opened = ndi.maximum_filter(ndi.minimum_filter(cur, size=k), size=k)
        dh = min(params.dh0_m + params.slope * w, params.dh_max_m)
        off |= (z - opened) > dh
        cur = opened
        if w >= params.max_building_m:
            break
        w = min(2.0 * w, params.max_building_m)
    ground = valid & ~off
    dtm = _block_surface(z, ground, posting_m, params.ground_block_m)
    # refine on sloping ground: an opening sits below a slope by up to slope × window/2, so cells near the
    # interpolated ground are ground too, and the ground is interpolated again from them
    for _ in range(2):
        if not np.isfinite(dtm).any():
            break
        ground = valid & (np.abs(z - dtm) <= params.dh0_m + 0.5) | (ground & (z - dtm <= params.dh0_m + 0.5))
        dtm = _block_surface(z, ground, posting_m, params.ground_block_m)
    return dtm, ground


def _block_surface(z: np.ndarray, ground: np.ndarray, posting_m: float, block_m: float) -> np.ndarray:
    """Median of the ground cells per block, interpolated back to the grid (blocks without ground: nearest)."""
    b = max(1, int(round(block_m / posting_m)))
    H, W = z.shape
    nb_r, nb_c = math.ceil(H / b), math.ceil(W / b)
    pad = np.full((nb_r * b, nb_c * b), np.nan)
    pad[:H, :W] = np.where(ground, z, np.nan)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        blocks = np.nanmedian(pad.reshape(nb_r, b, nb_c, b).transpose(0, 2, 1, 3).reshape(nb_r, nb_c, -1), axis=2)
    if not np.isfinite(blocks).any():
        return np.full(z.shape, np.nan, np.float32)
    blocks = fill_gaps(blocks)
    rr = (np.arange(H) + 0.5) / b - 0.5
    cc = (np.arange(W) + 0.5) / b - 0.5
    R, C = np.meshgrid(np.clip(rr, 0, nb_r - 1), np.clip(cc, 0, nb_c - 1), indexing="ij")
    return ndi.map_coordinates(blocks, [R, C], order=1, mode="nearest").astype(np.float32)


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
    from shapely.geometry import shape
    from shapely.ops import unary_union

    polys: dict[int, list] = {}
    for geom, val in shapes(labels.astype(np.int32), mask=labels > 0, transform=grid.transform):
        polys.setdefault(int(val), []).append(shape(geom))
    rows = []
    for k in sorted(polys):
        g = unary_union(polys[k]).buffer(0)
        if g.geom_type == "MultiPolygon":
            g = max(g.geoms, key=lambda p: p.area)
        g = g.simplify(grid.posting_m, preserve_topology=True)
        rect = g.minimum_rotated_rectangle
        rectangularity = g.area / rect.area if rect.area > 0 else 0.0
        if rectangularity >= params.rect_min:
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


def new_objects(
    z_a: np.ndarray,
    z_b: np.ndarray,
    dtm: np.ndarray,
    labels_b: np.ndarray,
    grid,
    params: DSMBuildingParams = DSMBuildingParams(),
    labels_a: np.ndarray | None = None,
):
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
    labels_a : int (rows, cols), optional, epoch A's building objects

    Returns
    -------
    GeoDataFrame of outlines (:func:`outlines`), one per new part.
    """
    posting = grid.posting_m
    ha = fill_gaps(z_a) - dtm
    hb = fill_gaps(z_b) - dtm
    part = (np.asarray(labels_b) > 0) & (ha < params.min_height_m) & (hb >= params.min_height_m)
    if labels_a is not None:
        part &= np.asarray(labels_a) == 0
    part = ndi.binary_opening(part, structure=np.ones((3, 3), bool), iterations=max(1, int(round(1.0 / posting))))
    lab, n = ndi.label(part)
    if n:
        sizes = np.bincount(lab.ravel(), minlength=n + 1)
        small = sizes * posting * posting < params.min_area_m2
        small[0] = True
        lab[small[lab]] = 0
        u = np.unique(lab)
        u = u[u > 0]
        lut = np.zeros(n + 1, np.int32)
        lut[u] = np.arange(1, u.size + 1)
        lab = lut[lab]
    return outlines(lab.astype(np.int32), grid, params)


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
    (:func:`footprint_layer`); without: the building objects of epoch A's DSM plus the parts of epoch B's
    objects that stand where A's surface was ground (new buildings, :func:`new_objects`). Heights are above the
    ground model of A's DSM (:func:`ground_model`, gaps filled).

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
    import pandas as pd

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
    bld, dtm, lab_a = buildings_from_dsm(z_a, grid, params)
    bld = bld.assign(source=source_dsm(epoch_a))
    # new buildings: the parts of B's objects standing where A's surface was ground
    post = new_objects(z_a, z_b, dtm, buildings_from_dsm(z_b, grid, params)[2], grid, params, labels_a=lab_a)
    if len(post):
        post = post.assign(source=source_new_dsm(epoch_b, epoch_a))
        post["building_id"] = np.arange(len(bld) + 1, len(bld) + 1 + len(post))
        bld = pd.concat([bld, post], ignore_index=True)
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
