"""A tiny two-date scene of gabled buildings with shadows, for the marked point process tests."""

from __future__ import annotations

import numpy as np
from scipy import ndimage

POSTING = 0.5


def _rect_mask(shape, cx, cy, L, l, th):
    ii, jj = np.mgrid[0 : shape[0], 0 : shape[1]].astype(float)
    c, s = np.cos(th), np.sin(th)
    u = (jj - cx) * c - (ii - cy) * s
    v = (jj - cx) * s + (ii - cy) * c
    return (np.abs(u) <= L / 2) & (np.abs(v) <= l / 2), v


#: clumps of tree crowns (cx, cy in cells, crown radius in cells), on both dates, clear of the buildings
TREES = [(20, 100, 6), (30, 108, 6), (24, 118, 6), (110, 140, 7), (121, 148, 6), (185, 70, 6), (182, 83, 6)]


def make_pair(seed: int = 0, size: int = 200, colour: bool = False, trees: bool = False):
    """Two images (date A, date B), their DSMs and truth masks.

    ``trees``: clumps of tree crowns (:data:`TREES`) — raised domes, rough at the cell scale in the DSM (leaves
    and gaps: ±1 m), dark and mottled in the image, each casting a shadow.

    Date A has buildings 0–4, date B buildings 1–5 (building 0 demolished, building 5 new). Returns a
    dict with image_a, image_b ((bands,) rows, cols float32), dsm_a, dsm_b, ground, truth_a, truth_b
    (bool), and the building list (cx, cy, L, l, θ) in cells.
    """
    rng = np.random.default_rng(seed)
    shape = (size, size)
    blds = [
        (45, 50, 26, 18, 0.2),
        (140, 45, 30, 20, 0.2),
        (60, 140, 22, 22, 0.25),
        (150, 135, 34, 18, 0.2),
        (100, 95, 20, 16, 0.22),
        (100, 170, 28, 18, 0.2),
    ]
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
        crowns = np.zeros(shape, bool)
        if trees:
            ii, jj = np.mgrid[0:size, 0:size].astype(float)
            trng = np.random.default_rng(100 + seed)  # the same trees on both dates
            for cx, cy, r in TREES:
                d2 = ((jj - cx) ** 2 + (ii - cy) ** 2) / r**2
                m = d2 <= 1.0
                crowns |= m
                shadow |= (ndimage.shift(m.astype(float), sun, order=0) > 0.5) & ~m
            tree_h = np.zeros(shape)
            for cx, cy, r in TREES:
                d2 = ((jj - cx) ** 2 + (ii - cy) ** 2) / r**2
                tree_h = np.maximum(tree_h, np.where(d2 <= 1.0, 6.0 * np.sqrt(np.clip(1 - d2, 0, 1)) + 2.0, 0.0))
            tree_h += np.where(crowns, trng.normal(0.0, 1.0, shape), 0.0)
            leaf = 80 + 30 * trng.random(shape)
        img[shadow] = 45
        if trees:
            img[crowns] = leaf[crowns]
            dsm = np.maximum(dsm, ground + tree_h)
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


def make_mound(seed: int = 0, size: int = 160):
    """One date (used as both): a building with walls (7 m) and a mound — a bare-earth patch as homogeneous
    as a roof, raised 5 m on a flat top whose sides slope 0.3 (17°) to the ground, planar everywhere.

    Returns image (1, size, size) float32, dsm float32, ground, and the masks of the building and of the mound
    where it stands over 2.5 m (bool).
    """
    rng = np.random.default_rng(seed)
    shape = (size, size)
    ground = 100.0 + np.zeros(shape)
    tex = ndimage.gaussian_filter(rng.normal(0, 1, shape), 1.5)
    img = 110 + 25 * tex / tex.std()
    dsm = ground.copy()
    b, v = _rect_mask(shape, 45, 45, 28, 20, 0.2)
    dsm[b] += 7.0
    img[b & (v >= 0)] = 200
    img[b & (v < 0)] = 165
    ii, jj = np.mgrid[0:size, 0:size].astype(float)
    d = np.maximum(np.maximum(np.abs(jj - 108) - 12, np.abs(ii - 108) - 9), 0.0)  # cells from a 24 × 18 top
    mound = np.clip(5.0 - 0.3 * POSTING * d, 0.0, None)
    dsm += mound
    img[mound > 2.0] = 185
    img = img + rng.normal(0, 3, shape)
    dsm = dsm + rng.normal(0, 0.2, shape)
    return img[None].astype(np.float32), dsm.astype(np.float32), ground, b, mound > 2.5
