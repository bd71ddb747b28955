"""Regions merged across tile seams == connected regions of the whole grid."""

from __future__ import annotations

import numpy as np
from affine import Affine
from scipy import ndimage

from geocd.change.regions import change_regions
from geocd.geodesy import AOIGrid
from geocd.tiling import TileGrid
from geocd.tiling.regions import merge_regions, region_mask_window, regions_layer, tile_regions


def _scene(seed=0, h=230, w=190):
    rng = np.random.default_rng(seed)
    g = AOIGrid("EPSG:32631", Affine(2.0, 0, 500000.0, 0, -2.0, 4800000.0), w, h)
    f = ndimage.gaussian_filter(rng.normal(size=(h, w)), 3)
    sign = np.where(f > 0.12, 1, np.where(f < -0.12, -1, 0)).astype(np.int8)
    # long thin regions that cross many seams, diagonal contacts at tile corners
    sign[5, :] = 1
    sign[:, 100] = -1
    sign[63, 63] = 1
    sign[64, 64] = 1
    dz = rng.normal(size=(h, w)) + 5 * sign
    dz[rng.random((h, w)) < 0.02] = np.nan
    return g, sign, dz


def test_merged_regions_equal_whole_grid_regions():
    g, sign, dz = _scene()
    ref = change_regions(sign, dz, g, min_cells=3, method="m", epoch_a="A", epoch_b="B")
    tg = TileGrid(g, (64, 64), 0)
    parts = []
    labels = {}
    for t in tg:
        tr = tile_regions(sign[t.core_slices], dz[t.core_slices], t, g)
        labels[t.index] = tr.labels
        tr.labels = None
        parts.append(tr)
    merged = merge_regions(parts, tg, min_cells=3)
    lay = regions_layer(merged, g, cell_area_m2=4.0, method="m", epoch_a="A", epoch_b="B")
    assert len(lay) == len(ref) > 20
    np.testing.assert_array_equal(lay["n_cells"], ref["n_cells"])
    np.testing.assert_array_equal(lay["sign"], ref["sign"])
    np.testing.assert_allclose(lay["volume_m3"], ref["volume_m3"], rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(lay["mean_dz_m"], ref["mean_dz_m"], rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(lay["max_dz_m"], ref["max_dz_m"])
    # the same polygons (the union of the tiles' pieces)
    for a, b in zip(lay.geometry, ref.geometry):
        assert abs(a.area - b.area) < 1e-6 and a.symmetric_difference(b).area < 1e-6
    # a region's cells from the tiles' label rasters
    k = int(np.argmax(lay["n_cells"].to_numpy()))
    m, sl = region_mask_window(merged, k, lambda t: labels[t.index], tg)
    assert m.sum() == lay["n_cells"].iloc[k]
    lab, _ = ndimage.label(sign == merged.sign[k], structure=np.ones((3, 3), bool))
    r, c = divmod(int(merged.first[k]), g.width)
    np.testing.assert_array_equal(m, (lab == lab[r, c])[sl])


def test_regions_written_in_batches_equal_the_whole_layer(tmp_path):
    """The changes layer appended batch by batch == the layer written at once (rows, order, geometries, type)."""
    import pyogrio

    from geocd.io.vector import write_gpkg
    from geocd.tiling.regions import regions_layer_batches

    g, sign, dz = _scene(seed=3)
    tg = TileGrid(g, (64, 64), 0)
    parts = []
    for t in tg:
        tr = tile_regions(sign[t.core_slices], dz[t.core_slices], t, g)
        tr.labels = None
        parts.append(tr)
    merged = merge_regions(parts, tg, min_cells=1)
    kw = dict(cell_area_m2=4.0, method="m", epoch_a="A", epoch_b="B")
    whole = regions_layer(merged, g, **kw)
    assert len(whole) > 50 and set(whole.geom_type) == {"Polygon", "MultiPolygon"}
    batches = regions_layer_batches(merged, g, batch=7, **kw)
    assert batches.geometry_type == "MultiPolygon"
    a = write_gpkg(tmp_path / "a.gpkg", {"changes": whole})
    b = write_gpkg(tmp_path / "b.gpkg", {"changes": batches})
    assert (
        pyogrio.read_info(a, layer="changes")["geometry_type"]
        == pyogrio.read_info(b, layer="changes")["geometry_type"]
        == "MultiPolygon"
    )
    ra = pyogrio.read_dataframe(a, layer="changes")
    rb = pyogrio.read_dataframe(b, layer="changes")
    assert ra.drop(columns="geometry").equals(rb.drop(columns="geometry"))
    assert list(ra.geometry.to_wkb()) == list(rb.geometry.to_wkb())
    # one region at a time == a batch; members as (tile, sign, label)
    assert all(merged.geometry[k].equals_exact(whole.geometry.iloc[k], 0) for k in range(len(merged)))
    assert all(len(merged.members[k]) == merged.members.counts[k] for k in range(len(merged)))
