"""geocd.change.metrics.roc_curve against scikit-learn's roc_curve and roc_auc_score (its numpy reference)."""

import numpy as np
import pytest

from geocd.change.metrics import roc_curve


@pytest.mark.parametrize("levels", [None, 7, 300])
def test_roc_curve_is_scikit_learns_bit_for_bit(levels):
    # here, not at the top: scikit-learn is 2 s of every pytest worker's collection
    from sklearn.metrics import roc_auc_score
    from sklearn.metrics import roc_curve as sk_roc_curve

    rng = np.random.default_rng(5)
    n = 20_000
    truth = rng.random(n) < 0.1
    score = rng.normal(0.0, 1.0, n) + 0.8 * truth
    if levels is not None:  # many ties
        score = np.round(score * levels / 4.0)
    score[rng.random(n) < 0.01] = np.nan
    valid = rng.random(n) < 0.9
    fpr, tpr, thr, auc = roc_curve(score, truth, valid, n_thresholds=10**9)
    ok = valid & np.isfinite(score)
    sf, st, sthr = sk_roc_curve(truth[ok], score[ok], drop_intermediate=True)
    np.testing.assert_array_equal(fpr, sf)
    np.testing.assert_array_equal(tpr, st)
    np.testing.assert_array_equal(thr, sthr)
    assert auc == roc_auc_score(truth[ok], score[ok])
    # thinned for plotting, the AUC unchanged
    f2, t2, th2, auc2 = roc_curve(score, truth, valid, n_thresholds=50)
    assert f2.size <= 50 and auc2 == auc and f2[0] == 0.0 and f2[-1] == 1.0


def test_roc_curve_of_one_class_has_no_auc():
    fpr, tpr, _, auc = roc_curve(np.arange(5.0), np.zeros(5, bool))
    assert np.isnan(auc) and fpr.tolist() == [0.0, 1.0] and tpr.tolist() == [0.0, 1.0]
