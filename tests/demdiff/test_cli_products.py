import json

import numpy as np
import pyogrio
import pytest
import rasterio
from click.testing import CliRunner

from geocd.cli import main
from geocd.io.raster import write_cog

from .synthetic import grid, pair


def _write_pair(tmp_path, **kw):
    a, b, info = pair(**kw)
    pa = write_cog(tmp_path / "a.tif", a.height_m, a.grid)
    pb = write_cog(tmp_path / "b.tif", b.height_m, b.grid)
    return a, b, info, pa, pb


@pytest.mark.slow
def test_cli_pair_products(tmp_path):
    a, b, info, pa, pb = _write_pair(tmp_path, shift_m=(5.0, 0.0, 1.0), bump_m=25.0)
    import geopandas as gpd
    from shapely.geometry import box

    l, bt, r, t = a.grid.bounds
    cx, cy = 0.5 * (l + r), 0.5 * (bt + t)
    fp = gpd.GeoDataFrame(
        {"name": ["on bump", "elsewhere"]},
        geometry=[box(cx - 40, cy - 40, cx + 40, cy + 40), box(l + 100, bt + 100, l + 160, bt + 160)],
        crs=a.grid.crs,
    )
    fp.to_file(tmp_path / "fp.gpkg")
    out = tmp_path / "out"
    res = CliRunner().invoke(
        main,
        [
            "--progress",
            "none",
            "demdiff",
            str(pa),
            str(pb),
            "--out",
            str(out),
            "--footprints",
            str(tmp_path / "fp.gpkg"),
            "--confidence",
            "99",
        ],
    )
    assert res.exit_code == 0, res.output
    for name in (
        "dh.tif",
        "dh.qml",
        "significance.tif",
        "significance.qml",
        "change_mask.tif",
        "changes.gpkg",
        "dh.png",
        "report.json",
    ):
        assert (out / f"demdiff_{name}").is_file(), name
    with rasterio.open(out / "demdiff_dh.tif") as ds:
        assert ds.descriptions == ("dh_m",) and ds.crs.to_epsg() == 32610
    with rasterio.open(out / "demdiff_significance.tif") as ds:
        assert ds.descriptions == ("confidence_pct", "sigma_m", "z")
        c = ds.read(1)
        assert np.nanmax(c) <= 100 and np.nanmin(c) >= 0
    with rasterio.open(out / "demdiff_change_mask.tif") as ds:
        assert ds.nodata == -128 and set(np.unique(ds.read(1))) <= {-128, -1, 0, 1}
    layers = {n for n, _ in pyogrio.list_layers(out / "demdiff_changes.gpkg")}
    assert {"changes", "buildings", "summary", "error_model", "variogram", "layer_styles"} <= layers
    st = pyogrio.read_dataframe(out / "demdiff_changes.gpkg", layer="layer_styles")
    assert set(st.f_table_name) == {"changes", "buildings"}
    assert "categorizedSymbol" in st[st.f_table_name == "changes"].styleQML.iloc[0]
    bl = pyogrio.read_dataframe(out / "demdiff_changes.gpkg", layer="buildings")
    from geocd.change.building_layer import check_building_layer

    check_building_layer(bl)  # the one building layer's schema (no volume σ: no per-cell error model here)
    assert list(bl["src_name"][:2]) == ["on bump", "elsewhere"] and (bl["source"][:2] == "footprints").all()
    assert bl["class"].iloc[0] in ("new", "raised") and bl["class"].iloc[1] == "unchanged"
    assert bl["confidence_pct"].iloc[0] == 99.0 and bl["confidence_pct"].iloc[1] == 0.0
    assert bl["volume_sigma_m3"].isna().all() and bl["volume_change_m3"].iloc[0] > 0
    ch = pyogrio.read_dataframe(out / "demdiff_changes.gpkg", layer="changes")
    assert (ch["sign"] == 1).any() and ch["volume_sigma_m3"].notna().all()
    rep = json.loads((out / "demdiff_report.json").read_text())
    assert rep["coreg"]["status"] == "ok" and rep["summary"]["volume_changed_m3"] > 0
    qml = (out / "demdiff_dh.qml").read_text()
    assert "singlebandpseudocolor" in qml and 'classificationMin="-' in qml


@pytest.mark.slow
def test_cli_series_from_list(tmp_path):
    g = grid(80, 80)
    base, _, _ = pair(g=g, noise_m=0.0)
    rr, cc = np.mgrid[0:80, 0:80]
    dome = np.exp(-((rr - 40) ** 2 + (cc - 40) ** 2) / (2 * 6.0**2))
    rng = np.random.default_rng(0)
    lines = []
    for k, amp in enumerate([0, 10, 25]):
        h = base.height_m + amp * dome + rng.normal(scale=0.2, size=g.shape)
        p = write_cog(tmp_path / f"e{k}.tif", h.astype(np.float32), g)
        lines.append(f"{p.name},2006-0{k + 1}-15,e{k}")
    (tmp_path / "series.txt").write_text("# path,date,name\n" + "\n".join(lines) + "\n")
    out = tmp_path / "ts"
    res = CliRunner().invoke(main, ["--progress", "none", "demdiff", str(tmp_path / "series.txt"), "--out", str(out)])
    assert res.exit_code == 0, res.output
    import pandas as pd

    df = pd.read_csv(out / "demdiff_timeseries.csv")
    assert list(df.epoch_b) == ["e1", "e2"]
    true = 25 * dome.sum() * g.cell_area_m2
    assert df.cumulative_net_m3.iloc[-1] == pytest.approx(true, rel=0.1)
    assert (out / "demdiff_timeseries.png").is_file()
    assert "timeseries" in {n for n, _ in pyogrio.list_layers(out / "demdiff_timeseries.gpkg")}


def test_cli_errors_are_one_line(tmp_path):
    a, _, _ = pair()
    pa = write_cog(tmp_path / "a.tif", a.height_m, a.grid)
    far = grid(x0=900000.0)
    pb = write_cog(tmp_path / "b.tif", a.height_m, far)
    res = CliRunner().invoke(main, ["--progress", "none", "demdiff", str(pa), str(pb), "--out", str(tmp_path / "o")])
    assert res.exit_code != 0 and "do not overlap" in res.output and "Traceback" not in res.output
    res = CliRunner().invoke(main, ["--progress", "none", "demdiff", str(pa), "--out", str(tmp_path / "o")])
    assert res.exit_code != 0 and "geocd: error" in res.output
