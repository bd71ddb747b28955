"""Appearance under a sun the model was not trained with (shadow-aware relighting).

The paper keeps one appearance model per sun-position bin (after Pollard et al.)
and names appearance models that handle large illumination changes as future
work. A new image whose sun is far from every trained bin has no appearance
model of its own; using the nearest bin's as is makes every moved shadow look
like change. This module is geocd's extension (not in the paper): the learned
occlusion density itself predicts where shadows fall under both suns.

1. A render pass with the trained bin gives, per pixel of the new image, the
   expected intensity ``E`` and the median visible surface point (where the
   ray's visibility drops to 0.5).
2. From that point (lifted by half a finest cell), the sun visibility
   ``s = exp(-∫ α)`` towards the trained bin's sun and towards the new sun
   (:func:`_kernels.surface_sun`). With a DSM of the training epoch
   (``shadow_dsm``), the point is lit or shadowed by the DSM's cast shadow
   instead (:func:`dsm_shadow_height`): the model's buildings are hollow
   (their interiors and most walls are never observed), so a sun ray from
   the ground behind a building often passes through it unblocked; a
   2.5-D surface is closed below.
3. Pixels fall in four transition classes (lit/shadow under the old sun ×
   lit/shadow under the new one, threshold 0.5); per class a robust line
   ``c ≈ a + b E`` and its residual spread are fitted on the new image (bisquare
   IRLS). Changes are a minority of pixels, so the fit follows the unchanged
   scene: Carlotto's joint-histogram idea, conditioned on the predicted shadow
   transition, which also absorbs global radiometric differences (season,
   sensor gain).
4. Every mixture along a pixel's ray is mapped by the pixel's class:
   ``μ' = a + b μ`` and ``σ' = sqrt((b σ)² + σ_extra²)``, ``σ_extra`` being the
   class's spread in excess of the lit→lit class's. Eq. 27 then runs unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Optional

import numpy as np

from ..errors import ConfigError
from ..geodesy import AOIGrid
from ..progress import Progress, ensure_progress
from . import _kernels as K
from .baseline import sample_grid
from .rays import image_rays
from .scene import MU, WEIGHT, VolumeModel
from .update import TILE_PIXELS, RayScratch

CLASSES = ("lit>lit", "lit>shadow", "shadow>lit", "shadow>shadow")


def sun_vector_enu(sun: tuple[float, float]) -> np.ndarray:
    """Unit vector towards the sun (azimuth clockwise from north, elevation; degrees), ENU."""
    az, el = np.radians(float(sun[0])), np.radians(float(sun[1]))
    return np.array([np.sin(az) * np.cos(el), np.cos(az) * np.cos(el), np.sin(el)])


def node_boxes(model: VolumeModel) -> tuple[np.ndarray, np.ndarray]:
    """Centre (N, 3) ENU metres and edge (N,) metres of every node."""
    n = model.n_nodes
    c = np.zeros((n, 3))
    s = np.zeros(n)
    K.node_boxes(model.geometry.geo_array(), model.block_root, model.child, c, s)
    return c, s


def occupied_leaves(model: VolumeModel, occupied_p: float = 0.02) -> np.ndarray:
    """Leaves whose own occlusion probability across one edge exceeds ``occupied_p``."""
    g = model.geometry
    edge = g.block_size_m / (2.0 ** model.level.astype(np.float64))
    p = -np.expm1(-model.alpha.astype(np.float64) * edge)
    return np.nonzero((model.child < 0) & (p > occupied_p))[0]


def cell_sun_visibility(
    model: VolumeModel,
    sun: tuple[float, float],
    cells: np.ndarray | None = None,
    skip_cells: float = 1.0,
    boxes: tuple[np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """Sun visibility (0..1) from the top face of every node in ``cells`` (default: occupied leaves); 1 elsewhere."""
    if cells is None:
        cells = occupied_leaves(model)
    centers, sizes = boxes if boxes is not None else node_boxes(model)
    g = model.geometry
    geo = g.geo_array()
    sc = RayScratch(geo)
    vis = np.ones(model.n_nodes)
    out = np.empty(cells.size)
    K.sun_visibility(
        cells.astype(np.int64),
        centers,
        sizes,
        sun_vector_enu(sun),
        float(skip_cells),
        g.box_lo,
        g.box_hi,
        geo,
        model.block_root,
        model.child,
        model.alpha,
        out,
        sc.seg_cell,
        sc.seg_len,
        sc.seg_t,
    )
    vis[cells] = out
    return vis


def mixture_mean(app: np.ndarray, b: int) -> np.ndarray:
    """Mean of each node's mixture in bin ``b`` (0.5 where empty)."""
    m = app[:, b]
    w = m[..., WEIGHT].astype(np.float64)
    ws = w.sum(axis=1)
    mu = (w * m[..., MU]).sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(ws > 0, mu / ws, 0.5)


@dataclass
class RelightFit:
    """Per transition class: line ``c = a + b E``, residual spread, pixel count."""

    a: np.ndarray = field(default_factory=lambda: np.zeros(4))
    b: np.ndarray = field(default_factory=lambda: np.ones(4))
    sigma: np.ndarray = field(default_factory=lambda: np.zeros(4))
    count: np.ndarray = field(default_factory=lambda: np.zeros(4, dtype=np.int64))

    def to_dict(self) -> dict:
        return {
            c: {
                "a": float(self.a[i]),
                "b": float(self.b[i]),
                "sigma": float(self.sigma[i]),
                "pixels": int(self.count[i]),
            }
            for i, c in enumerate(CLASSES)
        }


def robust_line(x: np.ndarray, y: np.ndarray, iters: int = 8) -> tuple[float, float, float]:
    """Bisquare-IRLS line fit ``y ≈ a + b x``; returns (a, b, robust residual sigma)."""
    A = np.column_stack([np.ones_like(x), x])
    w = np.ones_like(x)
    coef = np.array([0.0, 1.0])
    for _ in range(iters):
        sw = np.sqrt(w)
        coef, *_ = np.linalg.lstsq(A * sw[:, None], y * sw, rcond=None)
        r = y - A @ coef
        s = 1.4826 * np.median(np.abs(r)) + 1e-6
        u = r / (4.685 * s)
        w = np.where(np.abs(u) < 1, (1 - u * u) ** 2, 0.0)
    r = y - A @ coef
    return float(coef[0]), float(coef[1]), float(1.4826 * np.median(np.abs(r)))


def fit_classes(
    expected: np.ndarray,
    observed: np.ndarray,
    klass: np.ndarray,
    min_pixels: int = 200,
    lit_expected: np.ndarray | None = None,
) -> RelightFit:
    """Per-class robust lines ``observed ≈ a + b expected`` (classes 0..3, see :data:`CLASSES`).

    ``lit_expected``: optional expectation for the lit → lit class alone (a shading model's); a class too
    small to fit borrows the plain lit → lit line, fitted on ``expected``."""
    fit = RelightFit()
    for i in range(4):
        sel = klass == i
        fit.count[i] = int(sel.sum())
        if sel.sum() >= min_pixels:
            fit.a[i], fit.b[i], fit.sigma[i] = robust_line(expected[sel], observed[sel])
    if fit.count[0] < min_pixels:
        fit.a[0], fit.b[0], fit.sigma[0] = 0.0, 1.0, 0.0
    for i in (1, 2, 3):
        if fit.count[i] < min_pixels:  # borrow from the other shadow class, else from lit>lit
            j = 3 if i != 3 else 1
            src = j if fit.count[j] >= min_pixels else 0
            fit.a[i], fit.b[i], fit.sigma[i] = fit.a[src], fit.b[src], fit.sigma[src]
    if lit_expected is not None and fit.count[0] >= min_pixels:
        sel = klass == 0
        fit.a[0], fit.b[0], fit.sigma[0] = robust_line(lit_expected[sel], observed[sel])
    return fit


def _surface_rays(model: VolumeModel, camera: Any, depth_m: np.ndarray):
    """Per tile of image rows: (rr, cc, o, d, t) of every pixel's ray and its median visible surface depth."""
    rows, cols = depth_m.shape
    tile_rows = max(1, TILE_PIXELS // cols)
    for r0 in range(0, rows, tile_rows):
        o, d, rr, cc = image_rays(camera, model.geometry, r0, min(rows, r0 + tile_rows), cols, 1)
        yield rr, cc, o, d, depth_m[rr, cc].astype(np.float64)


def surface_sun_visibility(
    model: VolumeModel, camera: Any, depth_m: np.ndarray, sun: tuple[float, float]
) -> np.ndarray:
    """Sun visibility (rows, cols) of each pixel's median visible surface point (1 where there is none)."""
    g = model.geometry
    geo = g.geo_array()
    sc = RayScratch(geo)
    out = np.ones(depth_m.shape)
    f = g.finest_cell_m
    for rr, cc, o, d, t in _surface_rays(model, camera, depth_m):
        s = np.empty(rr.size)
        K.surface_sun(
            o,
            d,
            t,
            sun_vector_enu(sun),
            0.5 * f,
            1.0 * f,
            g.box_lo,
            g.box_hi,
            geo,
            model.block_root,
            model.child,
            model.alpha,
            s,
            sc.seg_cell,
            sc.seg_len,
            sc.seg_t,
        )
        out[rr, cc] = s
    return out


def dsm_shadow_height(
    dsm_m: np.ndarray, posting_m: float, sun: tuple[float, float], *, step_cells: float = 0.5
) -> np.ndarray:
    """Height below which a point of each cell lies in the DSM's cast shadow (same datum as the DSM).

    ``h(p) = max_k dsm(p + k·step·ŝ) − k·step·posting·tan(elevation)``: the highest line towards the sun
    that the surface blocks, marched in half-cell steps (bilinear) up to the distance at which the DSM's
    height range can still cast a shadow (so the cost grows with that range: terrain relief included).
    Grid rows run south, columns east; NaN cells and cells beyond the grid take the DSM's lowest height.

    Parameters
    ----------
    dsm_m : float (rows, cols), metres
    posting_m : float, cell size (metres)
    sun : (azimuth clockwise from north, elevation), degrees

    Returns
    -------
    float64 (rows, cols); +inf everywhere for a sun at or below the horizon, −inf for a DSM without a valid
    height or without relief
    """
    from scipy.ndimage import map_coordinates

    z = np.asarray(dsm_m, dtype=np.float64)
    az, el = np.radians(float(sun[0])), np.radians(float(sun[1]))
    if el <= 0:
        return np.full(z.shape, np.inf)
    ok = np.isfinite(z)
    if not ok.any():
        return np.full(z.shape, -np.inf)
    lo = float(z[ok].min())
    v = np.where(ok, z, lo)
    rise = float(z[ok].max()) - lo
    step_m = step_cells * posting_m
    n = int(np.ceil(rise / np.tan(el) / step_m)) if rise > 0 else 0
    rows, cols = np.mgrid[0 : z.shape[0], 0 : z.shape[1]].astype(np.float64)
    out = np.full(z.shape, -np.inf)
    dr, dc = -np.cos(az) * step_cells, np.sin(az) * step_cells
    for k in range(1, n + 1):
        s = map_coordinates(v, [rows + k * dr, cols + k * dc], order=1, mode="constant", cval=lo)
        np.maximum(out, s - k * step_m * np.tan(el), out=out)
    return out


def surface_dsm_sample(
    model: VolumeModel, camera: Any, depth_m: np.ndarray, maps: list[np.ndarray], grid: AOIGrid
) -> tuple[list[np.ndarray], np.ndarray]:
    """Each map on ``grid`` (the model's CRS) sampled at each pixel's median visible surface point.

    Returns
    -------
    samples : one float64 array (rows, cols) per map, NaN where the pixel has no surface point or the map none
    height_m : float64 (rows, cols), the surface point's ellipsoidal height (NaN where none)
    """
    fr = model.geometry.frame
    out = [np.full(depth_m.shape, np.nan) for _ in maps]
    height = np.full(depth_m.shape, np.nan)
    for rr, cc, o, d, t in _surface_rays(model, camera, depth_m):
        ok = np.isfinite(t)
        p = o + d * np.where(ok, t, 0.0)[:, None]
        lon, lat, h = fr.from_enu(p[:, 0], p[:, 1], p[:, 2])
        height[rr, cc] = np.where(ok, h, np.nan)
        for m, s in zip(maps, out):
            s[rr, cc] = np.where(ok, sample_grid(m, grid, lon, lat), np.nan)
    return out, height


def surface_dsm_sun_visibility(
    model: VolumeModel, camera: Any, depth_m: np.ndarray, shadow_heights_m: list[np.ndarray], grid: AOIGrid
) -> list[np.ndarray]:
    """1 (lit) or 0 (shadow) for each pixel's median visible surface point, lifted by half a finest cell,
    against each :func:`dsm_shadow_height` map (ellipsoidal metres on ``grid``); 1 where there is no point.
    The surface points are computed once for all the maps."""
    lift = 0.5 * model.geometry.finest_cell_m
    maps = [np.clip(h, -1e9, 1e9) for h in shadow_heights_m]  # ±inf (nothing reaches / sun below the horizon)
    hz, h = surface_dsm_sample(model, camera, depth_m, maps, grid)
    with np.errstate(invalid="ignore"):
        return [np.where(np.isfinite(h) & np.isfinite(z) & (h + lift < z), 0.0, 1.0) for z in hz]


def check_shadow_dsm(model: VolumeModel, shadow_dsm: tuple[np.ndarray, AOIGrid]) -> tuple[np.ndarray, AOIGrid]:
    """A (height_m, grid) pair for the relighting: ellipsoidal heights on a grid in the model's CRS."""
    try:
        dsm, grid = shadow_dsm
    except (TypeError, ValueError):
        raise ConfigError("shadow_dsm must be a (height_m array, AOIGrid) pair") from None
    model.geometry.check_crs(grid.crs, "the shadow DSM")
    dsm = np.asarray(dsm, dtype=np.float64)
    if dsm.shape != tuple(grid.shape):
        raise ConfigError(f"the shadow DSM has shape {dsm.shape} but its grid is {tuple(grid.shape)}")
    if not np.isfinite(dsm).any():
        raise ConfigError("the shadow DSM has no valid height; give a DSM that covers the model's AOI")
    return dsm, grid


def relight_mapping(
    model: VolumeModel,
    intensity: np.ndarray,
    camera: Any,
    b: int,
    sun_from: tuple[float, float],
    sun_to: tuple[float, float],
    *,
    vis_known: float = 0.2,
    shadow_dsm: tuple[np.ndarray, AOIGrid] | None = None,
    lit_scale: Callable[[np.ndarray], np.ndarray] | None = None,
    progress: Optional[Progress] = None,
) -> tuple[tuple[np.ndarray, np.ndarray, np.ndarray], dict]:
    """Per-pixel mixture map ``(a, b, σ_extra)`` for an image under ``sun_to`` against bin ``b`` (see module doc).

    ``shadow_dsm``: optional (height_m, grid) of the training epoch's surface (ellipsoidal metres, the
    model's CRS); the lit/shadow classes then come from its cast shadows instead of the model's density.
    ``lit_scale``: optional shading model, given the relight pass's median visible depth (rows, cols, m) it
    returns a multiplier (rows, cols) of the expected intensity of the lit → lit pixels, applied in the fit and
    the mapping (``b`` becomes ``b × scale``; NaN counts as 1). None of those measured is used by default
    (docs/volume.md, "Slope shading in the relighting").

    Returns
    -------
    mapping : three float64 arrays (rows, cols)
    info : dict with the suns, the class fits and the class fractions
    """
    from .render import render_image

    prog = ensure_progress(progress)
    rows, cols = intensity.shape
    base = render_image(model, camera, (rows, cols), app_bin=b, name="relight pass")
    prog(0.4, "sun visibility")
    if shadow_dsm is None:
        s_from = surface_sun_visibility(model, camera, base.depth_m, sun_from)
        s_to = surface_sun_visibility(model, camera, base.depth_m, sun_to)
    else:
        dsm, grid = check_shadow_dsm(model, shadow_dsm)
        s_from, s_to = surface_dsm_sun_visibility(
            model,
            camera,
            base.depth_m,
            [dsm_shadow_height(dsm, grid.posting_m, sun) for sun in (sun_from, sun_to)],
            grid,
        )
    prog(0.8, "fit")
    klass = (s_from < 0.5).astype(int) * 2 + (s_to < 0.5).astype(int)
    scale = np.ones((rows, cols))
    if lit_scale is not None:
        r = np.asarray(lit_scale(base.depth_m), dtype=np.float64)
        scale = np.where((klass == 0) & np.isfinite(r), r, 1.0)
    ok = np.isfinite(intensity) & np.isfinite(base.expected) & (base.vis_inf <= vis_known)
    fit = fit_classes(
        base.expected[ok].astype(np.float64),
        intensity[ok],
        klass[ok],
        lit_expected=None if lit_scale is None else (base.expected * scale)[ok].astype(np.float64),
    )
    extra = np.sqrt(np.maximum(fit.sigma**2 - fit.sigma[0] ** 2, 0.0))
    mapping = (fit.a[klass], fit.b[klass] * scale, extra[klass])
    frac = {c: float(np.mean(klass[ok] == i)) for i, c in enumerate(CLASSES)}
    info = {
        "from_sun": [float(sun_from[0]), float(sun_from[1])],
        "to_sun": [float(sun_to[0]), float(sun_to[1])],
        "shadows": "model density" if shadow_dsm is None else "DSM",
        "fit": fit.to_dict(),
        "class_fraction": frac,
    }
    prog(1.0, "relit")
    return mapping, info
