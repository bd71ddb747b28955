import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))

from synthetic import make_scene  # noqa: E402


@pytest.fixture(scope="session")
def scene():
    """A 40 m × 40 m textured scene with two buildings, seen by two affine RPC cameras."""
    return make_scene(seed=0, size_m=40.0)


@pytest.fixture(scope="session")
def chips(scene):
    from geocd.stereo import prepare_chip

    return [prepare_chip(img, name=n) for img, n in zip(scene.images, scene.names)]


@pytest.fixture(scope="session")
def pair_dem(scene, chips):
    """The pair matched with default parameters over a ±20 m range (the RPC's ±500 m range is tested elsewhere)."""
    from geocd.stereo import StereoParams, match_pair

    return match_pair(
        chips[0],
        chips[1],
        scene.cameras[0],
        scene.cameras[1],
        scene.grid,
        params=StereoParams(height_range_m=(185.0, 225.0)),
    )
