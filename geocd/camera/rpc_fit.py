"""Fit an RPC00B model to any geocd camera (terrain-independent).

The camera (physical pushbroom, frame, another RPC, ...) is sampled on a
regular 3-D grid of ground points (lon, lat, ellipsoidal height) covering the
image footprint over a height range, independent of any terrain model. Each
image coordinate is then fitted separately as a ratio of cubic polynomials
(RPC00B term order, denominator constant fixed to 1, so 39 unknowns per
coordinate) by linearised least squares::

    Num(x) - c * (Den(x) - 1) = c          (c = normalised sample or line)

iterated with weights ``1 / Den_prev(x)`` so that the minimised quantity
approaches the true image residual ``c - Num/Den`` (the classical
"terrain-independent" RPC fitting of Tao & Hu, 2001).

The unregularised problem is ill-posed: over a small footprint a pushbroom
camera is nearly affine, the 39 columns of the design matrix are nearly
dependent (condition number ~1e12 on sample_aoi's views, ~1e24 in the normal
equations) and very different coefficient sets give the same projections to
1e-9 px, so which one a solver returns depends on rounding (BLAS, CPU). The fit
is therefore made well-posed with a fixed conditioning: Tikhonov
regularisation with weight ``ridge * ||A||_2`` (``A`` the design matrix of
normalised coordinates), solved as the augmented least-squares problem
``[A; ridge*||A||_2*I] x = [c; 0]`` by SVD, with a fixed number of
reweighting passes. The condition number of that system is at most
``1 / ridge`` (1e7 by default), so the coefficients are a continuous function
of the camera: rounding-level changes of the input move them by ~1e-9 and the
projections by ~1e-11 px, while the bias the ridge adds stays below 1e-7 px on
the fit grid of a satellite view (both measured in ``tests/camera/test_rpc_fit.py``).

The fit is reported on a *check grid* shifted by half a grid step in all three
dimensions (points the fit never saw): :class:`RPCFitReport` gives its RMS and
maximum residual in pixels.

Pixel convention: geocd's (col, row) with (0, 0) at the upper-left corner of
the image; the RPC's own pixel origin is the centre of the first pixel, so the
fit targets ``samp = col - 0.5`` and ``line = row - 0.5`` (see
:mod:`geocd.camera.rpc`).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any, Callable

import numpy as np

from ..errors import CameraError, ConfigError, ProcessingError
from . import _kernels as K
from .base import Camera
from .rpc import PIXEL_SHIFT, RPCModel


@dataclass(frozen=True)
class RPCFitReport:
    """How well a fitted RPC reproduces its camera (all residuals in pixels).

    Attributes
    ----------
    fit_rms_px, fit_max_px : residual on the fitting grid (Euclidean, col/row)
    check_rms_px, check_max_px : residual on the half-step-shifted check grid
    check_max_col_px, check_max_row_px : per-axis maxima on the check grid
    n_fit, n_check : number of grid points used
    iterations : least-squares solves per coordinate (fixed)
    ridge : Tikhonov weight relative to the design matrix's largest singular value
    lon_range, lat_range : degrees; h_range : metres (ellipsoidal), the fitted box
    """

    fit_rms_px: float
    fit_max_px: float
    check_rms_px: float
    check_max_px: float
    check_max_col_px: float
    check_max_row_px: float
    n_fit: int
    n_check: int
    iterations: int
    ridge: float
    lon_range: tuple[float, float]
    lat_range: tuple[float, float]
    h_range: tuple[float, float]

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        for k in ("lon_range", "lat_range", "h_range"):
            d[k] = list(d[k])
        return d


def _grid(lo: float, hi: float, n: int, shifted: bool) -> np.ndarray:
    g = np.linspace(lo, hi, n)
    if shifted:
        return 0.5 * (g[1:] + g[:-1])
    return g


def _ground_box(
    camera: Camera, h_range: tuple[float, float], densify: int = 16
) -> tuple[tuple[float, float], tuple[float, float]]:
    """Bounding lon/lat box of the image footprint over the height range."""
    lons, lats = [], []
    for h in np.linspace(h_range[0], h_range[1], 3):
        poly = camera.footprint(float(h), densify=densify)
        x, y = poly.exterior.xy
        lons.extend(x)
        lats.extend(y)
    return (float(min(lons)), float(max(lons))), (float(min(lats)), float(max(lats)))


def _single_thread_blas():
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover - threadpoolctl comes with scikit-learn
        import contextlib

        return contextlib.nullcontext()
    return threadpool_limits(limits=1, user_api="blas")


def _solve_coordinate(T: np.ndarray, c: np.ndarray, ridge: float, n_iter: int) -> tuple[np.ndarray, np.ndarray, int]:
    """Fit normalised coordinate c ≈ (num·T)/(den·T), den[0] = 1, Tikhonov-regularised.

    Parameters
    ----------
    T : (20, N) monomials; c : (N,) normalised targets.
    ridge : regularisation relative to the design matrix's largest singular value
        (the regularised system's condition number is at most ``1 / ridge``).
    n_iter : solves (the first unweighted, then reweighted by ``1 / |Den|``).

    Returns
    -------
    num (20,), den (20,), iterations
    """
    n = c.size
    A = np.empty((n, 39))
    A[:, :20] = T.T
    A[:, 20:] = -c[:, None] * T[1:].T
    lam = ridge * float(np.linalg.norm(A, 2))
    reg = np.zeros((39, 39))
    reg[np.diag_indices_from(reg)] = lam
    w = np.ones(n)
    num = np.zeros(20)
    den = np.zeros(20)
    den[0] = 1.0
    for _ in range(n_iter):
        Aug = np.vstack([A * w[:, None], reg])
        bug = np.concatenate([c * w, np.zeros(39)])
        try:
            x = np.linalg.lstsq(Aug, bug, rcond=None)[0]
        except np.linalg.LinAlgError as exc:  # pragma: no cover - the ridge keeps the system full rank
            raise ProcessingError("RPC fit: the least-squares solve failed; widen the ground grid") from exc
        num = x[:20]
        den = np.concatenate([[1.0], x[20:]])
        D = den @ T
        if np.any(D == 0) or not np.all(np.isfinite(D)):
            raise ProcessingError("RPC fit: the fitted denominator vanishes inside the fit box; reduce the box")
        w = 1.0 / np.abs(D)
    return num, den, n_iter


def fit_rpc(
    camera: Camera,
    h_range: tuple[float, float],
    *,
    lon_range: tuple[float, float] | None = None,
    lat_range: tuple[float, float] | None = None,
    n_xy: int = 21,
    n_h: int = 9,
    ridge: float = 1e-7,
    n_iter: int = 3,
    width: int | None = None,
    height: int | None = None,
    source: str = "",
    progress: Callable | None = None,
) -> tuple[RPCModel, RPCFitReport]:
    """Fit an RPC00B to ``camera`` over a terrain-independent 3-D grid.

    Parameters
    ----------
    camera : Camera
        Any model of the camera protocol (must project every grid point).
    h_range : (h_min, h_max)
        Ellipsoidal height range, metres. The RPC's height normalisation spans
        exactly this range; use the scene's range with a margin.
    lon_range, lat_range : (min, max) degrees, optional
        Horizontal extent of the grid; default: the bounding box of the image
        footprint over ``h_range`` (needs the camera's image size).
    n_xy, n_h : int
        Grid nodes per horizontal axis and height layers (≥ 4 each; the cubic
        terms need at least 4 layers).
    ridge : float
        Tikhonov weight relative to the largest singular value of the design
        matrix: the fit's condition number is at most ``1 / ridge``. The default
        1e-7 keeps the coefficients reproducible across machines to ~1e-9 and adds
        less than 1e-7 px of bias on satellite views (see the module docstring).
    n_iter : int
        Least-squares solves (the first unweighted, the others reweighted by
        ``1 / |Den|``); a fixed count, so the result does not hinge on a stopping test.
    width, height : int, optional
        Image size stored in the model (default: the camera's).
    source : str
        Provenance written into the model.

    Returns
    -------
    rpc : RPCModel
    report : RPCFitReport
        Residuals on the fit grid and on the half-step-shifted check grid.

    Raises
    ------
    ConfigError
        Bad grid sizes or an empty height range.
    CameraError
        When the camera cannot project some grid points (NaN).
    """
    if not 0 < ridge < 1 or n_iter < 1:
        raise ConfigError(f"RPC fit needs 0 < ridge < 1 and n_iter >= 1, got ridge={ridge}, n_iter={n_iter}")
    if n_xy < 4 or n_h < 4:
        raise ConfigError(f"RPC fit needs at least 4 nodes per axis (cubic terms), got n_xy={n_xy}, n_h={n_h}")
    h0, h1 = float(h_range[0]), float(h_range[1])
    if not (h1 > h0):
        raise ConfigError(f"RPC fit height range {h_range} is empty; give (h_min, h_max) with h_max > h_min")
    if lon_range is None or lat_range is None:
        blon, blat = _ground_box(camera, (h0, h1))
        lon_range = lon_range or blon
        lat_range = lat_range or blat
    lon0, lon1 = map(float, lon_range)
    lat0, lat1 = map(float, lat_range)
    if not (lon1 > lon0 and lat1 > lat0):
        raise ConfigError(f"RPC fit ground box lon {lon_range}, lat {lat_range} is empty")

    def sample(shifted: bool):
        g = np.meshgrid(
            _grid(lon0, lon1, n_xy, shifted),
            _grid(lat0, lat1, n_xy, shifted),
            _grid(h0, h1, n_h, shifted),
            indexing="ij",
        )
        lon, lat, h = (a.ravel() for a in g)
        col, row = camera.project(lon, lat, h)
        col, row = np.asarray(col, float), np.asarray(row, float)
        bad = ~(np.isfinite(col) & np.isfinite(row))
        if bad.any():
            raise CameraError(
                f"the camera cannot project {int(bad.sum())} of {bad.size} RPC-fit grid points; "
                "restrict the ground box or height range to where the camera is defined"
            )
        return lon, lat, h, col - PIXEL_SHIFT, row - PIXEL_SHIFT

    lon, lat, h, samp, line = sample(False)
    if progress is not None:
        progress(0.3, "RPC fit: grid projected")
    norm = np.empty(10)
    norm[2], norm[7] = 0.5 * (lat0 + lat1), 0.5 * (lat1 - lat0)
    norm[3], norm[8] = 0.5 * (lon0 + lon1), 0.5 * (lon1 - lon0)
    norm[4], norm[9] = 0.5 * (h0 + h1), 0.5 * (h1 - h0)
    for k_off, k_scale, v in ((0, 5, line), (1, 6, samp)):
        lo, hi = float(v.min()), float(v.max())
        norm[k_off] = 0.5 * (lo + hi)
        norm[k_scale] = max(0.5 * (hi - lo), 1.0)
    L = (lon - norm[3]) / norm[8]
    P = (lat - norm[2]) / norm[7]
    H = (h - norm[4]) / norm[9]
    T = K.terms_ref(L, P, H)
    # tiny dense products: a multi-threaded BLAS only loses time here (by 100x on a busy machine)
    with _single_thread_blas():
        ln, ld, it_l = _solve_coordinate(T, (line - norm[0]) / norm[5], ridge, n_iter)
        sn, sd, it_s = _solve_coordinate(T, (samp - norm[1]) / norm[6], ridge, n_iter)
    if progress is not None:
        progress(0.8, "RPC fit: solved")
    w = width if width is not None else camera.width
    hgt = height if height is not None else camera.height
    rpc = RPCModel.from_arrays(
        np.stack([ln, ld, sn, sd]), norm, width=w, height=hgt, source=source or f"fitted to {camera.kind} camera"
    )

    def resid(lon_, lat_, h_, s_, l_):
        c, r = rpc.project(lon_, lat_, h_)
        dc = c - PIXEL_SHIFT - s_
        dr = r - PIXEL_SHIFT - l_
        return dc, dr

    dc, dr = resid(lon, lat, h, samp, line)
    e_fit = np.hypot(dc, dr)
    clon, clat, ch, cs, cl = sample(True)
    dc2, dr2 = resid(clon, clat, ch, cs, cl)
    e_chk = np.hypot(dc2, dr2)
    report = RPCFitReport(
        fit_rms_px=float(np.sqrt(np.mean(e_fit**2))),
        fit_max_px=float(e_fit.max()),
        check_rms_px=float(np.sqrt(np.mean(e_chk**2))),
        check_max_px=float(e_chk.max()),
        check_max_col_px=float(np.abs(dc2).max()),
        check_max_row_px=float(np.abs(dr2).max()),
        n_fit=int(lon.size),
        n_check=int(clon.size),
        iterations=int(max(it_l, it_s)),
        ridge=float(ridge),
        lon_range=(lon0, lon1),
        lat_range=(lat0, lat1),
        h_range=(h0, h1),
    )
    if progress is not None:
        progress(1.0, f"RPC fit: check max {report.check_max_px:.2e} px")
    return rpc, report


def rpc_camera_difference(rpc: Camera, camera: Camera, lon: np.ndarray, lat: np.ndarray, h: np.ndarray) -> np.ndarray:
    """Euclidean image distance (pixels) between two cameras' projections of the same ground points."""
    c1, r1 = rpc.project(lon, lat, h)
    c2, r2 = camera.project(lon, lat, h)
    return np.hypot(np.asarray(c1) - c2, np.asarray(r1) - r2)
