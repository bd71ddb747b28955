"""The tiling layer: tiled == whole-grid for a focal filter, resume, seam rule, COG products."""

from __future__ import annotations

import sys

import cloudpickle
import numpy as np
import pytest
import rasterio
from affine import Affine
from scipy import ndimage

from geocd.errors import CancelledError, ConfigError
from geocd.geodesy import AOIGrid
from geocd.io.raster import write_cog
from geocd.tiling import ArraySource, RasterProduct, RasterSource, TileGrid, TileOutput, overlap_cells, run_tiled
from geocd.tiling.store import WORK_DIR

# tile functions defined here travel by value to dask worker processes
cloudpickle.register_pickle_by_value(sys.modules[__name__])

RADIUS = 3


def _grid(h=203, w=157, post=2.0):
    return AOIGrid("EPSG:32631", Affine(post, 0, 500000.0, 0, -post, 4800000.0), w, h)


def _field(g, seed=0):
    rng = np.random.default_rng(seed)
    a = ndimage.gaussian_filter(rng.normal(size=g.shape), 4).astype(np.float32)
    a[40:60, 30:50] = np.nan
    return a


def focal(a: np.ndarray) -> np.ndarray:
    """Mean of the (2R+1)² window; NaN where the window leaves the grid or touches NaN.

    Summed offset by offset (the same additions in the same order for every cell), so the
    value of a cell does not depend on where the array starts (a running-sum filter's does).
    """
    h, w = a.shape
    pad = np.full((h + 2 * RADIUS, w + 2 * RADIUS), np.nan)
    pad[RADIUS:-RADIUS, RADIUS:-RADIUS] = a
    s = np.zeros((h, w))
    for dr in range(2 * RADIUS + 1):
        for dc in range(2 * RADIUS + 1):
            s += pad[dr : dr + h, dc : dc + w]
    return (s / (2 * RADIUS + 1) ** 2).astype(np.float32)


def focal_tile(arrays, ctx):
    f = focal(arrays["x"])
    return TileOutput(arrays={"f": f}, small=(int(np.isfinite(ctx.crop(f)).sum()), float(np.nansum(ctx.crop(f)))))


def test_tile_grid_covers_grid_once():
    g = _grid()
    tg = TileGrid(g, (64, 50), 5)
    seen = np.zeros(g.shape, int)
    for t in tg:
        seen[t.core_slices] += 1
        r0, c0, h, w = t.read
        assert r0 >= 0 and c0 >= 0 and r0 + h <= g.height and c0 + w <= g.width
        # the read window holds the core plus the overlap wherever the grid allows
        assert t.core[0] - r0 == min(5, t.core[0])
    assert (seen == 1).all()
    assert len(tg) == 4 * 4
    assert overlap_cells(g, metres=7.0) == 4 and overlap_cells(cells=3) == 3
    with pytest.raises(ConfigError):
        overlap_cells(cells=-1)


@pytest.mark.parametrize("scheduler", ["sync", "threads"])
def test_focal_filter_tiled_equals_untiled(tmp_path, scheduler):
    g = _grid()
    a = _field(g)
    ref = focal(a)
    run = run_tiled(
        focal_tile,
        g,
        {"x": ArraySource(a)},
        overlap_cells=RADIUS,
        tile_size=(48, 40),
        out=tmp_path,
        stage="focal",
        scheduler=scheduler,
    )
    np.testing.assert_array_equal(run.read("f"), ref)
    n = sum(s[0] for _, s in run.smalls())
    assert n == int(np.isfinite(ref).sum())
    # the declared overlap matters: one cell too few is wrong at the seams
    bad = run_tiled(
        focal_tile,
        g,
        {"x": ArraySource(a)},
        overlap_cells=RADIUS - 1,
        tile_size=(48, 40),
        out=tmp_path,
        stage="focal-short",
        scheduler="sync",
    )
    diff = ~np.isclose(bad.read("f"), ref, equal_nan=True)
    assert diff.any()


def test_products_from_files_match_write_cog(tmp_path):
    g = _grid()
    a = _field(g)
    src = tmp_path / "x.tif"
    write_cog(src, a, g)
    ref_path = write_cog(tmp_path / "ref.tif", focal(a), g, tags={"units": "m"})
    prod = RasterProduct(str(tmp_path / "out" / "f.tif"), bands=("f",), tags={"units": "m"})
    run = run_tiled(
        focal_tile,
        g,
        {"x": RasterSource(str(src))},
        overlap_cells=RADIUS,
        tile_size=64,
        out=tmp_path / "out",
        stage="focal",
        products={"f": prod},
        scheduler="sync",
    )
    with rasterio.open(run.products["f"]) as d1, rasterio.open(ref_path) as d2:
        np.testing.assert_array_equal(d1.read(), d2.read())
        assert d1.overviews(1) == d2.overviews(1)
        np.testing.assert_array_equal(
            d1.read(1, out_shape=(g.height // 2, g.width // 2)), d2.read(1, out_shape=(g.height // 2, g.width // 2))
        )
        assert d1.tags()["units"] == "m" and d1.profile["blockxsize"] == d2.profile["blockxsize"]
        assert d1.descriptions == ("f",)
    # nothing partial or temporary next to the product
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == sorted([WORK_DIR, "f.tif"])


class _StopAfter:
    def __init__(self, n):
        self.n = n
        self.calls = 0

    def __call__(self, fraction, message=""):
        self.calls += 1
        if self.calls > self.n:
            raise CancelledError("stop")


@pytest.mark.parametrize("scheduler", ["sync", "threads"])
def test_cancel_then_resume_redoes_only_unfinished_tiles(tmp_path, scheduler):
    g = _grid()
    a = _field(g)
    kw = dict(overlap_cells=RADIUS, tile_size=(48, 40), out=tmp_path, stage="focal")
    prod = {"f": RasterProduct(str(tmp_path / "f.tif"), ("f",))}
    with pytest.raises(CancelledError):
        run_tiled(
            focal_tile, g, {"x": ArraySource(a)}, progress=_StopAfter(6), scheduler=scheduler, products=prod, **kw
        )
    assert not (tmp_path / "f.tif").exists()
    run = run_tiled(focal_tile, g, {"x": ArraySource(a)}, scheduler="sync", products=prod, **kw)
    # the tiles finished when the cancel came are kept (6 of 20 in order; threads: those that had finished)
    assert (run.n_resumed == 6 if scheduler == "sync" else 6 <= run.n_resumed < 20) and run.n_tiles == 20
    np.testing.assert_array_equal(run.read("f"), focal(a))
    # a changed command (other input) does not reuse the tiles
    run2 = run_tiled(focal_tile, g, {"x": ArraySource(a + 1)}, **kw)
    assert run2.n_resumed == 0
    np.testing.assert_allclose(run2.read("f"), focal(a + 1), rtol=1e-6)


def blobs_tile(arrays, ctx):
    import geopandas as gpd
    from shapely.geometry import box

    m = arrays["x"] > 1.0
    lab, n = ndimage.label(m)
    geoms = []
    for sl in ndimage.find_objects(lab):
        r0, r1, c0, c1 = sl[0].start, sl[0].stop, sl[1].start, sl[1].stop
        x0, y0 = ctx.read_grid.transform @ (c0, r0)
        x1, y1 = ctx.read_grid.transform @ (c1, r1)
        geoms.append(box(x0, y1, x1, y0))
    return TileOutput(vectors=gpd.GeoDataFrame({"k": np.arange(len(geoms))}, geometry=geoms, crs=ctx.grid.crs))


def test_vectors_kept_by_centre_once(tmp_path):
    g = _grid(160, 160)
    a = np.zeros(g.shape, np.float32)
    # small objects everywhere, some across the tile seams at 50, 100, 150
    rng = np.random.default_rng(3)
    centres = rng.integers(3, 157, size=(40, 2))
    for r, c in centres:
        a[r - 2 : r + 3, c - 2 : c + 3] = 2.0
    whole = blobs_tile({"x": a}, type("C", (), {"read_grid": g, "grid": g})())
    run = run_tiled(
        blobs_tile,
        g,
        {"x": ArraySource(a)},
        overlap_cells=8,
        tile_size=50,
        out=tmp_path,
        stage="blobs",
        scheduler="sync",
    )
    merged = run.vectors()
    assert len(merged) == len(whole.vectors)

    def key(gdf):
        return sorted(
            (round(b[0], 3), round(b[1], 3), round(b[2], 3), round(b[3], 3)) for b in gdf.geometry.bounds.to_numpy()
        )

    assert key(merged) == key(whole.vectors)


def _worker_threads(_):
    import os

    import numba

    return os.environ.get("NUMBA_NUM_THREADS"), numba.config.NUMBA_NUM_THREADS


@pytest.mark.slow
def test_processes_scheduler_same_result(tmp_path, monkeypatch):
    """Also: each local worker process runs numba on one thread (whatever this process's setting)."""
    from geocd.tiling.engine import open_engine

    monkeypatch.setenv("NUMBA_NUM_THREADS", "2")  # what a user's process has on a 2-core machine
    with open_engine("processes", n_workers=1, memory_limit="1GB") as eng:
        assert eng.client.submit(_worker_threads, 0).result() == ("1", 1)
    g = _grid()
    a = _field(g)
    run = run_tiled(
        focal_tile,
        g,
        {"x": ArraySource(a)},
        overlap_cells=RADIUS,
        tile_size=(64, 64),
        out=tmp_path,
        stage="focal",
        scheduler="processes",
        n_workers=2,
        memory_limit="1GB",
    )
    np.testing.assert_array_equal(run.read("f"), focal(a))


@pytest.mark.parametrize("merge_runs", [False, True])
def test_a_selection_of_tiles_runs_only_those_and_fills_the_rest(tmp_path, merge_runs):
    """A pass over some tiles (the tiered run's flagged tiles): only they run (runs of neighbours along a
    tile row as one unit with ``merge_runs``), their cores equal the whole grid's result (declared
    overlap), the other cores hold the product's fill value, and reading the store there gives NaN."""
    g = _grid()
    x = _field(g)
    want = focal(x)
    full = TileGrid(g, (64, 50), RADIUS)
    sel = np.zeros(full.shape, bool)
    sel[1, 1] = sel[1, 2] = sel[3, 2] = True
    tg = full.with_selection(sel, merge_runs=merge_runs)
    n_units = 2 if merge_runs else 3
    assert len(tg) == n_units and len(list(tg.all_tiles())) == len(full)
    if merge_runs:
        assert [t.core for t in tg] == [(64, 50, 64, 100), (192, 100, 11, 50)]
        assert [t.read for t in tg] == [(61, 47, 70, 106), (189, 97, 14, 56)]
    seen = []
    out = tmp_path / "sel"
    run = run_tiled(
        focal_tile,
        tg,
        {"x": ArraySource(x)},
        out=out,
        stage="focal-sel",
        products={"f": RasterProduct(str(out / "f.tif"), ("f",), fill={"f": -9.0}, nodata=-9999.0)},
        progress=lambda f, m: seen.append(m),
    )
    assert run.n_tiles == n_units and seen[-1].endswith(f"{n_units}/{n_units} tiles")
    assert len(list(run.smalls())) == n_units
    with rasterio.open(run.products["f"]) as ds:
        got = ds.read(1)
    examined = np.zeros(g.shape, bool)
    for t in tg:
        examined[t.core_slices] = True
    assert examined.sum() == sum(t.n_cells for t in tg) == 64 * 50 * 2 + 11 * 50
    np.testing.assert_array_equal(got[examined], want[examined])
    assert (got[~examined] == -9.0).all()
    a = run.read("f")
    assert np.isnan(a[~examined]).all()
    np.testing.assert_array_equal(a[examined], want[examined])
    with pytest.raises(ConfigError, match="tile selection has shape"):
        TileGrid(g, (64, 50), 0, np.zeros((2, 2), bool))


def test_release_local_stops_only_a_cluster_the_run_started():
    """The client's last whole-scene step runs without the workers of a LocalCluster it started; an engine
    given by the caller is left alone; tiles after the release run in this process."""
    from geocd.tiling.engine import Engine, open_engine

    with open_engine("sync") as eng:
        assert not eng.release_local()
    given = Engine("threads", 1)
    with open_engine(given) as eng:
        assert eng is given and not eng.release_local()
    with open_engine("threads", n_workers=1) as eng:
        assert eng.owned and eng.cluster is not None
        assert eng.release_local()
        assert eng.client is None and eng.cluster is None
        assert sorted(r for _, r in eng.map_unordered(lambda x, shared: x * 2, [1, 2, 3])) == [2, 4, 6]


def test_a_product_that_cannot_fit_is_refused_before_writing_and_the_rerun_resumes(tmp_path, monkeypatch):
    import geocd.tiling.writer as writer
    from geocd.errors import DiskFullError
    from geocd.io.outputs import OutputFolderWarning

    g = _grid()
    a = _field(g)
    prod = {"f": RasterProduct(str(tmp_path / "f.tif"), ("f",))}
    raw = writer.assembly_bytes(prod["f"], g.shape)
    assert raw == 203 * 157 * 4 * (1 + 1 / 4)  # one float32 band and its 2× overview
    kw = dict(overlap_cells=RADIUS, tile_size=64, out=tmp_path, stage="focal", products=prod, scheduler="sync")
    # the assembly GeoTIFF and a 4× compressed COG would not fit: refused, nothing written beside the tiles
    monkeypatch.setattr(writer, "free_bytes", lambda p: int(raw * 1.2))
    with pytest.raises(DiskFullError, match=r"f\.tif.*free some space and run the same command again"):
        run_tiled(focal_tile, g, {"x": ArraySource(a)}, **kw)
    assert sorted(p.name for p in tmp_path.iterdir()) == [WORK_DIR]
    assert not list((tmp_path / WORK_DIR).rglob("*.part*"))
    # room for a compressed COG but not for an incompressible one: written, with a warning
    monkeypatch.setattr(writer, "free_bytes", lambda p: int(raw * 1.5))
    with pytest.warns(OutputFolderWarning, match="may need up to"):
        run = run_tiled(focal_tile, g, {"x": ArraySource(a)}, **kw)
    assert run.n_resumed == run.n_tiles  # the rerun only assembled the product
    np.testing.assert_array_equal(run.read("f"), focal(a))
