"""A numba selection helper shared by the kernels of several methods."""

from __future__ import annotations

from numba import njit


@njit(cache=True, inline="always")
def select_kth(buf, n, k):
    """The k-th smallest of ``buf[:n]`` (0-based), partially reordering it (Wirth's selection); afterwards
    ``buf[:k]`` holds values ≤ it."""
    lo = 0
    hi = n - 1
    while lo < hi:
        x = buf[k]
        i = lo
        j = hi
        while True:
            while buf[i] < x:
                i += 1
            while x < buf[j]:
                j -= 1
            if i <= j:
                t = buf[i]
                buf[i] = buf[j]
                buf[j] = t
                i += 1
                j -= 1
            if i > j:
                break
        if j < k:
            lo = i
        if k < i:
            hi = j
    return buf[k]
