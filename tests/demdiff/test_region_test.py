"""The demdiff region test: a minimum mapping unit derived from the noise model (variogram + cell test)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.special import erfc

from geocd.demdiff import DEMDiffParams, dem_difference
from geocd.demdiff.significance import _torus_field, noise_mass_needed, noise_region_filter, noise_region_null
from geocd.demdiff.uncertainty import VariogramModel
from geocd.errors import ConfigError

from .synthetic import grid, pair

VG = VariogramModel(0.3, (4.0, 30.0), (0.4, 0.3))


def _noise_maps(vg, level, seeds):
    """Independent noise fields (other seeds than the null's) and their cell test at ``level``."""
    for s in seeds:
        g = _torus_field(vg, (1.0, 1.0), 512, np.random.default_rng(100 + s))
        conf = 100.0 * (1.0 - erfc(np.abs(g) / np.sqrt(2.0)))
        yield np.where(conf >= level, np.sign(g), 0).astype(np.int8), conf


@pytest.mark.parametrize("level,min_cells", [(99.0, 1), (90.0, 1), (95.0, 4)])
def test_noise_regions_survive_at_the_rate_the_level_allows(level, min_cells):
    """On noise with the model's correlation, the share of regions kept is 1 − level (per-region error rate),
    for the regions the map reports (≥ min_cells cells; the null is made of the same)."""
    null = noise_region_null(VG, (1.0, 1.0), level, min_cells)
    assert null.size >= 2000
    tested = kept = 0
    for sign, conf in _noise_maps(VG, level, range(3)):
        out, info = noise_region_filter(sign, conf, level, null, min_cells)
        tested += info["regions_tested"]
        kept += info["regions_tested"] - info["regions_dropped"]
        assert np.all((out == 0) | (out == sign))
    share = kept / tested
    assert tested > 1500
    assert abs(share - (1 - level / 100)) < 0.35 * (1 - level / 100) + 0.002, share


def test_a_null_of_smaller_regions_is_caught():
    """A null of every noise cluster (singletons too) for a map of ≥ 4-cell regions keeps far too many."""
    null1 = noise_region_null(VG, (1.0, 1.0), 95.0, 1)
    tested = kept = 0
    for sign, conf in _noise_maps(VG, 95.0, range(2)):
        _, info = noise_region_filter(sign, conf, 95.0, null1, 4)
        tested += info["regions_tested"]
        kept += info["regions_tested"] - info["regions_dropped"]
    assert kept / tested > 0.2


def test_too_few_noise_regions_keep_every_region():
    """Noise that seldom forms regions of the mapping unit's size cannot rank them: nothing is dropped."""
    null = np.array([5.0, 9.0])
    sign = np.zeros((20, 20), np.int8)
    sign[2:4, 2:4] = 1
    out, info = noise_region_filter(sign, np.full(sign.shape, 99.5), 99.0, null, 4)
    assert info["regions_dropped"] == 0 and np.array_equal(out, sign) and np.isnan(info["mass_needed"])


def test_the_null_of_another_level_is_caught():
    """A 99 % map tested against the 90 % null (its clusters are larger and their evidence counts from
    p = 0.1) no longer keeps 1 % of the noise regions."""
    null90 = noise_region_null(VG, (1.0, 1.0), 90.0, 1)
    tested = kept = 0
    for sign, conf in _noise_maps(VG, 99.0, range(2)):
        _, info = noise_region_filter(sign, conf, 99.0, null90, 1)
        tested += info["regions_tested"]
        kept += info["regions_tested"] - info["regions_dropped"]
    assert tested > 2000 and kept / tested < 0.003


def test_the_mapping_unit_grows_with_the_correlation_range():
    """Not a constant: the evidence a region needs follows the variogram (and the level)."""
    short = noise_mass_needed(noise_region_null(VariogramModel(0.9, (3.0,), (0.1,)), (1.0, 1.0), 99.0, 1), 99.0)
    long_ = noise_mass_needed(noise_region_null(VariogramModel(0.0, (20.0,), (1.0,)), (1.0, 1.0), 99.0, 1), 99.0)
    assert long_ > 5 * short
    # deterministic: the same model gives the same null
    np.testing.assert_array_equal(
        noise_region_null(VG, (1.0, 1.0), 95.0, 1), noise_region_null(VG, (1.0, 1.0), 95.0, 1)
    )


@pytest.mark.slow
def test_demdiff_region_test_keeps_the_real_change_and_drops_noise_regions():
    a, b, info = pair(shift_m=(4.0, -3.0, 1.5), bump_m=20.0, g=grid(170, 150), seed=2)
    off = dem_difference(a, b, params=DEMDiffParams(region_test="off"))
    on = dem_difference(a, b)  # the default
    ri = on.summary["region_test"]
    assert "region_test" not in off.summary
    assert ri["regions_tested"] == len(off.regions) == 28
    # the scene's one change is the bump; 20 of its 27 noise regions are dropped (7 survive: more than the
    # 5 % the level allows — the synthetic noise is not exactly the fitted model)
    assert ri["regions_dropped"] == 20 and ri["cells_dropped"] == 91 and len(on.regions) == 8
    # the bump (the largest region) is kept whole; only cells of dropped regions changed
    assert on.regions["n_cells"].iloc[0] == off.regions["n_cells"].iloc[0] > 400
    changed = on.sign != off.sign
    assert changed.sum() == 91 and np.all(on.sign[changed] == 0)
    with pytest.raises(ConfigError):
        DEMDiffParams(region_test="yes")
