"""Per-image probability maps onto the ground grid, with occlusion, and several views combined.

The orthorectification itself is :func:`geocd.ortho.orthorectify` (true ortho:
every grid cell is placed at its surface height, projected into the image,
and marked unobserved when the surface between it and the camera hides it).
This module supplies what the thesis's projection needs around it:

* :func:`building_surface` — the surface a ray meets: the DEM with building
  footprints extruded to their height (the thesis's building map), or a DSM;
  a ray that meets a building lands on the roof, never on the ground behind;
* :func:`project_view` — one image's probability map (or a window of it, a
  "detailed view") on the grid: values, observed mask, weight per cell;
* :func:`combine_views` — the weighted mean over the views that observe a cell
  (weight = cosine of the incidence angle on the surface × the view's sampling
  density, capped at one image pixel per cell); unobserved cells stay NaN.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..camera import Camera
from ..errors import ConfigError, GridError
from ..geodesy import AOIGrid
from ..ortho import OrthoParams, orthorectify, view_geometry

#: footprint attributes tried for building heights above the ground (m)
HEIGHT_FIELDS = ("height_m", "height", "HEIGHT", "hgt", "building_height", "bldg_h")


def building_surface(
    dem_m: np.ndarray, grid: AOIGrid, footprints=None, height_field: str | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """DEM with footprints extruded to their height, and the building occupancy (fraction of each cell).

    Parameters
    ----------
    dem_m : float (rows, cols) on ``grid``, ellipsoidal m (NaN = no height)
    footprints : GeoDataFrame of polygons, optional (reprojected to the grid's CRS)
    height_field : attribute with the building height above the ground (m); None = the first of
        :data:`HEIGHT_FIELDS` present. Without heights the occupancy is still returned and the surface
        is the DEM.

    Returns
    -------
    surface_m : float64 (rows, cols); occupancy : float32 (rows, cols) in [0, 1]
    """
    from rasterio.features import rasterize

    dem = np.asarray(dem_m, np.float64)
    if dem.shape != grid.shape:
        raise GridError(f"DEM shape {dem.shape} does not match the grid {grid.shape}")
    surface = dem.copy()
    occ = np.zeros(grid.shape, np.float32)
    if footprints is None or len(footprints) == 0:
        return surface, occ
    fp = footprints.to_crs(grid.crs) if footprints.crs is not None else footprints
    # occupancy: fraction of 4 × 4 sub-samples of each cell inside a footprint
    k = 4
    t = grid.transform
    from affine import Affine

    fine = rasterize(
        [(g, 1) for g in fp.geometry],
        out_shape=(grid.height * k, grid.width * k),
        transform=t @ Affine.scale(1.0 / k),
        fill=0,
        dtype="uint8",
    )
    occ = fine.reshape(grid.height, k, grid.width, k).mean(axis=(1, 3)).astype(np.float32)
    if height_field is None:
        height_field = next((h for h in HEIGHT_FIELDS if h in fp.columns), None)
    elif height_field not in fp.columns:
        raise ConfigError(
            f"footprints have no attribute {height_field!r}; attributes: {[c for c in fp.columns if c != 'geometry']}"
        )
    if height_field is not None:
        h = fp[height_field].astype(float).to_numpy()
        ok = np.isfinite(h) & (h > 0)
        if ok.any():
            hag = rasterize(
                [(g, float(v)) for g, v in zip(fp.geometry[ok], h[ok])],
                out_shape=grid.shape,
                transform=t,
                fill=0.0,
                dtype="float32",
                all_touched=False,
            )
            surface = np.where(hag > 0, dem + hag, dem)
    return surface, occ


@dataclass
class ProjectedView:
    """One view's probability on the grid.

    Attributes
    ----------
    values : float32 (rows, cols), NaN where not observed
    observed : bool (rows, cols)
    weight : float32 (rows, cols), 0 where not observed
    name : str
    """

    values: np.ndarray
    observed: np.ndarray
    weight: np.ndarray
    name: str = ""


def view_weight(result) -> np.ndarray:
    """Per-cell weight of an orthorectified view: cos(incidence) × min(1, image pixels per cell)²."""
    w = result.weights
    cos_inc = np.nan_to_num(np.asarray(w["cos_incidence"], np.float64), nan=0.0)
    ppc = np.nan_to_num(np.asarray(w["px_per_cell"], np.float64), nan=0.0)
    out = cos_inc * np.minimum(ppc, 1.0) ** 2
    out[~result.observed] = 0.0
    return out.astype(np.float32)


def project_view(
    probability: np.ndarray,
    camera: Camera,
    grid: AOIGrid,
    surface_m: np.ndarray,
    *,
    window: tuple[int, int, int, int] | None = None,
    geometry=None,
    name: str = "",
    params: OrthoParams = OrthoParams(),
) -> ProjectedView:
    """Orthorectify one probability map (image geometry) onto the grid with occlusion.

    Parameters
    ----------
    probability : float (rows, cols) in the image's full geometry, NaN = no data
    window : (row0, col0, height, width), optional: only this part of the image is a view
        (a "detailed view" cut from a larger photograph); the rest is treated as unseen.
    geometry : ViewGeometry, optional, reused from an earlier call with the same camera and surface
    """
    p = np.asarray(probability, np.float32)
    if p.ndim != 2:
        raise ConfigError(f"probability map must be (rows, cols), got {p.shape}")
    col0 = row0 = 0
    if window is not None:
        r0, c0, h, w = (int(v) for v in window)
        p = p[r0 : r0 + h, c0 : c0 + w]
        row0, col0 = r0, c0
    res = orthorectify(p, camera, grid, surface_m, col0=col0, row0=row0, params=params, geometry=geometry)
    vals = res.values[0].astype(np.float32)
    return ProjectedView(values=vals, observed=res.observed.copy(), weight=view_weight(res), name=name)


def combine_views(views: list[ProjectedView]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Weighted mean of several projected views.

    Returns
    -------
    mean : float32 (rows, cols), NaN where no view observes the cell (or all weights are 0)
    weight : float32 (rows, cols), the summed weights
    count : uint8 (rows, cols), number of views observing the cell
    """
    if not views:
        raise ConfigError("no view to combine")
    shape = views[0].values.shape
    num = np.zeros(shape)
    den = np.zeros(shape)
    cnt = np.zeros(shape, np.int32)
    for v in views:
        if v.values.shape != shape:
            raise GridError("projected views are on different grids")
        ok = v.observed & np.isfinite(v.values) & (v.weight > 0)
        num[ok] += v.weight[ok] * v.values[ok]
        den[ok] += v.weight[ok]
        cnt[ok] += 1
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(den > 0, num / den, np.nan).astype(np.float32)
    return mean, den.astype(np.float32), np.minimum(cnt, 255).astype(np.uint8)


def cell_pixels(
    camera: Camera, grid: AOIGrid, surface_m: np.ndarray, image_shape: tuple[int, int], geometry=None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The image pixel each grid cell is seen in: (row, col) int arrays (−1 where unobserved), observed mask.

    Used to carry labels drawn on the map into an image, and a grid quantity (height above ground)
    into image space.
    """
    H, W = image_shape
    index = np.arange(H * W, dtype=np.float64).reshape(H, W)
    geo = geometry if geometry is not None else view_geometry(camera, grid, surface_m)
    res = orthorectify(
        index, camera, grid, surface_m, params=OrthoParams(resampling="nearest", antialias=False), geometry=geo
    )
    obs = res.observed & np.isfinite(res.values[0])
    flat = np.where(obs, res.values[0], -1).astype(np.int64)
    rows = np.where(obs, flat // W, -1)
    cols = np.where(obs, flat % W, -1)
    return rows, cols, obs


def grid_to_image(
    values: np.ndarray,
    rows: np.ndarray,
    cols: np.ndarray,
    observed: np.ndarray,
    image_shape: tuple[int, int],
    max_gap_px: float = 3.0,
) -> np.ndarray:
    """Carry a grid quantity into image space: each observed cell paints the pixel it is seen in, and
    pixels within ``max_gap_px`` of a painted pixel take the nearest painted value (NaN beyond)."""
    from scipy import ndimage

    out = np.full(image_shape, np.nan, np.float32)
    ok = observed & np.isfinite(values)
    out[rows[ok], cols[ok]] = values[ok]
    miss = ~np.isfinite(out)
    if miss.all():
        return out
    dist, (ii, jj) = ndimage.distance_transform_edt(miss, return_indices=True)
    fill = out[ii, jj]
    return np.where(miss & (dist <= max_gap_px), fill, out).astype(np.float32)
