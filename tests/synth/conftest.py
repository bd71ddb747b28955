"""Fixtures for the simulator tests: a tiny town, its packed scenes and a generated tiny scene folder."""

from __future__ import annotations

import pytest

from geocd.synth.generate import SynthParams, generate
from geocd.synth.render import pack_scene
from geocd.synth.scene import build_town


@pytest.fixture(scope="session")
def tiny_params() -> SynthParams:
    return SynthParams.tiny(seed=1)


@pytest.fixture(scope="session")
def tiny_town(tiny_params):
    return build_town(tiny_params.town_params())


@pytest.fixture(scope="session")
def tiny_scenes(tiny_town):
    return {"A": pack_scene(tiny_town, "A"), "B": pack_scene(tiny_town, "B")}


@pytest.fixture(scope="session")
def tiny_scene_dir(tmp_path_factory, tiny_params):
    out = tmp_path_factory.mktemp("tiny_scene")
    res = generate(tiny_params, out)
    return res
