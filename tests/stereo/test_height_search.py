"""The height search must not silently cut the scene's heights (tall structures on a plateau)."""

import numpy as np
import pytest
from scipy import ndimage

from geocd.stereo.match import confident_coherent, interval_margin_m, robust_height_interval


def _planes(z: np.ndarray) -> dict:
    """Coarse-level planes with every finite height a confident match."""
    return {"z_raw": z, "best_c": np.where(np.isfinite(z), 0.1, np.nan)}


def _plateau_and_pyramid(n=80, apex=140.0, base=200.0, half=10):
    """A 80 × 80-cell coarse level: a plateau at 200 m and a small steep pyramid (few cells near the apex)."""
    i, j = np.mgrid[0:n, 0:n]
    d = np.maximum(np.abs(i - n / 2), np.abs(j - n / 2))
    z = base + 0.5 * np.sin(i / 5.0) + np.maximum(0.0, apex * (1 - d / half))
    return z


def test_interval_keeps_a_thin_apex():
    z = _plateau_and_pyramid()
    lo, hi = np.full(z.shape, -300.0), np.full(z.shape, 700.0)
    p = _planes(z)
    # as the matcher does: margin from the level's own slopes (8 m cells, 4 m steps, 7-cell window)
    margin = interval_margin_m(p, confident_coherent(p, 40.0), 8.0, 4.0, 3)
    iv = robust_height_interval(p, lo, hi, bin_m=40.0, margin_m=margin)
    assert iv is not None
    # the old rule (grow while a bin holds ≥ 10 % of the fullest one, one bin of margin) stopped at 260 m,
    # 80 m below this apex; the bins above hold 168, 96 and 24 matches against 6111 on the plateau
    assert iv[0] <= z.min() and iv[1] >= z.max()
    assert iv[1] - iv[0] < 500.0  # and still narrows the 1000 m range
    # without a margin the apex cell itself (alone, too steep to be coherent) is just above the last bin
    iv0 = robust_height_interval(p, lo, hi, bin_m=40.0, margin_m=0.0)
    assert iv0[1] >= z.max() - 1.0


def test_interval_ignores_a_small_false_cluster_apart_and_keeps_a_high_roof():
    z = _plateau_and_pyramid(apex=0.0)
    z[5:8, 5:8] = 520.0  # 9 cells of coherent false matches, far above
    lo, hi = np.full(z.shape, -300.0), np.full(z.shape, 700.0)
    iv = robust_height_interval(_planes(z), lo, hi, bin_m=40.0, margin_m=0.0, window=7)
    assert iv is not None and iv[1] < 300.0
    z[50:70, 50:70] = 420.0  # a flat roof (400 cells > (2·7 − 1)²) with empty bins below
    iv = robust_height_interval(_planes(z), lo, hi, bin_m=40.0, margin_m=0.0, window=7)
    assert iv is not None and iv[1] >= 420.0 and iv[1] < 500.0


@pytest.fixture(scope="module")
def ziggurat():
    from synthetic import H0, make_surface_scene, pyramid_dsm

    # 7 terraces, 20 m each, apex 140 m above a rolling plateau, in a 360 m AOI; the cameras' RPC height range
    # (±500 m) is all the matcher is told
    f = pyramid_dsm(140.0, 110.0, steps=7)
    return make_surface_scene(
        f,
        size_m=360.0,
        posting_m=1.0,
        gsd_m=1.0,
        parallax_a=(0.45, 0.03),
        parallax_b=(-0.405, 0.01),
        h_range=(H0 - 10.0, H0 + 160.0),
        height_scale_m=500.0,
    )


@pytest.mark.slow
def test_tall_structure_is_not_cut_by_the_coarse_interval(ziggurat):
    from geocd.stereo import StereoParams, match_pair, prepare_chip

    sc = ziggurat
    chips = [prepare_chip(im, name=n) for im, n in zip(sc.images, sc.names)]
    pd = match_pair(chips[0], chips[1], sc.cameras[0], sc.cameras[1], sc.grid)
    iv = pd.meta["coarse_interval_m"]
    assert iv[0] <= float(sc.truth.min()) and iv[1] >= float(sc.truth.max())
    err = pd.z_m - sc.truth
    # the top terrace (away from its edges): all there, none off by more than 1 m (was ~100 m too low)
    top = ndimage.binary_erosion(sc.truth > sc.truth.max() - 1.0, np.ones((9, 9), bool))
    assert top.sum() > 300
    assert pd.valid[top].mean() > 0.95
    assert np.all(np.abs(err[top & pd.valid]) <= 1.0)
    # no more bad valid cells than when the user gives a tight range around the truth (no narrowing at all)
    wide = match_pair(
        chips[0], chips[1], sc.cameras[0], sc.cameras[1], sc.grid, params=StereoParams(height_range_m=(180.0, 380.0))
    )
    bad = int((np.abs(err[pd.valid]) > 1.0).sum())
    bad_wide = int((np.abs((wide.z_m - sc.truth)[wide.valid]) > 1.0).sum())
    assert bad <= 1.1 * bad_wide, (bad, bad_wide)
    assert pd.valid.mean() >= wide.valid.mean() - 0.02
