"""Any camera composed with an image-space affine correction (bias compensation).

Satellite RPCs without ground control are off by metres (Pléiades: ~8 m CE90), and
two dates are off independently. Grodecki & Dial (2003) showed that for a
pushbroom image of limited extent the whole error is absorbed by an affine map in
*image* space applied after the camera::

    u' = u + t + M (u − u0)

with ``u = base.project(ground)`` (col, row), ``t`` a shift (px), ``M`` a 2 × 2
linear part (px per px; zero for a pure shift) and ``u0`` the image point the
linear part is centred on. :class:`CorrectedCamera` wraps any camera of the
protocol (RPC, frame, ...) with such a map, so every method that takes a camera
sees the corrected geometry without knowing it was corrected.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np

from ..errors import CameraError
from .base import Camera, GroundProjector, _as_f64, camera_from_dict, register_camera


@register_camera
class CorrectedCamera(Camera):
    """``base`` followed by the image-space affine ``u' = u + t + M (u − u0)``.

    Parameters
    ----------
    base : Camera
        The camera being corrected (any kind).
    shift_px : (2,) array_like
        ``t`` = (Δcol, Δrow), pixels.
    linear : (2, 2) array_like, optional
        ``M`` (rows: col, row; columns: col, row), dimensionless; default zero.
    centre_px : (2,) array_like, optional
        ``u0`` (col, row); default the image centre (or the origin when the size is unknown).
    provenance : dict, optional
        How the correction was obtained (written with :meth:`to_dict`).
    """

    kind: ClassVar[str] = "corrected"

    def __init__(
        self,
        base: Camera,
        shift_px: Any = (0.0, 0.0),
        linear: Any = None,
        centre_px: Any = None,
        provenance: dict | None = None,
    ):
        if not isinstance(base, Camera):
            raise CameraError(f"a corrected camera needs a geocd camera to correct, got {type(base).__name__}")
        t = np.asarray(shift_px, dtype=np.float64).reshape(2)
        M = np.zeros((2, 2)) if linear is None else np.asarray(linear, dtype=np.float64).reshape(2, 2)
        if centre_px is None:
            centre_px = (0.5 * base.width, 0.5 * base.height) if base.width and base.height else (0.0, 0.0)
        u0 = np.asarray(centre_px, dtype=np.float64).reshape(2)
        if not (np.all(np.isfinite(t)) and np.all(np.isfinite(M)) and np.all(np.isfinite(u0))):
            raise CameraError("image-space correction holds NaN/inf; re-estimate it")
        if abs(np.linalg.det(np.eye(2) + M)) < 1e-6:
            raise CameraError("image-space correction is singular (I + M not invertible); re-estimate it")
        self.base = base
        self.shift_px = t
        self.linear = M
        self.centre_px = u0
        self.provenance = dict(provenance or {})
        self.width = base.width
        self.height = base.height
        self._inv = np.linalg.inv(np.eye(2) + M)

    # --- the map and its inverse --------------------------------------------------------------
    def _forward(self, c: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        (m00, m01), (m10, m11) = self.linear
        dc, dr = c - self.centre_px[0], r - self.centre_px[1]
        return c + self.shift_px[0] + m00 * dc + m01 * dr, r + self.shift_px[1] + m10 * dc + m11 * dr

    def _backward(self, c: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        (i00, i01), (i10, i11) = self._inv
        pc = c - self.shift_px[0] - self.centre_px[0]
        pr = r - self.shift_px[1] - self.centre_px[1]
        return self.centre_px[0] + i00 * pc + i01 * pr, self.centre_px[1] + i10 * pc + i11 * pr

    @property
    def sensor_kind(self) -> str:
        """The kind of the camera underneath (what pairing rules compare)."""
        return getattr(self.base, "sensor_kind", self.base.kind)

    @property
    def is_shift(self) -> bool:
        return not np.any(self.linear)

    # --- the protocol ---------------------------------------------------------------------------
    def project(self, lon, lat, h):
        c, r = self.base.project(lon, lat, h)
        return self._forward(c, r)

    def localize(self, col, row, h):
        col, row, h = _as_f64(col, row, h)
        c, r = self._backward(col, row)
        return self.base.localize(c, r, h)

    def dproj_dh(self, lon, lat, h):
        dc, dr = self.base.dproj_dh(lon, lat, h)
        (m00, m01), (m10, m11) = self.linear
        return dc + m00 * dc + m01 * dr, dr + m10 * dc + m11 * dr

    def height_range(self):
        return self.base.height_range()

    def ground_projector(self, x, y, crs=None) -> "CorrectedGroundProjector":
        return CorrectedGroundProjector(self, self.base.ground_projector(x, y, crs))

    # --- crops and RPC export (when the camera underneath has them) -----------------------------
    @property
    def cropped(self):
        """``cropped(col0, row0, width, height)``: the corrected camera of a crop (needs a croppable base)."""
        base_crop = getattr(self.base, "cropped")  # AttributeError when the base cannot be cropped

        def crop(col0: float, row0: float, width: int | None = None, height: int | None = None) -> "CorrectedCamera":
            return CorrectedCamera(
                base_crop(col0, row0, width, height),
                self.shift_px,
                self.linear,
                self.centre_px - np.array([col0, row0]),
                self.provenance,
            )

        return crop

    @property
    def to_rasterio(self):
        """RPC export: a pure shift folds exactly into an RPC's pixel offsets (an affine part does not)."""
        if not self.is_shift or not hasattr(self.base, "cropped") or not hasattr(self.base, "to_rasterio"):
            raise AttributeError("only a shift-corrected RPC camera can be written as RPC tags")
        folded = self.base.cropped(-self.shift_px[0], -self.shift_px[1], self.base.width, self.base.height)
        return folded.to_rasterio

    # --- serialisation -----------------------------------------------------------------------------
    def to_dict(self) -> dict:
        return {
            "kind": self.kind,
            "base": self.base.to_dict(),
            "shift_px": self.shift_px.tolist(),
            "linear": self.linear.tolist(),
            "centre_px": self.centre_px.tolist(),
            "provenance": self.provenance,
        }

    @classmethod
    def from_dict(cls, d: dict) -> "CorrectedCamera":
        if "base" not in d:
            raise CameraError("corrected camera description lacks 'base' (the camera it corrects)")
        return cls(
            camera_from_dict(d["base"]),
            d.get("shift_px", (0.0, 0.0)),
            d.get("linear"),
            d.get("centre_px"),
            d.get("provenance"),
        )

    def __repr__(self) -> str:  # pragma: no cover - cosmetic
        return (
            f"<CorrectedCamera of {self.base!r}: shift ({self.shift_px[0]:+.2f}, {self.shift_px[1]:+.2f}) px"
            f"{'' if self.is_shift else ', affine'}>"
        )


class CorrectedGroundProjector(GroundProjector):
    """The base camera's prepared projector followed by the image-space correction."""

    def __init__(self, camera: CorrectedCamera, base_projector: GroundProjector):
        self.camera = camera
        self.base_projector = base_projector
        self.lon, self.lat = base_projector.lon, base_projector.lat

    def project(self, h):
        c, r = self.base_projector.project(h)
        return self.camera._forward(c, r)

    def dproj_dh(self, h):
        dc, dr = self.base_projector.dproj_dh(h)
        (m00, m01), (m10, m11) = self.camera.linear
        return dc + m00 * dc + m01 * dr, dr + m10 * dc + m11 * dr
