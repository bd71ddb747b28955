"""The work folder's journal: entries geocd did not write for this user are never unpickled."""

from __future__ import annotations

import os
import pickle

import numpy as np
import pytest
from affine import Affine

from geocd.errors import ProcessingError
from geocd.geodesy import AOIGrid
from geocd.tiling import ArraySource, TileGrid, TileOutput, run_tiled
from geocd.tiling import store as st
from geocd.tiling.store import WORK_DIR, TileStore


class _RunsCode:
    """Unpickling this creates a marker file (what a planted journal entry would do)."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def _grid(h=60, w=50):
    return AOIGrid("EPSG:32631", Affine(1.0, 0, 500000.0, 0, -1.0, 4800000.0), w, h)


def _store(tmp_path):
    tg = TileGrid(_grid(), (30, 25))
    return TileStore(tmp_path / WORK_DIR, "t", "k" * 64, tg), tg


def test_an_entry_written_here_reads_back(tmp_path):
    store, tg = _store(tmp_path)
    t = next(iter(tg))
    store.save(t, {"a": np.ones((2, 2))}, {"sum": 4.0})
    assert store.done(t) and store.small(t) == {"sum": 4.0}
    assert store._done_path(t).read_bytes().startswith(st._MAC_MAGIC)


@pytest.mark.parametrize("kind", ["plain pickle", "signed with another key", "signature of other bytes"])
def test_a_planted_entry_is_not_unpickled(tmp_path, kind, monkeypatch):
    store, tg = _store(tmp_path)
    t = next(iter(tg))
    marker = tmp_path / "pwned"
    evil = pickle.dumps(_RunsCode(marker))
    p = store._done_path(t)
    if kind == "plain pickle":
        p.write_bytes(evil)
    elif kind == "signed with another key":
        with monkeypatch.context() as m:
            m.setattr(st, "_work_key", lambda: b"\1" * 32)
            p.write_bytes(st._sign(evil))
    else:
        good = st._sign(pickle.dumps(1))
        p.write_bytes(good[: -len(pickle.dumps(1))] + evil)
    with pytest.raises(ProcessingError, match="not written by geocd for this user"):
        store.small(t)
    assert not store.done(t) and not p.exists()  # the tile counts as not finished: it is computed again
    assert not marker.exists()


def test_a_run_recomputes_a_tile_whose_entry_was_planted(tmp_path):
    g = _grid()
    x = np.arange(g.height * g.width, dtype=np.float32).reshape(g.shape)

    def tile(arrays, ctx):
        return TileOutput(arrays={"y": arrays["x"] * 2}, small=float(np.sum(ctx.crop(arrays["x"]))))

    kw = dict(tile_size=(30, 25), out=tmp_path, stage="plant", scheduler="sync")
    run_tiled(tile, g, {"x": ArraySource(x)}, **kw)
    entries = sorted((tmp_path / WORK_DIR).rglob("*.done.pkl"))
    assert len(entries) == 4
    marker = tmp_path / "pwned"
    entries[0].write_bytes(pickle.dumps(_RunsCode(marker)))
    run = run_tiled(tile, g, {"x": ArraySource(x)}, **kw)
    assert run.n_resumed == 3 and not marker.exists()
    assert sum(s for _t, s in run.smalls()) == pytest.approx(float(x.sum()))
    np.testing.assert_array_equal(run.read("y"), x * 2)


def test_the_key_file_is_private_and_reused(tmp_path, monkeypatch):
    monkeypatch.setenv(st.WORK_KEY_ENV, str(tmp_path / "k" / "work_key"))
    monkeypatch.setattr(st, "_KEYS", {})
    k1 = st._work_key()
    assert len(k1) == 32 and (tmp_path / "k" / "work_key").stat().st_mode & 0o077 == 0
    monkeypatch.setattr(st, "_KEYS", {})
    assert st._work_key() == k1
    # no writable place for the key: a key of this process (entries of other runs are recomputed)
    (tmp_path / "file").write_text("")
    monkeypatch.setenv(st.WORK_KEY_ENV, str(tmp_path / "file" / "work_key"))
    assert len(st._work_key()) == 32
