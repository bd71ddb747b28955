"""The tiered run (geocd run --screen): flagged tiles, stereo on them only, the not-examined code."""

from __future__ import annotations

import numpy as np
import pytest

from geocd.change.building_layer import CHANGED
from geocd.screen.tiered import flag_tiles


def test_flagged_tiles_are_the_tiling_layers_tiles():
    changed = np.zeros((300, 260), bool)
    changed[10:12, 10:12] = True  # tile (0, 0)
    changed[70:75, 40:45] = True  # tile (1, 0)
    changed[200:210, 200:205] = True  # tile (3, 3)
    fl = flag_tiles(changed, 64)
    assert fl.tiles.shape == (5, 5)
    assert fl.tiles.sum() == 3 and np.isclose(fl.tile_fraction, 3 / 25)
    assert sorted(zip(*np.nonzero(fl.tiles))) == [(0, 0), (1, 0), (3, 3)]
    ex = fl.examined(changed.shape)
    assert ex.shape == changed.shape and ex[changed].all()  # every changed cell is in an examined tile
    assert ex.sum() == 64 * 64 * 3 and np.isclose(fl.cell_fraction(changed.shape), ex.mean())
    assert not ex[64:128, 64:128].any()  # an unflagged tile
    # the tiles are the tiling layer's: same cores
    from affine import Affine

    from geocd.geodesy import AOIGrid
    from geocd.tiling import TileGrid

    tg = TileGrid(AOIGrid("EPSG:32631", Affine(1, 0, 0, 0, -1, 0), 260, 300), 64, 0, fl.tiles)
    m = np.zeros(changed.shape, bool)
    for t in tg:
        m[t.core_slices] = True
    np.testing.assert_array_equal(m, ex)
    # a tile needs min_cells changed cells
    assert flag_tiles(changed, 64, min_cells=10).tiles.sum() == 2
    assert not flag_tiles(np.zeros((50, 50), bool), 64).tiles.any()


def _flag_most_changed_tiles(m, grid, tile, k):
    """The k tiles holding the most truth change, plus nothing else (a stand-in for the screen's flags)."""
    from geocd.io.raster import read_on_grid

    truth = np.nan_to_num(read_on_grid(m.truth_path("change_mask"), grid)) > 0
    H, W = grid.shape
    nr, nc = -(-H // tile), -(-W // tile)
    pad = np.zeros((nr * tile, nc * tile), bool)
    pad[:H, :W] = truth
    counts = pad.reshape(nr, tile, nc, tile).sum(axis=(1, 3))
    sel = np.zeros((nr, nc), bool)
    sel.flat[np.argsort(counts.ravel())[::-1][:k]] = True
    return sel


@pytest.fixture(scope="module")
def full_run(request, tmp_path_factory):
    """sample_aoi's cached pair-DEMs and the full (untiered) change run on them, without the building
    derivation: (manifest, {epoch: [PairDEM]}, grid, run_change's answer), shared by the tests below."""
    from geocd.pipeline import RunConfig, run_change
    from tests.sample_aoi_cache import sample_aoi_pairs

    m, full, grid = sample_aoi_pairs(request.config.cache.mkdir("geocd_sample_aoi_stereo"))
    rf = run_change(m, full, grid, out_dir=tmp_path_factory.mktemp("full"), config=RunConfig(derive_buildings=False))
    return m, full, grid, rf


@pytest.mark.slow
def test_tiered_stereo_and_change_run_only_on_flagged_tiles(sample_aoi, tmp_path, full_run):
    """sample_aoi, two flagged 128-cell tiles of 25: stereo matches only those tiles (tile count, the
    flags value 255 and no height elsewhere), their heights equal the full run's within the tiled
    stereo's tolerance, and the change mask codes every other cell −127 "not examined" while the
    flagged tiles' change map agrees with the full run's there."""
    import rasterio

    from geocd.consistency import NOT_EXAMINED
    from geocd.tiling.params import TilingParams
    from geocd.pipeline import RunConfig, run_change
    from geocd.screen.tiered import Flagged
    from geocd.stereo import read_pair_dem
    from geocd.stereo.products import FLAGS_NOT_EXAMINED
    from geocd.stereo.tiled import run_stereo_tiled

    m, full, grid, rf = full_run
    tile = 128
    sel = _flag_most_changed_tiles(m, grid, tile, 2)
    fl = Flagged(tile, sel)
    ex = fl.examined(grid.shape)
    cfg = RunConfig()
    st = run_stereo_tiled(
        m,
        out_dir=tmp_path / "t",
        epochs=["B"],
        params=cfg.stereo,
        grid=grid,
        pairs=cfg.pairs,
        tiling=TilingParams(tile_size=tile, scheduler="sync"),
        tiles=sel,
    )
    tiered = {k.split("/", 1)[1]: read_pair_dem(p) for k, p in st["outputs"].items()}
    assert len(tiered) == 3
    by_name = {p.name: p for p in full["B"]}
    for name, t in tiered.items():
        assert t.meta["tiled"]["tiles"] == 2 and t.meta["tiled"]["tiles_in_grid"] == 25
        # nothing outside the flagged tiles: no height, not valid, flags 255 (not examined)
        assert not t.valid[~ex].any() and np.isnan(t.z_m[~ex]).all()
        assert (t.flags[~ex] == FLAGS_NOT_EXAMINED).all() and not (t.flags[ex] == FLAGS_NOT_EXAMINED).any()
        f = by_name[name]
        both = t.valid & f.valid & ex
        # the tiled stereo's tolerance (docs/tiling.md: 94-98 % of cells within 0.1 m of the untiled match)
        close = np.abs(t.z_m[both] - f.z_m[both]) <= 0.1
        assert close.mean() >= 0.90, (name, close.mean())
        assert abs(t.valid[ex].mean() - f.valid[ex].mean()) <= 0.02, name
    # the change test and products with the examined mask
    cfg = RunConfig(derive_buildings=False)
    rt = run_change(
        m, {"A": full["A"], "B": list(tiered.values())}, grid, out_dir=tmp_path / "tier", config=cfg, examined=ex
    )
    with rasterio.open(rt["outputs"]["change_mask"]) as ds:
        mt = ds.read(1)
    with rasterio.open(rf["outputs"]["change_mask"]) as ds:
        mf = ds.read(1)
    assert (mt[~ex] == NOT_EXAMINED).all() and not (mt[ex] == NOT_EXAMINED).any()
    assert rt["summary"]["examined_fraction"] == pytest.approx(ex.mean(), abs=1e-4)
    chf, cht = (mf == 1) | (mf == -1), (mt == 1) | (mt == -1)
    assert chf[ex].sum() > 400  # the flagged tiles hold real change (804 cells)
    inter = (chf & cht & ex).sum()
    union = ((chf | cht) & ex).sum()
    # changed cells of the flagged tiles vs the full run: Jaccard 0.862 measured (804 full, 725 tiered cells)
    assert inter / union >= 0.80, inter / union
    assert abs(int(cht[ex].sum()) - int(chf[ex].sum())) <= 0.15 * chf[ex].sum()
    # the buildings layer: no building outside the flagged tiles is reported unchanged by silence
    b = rt["buildings"]
    if b is not None and len(b):
        outside = b["frac_examined"] == 0
        assert not b.loc[outside, "class"].isin(["unchanged", *CHANGED]).any()


@pytest.mark.slow
def test_unflagged_cells_are_not_examined_never_unchanged(sample_aoi, tmp_path, full_run):
    """The change products of a tiered run on the full run's pair-DEMs: inside the flagged tiles the mask is
    the full run's, bit for bit; every other cell is −127 "not examined" (never 0); unobserved buildings
    reaching into unflagged tiles are "not examined"; the summary says how much was examined."""
    import rasterio

    from geocd.consistency import NOT_EXAMINED, SelfConsistencyModel
    from geocd.pipeline import RunConfig, run_change
    from geocd.screen.tiered import Flagged

    m, full, grid, rf = full_run
    sel = np.zeros((5, 5), bool)
    sel[1:3, 1:4] = True
    ex = Flagged(128, sel).examined(grid.shape)
    cfg = RunConfig(derive_buildings=False)
    # the model the full run learned on these pair-DEMs (learning it again gives the same model)
    model = SelfConsistencyModel.load(rf["outputs"]["model"])
    rt = run_change(m, full, grid, out_dir=tmp_path / "tier", config=cfg, examined=ex, model=model)
    with rasterio.open(rt["outputs"]["change_mask"]) as ds:
        mt = ds.read(1)
        assert "-127 not examined" in ds.tags(1).get("long_name", "")
    with rasterio.open(rf["outputs"]["change_mask"]) as ds:
        mf = ds.read(1)
    np.testing.assert_array_equal(mt[ex], mf[ex])
    assert (mt[~ex] == NOT_EXAMINED).all()
    assert not (mf == NOT_EXAMINED).any()
    assert rt["summary"]["examined_fraction"] == pytest.approx(6 * 128 * 128 / 360000, abs=1e-4)
    assert "examined_fraction" not in rf["summary"]
    b, bf = rt["buildings"], rf["buildings"]
    assert "frac_examined" in b and "frac_examined" not in bf
    ne = (b["class"] == "not examined").to_numpy()
    assert ne.any()
    assert (bf["class"].to_numpy()[ne] == "unobserved").all() and (b["frac_examined"].to_numpy()[ne] < 1).all()
    keep = ~ne
    np.testing.assert_array_equal(b["class"].to_numpy()[keep], bf["class"].to_numpy()[keep])
    # the whole grid examined (a tiered run that matched everything): the full run's classes, also for
    # footprints with no cell on the grid (they stay unobserved)
    ra = run_change(
        m, full, grid, out_dir=tmp_path / "all", config=cfg, examined=np.ones(grid.shape, bool), model=model
    )
    np.testing.assert_array_equal(ra["buildings"]["class"].to_numpy(), bf["class"].to_numpy())


def test_calibration_is_fitted_on_screen_unchanged_cells_not_on_the_flagged_change():
    """A scene-class model applied to data twice as noisy (true scale 2). The examined half of the grid holds
    many weak changes (40 % of its cells, 1.5–4 × the static spread: too weak to be trimmed by the fit). Fitted
    on every examined cell (what the change test does alone) the scale is biased high; fitted on the cells the
    screen calls unchanged (dissimilarity ≤ the no-change median, away from screen-changed cells) it is the
    static scene's."""
    from types import SimpleNamespace

    from geocd.consistency import ChangeParams, ConsistencyParams, change_test, learn_self_consistency
    from geocd.screen.tiered import calibration_cells, fit_calibration_on

    from ..fakes import Rec

    shape = (200, 200)
    grid = SimpleNamespace(posting_m=1.0)

    def rec(truth, rng, name, noise):
        score = rng.uniform(-2.0, 1.0, shape).astype(np.float32)
        err = rng.normal(size=shape) * (0.1 + 0.3 * (score + 2.0)) * noise
        return Rec(
            (truth + err).astype(np.float32), score, np.ones(shape, np.float32), np.ones(shape, bool), grid, name
        )

    rng = np.random.default_rng(4)
    flat = np.zeros(shape, np.float32)
    model = learn_self_consistency(
        [[rec(flat, rng, f"M{i}", 1.0) for i in range(3)]], ConsistencyParams(n_score_bins=10, min_bin_count=500)
    )
    examined = np.zeros(shape, bool)
    examined[:, :100] = True
    # weak changes: 8 × 8 blocks over 40 % of the examined half
    blocks = rng.random((25, 13)) < 0.4
    weak = np.repeat(np.repeat(blocks, 8, 0), 8, 1)[:, :100]
    truth_b = flat.copy()
    truth_b[:, :100][weak] += rng.choice([-1.0, 1.0], weak.sum()) * rng.uniform(1.5, 4.0, weak.sum())
    A = [rec(flat, rng, "A0", 2.0)]
    B = [rec(truth_b, rng, "B0", 2.0)]
    # the screen: changed blocks look dissimilar (some above its threshold, the rest between the null's
    # median and the threshold), static cells look alike
    d = rng.uniform(0.3, 0.9, shape)
    ch_cells = np.zeros(shape, bool)
    ch_cells[:, :100] = weak
    d[ch_cells] = rng.uniform(1.1, 1.6, ch_cells.sum())
    screen_changed = ch_cells & (d > 1.4)
    cells = calibration_cells(d, 1.0, screen_changed, examined, 2)
    assert cells.sum() > 5000 and not (cells & ~examined).any() and not (cells & ch_cells).any()
    params = ChangeParams()
    new, offsets = fit_calibration_on(A, B, model, params, cells)

    # the change test alone, seeing only the examined cells (the old behaviour): fitted on all of them
    def only(r, keep):
        return Rec(
            np.where(keep, r.z_m, np.nan).astype(np.float32), r.score, r.g_px_per_m, r.valid & keep, grid, r.name
        )

    old = change_test([only(A[0], examined)], [only(B[0], examined)], model, params).calibration
    whole_static = fit_calibration_on(A, B, model, params, ~ch_cells)[0]
    assert whole_static.scale == pytest.approx(2.0, rel=0.1)
    assert new.scale == pytest.approx(whole_static.scale, rel=0.05)
    assert old.scale > 1.15 * whole_static.scale
    # the change test takes the calibration and the offsets it was fitted with
    res = change_test(A, B, model, params, offsets=offsets, calibration=new)
    assert res.calibration is new


def test_stereo_plan_sizes_windows_from_the_scene_and_falls_back_to_the_whole_grid():
    """Windows keep every coarse level (side ≥ the pair's need, in whole screen tiles); when they would read the
    whole grid anyway (a small scene, scattered flags) the whole grid is matched once, untiled."""
    from geocd.screen.tiered import Flagged, plan_stereo

    # Kahramanmaraş's grid and flags (25 of 72 128-cell tiles, spread over the scene), 448-cell need, 64 margin
    flags = np.zeros((8, 9), bool)
    for i, j in [
        (0, 1),
        (0, 2),
        (0, 4),
        (0, 5),
        (1, 3),
        (1, 4),
        (3, 2),
        (4, 0),
        (4, 1),
        (4, 2),
        (4, 3),
        (4, 4),
        (4, 5),
        (5, 1),
        (5, 2),
        (5, 3),
        (5, 6),
        (5, 7),
        (6, 3),
        (6, 4),
        (7, 1),
        (7, 3),
        (7, 4),
        (7, 5),
        (7, 6),
    ]:
        flags[i, j] = True
    p = plan_stereo(Flagged(128, flags), (1004, 1048), 448, 64)
    assert p.tile_cells == 512 and p.whole_grid and p.examined((1004, 1048)).all()
    # a city of 8 000² cells with two flagged screen tiles far apart: two 512-cell windows, margin once each
    big = np.zeros((63, 63), bool)
    big[5, 5] = big[40, 50] = True  # stereo tiles (1, 1) and (10, 12), inside the grid
    p = plan_stereo(Flagged(128, big), (8000, 8000), 448, 64)
    assert not p.whole_grid and p.tile_cells == 512 and p.tiles.sum() == 2
    assert p.read_cells == 2 * (512 + 128) ** 2
    ex = p.examined((8000, 8000))
    assert ex.sum() == 2 * 512**2 and ex[5 * 128, 5 * 128] and ex[40 * 128, 50 * 128]
    # neighbouring stereo tiles of a row share one window (one margin)
    big[5, 9] = True  # stereo tile (1, 2), beside (1, 1)
    p = plan_stereo(Flagged(128, big), (8000, 8000), 448, 64)
    assert p.tiles.sum() == 3 and p.read_cells == (2 * 512 + 128) * (512 + 128) + (512 + 128) ** 2
    # a need below the screen's tile: the screen's tiles as they are
    assert plan_stereo(Flagged(128, big), (8000, 8000), 100, 64).tile_cells == 128


def _local_event_screen(seed: int = 3, with_change: bool = True):
    """A screened pair and a no-change pair on 768² cells (6 × 6 tiles of 128, 16-cell screen units), built unit by
    unit. Stable units: 0.30 + Exp(0.08) (the cross-date pair: views 5° apart, buildings lean alike); the no-change
    pair: 0.35 + Exp(0.25) (its views 18° apart: buildings lean differently, a wider distribution). A local event in
    tiles (2..3, 2..3): two changed houses of 1 × 2 units per tile, d ∈ [0.95, 1.3] — above the stable values,
    below the no-change pair's 99 % (≈ 1.5) — plus one house across the edge of tiles (3, 3) and (3, 4), 1.5
    units in the first, 0.5 in the second."""
    rng = np.random.default_rng(seed)
    n = 48
    units = 0.30 + rng.exponential(0.08, (n, n))
    null_units = 0.35 + rng.exponential(0.25, (n, n))
    houses = []
    if with_change:
        for ti in (2, 3):
            for tj in (2, 3):
                houses += [(8 * ti + 1, 8 * tj + 1), (8 * ti + 4, 8 * tj + 5)]
        for i, j in houses:
            units[i : i + 1, j : j + 2] = rng.uniform(0.95, 1.3, 2)
    d = np.kron(units, np.ones((16, 16))).astype(np.float32)
    if with_change:  # the straddling house: cells 3·128 + 40 … + 56 rows, cols 3·128 + 104 … 4·128 + 8
        r0, c0 = 3 * 128 + 40, 3 * 128 + 104
        d[r0 : r0 + 16, c0 : c0 + 32] = 1.2
    null = np.kron(null_units, np.ones((16, 16))).astype(np.float32)
    return d, null


def test_flag_rule_holds_recall_when_the_no_change_pair_is_wider_than_the_screened_pair():
    """The no-change pair's views are farther apart than the screened pair's, so its 99 % quantile (≈ 1.5) sits
    above every changed house (0.95–1.3). The old rule (that quantile, then Otsu's split above it, any region
    flags its tile) flags none of the event's tiles; the tiered run's rule (the lower of that quantile and the
    screened pair's own 99 % one; a tile flagged when its changed area exceeds a Binomial(64, 0.01) count's 99 %
    quantile, 3 units; plus tiles a flagged tile's changed region reaches into) flags exactly the five tiles the
    event touches. Without change, the rule flags at most one tile of 36 by chance."""
    from scipy import ndimage

    from geocd.screen.threshold import NullDistribution, threshold_from_nochange
    from geocd.screen.tiered import chance_cells, flag_threshold, flag_tiles_by_chance

    d, null_d = _local_event_screen()
    valid = np.ones(d.shape, bool)
    null = NullDistribution.from_values(null_d, "A: A1/A2")
    event = np.zeros((6, 6), bool)
    event[2:4, 2:4] = True
    reached = event.copy()
    reached[3, 4] = True

    def regions(t):
        c = d > t
        lab, n = ndimage.label(c, structure=np.ones((3, 3), bool))
        keep = np.bincount(lab.ravel()) >= 16
        keep[0] = False
        return keep[lab]

    # the old rule: the no-change pair's 99 % quantile, then Otsu's split above it; any region flags its tile
    t_old = threshold_from_nochange(null_d, 1.0, d_test=d)
    assert t_old > 1.4
    assert not (flag_tiles(regions(t_old), 128).tiles & event).any()
    # the new rule: the screened pair's own quantile is the lower bound here, and the rule says so
    t, rule, info = flag_threshold(d, null, 1.0)
    assert t == pytest.approx(np.quantile(d, 0.99)) and t < 0.95 < null.threshold(1.0)
    assert "own" in rule and info["own_quantile"] < info["null_quantile"]
    assert chance_cells(np.array([64.0]), 0.01, 0.01)[0] == 3
    fl, tinfo = flag_tiles_by_chance(regions(t), valid, 128, 16, 0.01)
    np.testing.assert_array_equal(fl.tiles, reached)
    assert tinfo["tiles_by_chance_rule"] == 4 and tinfo["tiles_added_by_reach"] == 1
    # with the no-change pair's threshold instead of the lower bound, the event is lost (the old threshold fails)
    fl_null, _ = flag_tiles_by_chance(regions(null.threshold(1.0)), valid, 128, 16, 0.01)
    assert not (fl_null.tiles & event).any()
    # nothing changed: the own quantile flags 1 % of the cells by construction, scattered; chance keeps them out
    d0, _ = _local_event_screen(with_change=False)
    t0, _, _ = flag_threshold(d0, null, 1.0)
    c0 = d0 > t0
    assert 0.005 < c0.mean() <= 0.011
    fl0, _ = flag_tiles_by_chance(c0, valid, 128, 16, 0.01)
    assert fl0.tiles.sum() <= 1
    assert flag_tiles(c0, 128).tiles.sum() > 10  # the old "any region" tile rule would flag most tiles
    # no no-change pair and too few screened values: a clear error, not a threshold of nothing
    from geocd.errors import EmptyDataError

    with pytest.raises(EmptyDataError, match="no-change pair"):
        flag_threshold(np.full((5, 5), np.nan), None, 1.0)


def test_geocd_run_screen_takes_a_cnn_feature(sample_aoi, tmp_path):
    """`geocd run --screen --screen-feature cnn` builds the screen's CNN spec from --screen-backbone/-weights/-layer
    (checked before any stereo: a missing weights file is refused with where trained ones come from)."""
    from click.testing import CliRunner

    from geocd.cli import main

    r = CliRunner().invoke(
        main,
        [
            "--progress",
            "none",
            "run",
            str(sample_aoi),
            "--screen",
            "--screen-feature",
            "cnn",
            "--screen-backbone",
            "efficientnet_lite0",
            "--out",
            str(tmp_path / "out"),
        ],
    )
    assert r.exit_code != 0
    assert "weights file the user names" in r.output and "efficientnet_lite0" in r.output
    assert not (tmp_path / "out" / "stereo").exists()
