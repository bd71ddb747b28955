"""Projection onto the ground: footprints extruded, occlusion behind a building, weighted combination."""

from __future__ import annotations

import numpy as np
import pytest

from geocd.geodesy import AOIGrid
from geocd.landcover.project import (
    ProjectedView,
    building_surface,
    cell_pixels,
    combine_views,
    grid_to_image,
    project_view,
)

CRS = "EPSG:32631"
E0, N0 = 500000.0, 4800000.0


def _grid():
    return AOIGrid.from_bounds(E0, N0, E0 + 60, N0 + 60, 1.0, CRS)


def _building():
    import geopandas as gpd
    from shapely.geometry import box

    return gpd.GeoDataFrame({"height_m": [12.0]}, geometry=[box(E0 + 25, N0 + 25, E0 + 35, N0 + 35)], crs=CRS)


def test_building_surface_extrudes_and_occupies():
    g = _grid()
    dem = np.full(g.shape, 100.0)
    surf, occ = building_surface(dem, g, _building())
    assert surf.max() == 112.0 and (surf == 112.0).sum() == 100
    assert occ.sum() == pytest.approx(100.0)
    assert set(np.unique(occ)) == {0.0, 1.0}
    surf2, occ2 = building_surface(dem, g, None)
    assert (surf2 == 100.0).all() and not occ2.any()


def test_rays_meet_the_building_not_the_ground_behind():
    """An oblique camera east of a 12 m block: the block's roof is seen, the ground west of it is hidden."""
    from geocd.camera.frame import FrameCamera

    g = _grid()
    dem = np.full(g.shape, 100.0)
    surf, _ = building_surface(dem, g, _building())
    # camera 40 m above ground, 60 m east of the block's centre, looking west-down (about 56° off nadir)
    cam = FrameCamera(
        width=400,
        height=400,
        focal_px=300.0,
        position=(E0 + 90.0, N0 + 30.0, 140.0),
        opk_deg=(0.0, 56.0, 0.0),
        crs=CRS,
        vertical_datum="ellipsoid",
    )
    prob = np.full((400, 400), 0.7, np.float32)
    v = project_view(prob, cam, g, surf, name="oblique")
    rows, cols = np.indices(g.shape)
    x = cols + 0.5  # metres east of E0
    y = N0 + 60 - (rows + 0.5) - N0
    roof = (x > 25) & (x < 35) & (y > 25) & (y < 35)
    behind = (x > 8) & (x < 24) & (y > 27) & (y < 33)  # west of the block: its shadow from the camera
    assert v.observed[roof].mean() > 0.95
    assert v.observed[behind].mean() < 0.2
    assert np.isnan(v.values[behind & ~v.observed]).all()
    assert np.allclose(v.values[v.observed], 0.7, atol=1e-5)
    # without the building the same cells are seen
    v0 = project_view(prob, cam, g, dem)
    assert v0.observed[behind].mean() > 0.95
    # a window of the image is a smaller view
    vw = project_view(prob, cam, g, surf, window=(0, 0, 400, 200))
    assert 0 < vw.observed.sum() < v.observed.sum()


def test_combine_views_weighted():
    a = ProjectedView(
        values=np.array([[0.2, np.nan]], np.float32),
        observed=np.array([[True, False]]),
        weight=np.array([[1.0, 0.0]], np.float32),
    )
    b = ProjectedView(
        values=np.array([[0.8, np.nan]], np.float32),
        observed=np.array([[True, False]]),
        weight=np.array([[3.0, 0.0]], np.float32),
    )
    m, w, n = combine_views([a, b])
    assert m[0, 0] == pytest.approx(0.65) and np.isnan(m[0, 1])
    assert w[0, 0] == 4.0 and n.tolist() == [[2, 0]]


def test_cell_pixels_and_back():
    from geocd.camera.frame import FrameCamera

    g = _grid()
    dem = np.full(g.shape, 100.0)
    cam = FrameCamera(
        width=120,
        height=120,
        focal_px=1000.0,
        position=(E0 + 30.0, N0 + 30.0, 600.0),
        opk_deg=(0.0, 0.0, 0.0),
        crs=CRS,
        vertical_datum="ellipsoid",
    )
    rows, cols, obs = cell_pixels(cam, g, dem, (120, 120))
    assert obs.all()
    # nadir, 0.5 m pixels, north up: cell (r, c) is seen near pixel (2r + 1, 2c + 1)
    assert np.abs(rows - (2 * np.arange(60)[:, None] + 1)).max() <= 1
    assert np.abs(cols - (2 * np.arange(60)[None, :] + 1)).max() <= 1
    val = np.arange(3600, dtype=np.float32).reshape(60, 60)
    img = grid_to_image(val, rows, cols, obs, (120, 120))
    assert np.isfinite(img).all()
    assert img[61, 41] == val[30, 20]
