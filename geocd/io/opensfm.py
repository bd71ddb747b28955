"""OpenSfM / OpenDroneMap ``reconstruction.json`` → geocd frame cameras.

OpenSfM (and ODM, which runs it) stores the oriented images of a reconstruction as::

    [ {"cameras": {id: {"projection_type": "perspective" | "brown" | ..., "width", "height",
                        "focal" | "focal_x", "focal_y", "c_x", "c_y", "k1", "k2", "k3", "p1", "p2"}},
       "shots": {image name: {"camera": id, "rotation": [rx, ry, rz], "translation": [tx, ty, tz], ...}},
       "reference_lla": {"latitude", "longitude", "altitude"} }, ... ]

Conventions (OpenSfM's): the world frame is **topocentric** (east, north, up in metres) at
``reference_lla`` (in the file, or in ``reference_lla.json`` beside it as ODM writes it);
a shot maps a world point ``X`` to camera coordinates ``R X + t`` with ``R`` the Rodrigues
rotation of ``rotation`` and OpenCV camera axes (x right, y down, z forward); normalized
image coordinates are pixels from the image centre divided by ``max(width, height)``, so
``focal`` (and ``c_x``, ``c_y``) are in units of the larger image side. ``perspective``
cameras have radial ``k1, k2``; ``brown`` cameras ``k1, k2, k3, p1, p2`` as OpenCV.
``fisheye``, ``spherical`` and other projections are refused (undistort the images first,
e.g. ODM's ``opensfm/undistorted``).

geocd frame cameras live in a projected CRS: by default a transverse Mercator centred on
the reference point (scale 1 there, :func:`local_tm_crs`), or the ``crs`` asked for. Each
camera's centre is converted exactly (topocentric → geographic → that CRS), its rotation
turned by the angle between the topocentric axes and the grid at the reference point. Like
every aerial-triangulation export geocd reads, the projected + height frame is then treated
as Cartesian (:mod:`geocd.camera.frame`): within a few km of the reference the local
transverse Mercator departs from the topocentric frame by millimetres (a UTM zone's scale
factor alone would cost up to 0.04 %, 4 cm at 100 m from the camera).
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from ..camera.frame import FrameCamera, rotation_to_opk
from ..errors import FrameCameraError, InputFileNotFoundError
from ..geodesy import as_crs, transformer

_CV_TO_PATB = np.diag([1.0, -1.0, -1.0])


def rodrigues(v: Any) -> np.ndarray:
    """Rotation matrix of an axis-angle vector (radians)."""
    v = np.asarray(v, float)
    a = float(np.linalg.norm(v))
    if a < 1e-15:
        return np.eye(3)
    k = v / a
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(a) * kx + (1.0 - math.cos(a)) * (kx @ kx)


def _enu_to_ecef(e, n, u, lon0, lat0, h0):
    """Topocentric (east, north, up) metres at (lon0, lat0, h0) → ECEF (WGS84)."""
    t = transformer("EPSG:4979", "EPSG:4978")
    x0, y0, z0 = t.transform(lon0, lat0, h0)
    lo, la = math.radians(lon0), math.radians(lat0)
    sl, cl, sp, cp = math.sin(lo), math.cos(lo), math.sin(la), math.cos(la)
    x = x0 - sl * e - sp * cl * n + cp * cl * u
    y = y0 + cl * e - sp * sl * n + cp * sl * u
    z = z0 + cp * n + sp * u
    return x, y, z


def topocentric_to(crs, e, n, u, reference: tuple[float, float, float]):
    """Topocentric points at ``reference`` (lon, lat, ellipsoidal h) → (x, y) in ``crs`` and ellipsoidal h."""
    x, y, z = _enu_to_ecef(np.asarray(e, float), np.asarray(n, float), np.asarray(u, float), *reference)
    lon, lat, h = transformer("EPSG:4978", "EPSG:4979").transform(x, y, z)
    gx, gy = transformer("EPSG:4326", crs).transform(lon, lat)
    return np.asarray(gx), np.asarray(gy), np.asarray(h)


def local_tm_crs(lon: float, lat: float):
    """A transverse Mercator CRS centred on (lon, lat) with scale 1 there (WGS84, metres).

    The frame in which a topocentric reconstruction is closest to Cartesian: within 5 km of
    the centre its scale differs from 1 by less than 3e-7 (UTM: up to 4e-4).
    """
    return as_crs(f"+proj=tmerc +lat_0={lat:.9f} +lon_0={lon:.9f} +k=1 +x_0=0 +y_0=0 +ellps=WGS84 +units=m +no_defs")


def _grid_rotation(crs, reference) -> np.ndarray:
    """3×3 rotation taking topocentric axes to the projected CRS's grid axes at the reference point."""
    x0, y0, _ = topocentric_to(crs, 0.0, 0.0, 0.0, reference)
    xe, ye, _ = topocentric_to(crs, 100.0, 0.0, 0.0, reference)
    a = math.atan2(float(ye - y0), float(xe - x0))  # direction of east on the grid
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def opensfm_camera_to_kw(cam: Mapping[str, Any], *, where: str) -> dict:
    """One OpenSfM camera → :class:`FrameCamera` interior keyword arguments."""
    ptype = str(cam.get("projection_type", "perspective")).lower()
    try:
        w, h = int(cam["width"]), int(cam["height"])
    except (KeyError, TypeError, ValueError) as exc:
        raise FrameCameraError(f"{where}: camera needs integer 'width' and 'height'") from exc
    size = max(w, h)
    if ptype == "perspective":
        f = float(cam["focal"]) * size
        return dict(
            width=w,
            height=h,
            focal_px=(f, f),
            principal_point_px=(w / 2.0, h / 2.0),
            distortion={"k1": float(cam.get("k1", 0.0)), "k2": float(cam.get("k2", 0.0))},
        )
    if ptype == "brown":
        fx = float(cam["focal_x"]) * size
        fy = float(cam.get("focal_y", cam["focal_x"])) * size
        pp = (w / 2.0 + float(cam.get("c_x", 0.0)) * size, h / 2.0 + float(cam.get("c_y", 0.0)) * size)
        dist = {k: float(cam.get(k, 0.0)) for k in ("k1", "k2", "k3", "p1", "p2")}
        return dict(width=w, height=h, focal_px=(fx, fy), principal_point_px=pp, distortion=dist)
    raise FrameCameraError(
        f"{where}: projection type {ptype!r} is not supported (geocd frame cameras are pinhole with Brown–Conrady "
        "distortion: OpenSfM 'perspective' and 'brown'); use the undistorted images and their reconstruction "
        "(ODM: opensfm/undistorted/reconstruction.json)"
    )


def _reference(doc: Mapping, path: Path, reference_lla: Any) -> tuple[float, float, float]:
    ref = reference_lla if reference_lla is not None else doc.get("reference_lla")
    if ref is None:
        side = path.with_name("reference_lla.json")
        if side.is_file():
            ref = json.loads(side.read_text(encoding="utf-8"))
    if ref is None:
        raise FrameCameraError(
            f"{path} has no 'reference_lla' and no reference_lla.json beside it: its coordinates are relative to "
            "an unknown point; pass reference_lla=(lon, lat, h) (--reference LON LAT H) or use ODM's "
            "opensfm folder, which holds reference_lla.json"
        )
    if isinstance(ref, Mapping):
        try:
            return float(ref["longitude"]), float(ref["latitude"]), float(ref.get("altitude", 0.0))
        except (KeyError, TypeError, ValueError) as exc:
            raise FrameCameraError(f"{path}: reference_lla needs latitude, longitude and altitude") from exc
    lon, lat, h = (float(v) for v in ref)
    return lon, lat, h


def read_opensfm_cameras(
    path: os.PathLike | str, *, crs: Any = None, reference_lla: Any = None, vertical_datum: str = "ellipsoid"
) -> dict[str, FrameCamera]:
    """An OpenSfM/ODM ``reconstruction.json`` → ``{image name: FrameCamera}``.

    Parameters
    ----------
    path : reconstruction.json (a list of reconstructions; every shot of every one is read)
    crs : projected CRS for the cameras (default: a transverse Mercator centred on the reference)
    reference_lla : (lon, lat, h) of the topocentric origin, when the file does not hold it
    vertical_datum : datum of the reference altitude: "ellipsoid" (default; OpenSfM's GPS
        altitudes), "egm96" or "egm2008" (then the cameras' z are in that datum)

    Raises
    ------
    InputFileNotFoundError, FrameCameraError
    """
    p = Path(path)
    if not p.is_file():
        raise InputFileNotFoundError(
            f"OpenSfM reconstruction {p} does not exist; check the path (ODM: <project>/opensfm/reconstruction.json)"
        )
    try:
        doc = json.loads(p.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise FrameCameraError(f"{p} is not JSON ({exc}); expected OpenSfM's reconstruction.json") from exc
    recs = doc if isinstance(doc, list) else [doc]
    if not recs or not all(isinstance(r, Mapping) and "shots" in r and "cameras" in r for r in recs):
        raise FrameCameraError(f"{p} is not an OpenSfM reconstruction: it needs 'cameras' and 'shots'")
    out: dict[str, FrameCamera] = {}
    for i, rec in enumerate(recs):
        ref = _reference(rec, p, reference_lla)
        use_crs = as_crs(crs) if crs is not None else local_tm_crs(ref[0], ref[1])
        g = _grid_rotation(use_crs, ref)
        intr = {cid: opensfm_camera_to_kw(c, where=f"{p} camera {cid!r}") for cid, c in rec["cameras"].items()}
        for name, shot in rec["shots"].items():
            cid = shot.get("camera")
            if cid not in intr:
                raise FrameCameraError(
                    f"{p}: shot {name!r} uses camera {cid!r}, which the reconstruction does "
                    f"not define (it has {sorted(intr)})"
                )
            r = rodrigues(shot.get("rotation", (0.0, 0.0, 0.0)))
            t = np.asarray(shot.get("translation", (0.0, 0.0, 0.0)), float)
            centre = -r.T @ t  # topocentric
            x, y, h = topocentric_to(use_crs, *centre, ref)
            z = float(h)  # in the datum of the reference altitude
            rot_patb = g @ r.T @ _CV_TO_PATB  # camera (PATB axes) → grid
            out[name] = FrameCamera(
                position=(float(x), float(y), z),
                opk_deg=rotation_to_opk(rot_patb),
                crs=use_crs,
                vertical_datum=vertical_datum,
                source=f"OpenSfM {p.name} reconstruction {i} shot {name}",
                **intr[cid],
            )
    return out
