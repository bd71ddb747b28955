"""geocd._fft.fftconvolve against scipy.signal.fftconvolve, which it stands in for."""

import numpy as np
import pytest

from geocd._fft import fftconvolve


@pytest.mark.parametrize("dtype", [np.float64, np.float32, np.int32])
def test_equals_scipy_signal_bit_for_bit(dtype):
    from scipy import signal  # here, not at the top: 1.5 s of every pytest worker's collection

    rng = np.random.default_rng(0)
    # kernels smaller than the array (pointing's patch correlation) and larger (demdiff's covariance kernel)
    for shape_a, shape_k in (((41, 41), (25, 25)), ((57, 63), (31, 29)), ((9, 9), (9, 9)), ((30, 20), (59, 39))):
        a = (rng.normal(size=shape_a) * 10).astype(dtype)
        k = (rng.normal(size=shape_k) * 10).astype(dtype)
        for mode in ("full", "same", "valid"):
            if mode == "valid" and any(sk > sa for sa, sk in zip(shape_a, shape_k)):
                with pytest.raises(ValueError, match="inside"):
                    fftconvolve(a, k, mode)
                continue
            want = signal.fftconvolve(a, k, mode=mode)
            got = fftconvolve(a, k, mode)
            assert got.dtype == want.dtype
            np.testing.assert_array_equal(got, want, err_msg=f"{shape_a} {shape_k} {mode}")


def test_bad_calls_are_refused():
    with pytest.raises(ValueError, match="mode"):
        fftconvolve(np.ones((3, 3)), np.ones((2, 2)), "middle")
    with pytest.raises(ValueError, match="dimensions"):
        fftconvolve(np.ones((3, 3)), np.ones(2))
    with pytest.raises(ValueError, match="real"):
        fftconvolve(np.ones((3, 3), complex), np.ones((2, 2)))
