"""sample_aoi's Table 2 row through `geocd mpp` on geocd stereo's product DSM (a median over the matching window),
whose difference from the default DSMs is the largest effect on these figures measured so far (docs/mpp.md)."""

from __future__ import annotations

import pytest

from tests.mpp.sample_aoi_table2 import check_table2


@pytest.mark.slow
def test_sample_aoi_table2_through_geocd_mpp_window_median(sample_aoi, tmp_path):
    """geocd stereo's product DSM (0.751 / 0.7557 before the notches, 0.7388 / 0.742 before the roof holes, 0.709 /
    0.7135 with the texture evidence, 0.686 / 0.691 before the growth, 0.681 / 0.686 before the turn)."""
    check_table2(
        sample_aoi,
        tmp_path,
        "window",
        {"DP": 0.7616, "DP_precision": 0.9527, "HO": 11, "FO": 0, "HV": 2, "FV": 0, "DP_precision_gain": 0.0144},
        {"DP": 0.7667, "FO": 1},
    )
