"""True orthorectification onto an AOI grid: arrays in, arrays out.

Every grid cell is placed at its DSM height, projected into the image through
the camera protocol (RPC and frame cameras alike, never a branch on the kind)
and sampled there. A cell the camera cannot see because the surface between
it and the camera is higher (a street behind a building, a wall facing away)
is marked occluded instead of receiving the occluder's pixel (true ortho; no
"ghost" buildings smeared over the ground). Visibility is decided by marching
up each cell's line of sight through the DSM (:func:`._kernels.occlusion_march`).

The line of sight comes from the protocol alone: at fixed image position, the
ground point moves with height by ``d(x, y)/dh = −J⁻¹ ∂(col, row)/∂h``, where
``J = ∂(col, row)/∂(x, y)`` at fixed height (finite differences of
``project``) and ``∂(col, row)/∂h`` is the camera's ``dproj_dh``.

The same function orthorectifies a float array given in image space (e.g. a
per-image class-probability map) and returns per-cell weights (view zenith,
incidence on the DSM surface, image pixels per cell) for whoever fuses views.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..camera import Camera
from ..errors import ConfigError, EmptyDataError, GridError
from ..geodesy import AOIGrid
from ..params import ParamsMixin
from ..stereo.sweep import grid_metres_per_unit
from . import _kernels as K

#: per-cell status codes of an orthoimage (uint8)
SEEN = 0
SEEN_FILLED_HEIGHT = 1
OCCLUDED = 2
OUTSIDE_IMAGE = 3
NO_HEIGHT = 4
#: short names of the status codes (JSON keys, band category labels)
STATUS_NAMES = {
    SEEN: "seen",
    SEEN_FILLED_HEIGHT: "seen_filled_height",
    OCCLUDED: "occluded",
    OUTSIDE_IMAGE: "outside_image",
    NO_HEIGHT: "no_height",
}
STATUS_LABELS = {
    SEEN: "seen",
    SEEN_FILLED_HEIGHT: "seen (height filled in a DSM hole)",
    OCCLUDED: "occluded (hidden from the camera)",
    OUTSIDE_IMAGE: "outside the image or image nodata",
    NO_HEIGHT: "no DSM height",
}
RESAMPLINGS = ("bilinear", "nearest")


@dataclass(frozen=True)
class OrthoParams(ParamsMixin):
    """How to orthorectify.

    Attributes
    ----------
    resampling : "bilinear" (images, probability maps) or "nearest" (class labels)
    antialias : bool
        With bilinear sampling, low-pass the image first when a grid cell spans 1.5
        image pixels or more (median over the grid): Gaussian of σ = ½·sqrt(r² − 1) px
        for r pixels per cell, so a fine image on a coarser grid does not alias.
    occlusion : bool
        Mark cells hidden from the camera by the DSM (true ortho). False gives a
        classic DSM ortho, where hidden cells receive the occluder's pixel.
    occlusion_tol_m : float or None
        How far (m) the DSM must rise above a line of sight to block it. None: from
        the DSM itself, ``max(0.5, 3 σ)`` with σ its local height noise (NMAD of the
        residual to a 3×3 median), so DSM noise does not hide cells; 0.5 m is a sixth
        of a storey, far below any wall that hides a street.
    step_cells : float
        Ray-march step (grid cells of horizontal distance).
    fill_value : float
        Value of unobserved cells in integer outputs (float outputs get NaN).
    """

    _kind = "ortho"

    resampling: str = "bilinear"
    antialias: bool = True
    occlusion: bool = True
    occlusion_tol_m: float | None = None
    step_cells: float = 0.5
    fill_value: float = 0.0

    def __post_init__(self) -> None:
        if self.resampling not in RESAMPLINGS:
            raise ConfigError(f"ortho resampling must be one of {RESAMPLINGS}, got {self.resampling!r}")
        if self.occlusion_tol_m is not None and not (self.occlusion_tol_m >= 0):
            raise ConfigError(f"occlusion_tol_m must be ≥ 0 m, got {self.occlusion_tol_m}")
        if not (0 < self.step_cells <= 2):
            raise ConfigError(f"step_cells must be in (0, 2], got {self.step_cells}")


@dataclass
class ViewGeometry:
    """Where each grid cell lands in an image, and how the camera looks at it.

    Attributes (all (rows, cols), NaN where the cell has no height or does not project)
    ----------
    col, row : float64, image coordinates of the cell at its DSM height (pixel-corner convention)
    ray_j, ray_i : float64, grid columns / rows per metre of height up the line of sight
    view_zenith_deg : float32, angle of the line of sight from the vertical
    view_azimuth_deg : float32, direction from the cell towards the camera, clockwise from grid north
    incidence_deg : float32, angle between the DSM surface normal and the line of sight
        (0 = seen face-on; ≥ 90 = back-facing)
    px_per_cell : float32, image pixels per grid cell side (sqrt of the area ratio)
    """

    col: np.ndarray
    row: np.ndarray
    ray_j: np.ndarray
    ray_i: np.ndarray
    view_zenith_deg: np.ndarray
    view_azimuth_deg: np.ndarray
    incidence_deg: np.ndarray
    px_per_cell: np.ndarray

    @property
    def weights(self) -> dict[str, np.ndarray]:
        """Per-cell weights for fusing views: the angles, the sampling, and ``cos_incidence`` (0 when back-facing)."""
        cos_inc = np.clip(np.cos(np.radians(self.incidence_deg.astype(np.float64))), 0.0, 1.0).astype(np.float32)
        return {
            "view_zenith_deg": self.view_zenith_deg,
            "view_azimuth_deg": self.view_azimuth_deg,
            "incidence_deg": self.incidence_deg,
            "px_per_cell": self.px_per_cell,
            "cos_incidence": cos_inc,
        }


@dataclass
class OrthoResult:
    """An orthorectified array on the AOI grid.

    Attributes
    ----------
    values : (bands, rows, cols), the input's dtype (integers rounded and clipped);
        NaN (floats) or ``params.fill_value`` (integers) where not observed
    observed : bool (rows, cols), the camera sees the cell and the image has data there
    status : uint8 (rows, cols), one of :data:`STATUS_LABELS`
    geometry : ViewGeometry
    occlusion_tol_m : float, the tolerance used
    notes : list of str
    """

    values: np.ndarray
    observed: np.ndarray
    status: np.ndarray
    geometry: ViewGeometry
    occlusion_tol_m: float = float("nan")
    notes: list[str] = field(default_factory=list)

    @property
    def occluded(self) -> np.ndarray:
        return self.status == OCCLUDED

    @property
    def weights(self) -> dict[str, np.ndarray]:
        return self.geometry.weights

    def fractions(self) -> dict[str, float]:
        """Share of the grid cells in each status."""
        n = self.status.size
        return {STATUS_NAMES[k]: round(float(np.count_nonzero(self.status == k)) / n, 5) for k in STATUS_NAMES}


# ---------------------------------------------------------------------------------------------
# geometry
# ---------------------------------------------------------------------------------------------
def view_geometry(camera: Camera, grid: AOIGrid, dsm_m: np.ndarray) -> ViewGeometry:
    """Project every cell at its DSM height and derive its line of sight (see the module docstring).

    Parameters
    ----------
    camera : any :class:`~geocd.camera.Camera`
    grid : AOIGrid (projected CRS)
    dsm_m : float (rows, cols), ellipsoidal metres, NaN = no height
    """
    dsm = np.asarray(dsm_m, np.float64)
    if dsm.shape != grid.shape:
        raise GridError(
            f"DSM shape {dsm.shape} does not match the grid {grid.shape}; resample it onto the grid "
            "(geocd.io.raster.read_dem(path, grid=grid))"
        )
    ok = np.isfinite(dsm)
    if not ok.any():
        raise EmptyDataError("the DSM has no valid height on the grid; give a DSM that covers the AOI")
    z = np.where(ok, dsm, float(np.median(dsm[ok])))
    x, y = grid.xy()
    px, py = grid.posting  # CRS units per cell
    dx, dy = 0.5 * px, 0.5 * py
    pr = camera.ground_projector(
        np.concatenate([x.ravel(), x.ravel() + dx, x.ravel()]),
        np.concatenate([y.ravel(), y.ravel(), y.ravel() - dy]),
        grid.crs,
    )
    zz = np.concatenate([z.ravel()] * 3)
    c, r = pr.project(zz)
    n = x.size
    dc_dh, dr_dh = camera.ground_projector(x.ravel(), y.ravel(), grid.crs).dproj_dh(z.ravel())
    c0, r0 = c[:n], r[:n]
    cj, rj = (c[n : 2 * n] - c0) / 0.5, (r[n : 2 * n] - r0) / 0.5  # per grid column (east)
    ci, ri = (c[2 * n :] - c0) / 0.5, (r[2 * n :] - r0) / 0.5  # per grid row (south)
    det = cj * ri - ci * rj
    with np.errstate(invalid="ignore", divide="ignore"):
        vj = -(ri * dc_dh - ci * dr_dh) / det
        vi = -(-rj * dc_dh + cj * dr_dh) / det
        px_per_cell = np.sqrt(np.abs(det))
    shape = grid.shape
    m_per_unit = grid_metres_per_unit(grid)
    east = vj * px * m_per_unit  # metres east per metre up the ray
    north = -vi * py * m_per_unit
    zen = np.degrees(np.arctan(np.hypot(east, north)))
    az = np.degrees(np.arctan2(east, north)) % 360.0
    # incidence on the DSM surface: normal (−∂z/∂e, −∂z/∂n, 1) against the ray (e, n, 1)
    with np.errstate(invalid="ignore"):
        gi, gj = np.gradient(dsm, py * m_per_unit, px * m_per_unit)  # ∂z/∂(row = −north), ∂z/∂(col = east)
        dz_de, dz_dn = gj, -gi
        e2, n2 = east.reshape(shape), north.reshape(shape)
        dot = -dz_de * e2 - dz_dn * n2 + 1.0
        inc = np.degrees(
            np.arccos(np.clip(dot / (np.sqrt(dz_de**2 + dz_dn**2 + 1.0) * np.sqrt(e2**2 + n2**2 + 1.0)), -1.0, 1.0))
        )
    bad = ~ok

    def f(a: np.ndarray, dtype=np.float64) -> np.ndarray:
        a = np.asarray(a, dtype).reshape(shape)
        a[bad] = np.nan
        return a

    return ViewGeometry(
        col=f(c0),
        row=f(r0),
        ray_j=f(vj),
        ray_i=f(vi),
        view_zenith_deg=f(zen, np.float32),
        view_azimuth_deg=f(az, np.float32),
        incidence_deg=f(inc, np.float32),
        px_per_cell=f(px_per_cell, np.float32),
    )


def dsm_noise_m(dsm_m: np.ndarray) -> float:
    """Local height noise of a DSM (m): NMAD of its residual to a 3×3 median (0 for an exact DSM)."""
    from scipy import ndimage

    d = np.asarray(dsm_m, np.float64)
    ok = np.isfinite(d)
    if ok.sum() < 9:
        return 0.0
    fill = np.where(ok, d, float(np.median(d[ok])))
    res = (d - ndimage.median_filter(fill, size=3, mode="nearest"))[ok]
    return float(1.4826 * np.median(np.abs(res - np.median(res))))


def occlusion_margin_cells(
    dsm_m: np.ndarray,
    geometry: ViewGeometry | None = None,
    max_view_zenith_deg: float | None = None,
    posting_m: float = 1.0,
) -> int:
    """Context (grid cells) a tile needs on each side for its occlusion test to see every occluder.

    ``(max − min DSM height) · tan(max view zenith) / posting``, rounded up: the
    farthest a line of sight can travel before it clears the highest surface.
    """
    d = np.asarray(dsm_m, np.float64)
    ok = np.isfinite(d)
    if not ok.any():
        return 0
    relief = float(d[ok].max() - d[ok].min())
    if geometry is not None:
        t = np.hypot(geometry.ray_j, geometry.ray_i)
        t = t[np.isfinite(t)]
        cells_per_m = float(t.max()) if t.size else 0.0
        return int(math.ceil(relief * cells_per_m)) + 1
    if max_view_zenith_deg is None:
        raise ConfigError("give the view geometry or the largest view zenith angle")
    return int(math.ceil(relief * math.tan(math.radians(max_view_zenith_deg)) / posting_m)) + 1


def fill_dsm_holes(
    dsm_m: np.ndarray, prior_m: np.ndarray | None = None, low_band_m: float = 1.0
) -> tuple[np.ndarray, np.ndarray]:
    """Fill NaN holes of a DSM for orthorectification → (filled, was_hole).

    Holes of a stereo DSM are mostly ground that one view could not see (beside
    buildings), so they are filled with the prior terrain DEM where given, else
    with the nearest *low* cell of the hole's rim: rim cells within ``low_band_m``
    of the rim's lower quartile. A hole between a roof and a street takes the
    street's height, never the roof's (no "ghost" roof on the ground).
    """
    from scipy import ndimage

    d = np.asarray(dsm_m, np.float64).copy()
    hole = ~np.isfinite(d)
    if not hole.any():
        return d, hole
    if prior_m is not None:
        p = np.asarray(prior_m, np.float64)
        if p.shape != d.shape:
            raise GridError(f"prior DEM shape {p.shape} does not match the DSM {d.shape}")
        d[hole] = p[hole]
    todo = ~np.isfinite(d)
    if not todo.any() or not np.isfinite(d).any():
        return d, hole
    lab, n = ndimage.label(todo, structure=np.ones((3, 3)))
    rim_of = ndimage.grey_dilation(lab, size=3) * np.isfinite(d)  # valid cells touching a hole, by label
    seed = np.zeros(d.shape, bool)
    for k, sl in enumerate(ndimage.find_objects(rim_of), start=1):
        if sl is None:
            continue
        sl = tuple(slice(max(s.start - 1, 0), s.stop + 1) for s in sl)
        rim = rim_of[sl] == k
        v = d[sl][rim]
        seed[sl] |= rim & (d[sl] <= np.percentile(v, 25) + low_band_m)
    if not seed.any():
        seed = np.isfinite(d)
    idx = ndimage.distance_transform_edt(~seed, return_distances=False, return_indices=True)
    d[todo] = d[idx[0][todo], idx[1][todo]]
    return d, hole


# ---------------------------------------------------------------------------------------------
# orthorectification
# ---------------------------------------------------------------------------------------------
def _gauss_nan(band: np.ndarray, ok: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian low-pass over the valid pixels only (normalized convolution); invalid pixels → 0."""
    from scipy import ndimage

    num = ndimage.gaussian_filter(np.where(ok, band, 0.0).astype(np.float64), sigma, mode="nearest")
    den = ndimage.gaussian_filter(ok.astype(np.float64), sigma, mode="nearest")
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(ok & (den > 0), num / den, 0.0)


def _as_bands(image: Any) -> np.ndarray:
    a = np.asarray(image)
    if a.dtype == bool:
        a = a.astype(np.uint8)
    if a.ndim == 2:
        a = a[None]
    if a.ndim != 3:
        raise ConfigError(f"image must be (rows, cols) or (bands, rows, cols), got shape {a.shape}")
    if not (np.issubdtype(a.dtype, np.integer) or np.issubdtype(a.dtype, np.floating)):
        raise ConfigError(f"image dtype {a.dtype} is not numeric")
    return a


def orthorectify(
    image: np.ndarray,
    camera: Camera,
    grid: AOIGrid,
    dsm_m: np.ndarray,
    *,
    valid: np.ndarray | None = None,
    col0: float = 0.0,
    row0: float = 0.0,
    params: OrthoParams = OrthoParams(),
    dsm_filled: np.ndarray | None = None,
    geometry: ViewGeometry | None = None,
) -> OrthoResult:
    """Orthorectify an image-space array onto an AOI grid with a DSM (true ortho).

    Parameters
    ----------
    image : (rows, cols) or (bands, rows, cols), any numeric dtype
        Pixels of the image (or a window of it), e.g. a multi-band image, or a
        float class-probability map computed in image space.
    camera : any :class:`~geocd.camera.Camera`
        The camera of the full image; ``image`` starts at pixel ``(col0, row0)`` of it
        (a pointing correction ``(dcol, drow)`` is applied by passing ``col0 − dcol``).
    grid : AOIGrid
    dsm_m : float (rows, cols) on ``grid``, ellipsoidal metres; NaN = no height
        (such cells are unobserved; see :func:`fill_dsm_holes`).
    valid : bool (rows, cols) of ``image``, optional; False = nodata. NaN in a
        float band is nodata too.
    dsm_filled : bool (rows, cols) on the grid, optional: cells whose height was
        filled in a hole (status :data:`SEEN_FILLED_HEIGHT` when seen).
    geometry : ViewGeometry, optional
        Reuse one from :func:`view_geometry` (same camera, grid and DSM) when
        orthorectifying several arrays of one image.

    Returns
    -------
    OrthoResult
    """
    img = _as_bands(image)
    B, H, W = img.shape
    if H == 0 or W == 0:
        raise EmptyDataError("the image is empty")
    dsm = np.asarray(dsm_m, np.float64)
    geo = geometry if geometry is not None else view_geometry(camera, grid, dsm)
    if geo.col.shape != grid.shape:
        raise GridError(f"view geometry shape {geo.col.shape} does not match the grid {grid.shape}")
    out_dtype = img.dtype
    work_dtype = np.float64 if img.dtype == np.float64 else np.float32
    work = np.ascontiguousarray(img, dtype=work_dtype)
    ok_px = np.ones((H, W), bool) if valid is None else np.asarray(valid, bool).copy()
    if ok_px.shape != (H, W):
        raise GridError(f"valid mask shape {ok_px.shape} does not match the image {(H, W)}")
    if np.issubdtype(img.dtype, np.floating):
        ok_px &= np.all(np.isfinite(work), axis=0)
    notes: list[str] = []
    mode = K.BILINEAR if params.resampling == "bilinear" else K.NEAREST
    if mode == K.BILINEAR and params.antialias:
        ppc = geo.px_per_cell[np.isfinite(geo.px_per_cell)]
        ratio = float(np.median(ppc)) if ppc.size else 1.0
        if ratio >= 1.5:
            sigma = 0.5 * math.sqrt(ratio * ratio - 1.0)
            work = np.stack([_gauss_nan(b, ok_px, sigma) for b in work]).astype(work_dtype)
            notes.append(f"image low-passed (Gaussian σ {sigma:.2f} px) before sampling: {ratio:.2f} image px per cell")
    col = np.ascontiguousarray(geo.col - float(col0))
    row = np.ascontiguousarray(geo.row - float(row0))
    vals = np.empty((B,) + grid.shape, work_dtype)
    ok = np.empty(grid.shape, bool)
    K.sample_image(work, np.ascontiguousarray(ok_px, np.uint8), col, row, mode, vals, ok)

    has_h = np.isfinite(dsm)
    status = np.full(grid.shape, OUTSIDE_IMAGE, np.uint8)
    status[ok] = SEEN
    if dsm_filled is not None:
        status[ok & np.asarray(dsm_filled, bool)] = SEEN_FILLED_HEIGHT
    tol = float("nan")
    if params.occlusion:
        tol = params.occlusion_tol_m if params.occlusion_tol_m is not None else max(0.5, 3.0 * dsm_noise_m(dsm))
        occ = np.empty(grid.shape, bool)
        K.occlusion_march(
            np.ascontiguousarray(np.where(has_h, dsm, np.nan)),
            np.ascontiguousarray(geo.ray_j),
            np.ascontiguousarray(geo.ray_i),
            float(tol),
            float(params.step_cells),
            occ,
        )
        status[occ & ok] = OCCLUDED
    status[~has_h] = NO_HEIGHT
    observed = status <= SEEN_FILLED_HEIGHT
    if np.issubdtype(out_dtype, np.integer):
        info = np.iinfo(out_dtype)
        if mode == K.BILINEAR:
            vals = np.rint(vals)
        vals = np.clip(vals, info.min, info.max)
        fill = np.clip(params.fill_value, info.min, info.max)
        values = np.where(observed[None], vals, fill).astype(out_dtype)
    else:
        values = np.where(observed[None], vals, np.nan).astype(out_dtype)
    return OrthoResult(values=values, observed=observed, status=status, geometry=geo, occlusion_tol_m=tol, notes=notes)
