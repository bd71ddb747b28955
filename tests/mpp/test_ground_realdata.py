"""The terrain ``geocd mpp`` takes when no ground is given, on real DSMs it was not chosen on (docs/mpp.md)."""

import importlib.util

import pytest

from tests.conftest import REPO, shared_data

pytestmark = pytest.mark.realdata


def _eval():
    spec = importlib.util.spec_from_file_location("eval_mpp_ground", REPO / "bench" / "eval_mpp_ground.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.parametrize(
    "name, terrain, opening",
    [("pair", 0.116, 0.596), ("triplet", 0.160, 0.637)],  # s2p's Réunion pair and Marseille triplet DSMs
)
def test_the_terrain_filter_leaves_the_streets_on_the_ground(name, terrain, opening):
    """Share of cells more than 2.5 m above the ground: the terrain filter (the default) against the former one
    opening wider than every building, which sinks to the lowest street of a city on a slope; both far below the
    refusal's 90 %."""
    ev = _eval()
    z, posting = ev.read(shared_data("s2p_pleiades", "expected_output", name, "dsm.tif"))
    s = ev.raised_shares(z, posting)
    assert s["terrain_filter"] == pytest.approx(terrain, abs=0.02)
    assert s["one_opening"] == pytest.approx(opening, abs=0.03)
    assert s["terrain_filter"] < s["raised_max"]
