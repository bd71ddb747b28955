"""FFT convolution shared by several methods, without importing ``scipy.signal``.

``scipy.signal`` costs about 1.5 s of start-up (it imports ``scipy.stats``); :func:`fftconvolve` makes the same
``scipy.fft`` calls on the same padded shapes as ``scipy.signal.fftconvolve`` for real arrays, so it returns the
same numbers bit for bit.
"""

from __future__ import annotations

import numpy as np
from scipy import fft as sp_fft


def _real(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x)
    if x.dtype.kind == "c":
        raise ValueError("fftconvolve takes real arrays")
    return x if x.dtype.kind == "f" else x.astype(np.float64)


def fftconvolve(a: np.ndarray, kernel: np.ndarray, mode: str = "full") -> np.ndarray:
    """Linear convolution of the real N-d arrays ``a`` and ``kernel`` by FFT.

    Parameters
    ----------
    a, kernel : real arrays of the same number of dimensions
    mode : "full" (A + K - 1 per axis), "same" (A, centred as scipy centres it) or "valid" (A - K + 1, where
        the kernel lies wholly inside ``a``; needs A ≥ K on every axis)

    Returns
    -------
    ``scipy.signal.fftconvolve(a, kernel, mode)`` bit for bit: float32 when both are float32, else float64.
    """
    if a.ndim != kernel.ndim:
        raise ValueError(f"a has {a.ndim} dimensions and kernel {kernel.ndim}")
    if mode == "valid" and any(k > n for n, k in zip(a.shape, kernel.shape)):
        raise ValueError(f"mode 'valid' needs the kernel {kernel.shape} inside a {a.shape}")
    full = [n + k - 1 for n, k in zip(a.shape, kernel.shape)]
    fshape = [sp_fft.next_fast_len(n, True) for n in full]
    axes = tuple(range(a.ndim))
    spec = sp_fft.rfftn(_real(a), fshape, axes=axes)
    spec *= sp_fft.rfftn(_real(kernel), fshape, axes=axes)
    ret = sp_fft.irfftn(spec, fshape, axes=axes)[tuple(slice(n) for n in full)]
    if mode == "full":
        return ret
    if mode == "same":
        out = a.shape
    elif mode == "valid":
        out = tuple(n - k + 1 for n, k in zip(a.shape, kernel.shape))
    else:
        raise ValueError(f"mode must be 'full', 'same' or 'valid', got {mode!r}")
    start = [(f - o) // 2 for f, o in zip(full, out)]
    return ret[tuple(slice(s, s + o) for s, o in zip(start, out))]
