"""The paper's Table 2 measures: missed objects (HO), false objects (FO), missed changes (HV), false
changes (FV) and the pixel F-measure of the building masks (DP).

Definitions used here (the paper gives no overlap rule; these are stated so the figures can be checked):

* a truth building is **found** when the detected building mask of a date it exists on covers at least
  half of its footprint; otherwise it is missed (HO);
* a detected building (a connected component of the union of all rectangles) is **false** (FO) when less
  than half of its area lies on truth buildings of either date;
* a truth change (new building: the ξ = 2 mask must cover half of it; demolished: the ξ = 1 mask) that is
  not covered is a missed change (HV); a detected change (connected component of the ξ = 1 or ξ = 2 mask)
  with less than half of its area on truth changes of its kind is a false change (FV);
* DP is the F-measure of the date-1 and date-2 building masks against the truth masks, pixels of both
  dates pooled; ``change_f`` the same for the changed-building masks;
* a building cut by the grid's border is scored by its pixels only: its cells on the grid are building
  cells of the truth masks (and of the truth changes), but it is not an object that can be missed
  (``scored`` False in :func:`sample_truth`'s objects), since too little of it may be on the grid.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from ..errors import ConfigError
from . import _kernels as K
from .model import BOTH, ONLY_1, ONLY_2


def rect_masks(rects: np.ndarray, xi: np.ndarray, shape: tuple[int, int]) -> dict[str, np.ndarray]:
    """Boolean masks on the grid: ``date1`` (ξ ∈ {*, 1}), ``date2`` (ξ ∈ {*, 2}), ``new`` (ξ = 2),
    ``demolished`` (ξ = 1), ``any``, and ``label`` (int32 index of the last rectangle covering a cell, −1 none)."""
    label = np.full(shape, -1, np.int32)
    out = {k: np.zeros(shape, bool) for k in ("date1", "date2", "new", "demolished", "any")}
    for k, (r, x) in enumerate(zip(rects, xi)):
        sl, u, v, _ = K._rect_grid(r, shape, 1.0)
        m = (np.abs(u) <= r[2] / 2) & (np.abs(v) <= r[3] / 2)
        out["any"][sl] |= m
        if x in (BOTH, ONLY_1):
            out["date1"][sl] |= m
        if x in (BOTH, ONLY_2):
            out["date2"][sl] |= m
        if x == ONLY_2:
            out["new"][sl] |= m
        if x == ONLY_1:
            out["demolished"][sl] |= m
        label[sl][m] = k
    out["label"] = label
    return out


def _f(tp: float, fp: float, fn: float) -> dict[str, float]:
    p = tp / (tp + fp) if tp + fp else 0.0
    r = tp / (tp + fn) if tp + fn else 0.0
    return {"precision": round(p, 4), "recall": round(r, 4), "f": round(2 * p * r / (p + r), 4) if p + r else 0.0}


def _cover(mask: np.ndarray, obj: np.ndarray) -> float:
    n = obj.sum()
    return float((mask & obj).sum()) / n if n else 0.0


def _components(mask: np.ndarray, min_cells: int = 1) -> list[np.ndarray]:
    lab, n = ndimage.label(mask, structure=np.ones((3, 3)))
    out = []
    for k, sl in enumerate(ndimage.find_objects(lab), start=1):
        m = np.zeros(mask.shape, bool)
        m[sl] = lab[sl] == k
        if m.sum() >= min_cells:
            out.append(m)
    return out


def table2(
    masks: dict[str, np.ndarray],
    truth_objects: list[dict],
    truth_1: np.ndarray,
    truth_2: np.ndarray,
    observed: np.ndarray | None = None,
) -> dict:
    """Table 2 on a scene with building truth of both dates.

    Parameters
    ----------
    masks : from :func:`rect_masks`
    truth_objects : one dict per truth building: ``mask`` (bool grid), ``dates`` (subset of {1, 2}),
        ``change`` (None, "new" or "demolished"), optional ``scored`` (default True; False: a building cut
        by the border, which counts in the masks but cannot be missed)
    truth_1, truth_2 : bool building masks of each date
    observed : bool, cells where the evaluation counts (default all)
    """
    obs = np.ones(truth_1.shape, bool) if observed is None else observed
    scored = [t for t in truth_objects if t.get("scored", True)]
    ho = sum(
        1
        for t in scored
        if not any(_cover(masks["date1" if d == 1 else "date2"], t["mask"]) >= 0.5 for d in t["dates"])
    )
    truth_any = truth_1 | truth_2
    det = _components(masks["any"] & obs)
    fo = sum(1 for m in det if _cover(truth_any, m) < 0.5)
    changes = [t for t in truth_objects if t["change"]]
    hv = sum(1 for t in changes if t.get("scored", True) and _cover(masks[t["change"]], t["mask"]) < 0.5)
    fv = 0
    n_det_changes = 0
    for kind in ("new", "demolished"):
        tm = np.zeros(truth_1.shape, bool)
        for t in changes:
            if t["change"] == kind:
                tm |= t["mask"]
        for m in _components(masks[kind] & obs):
            n_det_changes += 1
            fv += _cover(tm, m) < 0.5
    tp = fp = fn = 0
    for d, tm in ((masks["date1"], truth_1), (masks["date2"], truth_2)):
        tp += int((d & tm & obs).sum())
        fp += int((d & ~tm & obs).sum())
        fn += int((~d & tm & obs).sum())
    tch = np.zeros(truth_1.shape, bool)
    for t in changes:
        tch |= t["mask"]
    dch = (masks["new"] | masks["demolished"]) & obs
    cf = _f(int((dch & tch).sum()), int((dch & ~tch).sum()), int((~dch & tch & obs).sum()))
    dp = _f(tp, fp, fn)
    return {
        "objects": len(scored),
        "changes": sum(1 for t in changes if t.get("scored", True)),
        "detected_objects": len(det),
        "detected_changes": n_det_changes,
        "HO": ho,
        "FO": fo,
        "HV": hv,
        "FV": int(fv),
        "DP": dp["f"],
        "DP_precision": dp["precision"],
        "DP_recall": dp["recall"],
        "change_f": cf["f"],
    }


def table2_change_only(masks: dict[str, np.ndarray], change_label: np.ndarray, min_cells: int = 40) -> dict:
    """What a change-only label (LEVIR-CD: built or demolished, no building truth) allows: HV, FV and the
    pixel F-measure of the changed-building mask. HO, FO and DP need building truth and are None."""
    truth = _components(change_label.astype(bool), min_cells)
    dch = masks["new"] | masks["demolished"]
    hv = sum(1 for t in truth if _cover(dch, t) < 0.5)
    det = _components(dch)
    tl = change_label.astype(bool)
    fv = sum(1 for m in det if _cover(tl, m) < 0.5)
    cf = _f(int((dch & tl).sum()), int((dch & ~tl).sum()), int((~dch & tl).sum()))
    return {
        "objects": None,
        "changes": len(truth),
        "detected_changes": len(det),
        "HO": None,
        "FO": None,
        "HV": hv,
        "FV": fv,
        "DP": None,
        "change_f": cf["f"],
        "change_precision": cf["precision"],
        "change_recall": cf["recall"],
    }


def sample_truth(
    footprints_all, grid, min_in_aoi: float = 0.5, cut_buildings: str = "masks"
) -> tuple[list[dict], np.ndarray, np.ndarray]:
    """Truth objects and date masks from a geocd synth ``footprints_all`` layer (``status`` per building).

    Parameters
    ----------
    min_in_aoi : float
        A building with less than this share of its footprint on the grid is *cut* by the border.
    cut_buildings : {"masks", "drop"}
        "masks" (default): a cut building's cells on the grid are building cells of the date masks, and it
        is in the objects with ``scored`` False (its pixels count in DP, FO, FV and change_f; it is never a
        missed object or change). "drop": it is left out of the masks and the objects, so a detection on
        it is a false object and false pixels (the scoring of geocd's figures until 24 Nov 2026).
    """
    from rasterio.features import rasterize
    from shapely.geometry import box

    if cut_buildings not in ("masks", "drop"):
        raise ConfigError(f"cut_buildings must be 'masks' or 'drop', got {cut_buildings!r}")
    gb = box(*grid.bounds)
    t1 = np.zeros(grid.shape, bool)
    t2 = np.zeros(grid.shape, bool)
    objs = []
    for geom, status in zip(footprints_all.geometry, footprints_all["status"]):
        on_grid = geom.intersection(gb).area
        whole = on_grid >= min_in_aoi * geom.area
        if on_grid <= 0 or (not whole and cut_buildings == "drop"):
            continue
        m = rasterize([(geom, 1)], out_shape=grid.shape, transform=grid.transform, fill=0, dtype="uint8") > 0
        if not whole and not m.any():  # a corner on the grid too small to hold a cell centre
            continue
        dates = (1,) if status == "demolished" else (2,) if status == "new" else (1, 2)
        change = status if status in ("new", "demolished") else None
        objs.append({"mask": m, "dates": dates, "change": change, "status": status, "scored": bool(whole)})
        if 1 in dates:
            t1 |= m
        if 2 in dates:
            t2 |= m
    return objs, t1, t2
