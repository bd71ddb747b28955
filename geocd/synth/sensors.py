"""Simulated sensors: a physical pushbroom line scanner at orbital distance, and the sun.

Pushbroom model (:class:`PushbroomCamera`)
------------------------------------------
Everything is expressed in the exact local East-North-Up frame
(:class:`geocd.geodesy.LocalFrame`, via ECEF) at the scene centre:

* the platform moves on a straight line ``P(t) = P0 + V t`` (over the fraction
  of a second a small scene takes, the orbit arc departs from its chord by
  micrometres); it sits at ``altitude_m`` above the ellipsoid and ``V`` is
  horizontal at the platform with the orbit's heading;
* the attitude is constant during the scan: camera axes ``x`` (along the CCD
  line, across track), ``y`` (along track) and boresight ``z``; the scan plane at
  time ``t`` passes through ``P(t)`` and is spanned by ``x`` and ``z``;
* image row ``r`` is time ``t = (r - row0) * line_period_s``; image column
  ``c`` is the look angle ``tan = (c - col0) * ifov_rad`` along the CCD line.

Projection is closed-form (``t`` from the scan-plane condition, then the
column); localization intersects the pixel's ray with the ellipsoidal height
surface by Newton iterations. Earth rotation during the scan, aberration,
lens distortion and attitude jitter are not modelled (document them as such).

View angles follow the satellite convention: ``along_deg`` is the pitch (positive
= looking ahead along the velocity), ``across_deg`` the roll (positive = looking
to the right of the ground track), both measured at the platform from its
local nadir. The incidence angle at the ground is a few degrees larger
because of Earth curvature; both are recorded.
"""

from __future__ import annotations

import datetime as _dt
import math
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from ..camera.base import Camera, _as_f64, register_camera
from ..errors import CameraError, ConfigError
from ..geodesy import LocalFrame

GM_EARTH = 3.986004418e14  # m^3/s^2
R_EARTH = 6378137.0


# ------------------------------------------------------------------------------------------
# Sun
# ------------------------------------------------------------------------------------------
def sun_position(lon: float, lat: float, when_utc: _dt.datetime) -> tuple[float, float]:
    """Solar azimuth (degrees clockwise from north) and elevation (degrees) at a place and time.

    NOAA's solar-position equations (Spencer/Meeus low-precision form,
    accurate to about 0.1°), without atmospheric refraction.
    """
    if when_utc.tzinfo is not None:
        when_utc = when_utc.astimezone(_dt.timezone.utc).replace(tzinfo=None)
    doy = when_utc.timetuple().tm_yday
    hour = when_utc.hour + when_utc.minute / 60.0 + when_utc.second / 3600.0
    g = 2.0 * math.pi / 365.0 * (doy - 1 + (hour - 12.0) / 24.0)
    eqtime = 229.18 * (
        0.000075
        + 0.001868 * math.cos(g)
        - 0.032077 * math.sin(g)
        - 0.014615 * math.cos(2 * g)
        - 0.040849 * math.sin(2 * g)
    )
    decl = (
        0.006918
        - 0.399912 * math.cos(g)
        + 0.070257 * math.sin(g)
        - 0.006758 * math.cos(2 * g)
        + 0.000907 * math.sin(2 * g)
        - 0.002697 * math.cos(3 * g)
        + 0.00148 * math.sin(3 * g)
    )
    tst = hour * 60.0 + eqtime + 4.0 * lon  # true solar time, minutes
    ha = math.radians(tst / 4.0 - 180.0)
    phi = math.radians(lat)
    cos_zen = math.sin(phi) * math.sin(decl) + math.cos(phi) * math.cos(decl) * math.cos(ha)
    zen = math.acos(max(-1.0, min(1.0, cos_zen)))
    az = math.degrees(math.atan2(math.sin(ha), math.cos(ha) * math.sin(phi) - math.tan(decl) * math.cos(phi))) + 180.0
    return az % 360.0, 90.0 - math.degrees(zen)


def sun_direction_enu(azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    """Unit vector towards the sun in East-North-Up."""
    az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
    return np.array([math.sin(az) * math.cos(el), math.cos(az) * math.cos(el), math.sin(el)])


@dataclass(frozen=True)
class Sun:
    """Sun position for one epoch (degrees) and the time it was computed for."""

    azimuth_deg: float
    elevation_deg: float
    when_utc: str = ""

    def direction_enu(self) -> np.ndarray:
        return sun_direction_enu(self.azimuth_deg, self.elevation_deg)

    def to_dict(self) -> dict:
        return {"azimuth_deg": self.azimuth_deg, "elevation_deg": self.elevation_deg, "when_utc": self.when_utc}


# ------------------------------------------------------------------------------------------
# Pushbroom camera
# ------------------------------------------------------------------------------------------
def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


@register_camera
@dataclass(frozen=True, eq=False, repr=False)
class PushbroomCamera(Camera):
    """Physical pushbroom line scanner on a linear trajectory (see the module docstring).

    Parameters
    ----------
    lon0, lat0, h0 : float
        Origin of the ENU frame the model lives in (degrees, ellipsoidal metres).
    p0_enu, velocity_enu : (3,) float
        Platform position at t = 0 (m) and velocity (m/s), ENU.
    x_axis, y_axis, z_axis : (3,) float
        Orthonormal camera axes in ENU (CCD line, along track, boresight).
    ifov_rad : float
        Angular size of one detector (tangent units per column).
    line_period_s : float
        Time between two image lines.
    col0, row0 : float
        Column of the boresight, row of t = 0 (geocd pixel convention).
    width, height : int
        Image size in pixels.
    info : dict
        Descriptive metadata (angles, altitude, GSD), not used by the geometry.
    """

    lon0: float
    lat0: float
    h0: float
    p0_enu: np.ndarray
    velocity_enu: np.ndarray
    x_axis: np.ndarray
    y_axis: np.ndarray
    z_axis: np.ndarray
    ifov_rad: float
    line_period_s: float
    col0: float
    row0: float
    width: int | None = None
    height: int | None = None
    info: dict = field(default_factory=dict)

    kind: ClassVar[str] = "pushbroom"

    def __post_init__(self) -> None:
        for name in ("p0_enu", "velocity_enu", "x_axis", "y_axis", "z_axis"):
            v = np.asarray(getattr(self, name), dtype=np.float64).reshape(-1)
            if v.shape != (3,) or not np.all(np.isfinite(v)):
                raise CameraError(f"pushbroom camera {name} must be 3 finite numbers, got {getattr(self, name)!r}")
            object.__setattr__(self, name, v)
        R = np.stack([self.x_axis, self.y_axis, self.z_axis])
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-9):
            raise CameraError("pushbroom camera axes are not orthonormal; rebuild the camera with make_pushbroom()")
        if not (self.ifov_rad > 0 and self.line_period_s > 0):
            raise CameraError("pushbroom camera ifov_rad and line_period_s must be positive")
        if float(self.y_axis @ self.velocity_enu) <= 0:
            raise CameraError("pushbroom camera velocity does not cross the scan plane (y_axis · V ≤ 0)")

    @property
    def frame(self) -> LocalFrame:
        return LocalFrame(self.lon0, self.lat0, self.h0)

    # --- geometry in ENU ----------------------------------------------------------------
    def project_enu(self, e: np.ndarray, n: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """ENU points → (col, row), closed form."""
        X = np.stack([e, n, u], axis=-1) - self.p0_enu
        t = (X @ self.y_axis) / float(self.y_axis @ self.velocity_enu)
        q = X - t[..., None] * self.velocity_enu
        zq = q @ self.z_axis
        with np.errstate(divide="ignore", invalid="ignore"):
            col = self.col0 + (q @ self.x_axis) / zq / self.ifov_rad
        col = np.where(zq > 0, col, np.nan)
        row = self.row0 + t / self.line_period_s
        return col, row

    def rays_enu(self, col: np.ndarray, row: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixel rays: origin (…, 3) at the platform and unit direction (…, 3), ENU."""
        col, row = _as_f64(col, row)
        t = (row - self.row0) * self.line_period_s
        origin = self.p0_enu + t[..., None] * self.velocity_enu
        a = (col - self.col0) * self.ifov_rad
        d = self.z_axis + a[..., None] * self.x_axis
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        return origin, d

    # --- the camera protocol ---------------------------------------------------------
    def project(self, lon, lat, h):
        lon, lat, h = _as_f64(lon, lat, h)
        e, n, u = self.frame.to_enu(lon, lat, h)
        return self.project_enu(e, n, u)

    def localize(self, col, row, h):
        col, row, h = _as_f64(col, row, h)
        o, d = self.rays_enu(col, row)
        fr = self.frame
        # start: intersect with the tangent plane u = h - h0, then Newton on the geodetic height
        s = (h - self.h0 - o[..., 2]) / d[..., 2]
        for _ in range(6):
            p = o + s[..., None] * d
            _, _, hp = fr.from_enu(p[..., 0], p[..., 1], p[..., 2])
            s = s - (hp - h) / d[..., 2]
        p = o + s[..., None] * d
        lon, lat, _ = fr.from_enu(p[..., 0], p[..., 1], p[..., 2])
        bad = ~np.isfinite(s) | (s <= 0)
        lon = np.where(bad, np.nan, lon)
        lat = np.where(bad, np.nan, lat)
        return lon, lat

    def dproj_dh(self, lon, lat, h, step_m: float = 0.5):
        """Central difference over ±``step_m`` (the model is smooth: truncation error ≪ 1e-9 px/m)."""
        lon, lat, h = _as_f64(lon, lat, h)
        c1, r1 = self.project(lon, lat, h + step_m)
        c0, r0 = self.project(lon, lat, h - step_m)
        return (c1 - c0) / (2 * step_m), (r1 - r0) / (2 * step_m)

    def view_angles(self, lon: float, lat: float, h: float) -> dict:
        """Off-nadir (at the platform) and incidence/azimuth (at the ground point) of the view of a point."""
        fr = self.frame
        e, n, u = fr.to_enu(lon, lat, h)
        col, row = self.project_enu(np.atleast_1d(e), np.atleast_1d(n), np.atleast_1d(u))
        o, d = self.rays_enu(col, row)
        o, d = o[0], d[0]
        # local up at the platform and at the point, in this ENU frame
        lon_s, lat_s, h_s = fr.from_enu(o[0], o[1], o[2])
        up_s = _up_in_frame(fr, float(lon_s), float(lat_s))
        up_g = _up_in_frame(fr, lon, lat)
        off = math.degrees(math.acos(float(-d @ up_s)))
        inc = math.degrees(math.acos(float(-d @ up_g)))
        # azimuth of the direction from the ground towards the satellite, in the ground's ENU
        g_fr = LocalFrame(lon, lat, h)
        se, sn, su = g_fr.to_enu(float(lon_s), float(lat_s), float(h_s))
        az = math.degrees(math.atan2(float(se), float(sn))) % 360.0
        return {
            "off_nadir_deg": off,
            "incidence_deg": inc,
            "view_azimuth_deg": az,
            "satellite_height_m": float(h_s),
            "slant_range_m": float(np.linalg.norm(o - np.array([e, n, u]).ravel())),
        }

    # --- serialisation ----------------------------------------------------------------------
    def to_dict(self) -> dict:
        d: dict[str, Any] = {"kind": self.kind}
        for f in ("lon0", "lat0", "h0", "ifov_rad", "line_period_s", "col0", "row0", "width", "height"):
            d[f] = getattr(self, f)
        for f in ("p0_enu", "velocity_enu", "x_axis", "y_axis", "z_axis"):
            d[f] = getattr(self, f).tolist()
        d["info"] = dict(self.info)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "PushbroomCamera":
        keys = (
            "lon0",
            "lat0",
            "h0",
            "p0_enu",
            "velocity_enu",
            "x_axis",
            "y_axis",
            "z_axis",
            "ifov_rad",
            "line_period_s",
            "col0",
            "row0",
        )
        missing = [k for k in keys if k not in d]
        if missing:
            raise CameraError(f"pushbroom camera description lacks {missing}")
        return cls(**{k: d[k] for k in keys}, width=d.get("width"), height=d.get("height"), info=d.get("info", {}))

    def __repr__(self) -> str:  # pragma: no cover - cosmetic
        i = self.info
        return f"<PushbroomCamera {self.width}x{self.height} along={i.get('along_deg')} across={i.get('across_deg')}>"


def _up_in_frame(fr: LocalFrame, lon: float, lat: float) -> np.ndarray:
    """Geodetic normal at (lon, lat) expressed in the ENU axes of ``fr``."""
    lam, phi = math.radians(lon), math.radians(lat)
    up_ecef = np.array([math.cos(phi) * math.cos(lam), math.cos(phi) * math.sin(lam), math.sin(phi)])
    return fr._rot @ up_ecef


def make_pushbroom(
    lon0: float,
    lat0: float,
    h0: float,
    *,
    along_deg: float,
    across_deg: float,
    heading_deg: float = 192.0,
    altitude_m: float = 620e3,
    gsd_m: float = 0.5,
    cover_lonlath: np.ndarray | None = None,
    margin_px: int = 8,
    name: str = "",
) -> PushbroomCamera:
    """Build a pushbroom view of the point (lon0, lat0, h0).

    Parameters
    ----------
    along_deg, across_deg : float
        Pitch and roll off-nadir angles at the platform (degrees; see module doc).
    heading_deg : float
        Azimuth of the ground track (192° ≈ a descending sun-synchronous pass).
    altitude_m : float
        Platform altitude above the ellipsoid.
    gsd_m : float
        Ground sampling distance at (lon0, lat0, h0) in both directions (the
        detector angle and line period are chosen to give it, as for
        resampled Level-1 products).
    cover_lonlath : (N, 3) array, optional
        Ground points (lon, lat, h) the image must contain; sets the image size
        and the boresight position in it. Default: a 64-pixel square.
    margin_px : int
        Extra pixels around the covered points.
    """
    if not (0.0 <= abs(along_deg) < 60 and 0.0 <= abs(across_deg) < 60):
        raise ConfigError(f"off-nadir angles must be below 60°, got along={along_deg}, across={across_deg}")
    if not (gsd_m > 0 and altitude_m > 1e4):
        raise ConfigError(f"gsd_m must be positive and altitude_m orbital (> 10 km), got {gsd_m}, {altitude_m}")
    fr = LocalFrame(lon0, lat0, h0)
    heading = math.radians(heading_deg)
    track = np.array([math.sin(heading), math.cos(heading), 0.0])  # ENU at the scene
    ta, tc = math.tan(math.radians(along_deg)), math.tan(math.radians(across_deg))
    # iterate: direction defined in the platform's local frame; platform at the given altitude
    d = _unit(np.array([0.0, 0.0, -1.0]) + ta * track + tc * np.cross(track, [0.0, 0.0, 1.0]))
    S = -d * altitude_m
    for _ in range(30):
        lon_s, lat_s, _ = fr.from_enu(S[0], S[1], S[2])
        up = _up_in_frame(fr, float(lon_s), float(lat_s))
        along = _unit(track - (track @ up) * up)
        across = np.cross(along, up)
        d = _unit(-up + ta * along + tc * across)
        # slant range s so that the platform is at the altitude: solve h(S) = altitude by Newton
        s = float(np.linalg.norm(S))
        for _ in range(20):
            Sn = -d * s
            _, _, hs = fr.from_enu(Sn[0], Sn[1], Sn[2])
            ds = (float(hs) - altitude_m) / float(-d @ up)
            s -= ds
            if abs(ds) < 1e-6:
                break
        S_new = -d * s
        if np.linalg.norm(S_new - S) < 1e-6:
            S = S_new
            break
        S = S_new
    lon_s, lat_s, _ = fr.from_enu(S[0], S[1], S[2])
    up = _up_in_frame(fr, float(lon_s), float(lat_s))
    along = _unit(track - (track @ up) * up)
    r_orbit = R_EARTH + altitude_m
    v = math.sqrt(GM_EARTH / r_orbit)
    V = v * along
    z = d
    y = _unit(V - (V @ z) * z)
    x = np.cross(y, z)
    slant = float(np.linalg.norm(S))
    ifov = gsd_m / slant
    dt = gsd_m / v
    cam = PushbroomCamera(lon0, lat0, h0, S, V, x, y, z, ifov, dt, 0.0, 0.0, 64, 64)
    # rescale the detector angle and the line period so the ground sampling is gsd_m at the centre
    for _ in range(3):
        lon_a, lat_a = cam.localize(np.array([-0.5, 0.5, 0.0, 0.0]), np.array([0.0, 0.0, -0.5, 0.5]), np.full(4, h0))
        e, n, _u = fr.to_enu(lon_a, lat_a, np.full(4, h0))
        g_col = math.hypot(e[1] - e[0], n[1] - n[0])
        g_row = math.hypot(e[3] - e[2], n[3] - n[2])
        ifov *= gsd_m / g_col
        dt *= gsd_m / g_row
        cam = PushbroomCamera(lon0, lat0, h0, S, V, x, y, z, ifov, dt, 0.0, 0.0, 64, 64)
    if cover_lonlath is None:
        c0, r0, w, hgt = 32.0, 32.0, 64, 64
    else:
        pts = np.asarray(cover_lonlath, float)
        cc, rr = cam.project(pts[:, 0], pts[:, 1], pts[:, 2])
        if not (np.all(np.isfinite(cc)) and np.all(np.isfinite(rr))):
            raise ConfigError("some cover points are behind the sensor")
        cmin, cmax = math.floor(cc.min()) - margin_px, math.ceil(cc.max()) + margin_px
        rmin, rmax = math.floor(rr.min()) - margin_px, math.ceil(rr.max()) + margin_px
        c0, r0, w, hgt = -float(cmin), -float(rmin), int(cmax - cmin), int(rmax - rmin)
    info = {
        "name": name,
        "along_deg": along_deg,
        "across_deg": across_deg,
        "heading_deg": heading_deg,
        "altitude_m": altitude_m,
        "gsd_m": gsd_m,
        "orbit_speed_m_s": v,
    }
    cam = PushbroomCamera(lon0, lat0, h0, S, V, x, y, z, ifov, dt, c0, r0, w, hgt, info)
    ang = cam.view_angles(lon0, lat0, h0)
    info.update({k: round(v_, 6) for k, v_ in ang.items()})
    return cam
