"""Rational polynomial camera (RPC00B).

One model for every vendor format: the readers in :mod:`geocd.io.rpc` all return
an :class:`RPCModel`. Coefficients are stored in RPC00B term order (GDAL,
GeoTIFF tags, DigitalGlobe, Pléiades, the table of Appendix A of the SRI paper):

    1, L, P, H, LP, LH, PH, L², P², H², PLH, L³, LP², LH², L²P, P³, PH², L²H, P²H, H³

with L, P, H the normalised longitude, latitude and ellipsoidal height.
RPC00A files (old NITF) are converted on read with :func:`rpc00a_to_rpc00b`.

Pixel convention: the RPC's own origin is the centre of the first pixel; geocd
(like GDAL's RPC transformer) reports ``col = samp + 0.5``, ``row = line + 0.5``
so that ``(0, 0)`` is the upper-left corner of the image (see
:mod:`geocd.camera.base`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from ..errors import LocalizationError, RPCParseError
from . import _kernels as K
from .base import Camera, register_camera

#: RPC00A index for each RPC00B term: ``b[k] = a[RPC00A_FROM_B[k]]``
#: RPC00A order: 1, L, P, H, LP, LH, PH, LPH, L², P², H², L³, L²P, L²H, LP², P³, P²H, LH², PH², H³
_A_ORDER = (
    "1",
    "L",
    "P",
    "H",
    "LP",
    "LH",
    "PH",
    "PLH",
    "LL",
    "PP",
    "HH",
    "LLL",
    "LLP",
    "LLH",
    "LPP",
    "PPP",
    "PPH",
    "LHH",
    "PHH",
    "HHH",
)
RPC00A_FROM_B = np.array([_A_ORDER.index(t) for t in K.TERMS_RPC00B])

#: GDAL adds this to the RPC's pixel coordinates (centre-of-first-pixel origin → corner origin)
PIXEL_SHIFT = 0.5

_NORM_FIELDS = (
    "line_off",
    "samp_off",
    "lat_off",
    "lon_off",
    "height_off",
    "line_scale",
    "samp_scale",
    "lat_scale",
    "lon_scale",
    "height_scale",
)


def _flat_f64(*arrays) -> tuple[tuple[int, ...], tuple[np.ndarray, ...]]:
    """Broadcast shape and contiguous, writable 1-D float64 views (copies only when needed).

    Writable too: numba compiles a separate specialization of a kernel for read-only
    arrays (broadcasts are read-only), and each costs a full compile on a cold cache.
    """
    arrs = [np.asarray(a, dtype=np.float64) for a in arrays]
    shape = np.broadcast_shapes(*(a.shape for a in arrs))
    return shape, tuple(np.require(np.broadcast_to(a, shape), np.float64, ["C", "W"]).reshape(-1) for a in arrs)


def rpc00a_to_rpc00b(coefs20: np.ndarray) -> np.ndarray:
    """Reorder a 20-coefficient polynomial from RPC00A to RPC00B term order."""
    c = np.asarray(coefs20, dtype=np.float64)
    if c.shape[-1] != 20:
        raise RPCParseError(f"an RPC polynomial has 20 coefficients, got {c.shape[-1]}")
    return c[..., RPC00A_FROM_B]


@register_camera
@dataclass(frozen=True, eq=False, repr=False)
class RPCModel(Camera):
    """An RPC00B rational-function camera (90 parameters).

    Parameters
    ----------
    line_num, line_den, samp_num, samp_den : (20,) float64
        Polynomial coefficients in RPC00B order.
    line_off, samp_off, lat_off, lon_off, height_off : float
        Offsets (pixels, degrees, metres).
    line_scale, samp_scale, lat_scale, lon_scale, height_scale : float
        Scales (same units). Must be non-zero.
    width, height : int, optional
        Image size in pixels when known.
    err_bias, err_rand : float, optional
        Vendor error estimates (metres), kept for reporting.
    source : str
        Where the model came from (file and format), for `geocd info` and provenance.
    """

    line_num: np.ndarray
    line_den: np.ndarray
    samp_num: np.ndarray
    samp_den: np.ndarray
    line_off: float
    samp_off: float
    lat_off: float
    lon_off: float
    height_off: float
    line_scale: float
    samp_scale: float
    lat_scale: float
    lon_scale: float
    height_scale: float
    width: int | None = None
    height: int | None = None
    err_bias: float | None = None
    err_rand: float | None = None
    source: str = ""
    _coefs: np.ndarray = field(init=False, repr=False)
    _norm: np.ndarray = field(init=False, repr=False)
    _norm_px: np.ndarray = field(init=False, repr=False)
    _init: np.ndarray = field(init=False, repr=False)
    _cubic_ready: bool = field(init=False, repr=False, default=False)

    kind: ClassVar[str] = "rpc"

    def __post_init__(self) -> None:
        coefs = []
        for name in ("line_num", "line_den", "samp_num", "samp_den"):
            try:
                c = np.asarray(getattr(self, name), dtype=np.float64).reshape(-1)
            except (TypeError, ValueError) as exc:
                raise RPCParseError(f"RPC {name} is not a list of numbers ({exc}); check the file") from exc
            if c.shape != (20,):
                raise RPCParseError(
                    f"RPC {name} has {c.size} coefficients, RPC00B needs 20; the file is truncated "
                    "or not an RPC00B model"
                )
            if not np.all(np.isfinite(c)):
                raise RPCParseError(f"RPC {name} contains NaN/inf; the RPC file is corrupt")
            object.__setattr__(self, name, c)
            coefs.append(c)
        norm = []
        for name in _NORM_FIELDS:
            v = getattr(self, name)
            try:
                v = float(v)
            except (TypeError, ValueError) as exc:
                raise RPCParseError(f"RPC {name}={v!r} is not a number; check the RPC file") from exc
            if not np.isfinite(v):
                raise RPCParseError(f"RPC {name} is {v}; the RPC file is corrupt")
            if name.endswith("_scale") and v == 0.0:
                raise RPCParseError(f"RPC {name} is 0 (division by zero); the RPC file is corrupt")
            object.__setattr__(self, name, v)
            norm.append(v)
        if not np.any(coefs[1]) or not np.any(coefs[3]):
            raise RPCParseError("an RPC denominator is identically zero; the RPC file is corrupt")
        object.__setattr__(self, "_coefs", np.ascontiguousarray(np.stack(coefs)))
        object.__setattr__(self, "_norm", np.asarray(norm, dtype=np.float64))
        norm_px = np.array(norm, dtype=np.float64)
        norm_px[:2] += PIXEL_SHIFT  # line_off, samp_off in GDAL's corner-origin convention
        object.__setattr__(self, "_norm_px", norm_px)
        object.__setattr__(self, "_init", self._affine_start())

    # --- construction helpers ---------------------------------------------------
    @classmethod
    def from_arrays(cls, coefs: np.ndarray, norm: np.ndarray, **kw: Any) -> "RPCModel":
        """From ``coefs[4, 20]`` (line_num, line_den, samp_num, samp_den) and ``norm[10]``."""
        c = np.asarray(coefs, float)
        kw.update(dict(zip(_NORM_FIELDS, map(float, norm))))
        return cls(line_num=c[0], line_den=c[1], samp_num=c[2], samp_den=c[3], **kw)

    def replace(self, **changes: Any) -> "RPCModel":
        d = {
            f: getattr(self, f)
            for f in (
                "line_num",
                "line_den",
                "samp_num",
                "samp_den",
                *_NORM_FIELDS,
                "width",
                "height",
                "err_bias",
                "err_rand",
                "source",
            )
        }
        d.update(changes)
        return RPCModel(**d)

    def cropped(self, col0: float, row0: float, width: int | None = None, height: int | None = None) -> "RPCModel":
        """The model of a crop whose upper-left pixel is (col0, row0) of this image.

        Exact: only the pixel offsets change (``samp_off - col0``, ``line_off - row0``).
        """
        return self.replace(
            samp_off=self.samp_off - col0,
            line_off=self.line_off - row0,
            width=width,
            height=height,
            source=f"{self.source} cropped at col={col0:g} row={row0:g}",
        )

    def _affine_start(self) -> np.ndarray:
        """Newton start vector (see :func:`_kernels.rpc_localize`), affine part only.

        Affine fit (sn, ln) ≈ a + A [L, P] + b H over the validity cube, inverted; the cubic
        slot holds the same affine map until :meth:`_fit_cubic_start` refines it.
        """
        g = np.linspace(-1.0, 1.0, 7)
        L, P, H = (a.ravel() for a in np.meshgrid(g, g, g, indexing="ij"))
        T = K.terms_ref(L, P, H)
        with np.errstate(all="ignore"):
            sn = (self._coefs[2] @ T) / (self._coefs[3] @ T)
            ln = (self._coefs[0] @ T) / (self._coefs[1] @ T)
        ok = np.isfinite(sn) & np.isfinite(ln) & (np.abs(sn) < 1e150) & (np.abs(ln) < 1e150)
        if ok.sum() < 4:
            raise RPCParseError("the RPC has no finite image coordinates over its validity box; the file is corrupt")
        X = np.column_stack([np.ones(ok.sum()), L[ok], P[ok], H[ok]])
        try:
            with np.errstate(all="ignore"):
                cs, *_ = np.linalg.lstsq(X, sn[ok], rcond=None)
                cl, *_ = np.linalg.lstsq(X, ln[ok], rcond=None)
            A = np.array([[cs[1], cs[2]], [cl[1], cl[2]]])
            M = np.linalg.inv(A)
        except np.linalg.LinAlgError as exc:
            raise RPCParseError(
                "the RPC does not map ground to image one-to-one (singular affine part); the file is corrupt"
            ) from exc
        init = np.zeros(K.INIT_SIZE)
        init[K.INIT_AFFINE] = [M[0, 0], M[0, 1], M[1, 0], M[1, 1], cs[0], cl[0], cs[3], cl[3]]
        if not np.all(np.isfinite(init[K.INIT_AFFINE])):
            raise RPCParseError("the RPC's affine part is not finite; the file is corrupt")
        # the cubic start's box: the image box [-1, 1]² and the image of the validity cube
        with np.errstate(all="ignore"):
            s0, s1 = min(-1.0, np.percentile(sn[ok], 0.0)), max(1.0, np.percentile(sn[ok], 100.0))
            l0, l1 = min(-1.0, np.percentile(ln[ok], 0.0)), max(1.0, np.percentile(ln[ok], 100.0))
        s0, s1, l0, l1 = (float(np.clip(v, -1e6, 1e6)) for v in (s0, s1, l0, l1))
        init[K.INIT_BOX] = [(s0 + s1) / 2, (s1 - s0) / 2, (l0 + l1) / 2, (l1 - l0) / 2]
        # until _fit_cubic_start runs, the cubic slots hold the same affine map:
        # L = c0 + c1 u + c2 v + c3 H with sn = cu + hu u, ln = cv + hv v
        a0, a1, b0, b1 = cs[0], cl[0], cs[3], cl[3]
        for base, (cu, hu, cv, hv) in ((8, (0.0, 1.0, 0.0, 1.0)), (48, tuple(init[K.INIT_BOX]))):
            for row, (m0, m1) in ((base, (M[0, 0], M[0, 1])), (base + 20, (M[1, 0], M[1, 1]))):
                init[row : row + 4] = [m0 * (cu - a0) + m1 * (cv - a1), m0 * hu, m1 * hv, -m0 * b0 - m1 * b1]
        return init

    def _fit_cubic_start(self) -> None:
        """Refine the Newton starts: cubic (L, P) = f(sn, ln, H) fitted on exact image-space grids.

        Two fits: over the image box (|sn|, |ln| <= 1) and over the image of the validity
        cube (which is larger for RPCs of crops). Done once, on the first localization, not at
        construction (reading a file stays cheap).
        """
        init = self._init.copy()
        for base, (cu, hu, cv, hv) in ((8, (0.0, 1.0, 0.0, 1.0)), (48, tuple(self._init[K.INIT_BOX]))):
            g = np.linspace(-1.0, 1.0, 13)
            u, v, H = (a.ravel() for a in np.meshgrid(g, g, np.linspace(-1.0, 1.0, 5), indexing="ij"))
            st, lt = cu + hu * u, cv + hv * v
            n = st.size
            lon = np.empty(n)
            lat = np.empty(n)
            its = np.empty(n, dtype=np.int32)
            K.rpc_localize(
                st * self.samp_scale + self.samp_off,
                lt * self.line_scale + self.line_off,
                H * self.height_scale + self.height_off,
                self._coefs,
                self._norm,
                self._init,
                1e-10,
                60,
                lon,
                lat,
                its,
            )
            ok = its >= 0
            if ok.sum() < 60:
                continue  # keep the affine start there
            X = K.terms_ref(u[ok], v[ok], H[ok]).T
            Lt = (lon[ok] - self.lon_off) / self.lon_scale
            Pt = (lat[ok] - self.lat_off) / self.lat_scale
            try:
                cL, *_ = np.linalg.lstsq(X, Lt, rcond=None)
                cP, *_ = np.linalg.lstsq(X, Pt, rcond=None)
            except np.linalg.LinAlgError:
                continue
            if np.all(np.isfinite(cL)) and np.all(np.isfinite(cP)):
                init[base : base + 20] = cL
                init[base + 20 : base + 40] = cP
        object.__setattr__(self, "_init", init)
        object.__setattr__(self, "_cubic_ready", True)

    # --- the camera protocol ---------------------------------------------------------
    def project(self, lon, lat, h):
        shape, (lon, lat, h) = _flat_f64(lon, lat, h)
        col = np.empty(lon.size)
        row = np.empty(lon.size)
        # _norm_px: offsets + 0.5, so the kernel writes GDAL's corner-origin pixels directly
        K.rpc_project(lon, lat, h, self._coefs, self._norm_px, col, row)
        return col.reshape(shape), row.reshape(shape)

    def dproj_dh(self, lon, lat, h):
        shape, (lon, lat, h) = _flat_f64(lon, lat, h)
        ds = np.empty(lon.size)
        dl = np.empty(lon.size)
        K.rpc_dproj_dh(lon, lat, h, self._coefs, self._norm, ds, dl)
        return ds.reshape(shape), dl.reshape(shape)

    def localize(
        self,
        col,
        row,
        h,
        *,
        tol_px: float = 1e-9,
        max_iter: int = 60,
        return_iterations: bool = False,
        strict: bool = False,
    ):
        """Image + height → (lon, lat) by damped Newton (see :func:`_kernels.rpc_localize`).

        Parameters
        ----------
        tol_px : float
            Convergence tolerance on the image residual, pixels.
        return_iterations : bool
            Also return the per-sample iteration count (−1 = not converged).
        strict : bool
            Raise :class:`LocalizationError` if any finite sample did not converge
            (default: such samples are NaN).
        """
        shape, (col, row, h) = _flat_f64(col, row, h)
        lon = np.empty(col.size)
        lat = np.empty(col.size)
        its = np.empty(col.size, dtype=np.int32)
        if not self._cubic_ready:
            self._fit_cubic_start()
        K.rpc_localize(col, row, h, self._coefs, self._norm_px, self._init, float(tol_px), int(max_iter), lon, lat, its)
        if strict:
            bad = (its < 0) & np.isfinite(col) & np.isfinite(row) & np.isfinite(h)
            if bad.any():
                raise LocalizationError(
                    f"RPC localization did not converge for {int(bad.sum())} of {bad.size} samples "
                    "(points far outside the RPC's validity box?); restrict the points to the image and "
                    "the RPC height range"
                )
        out = (lon.reshape(shape), lat.reshape(shape))
        return (*out, its.reshape(shape)) if return_iterations else out

    def project_reference(self, lon, lat, h):
        """:meth:`project` in numpy (:func:`_kernels.project_ref`; no compile), few points."""
        shape, (lon, lat, h) = _flat_f64(lon, lat, h)
        col, row = K.project_ref(lon, lat, h, self._coefs, self._norm_px)
        return col.reshape(shape), row.reshape(shape)

    def localize_reference(self, col, row, h):
        """:meth:`localize` by damped Newton in numpy from the kernels' affine start
        (:func:`_kernels.localize_ref`; no compile), few points."""
        shape, (col, row, h) = _flat_f64(col, row, h)
        lon, lat = K.localize_ref(col, row, h, self._coefs, self._norm_px, init=self._init)
        return lon.reshape(shape), lat.reshape(shape)

    def dproj_dh_reference(self, lon, lat, h):
        shape, (lon, lat, h) = _flat_f64(lon, lat, h)
        ds, dl = K.dproj_dh_ref(lon, lat, h, self._coefs, self._norm)
        return ds.reshape(shape), dl.reshape(shape)

    def height_range(self) -> tuple[float, float]:
        return (self.height_off - abs(self.height_scale), self.height_off + abs(self.height_scale))

    def validity_box(self) -> dict[str, tuple[float, float]]:
        """The normalised cube [-1, 1]³ in ground units: lon, lat (deg), h (m)."""
        return {
            "lon": (self.lon_off - abs(self.lon_scale), self.lon_off + abs(self.lon_scale)),
            "lat": (self.lat_off - abs(self.lat_scale), self.lat_off + abs(self.lat_scale)),
            "h": self.height_range(),
        }

    def image_corners(self) -> np.ndarray:
        if self.width is None or self.height is None:
            # fall back on the RPC's own image box (offset ± scale)
            c0 = max(self.samp_off - abs(self.samp_scale), 0.0) + PIXEL_SHIFT - 0.5
            r0 = max(self.line_off - abs(self.line_scale), 0.0) + PIXEL_SHIFT - 0.5
            c1 = self.samp_off + abs(self.samp_scale) + PIXEL_SHIFT
            r1 = self.line_off + abs(self.line_scale) + PIXEL_SHIFT
            return np.array([[c0, r0], [c1, r0], [c1, r1], [c0, r1]])
        return super().image_corners()

    # --- serialisation ------------------------------------------------------------------
    def to_dict(self) -> dict:
        d: dict[str, Any] = {"kind": self.kind}
        for f in ("line_num", "line_den", "samp_num", "samp_den"):
            d[f] = getattr(self, f).tolist()
        for f in _NORM_FIELDS:
            d[f] = getattr(self, f)
        for f in ("width", "height", "err_bias", "err_rand", "source"):
            if getattr(self, f) not in (None, ""):
                d[f] = getattr(self, f)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "RPCModel":
        keys = ("line_num", "line_den", "samp_num", "samp_den", *_NORM_FIELDS)
        missing = [k for k in keys if k not in d]
        if missing:
            raise RPCParseError(f"RPC description lacks {missing}; it must hold all 90 RPC parameters")
        kw = {k: d[k] for k in keys}
        for k in ("width", "height", "err_bias", "err_rand", "source"):
            if k in d:
                kw[k] = d[k]
        return cls(**kw)

    def to_gdal_metadata(self) -> dict[str, str]:
        """The GDAL ``RPC`` metadata domain (what GeoTIFF/NITF RPC tags hold)."""
        md = {
            "LINE_OFF": repr(self.line_off),
            "SAMP_OFF": repr(self.samp_off),
            "LAT_OFF": repr(self.lat_off),
            "LONG_OFF": repr(self.lon_off),
            "HEIGHT_OFF": repr(self.height_off),
            "LINE_SCALE": repr(self.line_scale),
            "SAMP_SCALE": repr(self.samp_scale),
            "LAT_SCALE": repr(self.lat_scale),
            "LONG_SCALE": repr(self.lon_scale),
            "HEIGHT_SCALE": repr(self.height_scale),
            "LINE_NUM_COEFF": " ".join(repr(float(v)) for v in self.line_num),
            "LINE_DEN_COEFF": " ".join(repr(float(v)) for v in self.line_den),
            "SAMP_NUM_COEFF": " ".join(repr(float(v)) for v in self.samp_num),
            "SAMP_DEN_COEFF": " ".join(repr(float(v)) for v in self.samp_den),
        }
        box = self.validity_box()
        md.update(
            {
                "MIN_LONG": repr(box["lon"][0]),
                "MAX_LONG": repr(box["lon"][1]),
                "MIN_LAT": repr(box["lat"][0]),
                "MAX_LAT": repr(box["lat"][1]),
            }
        )
        if self.err_bias is not None:
            md["ERR_BIAS"] = repr(float(self.err_bias))
        if self.err_rand is not None:
            md["ERR_RAND"] = repr(float(self.err_rand))
        return md

    def to_rasterio(self):
        """A :class:`rasterio.rpc.RPC` (for writing GeoTIFF RPC tags or GDAL's transformer)."""
        from rasterio.rpc import RPC

        return RPC(
            height_off=self.height_off,
            height_scale=self.height_scale,
            lat_off=self.lat_off,
            lat_scale=self.lat_scale,
            line_den_coeff=self.line_den.tolist(),
            line_num_coeff=self.line_num.tolist(),
            line_off=self.line_off,
            line_scale=self.line_scale,
            long_off=self.lon_off,
            long_scale=self.lon_scale,
            samp_den_coeff=self.samp_den.tolist(),
            samp_num_coeff=self.samp_num.tolist(),
            samp_off=self.samp_off,
            samp_scale=self.samp_scale,
            err_bias=self.err_bias,
            err_rand=self.err_rand,
        )

    @classmethod
    def from_rasterio(cls, rpc, **kw: Any) -> "RPCModel":
        """From a :class:`rasterio.rpc.RPC` (GeoTIFF/NITF tags read by GDAL)."""
        return cls(
            line_num=rpc.line_num_coeff,
            line_den=rpc.line_den_coeff,
            samp_num=rpc.samp_num_coeff,
            samp_den=rpc.samp_den_coeff,
            line_off=rpc.line_off,
            samp_off=rpc.samp_off,
            lat_off=rpc.lat_off,
            lon_off=rpc.long_off,
            height_off=rpc.height_off,
            line_scale=rpc.line_scale,
            samp_scale=rpc.samp_scale,
            lat_scale=rpc.lat_scale,
            lon_scale=rpc.long_scale,
            height_scale=rpc.height_scale,
            err_bias=rpc.err_bias if rpc.err_bias not in (None, -1.0) else None,
            err_rand=rpc.err_rand if rpc.err_rand not in (None, -1.0) else None,
            **kw,
        )

    def __repr__(self) -> str:
        size = f"{self.width}x{self.height}" if self.width else "size unknown"
        return (
            f"<RPCModel {size} lon={self.lon_off:.5f} lat={self.lat_off:.5f} "
            f"h={self.height_off:g}±{self.height_scale:g} m{' from ' + self.source if self.source else ''}>"
        )
