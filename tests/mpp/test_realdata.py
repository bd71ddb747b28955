"""The marked point process on a real LEVIR-CD pair (../shared): pinned rows of docs/mpp.md's LEVIR tables."""

from __future__ import annotations

import warnings

import pytest

from geocd.mpp.detect import detect
from geocd.mpp.evaluate import rect_masks, table2_change_only
from geocd.mpp.params import MPPParams

from ..conftest import shared_data


@pytest.fixture(scope="module")
def test_7():
    import rasterio
    from rasterio.errors import NotGeoreferencedWarning

    root = shared_data("levircd_building_change_samples")
    out = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NotGeoreferencedWarning)
        for sub in ("A", "B", "label"):
            with rasterio.open(root / sub / "test_7_0256_0512.png") as ds:
                out.append(ds.read() if sub != "label" else ds.read(1) > 0)
    return out


def _row(pair, method, prototypes):
    a, b, lab = pair
    d = detect(a, b, 0.5, MPPParams(prototypes=prototypes), method=method)
    return table2_change_only(rect_masks(d.result.rects, d.result.xi, lab.shape), lab), d


@pytest.mark.realdata
@pytest.mark.slow
def test_levir_edge_only_row(test_7):
    """EV on test_7: 12 label changes, HV 8, 4 detected, changed-building F 0.351 (seed 0; grey-model births,
    the colour mask holding no building-sized patch)."""
    t, _ = _row(test_7, "EV", "auto")
    assert t["changes"] == 12 and t["HV"] == 8 and t["detected_changes"] <= 6, t
    assert t["change_f"] == pytest.approx(0.351, abs=0.03), t


@pytest.mark.realdata
@pytest.mark.slow
def test_levir_joint_model_rows(test_7):
    """ED on test_7: LEVIR's grey and brown roofs give the red-roof mask no building-sized patch, so "auto"
    reads the pair with the grey-image model (gradient + homogeneity): 4 of 12 changes found, none false,
    changed-building F 0.491 (docs/mpp.md; the colour model found nothing here)."""
    t, d = _row(test_7, "ED", "auto")
    assert d.thresholds[0]["prototypes"] == "gradient + homogeneity", d.thresholds
    assert d.thresholds[1]["prototypes"] == "gradient + homogeneity", d.thresholds
    assert any("none the size of a building" in n for n in d.notes), d.notes
    assert t["HV"] == 8 and t["FV"] <= 1, t
    assert t["change_f"] == pytest.approx(0.491, abs=0.03), t
