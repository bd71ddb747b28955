"""geodesy: ECEF/ENU frames, geoid undulations against PROJ, AOI grids, vertical-datum errors."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
from affine import Affine
from pyproj import CRS, Transformer

from geocd import geodesy as G
from geocd.errors import CRSError, GridError, NoOverlapError, VerticalDatumError

EGM96_GTX = Path("/usr/share/proj/egm96_15.gtx")
needs_egm96 = pytest.mark.skipif(G.find_geoid_grid("egm96") is None, reason="EGM96 geoid grid not installed")


def random_geodetic(n: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    lon = rng.uniform(-180, 180, n)
    lat = np.degrees(np.arcsin(rng.uniform(-0.999, 0.999, n)))
    h = rng.uniform(-500, 9000, n)
    return lon, lat, h


# ------------------------------------------------------------------------------------------
# ECEF and ENU
# ------------------------------------------------------------------------------------------
def test_ecef_matches_pyproj():
    lon, lat, h = random_geodetic(500)
    t = Transformer.from_crs("EPSG:4979", "EPSG:4978", always_xy=True)
    xr, yr, zr = t.transform(lon, lat, h)
    x, y, z = G.geodetic_to_ecef(lon, lat, h)
    np.testing.assert_allclose(x, xr, atol=1e-6)
    np.testing.assert_allclose(y, yr, atol=1e-6)
    np.testing.assert_allclose(z, zr, atol=1e-6)
    lo, la, hh = G.ecef_to_geodetic(x, y, z)
    np.testing.assert_allclose(lo, lon, atol=1e-11)
    np.testing.assert_allclose(la, lat, atol=1e-11)
    np.testing.assert_allclose(hh, h, atol=1e-6)


@pytest.mark.parametrize("origin", [(24.4, -33.7, 500.0), (2.35, 48.85, 35.0), (-120.0, 79.0, 0.0)])
def test_enu_round_trip_1e6_m(origin):
    frame = G.LocalFrame(*origin)
    rng = np.random.default_rng(1)
    e, n, u = rng.uniform(-20000, 20000, 300), rng.uniform(-20000, 20000, 300), rng.uniform(-200, 3000, 300)
    lon, lat, h = frame.from_enu(e, n, u)
    e2, n2, u2 = frame.to_enu(lon, lat, h)
    assert max(np.abs(e2 - e).max(), np.abs(n2 - n).max(), np.abs(u2 - u).max()) < 1e-6
    # and starting from geodetic points near the origin
    lon = origin[0] + rng.uniform(-0.1, 0.1, 300)
    lat = origin[1] + rng.uniform(-0.1, 0.1, 300)
    h = rng.uniform(-100, 3000, 300)
    lo, la, hh = frame.from_enu(*frame.to_enu(lon, lat, h))
    x0, y0, z0 = G.geodetic_to_ecef(lon, lat, h)
    x1, y1, z1 = G.geodetic_to_ecef(lo, la, hh)
    assert np.sqrt((x1 - x0) ** 2 + (y1 - y0) ** 2 + (z1 - z0) ** 2).max() < 1e-6


def test_enu_axes():
    frame = G.LocalFrame(24.4, -33.7, 100.0)
    e, n, u = frame.to_enu(24.4, -33.7, 150.0)
    assert (float(e), float(n), float(u)) == pytest.approx((0.0, 0.0, 50.0), abs=1e-6)
    e, n, u = frame.to_enu(24.4, -33.7 + 0.001, 100.0)
    assert float(n) == pytest.approx(110.9, abs=0.5) and abs(float(e)) < 1e-6 and float(u) < 0
    e, n, u = frame.to_enu(24.401, -33.7, 100.0)
    assert float(e) == pytest.approx(92.7, abs=0.5) and abs(float(n)) < 1e-3


# ------------------------------------------------------------------------------------------
# CRS helpers
# ------------------------------------------------------------------------------------------
def test_lonlat_round_trip_and_utm():
    crs = G.utm_crs_for(24.4, -33.7)
    assert crs.to_epsg() == 32735
    assert G.utm_crs_for(2.35, 48.85).to_epsg() == 32631
    lon, lat, _ = random_geodetic(50, seed=3)
    lon = 24.4 + (lon / 180) * 2
    lat = -33.7 + (lat / 90) * 2
    x, y = G.from_lonlat(lon, lat, crs)
    lo, la = G.to_lonlat(x, y, crs)
    np.testing.assert_allclose(lo, lon, atol=1e-10)
    np.testing.assert_allclose(la, lat, atol=1e-10)
    # EPSG:4326 is lat/lon by the book; geocd is always (x, y) = (lon, lat)
    lo, la = G.to_lonlat(lon, lat, "EPSG:4326")
    np.testing.assert_array_equal(lo, lon)


def test_as_crs_and_vertical_datum_of():
    with pytest.raises(CRSError, match="EPSG"):
        G.as_crs("not a crs")
    assert G.as_crs(None).to_epsg() == 4326
    assert G.vertical_datum_of("EPSG:32735+5773") == "egm96"
    assert G.vertical_datum_of("EPSG:32735+3855") == "egm2008"
    assert G.vertical_datum_of("EPSG:4979") == "ellipsoid"
    assert G.vertical_datum_of("EPSG:32735", default="x") == "x"
    assert G.horizontal_crs("EPSG:32735+5773").to_epsg() == 32735
    assert G.normalize_datum_name("EGM-2008") == "egm2008"
    assert G.normalize_datum_name("WGS84") == "ellipsoid"


# ------------------------------------------------------------------------------------------
# geoid undulation against PROJ
# ------------------------------------------------------------------------------------------
def proj_egm96_undulation(lon, lat):
    """N from PROJ's vgridshift on the same grid file (independent interpolation)."""
    t = Transformer.from_pipeline(
        "+proj=pipeline +step +proj=unitconvert +xy_in=deg +xy_out=rad "
        f"+step +proj=vgridshift +grids={EGM96_GTX} +multiplier=1 "
        "+step +proj=unitconvert +xy_in=rad +xy_out=deg"
    )
    _, _, z = t.transform(lon, lat, np.zeros_like(lon))
    return np.asarray(z)


@pytest.mark.skipif(not EGM96_GTX.is_file(), reason=f"{EGM96_GTX} not installed")
def test_geoid_undulation_matches_proj_vgridshift():
    lon, lat, _ = random_geodetic(3000, seed=4)
    lat = np.clip(lat, -89.0, 89.0)
    # seams and special places: the antimeridian, Greenwich, grid nodes, the study site
    lon = np.r_[lon, 179.999, -179.999, 180.0, -180.0, 0.0, 0.125, 24.4]
    lat = np.r_[lat, 10.0, 10.0, 10.0, 10.0, 51.5, 0.25, -33.7]
    n = G.geoid_undulation(lon, lat, "egm96")
    ref = proj_egm96_undulation(lon, lat)
    assert np.abs(n - ref).max() <= 0.01
    assert G.geoid_undulation(24.4, -33.7, "EGM96") == pytest.approx(28.33, abs=0.05)


@needs_egm96
def test_geoid_undulation_nan_and_shapes():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        n = G.geoid_undulation(np.array([[24.4, np.nan]]), np.array([[-33.7, -33.7]]), "egm96")
    assert n.shape == (1, 2) and np.isfinite(n[0, 0]) and np.isnan(n[0, 1])
    assert np.all(G.geoid_undulation([1.0, 2.0], [3.0, 4.0], "ellipsoid") == 0)


@needs_egm96
def test_to_ellipsoidal():
    h = G.to_ellipsoidal(np.array([100.0, 200.0]), [24.4, 24.4], [-33.7, -33.7], "egm96")
    np.testing.assert_allclose(h, [100 + 28.329, 200 + 28.329], atol=0.01)
    np.testing.assert_array_equal(G.to_ellipsoidal([5.0], [0.0], [0.0], None), [5.0])
    np.testing.assert_array_equal(G.to_ellipsoidal([5.0], [0.0], [0.0], "ellipsoid"), [5.0])


def test_missing_geoid_grid_raises_with_fix(monkeypatch, tmp_path):
    monkeypatch.setattr(G, "geoid_search_dirs", lambda: [tmp_path])
    assert G.find_geoid_grid("egm96") is None
    with pytest.raises(VerticalDatumError) as ei:
        G.geoid_undulation(24.4, -33.7, "egm96")
    msg = str(ei.value)
    assert "egm96_15.gtx" in msg and "proj-data" in msg and "GEOCD_GEOID_DIR" in msg and str(tmp_path) in msg
    with pytest.raises(VerticalDatumError, match="allow-geoid-substitute"):
        G.geoid_undulation(24.4, -33.7, "egm2008", allow_substitute=False)
    with pytest.raises(VerticalDatumError, match="EGM2008"):
        G.geoid_undulation(24.4, -33.7, "egm2008", allow_substitute=True)  # no EGM96 either
    with pytest.raises(VerticalDatumError, match="convert"):
        G.geoid_undulation(24.4, -33.7, "navd88")


@needs_egm96
def test_egm2008_substitute_uses_egm96_with_warning(monkeypatch, tmp_path):
    egm96 = G.find_geoid_grid("egm96")
    monkeypatch.setattr(G, "geoid_search_dirs", lambda: [tmp_path, egm96.parent])
    if G.find_geoid_grid("egm2008") is not None:  # pragma: no cover - grid present on this machine
        pytest.skip("an EGM2008 grid is installed")
    with pytest.warns(UserWarning, match="EGM96 instead"):
        n = G.geoid_undulation(24.4, -33.7, "egm2008", allow_substitute=True)
    assert n == pytest.approx(G.geoid_undulation(24.4, -33.7, "egm96"))


def test_geoid_dir_env(monkeypatch, tmp_path):
    monkeypatch.setenv("GEOCD_GEOID_DIR", str(tmp_path))
    assert G.geoid_search_dirs()[0] == tmp_path


# ------------------------------------------------------------------------------------------
# AOI grid
# ------------------------------------------------------------------------------------------
def test_aoigrid_from_bounds_snaps_and_covers():
    g = G.AOIGrid.from_bounds(1003.0, 2001.0, 1051.0, 2040.0, 5.0, "EPSG:32735")
    assert g.transform == Affine(5.0, 0.0, 1000.0, 0.0, -5.0, 2040.0)
    assert (g.width, g.height) == (11, 8)
    l, b, r, t = g.bounds
    assert l <= 1003.0 and b <= 2001.0 and r >= 1051.0 and t >= 2040.0
    assert g.posting == (5.0, 5.0) and g.posting_m == 5.0 and g.cell_area_m2 == 25.0
    assert g.shape == (8, 11)
    # exact multiples do not grow an extra cell
    g2 = G.AOIGrid.from_bounds(0.0, 0.0, 100.0, 50.0, 10.0, "EPSG:32735")
    assert (g2.width, g2.height) == (10, 5)


def test_aoigrid_xy_rowcol_inverse():
    g = G.AOIGrid.from_bounds(500000.0, 6200000.0, 500300.0, 6200200.0, 2.0, 32735)
    x, y = g.xy()
    assert x.shape == g.shape
    assert x[0, 0] == 500001.0 and y[0, 0] == 6200199.0  # cell centres
    assert x[0, 1] - x[0, 0] == 2.0 and y[1, 0] - y[0, 0] == -2.0
    row, col = g.rowcol(x, y)
    np.testing.assert_allclose(row, np.arange(g.height)[:, None] + 0.5 + 0 * col)
    np.testing.assert_allclose(col, np.arange(g.width)[None, :] + 0.5 + 0 * row)
    xs, ys = g.xy(rows=[0, 3], cols=[5, 7])
    np.testing.assert_allclose(xs, x[[0, 3], [5, 7]])
    np.testing.assert_allclose(ys, y[[0, 3], [5, 7]])
    lon, lat = g.lonlat()
    assert lon.shape == g.shape and np.all((lon > 20) & (lon < 30))


def test_aoigrid_subgrid_and_dict():
    g = G.AOIGrid.from_bounds(0.0, 0.0, 100.0, 80.0, 1.0, "EPSG:32735")
    s = g.subgrid(10, 20, 30, 40)
    assert (s.height, s.width) == (30, 40)
    xs, ys = s.xy()
    x, y = g.xy()
    np.testing.assert_array_equal(xs, x[10:40, 20:60])
    np.testing.assert_array_equal(ys, y[10:40, 20:60])
    with pytest.raises(GridError, match="exceeds"):
        g.subgrid(70, 0, 20, 10)
    g2 = G.AOIGrid.from_dict(g.to_dict())
    assert g2.same_as(g) and not g2.same_as(s)
    with pytest.raises(GridError, match="needs crs"):
        G.AOIGrid.from_dict({"crs": "EPSG:32735"})


def test_aoigrid_rejects_bad_grids():
    with pytest.raises(GridError, match="positive size"):
        G.AOIGrid(CRS.from_epsg(32735), Affine(1, 0, 0, 0, -1, 0), 0, 5)
    with pytest.raises(GridError, match="north-up"):
        G.AOIGrid(CRS.from_epsg(32735), Affine(1, 0.1, 0, 0, -1, 0), 5, 5)
    with pytest.raises(GridError, match="negative y"):
        G.AOIGrid(CRS.from_epsg(32735), Affine(1, 0, 0, 0, 1, 0), 5, 5)
    with pytest.raises(GridError):
        G.AOIGrid.from_bounds(0, 0, 10, 10, 0.0, 32735)
    with pytest.raises(GridError):
        G.AOIGrid.from_bounds(10, 0, 0, 10, 1.0, 32735)


def test_intersect_bounds():
    assert G.intersect_bounds((0, 0, 10, 10), (5, -5, 15, 8)) == (5, 0, 10, 8)
    with pytest.raises(NoOverlapError, match="do not overlap"):
        G.intersect_bounds((0, 0, 1, 1), (2, 2, 3, 3))
