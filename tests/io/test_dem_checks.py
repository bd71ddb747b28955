"""A DEM's values are checked before anything is computed from them: undeclared nodata values are refused (or
declared with ``--nodata``), values that are not heights are refused or reported, on every path."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from click.testing import CliRunner

from geocd.cli import main
from geocd.errors import UnsupportedFormatError
from geocd.io.raster import DEMValueWarning, check_dem_file, read_dem, undeclared_nodata, write_cog
from tests.conftest import shared_data
from tests.demdiff.synthetic import grid, pair
from tests.reliability.scenes import error_lines


def _terrain(rows=60, cols=75, base=300.0, seed=0):
    rng = np.random.default_rng(seed)
    rr, cc = np.mgrid[0:rows, 0:cols]
    return (base + 40 * np.sin(rr / 9.0) + 25 * np.cos(cc / 7.0) + rng.normal(0, 0.5, (rows, cols))).astype(np.float32)


def _write(tmp_path, h, name="dem.tif", **kw):
    return write_cog(tmp_path / name, h, grid(*h.shape), **kw)


@pytest.mark.parametrize(
    "value,cells",
    [
        (-9999.0, "columns"),  # 1/15 of the columns: the DEM
        (-9999.0, "scattered"),  # 0.5 % of the cells
        (-9999.0, "one"),  # a single cell still poisons its neighbours when resampled
        (-32768.0, "scattered"),
        (float(np.finfo(np.float32).min), "columns"),
        (1e30, "half"),
        (0.0, "scattered"),  # zeros as nodata in a mountain DEM (1,500 m)
    ],
)
def test_undeclared_nodata_is_refused_with_the_fix(tmp_path, value, cells):
    h = _terrain(base=1500.0 if value == 0 else 300.0)
    if cells == "columns":
        h[:, ::15] = value
    elif cells == "scattered":
        h.flat[np.random.default_rng(1).choice(h.size, int(0.005 * h.size), replace=False)] = value
    elif cells == "one":
        h[10, 10] = value
    else:
        h[: h.shape[0] // 2] = value
    p = _write(tmp_path, h)
    with pytest.raises(UnsupportedFormatError, match="undeclared nodata") as e:
        read_dem(p)
    v = str(np.float32(value)).removesuffix(".0")  # as the float32 file stores it
    assert f"--nodata {v}" in str(e.value) and f"gdal_edit.py -a_nodata {v}" in str(e.value), e.value
    # declared, the run proceeds and those cells are nodata
    d = read_dem(p, nodata=value)
    assert np.isnan(d.height_m[h == value]).all() and np.isfinite(d.height_m[h != value]).all()
    # the same check on the path that reads the DEM tile by tile
    with pytest.raises(UnsupportedFormatError, match="undeclared nodata"):
        check_dem_file(p)
    check_dem_file(p, nodata=value)


def test_a_resampled_read_never_mixes_a_sentinel_into_its_neighbours(tmp_path):
    h = _terrain()
    h[:, ::15] = -9999.0
    p = _write(tmp_path, h)
    g = grid(*h.shape)
    from geocd.geodesy import AOIGrid

    half = AOIGrid(g.crs, g.transform @ g.transform.translation(0.5, 0.5), g.width - 1, g.height - 1)
    d = read_dem(p, grid=half, nodata=-9999.0)
    v = d.height_m[np.isfinite(d.height_m)]
    assert v.min() > 200.0, v.min()  # bilinear with a -9999 neighbour would give thousands below


def test_real_terrain_is_not_taken_for_nodata(tmp_path):
    sea = _terrain(base=20.0)
    sea[:, :30] = 0.0  # a coast: the sea at exactly 0 m beside land rising from it
    assert undeclared_nodata(sea) == []
    read_dem(_write(tmp_path, sea, "coast.tif"))
    deep = np.linspace(-10_500.0, 100.0, 60 * 75, dtype=np.float32).reshape(60, 75)
    deep.flat[::97] = -9999.0  # a bathymetry passes through -9999 m: not isolated, not nodata
    assert undeclared_nodata(deep) == []


@pytest.mark.parametrize("share,refused", [(0.004, False), (0.05, True)])
def test_infinite_or_out_of_range_values_are_reported_or_refused(tmp_path, share, refused):
    h = _terrain()
    idx = np.random.default_rng(2).choice(h.size, int(share * h.size), replace=False)
    h.flat[idx[::2]] = np.inf
    h.flat[idx[1::2]] = 5e4 + np.arange(idx[1::2].size)  # scattered, not one repeated value
    p = _write(tmp_path, h)
    if refused:
        with pytest.raises(UnsupportedFormatError, match="are not terrain heights in metres"):
            read_dem(p)
        return
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        d = read_dem(p)
    assert any(issubclass(x.category, DEMValueWarning) and f"{idx.size} value(s)" in str(x.message) for x in w), [
        str(x.message) for x in w
    ]
    assert np.isnan(d.height_m.flat[idx]).all()


def test_a_centimetre_dem_gets_the_units_hint(tmp_path):
    p = _write(tmp_path, _terrain() * 100.0)
    with pytest.raises(UnsupportedFormatError, match="centimetres"):
        read_dem(p)


# ---------------------------------------------------------------------------------------------------------------
# the command line: demdiff in memory and tiled, the same errors before any work
# ---------------------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def dem_pair(tmp_path_factory):
    d = tmp_path_factory.mktemp("demcheck")
    g = grid(80, 90)
    a, b, truth = pair(g=g, bump_m=20.0, bump_radius_px=8)
    pa = write_cog(d / "a.tif", a.height_m, g)
    pb = write_cog(d / "b.tif", b.height_m, g)
    bad = b.height_m.copy()
    bad[:, ::15] = -9999.0
    pbad = write_cog(d / "b_9999.tif", bad, g)
    return pa, pb, pbad


def _demdiff(*args):
    return CliRunner().invoke(main, ["--progress", "none", "demdiff", *map(str, args), "--no-plots", "--json"])


@pytest.mark.parametrize("tiled", ["--untiled", "--tiled"])
@pytest.mark.slow
def test_demdiff_refuses_undeclared_nodata_and_runs_with_it_declared(dem_pair, tmp_path, tiled):
    import json

    pa, pb, pbad = dem_pair
    r = _demdiff(pa, pbad, "--out", tmp_path / "bad", tiled)
    assert r.exit_code == 2, r.output
    errs = error_lines(r.stderr)
    assert len(errs) == 1 and "undeclared nodata" in errs[0] and "--nodata -9999" in errs[0], r.stderr
    assert not (tmp_path / "bad").exists() or not any((tmp_path / "bad").iterdir())
    clean = _demdiff(pa, pb, "--out", tmp_path / "clean", tiled)
    declared = _demdiff(pa, pbad, "--out", tmp_path / "declared", tiled, "--nodata", "-9999")
    assert clean.exit_code == 0 and declared.exit_code == 0, declared.output
    vc, vd = (json.loads(x.stdout)["summary"] for x in (clean, declared))
    # a fifteenth of B's columns is unobserved: the volume found is a part of the clean run's, never a sentinel's
    # thousands of metres (the DEM: -5,078,999 Mm³ for +33.5)
    assert 0.6 * vc["volume_changed_m3"] < vd["volume_changed_m3"] <= 1.02 * vc["volume_changed_m3"], (vc, vd)
    assert abs(vd["stable_nmad_m"] - vc["stable_nmad_m"]) < 0.05, (vc, vd)


@pytest.mark.parametrize(
    "kind,needle",
    [("rgb", "is not a DEM"), ("complex", "holds complex values"), ("two_bands", "is not named as heights")],
)
def test_tiled_demdiff_makes_every_dem_check(dem_pair, tmp_path, kind, needle):
    import rasterio

    pa, _, _ = dem_pair
    with rasterio.open(pa) as ds:
        prof = {k: ds.profile[k] for k in ("crs", "transform", "width", "height")}
        h = ds.read(1)
    p = tmp_path / f"{kind}.tif"
    if kind == "rgb":
        arr, extra = np.stack([np.clip(h, 0, 255).astype(np.uint8)] * 3), dict(photometric="RGB")
    elif kind == "complex":
        arr, extra = (h + 1j * h).astype(np.complex64)[None], {}
    else:
        arr, extra = np.stack([h, h]), {}
    with rasterio.open(p, "w", driver="GTiff", count=arr.shape[0], dtype=arr.dtype, **prof, **extra) as ds:
        ds.write(arr)
    msgs = []
    for mode in ("--untiled", "--tiled"):
        r = _demdiff(pa, p, "--out", tmp_path / mode, mode)
        assert r.exit_code == 2, (mode, r.output)
        errs = error_lines(r.stderr)
        assert len(errs) == 1 and needle in errs[0], (mode, r.stderr)
        msgs.append(errs[0])
    assert msgs[0] == msgs[1]


# ---------------------------------------------------------------------------------------------------------------
# every real DEM of ../shared/data passes (the constants were checked on them)
# ---------------------------------------------------------------------------------------------------------------
_REAL = [
    "usgs_msh_dome_dems/geotiff_utm10n/2.tif",
    "usgs_msh_dome_dems/geotiff_utm10n/27.tif",
    "cnes_demcompare_srtm/srtm_ref.tif",
    "cnes_demcompare_srtm/srtm_blurred_and_shifted.tif",
    "cnes_demcompare_srtm/Copernicus_DSM_10_N45_00_E005_00_DEM.tif",
    "cnes_pleiades_ventoux/srtm/N44E005.hgt",
    "s2p_pleiades/expected_output/pair/dsm.tif",
    "s2p_pleiades/expected_output/triplet/dsm.tif",
    "orthority_baviaans_aerial_qb2/ngi/dem.tif",
]


@pytest.mark.realdata
@pytest.mark.parametrize("rel", _REAL)
def test_real_dems_pass_the_checks(rel):
    p = shared_data(*rel.split("/"))
    with warnings.catch_warnings():
        warnings.simplefilter("error", DEMValueWarning)
        check_dem_file(p)
        assert np.isfinite(read_dem(p).height_m).any()


def test_sentinels_are_found_in_a_large_dem_with_averaged_overviews(tmp_path, monkeypatch):
    """A decimated read takes the overview, whose averages hide -9999: the check reads whole rows at full
    resolution, in strips when the DEM is large."""
    import geocd.io.raster as R

    h = _terrain(rows=600, cols=640)
    h[:, ::15] = -9999.0
    p = _write(tmp_path, h, "big.tif")  # a COG: write_cog adds averaged overviews
    import rasterio

    with rasterio.open(p) as ds:
        assert ds.overviews(1), "the test needs a file with overviews"
    monkeypatch.setattr(R, "CHECK_CELLS", 20_000)  # force the strip sampling
    with pytest.raises(UnsupportedFormatError, match=r"-9999 in .* strips of whole rows"):
        check_dem_file(p)
