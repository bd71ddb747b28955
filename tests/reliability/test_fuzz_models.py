"""Fuzzing the readers of model and camera files (short runs; bench/fuzz_inputs.py runs them for thousands).

Volume (octree) models (edits of their arrays: pointers, levels, roots, densities), self-consistency models
(structural mutations of a real one: wrong types, deleted and renamed keys at any depth,
and byte mutations of its JSON), frame-camera sidecars (structural mutations), RPC files in four text formats and
PyTorch weights files (byte mutations): every reader returns a result or raises a GeoCDError, nothing else, and what it accepts is
usable — a model gives p-values in [0, 1], a camera projects a point of its scene to finite pixels.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from .fuzz_targets import (
    byte_mutations,
    check_frame_sidecar,
    check_model_bytes,
    check_model_tree,
    check_rpc_file,
    check_torch_bytes,
    tree_ops,
)

REPO = Path(__file__).resolve().parents[2]
_FAST = dict(
    deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow], database=None
)


@pytest.fixture(scope="module")
def model_doc():
    """sample-sized copy of the shipped Marseille model (fewer |Δ̃| counts to mutate, same structure)."""
    return json.loads((REPO / "examples/kahramanmaras/marseille_urban_model.json").read_text())


@pytest.fixture(scope="module")
def sidecar_doc(tmp_path_factory):
    from geocd.io.frame import write_frame_sidecar
    from tests.camera.test_frame import make_cam

    p = write_frame_sidecar(tmp_path_factory.mktemp("fuzz_frame") / "img.json", make_cam())
    return json.loads(Path(p).read_text())


@pytest.fixture(scope="module")
def rpc_files(tmp_path_factory):
    from tests.camera.test_rpc import synthetic_rpc
    from tests.io.test_rpc_readers import write_geocd_json, write_geom, write_ikonos, write_rpb

    d = tmp_path_factory.mktemp("fuzz_rpc_files")
    m = synthetic_rpc(0)
    return {
        name: Path(w(m, d / name)).read_bytes()
        for name, w in (
            ("img_rpc.txt", write_ikonos),
            ("img.RPB", write_rpb),
            ("img.geom", write_geom),
            ("img.rpc.json", write_geocd_json),
        )
    }


def test_unmutated_files_are_accepted(model_doc, sidecar_doc, rpc_files, tmp_path):
    assert check_model_tree(model_doc, [], tmp_path) == "ok"
    assert check_frame_sidecar(sidecar_doc, [], tmp_path) == "ok"
    for name, data in rpc_files.items():
        assert check_rpc_file(name, data, ("truncate", 1.0, b"x", 1, 0, False), tmp_path) == "ok", name


@pytest.mark.parametrize(
    "edit,needle",
    [
        (lambda d: d.update(hist=d["hist"][:-1]), "'hist' has shape"),
        (lambda d: d.update(score_edges=d["score_edges"][::-1]), "increasing"),
        (lambda d: d["hist"][0].__setitem__(0, -5), "counts"),
        (lambda d: d.update(hist=[[0] * len(r) for r in d["hist"]]), "empty"),
        (lambda d: d["curves"].update({"99": [1.0, 2.0]}), "one threshold"),
        (lambda d: d["curves"].update({"150": d["curves"]["99"]}), "outside (0, 100)"),
        (lambda d: d["region_null"]["masses"][0].__setitem__(0, "x"), "masses"),
        (lambda d: d["region_null"].update(cluster_confidence=0), "cluster_confidence"),
        (lambda d: d["reference_law"].update(scale=0.0), "scale > 0"),
        (lambda d: d.pop("score_edges"), "'score_edges' is missing"),
    ],
)
def test_a_damaged_model_is_named(model_doc, tmp_path, edit, needle):
    import copy

    from geocd.consistency import SelfConsistencyModel
    from geocd.errors import ConfigError

    d = copy.deepcopy(model_doc)
    edit(d)
    p = tmp_path / "m.json"
    p.write_text(json.dumps(d))
    with pytest.raises(ConfigError, match="damaged self-consistency model") as e:
        SelfConsistencyModel.load(p)
    assert needle in str(e.value) and str(p) in str(e.value)


@settings(max_examples=150, **_FAST)
@given(ops=tree_ops)
@pytest.mark.slow
def test_fuzz_model_structure(model_doc, ops, tmp_path_factory):
    check_model_tree(model_doc, ops, tmp_path_factory.getbasetemp())


@settings(max_examples=60, **_FAST)
@given(mutation=byte_mutations)
@pytest.mark.slow
def test_fuzz_model_bytes(model_doc, mutation, tmp_path_factory):
    check_model_bytes(json.dumps(model_doc).encode(), mutation, tmp_path_factory.getbasetemp())


@settings(max_examples=200, **_FAST)
@given(ops=tree_ops)
def test_fuzz_frame_sidecar(sidecar_doc, ops, tmp_path_factory):
    check_frame_sidecar(sidecar_doc, ops, tmp_path_factory.getbasetemp())


@pytest.mark.parametrize("name", ["img_rpc.txt", "img.RPB", "img.geom", "img.rpc.json"])
@settings(max_examples=60, **_FAST)
@given(mutation=byte_mutations)
def test_fuzz_rpc_files(rpc_files, name, mutation, tmp_path_factory):
    check_rpc_file(name, rpc_files[name], mutation, tmp_path_factory.getbasetemp())


def test_a_model_accepted_by_the_reader_gives_p_values_in_range(model_doc, tmp_path):
    from geocd.consistency import SelfConsistencyModel

    p = tmp_path / "m.json"
    p.write_text(json.dumps(model_doc))
    m = SelfConsistencyModel.load(p)
    pv = m.pvalue(np.array([0.0, 0.5, 3.0, 1e6]), np.array([-1.0, 0.0, 1.0, 5.0]))
    assert np.all((pv >= 0) & (pv <= 1))


@pytest.fixture(scope="module")
def torch_bytes(tmp_path_factory):
    from tests.screen.test_torchfile import _tensor_pickle, _zip

    return _zip(tmp_path_factory.mktemp("fuzz_pth") / "w.pth", _tensor_pickle(0, (2, 2), (2, 1))).read_bytes()


def test_the_unmutated_weights_file_reads(torch_bytes, tmp_path):
    assert check_torch_bytes(torch_bytes, ("truncate", 1.0, b"x", 1, 0, False), tmp_path) == "ok"


@settings(max_examples=150, **_FAST)
@given(mutation=byte_mutations)
def test_fuzz_torch_weights(torch_bytes, mutation, tmp_path_factory):
    check_torch_bytes(torch_bytes, mutation, tmp_path_factory.getbasetemp())


# ---------------------------------------------------------------------------------------------------------------
# volume (octree) models: any edit of the arrays is refused on load, or the model is safe to trace rays through
# ---------------------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def volume_model(tmp_path_factory):
    from geocd.volume import VolumeModel, save_model
    from geocd.volume.refine import refine_model
    from tests.volume import toyscene as T

    m = VolumeModel.create(T.volume_geometry(finest_cell_m=1.0, max_depth=2), init_depth=1)
    m.alpha[np.flatnonzero(m.child < 0)[:40]] = 50.0
    refine_model(m)
    return save_model(m, tmp_path_factory.mktemp("fuzz_vol") / "model")


_ARRAY_EDITS = st.lists(
    st.tuples(
        st.sampled_from(["child", "level", "block_root", "alpha", "app"]),
        st.integers(0, 10**6),
        st.one_of(
            st.integers(-(10**9), 10**9),
            st.sampled_from([-1, 0, 1, 7, 8, 10**8]),
            st.floats(allow_nan=True, allow_infinity=True),
        ),
    ),
    min_size=1,
    max_size=3,
)


@settings(max_examples=60, **_FAST)
@given(edits=_ARRAY_EDITS)
def test_fuzz_volume_model_arrays(volume_model, edits, tmp_path_factory):
    import shutil

    from geocd.errors import GeoCDError
    from geocd.volume import expected_height_map, load_model

    d = Path(tmp_path_factory.mktemp("vm")) / "model"
    shutil.copytree(volume_model, d)
    for name, where, value in edits:
        a = np.load(d / f"{name}.npy")
        flat = a.reshape(-1).copy()
        try:
            with np.errstate(over="ignore", invalid="ignore"):
                flat[where % flat.size] = value
        except (OverflowError, ValueError):  # a value the array's dtype cannot hold: not a file one can write
            continue
        np.save(d / f"{name}.npy", flat.reshape(a.shape))
    try:
        m = load_model(d)
    except GeoCDError:
        return
    h, _ = expected_height_map(m)  # a model the loader accepts is safe to trace: no crash, no read out of bounds
    assert h.shape
