"""Fuzzing (short runs; bench/fuzz_inputs.py runs the same targets for thousands of examples).

Manifests (structural mutations: typos in keys at any depth, wrong types, deletions, extra keys; and byte
mutations of the YAML), DEM GeoTIFFs (byte mutations biased to the header: TIFF tags, GeoKeys, GDAL metadata)
and RPC metadata values (GDAL's RPC domain): every reader returns a result or raises a GeoCDError, nothing else;
an accepted RPC is plausible and projects to finite pixels.
"""

from __future__ import annotations

import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, example, given, settings

from .fuzz_targets import (
    byte_mutations,
    check_dem_bytes,
    check_manifest_text,
    check_manifest_tree,
    check_rpc_tags,
    dump_yaml,
    rpc_tag_edits,
    rpc_tags_of,
    tree_ops,
)
from .scenes import make_scene, write_dem_pair

_FAST = dict(
    deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow], database=None
)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    sc = make_scene(tmp_path_factory.mktemp("fuzz_scene"))
    return sc, yaml.safe_load(sc.manifest.read_text())


@pytest.fixture(scope="module")
def dem_bytes(tmp_path_factory):
    a, _ = write_dem_pair(tmp_path_factory.mktemp("fuzz_dem"), rows=24, cols=24)
    return a.read_bytes()


@pytest.fixture(scope="module")
def rpc_image(tmp_path_factory):
    from geocd.io.raster import write_image
    from tests.stereo.synthetic import affine_rpc

    d = tmp_path_factory.mktemp("fuzz_rpc")
    p = write_image(d / "img.tif", np.ones((1, 16, 16), np.uint8))
    return p, rpc_tags_of(affine_rpc(0.5, (0.5, 0.05), 120, 120))


def test_unmutated_inputs_are_accepted(scene, dem_bytes, rpc_image, tmp_path):
    sc, doc = scene
    assert check_manifest_tree(doc, [], sc.root) == "ok"
    assert check_dem_bytes(dem_bytes, ("truncate", 1.0, b"x", 1, 0, False), tmp_path) == "ok"
    assert check_rpc_tags(*rpc_image, {}) == "ok"


@settings(max_examples=300, **_FAST)
@given(ops=tree_ops)
def test_fuzz_manifest_structure(scene, ops):
    sc, doc = scene
    check_manifest_tree(doc, ops, sc.root)


@settings(max_examples=100, **_FAST)
@given(mutation=byte_mutations)
def test_fuzz_manifest_text(scene, mutation, tmp_path_factory):
    sc, doc = scene
    d = tmp_path_factory.mktemp("mt")
    (d / "images").symlink_to(sc.root / "images")
    for f in ("dem.tif", "footprints.gpkg"):
        (d / f).symlink_to(sc.root / f)
    check_manifest_text(dump_yaml(doc), mutation, d)


@settings(max_examples=100, **_FAST)
@given(mutation=byte_mutations)
@example(mutation=("flip", 0.5208078563543089, b"\xd5\xa0", 26, 26, True))  # found by bench/fuzz_inputs.py: a
# corrupt GeoKey citation made rasterio.open raise UnicodeDecodeError
def test_fuzz_dem_geotiff(dem_bytes, mutation, tmp_path_factory):
    check_dem_bytes(dem_bytes, mutation, tmp_path_factory.mktemp("dm"))


@settings(max_examples=150, **_FAST)
@given(edits=rpc_tag_edits)
def test_fuzz_rpc_tag_values(rpc_image, edits):
    check_rpc_tags(*rpc_image, edits)


def test_implausible_tag_values_are_refused(rpc_image):
    """What the fuzzer must never see accepted (the issue's cases, through GDAL's RPC domain)."""
    for edits in (
        {"LAT_OFF": "95"},
        {"LONG_OFF": "400"},
        {"HEIGHT_OFF": "1e308"},
        {"LINE_OFF": "abc"},
        {"SAMP_NUM_COEFF": "1e300"},
    ):
        assert check_rpc_tags(*rpc_image, edits) == "RPCParseError", edits
