"""Bad inputs give clear errors or warnings, never silent garbage."""

import numpy as np
import pytest
from synthetic import affine_rpc

from geocd.camera import Camera
from geocd.errors import ConfigError, CRSError, EmptyDataError, NoOverlapError
from geocd.geodesy import AOIGrid
from geocd.stereo import FLAGS, ImageChip, StereoGeometryWarning, StereoParams, match_pair, prepare_chip


class NoRangeCamera(Camera):
    """A camera without a height range (like a frame camera), delegating to another."""

    kind = "test-norange"

    def __init__(self, inner):
        self.inner = inner
        self.width, self.height = inner.width, inner.height

    def project(self, lon, lat, h):
        return self.inner.project(lon, lat, h)

    def localize(self, col, row, h):
        return self.inner.localize(col, row, h)

    def dproj_dh(self, lon, lat, h):
        return self.inner.dproj_dh(lon, lat, h)

    def to_dict(self):
        return {"kind": self.kind}

    @classmethod
    def from_dict(cls, d):  # pragma: no cover
        raise NotImplementedError


def test_non_overlapping_pair(scene, chips):
    far = affine_rpc(
        0.5, (-0.45, 0.02), scene.cameras[1].width, scene.cameras[1].height, centre_px=(3000.0, 3000.0)
    )  # looks 1.5 km away
    with pytest.raises(NoOverlapError, match="do not overlap"):
        match_pair(chips[0], chips[1], scene.cameras[0], far, scene.grid)


def test_no_height_range(scene, chips):
    cams = [NoRangeCamera(c) for c in scene.cameras]
    with pytest.raises(ConfigError, match="no height search range"):
        match_pair(chips[0], chips[1], cams[0], cams[1], scene.grid)
    # a DEM or an explicit range fixes it
    pd = match_pair(
        chips[0], chips[1], cams[0], cams[1], scene.grid, params=StereoParams(height_range_m=(190.0, 220.0))
    )
    assert pd.completeness > 0.8


def test_fully_nodata_image(scene, chips):
    with pytest.raises(EmptyDataError, match="nodata"):
        prepare_chip(scene.images[0], valid=np.zeros(scene.images[0].shape, bool))
    empty = ImageChip(np.full((50, 50), np.nan, np.float32), name="empty")
    with pytest.raises(EmptyDataError, match="nodata"):
        match_pair(chips[0], empty, scene.cameras[0], scene.cameras[1], scene.grid)


def test_image_nodata_over_the_aoi_only(scene, chips):
    """An image valid elsewhere but nodata where the AOI is: no overlap."""
    data = chips[1].data.copy()
    data[:, :] = np.nan
    data[:5, :5] = 100.0
    with pytest.raises(NoOverlapError):
        match_pair(chips[0], ImageChip(data, name="corner"), scene.cameras[0], scene.cameras[1], scene.grid)


def test_degenerate_base_warns_and_invalidates(scene, chips):
    # the second view looks from (almost) the same direction as the first
    twin = affine_rpc(0.5, (0.56, 0.05), scene.cameras[1].width, scene.cameras[1].height)
    with pytest.warns(StereoGeometryWarning, match="base/height"):
        pd = match_pair(chips[0], chips[1], scene.cameras[0], twin, scene.grid)
    assert not pd.valid.any()
    assert np.all(pd.flags & FLAGS["weak_geometry"])
    assert np.nanmax(pd.g_px_per_m) < 0.02


def test_weak_geometry_partially(scene, chips):
    """A base/height threshold above the pair's invalidates with a warning (g-based)."""
    with pytest.warns(StereoGeometryWarning):
        pd = match_pair(
            chips[0], chips[1], scene.cameras[0], scene.cameras[1], scene.grid, params=StereoParams(min_base_height=0.6)
        )
    assert not pd.valid.any()


def test_geographic_grid_refused(scene, chips):
    g = AOIGrid.from_bounds(5.29, 44.09, 5.31, 44.11, 1e-4, "EPSG:4326")
    with pytest.raises(CRSError, match="projected"):
        match_pair(chips[0], chips[1], scene.cameras[0], scene.cameras[1], g)


def test_bad_params():
    with pytest.raises(ConfigError, match="odd"):
        StereoParams(window=6)
    with pytest.raises(ConfigError, match="empty"):
        StereoParams(height_range_m=(10.0, 5.0))
    with pytest.raises(ConfigError, match="score"):
        StereoParams(score="census")
    p = StereoParams(height_range_m=(1, 2))
    assert StereoParams.from_dict(p.to_dict()) == p
