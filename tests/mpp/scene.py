"""A tiny two-date scene of gabled buildings with shadows, for the marked point process tests."""

from __future__ import annotations

import numpy as np
from scipy import ndimage

POSTING = 0.5


def _rect_mask(shape, cx, cy, L, l, th):
    ii, jj = np.mgrid[0:shape[0], 0:shape[1]].astype(float)
    c, s = np.cos(th), np.sin(th)
    u = (jj - cx) * c - (ii - cy) * s
    v = (jj - cx) * s + (ii - cy) * c
    return (np.abs(u) <= L / 2) & (np.abs(v) <= l / 2), v


def make_pair(seed: int = 0, size: int = 200, colour: bool = False):
    """Two images (date A, date B), their DSMs and truth masks.

    Date A has buildings 0–4, date B buildings 1–5 (building 0 demolished, building 5 new). Returns a
    dict with image_a, image_b ((bands,) rows, cols float32), dsm_a, dsm_b, ground, truth_a, truth_b
    (bool), and the building list (cx, cy, L, l, θ) in cells.
    """
    rng = np.random.default_rng(seed)
    shape = (size, size)
    blds = [(45, 50, 26, 18, 0.2), (140, 45, 30, 20, 0.2), (60, 140, 22, 22, 0.25), (150, 135, 34, 18, 0.2),
            (100, 95, 20, 16, 0.22), (100, 170, 28, 18, 0.2)]
    ground = 100.0 + 0.01 * np.arange(size)[None, :] + np.zeros(shape)
    tex = ndimage.gaussian_filter(rng.normal(0, 1, shape), 1.5)
    tex = 110 + 25 * tex / tex.std()
    out = {"buildings": blds, "ground": ground}
    for date, ids, gain, sun in (("a", range(0, 5), 1.0, (3, 2)), ("b", range(1, 6), 1.15, (2, 3))):
        img = tex.copy()
        dsm = ground.copy()
        truth = np.zeros(shape, bool)
        shadow = np.zeros(shape, bool)
        for k in ids:
            cx, cy, L, l, th = blds[k]
            m, v = _rect_mask(shape, cx, cy, L, l, th)
            sh = ndimage.shift(m.astype(float), sun, order=0) > 0.5
            shadow |= sh & ~m
            truth |= m
        img[shadow] = 45
        for k in ids:
            cx, cy, L, l, th = blds[k]
            m, v = _rect_mask(shape, cx, cy, L, l, th)
            img[m & (v >= 0)] = 200
            img[m & (v < 0)] = 165
            dsm[m] += 7.0
        img = gain * img + rng.normal(0, 3, shape)
        out[f"image_{date}"] = (np.stack([img * 1.05, img, img * 0.9]) if colour else img[None]).astype(np.float32)
        out[f"dsm_{date}"] = (dsm + rng.normal(0, 0.2, shape)).astype(np.float32)
        out[f"truth_{date}"] = truth
    return out
