"""A drone pair with strong barrel distortion (k1 = −0.26) over an AOI much larger than its footprints."""

import numpy as np
import pytest

from geocd.errors import ConfigError
from geocd.stereo import StereoParams, match_pair, prepare_chip


@pytest.fixture(scope="module")
def drone_pair():
    from synthetic import make_frame_scene

    sc = make_frame_scene()
    chips = [prepare_chip(im, name=n) for im, n in zip(sc.images, sc.names)]
    return sc, chips


@pytest.mark.slow
def test_distorted_frames_match_in_the_images_only(drone_pair):
    from synthetic import H0

    sc, chips = drone_pair
    pd = match_pair(
        chips[0],
        chips[1],
        sc.cameras[0],
        sc.cameras[1],
        sc.grid,
        params=StereoParams(height_range_m=(H0 - 20.0, H0 + 30.0)),
    )
    # the plane count comes from cells inside the images (≈ 2.2 px/m each here); cells beyond the fold
    # (thousands of px/m without the domain check) made the sweep run for hours
    assert pd.meta["jmax_px_per_m"] < 5.0
    assert pd.meta["evaluations"] < 1.0e8
    lon, lat = sc.grid.lonlat()
    inside = np.ones(sc.grid.shape, bool)
    for cam in sc.cameras:
        c, r = cam.project(lon, lat, np.where(pd.valid, pd.z_m, sc.truth))
        inside &= cam.in_image(c, r)
    assert not np.any(pd.valid & ~inside)  # every valid cell lands in both frames
    assert pd.flag_counts()["out_of_image"] > 0.5 * (~inside).sum()
    v = pd.valid & sc.visible
    assert v.sum() > 0.8 * sc.visible.sum()
    err = np.abs(pd.z_m - sc.truth)[v]
    assert np.median(err) < 0.1


def test_plane_count_has_a_hard_cap(scene, chips):
    p = StereoParams(height_range_m=(-300.0, 700.0), max_coarse_heights=256)  # ~1100 planes of 0.9 m, 1 level
    with pytest.raises(ConfigError, match="height planes"):
        match_pair(chips[0], chips[1], scene.cameras[0], scene.cameras[1], scene.grid, params=p)
