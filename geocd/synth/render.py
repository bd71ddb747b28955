"""Render images of a synthetic town through any geocd camera.

Pipeline for one view (:func:`render_view`):

1. **Rays.** Every pixel is integrated over its area with ``k × k`` stratified
   samples at ``(j + 0.5 + a, i + 0.5 + b)``, ``a, b ∈ {(m + 0.5)/k − 0.5}``
   (geocd's pixel convention: (0, 0) is the upper-left *corner*). Each sample's
   ray comes from the camera itself: the physical pushbroom model gives exact
   ENU rays (mapped to map space by the scene frame's polynomial, < 1e-6 m),
   a frame camera in the scene's CRS with ellipsoidal heights gives its rays
   directly, and any other camera is localized at the top and the bottom of
   the scene (the chord; curvature of a ray in map space over the scene's
   height band is < 1e-4 m).
2. **Ray casting** (:mod:`geocd.synth._kernels`): first hit on the terrain or
   the objects (real occlusions), Lambertian shading with cast shadows
   (a shadow ray per sample) and a sky term, procedural world-space albedo.
3. **Sensor** (:func:`to_sensor_counts`): mean over the samples (detector
   integration), Gaussian PSF (``psf_sigma_px``), gain/offset and haze,
   shot + read noise, quantization to ``nbits``.

:func:`trace_view` casts the same rays without shading (hit points), used by
the truth products (per-image change masks) and the geometric checks.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..camera.base import Camera
from ..errors import ConfigError
from ..progress import ensure_progress
from . import _kernels as K
from .scene import C_BUILDING, C_CAR, C_TREE, K_ELLIPSOID, K_POLY, Epoch, Town

#: bin size of the acceleration grid (metres)
GRID_BIN_M = 4.0


# ------------------------------------------------------------------------------------------
# packing a scene epoch for the kernels
# ------------------------------------------------------------------------------------------
def _box_planes(rect, z_lo: float, z_hi: float) -> list[list[float]]:
    u, v = rect.axes
    c = np.array([rect.cx, rect.cy])
    L, W = rect.half_len, rect.half_wid
    return [
        [u[0], u[1], 0.0, float(u @ c + L)],
        [-u[0], -u[1], 0.0, float(-u @ c + L)],
        [v[0], v[1], 0.0, float(v @ c + W)],
        [-v[0], -v[1], 0.0, float(-v @ c + W)],
        [0.0, 0.0, -1.0, -z_lo],
        [0.0, 0.0, 1.0, z_hi],
    ]


def _gable_planes(rect, z_lo: float, eave: float, top: float) -> list[list[float]]:
    pl = _box_planes(rect, z_lo, top)[:5]
    r, _, half_span = rect.ridge()
    w = np.array([-r[1], r[0]])  # across the ridge
    c = np.array([rect.cx, rect.cy])
    k = (top - eave) / half_span
    nrm = math.sqrt(k * k + 1.0)
    for s in (1.0, -1.0):
        n = np.array([s * k * w[0], s * k * w[1], 1.0])
        d = top + s * k * float(w @ c)
        pl.append([n[0] / nrm, n[1] / nrm, n[2] / nrm, d / nrm])
    return pl


def pack_scene(town: Town, epoch: Epoch | str) -> K.SceneArrays:
    """Flatten one epoch of ``town`` into the kernels' arrays (see :class:`_kernels.SceneArrays`)."""
    ep = town.epochs[epoch] if isinstance(epoch, str) else epoch
    T = town.terrain
    terr = np.ascontiguousarray(T.height_m, dtype=np.float64)
    terr_meta = np.array([T.x0, T.y0, T.step, float(terr.min()), float(terr.max())])
    kinds, clss, planes, npl, ell, rgb, rgb2, par, bbox = [], [], [], [], [], [], [], [], []

    def add(kind, cls, pl, e, c1, c2, p, bb):
        kinds.append(kind)
        clss.append(cls)
        P = np.zeros((8, 4))
        if pl:
            P[: len(pl)] = pl
        planes.append(P)
        npl.append(len(pl))
        ell.append(e if e is not None else [0.0] * 5)
        rgb.append(c1)
        rgb2.append(c2)
        par.append(p)
        bbox.append(bb)

    for b in ep.buildings:
        for part in b.parts:
            xs, ys = part.corners()[:, 0], part.corners()[:, 1]
            z_lo = float(town.terrain.at(xs, ys).min()) - 1.0
            z_lo = min(z_lo, b.ground_m - 1.0)
            if b.roof == "gabled":
                pl = _gable_planes(part, z_lo, b.eave_m, b.top_m)
                role = 1.0
            else:
                pl = _box_planes(part, z_lo, b.eave_m)
                role = 0.0
            add(
                K_POLY,
                C_BUILDING,
                pl,
                None,
                b.roof_rgb,
                b.wall_rgb,
                [b.ground_m, 3.0, role, 1000 + b.building_id],
                [xs.min(), ys.min(), z_lo, xs.max(), ys.max(), b.top_m],
            )
    for c in ep.cars:
        body = c.body
        u, _ = body.axes
        xs, ys = body.corners()[:, 0], body.corners()[:, 1]
        g = c.ground_m
        add(
            K_POLY,
            C_CAR,
            _box_planes(body, g - 0.3, g + 0.95),
            None,
            c.rgb,
            c.rgb,
            [g, 3.0, 2.0, 50000 + c.car_id],
            [xs.min(), ys.min(), g - 0.3, xs.max(), ys.max(), g + 0.95],
        )
        cab = type(body)(body.cx - 0.25 * u[0], body.cy - 0.25 * u[1], 1.15, 0.78, body.angle)
        add(
            K_POLY,
            C_CAR,
            _box_planes(cab, g + 0.5, g + c.height_m),
            None,
            c.rgb,
            c.rgb,
            [g, 3.0, 3.0, 50000 + c.car_id],
            [xs.min(), ys.min(), g + 0.5, xs.max(), ys.max(), g + c.height_m],
        )
    for t in ep.trees:
        e = [t.cx, t.cy, t.crown_cz, t.crown_r, t.crown_rz]
        add(
            K_ELLIPSOID,
            C_TREE,
            [],
            e,
            (t.tint, t.tint, t.tint),
            (0.0, 0.0, 0.0),
            [t.ground_m, 3.0, 4.0, 90000 + t.tree_id],
            [t.cx - t.crown_r, t.cy - t.crown_r, t.crown_cz - t.crown_rz, t.cx + t.crown_r, t.cy + t.crown_r, t.top_m],
        )
    n = len(kinds)
    if n == 0:  # a dummy object far below the terrain keeps the arrays non-empty
        add(K_POLY, C_BUILDING, [], None, (0, 0, 0), (0, 0, 0), [0, 3, 0, 0], [0, 0, -1e6, 0, 0, -1e6])
    bbox = np.array(bbox, dtype=np.float64)
    ex = town.extent
    gx0, gy0 = min(ex[0], bbox[:, 0].min()) - 1.0, min(ex[1], bbox[:, 1].min()) - 1.0
    gx1, gy1 = max(ex[2], bbox[:, 3].max()) + 1.0, max(ex[3], bbox[:, 4].max()) + 1.0
    gs = GRID_BIN_M
    gnx, gny = int(math.ceil((gx1 - gx0) / gs)), int(math.ceil((gy1 - gy0) / gs))
    cells: list[list[int]] = [[] for _ in range(gnx * gny)]
    for k, bb in enumerate(bbox):
        i0 = max(int(math.floor((bb[0] - gx0) / gs)), 0)
        i1 = min(int(math.floor((bb[3] - gx0) / gs)), gnx - 1)
        j0 = max(int(math.floor((bb[1] - gy0) / gs)), 0)
        j1 = min(int(math.floor((bb[4] - gy0) / gs)), gny - 1)
        for j in range(j0, j1 + 1):
            for i in range(i0, i1 + 1):
                cells[j * gnx + i].append(k)
    start = np.zeros(gnx * gny + 1, dtype=np.int64)
    start[1:] = np.cumsum([len(c) for c in cells])
    items = np.array([k for c in cells for k in c], dtype=np.int64)
    streets = np.array(
        [
            [
                s.x0,
                s.y0,
                (s.x1 - s.x0) / math.hypot(s.x1 - s.x0, s.y1 - s.y0),
                (s.y1 - s.y0) / math.hypot(s.x1 - s.x0, s.y1 - s.y0),
                math.hypot(s.x1 - s.x0, s.y1 - s.y0),
                s.half_width,
                s.sidewalk_m,
            ]
            for s in town.streets
        ],
        dtype=np.float64,
    ).reshape(-1, 7)
    patches = np.array(
        [[p.rect.cx, p.rect.cy, p.rect.half_len, p.rect.half_wid, p.rect.angle, p.material] for p in ep.patches],
        dtype=np.float64,
    ).reshape(-1, 6)
    colours = np.array(
        [
            ep.grass_rgb,
            ep.vegetation_rgb,
            (0.13, 0.13, 0.14),
            (0.36, 0.35, 0.33),
            (0.42, 0.34, 0.25),
            (0.80, 0.80, 0.78),
            (0.05, 0.06, 0.08),
            (0.16, 0.27, 0.09),
            (ep.vegetation_nir[0], ep.vegetation_nir[1], 0.0),
        ],
        dtype=np.float64,
    )
    zr = np.array([bbox[:, 2].min(), bbox[:, 5].max()])
    return K.SceneArrays(
        terr=terr,
        terr_meta=terr_meta,
        terr_block_max=K.terrain_block_max(terr),
        kind=np.array(kinds, np.int64),
        cls=np.array(clss, np.int64),
        planes=np.ascontiguousarray(np.array(planes, np.float64)),
        nplanes=np.array(npl, np.int64),
        ell=np.array(ell, np.float64),
        rgb=np.array(rgb, np.float64),
        rgb2=np.array(rgb2, np.float64),
        par=np.array(par, np.float64),
        grid_meta=np.array([gx0, gy0, gs, gnx, gny], np.float64),
        grid_start=start,
        grid_items=items if items.size else np.zeros(1, np.int64),
        zrange=zr,
        streets=streets,
        patches=patches,
        colours=colours,
    )


def scene_z_band(S: K.SceneArrays, margin_m: float = 2.0) -> tuple[float, float]:
    """(z_bottom, z_top) that brackets every surface of the packed scene."""
    lo = min(S.terr_meta[3], S.zrange[0]) - margin_m
    hi = max(S.terr_meta[4], S.zrange[1]) + margin_m
    return float(lo), float(hi)


# ------------------------------------------------------------------------------------------
# rays
# ------------------------------------------------------------------------------------------
def camera_rays(
    town: Town, camera: Camera, col: np.ndarray, row: np.ndarray, z_band: tuple[float, float]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rays of image points in map space, clipped to the scene's height band.

    Returns
    -------
    origin : (N, 3) point of the ray at the top of the band
    direction : (N, 3) unit vector (downwards)
    t_max : (N,) length of the ray inside the band (m)
    """
    col = np.asarray(col, float).ravel()
    row = np.asarray(row, float).ravel()
    z_bot, z_top = z_band
    fr = town.frame
    kind = getattr(camera, "kind", "")
    if hasattr(camera, "rays_enu"):
        o, d = camera.rays_enu(col, row)
        # the ENU vertical differs from the ellipsoidal height by millimetres over the scene: pad the band
        coef, scale, h0 = fr._poly
        A = np.empty((col.size, 3))
        D = np.empty((col.size, 3))
        L = np.empty(col.size)
        K.enu_rays_to_map(
            np.ascontiguousarray(o),
            np.ascontiguousarray(d),
            z_top + 1.0 - fr.h0,
            z_bot - 1.0 - fr.h0,
            np.ascontiguousarray(coef),
            float(scale[0]),
            h0,
            A,
            D,
            L,
        )
        return A, D, L
    elif (
        kind == "frame"
        and getattr(camera, "vertical_datum", None) == "ellipsoid"
        and camera.crs.equals(fr.crs, ignore_axis_order=True)
    ):
        d = camera.rays_world(col, row).T  # (N, 3) map-space directions, z-component < 0 looking down
        P = np.array(camera.position, float) - np.array([fr.e0, fr.n0, 0.0])
        with np.errstate(divide="ignore", invalid="ignore"):
            s_top = (z_top + 1.0 - P[2]) / d[:, 2]
            s_bot = (z_bot - 1.0 - P[2]) / d[:, 2]
        A = P + s_top[:, None] * d
        B = P + s_bot[:, None] * d
    else:
        lon_a, lat_a = camera.localize(col, row, np.full(col.shape, z_top + 1.0))
        lon_b, lat_b = camera.localize(col, row, np.full(col.shape, z_bot - 1.0))
        xa, ya = fr.from_lonlat(lon_a, lat_a)
        xb, yb = fr.from_lonlat(lon_b, lat_b)
        A = np.column_stack([xa, ya, np.full(col.shape, z_top + 1.0)])
        B = np.column_stack([xb, yb, np.full(col.shape, z_bot - 1.0)])
    D = B - A
    L = np.linalg.norm(D, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        D = D / L[:, None]
    bad = ~np.all(np.isfinite(D), axis=1) | ~np.all(np.isfinite(A), axis=1)
    A[bad] = 0.0
    D[bad] = (0.0, 0.0, -1.0)
    L[bad] = -1.0  # t_max < 0: no hit
    return np.ascontiguousarray(A), np.ascontiguousarray(D), np.ascontiguousarray(L)


def _sample_offsets(k: int) -> np.ndarray:
    return (np.arange(k) + 0.5) / k - 0.5


def sun_direction_map(town: Town, sun_enu: np.ndarray) -> np.ndarray:
    """The sun direction (ENU unit vector) expressed in map space (grid convergence, scale)."""
    fr = town.frame
    a = np.array(fr.enu_to_map(0.0, 0.0, 0.0), float).ravel()
    b = np.array(fr.enu_to_map(*(1000.0 * np.asarray(sun_enu, float))), float).ravel()
    d = b - a
    return d / np.linalg.norm(d)


# ------------------------------------------------------------------------------------------
# rendering
# ------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class RenderParams:
    """Sampling and lighting of :func:`render_view`.

    Attributes
    ----------
    supersample : int
        k: k × k samples per pixel (detector area integration).
    sun_irradiance, sky_irradiance : float
        Relative irradiance of the direct sun and of the sky (shadows receive only the sky).
    block_rows : int
        Rows rendered per kernel call (memory and progress granularity).
    """

    supersample: int = 2
    sun_irradiance: float = 1.0
    sky_irradiance: float = 0.25
    block_rows: int = 64

    def __post_init__(self) -> None:
        if not (1 <= self.supersample <= 8):
            raise ConfigError(f"supersample must be within 1..8, got {self.supersample}")


@dataclass
class RenderResult:
    """Radiance image (4, rows, cols) float32: R, G, B, near-infrared (linear, relative units)."""

    radiance: np.ndarray
    samples_per_pixel: int
    seconds: float = 0.0


def render_view(
    town: Town,
    epoch: str,
    camera: Camera,
    sun_enu: np.ndarray,
    params: RenderParams = RenderParams(),
    *,
    scene: K.SceneArrays | None = None,
    window: tuple[int, int, int, int] | None = None,
    progress: Callable | None = None,
) -> RenderResult:
    """Render the radiance an ideal sensor would integrate over each pixel of ``camera``.

    Parameters
    ----------
    town, epoch : the scene and the epoch name ("A", "B")
    camera : any geocd Camera with width/height
    sun_enu : (3,) unit vector towards the sun (East-North-Up)
    params : RenderParams
    scene : packed epoch (computed when not given)
    window : (row0, col0, rows, cols), optional sub-image

    Returns
    -------
    RenderResult with ``radiance`` of shape (4, rows, cols): R, G, B, NIR.
    """
    import time

    prog = ensure_progress(progress)
    S = scene if scene is not None else pack_scene(town, epoch)
    if window is None:
        if camera.width is None or camera.height is None:
            raise ConfigError("the camera has no image size; give width/height or a window")
        window = (0, 0, int(camera.height), int(camera.width))
    r0, c0, nr, nc = window
    k = params.supersample
    off = _sample_offsets(k)
    sun = np.ascontiguousarray(sun_direction_map(town, sun_enu))
    light = np.array([params.sun_irradiance, params.sky_irradiance])
    band = scene_z_band(S)
    out = np.zeros((4, nr, nc), dtype=np.float32)
    t_start = time.perf_counter()
    for b0 in range(0, nr, params.block_rows):
        b1 = min(nr, b0 + params.block_rows)
        rows = r0 + np.arange(b0, b1) + 0.5
        cols = c0 + np.arange(nc) + 0.5
        R = rows[:, None, None, None] + off[None, None, :, None]
        C = cols[None, :, None, None] + off[None, None, None, :]
        R, C = np.broadcast_arrays(R, C)
        o, d, tm = camera_rays(town, camera, C.ravel(), R.ravel(), band)
        rgb = np.empty((o.shape[0], 4))
        tt = np.empty(o.shape[0])
        ob = np.empty(o.shape[0], dtype=np.int64)
        K.render_rays(o, d, tm, sun, light, S, rgb, tt, ob)
        rgb = rgb.reshape(b1 - b0, nc, k * k, 4).mean(axis=2)
        out[:, b0:b1, :] = np.moveaxis(rgb, 2, 0)
        prog(b1 / nr, f"rendered rows {b1}/{nr}")
    return RenderResult(out, k * k, time.perf_counter() - t_start)


def trace_view(
    town: Town,
    camera: Camera,
    scene: K.SceneArrays,
    cols: np.ndarray,
    rows: np.ndarray,
    z_band: tuple[float, float] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """First hits (map-space points (N, 3), object index (N,)) of the rays through image points."""
    band = z_band or scene_z_band(scene)
    o, d, tm = camera_rays(town, camera, cols, rows, band)
    t = np.empty(o.shape[0])
    ob = np.empty(o.shape[0], dtype=np.int64)
    fc = np.empty(o.shape[0], dtype=np.int64)
    K.trace_first_hit(o, d, tm, scene, t, ob, fc)
    with np.errstate(invalid="ignore"):
        p = o + t[:, None] * d
    p[ob == -2] = np.nan
    return p, ob


def surface_height(
    scene: K.SceneArrays, x: np.ndarray, y: np.ndarray, return_object: bool = False
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Height of the first surface seen from straight above at map points (x, y): the DSM.

    With ``return_object`` also the object index hit (−1 = terrain).
    """
    x = np.asarray(x, float)
    shape = x.shape
    _, z_top = scene_z_band(scene)
    n = x.size
    o = np.column_stack([x.ravel(), np.asarray(y, float).ravel(), np.full(n, z_top)])
    d = np.tile([0.0, 0.0, -1.0], (n, 1))
    tm = np.full(n, 1e4)
    t = np.empty(n)
    ob = np.empty(n, dtype=np.int64)
    fc = np.empty(n, dtype=np.int64)
    K.trace_first_hit(np.ascontiguousarray(o), np.ascontiguousarray(d), tm, scene, t, ob, fc)
    z = (z_top - t).reshape(shape)
    if return_object:
        return z, ob.reshape(shape)
    return z


# ------------------------------------------------------------------------------------------
# sensor
# ------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class SensorRadiometry:
    """How radiance becomes counts.

    ``counts = gain * blur(radiance + haze) + dark``, then shot noise
    (variance ``counts / electrons_per_count``) and read noise, rounded and
    clipped to ``[0, 2**nbits - 1]``. For 8-bit RGB a display gamma is applied
    before quantization.
    """

    nbits: int = 11
    gain: float = 1500.0
    dark: float = 40.0
    haze: float = 0.02
    psf_sigma_px: float = 0.5
    electrons_per_count: float = 8.0
    read_noise: float = 2.0
    gamma: float = 1.0
    bands: str = "pan"  # pan | rgb

    def to_dict(self) -> dict:
        from dataclasses import asdict

        return asdict(self)


#: pan band as a mix of R, G, B, NIR (a broad 450–830 nm response, like Pléiades/WorldView pan)
PAN_WEIGHTS = np.array([0.22, 0.30, 0.13, 0.35])


def to_sensor_counts(radiance: np.ndarray, radiometry: SensorRadiometry, rng: np.random.Generator) -> np.ndarray:
    """Blur, noise and quantize a (4, rows, cols) radiance image (R, G, B, NIR).

    Returns uint16 (1, rows, cols) for ``bands="pan"`` or uint8/uint16 (3, rows, cols) for ``"rgb"``.
    """
    from scipy.ndimage import gaussian_filter

    r = radiometry
    if r.bands == "pan":
        img = np.tensordot(PAN_WEIGHTS, radiance.astype(np.float64), axes=1)[None]
    elif r.bands == "rgb":
        img = radiance[:3].astype(np.float64)
    else:
        raise ConfigError(f"bands must be 'pan' or 'rgb', got {r.bands!r}")
    if r.psf_sigma_px > 0:
        img = np.stack([gaussian_filter(b, r.psf_sigma_px, mode="nearest") for b in img])
    img = img + r.haze
    if r.gamma != 1.0:
        img = np.clip(img, 0, None) ** (1.0 / r.gamma)
    counts = r.gain * img + r.dark
    sigma = np.sqrt(np.clip(counts, 0, None) / r.electrons_per_count + r.read_noise**2)
    counts = counts + sigma * rng.standard_normal(counts.shape)
    top = 2**r.nbits - 1
    out = np.clip(np.rint(counts), 0, top)
    return out.astype(np.uint8 if r.nbits <= 8 else np.uint16)
