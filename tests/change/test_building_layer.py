"""The one building layer: its schema, its check, the footprint layer with new buildings, the docs' table."""

import re

import numpy as np
import pytest
from shapely.geometry import box

from geocd.change.building_layer import (
    CLASSES,
    COLUMNS,
    NAMES,
    building_layer_problems,
    check_building_layer,
    summarize,
    summary_line,
)
from geocd.change.dsm_buildings import footprint_layer
from geocd.consistency import ChangeResult
from geocd.geodesy import AOIGrid
from tests.conftest import REPO

GRID = AOIGrid.from_bounds(500000.0, 4000000.0, 500080.0, 4000080.0, 0.5, "EPSG:32631")


def _scene():
    """Flat ground; footprints 11 (9 m, gone), 12 (6 m, unchanged), 13 (unobserved); a 9 m building built
    between the dates outside every footprint."""
    import geopandas as gpd

    l, b, r, t = GRID.bounds
    fps = gpd.GeoDataFrame(
        {"id": [11, 12, 13], "name": ["a", "b", "c"]},
        geometry=[
            box(l + 5, b + 5, l + 20, b + 20),
            box(l + 40, b + 5, l + 55, b + 20),
            box(l + 5, b + 50, l + 20, b + 65),
        ],
        crs=GRID.crs,
    )
    from geocd.io.vector import polygons_to_mask

    def burn(g):
        return polygons_to_mask(gpd.GeoDataFrame(geometry=[g], crs=GRID.crs), GRID).astype(bool)

    rng = np.random.default_rng(0)
    za = rng.normal(0, 0.1, GRID.shape).astype(np.float32)
    zb = za + rng.normal(0, 0.1, GRID.shape).astype(np.float32)
    za[burn(fps.geometry[0])] += 9.0
    za[burn(fps.geometry[1])] += 6.0
    zb[burn(fps.geometry[1])] += 6.0
    new = box(l + 45, b + 45, l + 60, b + 60)
    zb[burn(new)] += 9.0
    dz = (zb - za).astype(np.float32)
    obs = np.ones(GRID.shape, bool)
    obs[burn(fps.geometry[2])] = False
    conf = np.where(np.abs(dz) > 2, 99.0, 0.0).astype(np.float32)
    conf[~obs] = np.nan
    ch = (np.sign(dz) * (conf > 0)).astype(np.int8)
    res = ChangeResult(
        dz, dz / 2.0, np.zeros_like(dz), conf, ch, obs.astype(np.int16), GRID, (90.0, 95.0, 99.0), min_region_cells=9
    )
    return fps, res, za, zb, new


def test_footprint_layer_follows_the_schema_and_holds_the_new_buildings(tmp_path):
    """Footprints classed in the layer's words (gone to the ground: collapsed), the unobserved one coded empty,
    the unchanged one at confidence 0, the new building outside every footprint in the same layer; the schema
    survives the GeoPackage (NaN written as NULL and read back as NaN)."""
    import geopandas as gpd

    from geocd.io.vector import write_gpkg

    fps, res, za, zb, new = _scene()
    layer = footprint_layer(fps, res, GRID, z_a=za, z_b=zb, id_field="id")
    check_building_layer(layer)
    assert tuple(layer.columns[: len(NAMES)]) == NAMES and {"src_id", "src_name"} <= set(layer.columns)
    by = layer.set_index("building_id")
    assert list(layer["building_id"]) == [11, 12, 13, -1]
    assert by.loc[11, "class"] == "collapsed" and by.loc[11, "confidence_pct"] == 99.0
    assert by.loc[11, "height_before_m"] == pytest.approx(9, abs=0.3) and by.loc[11, "volume_lost_m3"] > 1500
    assert by.loc[12, "class"] == "unchanged" and by.loc[12, "confidence_pct"] == 0.0
    u = by.loc[13]
    assert u["class"] == "unobserved" and np.isnan(u["confidence_pct"]) and np.isnan(u["mean_dz_m"])
    assert np.isnan(u[["frac_changed", "volume_change_m3", "volume_lost_m3"]].astype(float)).all()
    n = by.loc[-1]
    assert n["source"] == "change map" and n["class"] == "new" and n["confidence_pct"] == 99.0
    assert n.geometry.area == pytest.approx(new.area, rel=0.05)
    assert set(layer["source"]) == {"footprints", "change map"}
    p = write_gpkg(tmp_path / "b.gpkg", {"buildings": layer})
    back = gpd.read_file(p, layer="buildings")
    check_building_layer(back)
    s = summarize(layer)
    assert s == {
        "source": "footprints + change map",
        "classes": {"collapsed": 1, "new": 1, "unchanged": 1, "unobserved": 1},
        "volume_lost_m3": pytest.approx(
            float(layer.loc[layer["class"] == "collapsed", "volume_lost_m3"].sum()), abs=0.2
        ),
    }
    # the noise of an unchanged building is no loss
    assert (
        s["volume_lost_m3"] < float(np.nansum(layer["volume_lost_m3"]))
        or not (layer.loc[layer["class"] == "unchanged", "volume_lost_m3"] > 0).any()
    )
    line = summary_line(s)
    assert line.startswith("buildings (footprints + change map): 1 collapsed, 1 new, 1 unchanged, 1 unobserved")
    no_new = footprint_layer(fps, res, GRID, z_a=za, z_b=zb, id_field="id", detect_new=False)
    assert list(no_new["building_id"]) == [11, 12, 13]


def test_the_check_names_each_break_of_the_schema():
    """What the issue found in the two old layers, each caught: another class word, the unobserved coded 0,
    an unchanged building with a confidence, another source word, columns out of order."""
    fps, res, za, zb, _ = _scene()
    good = footprint_layer(fps, res, GRID, z_a=za, z_b=zb, id_field="id")
    assert building_layer_problems(good) == []

    def broken(**change):
        b = good.copy()
        for col, (row, v) in change.items():
            b.loc[row, col] = v
        return building_layer_problems(b)

    assert any("demolished" in p for p in broken(**{"class": (0, "demolished")}))
    assert any("unobserved" in p and "confidence_pct" in p for p in broken(confidence_pct=(2, 0.0)))
    assert any("unchanged" in p for p in broken(confidence_pct=(1, 57.7)))
    assert any("sources" in p for p in broken(source=(0, "footprint")))
    assert any("outside (0, 100]" in p for p in broken(confidence_pct=(0, 0.0)))
    assert any("mean_dz_m" in p for p in broken(mean_dz_m=(2, 0.0)))
    swapped = good[["building_id", "class", "source", *good.columns[3:]]]
    assert any("columns start" in p for p in building_layer_problems(swapped))
    assert building_layer_problems(swapped[["building_id", "source", "class", "confidence_pct", "geometry"]]) != []
    assert building_layer_problems(good[[*NAMES[:4], "geometry"]], shared_only=True) == []
    with pytest.raises(ValueError, match="does not follow the schema"):
        check_building_layer(swapped)
    assert summary_line(None) == "buildings: no building layer"
    assert summary_line({"source": None, "reason": "no footprints"}) == "buildings: no building layer (no footprints)"
    assert summary_line({"source": "A DSM", "classes": {}}) == "buildings (A DSM): none found"


def test_an_empty_layer_is_written_and_read_in_the_schema(tmp_path):
    """A DSM without a building object still gives the run its one (empty) building layer."""
    import geopandas as gpd

    from geocd.change.building_layer import empty_layer
    from geocd.io.vector import write_gpkg

    p = write_gpkg(tmp_path / "e.gpkg", {"buildings": empty_layer(GRID.crs)})
    back = gpd.read_file(p, layer="buildings")
    assert len(back) == 0 and tuple(back.columns[: len(NAMES)]) == NAMES
    check_building_layer(back)
    assert summary_line(summarize(back, "A DSM")) == "buildings (A DSM): none found"


def test_the_products_page_documents_every_column_and_class():
    """docs/reference/products.md: the building layer's table lists every column, in order, with its unit;
    every class is named."""
    text = (REPO / "docs" / "reference" / "products.md").read_text(encoding="utf-8")
    sec = text[text.index("## The `buildings` layer") :]
    rows = re.findall(r"^\| `([a-z0-9_]+)` \| ([^|]+) \| ([^|]*) \|", sec, flags=re.M)
    assert [r[0] for r in rows[: len(COLUMNS)]] == list(NAMES)
    for (name, dtype, unit), col in zip(rows, COLUMNS):
        assert dtype.strip() == col.dtype and unit.strip() == (col.unit or ""), name
    for c in CLASSES:
        assert f"`{c}`" in sec, c


def test_the_summary_adds_up_the_loss_of_lowered_buildings_only():
    """On a scene where nothing changed the per-building Δz is noise: the run's summary must not report it as
    a lost volume (a Marseille pair against a pair of the same date read "37,582 m³ lost" with 0 changed)."""
    import pandas as pd

    layer = pd.DataFrame(
        {
            "source": "A DSM",
            "class": ["unchanged", "unobserved", "collapsed", "partly collapsed", "raised"],
            "volume_lost_m3": [120.0, np.nan, 3000.0, 400.0, 0.0],
        }
    )
    assert summarize(layer)["volume_lost_m3"] == 3400.0
    assert summarize(layer[layer["class"] == "unchanged"])["volume_lost_m3"] == 0.0
    assert "m³ lost" not in summary_line(summarize(layer[layer["class"] == "unchanged"]))
