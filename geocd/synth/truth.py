"""Truth products of a synthetic town (arrays in, arrays out).

* :func:`truth_grid`: the AOI grid (UTM, ``posting_m``) every truth raster lives on.
* :func:`dsm`: the first surface seen from straight above at each cell centre
  (the renderer's own ray caster with vertical rays, so truth and images agree
  exactly); :func:`bare_dem`: the terrain alone.
* :func:`change_products`: 3-D change mask ``|DSM_B − DSM_A| > threshold_m``
  with connected regions smaller than ``min_area_m2`` dropped, and the class
  of object that changed (building, car, tree).
* :func:`image_change_mask`: which pixels of an image see a 3-D change: the
  pixel's rays are cast into both epochs and the pixel is changed when the
  first surfaces differ by more than ``threshold_m`` (3-D distance) for at
  least half of its samples. This is the truth for per-pixel ROC curves;
  occlusions are handled (a new building hides the ground behind it).
* :func:`non3d_mask`: cells whose appearance changes without a 3-D change
  (repainted roofs, vegetation season), which methods must not report.
* :func:`surface_cover`: what covers each cell seen from straight above (grass, tree, building, car,
  asphalt, pavement, soil, marking) — the exact truth of land-cover conditions such as vegetation.
* :func:`footprints_frame`: per-epoch footprints with their status.
* :func:`corner_check`: truth building corners projected through a camera
  (e.g. the written RPC) versus where the renderer drew them.
"""

from __future__ import annotations

import numpy as np

from ..camera.base import Camera
from ..geodesy import AOIGrid
from . import _kernels as K
from .render import camera_rays, scene_z_band, surface_height
from .scene import C_BUILDING, C_CAR, C_TREE, M_ASPHALT, M_GRASS, M_MARKING, M_PAVEMENT, M_SOIL, Town, building_status

#: change-mask threshold on |ΔDSM| (metres) and minimum region area (m²), unless given
CHANGE_THRESHOLD_M = 1.0
MIN_CHANGE_AREA_M2 = 1.0

#: codes of :func:`change_products`'s class raster and :func:`non3d_mask`
CLASS_CODES = {"none": 0, "building": 1, "car": 2, "tree": 3}
NON3D_CODES = {"none": 0, "repainted_roof": 1, "vegetation_season": 2}
#: codes of :func:`surface_cover`; vegetation is grass or tree
COVER_CODES = {"grass": 1, "tree": 2, "building": 3, "car": 4, "asphalt": 5, "pavement": 6, "soil": 7, "marking": 8}
VEGETATION_CODES = (1, 2)


def truth_grid(town: Town, posting_m: float = 0.5) -> AOIGrid:
    """The AOI grid in the town's UTM CRS (cell edges on multiples of the posting)."""
    left, bottom, right, top = town.aoi_bounds_utm
    return AOIGrid.from_bounds(left, bottom, right, top, posting_m, town.frame.crs)


def _grid_xy(town: Town, grid: AOIGrid) -> tuple[np.ndarray, np.ndarray]:
    X, Y = grid.xy()
    return X - town.frame.e0, Y - town.frame.n0


def dsm(town: Town, scene: K.SceneArrays, grid: AOIGrid) -> tuple[np.ndarray, np.ndarray]:
    """Surface height (float64, ellipsoidal m) and object class code (uint8) at the grid's cell centres."""
    x, y = _grid_xy(town, grid)
    z, ob = surface_height(scene, x, y, return_object=True)
    cls = np.zeros(ob.shape, np.uint8)
    hit = ob >= 0
    code = {C_BUILDING: 1, C_CAR: 2, C_TREE: 3}
    c = scene.cls[np.where(hit, ob, 0)]
    for k, v in code.items():
        cls[hit & (c == k)] = v
    return z, cls


def surface_cover(town: Town, scene: K.SceneArrays, grid: AOIGrid) -> np.ndarray:
    """What covers each cell centre seen from straight above (uint8, :data:`COVER_CODES`).

    The object the vertical ray meets first (building, car, tree crown), else the ground material.
    Vegetation is ``np.isin(cover, VEGETATION_CODES)`` (grass or tree).
    """
    x, y = _grid_xy(town, grid)
    _, ob = surface_height(scene, x, y, return_object=True)
    mat = np.empty(x.size, np.int64)
    K.ground_material_many(scene, np.ascontiguousarray(x.ravel()), np.ascontiguousarray(y.ravel()), mat)
    mat = mat.reshape(x.shape)
    out = np.zeros(x.shape, np.uint8)
    ground = {M_GRASS: "grass", M_ASPHALT: "asphalt", M_PAVEMENT: "pavement", M_SOIL: "soil", M_MARKING: "marking"}
    for m, name in ground.items():
        out[(ob < 0) & (mat == m)] = COVER_CODES[name]
    c = scene.cls[np.maximum(ob, 0)]
    for k, name in ((C_BUILDING, "building"), (C_CAR, "car"), (C_TREE, "tree")):
        out[(ob >= 0) & (c == k)] = COVER_CODES[name]
    return out


def write_cover_truth(truth_dir, town: Town, scenes: dict, grid: AOIGrid) -> list:
    """Write ``cover_A.tif`` and ``cover_B.tif`` (:func:`surface_cover` of each epoch) into ``truth_dir``."""
    from pathlib import Path

    from ..io.raster import write_cog

    legend = ", ".join(f"{v} {k}" for k, v in COVER_CODES.items())
    out = []
    for ep, sc in scenes.items():
        p = Path(truth_dir) / f"cover_{ep}.tif"
        write_cog(
            p,
            surface_cover(town, sc, grid),
            grid,
            dtype="uint8",
            nodata=0,
            tags={"content": f"surface cover seen from above, epoch {ep}: {legend}; vegetation = grass or tree"},
        )
        out.append(p)
    return out


def bare_dem(town: Town, grid: AOIGrid) -> np.ndarray:
    """Terrain height (float64, ellipsoidal m) at the grid's cell centres."""
    x, y = _grid_xy(town, grid)
    return town.terrain.at(x, y)


def change_products(
    dsm_a: np.ndarray,
    dsm_b: np.ndarray,
    cls_a: np.ndarray,
    cls_b: np.ndarray,
    posting_m: float,
    threshold_m: float = CHANGE_THRESHOLD_M,
    min_area_m2: float = MIN_CHANGE_AREA_M2,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """3-D change mask from two exact DSMs.

    Returns
    -------
    mask : uint8, 1 where |ΔDSM| > threshold_m (regions below ``min_area_m2`` removed)
    cls : uint8 class code of the changed object (the higher of the two surfaces), 0 elsewhere
    sign : int8, +1 raised, −1 lowered, 0 unchanged
    """
    from scipy import ndimage

    d = dsm_b - dsm_a
    m = np.abs(d) > threshold_m
    lab, n = ndimage.label(m, structure=np.ones((3, 3)))
    if n:
        sizes = ndimage.sum(m, lab, index=np.arange(1, n + 1)) * posting_m * posting_m
        small = np.concatenate([[False], sizes < min_area_m2])
        m[small[lab]] = False
    cls = np.where(d > 0, cls_b, cls_a).astype(np.uint8)
    cls[~m] = 0
    sign = np.zeros(d.shape, np.int8)
    sign[m & (d > 0)] = 1
    sign[m & (d < 0)] = -1
    return m.astype(np.uint8), cls, sign


def non3d_mask(
    town: Town, scene_a: K.SceneArrays, scene_b: K.SceneArrays, grid: AOIGrid, change_mask: np.ndarray
) -> np.ndarray:
    """Cells whose appearance changes with no 3-D change: 1 repainted roof, 2 vegetation (season)."""
    x, y = _grid_xy(town, grid)
    _, ob_a = surface_height(scene_a, x, y, return_object=True)
    _, ob_b = surface_height(scene_b, x, y, return_object=True)
    out = np.zeros(x.shape, np.uint8)
    repainted = {c.object_id for c in town.changes if c.kind == "repaint"}
    if any(c.kind == "season" for c in town.changes):
        mat = np.empty(x.size, np.int64)
        K.ground_material_many(scene_a, np.ascontiguousarray(x.ravel()), np.ascontiguousarray(y.ravel()), mat)
        grass = (ob_a == -1) & (ob_b == -1) & (mat.reshape(x.shape) == M_GRASS)
        trees = (
            (ob_a >= 0)
            & (scene_a.cls[np.maximum(ob_a, 0)] == C_TREE)
            & (ob_b >= 0)
            & (scene_b.cls[np.maximum(ob_b, 0)] == C_TREE)
        )
        out[grass | trees] = NON3D_CODES["vegetation_season"]
    if repainted:
        bid_a = np.where(ob_a >= 0, scene_a.par[np.maximum(ob_a, 0), 3] - 1000, -1)
        cls_a = np.where(ob_a >= 0, scene_a.cls[np.maximum(ob_a, 0)], -1)
        rp = (cls_a == C_BUILDING) & np.isin(bid_a, list(repainted))
        out[rp] = NON3D_CODES["repainted_roof"]
    out[change_mask > 0] = 0
    return out


def image_change_mask(
    town: Town,
    camera: Camera,
    scene_a: K.SceneArrays,
    scene_b: K.SceneArrays,
    *,
    threshold_m: float = CHANGE_THRESHOLD_M,
    supersample: int = 2,
    block_rows: int = 128,
) -> tuple[np.ndarray, np.ndarray]:
    """Pixels of ``camera``'s image that see a 3-D change between the two epochs.

    Returns
    -------
    mask : uint8 (rows, cols), 1 where at least half of the pixel's samples see surfaces
        more than ``threshold_m`` apart in the two epochs
    fraction : float32 (rows, cols), the fraction of such samples
    """
    h, w = int(camera.height), int(camera.width)
    k = supersample
    off = (np.arange(k) + 0.5) / k - 0.5
    za, zb = scene_z_band(scene_a), scene_z_band(scene_b)
    band = (min(za[0], zb[0]), max(za[1], zb[1]))
    frac = np.zeros((h, w), np.float32)
    for b0 in range(0, h, block_rows):
        b1 = min(h, b0 + block_rows)
        R = (np.arange(b0, b1) + 0.5)[:, None, None, None] + off[None, None, :, None]
        C = (np.arange(w) + 0.5)[None, :, None, None] + off[None, None, None, :]
        R, C = np.broadcast_arrays(R, C)
        o, d, tm = camera_rays(town, camera, C.ravel(), R.ravel(), band)
        n = o.shape[0]
        hits = []
        for S in (scene_a, scene_b):
            t = np.empty(n)
            ob = np.empty(n, np.int64)
            fc = np.empty(n, np.int64)
            K.trace_first_hit(o, d, tm, S, t, ob, fc)
            hits.append(np.where(ob[:, None] >= -1, o + t[:, None] * d, np.nan))
        dist = np.linalg.norm(hits[0] - hits[1], axis=1)
        ch = (dist > threshold_m) & np.isfinite(dist)
        frac[b0:b1] = ch.reshape(b1 - b0, w, k * k).mean(axis=2)
    return (frac >= 0.5).astype(np.uint8), frac


def footprints_frame(town: Town, epoch: str):
    """GeoDataFrame of the epoch's buildings (UTM) with ``building_id`` and ``status``."""
    import geopandas as gpd
    from shapely.affinity import translate

    status = building_status(town)[epoch]
    repainted = {c.object_id for c in town.changes if c.kind == "repaint"}
    dz = {c.object_id: c.dz_m for c in town.changes if c.kind in ("new", "demolished", "raised", "lowered")}
    rows = []
    for b in town.epochs[epoch].buildings:
        poly = translate(b.polygon(), town.frame.e0, town.frame.n0)
        rows.append(
            {
                "building_id": int(b.building_id),
                "status": status[b.building_id],
                "kind": b.kind,
                "roof": b.roof,
                "storeys": int(b.storeys),
                "ground_m": round(b.ground_m, 3),
                "eave_m": round(b.eave_m, 3),
                "top_m": round(b.top_m, 3),
                "height_m": round(b.top_m - b.ground_m, 3),
                "dz_m": round(float(dz.get(b.building_id, 0.0)), 3),
                "repainted": int(b.building_id in repainted),
                "geometry": poly,
            }
        )
    return gpd.GeoDataFrame(rows, geometry="geometry", crs=town.frame.crs.to_wkt())


def footprints_all(town: Town):
    """Every building of either epoch once, with its change status (new, demolished, raised, lowered, unchanged)."""
    import pandas as pd

    a = footprints_frame(town, "A")
    b = footprints_frame(town, "B")
    extra = b[~b["building_id"].isin(a["building_id"])]
    out = pd.concat([a, extra], ignore_index=True)
    st = {**building_status(town)["A"], **building_status(town)["B"]}
    out["status"] = [st[i] for i in out["building_id"]]
    return out


def objects_frame(town: Town, epoch: str, what: str):
    """Trees (crown disks) or cars (body rectangles) of an epoch as a GeoDataFrame (UTM)."""
    import geopandas as gpd
    from shapely.affinity import translate
    from shapely.geometry import Point

    ep = town.epochs[epoch]
    rows = []
    if what == "trees":
        for t in ep.trees:
            rows.append(
                {
                    "tree_id": t.tree_id,
                    "crown_r_m": round(t.crown_r, 3),
                    "top_m": round(t.top_m, 3),
                    "geometry": translate(Point(t.cx, t.cy).buffer(t.crown_r, 16), town.frame.e0, town.frame.n0),
                }
            )
    elif what == "cars":
        for c in ep.cars:
            rows.append(
                {
                    "car_id": c.car_id,
                    "height_m": c.height_m,
                    "geometry": translate(c.body.polygon(), town.frame.e0, town.frame.n0),
                }
            )
    else:
        raise ValueError(f"what must be 'trees' or 'cars', got {what!r}")
    if not rows:  # a small town may have no cars or trees: an empty layer with the same columns
        cols = ["tree_id", "crown_r_m", "top_m"] if what == "trees" else ["car_id", "height_m"]
        return gpd.GeoDataFrame({c: [] for c in cols}, geometry=[], crs=town.frame.crs.to_wkt())
    return gpd.GeoDataFrame(rows, geometry="geometry", crs=town.frame.crs.to_wkt())


def building_corners_lonlath(town: Town, epoch: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Roof corners (eaves and ridge ends) of the epoch's buildings: map xyz (N, 3), lon, lat, h."""
    pts = np.concatenate([b.corners_3d() for b in town.epochs[epoch].buildings])
    lon, lat = town.frame.to_lonlat(pts[:, 0], pts[:, 1])
    return pts, lon, lat, pts[:, 2]


def corner_check(
    town: Town, epoch: str, scene: K.SceneArrays, camera: Camera, model: Camera, tol_m: float = 0.01
) -> dict:
    """Truth building corners through ``model`` (e.g. the written RPC) vs where the renderer drew them.

    For every roof corner X (eave corners and ridge ends), the renderer's own
    ray through the physical projection ``u = camera.project(X)`` is built (the
    same ray generation that renders the image) and cast into the scene. The
    renderer drew X at ``u`` when that ray passes within ``tol_m`` of X and
    nothing is hit before X (the corner is not hidden: occluded corners are
    skipped). The error is ``|model.project(X) − u|`` in pixels.

    Returns
    -------
    dict: n_corners (in the image), n_visible, max_px, rms_px, max_ray_miss_m
    (largest distance between a visible corner and the renderer's ray).
    """
    X, lon, lat, h = building_corners_lonlath(town, epoch)
    col, row = camera.project(lon, lat, h)
    inside = np.isfinite(col) & (col > 1) & (row > 1) & (col < camera.width - 1) & (row < camera.height - 1)
    X, lon, lat, h, col, row = X[inside], lon[inside], lat[inside], h[inside], col[inside], row[inside]
    o, d, tm = camera_rays(town, camera, col, row, scene_z_band(scene))
    t = np.empty(o.shape[0])
    ob = np.empty(o.shape[0], np.int64)
    fc = np.empty(o.shape[0], np.int64)
    K.trace_first_hit(o, d, tm, scene, t, ob, fc)
    tc = np.sum((X - o) * d, axis=1)
    miss = np.linalg.norm(o + tc[:, None] * d - X, axis=1)
    vis = (miss < tol_m) & (t >= tc - tol_m)
    mc, mr = model.project(lon[vis], lat[vis], h[vis])
    err = np.hypot(mc - col[vis], mr - row[vis])
    return {
        "n_corners": int(inside.sum()),
        "n_visible": int(vis.sum()),
        "max_px": float(err.max()) if err.size else float("nan"),
        "rms_px": float(np.sqrt(np.mean(err**2))) if err.size else float("nan"),
        "max_ray_miss_m": float(miss[vis].max()) if vis.any() else float("nan"),
    }
