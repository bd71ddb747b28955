"""Self-consistency test on synthetic reconstructions with a known error model."""

import numpy as np
import pytest

from geocd.consistency import (
    CHANGE_NODATA,
    ChangeParams,
    ConsistencyParams,
    DEMAsEpoch,
    SelfConsistencyModel,
    change_test,
    learn_self_consistency,
    match_pairs,
    naive_threshold,
)
from geocd.errors import ConfigError, GridError, ProcessingError

from .fakes import Rec


SHAPE = (120, 120)


def make_rec(truth, rng, name, g=1.0, outlier_frac=0.0):
    """A reconstruction whose disparity error (px) grows with the score (as real matchers do)."""
    score = rng.uniform(-2.0, 1.0, SHAPE).astype(np.float32)  # lower = better
    sigma_px = 0.1 + 0.3 * (score + 2.0)  # 0.1 .. 1.0 px
    err_px = rng.normal(size=SHAPE) * sigma_px
    bad = rng.random(SHAPE) < outlier_frac * (score + 2) / 3
    err_px[bad] += rng.normal(scale=10, size=bad.sum())
    gg = np.full(SHAPE, g, np.float32)
    z = truth + err_px / gg
    valid = rng.random(SHAPE) > 0.05
    return Rec(np.where(valid, z, np.nan).astype(np.float32), score, gg, valid, None, name)


@pytest.fixture
def scene():
    rng = np.random.default_rng(42)
    truth_a = np.zeros(SHAPE, np.float32)
    truth_b = truth_a.copy()
    truth_b[20:50, 20:50] += 9.0  # new building (+9 m)
    truth_b[70:100, 60:90] -= 8.0  # demolished/lowered
    A = [make_rec(truth_a, rng, f"A{i}", outlier_frac=0.02) for i in range(3)]
    B = [make_rec(truth_b, rng, f"B{i}", outlier_frac=0.02) for i in range(3)]
    return A, B, truth_b - truth_a


def test_match_pairs_normalization():
    z = np.zeros((2, 2), np.float32)
    p = Rec(z, np.zeros((2, 2)), np.full((2, 2), 0.5), np.ones((2, 2), bool), name="p")
    q = Rec(z + 2.0, np.ones((2, 2)), np.full((2, 2), 0.5), np.ones((2, 2), bool), name="q")
    dt, sc, dz, both = match_pairs(p, q)
    # 2 m at 0.5 px/m on both sides: 2 / sqrt(4 + 4) = 0.7071 px
    assert np.allclose(dt, 2 / np.sqrt(8)) and np.all(sc == 1) and np.all(dz == 2) and both.all()
    d = DEMAsEpoch(z + 2.0, None, "lidar")
    dt2, sc2, _, _ = match_pairs(p, d)
    assert np.allclose(dt2, 2 * 0.5) and np.all(sc2 == 0)  # only the stereo side's uncertainty and score
    with pytest.raises(GridError):
        match_pairs(p, Rec(np.zeros((3, 3)), np.zeros((3, 3)), np.ones((3, 3)), np.ones((3, 3), bool)))


def test_curves_follow_the_error_model(scene):
    A, B, _ = scene
    model = learn_self_consistency([A, B[:0]], ConsistencyParams(n_score_bins=10, min_bin_count=500))
    # |Δ̃| between two recs of the same score s: normal with sigma sqrt(2)*sigma_px(s)/sqrt(2) ... combine
    c99 = np.asarray(model.curves["99"])
    c90 = np.asarray(model.curves["90"])
    assert np.all(np.diff(c99) >= -1e-9), "curves must be non-decreasing in score"
    assert np.all(c99 >= c90)
    assert c99[-1] > 2 * c99[0], "worse scores must get wider thresholds"
    assert model.bin_counts.sum() == model.provenance["n_match_pairs"]
    # fraction of same-epoch match pairs above the 99% curve ≈ 1%
    dt, sc, _, both = match_pairs(A[0], A[1])
    frac = np.mean(np.abs(dt[both]) > model.threshold(sc[both], 99))
    assert 0.003 < frac < 0.03


def test_change_test_finds_changes_with_low_false_alarms(scene):
    A, B, dz_true = scene
    model = learn_self_consistency([A, B])
    res = change_test(A, B, model, ChangeParams(confidences=(90, 95, 99)))
    truth = np.sign(dz_true)
    ch99 = res.changed_at(99)
    obs = res.observed
    inner_up = np.zeros(SHAPE, bool)
    inner_up[22:48, 22:48] = True
    ch95 = res.changed_at(95)
    # outliers at bad scores widen the 99% curve: most, not all, changed cells pass at 99%
    assert np.mean(ch99[inner_up & obs] == 1) > 0.6
    assert np.mean(ch95[inner_up & obs] == 1) > 0.9
    assert np.mean(ch95[70:100, 60:90][obs[70:100, 60:90]] == -1) > 0.85
    static = (truth == 0) & obs
    fa = np.mean(ch99[static] != 0)
    assert fa < 0.01, f"false-alarm rate {fa:.4f} on static cells at 99%"
    assert np.all(res.change[~obs] == CHANGE_NODATA)
    # without the minimum-size filter, speckle appears; naive |Δ̃| > 3 raises more of it than the test at 99%
    raw = change_test(A, B, model, ChangeParams(confidences=(99,), min_region_cells=1))
    fa_raw = np.mean(raw.changed_at(99)[static] != 0)
    assert fa <= fa_raw
    naive = naive_threshold(A, B, 3.0, min_region_cells=1)
    assert np.mean(naive[static] != 0) > fa_raw


def test_model_round_trip_and_new_confidence(tmp_path, scene):
    A, B, _ = scene
    model = learn_self_consistency([A], provenance={"scene_class": "synthetic"})
    p = model.save(tmp_path / "m.json")
    back = SelfConsistencyModel.load(p)
    assert back.provenance["scene_class"] == "synthetic"
    s = np.linspace(-2, 1, 7)
    assert np.allclose(back.threshold(s, 99), model.threshold(s, 99))
    t80 = back.threshold(s, 80)  # not stored: recomputed from the histogram
    assert np.all(t80 <= back.threshold(s, 90) + 1e-9)
    with pytest.raises(ConfigError):
        back.threshold(s, 100)


def test_one_pair_per_epoch_needs_a_model(scene):
    A, B, _ = scene
    with pytest.raises(ProcessingError, match="scene-class model"):
        learn_self_consistency([A[:1], B[:1]])
    # with a model learned elsewhere, one pair per epoch works
    model = learn_self_consistency([A])
    res = change_test(A[:1], B[:1], model)
    assert res.comparisons == ["A0 vs B0"]
    assert (res.changed_at(95)[25:45, 25:45] == 1).mean() > 0.8


def test_vertical_offsets_between_reconstructions_are_removed(scene):
    """RPC biases shift whole pair-DEMs: a +3 m offset on one epoch-B rec must not become a change."""
    from geocd.consistency import align_reconstructions

    A, B, dz_true = scene
    shifted = Rec(B[1].z_m + 3.0, B[1].score, B[1].g_px_per_m, B[1].valid, None, "B1+3m")
    recs, off = align_reconstructions([A[0], A[1], shifted])
    assert abs(off["A1"] - off["A0"]) < 0.05 and abs(off["B1+3m"] - off["A0"] - 3.0) < 0.1
    model = learn_self_consistency([A, B])
    res = change_test(A, [B[0], shifted, B[2]], model)
    static = (dz_true == 0) & res.observed
    assert np.mean(res.changed_at(99)[static] != 0) < 0.01
    raw = change_test(A, [B[0], shifted, B[2]], model, ChangeParams(align="none"))
    assert np.mean(raw.changed_at(95)[static] != 0) > np.mean(res.changed_at(95)[static] != 0)
    with pytest.raises(ConfigError):
        ChangeParams(align="sideways")


def test_unobserved_cells_are_nodata_at_every_level(scene):
    """changed_at must say "not seen" where no comparison observed a cell, not "unchanged"."""
    A, B, _ = scene
    hole = np.zeros(SHAPE, bool)
    hole[20:50, 20:50] = True  # the new building is hidden in every epoch-B reconstruction
    B2 = [Rec(np.where(hole, np.nan, r.z_m), r.score, r.g_px_per_m, r.valid & ~hole, None, r.name) for r in B]
    res = change_test(A, B2, learn_self_consistency([A, B]))
    for lev in (90, 95, 99):
        m = res.changed_at(lev)
        assert np.all(m[hole] == CHANGE_NODATA) and np.all(m[~res.observed] == CHANGE_NODATA)
        assert set(np.unique(m[res.observed])) <= {-1, 0, 1}


def test_results_do_not_depend_on_the_order_of_the_reconstructions(scene):
    """Giving the pair-DEMs in another order must not change a single cell (nor the offsets)."""
    A, B, _ = scene
    rng = np.random.default_rng(11)
    # different biases and coverage per reconstruction, so the choice of a reference would matter
    A = [
        Rec(
            r.z_m + np.float32(rng.normal(scale=0.5)),
            r.score,
            r.g_px_per_m,
            r.valid & (rng.random(SHAPE) > 0.2),
            None,
            r.name,
        )
        for r in A
    ]
    B = [
        Rec(
            r.z_m + np.float32(rng.normal(scale=0.5)),
            r.score,
            r.g_px_per_m,
            r.valid & (rng.random(SHAPE) > 0.2),
            None,
            r.name,
        )
        for r in B
    ]
    model = learn_self_consistency([A, B])
    assert model.hist.tolist() == learn_self_consistency([A[::-1], B[::-1]]).hist.tolist()
    ref = change_test(A, B, model)
    for a, b in ((A[::-1], B), (A, B[::-1]), ([A[1], A[2], A[0]], [B[2], B[0], B[1]])):
        res = change_test(a, b, model)
        assert res.vertical_offsets_m == ref.vertical_offsets_m and res.comparisons == ref.comparisons
        for k in ("confidence", "change", "dz_m", "dtilde", "score"):
            assert np.array_equal(getattr(res, k), getattr(ref, k), equal_nan=True), k


def test_offsets_are_separable_from_the_per_cell_test(scene):
    """Offsets computed once on the whole scene and passed to a tile give the whole-scene answer on that tile."""
    from geocd.consistency import vertical_offsets

    A, B, _ = scene
    model = learn_self_consistency([A, B])
    whole = change_test(A, B, model)
    off = vertical_offsets(A + B)
    assert off == whole.vertical_offsets_m
    sl = (slice(10, 60), slice(10, 60))
    tile = lambda rs: [Rec(r.z_m[sl], r.score[sl], r.g_px_per_m[sl], r.valid[sl], None, r.name) for r in rs]  # noqa: E731
    t = change_test(tile(A), tile(B), model, ChangeParams(min_region_cells=1), offsets=off)
    w1 = change_test(A, B, model, ChangeParams(min_region_cells=1), offsets=off)
    assert np.array_equal(t.confidence, w1.confidence[sl], equal_nan=True)


def test_pvalues_are_calibrated_on_static_data(scene):
    A, B, _ = scene
    model = learn_self_consistency([A[:2]], ConsistencyParams(n_score_bins=10, min_bin_count=500))
    dt, sc, _, both = match_pairs(A[0], A[2])  # a comparison the model did not see
    p = model.pvalue(dt[both], sc[both])
    for a in (0.01, 0.05, 0.2):
        assert np.mean(p < a) == pytest.approx(a, rel=0.35), a
    # larger disagreement at the same score is rarer
    s = np.full(5, float(np.median(sc[both])))
    assert np.all(np.diff(model.pvalue(np.array([0.1, 0.5, 1.0, 2.0, 5.0]), s)) <= 0)
    assert np.isnan(model.pvalue(np.array([np.nan]), np.array([0.0]))[0])


def test_combine_pvalues_majority_all_any():
    from geocd.consistency import combine_pvalues

    P = np.array([0.001, 0.02, 0.5, np.nan]).reshape(4, 1, 1)
    S = np.array([1, 1, -1, 1], np.int8).reshape(4, 1, 1)
    sign = np.ones((1, 1), np.int8)
    # three observed: 0.001 and 0.02 agree, 0.5 has the other sign (counts as 1)
    assert combine_pvalues(P, S, sign, "majority")[0, 0] == pytest.approx(0.02)
    assert combine_pvalues(P, S, sign, "all")[0, 0] == pytest.approx(1.0)
    assert combine_pvalues(P, S, sign, "any")[0, 0] == pytest.approx(0.001)
    assert combine_pvalues(P, S, np.zeros((1, 1), np.int8))[0, 0] == 1.0


def test_candidate_regions_and_their_evidence():
    from geocd.consistency import candidate_regions

    p = np.ones((8, 8))
    p[1:3, 1:3] = 0.001  # 4 strong cells
    p[5:7, 5:8] = 0.04  # 6 weak cells
    p[0, 7] = 1e-6  # a single extreme cell
    sign = np.ones((8, 8), np.int8)
    lab, mass, sg = candidate_regions(p, sign, 0.05, 4)
    assert lab.max() == 2 and sorted(np.bincount(lab.ravel())[1:]) == [4, 6]
    assert sorted(mass) == pytest.approx(sorted([4 * np.log(50), 6 * np.log(0.05 / 0.04)]))
    assert (sg == 1).all() and lab[0, 7] == 0  # below the mapping unit


def test_region_test_and_mapping_unit(scene):
    A, B, dz_true = scene
    model = learn_self_consistency([A, B], ConsistencyParams(min_region_cells=16))
    assert model.region_null["min_region_cells"] == 16 and model.has_region_test
    res = change_test(A, B, model)
    assert res.significance == "region" and res.min_region_cells == 16
    static = (dz_true == 0) & res.observed
    inner = np.zeros(SHAPE, bool)
    inner[22:48, 22:48] = True
    assert np.mean(res.changed_at(99)[inner & res.observed] == 1) > 0.9
    assert np.mean(res.changed_at(99)[static] != 0) < 0.005
    assert np.all(np.isfinite(res.cell_confidence[res.observed])) and np.all(
        np.isnan(res.cell_confidence[~res.observed])
    )
    # σ of dz from the error model: the synthetic errors are 0.1-1 px at g = 1 px/m, two reconstructions
    assert 0.1 < float(np.nanmedian(res.dz_sigma_m)) < 1.2
    # a 3 x 3 change (9 cells) is below the mapping unit: never reported
    B2 = [
        Rec(
            r.z_m + np.where(np.pad(np.ones((3, 3)), ((100, 17), (100, 17))) > 0, 9.0, 0.0).astype(np.float32),
            r.score,
            r.g_px_per_m,
            r.valid,
            None,
            r.name,
        )
        for r in B
    ]
    res2 = change_test(A, B2, model)
    assert np.all(res2.changed_at(90)[100:103, 100:103] <= 0)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_nanmedian_stack_equals_numpy(dtype):
    """Same values and dtype as ``np.nanmedian(stack, axis=0)`` — cells with 0 to n values, all-NaN grids, no NaN."""
    import warnings

    from geocd.stereo.surface import nanmedian_stack

    rng = np.random.default_rng(4)
    for n in (1, 2, 3, 4):
        a = rng.normal(size=(n, 40, 50)).astype(dtype)
        a[rng.uniform(size=a.shape) < 0.5] = np.nan
        a[:, :10] = np.nan  # a block no layer observes
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            want = np.nanmedian(a, axis=0)
        got = nanmedian_stack(a)
        assert got.dtype == want.dtype and np.isnan(got[:10]).all()
        np.testing.assert_array_equal(got, want)
        full = np.nan_to_num(a)
        np.testing.assert_array_equal(nanmedian_stack(full), np.median(full, axis=0))
        assert np.isnan(nanmedian_stack(np.full_like(a, np.nan))).all()


def test_isotonic_fit_equals_scikit_learns_to_rounding():
    """Pool-adjacent-violators with weights; gaps (NaN, zero weight) on the line between their fitted neighbours,
    the ends held, as ``IsotonicRegression(out_of_bounds="clip")`` predicts them."""
    from sklearn.isotonic import IsotonicRegression

    from geocd.consistency import _isotonic

    rng = np.random.default_rng(1)
    for t in range(300):
        n = int(rng.integers(1, 60))
        y = np.cumsum(rng.normal(0.2, 1.0, n)) if t % 2 else rng.normal(size=n)
        w = rng.integers(0, 50, n).astype(float)
        if t % 3 == 0:
            y[rng.random(n) < 0.2] = np.nan
        if t % 5 == 0:
            y = np.round(y, 1)  # ties
        ok = np.isfinite(y) & (w > 0)
        got = _isotonic(y, w)
        if not ok.any():
            assert np.isnan(got).all()
            continue
        x = np.arange(n, dtype=float)
        want = IsotonicRegression(out_of_bounds="clip").fit(x[ok], y[ok], sample_weight=w[ok]).predict(x)
        np.testing.assert_allclose(got, want, rtol=1e-13, atol=1e-13)
        assert np.all(np.diff(got) >= -1e-12)
