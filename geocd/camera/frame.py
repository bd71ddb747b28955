"""Frame (pinhole) camera: aerial photos with interior and exterior orientation.

Model
-----
* **World frame.** The exterior orientation (EO) lives in a *projected* CRS in
  metres (easting ``x``, northing ``y``) plus a height ``z`` in a named vertical
  datum (``"ellipsoid"``, ``"egm96"`` or ``"egm2008"``). Like orthority, ngi and
  most aerial-triangulation outputs, geocd treats this ``(x, y, z)`` frame as
  **Cartesian**: no earth curvature and no map scale-factor correction. This is
  the frame the EO was adjusted in, so it is the right frame to use it in; the
  approximation error is a property of the EO itself (at 5 km flying height and
  3 km from nadir, curvature alone would move a point by ~0.7 m vertically).
* **Ground ↔ world.** :meth:`FrameCamera.project` takes the protocol's WGS84
  lon/lat/ellipsoidal height, maps lon/lat to ``(x, y)`` in the EO CRS and the
  height to the EO datum, ``z = h - N(lon, lat)`` with ``N`` the geoid
  undulation (0 for ``"ellipsoid"``), then projects.
* **Rotation** (orthority's / PATB convention). ``opk_deg`` = (omega, phi,
  kappa) in degrees rotates the camera frame to the world frame::

      R_opk = Rx(omega) @ Ry(phi) @ Rz(kappa)

  with the PATB camera axes x right, y up, z backwards (out of the lens, away
  from the scene). geocd uses OpenCV camera axes (x right, y down, z forward),
  so camera → world is ``R = R_opk @ diag(1, -1, -1)`` and a world point ``X``
  has camera coordinates ``Xc = R.T @ (X - position)``. A nadir camera with
  omega = phi = kappa = 0 has image columns along +x (east) and rows along −y
  (south): north is up in the image.
* **Interior orientation** (OpenCV convention). Focal length ``fx, fy`` and
  principal point ``cx, cy`` in pixels; Brown–Conrady distortion
  ``k1, k2, k3`` (radial) and ``p1, p2`` (tangential) applied to normalised image
  coordinates ``(x, y) = (Xc0 / Xc2, Xc1 / Xc2)`` exactly as OpenCV's
  ``projectPoints`` does (see :mod:`geocd.camera._frame_kernels`).
* **Pixels** follow the protocol (:mod:`geocd.camera.base`): ``(0, 0)`` is the
  upper-left *corner* of the image, so the image centre is
  ``(width / 2, height / 2)``. orthority's pixel centres are at integers: its
  ``(j, i)`` is geocd's ``(col - 0.5, row - 0.5)``; its principal point offsets
  ``cx, cy`` are in units of ``max(width, height)`` pixels from the centre.

Points behind the camera project to NaN; rays that do not reach a height
surface (pointing upwards) localize to NaN.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, ClassVar, Mapping

import numpy as np
from pyproj import CRS

from ..errors import CRSError, FrameCameraError
from ..geodesy import (
    EGM96,
    EGM2008,
    ELLIPSOID,
    as_crs,
    from_lonlat,
    geoid_undulation,
    horizontal_crs,
    normalize_datum_name,
    to_lonlat,
    transformer,
    vertical_datum_of,
)
from . import _frame_kernels as K
from .base import Camera, GroundProjector, _as_f64, register_camera

#: vertical datums a frame camera's z (and ground heights in its frame) may use
FRAME_VERTICAL_DATUMS = (ELLIPSOID, EGM96, EGM2008)

#: distortion coefficient names (OpenCV's 5-coefficient Brown–Conrady model)
DISTORTION_KEYS = ("k1", "k2", "k3", "p1", "p2")

#: PATB (x right, y up, z back) → OpenCV (x right, y down, z forward) camera axes
_PATB_TO_CV = np.diag([1.0, -1.0, -1.0])


def opk_to_rotation(opk_deg: Any) -> np.ndarray:
    """Camera(PATB) → world rotation ``Rx(omega) @ Ry(phi) @ Rz(kappa)``; angles in degrees."""
    o, p, k = (math.radians(float(a)) for a in opk_deg)
    rx = np.array([[1, 0, 0], [0, math.cos(o), -math.sin(o)], [0, math.sin(o), math.cos(o)]])
    ry = np.array([[math.cos(p), 0, math.sin(p)], [0, 1, 0], [-math.sin(p), 0, math.cos(p)]])
    rz = np.array([[math.cos(k), -math.sin(k), 0], [math.sin(k), math.cos(k), 0], [0, 0, 1]])
    return rx @ ry @ rz


def rotation_to_opk(r_patb: np.ndarray) -> tuple[float, float, float]:
    """Inverse of :func:`opk_to_rotation` (degrees; phi in [-90, 90])."""
    r = np.asarray(r_patb, float)
    omega = math.atan2(-r[1, 2], r[2, 2])
    phi = math.asin(max(-1.0, min(1.0, r[0, 2])))
    kappa = math.atan2(-r[0, 1], r[0, 0])
    return (math.degrees(omega), math.degrees(phi), math.degrees(kappa))


# ------------------------------------------------------------------------------------------
# validation helpers (messages name the field and the fix)
# ------------------------------------------------------------------------------------------
#: largest image side a frame camera may have (pixels): a 10⁶ px frame is far beyond any sensor
MAX_SIZE_PX = 10**6
#: largest magnitude of a frame camera's numbers (focal length, principal point, position, angles): positions
#: are metres in a projected or geocentric CRS (|x| < 10⁸ m), angles degrees
MAX_ABS_VALUE = 1e9


def _floats(value: Any, name: str, n: int, hint: str) -> tuple[float, ...]:
    try:
        arr = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError, OverflowError) as exc:
        raise FrameCameraError(
            f"frame camera field '{name}'={_short(value)} is not {n} finite numbers; {hint}"
        ) from exc
    if arr.size != n:
        raise FrameCameraError(f"frame camera field '{name}' has {arr.size} values, it needs {n}; {hint}")
    if not np.all(np.isfinite(arr)):
        raise FrameCameraError(f"frame camera field '{name}' contains NaN/inf ({_short(value)}); {hint}")
    if np.any(np.abs(arr) > MAX_ABS_VALUE):
        raise FrameCameraError(
            f"frame camera field '{name}'={_short(value)} is out of range (|value| > {MAX_ABS_VALUE:g}); {hint}"
        )
    return tuple(float(v) for v in arr)


def _pair(value: Any, name: str, hint: str) -> tuple[float, float]:
    """A scalar (→ both) or a pair of finite numbers."""
    try:
        n = np.asarray(value, dtype=np.float64).size
    except (TypeError, ValueError, OverflowError):
        n = 2  # let _floats name the problem
    if n == 1:
        v = _floats(value, name, 1, hint)[0]
        return (v, v)
    return _floats(value, name, 2, hint)  # type: ignore[return-value]


def _size(value: Any, name: str) -> int:
    try:
        v = int(value)
        ok = not isinstance(value, bool) and float(value) == v and 0 < v <= MAX_SIZE_PX
    except (TypeError, ValueError, OverflowError):
        ok = False
    if not ok:
        raise FrameCameraError(
            f"frame camera field '{name}'={_short(value)} must be a whole number of pixels in 1..{MAX_SIZE_PX}; "
            "give the size of the image the camera belongs to"
        )
    return v


def _short(value: Any, n: int = 60) -> str:
    s = repr(value)
    return s if len(s) <= n else s[: n - 3] + "..."


def _distortion(value: Any) -> tuple[float, float, float, float, float]:
    if value is None:
        return (0.0, 0.0, 0.0, 0.0, 0.0)
    if isinstance(value, Mapping):
        unknown = sorted(set(value) - set(DISTORTION_KEYS))
        if unknown:
            raise FrameCameraError(
                f"frame camera field 'distortion' has unsupported coefficients {unknown}; geocd supports the "
                f"Brown–Conrady model {list(DISTORTION_KEYS)} (OpenCV's first five); undistort the images "
                "or refit the camera with that model"
            )
        vals = [value.get(k, 0.0) for k in DISTORTION_KEYS]
        return _floats(vals, "distortion", 5, "give numbers for k1, k2, k3, p1, p2")  # type: ignore[return-value]
    raise FrameCameraError(
        f"frame camera field 'distortion'={value!r} must be a mapping like "
        "{k1: 0.0, k2: 0.0, k3: 0.0, p1: 0.0, p2: 0.0} (a bare list would be ambiguous: OpenCV orders it "
        "k1, k2, p1, p2, k3)"
    )


def _crs(value: Any) -> CRS:
    if value is None:
        raise FrameCameraError(
            "frame camera field 'crs' is missing: the exterior orientation needs the projected CRS its "
            "x, y are in (e.g. 'EPSG:32735' or WKT)"
        )
    try:
        c = as_crs(value)
    except CRSError as exc:
        raise FrameCameraError(f"frame camera field 'crs': {exc}") from exc
    h = horizontal_crs(c)
    if not h.is_projected:
        raise FrameCameraError(
            f"frame camera field 'crs' is {h.name!r}, which is not a projected CRS; frame cameras treat "
            "(x, y, z) as Cartesian metres, so give the exterior orientation in a projected CRS such as UTM"
        )
    unit = (h.axis_info[0].unit_name or "").lower() if h.axis_info else ""
    if unit not in ("metre", "meter", "m"):
        raise FrameCameraError(
            f"frame camera field 'crs' has axis unit {unit!r}; the exterior orientation must be in metres "
            "(reproject the camera positions to a metric CRS)"
        )
    return c


def _datum(value: Any, crs: CRS) -> str:
    if value is None:
        value = vertical_datum_of(crs) if crs.is_compound else None
    if value is None:
        raise FrameCameraError(
            "frame camera field 'vertical_datum' is missing: say which heights the camera z (and ground "
            f"heights in its frame) are in, one of {list(FRAME_VERTICAL_DATUMS)} (usually the datum of "
            "the DEM used in the aerial triangulation)"
        )
    d = normalize_datum_name(value)
    if d not in FRAME_VERTICAL_DATUMS:
        raise FrameCameraError(
            f"frame camera field 'vertical_datum'={value!r} is not supported; use one of "
            f"{list(FRAME_VERTICAL_DATUMS)} (convert the heights first if they are in another datum)"
        )
    return d


def _crs_to_text(c: CRS) -> str:
    code = c.to_epsg()
    if code is not None:
        return f"EPSG:{code}"
    return c.to_wkt()


# ------------------------------------------------------------------------------------------
# the camera
# ------------------------------------------------------------------------------------------
@register_camera
@dataclass(frozen=True, eq=False, repr=False)
class FrameCamera(Camera):
    """A pinhole camera with Brown–Conrady distortion and an exterior orientation.

    Parameters
    ----------
    width, height : int
        Image size in pixels.
    focal_px : float or (fx, fy)
        Focal length in pixels (``focal_mm / pixel_size_mm``); see :meth:`from_mm`.
    position : (x, y, z)
        Projection centre: easting, northing (m, in ``crs``) and height (m, in
        ``vertical_datum``).
    opk_deg : (omega, phi, kappa)
        Orientation angles in degrees, orthority/PATB convention (module doc).
    crs : any CRS pyproj accepts
        Projected CRS (metres) of the exterior orientation. A compound CRS also
        gives the vertical datum.
    vertical_datum : {"ellipsoid", "egm96", "egm2008"}, optional
        Datum of ``z``; required unless ``crs`` is compound.
    principal_point_px : (col, row), optional
        Principal point in geocd pixels (corner origin); default the image centre
        ``(width / 2, height / 2)``.
    distortion : mapping, optional
        ``{"k1", "k2", "k3", "p1", "p2"}`` (missing keys are 0), OpenCV convention.
    allow_geoid_substitute : bool
        With ``vertical_datum="egm2008"`` and no EGM2008 grid on the machine,
        use EGM96 instead (with a warning) rather than failing.
    source : str
        Provenance (file and format), for ``geocd info``.
    """

    width: int
    height: int
    focal_px: Any
    position: Any
    opk_deg: Any
    crs: Any
    vertical_datum: str | None = None
    principal_point_px: Any = None
    distortion: Any = None
    allow_geoid_substitute: bool = False
    source: str = ""
    _params: np.ndarray = field(init=False, repr=False)
    _rot: np.ndarray = field(init=False, repr=False)

    kind: ClassVar[str] = "frame"

    def __post_init__(self) -> None:
        s = object.__setattr__
        s(self, "width", _size(self.width, "width"))
        s(self, "height", _size(self.height, "height"))
        fx, fy = _pair(self.focal_px, "focal_px", "give the focal length in pixels (focal_mm / pixel_size_mm)")
        if fx <= 0 or fy <= 0:
            raise FrameCameraError(f"frame camera field 'focal_px'={self.focal_px!r} must be positive")
        s(self, "focal_px", (fx, fy))
        if self.principal_point_px is None:
            pp = (self.width / 2.0, self.height / 2.0)
        else:
            pp = _floats(
                self.principal_point_px,
                "principal_point_px",
                2,
                "give [col, row] in pixels from the image's upper-left corner",
            )
        s(self, "principal_point_px", pp)
        s(self, "distortion", dict(zip(DISTORTION_KEYS, _distortion(self.distortion))))
        s(self, "position", _floats(self.position, "position", 3, "give [x, y, z] in the camera CRS (metres)"))
        s(self, "opk_deg", _floats(self.opk_deg, "opk_deg", 3, "give [omega, phi, kappa] in degrees"))
        crs = _crs(self.crs)
        s(self, "vertical_datum", _datum(self.vertical_datum, crs))
        s(self, "crs", horizontal_crs(crs))
        s(self, "allow_geoid_substitute", bool(self.allow_geoid_substitute))
        s(self, "source", str(self.source or ""))
        rot = opk_to_rotation(self.opk_deg) @ _PATB_TO_CV  # OpenCV camera → world
        s(self, "_rot", rot)
        d = self.distortion
        params = np.concatenate(
            [
                [fx, fy, pp[0], pp[1], d["k1"], d["k2"], d["k3"], d["p1"], d["p2"]],
                self.position,
                rot.T.reshape(-1),
                [K.max_radius2(d["k1"], d["k2"], d["k3"])],
            ]
        ).astype(np.float64)
        s(self, "_params", np.ascontiguousarray(params))

    # --- constructors --------------------------------------------------------------------
    @classmethod
    def from_mm(
        cls,
        width: int,
        height: int,
        focal_mm: float,
        pixel_size_mm: Any,
        *,
        principal_point_mm: Any = (0.0, 0.0),
        **kw: Any,
    ) -> "FrameCamera":
        """Build from metric interior orientation.

        Parameters
        ----------
        focal_mm : float
            Focal length in millimetres.
        pixel_size_mm : float or (sx, sy)
            Pixel pitch in millimetres (columns, rows).
        principal_point_mm : (dx, dy)
            Principal point offset from the image centre in millimetres, along
            columns (right) and rows (down).
        **kw
            The other :class:`FrameCamera` fields (position, opk_deg, crs, ...).
        """
        sx, sy = _pair(pixel_size_mm, "pixel_size_mm", "give the pixel pitch in millimetres")
        if sx <= 0 or sy <= 0:
            raise FrameCameraError(f"frame camera field 'pixel_size_mm'={pixel_size_mm!r} must be positive")
        f = _floats(focal_mm, "focal_mm", 1, "give the focal length in millimetres")[0]
        dx, dy = _floats(
            principal_point_mm, "principal_point_mm", 2, "give [dx, dy] in mm from the image centre (right, down)"
        )
        w, h = _size(width, "width"), _size(height, "height")
        return cls(
            width=w,
            height=h,
            focal_px=(f / sx, f / sy),
            principal_point_px=(w / 2.0 + dx / sx, h / 2.0 + dy / sy),
            **kw,
        )

    def replace(self, **changes: Any) -> "FrameCamera":
        """A copy with some fields changed (validated again)."""
        d = {
            f: getattr(self, f)
            for f in (
                "width",
                "height",
                "focal_px",
                "position",
                "opk_deg",
                "crs",
                "vertical_datum",
                "principal_point_px",
                "distortion",
                "allow_geoid_substitute",
                "source",
            )
        }
        d.update(changes)
        return FrameCamera(**d)

    def cropped(self, col0: float, row0: float, width: int, height: int) -> "FrameCamera":
        """The camera of a crop whose upper-left corner is (col0, row0) of this image (exact)."""
        cx, cy = self.principal_point_px
        return self.replace(
            width=width,
            height=height,
            principal_point_px=(cx - col0, cy - row0),
            source=f"{self.source} cropped at col={col0:g} row={row0:g}".strip(),
        )

    def rescaled(self, width: int, height: int) -> "FrameCamera":
        """The camera of this image resampled to ``width`` x ``height`` pixels (exact)."""
        sx, sy = width / self.width, height / self.height
        cx, cy = self.principal_point_px
        fx, fy = self.focal_px
        return self.replace(
            width=width, height=height, focal_px=(fx * sx, fy * sy), principal_point_px=(cx * sx, cy * sy)
        )

    # --- geometry accessors ----------------------------------------------------------------
    @property
    def rotation(self) -> np.ndarray:
        """(3, 3) camera → world rotation, OpenCV camera axes (x right, y down, z forward)."""
        return self._rot.copy()

    @property
    def params(self) -> np.ndarray:
        """The packed kernel parameters (see :mod:`geocd.camera._frame_kernels`)."""
        return self._params.copy()

    @property
    def intrinsic_matrix(self) -> np.ndarray:
        """(3, 3) K, geocd pixel convention (corner origin)."""
        (fx, fy), (cx, cy) = self.focal_px, self.principal_point_px
        return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])

    @property
    def has_distortion(self) -> bool:
        return any(v != 0.0 for v in self.distortion.values())

    @property
    def max_field_angle_deg(self) -> float:
        """Largest angle off the optical axis inside the distortion model's valid domain (degrees; 90 when unbounded).

        Beyond it the radial polynomial folds back (see :mod:`geocd.camera._frame_kernels`):
        such points project to NaN instead of landing, wrongly, inside the image.
        """
        r2 = float(self._params[21])
        return math.degrees(math.atan(math.sqrt(r2))) if math.isfinite(r2) else 90.0

    def position_lonlat_h(self) -> tuple[float, float, float]:
        """Projection centre as WGS84 lon, lat (degrees) and ellipsoidal height (m)."""
        x, y, z = self.position
        lon, lat = to_lonlat(x, y, self.crs)
        h = z + float(self.undulation(lon, lat))
        return float(lon), float(lat), h

    def undulation(self, lon: Any, lat: Any) -> np.ndarray:
        """Geoid undulation N of the camera's vertical datum (h_ellipsoidal = z + N), metres."""
        lon = np.asarray(lon, float)
        lat = np.asarray(lat, float)
        if self.vertical_datum == ELLIPSOID:
            return np.zeros(np.broadcast(lon, lat).shape)
        ok = np.isfinite(lon) & np.isfinite(lat)
        if np.all(ok):
            return np.asarray(
                geoid_undulation(lon, lat, self.vertical_datum, allow_substitute=self.allow_geoid_substitute), float
            )
        lon, lat = np.broadcast_arrays(lon, lat)
        out = np.full(lon.shape, np.nan)
        if ok.any():
            out[ok] = geoid_undulation(
                lon[ok], lat[ok], self.vertical_datum, allow_substitute=self.allow_geoid_substitute
            )
        return out

    # --- world frame (projected x, y + height z in the camera datum) -------------------------
    def project_world(self, x: Any, y: Any, z: Any) -> tuple[np.ndarray, np.ndarray]:
        """World ``(x, y, z)`` (camera CRS, camera datum) → ``(col, row)``; NaN behind the camera."""
        x, y, z = _as_f64(x, y, z)
        col = np.empty(x.size)
        row = np.empty(x.size)
        K.frame_project(x.ravel(), y.ravel(), z.ravel(), self._params, col, row)
        return col.reshape(x.shape), row.reshape(x.shape)

    def dproj_dz_world(self, x: Any, y: Any, z: Any) -> tuple[np.ndarray, np.ndarray]:
        """∂(col, row)/∂z at fixed world ``(x, y)``, pixels per metre."""
        x, y, z = _as_f64(x, y, z)
        dc = np.empty(x.size)
        dr = np.empty(x.size)
        K.frame_dproj_dz(x.ravel(), y.ravel(), z.ravel(), self._params, dc, dr)
        return dc.reshape(x.shape), dr.reshape(x.shape)

    def undistort(self, col: Any, row: Any, *, tol: float = 1e-14, max_iter: int = 30) -> tuple[np.ndarray, np.ndarray]:
        """Pixels → undistorted normalised camera coordinates ``(x, y)`` (NaN if not invertible)."""
        col, row = _as_f64(col, row)
        xn = np.empty(col.size)
        yn = np.empty(col.size)
        K.frame_undistort(col.ravel(), row.ravel(), self._params, float(tol), int(max_iter), xn, yn)
        return xn.reshape(col.shape), yn.reshape(col.shape)

    def rays_world(self, col: Any, row: Any, *, reference: bool = False) -> np.ndarray:
        """Unit-free world directions ``(3, ...)`` of the rays through pixels (OpenCV z = 1 scaling).

        ``reference``: undistort with the numpy reference (no kernel compile; a few points).
        """
        if reference:
            col, row = _as_f64(col, row)
            xn, yn = K.undistort_ref(col, row, self._params, n_iter=200)
        else:
            xn, yn = self.undistort(col, row)
        return np.tensordot(self._rot, np.stack([xn, yn, np.ones_like(xn)]), axes=1)

    def localize_world(self, col: Any, row: Any, z: Any) -> tuple[np.ndarray, np.ndarray]:
        """Pixels + world height ``z`` (camera datum) → world ``(x, y)``; NaN where the ray misses."""
        col, row, z = _as_f64(col, row, z)
        d = self.rays_world(col, row)
        return self._intersect(d, z)

    def _intersect(self, d: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        tx, ty, tz = self.position
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (z - tz) / d[2]
        ok = np.isfinite(t) & (t > 0)
        x = np.where(ok, tx + t * d[0], np.nan)
        y = np.where(ok, ty + t * d[1], np.nan)
        return x, y

    # --- the camera protocol ------------------------------------------------------------------
    def project(self, lon, lat, h):
        lon, lat, h = _as_f64(lon, lat, h)
        x, y = from_lonlat(lon, lat, self.crs)
        z = h - self.undulation(lon, lat)
        return self.project_world(x, y, z)

    def dproj_dh(self, lon, lat, h):
        # z = h - N(lon, lat): at fixed (lon, lat), dz/dh = 1
        lon, lat, h = _as_f64(lon, lat, h)
        x, y = from_lonlat(lon, lat, self.crs)
        z = h - self.undulation(lon, lat)
        return self.dproj_dz_world(x, y, z)

    def localize_reference(self, col, row, h):
        return self.localize(col, row, h, reference=True)

    def dproj_dh_reference(self, lon, lat, h):
        lon, lat, h = _as_f64(lon, lat, h)
        x, y = from_lonlat(lon, lat, self.crs)
        return K.dproj_dz_ref(x, y, h - self.undulation(lon, lat), self._params)

    def localize(self, col, row, h, *, tol_m: float = 1e-5, max_iter: int = 10, reference: bool = False):
        """Pixels + ellipsoidal height → (lon, lat): the undistorted ray meets the height surface.

        The surface ``h`` (ellipsoidal) is ``z = h - N(lon, lat)`` in the camera
        frame; where the datum is a geoid, the undulation at the intersection is
        iterated (fixed point, stops when it changes by less than ``tol_m``;
        it varies by millimetres over an aerial footprint, so 2–3 passes).
        Rays that do not reach the surface (pointing upwards) give NaN.
        """
        col, row, h = _as_f64(col, row, h)
        d = self.rays_world(col, row, reference=reference)
        if self.vertical_datum == ELLIPSOID:
            x, y = self._intersect(d, h)
            return to_lonlat(x, y, self.crs)
        lon0, lat0 = to_lonlat(self.position[0], self.position[1], self.crs)
        n = np.full(col.shape, float(self.undulation(lon0, lat0)))
        for _ in range(max_iter):
            x, y = self._intersect(d, h - n)
            lon, lat = to_lonlat(x, y, self.crs)
            n_new = self.undulation(lon, lat)
            n_new = np.where(np.isfinite(n_new), n_new, n)
            delta = np.abs(n_new - n)
            n = n_new
            if not np.any(delta > tol_m):
                break
        x, y = self._intersect(d, h - n)
        return to_lonlat(x, y, self.crs)

    def ground_projector(self, x: Any, y: Any, crs: Any = None) -> "FrameGroundProjector":
        """Prepare fixed map points: one CRS transform and one geoid lookup for all heights."""
        return FrameGroundProjector(self, x, y, crs)

    # --- serialisation ---------------------------------------------------------------------------
    def to_dict(self) -> dict:
        """The geocd frame sidecar schema (see :mod:`geocd.io.frame`)."""
        fx, fy = self.focal_px
        d: dict[str, Any] = {
            "kind": self.kind,
            "crs": _crs_to_text(self.crs),
            "vertical_datum": self.vertical_datum,
            "width": self.width,
            "height": self.height,
            "focal_px": fx if fx == fy else [fx, fy],
            "principal_point_px": list(self.principal_point_px),
            "distortion": dict(self.distortion),
            "position": list(self.position),
            "opk_deg": list(self.opk_deg),
        }
        if self.allow_geoid_substitute:
            d["allow_geoid_substitute"] = True
        if self.source:
            d["source"] = self.source
        return d

    @classmethod
    def from_dict(cls, d: Mapping) -> "FrameCamera":
        """Inverse of :meth:`to_dict`; also accepts the metric variants of the sidecar schema.

        Accepted keys: ``kind`` ("frame"), ``crs``, ``vertical_datum``, ``width``,
        ``height``, ``focal_px`` *or* ``focal_mm`` + ``pixel_size_mm``,
        ``principal_point_px`` (alias ``principal_point``) *or*
        ``principal_point_mm`` (offset from the centre, needs ``pixel_size_mm``),
        ``distortion``, ``position``, ``opk_deg`` *or* ``opk_rad``,
        ``allow_geoid_substitute``, ``source``.
        """
        if not isinstance(d, Mapping):
            raise FrameCameraError(f"a frame camera description must be a mapping, got {type(d).__name__}")
        known = {
            "kind",
            "crs",
            "vertical_datum",
            "width",
            "height",
            "focal_px",
            "focal_mm",
            "pixel_size_mm",
            "principal_point_px",
            "principal_point",
            "principal_point_mm",
            "distortion",
            "position",
            "opk_deg",
            "opk_rad",
            "allow_geoid_substitute",
            "source",
        }
        unknown = sorted(set(d) - known)
        if unknown:
            raise FrameCameraError(
                f"frame camera description has unknown fields {unknown}; known fields are {sorted(known)} "
                "(check the spelling)"
            )
        kind = d.get("kind", "frame")
        if kind != "frame":
            raise FrameCameraError(f"frame camera field 'kind' is {kind!r}; a frame camera sidecar says kind: frame")
        for k in ("width", "height", "position", "crs"):
            if k not in d:
                raise FrameCameraError(
                    f"frame camera description lacks '{k}'; add it (see geocd.io.frame for the schema)"
                )
        if "opk_deg" in d and "opk_rad" in d:
            raise FrameCameraError("frame camera description has both 'opk_deg' and 'opk_rad'; keep one")
        if "opk_deg" in d:
            opk = d["opk_deg"]
        elif "opk_rad" in d:
            opk = [math.degrees(v) for v in _floats(d["opk_rad"], "opk_rad", 3, "give [omega, phi, kappa] in radians")]
        else:
            raise FrameCameraError("frame camera description lacks 'opk_deg'; give [omega, phi, kappa] in degrees")
        kw: dict[str, Any] = dict(
            position=d["position"],
            opk_deg=opk,
            crs=d["crs"],
            vertical_datum=d.get("vertical_datum"),
            distortion=d.get("distortion"),
            allow_geoid_substitute=bool(d.get("allow_geoid_substitute", False)),
            source=d.get("source", ""),
        )
        pp_px = d.get("principal_point_px", d.get("principal_point"))
        if "principal_point_px" in d and "principal_point" in d:
            raise FrameCameraError(
                "frame camera description has both 'principal_point_px' and 'principal_point'; keep one"
            )
        if "focal_px" in d:
            if "focal_mm" in d:
                raise FrameCameraError("frame camera description has both 'focal_px' and 'focal_mm'; keep one")
            if "principal_point_mm" in d:
                if "pixel_size_mm" not in d:
                    raise FrameCameraError(
                        "'principal_point_mm' needs 'pixel_size_mm'; add it or give principal_point_px"
                    )
                sx, sy = _pair(d["pixel_size_mm"], "pixel_size_mm", "give the pixel pitch in millimetres")
                dx, dy = _floats(d["principal_point_mm"], "principal_point_mm", 2, "give [dx, dy] in mm")
                w, h = _size(d["width"], "width"), _size(d["height"], "height")
                pp_px = (w / 2.0 + dx / sx, h / 2.0 + dy / sy)
            return cls(width=d["width"], height=d["height"], focal_px=d["focal_px"], principal_point_px=pp_px, **kw)
        if "focal_mm" in d:
            if "pixel_size_mm" not in d:
                raise FrameCameraError(
                    "frame camera description gives 'focal_mm' without 'pixel_size_mm'; add the pixel pitch in "
                    "millimetres (sensor width in mm / image width in pixels) or give 'focal_px'"
                )
            if pp_px is not None:
                if "principal_point_mm" in d:
                    raise FrameCameraError(
                        "give the principal point once: 'principal_point_px' or 'principal_point_mm'"
                    )
                cam = cls.from_mm(d["width"], d["height"], d["focal_mm"], d["pixel_size_mm"], **kw)
                return cam.replace(principal_point_px=pp_px)
            return cls.from_mm(
                d["width"],
                d["height"],
                d["focal_mm"],
                d["pixel_size_mm"],
                principal_point_mm=d.get("principal_point_mm", (0.0, 0.0)),
                **kw,
            )
        raise FrameCameraError(
            "frame camera description lacks the focal length; give 'focal_px' (pixels) or 'focal_mm' with "
            "'pixel_size_mm'"
        )

    def __repr__(self) -> str:  # pragma: no cover - cosmetic
        x, y, z = self.position
        o, p, k = self.opk_deg
        return (
            f"<FrameCamera {self.width}x{self.height} f={self.focal_px[0]:.2f}px "
            f"at ({x:.2f}, {y:.2f}, {z:.2f} {self.vertical_datum}) opk=({o:.3f}, {p:.3f}, {k:.3f})°"
            f"{' from ' + self.source if self.source else ''}>"
        )


class FrameGroundProjector(GroundProjector):
    """Fixed map points for a frame camera: CRS transform and geoid undulation done once.

    ``project(h)`` / ``dproj_dh(h)`` then cost only the pinhole kernel.
    """

    def __init__(self, camera: FrameCamera, x: Any, y: Any, crs: Any = None):
        x, y = _as_f64(x, y)
        src = as_crs(crs)
        lon, lat = to_lonlat(x, y, src)
        super().__init__(camera, lon, lat)
        if horizontal_crs(src).equals(camera.crs, ignore_axis_order=True):
            xw, yw = x, y
        else:
            xw, yw = transformer(src, camera.crs).transform(x, y)
        self._xw = np.ascontiguousarray(np.asarray(xw, float).ravel())
        self._yw = np.ascontiguousarray(np.asarray(yw, float).ravel())
        self._n = np.ascontiguousarray(camera.undulation(self.lon, self.lat).ravel())

    def _z(self, h: Any) -> np.ndarray:
        h = np.broadcast_to(np.asarray(h, dtype=np.float64), self.lon.shape).ravel()
        return np.ascontiguousarray(h - self._n)

    def project(self, h: Any) -> tuple[np.ndarray, np.ndarray]:
        col = np.empty(self._xw.size)
        row = np.empty(self._xw.size)
        K.frame_project(self._xw, self._yw, self._z(h), self.camera._params, col, row)
        return col.reshape(self.shape), row.reshape(self.shape)

    def dproj_dh(self, h: Any) -> tuple[np.ndarray, np.ndarray]:
        dc = np.empty(self._xw.size)
        dr = np.empty(self._xw.size)
        K.frame_dproj_dz(self._xw, self._yw, self._z(h), self.camera._params, dc, dr)
        return dc.reshape(self.shape), dr.reshape(self.shape)
