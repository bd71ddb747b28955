"""Every numba kernel of geocd.probchange agrees with its numpy reference."""

import math

import numpy as np
import pytest

from geocd.probchange import _kernels as K


def _stack(rng, n=4, h=23, w=31, nan_frac=0.05):
    s = rng.uniform(0, 255, (n, h, w)).astype(np.float32)
    s[rng.random(s.shape) < nan_frac] = np.nan
    return s


@pytest.mark.parametrize("r,bands,min_count", [(2, 1, 15), (1, 1, 1), (2, 3, 10), (0, 2, 1)])
def test_patch_mad(r, bands, min_count):
    rng = np.random.default_rng(r * 10 + bands)
    st = _stack(rng, n=2 * bands)
    ia = np.arange(bands, dtype=np.int64)
    ib = np.arange(bands, 2 * bands, dtype=np.int64)
    h, w = st.shape[1:]
    out = np.empty((h, w), np.float32)
    K.patch_mad(st, ia, ib, r, min_count, out, np.empty((h, w)), np.empty((h, w), np.int32))
    ref = K.patch_mad_ref(st, ia, ib, r, min_count)
    assert np.array_equal(np.isnan(out), np.isnan(ref))
    np.testing.assert_allclose(out[np.isfinite(out)], ref[np.isfinite(ref)], rtol=1e-5, atol=1e-4)


@pytest.mark.parametrize("none_prior", [0.0, 0.3])
def test_depth_logprob(none_prior):
    rng = np.random.default_rng(1)
    vol = rng.uniform(0, 60, (3, 17, 9, 11)).astype(np.float32)
    vol[rng.random(vol.shape) < 0.1] = np.nan
    vol[:, :, 0, 0] = np.nan  # a pixel with nothing observed
    sigma, S = 4.0, 90.0
    out = np.empty(vol.shape[1:], np.float32)
    kb = np.empty(vol.shape[2:], np.int32)
    ln = np.empty(vol.shape[2:], np.float32)
    K.depth_logprob(
        vol,
        1 / sigma,
        math.log(S / sigma),
        math.log(none_prior) if none_prior else -math.inf,
        math.log1p(-none_prior),
        out,
        kb,
        ln,
    )
    ref, kref, lnref = K.depth_logprob_ref(vol, sigma, S, none_prior)
    fin = np.isfinite(ref)
    assert np.array_equal(fin, np.isfinite(out))
    np.testing.assert_allclose(out[fin], ref[fin], rtol=1e-5, atol=1e-4)
    assert np.array_equal(kb, kref)
    np.testing.assert_allclose(ln[np.isfinite(lnref)], lnref[np.isfinite(lnref)], rtol=1e-5, atol=1e-4)
    # probabilities (with ∅) sum to 1 where observed
    tot = np.exp(out.astype(np.float64)).sum(axis=0) + np.exp(ln.astype(np.float64))
    np.testing.assert_allclose(tot[kb >= 0], 1.0, atol=1e-5)
    assert kb[0, 0] == -1


@pytest.mark.parametrize("eps", [0.0, 0.1])
def test_change_llr(eps):
    rng = np.random.default_rng(2)
    n, h, w = 12, 7, 8
    e = rng.normal(0, 3, (n, h, w))
    logp = (e - np.log(np.exp(e).sum(axis=0))).astype(np.float32)
    vol = rng.uniform(0, 50, (2, n, h, w)).astype(np.float32)
    vol[rng.random(vol.shape) < 0.1] = np.nan
    sigma, S = 5.0, 80.0
    llr = np.empty((h, w))
    cov = np.empty((h, w), np.float32)
    K.change_llr(
        logp, vol, 1 / sigma, math.log(S / sigma), math.log(eps) if eps else -math.inf, math.log1p(-eps), llr, cov
    )
    ref, cref = K.change_llr_ref(logp, vol, sigma, S, eps)
    np.testing.assert_allclose(llr, ref, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(cov, cref, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("shape,step", [((37, 29), 8), ((5, 6), 4), ((16, 1), 3), ((9, 9), 1)])
def test_lattice_to_pixels(shape, step):
    rng = np.random.default_rng(3)
    la = int(math.ceil((shape[0] - 1) / step)) + 1 if shape[0] > 1 else 1
    lb = int(math.ceil((shape[1] - 1) / step)) + 1 if shape[1] > 1 else 1
    lat = rng.normal(size=(la, lb))
    out = np.empty(shape)
    K.lattice_to_pixels(lat, step, out)
    np.testing.assert_allclose(out, K.lattice_to_pixels_ref(lat, step, shape), atol=1e-12)
    # nodes are reproduced exactly
    np.testing.assert_allclose(out[::step, ::step], lat[: out[::step, ::step].shape[0], : out[::step, ::step].shape[1]])


def test_splat_bilinear():
    rng = np.random.default_rng(4)
    m = 500
    fc = rng.uniform(-2, 21, m)
    fr = rng.uniform(-2, 16, m)
    v = rng.normal(size=m)
    fc[::37] = np.nan
    sw = np.zeros((15, 20))
    sv = np.zeros((15, 20))
    K.splat_bilinear(fc, fr, v, sw, sv)
    rw, rv = K.splat_bilinear_ref(fc, fr, v, (15, 20))
    np.testing.assert_allclose(sw, rw, atol=1e-12)
    np.testing.assert_allclose(sv, rv, atol=1e-12)


def test_zbuffer():
    rng = np.random.default_rng(5)
    m = 400
    col = rng.uniform(-1, 12, m)
    row = rng.uniform(-1, 9, m)
    z = rng.uniform(0, 10, m)
    z[::23] = np.nan
    buf = np.full((8, 11), -np.inf)
    K.zbuffer_max(col, row, z, buf)
    occ = np.zeros(m, bool)
    K.zbuffer_test(col, row, z, buf, 1.0, occ)
    rbuf, rocc = K.zbuffer_ref(col, row, z, (8, 11), 1.0)
    np.testing.assert_array_equal(buf, rbuf)
    np.testing.assert_array_equal(occ, rocc)
