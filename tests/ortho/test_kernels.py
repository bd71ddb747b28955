"""The ortho kernels agree with their numpy references."""

import numpy as np
import pytest

from geocd.ortho import _kernels as K


@pytest.mark.parametrize("mode", [K.NEAREST, K.BILINEAR])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_sample_image_matches_reference(mode, dtype):
    rng = np.random.default_rng(3)
    img = rng.normal(100, 20, (3, 37, 41)).astype(dtype)
    valid = (rng.random((37, 41)) > 0.05).astype(np.uint8)
    col = rng.uniform(-2, 44, (25, 30))
    row = rng.uniform(-2, 40, (25, 30))
    col[0, :3] = np.nan
    col[1, 0], row[1, 1] = 0.25, 36.9  # half-pixel border zone (edge pixel repeated)
    out = np.empty((3, 25, 30), dtype)
    ok = np.empty((25, 30), bool)
    K.sample_image(img, valid, col, row, mode, out, ok)
    ref, ok_ref = K.sample_image_ref(img, valid, col, row, mode)
    assert np.array_equal(ok, ok_ref)
    assert ok.sum() > 300 and (~ok).sum() > 50
    np.testing.assert_allclose(out, ref, rtol=1e-6 if dtype == np.float32 else 1e-12, atol=1e-4)


def test_bilinear_reproduces_a_linear_image():
    """Pixel-corner convention: pixel [i, j] holds the value at (j + 0.5, i + 0.5)."""
    j = np.arange(20) + 0.5
    img = np.broadcast_to(j, (15, 20))[None].astype(np.float64).copy()
    col = np.array([[0.5, 3.25, 10.0, 19.5]])
    row = np.full_like(col, 7.3)
    out = np.empty((1, 1, 4))
    ok = np.empty((1, 4), bool)
    K.sample_image(img, np.ones((15, 20), np.uint8), col, row, K.BILINEAR, out, ok)
    assert ok.all()
    np.testing.assert_allclose(out[0, 0], col[0], atol=1e-12)


def test_occlusion_march_matches_reference():
    rng = np.random.default_rng(5)
    dsm = 100 + rng.normal(0, 0.2, (60, 70))
    dsm[20:30, 25:40] += 12.0
    dsm[45:50, 10:14] += 6.0
    dsm[5, 5] = np.nan
    ray_j = np.full(dsm.shape, 0.9) + rng.normal(0, 0.05, dsm.shape)
    ray_i = np.full(dsm.shape, -0.4)
    ray_i[:, 60:] = 0.0
    ray_j[:, 60:] = 0.0  # vertical rays: never occluded
    out = np.empty(dsm.shape, bool)
    K.occlusion_march(dsm, ray_j, ray_i, 0.5, 0.5, out)
    ref = K.occlusion_march_ref(dsm, ray_j, ray_i, 0.5, 0.5)
    assert out.sum() > 50
    assert np.array_equal(out, ref)
    assert not out[:, 60:].any()
