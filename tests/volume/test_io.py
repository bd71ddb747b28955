"""A damaged volume model folder is refused on load with a message naming the file (never a crash in a kernel)."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from geocd.errors import GeoCDError, UnsupportedFormatError
from geocd.volume import VolumeModel, expected_height_map, load_model, save_model
from geocd.volume.refine import refine_model

from . import toyscene as T


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    """A tiny model with refined cells (children appended after the breadth-first ones), saved."""
    m = VolumeModel.create(T.volume_geometry(finest_cell_m=1.0, max_depth=2), init_depth=1)
    m.alpha[np.flatnonzero(m.child < 0)[:40]] = 50.0  # dense leaves: refine splits them
    refine_model(m)
    assert m.n_nodes > VolumeModel.create(m.geometry, init_depth=1).n_nodes
    return save_model(m, tmp_path_factory.mktemp("vol") / "model")


def _copy(saved, tmp_path):
    return shutil.copytree(saved, tmp_path / "model")


def _edit(path, name, fn):
    """Change one array of the model folder with ``fn`` (in place), keeping model.json consistent."""
    a = np.load(path / f"{name}.npy")
    a = fn(a)
    np.save(path / f"{name}.npy", a)
    meta = json.loads((path / "model.json").read_text())
    meta["arrays"][name] = {"shape": list(a.shape), "dtype": str(a.dtype)}
    (path / "model.json").write_text(json.dumps(meta))


def _set(idx, value):
    def fn(a):
        a = a.copy()
        a[idx] = value
        return a

    return fn


def test_a_sound_model_loads_and_is_checked(saved):
    m = load_model(saved)
    assert (m.child >= 0).any() and int(m.level.max()) == 2
    inner = np.flatnonzero(m.child >= 0)
    assert np.all(m.child[inner] > inner)  # the format's invariant the loader relies on
    assert load_model(saved, mmap=True).n_nodes == m.n_nodes


def _inner(saved, k=0):
    child = np.load(saved / "child.npy")
    return int(np.flatnonzero(child >= 0)[k])


def _leaf(saved, k=0):
    child = np.load(saved / "child.npy")
    return int(np.flatnonzero(child < 0)[k])


DAMAGES = {
    # the reported crash: every child pointer far outside the arrays
    "child pointers 1e8": lambda s: ("child", lambda a: np.where(a >= 0, 100_000_000, a).astype(np.int32), "child.npy"),
    # one bad pointer: past the end, or with no room for 8 children
    "one pointer past the end": lambda s: ("child", _set(_inner(s), 10**6), "child.npy"),
    "one pointer without room for 8": lambda s: (
        "child",
        _set(_inner(s), np.load(s / "child.npy").size - 3),
        "child.npy",
    ),
    "a node its own child (a cycle)": lambda s: ("child", _set(_inner(s, 3), _inner(s, 3)), "child.npy"),
    "a pointer back to the root": lambda s: ("child", _set(_inner(s, 5), 0), "child.npy"),
    "a pointer below -1": lambda s: ("child", _set(_leaf(s), -7), "child.npy"),
    "two nodes share children": lambda s: (
        "child",
        _set(_leaf(s, -1), np.load(s / "child.npy")[_inner(s, -1)]),
        "child.npy",
    ),
    "a leaf at max_depth gets children": lambda s: (
        "child",
        _set(int(np.flatnonzero(np.load(s / "level.npy") == 2)[0]), np.load(s / "child.npy").size - 8),
        "child.npy",
    ),
    "a block root out of range": lambda s: ("block_root", _set((0, 0, 0), 10**7), "block_root.npy"),
    "a negative block root": lambda s: ("block_root", _set((0, 0, 0), -2), "block_root.npy"),
    "two blocks share a root": lambda s: ("block_root", lambda a: np.zeros_like(a), "block_root.npy"),
    "a level deeper than max_depth": lambda s: ("level", _set(_leaf(s), 9), "level.npy"),
    "children on the wrong level": lambda s: ("level", _set(int(np.load(s / "child.npy")[_inner(s)]), 0), "level.npy"),
    "a NaN density": lambda s: ("alpha", _set(_leaf(s), np.nan), "alpha.npy"),
    "a negative density": lambda s: ("alpha", _set(_leaf(s), -1.0), "alpha.npy"),
    "an infinite appearance": lambda s: ("app", _set((_leaf(s), 0, 0, 0), np.inf), "app.npy"),
    "a negative sigma": lambda s: ("app", _set((_leaf(s), 0, 0, 1), -0.1), "app.npy"),
    "child stored as int64": lambda s: ("child", lambda a: a.astype(np.int64), "child.npy"),
    "app without its bins axis": lambda s: ("app", lambda a: a[:, 0], "app.npy"),
    "app of one bin too few": lambda s: ("app", lambda a: a[:, :1], "app.npy"),
}


@pytest.mark.parametrize("name", sorted(DAMAGES))
def test_a_damaged_array_is_refused_naming_its_file(saved, tmp_path, name):
    p = _copy(saved, tmp_path)
    array, fn, where = DAMAGES[name](p)
    _edit(p, array, fn)
    with pytest.raises(UnsupportedFormatError, match="damaged") as ei:
        load_model(p)
    assert where in str(ei.value) and isinstance(ei.value, GeoCDError)


@pytest.mark.parametrize("name", ["block_root", "child", "level", "alpha", "app"])
def test_a_truncated_or_garbled_npy_is_refused_naming_it(saved, tmp_path, name):
    p = _copy(saved, tmp_path)
    f = p / f"{name}.npy"
    raw = f.read_bytes()
    f.write_bytes(raw[: len(raw) - 7])
    with pytest.raises(UnsupportedFormatError, match=rf"{name}\.npy is truncated"):
        load_model(p)
    with pytest.raises(UnsupportedFormatError, match=rf"{name}\.npy is truncated"):
        load_model(p, mmap=True)
    f.write_bytes(raw[:20])  # inside the header
    with pytest.raises(UnsupportedFormatError, match=rf"{name}\.npy"):
        load_model(p)
    f.write_bytes(b"\x93NUMPY\x01\x00" + bytes(range(256)))
    with pytest.raises(UnsupportedFormatError, match=rf"{name}\.npy"):
        load_model(p)
    # a header that promises a huge array: refused from the file size, nothing allocated
    huge = raw.replace(b"'shape': (", b"'shape': (99999999999, ", 1)
    f.write_bytes(huge)
    with pytest.raises(UnsupportedFormatError, match=rf"{name}\.npy"):
        load_model(p)


@pytest.mark.parametrize(
    "change",
    [
        "no arrays entry",
        "geometry NaN",
        "inverted AOI",
        "sun bins of 2",
        "history of strings",
        "not a dict",
        "n_blocks mismatch",
    ],
)
def test_damaged_metadata_is_refused(saved, tmp_path, change):
    p = _copy(saved, tmp_path)
    meta = json.loads((p / "model.json").read_text())
    if change == "no arrays entry":
        del meta["arrays"]["alpha"]
    elif change == "geometry NaN":
        meta["geometry"]["origin_enu"][0] = float("nan")
    elif change == "inverted AOI":
        b = meta["geometry"]["aoi_bounds"]
        meta["geometry"]["aoi_bounds"] = [b[2], b[1], b[0], b[3]]
    elif change == "sun bins of 2":
        meta["sun_bins"] = [[135.0, 60.0]]
    elif change == "history of strings":
        meta["history"] = ["x"]
    elif change == "not a dict":
        meta = [meta]
    elif change == "n_blocks mismatch":
        meta["geometry"]["n_blocks"][0] += 1
    (p / "model.json").write_text(json.dumps(meta))
    with pytest.raises(UnsupportedFormatError):
        load_model(p)


def test_the_checked_model_still_renders(saved):
    h, _grid = expected_height_map(load_model(saved))
    assert h.shape and np.isfinite(h).any()
