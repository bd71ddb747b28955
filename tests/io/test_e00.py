import numpy as np
import pytest

from geocd.errors import CRSError, InputFileNotFoundError, UnsupportedFormatError
from geocd.io.e00 import crs_from_prj, parse_e00_grid, read_e00_dem

from ..conftest import shared_data

NODATA = "-0.34028234663853E+39"


def _e00(values: np.ndarray, cell=10.0, ll=(561195.0, 5115055.0), pad_last=True, prj=True) -> str:
    nrows, ncols = values.shape
    lines = [
        "EXP  0 D:\\TEST.E00",
        "GRD  2",
        f"{ncols:10d}{nrows:10d} 2{NODATA}",
        f"{cell:21.14E}{cell:21.14E}",
        f"{ll[0]:21.14E}{ll[1]:21.14E}",
        f"{ll[0] + ncols * cell:21.14E}{ll[1] + nrows * cell:21.14E}",
    ]
    for r in range(nrows):
        row = ["-0.3402823E+39" if np.isnan(v) else f"{v:14.7E}" for v in values[r]]
        while pad_last and len(row) % 5:
            row.append(row[len(row) - 5])  # stale values, as ArcInfo writes them
        for k in range(0, len(row), 5):
            lines.append("".join(row[k : k + 5]))
    lines.append("EOG")
    if prj:
        lines += [
            "PRJ  2",
            "Projection    UTM",
            "~",
            "Zone          10",
            "~",
            "Datum         NAD83",
            "~",
            "Units         METERS",
            "~",
            "Spheroid      GRS1980",
            "~",
            "EOP",
        ]
    lines.append("EOS")
    return "\r\n".join(lines) + "\r\n"


def test_parse_small_grid(tmp_path):
    v = np.arange(21, dtype=float).reshape(3, 7) * 1.5 + 1000
    v[1, 3] = np.nan
    p = tmp_path / "g.e00"
    p.write_text(_e00(v), newline="")
    dem = read_e00_dem(p)
    assert dem.height_m.shape == (3, 7) and dem.height_m.dtype == np.float32
    np.testing.assert_allclose(dem.height_m, v, equal_nan=True)
    assert dem.grid.crs.to_epsg() == 26910
    t = dem.grid.transform
    assert (t.a, t.e, t.c, t.f) == (10.0, -10.0, 561195.0, 5115055.0 + 30)


def test_compressed_truncated_and_missing(tmp_path):
    with pytest.raises(UnsupportedFormatError, match="compressed"):
        parse_e00_grid("EXP  1 X\nGRD  2\n")
    with pytest.raises(UnsupportedFormatError, match="no grid"):
        parse_e00_grid("EXP  0 X\nARC  2\n")
    text = _e00(np.ones((4, 6)))
    cut = "\n".join(text.splitlines()[:8])
    with pytest.raises(UnsupportedFormatError, match="truncated"):
        parse_e00_grid(cut)
    with pytest.raises(InputFileNotFoundError):
        read_e00_dem(tmp_path / "nope.e00")


def test_prj_to_crs():
    assert crs_from_prj({"projection": "UTM", "zone": "33", "datum": "WGS84", "units": "METERS"}).to_epsg() == 32633
    assert crs_from_prj({"projection": "GEOGRAPHIC", "datum": "NAD83"}).to_epsg() == 4269
    with pytest.raises(CRSError):
        crs_from_prj({"projection": "LAMBERT"})


@pytest.mark.realdata
def test_msh_base_matches_the_merged_geotiffs():
    from geocd.io.raster import read_dem

    base = read_e00_dem(shared_data("usgs_msh_dome_dems", "raw_e00", "1_msh00_83.e00"))
    d2 = read_dem(shared_data("usgs_msh_dome_dems", "geotiff_utm10n", "2.tif"))
    assert base.grid.same_as(d2.grid)
    diff = base.height_m != d2.height_m
    # the GeoTIFF is the base with epoch 2's survey pasted over 1996 cells (see the data README)
    assert diff.sum() == 1996
    assert float(np.nanmin(base.height_m)) == pytest.approx(1361.796, abs=1e-3)
    e2 = read_e00_dem(shared_data("usgs_msh_dome_dems", "raw_e00", "2_msh104_83.e00"))
    assert e2.grid.posting == (2.0, 2.0) and e2.height_m.shape == (256, 301)
