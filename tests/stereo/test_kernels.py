"""numba kernels agree with their numpy references."""

import numpy as np
import pytest

from geocd.stereo import _kernels as K
from geocd.stereo.scores import mdl_from_stats, mdl_score_ref, ncc_from_stats, ssd_from_stats, window_stats


@pytest.fixture
def rng():
    return np.random.default_rng(42)


def test_warp_bilinear_matches_reference(rng):
    img = rng.normal(100, 20, size=(40, 50)).astype(np.float32)
    img[5, 7] = np.nan
    col = rng.uniform(-2, 53, size=(30, 31))
    row = rng.uniform(-2, 43, size=(30, 31))
    col[0, :5] = [0.5, 49.5, 0.49, 49.51, 7.5]  # exact edges
    row[0, :5] = [0.5, 39.5, 3.0, 3.0, 5.5]
    out = np.empty(col.shape, np.float32)
    K.warp_bilinear(img, col, row, out)
    ref = K.warp_bilinear_ref(img, col, row)
    assert np.array_equal(np.isnan(out), np.isnan(ref))
    ok = np.isfinite(ref)
    np.testing.assert_allclose(out[ok], ref[ok], rtol=1e-5, atol=1e-3)
    # pixel centres give the pixel values
    i, j = 10, 20
    K.warp_bilinear(img, np.array([[j + 0.5]]), np.array([[i + 0.5]]), out[:1, :1])
    assert out[0, 0] == pytest.approx(img[i, j])


@pytest.mark.parametrize("r", [1, 3, 5])
def test_box_moments_matches_integral_images(rng, r):
    a = rng.normal(128, 30, size=(37, 45)).astype(np.float32)
    b = (0.7 * a + rng.normal(0, 5, size=a.shape)).astype(np.float32)
    a[rng.random(a.shape) < 0.05] = np.nan
    b[:3, :] = np.nan
    out = np.empty((6, *a.shape))
    work = np.empty_like(out)
    K.box_moments(a, b, r, out, work)
    ref = K.box_moments_ref(a, b, r)
    np.testing.assert_allclose(out, ref, rtol=1e-9, atol=1e-6)


def _random_costs(rng, K_, shape):
    """Smooth-ish random cost curves with several minima and some undefined values."""
    t = np.linspace(0, 6 * np.pi, K_)[:, None, None]
    ph = rng.uniform(0, 2 * np.pi, size=shape)
    c = 0.5 + 0.3 * np.sin(t + ph) + 0.15 * rng.random((K_, *shape))
    c[rng.random(c.shape) < 0.03] = np.inf
    return c


def test_sweep_state_matches_reference(rng):
    """Stream a cost volume through sweep_update/finish and compare with the full-volume reference."""
    K_, shape = 40, (9, 11)
    a = rng.normal(128, 20, size=(K_, *shape)).astype(np.float32)
    b = (a + rng.normal(0, 15, size=a.shape)).astype(np.float32)
    b[rng.random(b.shape) < 0.02] = np.nan
    r, min_n, eps, excl = 1, 6.0, 4.0, 2.0
    kmin = rng.integers(0, 5, size=shape).astype(np.int32)
    kmax = rng.integers(25, K_, size=shape).astype(np.int32)
    st = K.new_state(shape)
    costs = np.empty((K_, *shape))
    stats = []
    out = np.empty((6, *shape))
    work = np.empty_like(out)
    for k in range(K_):
        K.box_moments(a[k], b[k], r, out, work)
        K.sweep_update(out, k, kmin, kmax, min_n, eps, excl, st)
        c, va, vb, cov = K.ncc_cost_ref(K.box_moments_ref(a[k], b[k], r), min_n, eps)
        c = np.where((k > kmax) | (k < kmin), np.inf, c)
        costs[k] = c
        stats.append((va, vb, cov))
    K.sweep_finish(K_, excl, st)
    ref = K.sweep_ref(costs, excl)
    np.testing.assert_array_equal(st[K.BEST_K], ref["best_k"])
    np.testing.assert_allclose(st[K.BEST_C], ref["best_c"], rtol=1e-9)
    np.testing.assert_allclose(st[K.BEST_CM], ref["best_cm"], rtol=1e-9)
    np.testing.assert_allclose(st[K.BEST_CP], ref["best_cp"], rtol=1e-9)
    np.testing.assert_array_equal(st[K.SEC_K], ref["sec_k"])
    np.testing.assert_allclose(st[K.SEC_C], ref["sec_c"], rtol=1e-9)
    # window statistics stored with the best minimum are those of its height
    kb = st[K.BEST_K].astype(int)
    ii, jj = np.nonzero(kb >= 0)
    va_ref = np.array([stats[kb[i, j]][0][i, j] for i, j in zip(ii, jj)])
    np.testing.assert_allclose(st[K.BEST_VA][ii, jj], va_ref, rtol=1e-7, atol=1e-9)


def test_sweep_reference_on_pure_cost_curves(rng):
    """The reference's minimum bookkeeping on hand-made curves."""
    inf = np.inf
    c = np.array([[0.9], [0.5], [0.6], [0.2], [0.3], [0.25], [0.7], [0.1], [inf]])[:, :, None]
    ref = K.sweep_ref(c, excl=1.0)
    assert ref["best_k"][0, 0] == 7 and ref["best_c"][0, 0] == 0.1
    assert ref["best_cm"][0, 0] == 0.7 and ref["best_cp"][0, 0] == inf
    # the second best more than one step away: 0.2 at k=3
    assert ref["sec_k"][0, 0] == 3 and ref["sec_c"][0, 0] == 0.2


def test_zbuffer_matches_reference(rng):
    n = 500
    col = rng.uniform(0, 20, n)
    row = rng.uniform(0, 20, n)
    z = rng.uniform(0, 10, n)
    cost = rng.uniform(0, 1, n)
    col[:3] = np.nan
    tol = np.full(n, 0.5)
    out = np.empty(n, bool)
    K.zbuffer_occluded(col, row, z, cost, tol, 2, 1, 15, 16, out)
    ref = K.zbuffer_occluded_ref(col, row, z, cost, tol, 2, 1, 15, 16)
    np.testing.assert_array_equal(out, ref)
    assert out.any() and not out.all()


def test_zbuffer_keeps_the_better_match():
    # two cells on one pixel: a high one (better cost) hides the low one, and vice versa
    col = np.array([5.2, 5.7, 9.0])
    row = np.array([3.1, 3.9, 3.0])
    z = np.array([10.0, 2.0, 0.0])
    tol = np.full(3, 1.0)
    out = np.empty(3, bool)
    K.zbuffer_occluded(col, row, z, np.array([0.1, 0.5, 0.2]), tol, 0, 0, 12, 6, out)
    assert out.tolist() == [False, True, False]
    K.zbuffer_occluded(col, row, z, np.array([0.6, 0.5, 0.2]), tol, 0, 0, 12, 6, out)
    assert out.tolist() == [True, False, False]


def test_mdl_from_moments_matches_direct_formula(rng):
    n = 49
    for _ in range(20):
        a = rng.normal(100, rng.uniform(1, 30), n)
        b = rng.uniform(-1, 1) * a + rng.normal(0, rng.uniform(0.5, 20), n) + rng.uniform(-20, 20)
        mom = np.array([n, a.sum(), b.sum(), (a * a).sum(), (b * b).sum(), (a * b).sum()])
        _, va, vb, cov = window_stats(mom)
        for sigma in (0.5, 2.0):
            assert mdl_from_stats(va, vb, cov, sigma) == pytest.approx(mdl_score_ref(np.stack([a, b]), sigma), abs=1e-9)
        assert ncc_from_stats(va, vb, cov) == pytest.approx(np.corrcoef(a, b)[0, 1], abs=1e-9)
        assert ssd_from_stats(va, vb, cov) == pytest.approx(np.mean(((a - a.mean()) - (b - b.mean())) ** 2), rel=1e-9)


def test_mdl_score_orders_matches():
    rng = np.random.default_rng(1)
    a = rng.normal(0, 20, 49)
    perfect = mdl_score_ref(np.stack([a, a + rng.normal(0, 1, 49)]), 1.0)
    noisy = mdl_score_ref(np.stack([a, a + rng.normal(0, 10, 49)]), 1.0)
    unrelated = mdl_score_ref(np.stack([a, rng.normal(0, 20, 49)]), 1.0)
    flat = mdl_score_ref(np.stack([rng.normal(0, 1, 49), rng.normal(0, 1, 49)]), 1.0)
    assert perfect < noisy < unrelated < 0.1
    assert abs(flat) < 0.5  # textureless: little evidence either way
    # three windows work in the reference too
    assert mdl_score_ref(np.stack([a, a, a]), 1.0) < mdl_score_ref(np.stack([a, a, rng.normal(0, 20, 49)]), 1.0)


def test_fused_sweep_step_equals_moments_then_update(rng):
    K_, shape = 25, (33, 70)  # > 32 columns: several column blocks
    r, min_n, eps, excl = 2, 12.0, 4.0, 2.0
    kmin = rng.integers(0, 4, size=shape).astype(np.int32)
    kmax = rng.integers(15, K_, size=shape).astype(np.int32)
    st1, st2 = K.new_state(shape), K.new_state(shape)
    mom = np.empty((6, *shape))
    work = np.empty_like(mom)
    for k in range(K_):
        a = rng.normal(128, 20, size=shape).astype(np.float32)
        b = (a + rng.normal(0, 10, size=shape)).astype(np.float32)
        b[rng.random(shape) < 0.03] = np.nan
        K.box_moments(a, b, r, mom, work)
        K.sweep_update(mom, k, kmin, kmax, min_n, eps, excl, st1)
        K.sweep_step(a, b, r, k, kmin, kmax, min_n, eps, excl, st2, work)
    K.sweep_finish(K_, excl, st1)
    K.sweep_finish(K_, excl, st2)
    np.testing.assert_allclose(st2, st1, rtol=1e-9, atol=1e-9)


def test_warp_lerp_equals_warp_of_interpolated_coordinates(rng):
    img = rng.normal(100, 20, size=(40, 50)).astype(np.float32)
    ca, ra = rng.uniform(0, 50, (20, 21)), rng.uniform(0, 40, (20, 21))
    cb, rb = ca + rng.normal(0, 2, ca.shape), ra + rng.normal(0, 2, ra.shape)
    out = np.empty(ca.shape, np.float32)
    K.warp_bilinear_lerp(img, ca, ra, cb, rb, 0.25, 3.0, 2.0, out)
    ref = K.warp_bilinear_ref(img, ca + 0.25 * (cb - ca) - 3.0, ra + 0.25 * (rb - ra) - 2.0)
    assert np.array_equal(np.isnan(out), np.isnan(ref))
    np.testing.assert_allclose(out[np.isfinite(ref)], ref[np.isfinite(ref)], rtol=1e-5, atol=1e-3)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_window_mean_matches_reference(rng, dtype):
    from geocd.stereo import window_mean

    x = rng.normal(0, 1, size=(29, 41)).astype(dtype)
    x[rng.random(x.shape) < 0.1] = np.nan
    x[:4, :4] = np.nan
    m, n = window_mean(x, 2)
    mr, nr = K.box_mean_ref(x, 2)
    np.testing.assert_array_equal(n, nr)
    np.testing.assert_allclose(m, mr, rtol=1e-9, atol=1e-9, equal_nan=True)


def _affine_geo(rng, shape, img_shape, shift=(0.0, 0.0)):
    """Per-cell (col, row, ∂col/∂j, ∂row/∂j, ∂col/∂i, ∂row/∂i) of a slightly rotated, scaled grid."""
    ii, jj = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float64)
    a, b, c, d = 1.3, 0.2, -0.15, 1.1  # ∂col/∂j, ∂row/∂j, ∂col/∂i, ∂row/∂i
    geo = np.empty((6, *shape))
    geo[0] = 4.0 + a * jj + c * ii + shift[0]
    geo[1] = 5.0 + b * jj + d * ii + shift[1]
    geo[2:] = np.array([a, b, c, d])[:, None, None]
    return geo


@pytest.mark.parametrize("r,q", [(3, 1), (2, 1), (3, 2), (2, 2)])
def test_subwindow_mdl_matches_reference(rng, r, q):
    img_a = rng.normal(100, 20, size=(40, 48)).astype(np.float32)
    img_b = (0.8 * img_a + rng.normal(5, 4, size=img_a.shape)).astype(np.float32)
    img_a[10, 12] = np.nan
    geo_a = _affine_geo(rng, (26, 29), img_a.shape)
    geo_b = _affine_geo(rng, (26, 29), img_b.shape, shift=(0.3, -0.2))
    geo_b[:2] += rng.normal(0, 0.5, size=geo_b[:2].shape)  # per-cell height errors
    geo_a[0, 3, 4] = np.nan  # a cell without a match
    centres = K.subwindow_centres(r, q)
    out = np.empty(geo_a.shape[1:])
    K.subwindow_mdl(img_a, img_b, geo_a, geo_b, r, q, centres, 6.0, 4.0, out)
    ref = K.subwindow_mdl_ref(img_a, img_b, geo_a, geo_b, r, q, centres, 6.0, 4.0)
    assert np.array_equal(np.isnan(out), np.isnan(ref))
    assert np.isnan(out[3, 4]) and np.isfinite(out).mean() > 0.5  # windows near the chip edge lose pixels
    np.testing.assert_allclose(out[np.isfinite(ref)], ref[np.isfinite(ref)], atol=1e-6)


def test_subwindow_mdl_of_whole_window_is_the_window_score(rng):
    """q ≥ r: one sub-window, the matching window itself → the plain MDL score of the window."""
    img_a = rng.normal(100, 20, size=(30, 30)).astype(np.float32)
    img_b = (img_a + rng.normal(0, 3, size=img_a.shape)).astype(np.float32)
    geo = np.zeros((6, 1, 1))
    geo[:, 0, 0] = [15.5, 14.5, 1.0, 0.0, 0.0, 1.0]
    out = np.empty((1, 1))
    K.subwindow_mdl(img_a, img_b, geo, geo, 3, 3, K.subwindow_centres(3, 3), 1.0, 4.0, out)
    win = np.stack([img_a[11:18, 12:19].ravel(), img_b[11:18, 12:19].ravel()]).astype(np.float64)
    assert out[0, 0] == pytest.approx(mdl_score_ref(win, 2.0), abs=1e-9)


def test_subwindow_mdl_sees_a_window_explained_only_in_part(rng):
    """A window straddling a height step: one side matches, the other is shifted by 3 px.
    The whole-window MDL still reads as a good match; its worst sub-window does not."""
    base = rng.normal(0, 25, size=(40, 40))
    img_a = base.astype(np.float32)
    img_b = base.copy()
    img_b[:, 20:] = np.roll(base, 3, axis=1)[:, 20:]  # right part of the scene at another height
    img_b = (img_b + rng.normal(0, 1, size=base.shape)).astype(np.float32)
    geo = np.zeros((6, 1, 1))
    geo[:, 0, 0] = [19.5, 20.5, 1.0, 0.0, 0.0, 1.0]  # window columns 16…22: 4 matched, 3 not
    out_sub = np.empty((1, 1))
    K.subwindow_mdl(img_a, img_b, geo, geo, 3, 1, K.subwindow_centres(3, 1), 6.0, 1.0, out_sub)
    whole = mdl_score_ref(np.stack([img_a[17:24, 16:23].ravel(), img_b[17:24, 16:23].ravel()]).astype(float), 1.0)
    good = mdl_score_ref(np.stack([img_a[17:24, 10:17].ravel(), img_b[17:24, 10:17].ravel()]).astype(float), 1.0)
    assert good < -3.0 and good < whole < -0.8  # the whole window still reads as a (weaker) match ...
    # ... its worst 3 × 3 part scores like two unrelated windows (≈ −½ bit/pixel, scores.py)
    assert out_sub[0, 0] > whole + 0.3 and out_sub[0, 0] > -0.7
