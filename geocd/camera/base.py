"""The one camera protocol every geometric model in geocd implements.

Conventions (the same for every camera kind):

* **Ground** coordinates are geographic WGS84 longitude/latitude in degrees and
  **ellipsoidal** height in metres (EPSG:4979). Cameras whose native frame is
  something else (a frame camera's projected CRS with geoid heights) convert
  internally; callers never ask which kind of camera they hold.
* **Image** coordinates ``(col, row)`` are continuous pixel coordinates with
  ``(0, 0)`` at the *upper-left corner* of the upper-left pixel, so the centre of
  array element ``[i, j]`` is ``(j + 0.5, i + 0.5)``. This is GDAL's and
  rasterio's convention (pixel-is-area); an RPC's own origin is the centre of the
  first pixel, and :class:`~geocd.camera.rpc.RPCModel` adds 0.5 as GDAL does.
* ``dproj_dh`` is the derivative of ``(col, row)`` with respect to ellipsoidal
  height at fixed ``(lon, lat)`` (pixels per metre): the image motion of a point
  sliding up a vertical line. The stereo normalization factor is built from it.

For work on a map grid, :meth:`Camera.ground_projector` prepares a projector for
fixed ``(x, y)`` in any CRS once, so a height sweep only evaluates the camera.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any, ClassVar

import numpy as np

from ..errors import CameraError

ArrayLike = Any  # numpy array or scalar

_REGISTRY: dict[str, type["Camera"]] = {}


def register_camera(cls: type["Camera"]) -> type["Camera"]:
    """Class decorator: make a camera kind loadable by :func:`camera_from_dict`."""
    _REGISTRY[cls.kind] = cls
    return cls


def camera_from_dict(d: dict) -> "Camera":
    """Rebuild any registered camera from :meth:`Camera.to_dict` output."""
    kind = d.get("kind")
    if kind not in _REGISTRY:
        raise CameraError(
            f"unknown camera kind {kind!r} in camera description; known kinds: {sorted(_REGISTRY)}. "
            "Write the camera with geocd's own writer or fix its 'kind' field."
        )
    return _REGISTRY[kind].from_dict(d)


def _as_f64(*arrays: ArrayLike) -> tuple[np.ndarray, ...]:
    arrs = np.broadcast_arrays(*[np.asarray(a, dtype=np.float64) for a in arrays])
    # C-contiguous and writable (copies only broadcast or read-only inputs: numba compiles a separate
    # kernel specialization for read-only arrays); 0-d inputs stay 0-d (np.ascontiguousarray makes them (1,))
    return tuple(np.require(a, np.float64, ["C", "W"]) for a in arrs)


class Camera(ABC):
    """Ground (lon, lat, ellipsoidal h) ↔ image (col, row) for one image."""

    kind: ClassVar[str] = "abstract"

    #: image size in pixels (None when unknown, e.g. an RPC file without its image)
    width: int | None
    height: int | None

    # --- the protocol ---------------------------------------------------------
    @abstractmethod
    def project(self, lon: ArrayLike, lat: ArrayLike, h: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """Ground → image.

        Parameters
        ----------
        lon, lat : array_like, degrees (WGS84)
        h : array_like, metres above the WGS84 ellipsoid

        Returns
        -------
        col, row : ndarray, float64, broadcast shape of the inputs (pixels)
        """

    @abstractmethod
    def localize(self, col: ArrayLike, row: ArrayLike, h: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """Image + ellipsoidal height → ground ``(lon, lat)`` in degrees.

        Samples that cannot be localized (ray parallel to the height surface, no
        convergence) are NaN; they are never silently wrong.
        """

    @abstractmethod
    def dproj_dh(self, lon: ArrayLike, lat: ArrayLike, h: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """∂(col, row)/∂h at fixed (lon, lat), pixels per metre."""

    @abstractmethod
    def to_dict(self) -> dict:
        """JSON-serialisable description, with a ``kind`` key (see :func:`camera_from_dict`)."""

    @classmethod
    @abstractmethod
    def from_dict(cls, d: dict) -> "Camera":
        """Inverse of :meth:`to_dict`."""

    # --- pure-numpy paths for a few points (summaries): no kernel compile ----------------
    def project_reference(self, lon: ArrayLike, lat: ArrayLike, h: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`project` by a plain numpy path, for a few points (see :meth:`localize_reference`)."""
        return self.project(lon, lat, h)

    def localize_reference(self, col: ArrayLike, row: ArrayLike, h: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`localize` by a plain numpy path, for a few points where compiling the numba
        kernels would cost more than the work (``geocd info``'s footprint); default: :meth:`localize`."""
        return self.localize(col, row, h)

    def dproj_dh_reference(self, lon: ArrayLike, lat: ArrayLike, h: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`dproj_dh` by a plain numpy path (see :meth:`localize_reference`)."""
        return self.dproj_dh(lon, lat, h)

    def localize_summary(self, col: ArrayLike, row: ArrayLike, h: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`localize` for summaries: the numpy path first, the methods' localizer where it did not converge.

        The numpy path (:meth:`localize_reference`) needs no kernel compile; where it leaves a point
        NaN, :meth:`localize` (the localizer every method uses; it compiles its kernels then) decides,
        so a summary reaches every point the methods reach, with the same result (the two agree to
        ~1e-10 deg where both converge).
        """
        col, row, h = (np.asarray(a, dtype=np.float64) for a in np.broadcast_arrays(col, row, h))
        lon, lat = (np.array(a, dtype=np.float64) for a in self.localize_reference(col, row, h))
        bad = ~(np.isfinite(lon) & np.isfinite(lat)) & np.isfinite(col) & np.isfinite(row) & np.isfinite(h)
        if bad.any():
            lon[bad], lat[bad] = self.localize(col[bad], row[bad], h[bad])
        return lon, lat

    # --- derived helpers (shared by all kinds) ---------------------------------------
    def height_range(self) -> tuple[float, float] | None:
        """Ellipsoidal height range the model is valid for (None when unbounded)."""
        return None

    def in_image(self, col: ArrayLike, row: ArrayLike) -> np.ndarray:
        """Whether image points lie in the camera's valid image domain: finite (a point the
        model cannot project is NaN) and, when the size is known, inside ``[0, width] × [0, height]``."""
        col, row = _as_f64(col, row)
        ok = np.isfinite(col) & np.isfinite(row)
        if self.width is not None and self.height is not None:
            with np.errstate(invalid="ignore"):
                ok &= (col >= 0) & (row >= 0) & (col <= self.width) & (row <= self.height)
        return ok

    def image_corners(self) -> np.ndarray:
        """(4, 2) corner coordinates (col, row) of the image, clockwise from upper-left."""
        if self.width is None or self.height is None:
            raise CameraError(
                f"{self.kind} camera has no image size; open it through its image "
                "(geocd.io.load_camera(image_path)) so the size is known"
            )
        w, h = float(self.width), float(self.height)
        return np.array([[0.0, 0.0], [w, 0.0], [w, h], [0.0, h]])

    def footprint(self, h: float, densify: int = 8, *, reference: bool = False):
        """Ground footprint (shapely Polygon in lon/lat) of the image at height ``h``.

        ``reference``: localize by the numpy path (:meth:`localize_summary`: no kernel compile unless
        the numpy path misses a point the methods' localizer reaches).
        """
        from shapely.geometry import Polygon

        c = self.image_corners()
        pts = []
        for k in range(4):
            a, b = c[k], c[(k + 1) % 4]
            for t in np.linspace(0.0, 1.0, densify, endpoint=False):
                pts.append(a + t * (b - a))
        pts = np.array(pts)
        loc = self.localize_summary if reference else self.localize
        lon, lat = loc(pts[:, 0], pts[:, 1], np.full(len(pts), h))
        if not np.all(np.isfinite(lon)):
            raise CameraError(f"image corners of this {self.kind} camera do not reach height {h} m")
        return Polygon(np.column_stack([lon, lat]))

    def ground_projector(self, x: ArrayLike, y: ArrayLike, crs: Any = None) -> "GroundProjector":
        """Prepare projection of fixed map points ``(x, y)`` for many heights.

        Parameters
        ----------
        x, y : array_like
            Horizontal coordinates in ``crs`` (map order x, y; easting/northing
            or lon/lat), any shape.
        crs : anything pyproj.CRS accepts; None means EPSG:4326 lon/lat.
        """
        from ..geodesy import to_lonlat

        lon, lat = to_lonlat(x, y, crs)
        return GroundProjector(self, lon, lat)

    def __repr__(self) -> str:  # pragma: no cover - cosmetic
        size = f"{self.width}x{self.height}" if self.width else "size unknown"
        return f"<{type(self).__name__} {size}>"


class GroundProjector:
    """Projects a fixed set of ground points at varying ellipsoidal heights.

    Camera kinds may subclass this to cache work that does not depend on height
    (CRS transforms, geoid undulations).
    """

    def __init__(self, camera: Camera, lon: np.ndarray, lat: np.ndarray):
        self.camera = camera
        self.lon, self.lat = _as_f64(lon, lat)

    @property
    def shape(self) -> tuple[int, ...]:
        return self.lon.shape

    def project(self, h: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """(col, row) of the prepared points at height(s) ``h`` (scalar or same shape)."""
        h = np.broadcast_to(np.asarray(h, dtype=np.float64), self.lon.shape)
        return self.camera.project(self.lon, self.lat, h)

    def dproj_dh(self, h: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        h = np.broadcast_to(np.asarray(h, dtype=np.float64), self.lon.shape)
        return self.camera.dproj_dh(self.lon, self.lat, h)
