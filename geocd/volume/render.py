"""Rendering from the volume model: expected image (paper Fig. 8) and expected height map.

* Expected image: ``E[c] = Σ_i vis_i (1 - e^{-α_i ℓ_i}) E[p_i] + vis_∞ · 0.5`` per pixel
  ray, with the appearance of the illumination bin nearest to the view's sun.
* Expected height map: vertical rays from above at each AOI grid cell centre;
  the height is where the visibility from above drops to 0.5 (the surface a
  viewer from above most likely sees; exact within a cell since α is constant
  there). Heights are WGS84 ellipsoidal metres; NaN where the ray reaches the
  bottom with visibility above 0.5.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Optional

import numpy as np

from ..errors import ProcessingError
from ..geodesy import AOIGrid, to_lonlat
from ..progress import Progress, ensure_progress
from . import _kernels as K
from .rays import check_camera_sees_volume, image_rays, vertical_rays
from .scene import VolumeModel
from .update import P_BACKGROUND, TILE_PIXELS, RayScratch

MEAN_BACKGROUND = 0.5
_E = np.zeros(0)


@dataclass
class RenderResult:
    """Per-pixel outputs of a render pass (arrays of the image's shape, float32).

    Attributes
    ----------
    expected : expected intensity in [0, 1]
    vis_inf : probability that the ray crosses the whole volume unoccluded
    density : density of the observed intensity (eq. 27 + background); NaN without observations
    depth_m : distance from the ray start (above the volume) to the median visible surface
    sun_bin : illumination bin used (-1: none trained, uniform appearance)
    segments : ray-cell segments traced
    """

    expected: np.ndarray
    vis_inf: np.ndarray
    density: np.ndarray
    depth_m: np.ndarray
    sun_bin: int
    segments: int


def appearance_bin(model: VolumeModel, sun: tuple[float, float] | None) -> int:
    """The trained illumination bin nearest to ``sun`` (-1 if no bin is trained)."""
    trained = model.trained_bins()
    if not trained:
        return -1
    if sun is None:
        return trained[0]
    d = [model.sun_bin_distance_deg(sun, b) for b in trained]
    return trained[int(np.argmin(d))]


def render_image(
    model: VolumeModel,
    camera: Any,
    shape: tuple[int, int],
    *,
    intensity: np.ndarray | None = None,
    sun: tuple[float, float] | None = None,
    stride: int = 1,
    name: str = "the view",
    app: np.ndarray | None = None,
    app_bin: int | None = None,
    mapping: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
    progress: Optional[Progress] = None,
) -> RenderResult:
    """Trace every pixel ray of a view (every ``stride``-th pixel; others NaN).

    Parameters
    ----------
    shape : (rows, cols) of the image
    intensity : optional (rows, cols) intensities in [0, 1] (NaN invalid) whose
        density is evaluated (change detection).
    app, app_bin : optional appearance array and bin to use instead of the model's.
    mapping : optional per-pixel radiometric map ``(a, b, s)`` of the mixtures, each (rows, cols)
        (relighting, :mod:`geocd.volume.relight`).
    """
    prog = ensure_progress(progress)
    rows, cols = int(shape[0]), int(shape[1])
    geom = model.geometry
    check_camera_sees_volume(camera, geom, cols, rows, name)
    b = appearance_bin(model, sun) if app_bin is None else int(app_bin)
    app_arr = model.app if app is None else app
    stride = max(int(stride), 1)
    out = {k: np.full((rows, cols), np.nan, dtype=np.float32) for k in ("expected", "vis_inf", "density", "depth_m")}
    geo = geom.geo_array()
    lo, hi = geom.box_lo, geom.box_hi
    sc = RayScratch(geo)
    tile_rows = max(stride, (TILE_PIXELS // max(cols // stride, 1)) * stride)
    n_segs = 0
    for r0 in range(0, rows, tile_rows):
        r1 = min(rows, r0 + tile_rows)
        o, d, rr, cc = image_rays(camera, geom, r0, r1, cols, stride)
        obs = intensity[rr, cc].astype(np.float64) if intensity is not None else np.full(rr.size, np.nan)
        dens = np.empty(rr.size)
        expv = np.empty(rr.size)
        vinf = np.empty(rr.size)
        tmed = np.empty(rr.size)
        if mapping is None:
            ma = mb = ms = np.zeros(0)
        else:
            ma, mb, ms = (np.ascontiguousarray(m_[rr, cc], dtype=np.float64) for m_ in mapping)
        n_segs += K.render_rays(
            o,
            d,
            obs,
            lo,
            hi,
            geo,
            model.block_root,
            model.child,
            model.alpha,
            app_arr,
            b,
            P_BACKGROUND,
            MEAN_BACKGROUND,
            model.params.appearance_prior_weight,
            ma,
            mb,
            ms,
            dens,
            expv,
            vinf,
            tmed,
            sc.seg_cell,
            sc.seg_len,
            sc.seg_t,
        )
        bad = ~np.isfinite(o[:, 0])
        for arr in (dens, expv, vinf, tmed):
            arr[bad] = np.nan
        out["density"][rr, cc] = dens
        out["expected"][rr, cc] = expv
        out["vis_inf"][rr, cc] = vinf
        out["depth_m"][rr, cc] = tmed
        prog(r1 / rows, f"render {name}: rows {r1}/{rows}")
    return RenderResult(out["expected"], out["vis_inf"], out["density"], out["depth_m"], b, int(n_segs))


def expected_image(
    model: VolumeModel,
    camera: Any,
    shape: tuple[int, int],
    *,
    sun: tuple[float, float] | None = None,
    stride: int = 1,
    progress: Optional[Progress] = None,
) -> RenderResult:
    """Expected image of a view (paper Fig. 8); see :func:`render_image`."""
    return render_image(model, camera, shape, sun=sun, stride=stride, progress=progress)


def expected_height_map(
    model: VolumeModel,
    grid: AOIGrid | None = None,
    *,
    posting_m: float | None = None,
    progress: Optional[Progress] = None,
) -> tuple[np.ndarray, AOIGrid]:
    """Height of the median visible surface from above, on an AOI grid.

    Parameters
    ----------
    grid : AOIGrid, optional
        Output grid (must be in the model's CRS); default: the model's AOI at
        ``posting_m`` (default: the finest cell size).

    Returns
    -------
    height_m : float32 (rows, cols), WGS84 ellipsoidal metres, NaN where unknown
    grid : the AOIGrid of ``height_m``
    """
    prog = ensure_progress(progress)
    geom = model.geometry
    if grid is None:
        grid = geom.aoi_grid(posting_m or geom.finest_cell_m)
    else:
        geom.check_crs(grid.crs, "the height-map grid")
    x, y = grid.xy()
    lon, lat = to_lonlat(x.ravel(), y.ravel(), grid.crs)
    fr = geom.frame
    e, n, _ = fr.to_enu(lon, lat, np.full(lon.shape, fr.h0))
    o, d = vertical_rays(geom, e, n)
    geo = geom.geo_array()
    sc = RayScratch(geo)
    N = o.shape[0]
    tmed = np.empty(N)
    dens = np.empty(N)
    expv = np.empty(N)
    vinf = np.empty(N)
    step = 262144
    for s in range(0, N, step):
        sl = slice(s, min(N, s + step))
        K.render_rays(
            o[sl],
            d[sl],
            np.full(sl.stop - sl.start, np.nan),
            geom.box_lo,
            geom.box_hi,
            geo,
            model.block_root,
            model.child,
            model.alpha,
            model.app,
            -1,
            P_BACKGROUND,
            MEAN_BACKGROUND,
            0.0,
            _E,
            _E,
            _E,
            dens[sl],
            expv[sl],
            vinf[sl],
            tmed[sl],
            sc.seg_cell,
            sc.seg_len,
            sc.seg_t,
        )
        prog(sl.stop / N, "height map")
    u = o[:, 2] - tmed
    ok = np.isfinite(u)
    h = np.full(N, np.nan)
    if ok.any():
        _, _, hh = fr.from_enu(e[ok], n[ok], u[ok])
        h[ok] = hh
    if not ok.any():
        raise ProcessingError(
            "the model has no surface yet (visibility from above never drops to 0.5); update it with more images"
        )
    return h.reshape(grid.shape).astype(np.float32), grid


def orthorectify(values: np.ndarray, camera: Any, height_m: np.ndarray, grid: AOIGrid) -> np.ndarray:
    """Sample an image-geometry array onto an AOI grid through ``camera`` at heights ``height_m``.

    Nearest-pixel sampling; NaN outside the image or where the height is NaN.
    """
    x, y = grid.xy()
    lon, lat = to_lonlat(x, y, grid.crs)
    with np.errstate(all="ignore"):
        c, r = camera.project(lon, lat, height_m.astype(np.float64))
    rows, cols = values.shape
    ok = np.isfinite(c) & np.isfinite(r) & (c >= 0) & (r >= 0) & (c < cols) & (r < rows)
    out = np.full(grid.shape, np.nan, dtype=np.float32)
    out[ok] = values[r[ok].astype(int), c[ok].astype(int)]
    return out


__all__ = ["RenderResult", "render_image", "expected_image", "expected_height_map", "orthorectify", "appearance_bin"]
