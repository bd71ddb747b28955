"""Building-level change: attribute input footprints from a per-cell change map.

The footprint rule below is the first step of every building layer: :func:`geocd.change.dsm_buildings.classify_damage`
turns its classes into the layer's (``demolished`` → ``collapsed``, ``lowered`` → ``collapsed`` / ``partly
collapsed`` / ``lowered`` by the heights) and writes the one schema of :mod:`geocd.change.building_layer`.
:func:`classify_buildings`' own frame is an intermediate result, not a layer.

For each footprint, with the signed change mask at the chosen confidence and
the two epochs' surfaces:

* ``unobserved``  — fewer than ``min_observed`` of its cells were observed in both epochs,
                    or less than ``min_inside`` of its area lies on the grid (AOI edge);
* ``new``         — mostly raised, and in epoch A the footprint stood at ground level
                    (median height inside minus median of a ring around it < ``ground_tol_m``);
* ``raised``      — mostly raised otherwise;
* ``demolished``  — mostly lowered, and in epoch B it stands at ground level;
* ``lowered``     — mostly lowered otherwise;
* ``unchanged``   — neither.

"Mostly" = the changed fraction of observed cells is at least ``min_changed``
(default 0.15, chosen for the 99% change map: on sample_aoi unchanged buildings
reach at most 0.03 at 99% but 0.27 at 90%, so classify from the 99% map).
A building is changed too when it holds a **changed part**: an 8-connected group of
same-sign changed cells inside it of at least the change map's minimum mapping unit
(``min_part_cells``, passed by the caller from the change test: the smallest region the
map can report, derived from the matching window), so that a region the ``changes`` layer
reports inside a building does not leave it "unchanged"; the class follows the part's sign.
**Off by default** (``changed_part``): on the generated towns it moves no class, and on the
real Kahramanmaraş pair, with building objects from a DSM, most of the parts it adds are
felled trees and roadworks inside the objects' outlines (docs/kahramanmaras.md).
Buildings derived from a DSM instead have their building-sized changed parts cut out into buildings of their
own (``split_changed``, on: :func:`geocd.change.dsm_buildings.split_changed_parts`).
The ground-level test uses a ring of cells ``ring_m`` wide around the
footprint (minus other footprints), so no bare-earth DEM is needed; a given
DEM is used instead when provided.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .building_layer import CHANGED, SOURCE_CHANGE_MAP, SOURCE_FOOTPRINTS

#: the footprint rule's classes (:func:`classify_buildings`; the layer's are :data:`~geocd.change.building_layer.CLASSES`)
CLASSES = ("new", "raised", "demolished", "lowered", "unchanged", "unobserved")
CHANGED_CLASSES = ("new", "raised", "demolished", "lowered")
#: the footprint rule's and a truth's class words → the building layer's, for comparing classes
_LAYER_CLASS = {"demolished": "collapsed"}


@dataclass(frozen=True)
class BuildingParams:
    min_observed: float = 0.3
    min_changed: float = 0.15
    min_inside: float = 0.5
    ground_tol_m: float = 1.5
    ring_m: float = 4.0
    changed_part: bool = False
    #: buildings derived from a DSM (no footprints): cut building-sized changed parts out of merged objects
    #: (:func:`geocd.change.dsm_buildings.split_changed_parts`)
    split_changed: bool = True
    #: buildings derived from a DSM: also split objects where the surface steps by a storey (an option, off:
    #: :func:`geocd.change.dsm_buildings.split_height_steps`)
    split_steps: bool = False


def largest_parts(change_mask: np.ndarray, labels: np.ndarray, n: int, keep=None) -> tuple[np.ndarray, np.ndarray]:
    """Each building's largest changed part: 8-connected same-sign changed cells inside it.

    Parameters
    ----------
    change_mask : int (rows, cols), +1 raised / −1 lowered; any other value is not changed
    labels : int (rows, cols), building ``k`` painted as ``k`` (1 … n), 0 elsewhere
    n : number of buildings
    keep : callable ``(sign, rows, cols) -> bool``, optional
        Whether a part (its sign and the grid indices of its cells) may count, e.g. not a felled tree.

    Returns
    -------
    cells : int64 (n,), the size of the largest part (0: none)
    sign : int8 (n,), its sign (+1 / −1; 0 when there is none; raised wins a tie)
    """
    from scipy import ndimage

    cells = np.zeros(n, np.int64)
    sign = np.zeros(n, np.int8)
    cm = np.asarray(change_mask)
    eight = np.ones((3, 3), bool)
    for i, sl in enumerate(ndimage.find_objects(labels, max_label=n)):
        if sl is None:
            continue
        inside = labels[sl] == (i + 1)
        for s in (1, -1):
            lab, k = ndimage.label(inside & (cm[sl] == s), structure=eight)
            if not k:
                continue
            sizes = np.bincount(lab.ravel())[1:]
            for j in np.argsort(-sizes, kind="stable"):
                if sizes[j] <= cells[i]:
                    break
                if keep is not None:
                    rr, cc = np.nonzero(lab == j + 1)
                    if not keep(s, rr + sl[0].start, cc + sl[1].start):
                        continue
                cells[i], sign[i] = int(sizes[j]), s
                break
    return cells, sign


def _ring_median(z: np.ndarray, inside: np.ndarray, other: np.ndarray, ring_cells: int) -> float:
    from scipy.ndimage import binary_dilation

    ring = binary_dilation(inside, iterations=max(1, ring_cells)) & ~inside & ~other
    v = z[ring]
    v = v[np.isfinite(v)]
    return float(np.median(v)) if v.size else float("nan")


def classify_buildings(
    footprints,
    change_mask: np.ndarray,
    dz_m: np.ndarray,
    grid,
    *,
    z_a: np.ndarray | None = None,
    z_b: np.ndarray | None = None,
    dem_m: np.ndarray | None = None,
    confidence: np.ndarray | None = None,
    params: BuildingParams = BuildingParams(),
    id_field: str | None = None,
    confidence_level: float | None = None,
    detect_new: bool = True,
    min_part_cells: int | None = None,
    part_keep=None,
):
    """Attribute footprints with their change, and add new buildings found in the change map.

    Parameters
    ----------
    footprints : GeoDataFrame (any CRS; reprojected to the grid's)
    change_mask : int8 (rows, cols), +1/−1/0, any other value (e.g. the −128 nodata) where unobserved
    dz_m : float (rows, cols), z_B − z_A
    z_a, z_b : float (rows, cols), optional, the epochs' surfaces (for new/demolished)
    dem_m : float (rows, cols), optional bare-earth DEM (replaces the ring test)
    confidence : float (rows, cols), optional per-cell confidence (percent)
    confidence_level : float, optional
        The confidence (percent) ``change_mask`` was made at; named in the ``rule`` attribute.
    detect_new : bool
        With both surfaces given, append the new buildings of :func:`detect_new_buildings`
        (raised regions outside every footprint): footprints of the earlier date cannot hold them.
    min_part_cells : int, optional
        The change map's minimum mapping unit (cells; a change test's ``min_region_cells``): a building
        holding a changed part of at least this size is changed whatever its changed fraction
        (``params.changed_part``). None: the fraction rule alone.
    part_keep : callable, optional
        Which parts may count (:func:`largest_parts`' ``keep``).

    Returns
    -------
    GeoDataFrame with columns building_id, n_cells, frac_observed (observed share of the whole footprint),
    frac_inside (share of the footprint on the grid), frac_changed, frac_raised, frac_lowered (of the observed
    cells), mean_dz_m, volume_m3, confidence (percent), rule (the rule that set the class, in words), class,
    geometry.
    """
    from rasterio.features import rasterize

    gdf = footprints.to_crs(grid.crs).reset_index(drop=True)
    ids = gdf[id_field].to_numpy() if id_field and id_field in gdf else np.arange(1, len(gdf) + 1)
    labels = rasterize(
        [(g, i + 1) for i, g in enumerate(gdf.geometry)],
        out_shape=grid.shape,
        transform=grid.transform,
        fill=0,
        dtype="int32",
        all_touched=False,
    )
    any_fp = labels > 0
    use_part = params.changed_part and min_part_cells is not None
    if use_part:
        part_cells, part_sign = largest_parts(change_mask, labels, len(gdf), keep=part_keep)
    ring_cells = int(round(params.ring_m / grid.posting_m))
    cell_area = grid.cell_area_m2
    pct = f"{confidence_level:g}% " if confidence_level is not None else ""
    rows = []
    for i in range(len(gdf)):
        inside = labels == (i + 1)
        n = int(inside.sum())
        area = max(float(gdf.geometry.iloc[i].area), 1e-9)
        rec = {"building_id": ids[i], "n_cells": n}
        if n == 0:
            rec.update(
                frac_observed=0.0,
                frac_inside=0.0,
                frac_changed=np.nan,
                frac_raised=np.nan,
                frac_lowered=np.nan,
                mean_dz_m=np.nan,
                volume_m3=np.nan,
                confidence=np.nan,
                rule=f"unobserved: no grid cell inside the footprint (min_inside {params.min_inside:g})",
                **{"class": "unobserved"},
            )
            rows.append(rec)
            continue
        inside_frac = min(1.0, n * cell_area / area)
        cm = change_mask[inside]
        obs = (cm >= -1) & (cm <= 1)
        nobs = int(obs.sum())
        # observed share of the whole footprint (cells off the grid count as unobserved)
        fobs = min(1.0, nobs * cell_area / area)
        raised = float(np.sum(cm == 1)) / max(nobs, 1)
        lowered = float(np.sum(cm == -1)) / max(nobs, 1)
        dzin = dz_m[inside]
        dzin = dzin[np.isfinite(dzin)]
        mean_dz = float(dzin.mean()) if dzin.size else np.nan
        conf = np.nan
        if confidence is not None:
            cin = confidence[inside]
            cin = cin[np.isfinite(cin) & (cin > 0)]
            conf = float(np.median(cin)) if cin.size else 0.0
        cls = "unchanged"
        rule = (
            f"unchanged: {100 * max(raised, lowered):.0f}% of observed cells changed at {pct}"
            f"(< min_changed {100 * params.min_changed:g}%)"
        )
        if inside_frac < params.min_inside:
            cls = "unobserved"
            rule = f"unobserved: {100 * inside_frac:.0f}% of the footprint on the grid (< min_inside {100 * params.min_inside:g}%)"
        elif nobs < params.min_observed * n:
            cls = "unobserved"
            rule = (
                f"unobserved: {100 * nobs / n:.0f}% of its cells observed in both epochs "
                f"(< min_observed {100 * params.min_observed:g}%)"
            )
        elif max(raised, lowered) >= params.min_changed or (use_part and part_cells[i] >= min_part_cells):
            if max(raised, lowered) >= params.min_changed:
                up = raised >= lowered
                frac = raised if up else lowered
                cls = "raised" if up else "lowered"
                rule = f"{cls}: {100 * frac:.0f}% of observed cells {cls} at {pct}(≥ min_changed {100 * params.min_changed:g}%)"
            else:
                up = part_sign[i] > 0
                cls = "raised" if up else "lowered"
                rule = (
                    f"{cls}: a {cls} part of {part_cells[i]} cells ({part_cells[i] * cell_area:.0f} m²) at {pct}"
                    f"(≥ the change map's mapping unit, {min_part_cells} cells); "
                    f"{100 * max(raised, lowered):.1f}% of observed cells changed (< min_changed "
                    f"{100 * params.min_changed:g}%)"
                )
            z = z_a if up else z_b
            if z is not None:
                zin = z[inside]
                zin = zin[np.isfinite(zin)]
                if dem_m is not None:
                    ground = dem_m[inside]
                    ground = float(np.nanmedian(ground)) if np.isfinite(ground).any() else np.nan
                else:
                    ground = _ring_median(z, inside, any_fp, ring_cells)
                if zin.size and np.isfinite(ground):
                    above = float(np.median(zin)) - ground
                    if above < params.ground_tol_m:
                        epoch = "A" if cls == "raised" else "B"
                        cls = "new" if cls == "raised" else "demolished"
                        ref = "the ground model" if dem_m is not None else "its surroundings"
                        rule += (
                            f"; at ground level in {epoch} (median {above:.1f} m above {ref} "
                            f"< ground_tol {params.ground_tol_m:g} m)"
                        )
        rec.update(
            frac_observed=round(fobs, 4),
            frac_inside=round(inside_frac, 4),
            frac_changed=round(raised + lowered, 4),
            frac_raised=round(raised, 4),
            frac_lowered=round(lowered, 4),
            mean_dz_m=mean_dz,
            volume_m3=float(np.nansum(dz_m[inside] * ((cm == 1) | (cm == -1))) * cell_area) if nobs else np.nan,
            confidence=conf,
            rule=rule,
            **{"class": cls},
        )
        rows.append(rec)
    import geopandas as gpd
    import pandas as pd

    out = gpd.GeoDataFrame(pd.DataFrame(rows), geometry=gdf.geometry.values, crs=gdf.crs)
    out.insert(1, "source", SOURCE_FOOTPRINTS)
    keep = [c for c in gdf.columns if c not in out.columns and c != gdf.geometry.name]
    for c in keep:
        out[f"src_{c}"] = gdf[c].values
    if detect_new and z_a is not None and z_b is not None and len(gdf):
        min_area = params.min_changed * float(np.median(gdf.geometry.area))
        new = detect_new_buildings(
            change_mask,
            dz_m,
            grid,
            z_a=z_a,
            z_b=z_b,
            footprint_mask=any_fp,
            min_area_m2=min_area,
            confidence=confidence,
            params=params,
            confidence_level=confidence_level,
        )
        if len(new):
            new = new.to_crs(out.crs)
            out = gpd.GeoDataFrame(pd.concat([out, new], ignore_index=True), geometry="geometry", crs=out.crs)
    return out


def footprint_windows(footprints, grid):
    """Each footprint's window on a large grid, for classifying buildings window by window.

    Yields ``(i, window, subgrid, near)``: the footprint's index, its bounding box grown by the
    classification ring (``BuildingParams.ring_m``) + 2 cells as ``(row0, col0, rows, cols)``, that
    window's grid, and the sorted indices of every footprint touching the window (``i`` included; in the
    layer's order, as rasterization paints in order). ``footprints`` must be in ``grid``'s CRS.
    """
    from shapely.geometry import box

    ring = int(round(BuildingParams().ring_m / grid.posting_m)) + 2
    inv = ~grid.transform
    sidx = footprints.sindex
    for i, geom in enumerate(footprints.geometry):
        l, b, r, t = geom.bounds
        c0, r0 = inv @ (l, t)
        c1, r1 = inv @ (r, b)
        R0, C0 = max(0, int(math.floor(r0)) - ring), max(0, int(math.floor(c0)) - ring)
        R1, C1 = min(grid.height, int(math.ceil(r1)) + ring), min(grid.width, int(math.ceil(c1)) + ring)
        if R1 <= R0 or C1 <= C0:
            R0, C0, R1, C1 = 0, 0, 1, 1
        win = (R0, C0, R1 - R0, C1 - C0)
        sub = grid.subgrid(*win)
        near = np.sort(sidx.query(box(*sub.bounds)))
        if i not in near:
            near = np.sort(np.append(near, i))
        yield i, win, sub, near


def detect_new_buildings(
    change_mask: np.ndarray,
    dz_m: np.ndarray,
    grid,
    *,
    z_a: np.ndarray,
    z_b: np.ndarray,
    footprint_mask: np.ndarray,
    min_area_m2: float,
    confidence: np.ndarray | None = None,
    params: BuildingParams = BuildingParams(),
    confidence_level: float | None = None,
):
    """New buildings that no footprint knows: raised regions outside every footprint.

    A user has the footprints of the earlier date at best, so buildings built since must come from
    the change map. A candidate is an 8-connected region of raised cells (``change_mask == 1``)
    outside every footprint that

    * covers at least ``min_area_m2`` (:func:`classify_buildings` passes ``min_changed`` × the
      median area of the given footprints: the raised part a typical building must show to be
      called changed);
    * stood at ground level in epoch A (median height inside the region minus the median of a
      ``ring_m`` ring around it, outside footprints: < ``ground_tol_m``) and rose by at least
      ``ground_tol_m`` (median Δz inside).

    Returns
    -------
    GeoDataFrame (the grid's CRS) with the columns of :func:`classify_buildings`, ``class`` "new",
    ``source`` "change map", negative ``building_id`` (−1, −2, … by decreasing area) and the region's
    polygon as geometry; empty when there is none.
    """
    import geopandas as gpd
    import pandas as pd
    from rasterio.features import shapes
    from scipy import ndimage
    from shapely.geometry import shape
    from shapely.ops import unary_union

    fp = np.asarray(footprint_mask, bool)
    lab, n_lab = ndimage.label((np.asarray(change_mask) == 1) & ~fp, structure=np.ones((3, 3), bool))
    cell_area = grid.cell_area_m2
    sizes = np.bincount(lab.ravel(), minlength=n_lab + 1)
    sizes[0] = 0
    ring_cells = int(round(params.ring_m / grid.posting_m))
    pct = f"{confidence_level:g}% " if confidence_level is not None else ""
    dz = np.asarray(dz_m, np.float64)
    rows, kept = [], []
    for rid in np.argsort(-sizes, kind="stable"):
        if sizes[rid] * cell_area < min_area_m2 or rid == 0:
            break
        inside = lab == rid
        za_in = z_a[inside]
        za_in = za_in[np.isfinite(za_in)]
        ground = _ring_median(z_a, inside, fp, ring_cells)
        above_a = float(np.median(za_in)) - ground if za_in.size and np.isfinite(ground) else np.nan
        d = dz[inside]
        d = d[np.isfinite(d)]
        raised_by = float(np.median(d)) if d.size else np.nan
        if not (above_a < params.ground_tol_m <= raised_by):
            continue
        conf = np.nan
        if confidence is not None:
            cin = confidence[inside]
            cin = cin[np.isfinite(cin) & (cin > 0)]
            conf = float(np.median(cin)) if cin.size else np.nan
        n = int(sizes[rid])
        rows.append(
            {
                "n_cells": n,
                "frac_observed": 1.0,
                "frac_inside": 1.0,
                "frac_changed": 1.0,
                "frac_raised": 1.0,
                "frac_lowered": 0.0,
                "mean_dz_m": float(d.mean()) if d.size else np.nan,
                "volume_m3": float(d.sum() * cell_area),
                "confidence": conf,
                "rule": (
                    f"new (detected): raised region of {n * cell_area:.0f} m² at {pct}outside every footprint "
                    f"(≥ {min_area_m2:.1f} m² = min_changed {100 * params.min_changed:g}% of the median "
                    f"footprint); {above_a:.1f} m above its surroundings in A (< ground_tol {params.ground_tol_m:g} m), "
                    f"raised by {raised_by:.1f} m (median, ≥ ground_tol)"
                ),
                "class": "new",
            }
        )
        kept.append(int(rid))
    if not rows:
        return gpd.GeoDataFrame(
            pd.DataFrame(columns=["building_id", "source"]), geometry=gpd.GeoSeries([], crs=grid.crs), crs=grid.crs
        )
    keep_lab = np.where(np.isin(lab, kept), lab, 0).astype(np.int32)
    parts: dict[int, list] = {}
    for geom, val in shapes(keep_lab, mask=keep_lab > 0, connectivity=8, transform=grid.transform):
        parts.setdefault(int(val), []).append(shape(geom))
    geoms = [unary_union(parts[r]) for r in kept]
    df = pd.DataFrame(rows)
    df.insert(0, "building_id", -np.arange(1, len(df) + 1))
    df.insert(1, "source", SOURCE_CHANGE_MAP)
    return gpd.GeoDataFrame(df, geometry=geoms, crs=grid.crs)


def _coarse(c: str) -> str:
    """A class for comparing with a truth: the layer's word, ``partly collapsed`` counted as ``lowered``."""
    c = _LAYER_CLASS.get(str(c), str(c))
    return "lowered" if c == "partly collapsed" else c


def building_scores(pred_class, truth_class) -> dict:
    """Building-level precision/recall/F1 of "changed" (a changed class of the building layer or of the
    footprint rule: new, raised, collapsed / demolished, partly collapsed, lowered).

    Unobserved predictions count as "not changed". Also reports class accuracy on the buildings that truly
    changed, in the building layer's words (``demolished`` = ``collapsed``; ``partly collapsed`` counts as
    ``lowered``).
    """
    changed = set(CHANGED_CLASSES) | set(CHANGED)
    pred = np.asarray([c in changed for c in pred_class])
    truth = np.asarray([c in changed for c in truth_class])
    tp = int(np.sum(pred & truth))
    fp = int(np.sum(pred & ~truth))
    fn = int(np.sum(~pred & truth))
    p = tp / (tp + fp) if tp + fp else 1.0
    r = tp / (tp + fn) if tp + fn else 1.0
    f1 = 2 * p * r / (p + r) if p + r else 0.0
    exact = np.asarray([_coarse(a) == _coarse(b) for a, b in zip(pred_class, truth_class)], bool)[truth]
    return {
        "tp": tp,
        "fp": fp,
        "fn": fn,
        "precision": p,
        "recall": r,
        "f1": f1,
        "class_accuracy_on_changed": float(exact.mean()) if exact.size else float("nan"),
    }


def score_buildings(
    pred, truth, *, aoi=None, id_field: str = "building_id", status_field: str = "status", min_inside: float = 0.5
) -> dict:
    """Building-level scores of a ``buildings`` layer against the truth, new buildings included.

    Parameters
    ----------
    pred : a building layer (:func:`geocd.change.dsm_buildings.footprint_layer`) or the frame of
        :func:`classify_buildings`: ``source`` "footprints" rows carry the given footprints' ids, the other rows
        are new buildings found in the change map
    truth : GeoDataFrame of every building of either date with its ``status`` (new, demolished, raised,
        lowered, unchanged) and the ids of the footprints given
    aoi : optional polygon (truth's CRS); truth buildings absent from the given footprints count only
        when at least ``min_inside`` of them lies inside it

    Returns
    -------
    dict of :func:`building_scores` over the footprint rows plus the truth buildings that no given
    footprint holds: a detected row is a true positive when it overlaps such a building not yet
    matched (largest overlap first), else a false positive; an unmatched one is a false negative.
    Also ``n_detected`` and ``n_truth_unknown`` (truth buildings missing from the footprints).
    """
    truth = truth.to_crs(pred.crs) if truth.crs is not None and pred.crs is not None else truth
    status = dict(zip(truth[id_field], truth[status_field]))
    src = np.asarray(pred["source"] if "source" in pred else np.full(len(pred), SOURCE_FOOTPRINTS))
    fp_rows = pred[src == SOURCE_FOOTPRINTS]
    det = pred[src != SOURCE_FOOTPRINTS]
    pred_cls = list(fp_rows["class"])
    truth_cls = [status.get(i, "unchanged") for i in fp_rows[id_field]]
    known = set(fp_rows[id_field])
    unknown = truth[~truth[id_field].isin(known)]
    if aoi is not None and len(unknown):
        frac = unknown.geometry.intersection(aoi).area / unknown.geometry.area.clip(lower=1e-9)
        unknown = unknown[frac.to_numpy() >= min_inside]
    matched: set = set()
    for _, d in det.iterrows():
        ov = unknown.geometry.intersection(d.geometry).area
        order = np.argsort(-ov.to_numpy(), kind="stable")
        hit = next((k for k in order if ov.iloc[k] > 0 and k not in matched), None)
        if hit is None:
            pred_cls.append(d["class"])
            truth_cls.append("unchanged")
        else:
            matched.add(hit)
            pred_cls.append(d["class"])
            truth_cls.append(unknown.iloc[hit][status_field])
    for k in range(len(unknown)):
        if k not in matched:
            pred_cls.append("unobserved")
            truth_cls.append(unknown.iloc[k][status_field])
    out = building_scores(pred_cls, truth_cls)
    out.update(n_detected=int(len(det)), n_truth_unknown=int(len(unknown)))
    return out
