"""The 2-D screen: features, d_g, superpixels, exclusions, thresholds, on tiny synthetic pairs."""

from __future__ import annotations

import numpy as np
import pytest

from geocd.errors import ConfigError, EmptyDataError, GridError
from geocd.screen import (
    DaisyFeature,
    FeatureSpec,
    NullDistribution,
    PatchFeature,
    RandomBankFeature,
    ScreenParams,
    f1_scores,
    screen_pair,
    segment_mean,
    shift_image,
    spread_to_pixels,
    threshold_best_f1,
    threshold_from_nochange,
)
from geocd.screen.core import EXCL_SHADOW, EXCL_VEGETATION, normalise_image, vegetation_mask

from .scenes import nochange, pair

CLASSICAL = [PatchFeature(16), RandomBankFeature(16), DaisyFeature(16)]


@pytest.mark.parametrize("feat", CLASSICAL, ids=lambda f: f.name)
def test_features_are_unit_norm_per_cell_and_in_range(feat):
    a, b, _ = pair()
    xa, xb = feat.extract(normalise_image(a)[0]), feat.extract(normalise_image(b)[0])
    assert xa.shape[:2] == (12, 12) and xa.shape == xb.shape
    n = np.linalg.norm(xa, axis=-1)
    assert np.allclose(n, 1, atol=1e-5)
    d = np.linalg.norm(xa - xb, axis=-1)
    if feat.name == "patch":  # zero-mean patches: d in [0, 2]
        assert d.max() <= 2 + 1e-6
    else:  # rectified, non-negative: d in [0, √2]
        assert (xa >= 0).all() and d.max() <= np.sqrt(2) + 1e-6


@pytest.mark.parametrize("feat", CLASSICAL, ids=lambda f: f.name)
@pytest.mark.slow
def test_declared_context_makes_window_features_equal_whole_image_ones(feat):
    """What tiling relies on: cells at least context_px inside a window see what they see in the whole image."""
    c = feat.cell_px
    m = int(np.ceil(feat.context_px / c)) * c  # whole cells of margin
    r0, c0 = 2 * c, 3 * c
    img = normalise_image(pair(size=r0 + c0 + 7 * c + 2 * m)[1])[0]
    whole = feat.extract(img)
    win = img[:, r0 - 0 : r0 + 6 * c + 2 * m, c0 : c0 + 5 * c + 2 * m]
    part = feat.extract(win)
    k = m // c
    inner = part[k : part.shape[0] - k, k : part.shape[1] - k]
    ref = whole[r0 // c + k : r0 // c + k + inner.shape[0], c0 // c + k : c0 // c + k + inner.shape[1]]
    assert inner.size and np.allclose(inner, ref, atol=1e-5)


def test_screen_finds_a_new_roof_with_the_threshold_of_a_nochange_pair():
    a, b, truth = pair()
    p = ScreenParams(feature=FeatureSpec("patch", 16))
    res = screen_pair(a, b, gsd_m=0.5, params=p)
    na, nb = nochange()
    null = NullDistribution.from_values(screen_pair(na, nb, gsd_m=0.5, params=p).dissimilarity, "null")
    t = threshold_from_nochange(screen_pair(na, nb, gsd_m=0.5, params=p).dissimilarity, 1.0, d_test=res.dissimilarity)
    assert t > null.threshold(1.0)  # Otsu's split above the null quantile binds here (the halo), not the noise
    s = f1_scores(res.dissimilarity > t, truth, res.valid)
    assert s["f1"] > 0.85, s
    s_noise = f1_scores(res.dissimilarity > null.threshold(1.0), truth, res.valid)
    assert s_noise["f1"] < s["f1"] - 0.2  # the bare 99 % quantile flags the grid's halo around the roof
    conf = null.confidence_pct(res.dissimilarity)
    assert np.nanmedian(conf[truth]) > 99 and np.nanmedian(conf[~truth]) < 90


def test_superpixels_sharpen_the_coarse_grid():
    """Felzenszwalb follows the roof's edges: better F1 at the best threshold than the bilinear grid alone
    (SLIC on a grey image: no worse)."""
    a, b, truth = pair(box=(52, 101, 61, 123))  # edges off the 16 px lattice
    f = {}
    for sp in ("none", "felzenszwalb", "slic"):
        r = screen_pair(a, b, gsd_m=0.5, params=ScreenParams(feature=FeatureSpec("patch", 16), superpixels=sp))
        f[sp] = threshold_best_f1([r.dissimilarity], [truth])[1]
    assert f["felzenszwalb"] > f["none"] + 0.04 and f["slic"] >= f["none"] - 0.01, f


def test_randbank_and_daisy_tolerate_two_pixels_of_misregistration():
    a, b, truth = pair()
    for kind in ("randbank", "daisy"):
        p = ScreenParams(feature=FeatureSpec(kind, 16))
        f0 = threshold_best_f1([screen_pair(a, b, gsd_m=0.5, params=p).dissimilarity], [truth])[1]
        f2 = threshold_best_f1([screen_pair(a, shift_image(b, 2.0), gsd_m=0.5, params=p).dissimilarity], [truth])[1]
        assert f0 > 0.75 and f2 > f0 - 0.1, (kind, f0, f2)


def test_vegetation_and_shadow_seen_in_both_dates_are_set_aside():
    a, b, truth = pair(rgb=True)
    veg = np.zeros(truth.shape, bool)
    veg[10:40, 10:60] = True
    sh = np.zeros(truth.shape, bool)
    sh[150:180, 120:180] = True
    for img, other in ((a, b), (b, a)):
        img[:, veg] = np.array([0.2, 0.6, 0.15])[:, None]  # green in both dates (another season: other shade)
        img[:, sh] *= 0.15  # cast shadow in both dates
    b[1, veg] = 0.45
    p = ScreenParams(feature=FeatureSpec("patch", 16))
    r = screen_pair(a, b, gsd_m=0.5, params=p, band_names_a=("red", "green", "blue"))
    assert (r.excluded[veg] & EXCL_VEGETATION).mean() > 0.9
    assert (r.excluded[sh] & EXCL_SHADOW).mean() > 0.9
    assert np.nanmax(r.dissimilarity[veg & (r.excluded > 0)]) == 0
    assert not (r.excluded[truth] & EXCL_VEGETATION).any()
    off = screen_pair(a, b, gsd_m=0.5, params=p.replace(vegetation="off", shadow="off"))
    assert (off.excluded == 0).all()
    assert vegetation_mask(normalise_image(a[:1])[0], np.ones(truth.shape, bool)) is None  # grey: no vegetation


def test_bad_inputs_fail_or_are_brought_together():
    a, b, _ = pair()
    with pytest.raises(GridError, match="one grid"):
        screen_pair(a, b[:, :100], gsd_m=0.5)
    with pytest.raises(GridError, match="smaller than one grid cell"):
        screen_pair(a[:, :8, :8], b[:, :8, :8], gsd_m=0.5)
    rgb = np.concatenate([b, b, b])
    r = screen_pair(a, rgb, gsd_m=0.5, params=ScreenParams(feature=FeatureSpec("patch", 16)))
    assert any("grey" in n for n in r.notes)
    with pytest.raises(ConfigError, match="weights"):
        FeatureSpec(kind="cnn", backbone="vgg19")
    with pytest.raises(ConfigError, match="unknown grid feature"):
        FeatureSpec(kind="sift")
    with pytest.raises(EmptyDataError):
        NullDistribution.from_values(np.full(50, np.nan))


def test_spread_and_segment_mean():
    d = np.array([[0.0, 1.0], [np.nan, 1.0]], np.float32)
    p = spread_to_pixels(d, (4, 4), 2)
    assert p[0, 0] == 0 and p[0, 3] == 1 and np.isnan(p[3, 0]) and np.isfinite(p).sum() == 15
    assert p[2, 1] == pytest.approx(4 / 7)  # the NaN corner's weight goes to the others
    assert np.allclose(spread_to_pixels(d, (4, 4), 2, "nearest")[2:, :2], np.nan, equal_nan=True)
    lab = np.array([[0, 0, 1], [0, 1, 1]])
    v = np.array([[1.0, 3.0, 5.0], [np.nan, 7.0, 9.0]])
    m = segment_mean(v, lab)
    assert np.allclose(m, [[2, 2, 7], [2, 7, 7]])


def test_null_distribution_threshold_and_confidence():
    v = np.linspace(0, 1, 10001)
    n = NullDistribution.from_values(v)
    assert n.threshold(1.0) == pytest.approx(0.99, abs=1e-3)
    assert n.confidence_pct(np.array([0.5, 0.995, np.nan]))[:2] == pytest.approx([50, 99.5], abs=0.05)
    with pytest.raises(ConfigError, match="percent"):
        n.threshold(0.0)
    t, f = threshold_best_f1([np.array([0.1, 0.2, 0.8, 0.9])], [np.array([0, 0, 1, 1], bool)])
    assert 0.2 <= t < 0.8 and f == 1.0


def test_a_view_shared_by_two_pairs_is_described_and_segmented_once():
    """The cross-date and the no-change pair share a view: its features and superpixels are reused, by content,
    and the results are those of a fresh computation."""
    from unittest import mock

    import geocd.screen.core as core

    a, b, _ = pair()
    na, _ = nochange()
    p = ScreenParams(feature=FeatureSpec("patch", 16))
    core._MEMO.clear()
    with mock.patch.object(core, "superpixels", wraps=core.superpixels) as sp:
        r1 = screen_pair(a, b, gsd_m=0.5, params=p)
        r2 = screen_pair(na, b, gsd_m=0.5, params=p)  # b again: segmented once
        assert sp.call_count == 3
    core._MEMO.clear()
    fresh = screen_pair(na, b, gsd_m=0.5, params=p)
    np.testing.assert_array_equal(r2.dissimilarity, fresh.dissimilarity)
    np.testing.assert_array_equal(r1.cell_dissimilarity, screen_pair(a, b, gsd_m=0.5, params=p).cell_dissimilarity)
    # another setting is another entry
    with mock.patch.object(core, "superpixels", wraps=core.superpixels) as sp:
        screen_pair(na, b, gsd_m=0.5, params=ScreenParams(feature=FeatureSpec("patch", 16), fz_scale=50.0))
        assert sp.call_count == 2
