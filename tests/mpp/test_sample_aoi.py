"""sample_aoi's Table 2 row through `geocd mpp`'s own pipeline with its default DSMs (docs/mpp.md, "The DSM's
surface median"); the product DSM's row is in test_sample_aoi_window.py, a file of its own so that pytest-xdist
runs the two side by side."""

from __future__ import annotations

import pytest

from tests.mpp.sample_aoi_table2 import check_table2


@pytest.mark.slow
def test_sample_aoi_table2_through_geocd_mpp_default(sample_aoi, tmp_path, request):
    """geocd mpp's default: no surface median (0.8998 / 0.8824, precision 0.9063, before the corner notches cut L
    shapes; 0.8822 / 0.8727 before the DSM's holes inside roofs took the roof's height; 0.8625 / 0.848 with the
    texture as the change label's evidence, before the DSMs'; 0.839 / 0.824 before the edge fit grew the
    rectangles over the raised blocks, 0.835 / 0.820 before it turned them). Its pair-DEMs are geocd run's,
    computed once for the test session (tests/sample_aoi_cache.py): those geocd mpp's default stereo makes."""
    from tests.sample_aoi_cache import sample_aoi_pairs

    _, pairs, _ = sample_aoi_pairs(request.config.cache.mkdir("geocd_sample_aoi_stereo"))
    check_table2(
        sample_aoi,
        tmp_path,
        None,
        {"DP": 0.9117, "DP_precision": 0.9307, "HO": 1, "FO": 1, "HV": 1, "FV": 1, "DP_precision_gain": 0.0345},
        {"DP": 0.8943, "FO": 4},
        pair_dems=pairs,
    )
