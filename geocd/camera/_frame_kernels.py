"""numba kernels for the frame (pinhole) camera, with pure-numpy references.

All kernels work in the camera's *world frame*: the projected CRS easting and
northing ``(x, y)`` in metres and the height ``z`` in the camera's vertical datum,
treated as a Cartesian frame (see :mod:`geocd.camera.frame`). The camera is
packed as ``params[22]``:

==========  ============================================================
index       meaning
==========  ============================================================
0, 1        fx, fy: focal length in pixels (columns, rows)
2, 3        cx, cy: principal point, geocd pixel convention (corner origin)
4, 5, 6     k1, k2, k3: radial distortion (OpenCV, normalised coordinates)
7, 8        p1, p2: tangential distortion (OpenCV)
9, 10, 11   Tx, Ty, Tz: projection centre in the world frame (m)
12 .. 20    M: world → camera rotation, row-major 3x3 (camera axes: x right,
            y down, z forward along the optical axis — OpenCV)
21          r²_max: the distortion model's valid domain, undistorted radius²
            (normalised); inf when the radial polynomial never folds back
==========  ============================================================

Projection: ``Xc = M (X - T)``; ``x = Xc0/Xc2``, ``y = Xc1/Xc2``; Brown–Conrady
distortion as OpenCV::

    r² = x² + y²,  q = 1 + k1 r² + k2 r⁴ + k3 r⁶
    xd = x q + 2 p1 x y + p2 (r² + 2 x²)
    yd = y q + p1 (r² + 2 y²) + 2 p2 x y
    col = fx xd + cx,  row = fy yd + cy

Points with ``Xc2 <= 0`` (behind the camera, or in its plane) give NaN.

**Valid domain.** The radial polynomial ``r_d = r (1 + k1 r² + k2 r⁴ + k3 r⁶)`` grows with
``r`` only up to the first root of ``dr_d/dr = 1 + 3 k1 r² + 5 k2 r⁴ + 7 k3 r⁶``
(:func:`max_radius2`; with k1 = −0.26 alone, r = 1.13, 48.5° off the axis). Beyond it the
model *folds back*: ground points far outside the field of view land inside the image,
and an image point has two undistorted solutions. Points with ``r² ≥ r²_max``, or where
the distortion's Jacobian is not positive (tangential terms), are outside the model's
domain: they project to NaN and pixels that only such points explain undistort to NaN.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from .._jit import parallel_njit

N_PARAMS = 22


def max_radius2(k1: float, k2: float, k3: float) -> float:
    """Undistorted radius² where the radial distortion stops growing (its first fold), inf if never.

    The smallest positive root of ``1 + 3 k1 u + 5 k2 u² + 7 k3 u³`` with ``u = r²``.
    """
    roots = np.roots([7.0 * k3, 5.0 * k2, 3.0 * k1, 1.0]) if (k1 or k2 or k3) else np.array([])
    u = [float(r.real) for r in np.atleast_1d(roots) if abs(r.imag) < 1e-12 * max(1.0, abs(r)) and r.real > 0]
    return min(u) if u else float("inf")


@njit(cache=True, inline="always")
def _distort(x, y, k1, k2, k3, p1, p2):
    r2 = x * x + y * y
    q = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * q + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * q + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return xd, yd


@njit(cache=True, inline="always")
def _distort_jac(x, y, k1, k2, k3, p1, p2):
    """Jacobian of (xd, yd) with respect to (x, y): (a, b, c, d) = [[a, b], [c, d]]."""
    r2 = x * x + y * y
    q = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    dq = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)  # dq/d(r²)
    a = q + 2.0 * x * x * dq + 2.0 * p1 * y + 6.0 * p2 * x
    b = 2.0 * x * y * dq + 2.0 * p1 * x + 2.0 * p2 * y
    c = 2.0 * x * y * dq + 2.0 * p1 * x + 2.0 * p2 * y
    d = q + 2.0 * y * y * dq + 6.0 * p1 * y + 2.0 * p2 * x
    return a, b, c, d


@njit(cache=True, inline="always")
def _in_domain(x, y, k1, k2, k3, p1, p2, r2max):
    """Whether normalised undistorted (x, y) lies where the distortion model is one-to-one."""
    if not x * x + y * y < r2max:
        return False
    a, b, c, d = _distort_jac(x, y, k1, k2, k3, p1, p2)
    return a * d - b * c > 0.0


@njit(cache=True, inline="always")
def _to_camera(x, y, z, tx, ty, tz, m):
    """World point → camera frame: M · (X − T), with M the row-major 3×3 rotation ``m``."""
    dx = x - tx
    dy = y - ty
    dz = z - tz
    return (m[0] * dx + m[1] * dy + m[2] * dz, m[3] * dx + m[4] * dy + m[5] * dz, m[6] * dx + m[7] * dy + m[8] * dz)


@parallel_njit()
def frame_project(x, y, z, params, out_col, out_row):
    """World (x, y, z) flat float64 arrays → (col, row) pixels; NaN behind the camera."""
    fx, fy, cx, cy = params[0], params[1], params[2], params[3]
    k1, k2, k3, p1, p2 = params[4], params[5], params[6], params[7], params[8]
    tx, ty, tz = params[9], params[10], params[11]
    m = params[12:21]
    r2max = params[21]
    for i in prange(x.shape[0]):
        xc, yc, zc = _to_camera(x[i], y[i], z[i], tx, ty, tz, m)
        if not zc > 0.0 or not _in_domain(xc / zc, yc / zc, k1, k2, k3, p1, p2, r2max):
            out_col[i] = np.nan
            out_row[i] = np.nan
            continue
        xd, yd = _distort(xc / zc, yc / zc, k1, k2, k3, p1, p2)
        out_col[i] = fx * xd + cx
        out_row[i] = fy * yd + cy


@parallel_njit()
def frame_dproj_dz(x, y, z, params, out_dcol, out_drow):
    """∂(col, row)/∂z at fixed (x, y) (pixels per metre), analytic chain rule."""
    fx, fy = params[0], params[1]
    k1, k2, k3, p1, p2 = params[4], params[5], params[6], params[7], params[8]
    tx, ty, tz = params[9], params[10], params[11]
    m = params[12:21]
    r2max = params[21]
    for i in prange(x.shape[0]):
        xc, yc, zc = _to_camera(x[i], y[i], z[i], tx, ty, tz, m)
        if not zc > 0.0 or not _in_domain(xc / zc, yc / zc, k1, k2, k3, p1, p2, r2max):
            out_dcol[i] = np.nan
            out_drow[i] = np.nan
            continue
        xn = xc / zc
        yn = yc / zc
        # d(Xc)/dz = third column of M
        dxn = (m[2] * zc - xc * m[8]) / (zc * zc)
        dyn = (m[5] * zc - yc * m[8]) / (zc * zc)
        a, b, c, d = _distort_jac(xn, yn, k1, k2, k3, p1, p2)
        out_dcol[i] = fx * (a * dxn + b * dyn)
        out_drow[i] = fy * (c * dxn + d * dyn)


@parallel_njit()
def frame_undistort(col, row, params, tol, max_iter, out_x, out_y):
    """(col, row) pixels → undistorted normalised camera coordinates (x, y).

    Newton iteration on the distortion model starting from the distorted point;
    converged when the residual in normalised coordinates is below ``tol``.
    Samples that do not converge in ``max_iter`` iterations, or converge outside the
    model's valid domain (a folded-back solution), get NaN.
    """
    fx, fy, cx, cy = params[0], params[1], params[2], params[3]
    k1, k2, k3, p1, p2 = params[4], params[5], params[6], params[7], params[8]
    r2max = params[21]
    no_dist = k1 == 0.0 and k2 == 0.0 and k3 == 0.0 and p1 == 0.0 and p2 == 0.0
    for i in prange(col.shape[0]):
        xd = (col[i] - cx) / fx
        yd = (row[i] - cy) / fy
        if no_dist or not (np.isfinite(xd) and np.isfinite(yd)):
            out_x[i] = xd
            out_y[i] = yd
            continue
        x = xd
        y = yd
        ok = False
        for _ in range(max_iter):
            fxd, fyd = _distort(x, y, k1, k2, k3, p1, p2)
            rx = fxd - xd
            ry = fyd - yd
            if rx * rx + ry * ry <= tol * tol:
                ok = True
                break
            a, b, c, d = _distort_jac(x, y, k1, k2, k3, p1, p2)
            det = a * d - b * c
            if det == 0.0 or not np.isfinite(det):
                break
            x -= (d * rx - b * ry) / det
            y -= (-c * rx + a * ry) / det
        if ok and _in_domain(x, y, k1, k2, k3, p1, p2, r2max):
            out_x[i] = x
            out_y[i] = y
        else:
            out_x[i] = np.nan
            out_y[i] = np.nan


# ---------------------------------------------------------------------------------------
# pure-numpy references (slow, obviously correct; tests check the kernels against them)
# ---------------------------------------------------------------------------------------
def _unpack_ref(params):
    p = np.asarray(params, float)
    return p[0], p[1], p[2], p[3], p[4:9], p[9:12], p[12:21].reshape(3, 3)


def in_domain_ref(x, y, params):
    """numpy reference of the valid-domain test (radius below the fold, positive Jacobian)."""
    k1, k2, k3, p1, p2 = np.asarray(params, float)[4:9]
    r2 = x**2 + y**2
    q = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    dq = k1 + 2 * k2 * r2 + 3 * k3 * r2**2
    a = q + 2 * x * x * dq + 2 * p1 * y + 6 * p2 * x
    b = 2 * x * y * dq + 2 * p1 * x + 2 * p2 * y
    d = q + 2 * y * y * dq + 6 * p1 * y + 2 * p2 * x
    return (r2 < np.asarray(params, float)[21]) & (a * d - b * b > 0)


def distort_ref(x, y, dist):
    k1, k2, k3, p1, p2 = dist
    r2 = x**2 + y**2
    q = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    return (x * q + 2 * p1 * x * y + p2 * (r2 + 2 * x**2), y * q + p1 * (r2 + 2 * y**2) + 2 * p2 * x * y)


def project_ref(x, y, z, params):
    """World → (col, row) with plain numpy (NaN behind the camera)."""
    fx, fy, cx, cy, dist, t, m = _unpack_ref(params)
    X = np.stack([np.asarray(x, float) - t[0], np.asarray(y, float) - t[1], np.asarray(z, float) - t[2]])
    xc, yc, zc = np.tensordot(m, X, axes=1)
    with np.errstate(all="ignore"):
        xd, yd = distort_ref(xc / zc, yc / zc, dist)
        ok = (zc > 0) & in_domain_ref(xc / zc, yc / zc, params)
    col = np.where(ok, fx * xd + cx, np.nan)
    row = np.where(ok, fy * yd + cy, np.nan)
    return col, row


def dproj_dz_ref(x, y, z, params, eps_m: float = 1e-3):
    """Central finite difference of :func:`project_ref` along z (pixels per metre)."""
    z = np.asarray(z, float)
    c1, r1 = project_ref(x, y, z + eps_m, params)
    c0, r0 = project_ref(x, y, z - eps_m, params)
    return (c1 - c0) / (2 * eps_m), (r1 - r0) / (2 * eps_m)


def undistort_ref(col, row, params, n_iter: int = 50):
    """Fixed-point inversion of the distortion (OpenCV's ``undistortPoints`` scheme)."""
    fx, fy, cx, cy, dist, _, _ = _unpack_ref(params)
    k1, k2, k3, p1, p2 = dist
    xd = (np.asarray(col, float) - cx) / fx
    yd = (np.asarray(row, float) - cy) / fy
    x, y = xd.copy(), yd.copy()
    for _ in range(n_iter):
        r2 = x**2 + y**2
        q = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
        x, y = ((xd - (2 * p1 * x * y + p2 * (r2 + 2 * x**2))) / q, (yd - (p1 * (r2 + 2 * y**2) + 2 * p2 * x * y)) / q)
    # a pixel no point of the domain reaches has no fixed point: the iteration then wanders
    xr, yr = distort_ref(x, y, dist)
    ok = in_domain_ref(x, y, params) & (np.hypot(xr - xd, yr - yd) < 1e-9)
    return np.where(ok, x, np.nan), np.where(ok, y, np.nan)
