"""The marked point process kernels agree with their numpy references."""

import numpy as np
import pytest

from geocd.mpp import _kernels as K


def _scene(seed=0, with_layers=True):
    rng = np.random.default_rng(seed)
    H, W = 70, 80
    grey = (100 + rng.normal(0, 3, (H, W))).astype(np.float32)
    grey[20:40, 25:55] = 180 + rng.normal(0, 3, (20, 30))
    grey[20:40, 40:55] = 150 + rng.normal(0, 3, (20, 15))  # a gabled roof: two halves
    valid = np.ones((H, W), bool)
    valid[:, :3] = False
    gy, gx = np.gradient(grey.astype(np.float64))
    mag = np.hypot(gx, gy).astype(np.float32)
    ori = (np.arctan2(-gy, gx) + np.pi / 2) % np.pi - np.pi / 2
    ori = ori.astype(np.float32)
    if with_layers:
        colour = (rng.random((H, W)) < 0.3).astype(np.uint8)
        colour[20:40, 25:55] = 1
        shadow = np.zeros((H, W), np.uint8)
        shadow[40:45, 25:55] = 1
        ndsm = np.zeros((H, W), np.float32)
        ndsm[20:40, 25:55] = 6.0
        ndsm[0, 0] = np.nan
    else:
        colour = shadow = np.zeros((0, 0), np.uint8)
        ndsm = np.zeros((0, 0), np.float32)
    rects = np.array(
        [
            [39.5, 29.5, 30, 20, 0.0],
            [39.5, 29.5, 20, 30, np.pi / 2],
            [40, 30, 26, 14, 0.3],
            [10, 60, 12, 9, -0.7],
            [77, 5, 20, 10, 1.2],
            [50, 50, 8, 8, 0.0],
        ]
    )
    return rects, grey, valid, mag, ori, colour, shadow, ndsm


@pytest.mark.parametrize("with_layers,ring_in,core_in", [(True, 1.0, 0.0), (False, 1.0, 0.0), (True, 4.5, 2.5)])
def test_rect_features_match_reference(with_layers, ring_in, core_in):
    rects, grey, valid, mag, ori, colour, shadow, ndsm = _scene(with_layers=with_layers)
    args = (grey, valid, mag, ori, colour, shadow, 0.0, 1.0, ndsm, 2.5, 1.0, 3.0, 4.0, 9.0, 2.0, -np.inf)
    out = np.empty((rects.shape[0], K.N_FEATURES))
    K.rect_features(rects, *args, ring_in, core_in, out)
    ref = K.rect_features_ref(rects, *args, ring_in, core_in)
    np.testing.assert_allclose(out, ref, rtol=1e-6, atol=1e-9)  # kurtosis: raw vs central moments
    # the aligned rectangle outlines the block; its shadow ring is shadow; it is raised with low surroundings
    if with_layers:
        assert out[0, K.F_SHADOW_OUT] > 0.9 and out[0, K.F_RAISED_IN] > 0.95 and out[0, K.F_RAISED_OUT] > 0.8
    assert out[0, K.F_GRADIENT] > out[2, K.F_GRADIENT] > 0
    assert out[0, K.F_COMPLETE] > 0.9 and out[5, K.F_COMPLETE] < 0.5


def test_overlaps_and_death_pass_match_references():
    rng = np.random.default_rng(1)
    n = 40
    rects = np.column_stack(
        [
            rng.uniform(0, 60, n),
            rng.uniform(0, 50, n),
            rng.uniform(4, 20, n),
            rng.uniform(4, 20, n),
            rng.uniform(-1.5, 1.5, n),
        ]
    )
    areas = np.array([K.rect_mask_ref(r, (50, 60)).sum() for r in rects], float)
    pi, pj = np.triu_indices(n, 1)
    out = np.empty(pi.size)
    K.pair_overlaps(rects, pi.astype(np.int64), pj.astype(np.int64), areas, 50, 60, out)
    ref = K.pair_overlaps_ref(rects, pi, pj, (50, 60))
    np.testing.assert_allclose(out, ref, atol=1e-12)
    assert (out > 0).sum() > 20
    keep = out > 0
    a = np.concatenate([pi[keep], pj[keep]])
    b = np.concatenate([pj[keep], pi[keep]])
    w = np.concatenate([out[keep], out[keep]])
    order = np.lexsort((b, a))
    a, b, w = a[order], b[order], w[order]
    indptr = np.concatenate([[0], np.cumsum(np.bincount(a, minlength=n))]).astype(np.int64)
    energy = rng.normal(-0.3, 0.6, n)
    for beta, delta in ((1.0, 1.0), (20.0, 0.5)):
        alive = np.ones(n, bool)
        alive[3] = False
        rand = rng.random(n)
        order_u = np.argsort(-energy, kind="stable").astype(np.int64)
        ref_alive = K.death_pass_ref(order_u, indptr, b.astype(np.int64), w, energy, alive, beta, delta, 2.5, rand)
        K.death_pass(order_u, indptr, b.astype(np.int64), w, energy, alive, beta, delta, 2.5, rand)
        assert np.array_equal(alive, ref_alive)
        assert 0 < alive.sum() < n - 1


def test_rect_steps_match_reference():
    rng = np.random.default_rng(2)
    H, W = 70, 80
    h = rng.normal(0.0, 0.2, (H, W)).astype(np.float32)
    h[20:40, 25:55] += 6.0  # a block with walls
    ii, jj = np.mgrid[0:H, 0:W]
    h += np.clip(4.0 - 0.2 * np.hypot(jj - 15, ii - 55), 0.0, None).astype(np.float32)  # a cone: slopes
    h[5:10, 5:10] = np.nan
    n = 80
    rects = np.column_stack(
        [
            rng.uniform(0, 80, n),
            rng.uniform(0, 70, n),
            rng.uniform(4, 40, n),
            rng.uniform(4, 40, n),
            rng.uniform(-1.5, 1.5, n),
        ]
    )
    fitted = [
        [39.5, 29.5, 30, 20, 0.0],
        [39.5, 29.5, 20, 30, np.pi / 2],
        [39.5, 29.5, 22, 12, 0.0],
        [39.5, 29.5, 50, 40, 0.0],
        [15, 55, 12, 12, 0.0],
    ]
    rects = np.vstack([fitted, rects])
    out = np.empty(len(rects))
    K.rect_steps(rects, h, 0.8, 0.5, 2.0, 4.0, 4.0, out)
    ref = K.rect_steps_ref(rects, h, 0.8, 0.5, 2.0, 4.0, 4.0)
    np.testing.assert_allclose(out, ref, atol=1e-12)
    # the block's outline steps all round (either way its sides are named); a rectangle inside the block
    # has roof on both sides of its outline, one around it ground; the slope's rectangle is not steep
    assert out[0] == out[1] == 1.0
    assert out[2] < 0.5 and out[3] < 0.5 and out[4] < 0.5
    assert 5 < (out > 0).sum() < len(rects) - 5


def test_median_kernel_is_numpys_median():
    """The grow kernel's median (quickselect) is ``np.median``: odd and even counts, ties, one value."""
    rng = np.random.default_rng(3)
    for n in [1, 2, 3, 4, 5, 8, 33, 200, 201]:
        for a in (rng.normal(size=n), rng.integers(0, 4, n).astype(float), np.round(rng.normal(size=n), 1)):
            assert K._median(a) == np.median(a), a
