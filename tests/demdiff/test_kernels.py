import math

import numpy as np
import pytest

from geocd.demdiff._kernels import (
    shift_grid,
    shift_grid_ref,
    terrain_attributes,
    terrain_attributes_ref,
    variogram_bins,
    variogram_bins_ref,
)
from geocd.demdiff.uncertainty import variogram_fft


@pytest.fixture
def dem():
    rng = np.random.default_rng(3)
    from scipy.ndimage import gaussian_filter

    h = 1000 + 50 * gaussian_filter(rng.normal(size=(40, 50)), 3)
    h[5, 7] = np.nan
    h[20:23, 30] = np.nan
    return h


def test_terrain_kernel_matches_reference(dem):
    a = terrain_attributes(dem, (10.0, 12.0))
    b = terrain_attributes_ref(dem, (10.0, 12.0))
    for k in a:
        assert np.array_equal(np.isnan(a[k]), np.isnan(b[k])), k
        np.testing.assert_allclose(a[k], b[k], rtol=1e-5, atol=1e-5, equal_nan=True, err_msg=k)
    assert np.isnan(a["slope_rad"][0]).all() and np.isnan(a["slope_rad"][4:7, 6:9]).all()


@pytest.mark.parametrize("aspect_deg", [0, 45, 90, 180, 270, 300])
def test_slope_and_aspect_of_a_plane(aspect_deg):
    # plane descending towards azimuth aspect_deg with slope 20°
    t = math.tan(math.radians(20))
    az = math.radians(aspect_deg)
    rr, cc = np.mgrid[0:12, 0:12].astype(float)
    x, y = cc * 5.0, -rr * 5.0
    h = 100 - t * (x * math.sin(az) + y * math.cos(az))
    a = terrain_attributes(h, (5.0, 5.0))
    inner = (slice(1, -1), slice(1, -1))
    np.testing.assert_allclose(np.degrees(a["slope_rad"][inner]), 20, atol=1e-4)
    d = (np.degrees(a["aspect_rad"][inner]) - aspect_deg + 180) % 360 - 180
    np.testing.assert_allclose(d, 0, atol=1e-3)
    np.testing.assert_allclose(a["max_curvature"][inner], 0, atol=1e-6)


@pytest.mark.parametrize("method", ["bilinear", "cubic"])
@pytest.mark.parametrize("shift", [(0.0, 0.0), (0.3, -0.7), (-2.25, 1.5), (3.0, 0.0), (0.0, -0.5)])
def test_shift_kernel_matches_reference(dem, method, shift):
    a = shift_grid(dem, *shift, method=method)
    b = shift_grid_ref(dem, *shift, method=method)
    assert np.array_equal(np.isnan(a), np.isnan(b))
    np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-9, equal_nan=True)


def test_shift_zero_is_identity_and_integer_shift_moves_cells(dem):
    np.testing.assert_array_equal(shift_grid(dem, 0, 0), dem)
    s = shift_grid(dem, 2, 1)
    np.testing.assert_array_equal(s[1:, 2:], dem[:-1, :-2])
    assert np.isnan(s[0]).all() and np.isnan(s[:, :2]).all()


def test_cubic_shift_reproduces_a_quadratic_surface():
    rr, cc = np.mgrid[0:20, 0:20].astype(float)
    h = 0.3 * cc**2 - 0.2 * rr * cc + rr
    s = shift_grid(h, 0.4, -0.3, method="cubic")
    exp = 0.3 * (cc - 0.4) ** 2 - 0.2 * (rr + 0.3) * (cc - 0.4) + (rr + 0.3)
    ok = np.isfinite(s)
    assert ok.sum() > 200
    np.testing.assert_allclose(s[ok], exp[ok], atol=0.05)


def test_variogram_kernel_matches_reference():
    rng = np.random.default_rng(0)
    x, y, z = rng.uniform(0, 500, 300), rng.uniform(0, 500, 300), rng.normal(size=300)
    edges = np.array([0.0, 10, 30, 60, 100, 200, 400])
    g1, n1 = variogram_bins(x, y, z, edges)
    g2, n2 = variogram_bins_ref(x, y, z, edges)
    np.testing.assert_array_equal(n1, n2)
    np.testing.assert_allclose(g1, g2, rtol=1e-10)


def test_fft_variogram_equals_all_pairs():
    rng = np.random.default_rng(5)
    z = rng.normal(size=(25, 31))
    m = rng.random(z.shape) > 0.3
    edges = np.array([5.0, 15, 25, 45, 80, 150, 300])
    g_fft, n_fft = variogram_fft(np.where(m, z, np.nan), m, (10.0, 10.0), edges)
    r, c = np.nonzero(m)
    g_pair, n_pair = variogram_bins((c + 0.5) * 10.0, -(r + 0.5) * 10.0, z[m], edges)
    np.testing.assert_array_equal(n_fft, n_pair)
    np.testing.assert_allclose(g_fft, g_pair, rtol=1e-8)


@pytest.mark.parametrize("method", ["bilinear", "cubic"])
def test_shift_window_and_points_equal_shift_grid(method):
    from geocd.demdiff._kernels import shift_margin, shift_points, shift_window

    rng = np.random.default_rng(5)
    h = rng.normal(size=(90, 80)) * 10 + 100
    h[30:34, 40:45] = np.nan
    for dc, dr in [(1.37, -2.61), (-3.2, 0.45), (0.0, 7.9)]:
        ref = shift_grid(h, dc, dr, method)
        m = shift_margin(dc, dr, method)
        # a tile with its margin: the core is bit-identical to the whole grid's
        r0, c0, r1, c1 = 20, 10, 70, 60
        R0, C0, R1, C1 = max(0, r0 - m), max(0, c0 - m), min(90, r1 + m), min(80, c1 + m)
        win = shift_window(h[R0:R1, C0:C1], (R0, C0), h.shape, dc, dr, method)
        np.testing.assert_array_equal(win[r0 - R0 : r1 - R0, c0 - C0 : c1 - C0], ref[r0:r1, c0:c1])
        # a window at the grid's corner sees the grid's border
        np.testing.assert_array_equal(
            shift_window(h[:40, :40], (0, 0), h.shape, dc, dr, method)[: 40 - m, : 40 - m], ref[: 40 - m, : 40 - m]
        )
        # points from patches
        rows = rng.integers(0, 90, 300)
        cols = rng.integers(0, 80, 300)
        R = m + 1
        pr, pc = rows - R, cols - R
        pad = np.pad(h, R + 1, constant_values=np.nan)
        patches = np.stack([pad[r + 1 : r + 1 + 2 * R + 1, c + 1 : c + 1 + 2 * R + 1] for r, c in zip(pr + R, pc + R)])
        v, ok = shift_points(patches, pr, pc, rows, cols, h.shape, dc, dr, method)
        assert ok
        np.testing.assert_array_equal(v, ref[rows, cols])
        # patches too small are reported
        _, ok2 = shift_points(
            patches[:, R - 1 : R + 1, R - 1 : R + 1], rows - 1, cols - 1, rows, cols, h.shape, dc, dr, method
        )
        assert not ok2
