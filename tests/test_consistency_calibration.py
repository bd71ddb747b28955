"""Transfer calibration of a scene-class self-consistency model to the tested comparisons."""

from types import SimpleNamespace

import numpy as np
import pytest

from geocd.consistency import (
    ChangeParams,
    ConsistencyParams,
    PairCalibration,
    change_test,
    fit_pair_calibration,
    learn_self_consistency,
    local_slope,
    model_learned_on,
)
from geocd.errors import ConfigError

from .fakes import Rec


SHAPE = (160, 160)
GRID = SimpleNamespace(posting_m=1.0)


def make_rec(truth, rng, name, noise=1.0):
    """Disparity error (px) growing with the score, times ``noise`` (1: the scene the model is learned on)."""
    score = rng.uniform(-2.0, 1.0, SHAPE).astype(np.float32)
    err_px = rng.normal(size=SHAPE) * (0.1 + 0.3 * (score + 2.0)) * noise
    g = np.full(SHAPE, 1.0, np.float32)
    return Rec((truth + err_px).astype(np.float32), score, g, np.ones(SHAPE, bool), GRID, name)


@pytest.fixture(scope="module")
def model():
    rng = np.random.default_rng(3)
    flat = np.zeros(SHAPE, np.float32)
    return learn_self_consistency(
        [[make_rec(flat, rng, f"M{i}") for i in range(3)]], ConsistencyParams(n_score_bins=10, min_bin_count=500)
    )


@pytest.mark.slow
def test_fit_recovers_scale_and_edge_sigma_with_a_changed_minority(model):
    """Data drawn from the calibration's own law (scale 2, 0.4 m misregistration), 15 % changed cells."""
    rng = np.random.default_rng(7)
    n = 400_000
    sc = rng.uniform(-2.0, 1.0, n)
    slope = rng.exponential(1.0, n)
    mpu = np.full(n, 1.5)
    truth = PairCalibration(2.0, 0.4)
    m_tot = truth.inflation(model, sc, slope, mpu) * model.threshold(sc, 50.0)
    # the static part: the model's law (normal per score here) widened to m_tot
    dt = rng.normal(size=n) * m_tot / 0.6745
    changed = rng.random(n) < 0.15
    dt[changed] += rng.choice([-1, 1], changed.sum()) * rng.uniform(6, 30, changed.sum())
    cal = fit_pair_calibration(model, dt, sc, slope, mpu)
    assert cal.scale == pytest.approx(2.0, rel=0.1)
    assert cal.edge_sigma_m == pytest.approx(0.4, rel=0.2)
    assert 0.12 < cal.trimmed_fraction < 0.2  # the changed cells (and 1 % of the static ones) trimmed
    # without the changed minority the medians are the law's own: tighter
    cal0 = fit_pair_calibration(model, dt[~changed], sc[~changed], slope[~changed], mpu[~changed])
    assert cal0.scale == pytest.approx(2.0, rel=0.05) and cal0.edge_sigma_m == pytest.approx(0.4, rel=0.1)
    # scale alone when no slope is known
    assert fit_pair_calibration(model, dt, sc, slope, mpu, fit_edge=False).edge_sigma_m == 0.0


def test_local_slope_of_a_ramp_and_beside_gaps():
    z = np.tile(np.arange(10, dtype=float) * 0.5, (6, 1))  # 0.5 m per cell along x
    assert np.allclose(local_slope(z, 1.0), 0.5)
    assert np.allclose(local_slope(z, 0.5), 1.0)
    z[:, 4] = np.nan  # a gap: neighbours keep their one-sided slope
    s = local_slope(z, 1.0)
    assert np.allclose(s[:, 3], 0.5) and np.allclose(s[:, 5], 0.5) and np.all(s[:, 4] == 0)


def test_transferred_model_is_calibrated_and_false_alarms_drop(model):
    """Epochs twice as noisy as the model's scene: as learned, the 99 % test flags static cells far beyond 1 %;
    calibrated (auto, since the model was learned elsewhere) it is back near 1 % and still finds the change."""
    rng = np.random.default_rng(11)
    truth_a = np.zeros(SHAPE, np.float32)
    truth_b = truth_a.copy()
    truth_b[30:70, 30:70] -= 15.0  # a collapsed block (6 % of the cells)
    A = [make_rec(truth_a, rng, "A0", noise=2.0)]
    B = [make_rec(truth_b, rng, "B0", noise=2.0)]
    static = truth_b == truth_a
    out = {}
    for cal in ("none", "auto"):
        res = change_test(A, B, model, ChangeParams(significance="cell", calibration=cal))
        hit = res.changed_at(99.0) != 0
        out[cal] = (hit[static].mean(), hit[~static].mean(), res.calibration)
    assert out["none"][2] is None and out["none"][0] > 0.05
    fa, recall, cal = out["auto"]
    assert cal is not None and cal.scale == pytest.approx(2.0, rel=0.15)
    assert fa < 0.02 and recall > 0.95
    # region test (the default) with the calibration: the static scene stays quiet
    res = change_test(A, B, model, ChangeParams())
    assert (res.changed_at(99.0) != 0)[static].mean() < 0.01
    assert (res.changed_at(99.0) != 0)[~static].mean() > 0.95


def test_auto_leaves_a_model_learned_on_the_same_reconstructions_alone():
    rng = np.random.default_rng(5)
    flat = np.zeros(SHAPE, np.float32)
    A = [make_rec(flat, rng, f"A{i}", noise=2.0) for i in range(2)]
    B = [make_rec(flat, rng, f"B{i}", noise=2.0) for i in range(2)]
    own = learn_self_consistency([A, B], ConsistencyParams(n_score_bins=10, min_bin_count=500))
    assert model_learned_on(own, A + B)
    assert change_test(A, B, own, ChangeParams()).calibration is None
    assert change_test(A, B, own, ChangeParams(calibration="pair")).calibration is not None
    with pytest.raises(ConfigError, match="calibration"):
        ChangeParams(calibration="scene")


def test_a_model_applied_to_data_like_its_own_is_left_alone(model):
    """Relative to the law fitted to the model's own static comparisons: inflation ≈ 1, same map."""
    assert model.reference_law and model.reference_law["scale"] == pytest.approx(1.0, abs=0.15)
    rng = np.random.default_rng(21)
    truth_a = np.zeros(SHAPE, np.float32)
    truth_b = truth_a.copy()
    truth_b[30:70, 30:70] += 6.0
    A, B = [make_rec(truth_a, rng, "A0")], [make_rec(truth_b, rng, "B0")]
    r0 = change_test(A, B, model, ChangeParams(calibration="none"))
    r1 = change_test(A, B, model, ChangeParams(calibration="pair"))
    assert r1.calibration.scale / r1.calibration.ref_scale == pytest.approx(1.0, abs=0.1)
    agree = (r0.changed_at(99.0) == r1.changed_at(99.0)).mean()
    assert agree > 0.99


def test_reference_law_round_trips(model, tmp_path):
    from geocd.consistency import SelfConsistencyModel

    back = SelfConsistencyModel.load(model.save(tmp_path / "m.json"))
    assert back.reference_law == model.reference_law


def test_cli_offers_the_calibration():
    from click.testing import CliRunner

    from geocd.cli import main

    for cmd in ("run", "change"):
        res = CliRunner().invoke(main, [cmd, "--help"])
        assert res.exit_code == 0 and "--calibration" in res.output and "auto|pair|none" in res.output.replace(" ", "")


def test_inflation_is_relative_to_the_models_own_law(model):
    """The inflation is m_tot / m_ref: data following the model's own law (its reference law) are read as they are,
    and a fit takes the reference law from the model."""
    import copy

    m = copy.deepcopy(model)
    m.reference_law = {"scale": 0.8, "edge_sigma_m": 0.5}
    sc = np.linspace(-2.0, 1.0, 50)
    mpu = np.full(50, 1.5)
    same = PairCalibration(0.8, 0.5, ref_scale=0.8, ref_edge_sigma_m=0.5)
    for g in (0.0, 1.0, 10.0):
        assert np.allclose(same.inflation(m, sc, np.full(50, g), mpu), 1.0)
    wider = PairCalibration(1.6, 0.5, ref_scale=0.8, ref_edge_sigma_m=0.5)
    assert np.allclose(wider.inflation(m, sc, np.zeros(50), mpu), 2.0)  # flat: the scale ratio
    steep = wider.inflation(m, sc, np.full(50, 1e4), mpu)
    assert np.all(steep < 1.01) and np.all(steep >= 1.0)  # steep: the edge term (same)
    rng = np.random.default_rng(9)
    n = 50_000
    dt = rng.normal(size=n) * m.threshold(rng.uniform(-2, 1, n), 50.0)
    cal = fit_pair_calibration(m, dt, rng.uniform(-2, 1, n), rng.exponential(1.0, n), np.full(n, 1.5))
    assert (cal.ref_scale, cal.ref_edge_sigma_m) == (0.8, 0.5)
    assert (
        fit_pair_calibration(
            m, dt, rng.uniform(-2, 1, n), rng.exponential(1.0, n), np.full(n, 1.5), reference=False
        ).ref_scale
        == 1.0
    )
