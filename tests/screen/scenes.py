"""Tiny synthetic pairs for the screen's tests: textured ground, a new roof in B, gain/noise between dates."""

from __future__ import annotations

import numpy as np
from scipy.ndimage import gaussian_filter


def texture(shape, seed, scale=2.0):
    rng = np.random.default_rng(seed)
    t = gaussian_filter(rng.standard_normal(shape), scale)
    return (t - t.min()) / (np.ptp(t) + 1e-9)


def pair(size=192, seed=0, box=(60, 110, 70, 130), rgb=False, gain=1.3, offset=0.05, noise=0.02):
    """(A, B, truth): B has a new flat roof (bright, with its own fine texture) in ``box`` = (r0, r1, c0, c1)."""
    rng = np.random.default_rng(seed + 100)
    ground = 0.35 + 0.4 * texture((size, size), seed)
    a = ground + noise * rng.standard_normal(ground.shape)
    b_scene = ground.copy()
    r0, r1, c0, c1 = box
    b_scene[r0:r1, c0:c1] = 0.85 + 0.1 * texture((r1 - r0, c1 - c0), seed + 1, 0.7)
    b = gain * b_scene + offset + noise * rng.standard_normal(ground.shape)
    truth = np.zeros((size, size), bool)
    truth[r0:r1, c0:c1] = True
    if rgb:
        a = np.stack([a * 0.9, a, a * 0.8])
        b = np.stack([b * 0.9, b, b * 0.8])
    else:
        a, b = a[None], b[None]
    return a.astype(np.float32), b.astype(np.float32), truth


def nochange(size=192, seed=0, gain=1.1, noise=0.02):
    """Two dates of the same ground (different noise, gain): the null pair."""
    rng = np.random.default_rng(seed + 200)
    ground = 0.35 + 0.4 * texture((size, size), seed)
    a = ground + noise * rng.standard_normal(ground.shape)
    b = gain * ground + noise * rng.standard_normal(ground.shape)
    return a[None].astype(np.float32), b[None].astype(np.float32)
