"""The work folder of a tiled pass: per-tile results and the journal that makes runs resumable.

Layout (hidden, inside the output folder)::

    <out>/.geocd-work/<stage>-<key16>/
        run.json                      what this pass is (its key: a hash of the command's parameters)
        r0000_c0001.<name>.npy        the tile's core of array <name> (one file per array)
        r0000_c0001.done.pkl          the tile's small results (reductions, vectors): the journal entry

Only the client process writes here (one writer). A tile is finished when its
``.done.pkl`` exists and is authentic; it is renamed into place after the tile's arrays,
so a run killed at any moment leaves finished tiles complete and unfinished ones invisible.

The journal entries are pickles, and unpickling runs whatever code a pickle names, so each
entry carries an HMAC-SHA256 of its bytes under a random key of this user
(``$GEOCD_WORK_KEY`` names the key file, else ``$XDG_CACHE_HOME/geocd/work_key``). An entry
geocd did not write here (planted in the folder, copied from another machine, damaged) is
never unpickled: its tile is computed again.
A pass with another key (a changed command: other parameters or inputs) never
reuses these files: opening it removes the stale folder of the same stage.
"""

from __future__ import annotations

import contextlib
import hashlib
import hmac
import json
import math
import os
import pickle
import secrets
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from ..errors import OutputError, ProcessingError
from ..geodesy import AOIGrid
from .grid import Tile, TileGrid

WORK_DIR = ".geocd-work"
#: environment variable naming the file of the key that authenticates journal entries
WORK_KEY_ENV = "GEOCD_WORK_KEY"
_MAC_MAGIC = b"GEOCD-HMAC-SHA256\n"
_MAC_BYTES = 32
_KEYS: dict[str, bytes] = {}


def _work_key() -> bytes:
    """This user's key for journal entries (created on first use, mode 0600).

    Where the key file cannot be read or written, a key of this process is used: entries of
    another run are then not trusted, and their tiles are computed again.
    """
    env = os.environ.get(WORK_KEY_ENV)
    path = Path(env) if env else Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "geocd" / "work_key"
    key = _KEYS.get(str(path))
    if key is not None:
        return key
    try:
        key = path.read_bytes()
        if len(key) < _MAC_BYTES:
            raise OSError("too short")
    except OSError:
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
            with os.fdopen(fd, "wb") as f:
                f.write(secrets.token_bytes(_MAC_BYTES))
        except FileExistsError:
            pass  # another process made it (or a short one is there: read below)
        except OSError:
            pass
        try:
            key = path.read_bytes()
        except OSError:
            key = b""
        if len(key) < _MAC_BYTES:
            key = secrets.token_bytes(_MAC_BYTES)  # this process only
    _KEYS[str(path)] = key
    return key


def _sign(payload: bytes) -> bytes:
    return _MAC_MAGIC + hmac.new(_work_key(), payload, hashlib.sha256).digest() + payload


def _verified_payload(raw: bytes) -> bytes | None:
    """The pickle of a journal entry if its HMAC is this user's, else None (never unpickled)."""
    head = len(_MAC_MAGIC)
    if len(raw) < head + _MAC_BYTES or not raw.startswith(_MAC_MAGIC):
        return None
    mac, payload = raw[head : head + _MAC_BYTES], raw[head + _MAC_BYTES :]
    if not hmac.compare_digest(mac, hmac.new(_work_key(), payload, hashlib.sha256).digest()):
        return None
    return payload


def _canon(o: Any) -> Any:
    if hasattr(o, "cache_key") and callable(o.cache_key):
        return _canon(o.cache_key())
    if isinstance(o, Mapping):
        return {str(k): _canon(v) for k, v in sorted(o.items(), key=lambda kv: str(kv[0]))}
    if isinstance(o, (list, tuple)):
        return [_canon(v) for v in o]
    if isinstance(o, np.ndarray):
        return {
            "ndarray_sha1": hashlib.sha1(np.ascontiguousarray(o).view(np.uint8)).hexdigest(),
            "shape": list(o.shape),
            "dtype": str(o.dtype),
        }
    if isinstance(o, (np.floating, np.integer, np.bool_)):
        return o.item()
    if isinstance(o, float):
        return repr(o) if not math.isfinite(o) else o
    if hasattr(o, "to_dict") and callable(o.to_dict):
        return _canon(o.to_dict())
    if hasattr(o, "__dataclass_fields__"):
        from dataclasses import asdict

        return _canon(asdict(o))
    if isinstance(o, (str, int, bool)) or o is None:
        return o
    return str(o)


def make_key(*parts: Any) -> str:
    """A stable hash (hex sha256) of parameters, input identities, grid and tiling."""
    from .. import __version__

    blob = json.dumps([__version__, _canon(list(parts))], sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(blob.encode()).hexdigest()


def _replace_atomic(tmp: Path, final: Path) -> None:
    os.replace(tmp, final)


class TileStore:
    """Per-tile results of one pass (see module docstring).

    Parameters
    ----------
    root : the work folder of the run (``<out>/.geocd-work``)
    stage : name of the pass (e.g. ``demdiff-scan``)
    key : hash of everything the pass's results depend on (:func:`make_key`)
    tile_grid : the tiling
    """

    def __init__(self, root: os.PathLike | str, stage: str, key: str, tile_grid: TileGrid):
        self.root = Path(root)
        self.stage = stage
        self.key = key
        self.tile_grid = tile_grid
        self.path = self.root / f"{stage}-{key[:16]}"
        try:
            self.path.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise OutputError(f"cannot create the work folder {self.path}: {exc}") from exc
        for stale in self.root.glob(f"{stage}-*"):
            if stale != self.path and stale.is_dir() and len(stale.name) == len(self.path.name):
                shutil.rmtree(stale, ignore_errors=True)
        meta = self.path / "run.json"
        if not meta.exists():
            tmp = meta.with_suffix(".json.part")
            tmp.write_text(
                json.dumps(
                    {
                        "stage": stage,
                        "key": key,
                        "grid": tile_grid.grid.to_dict(),
                        "tile_size": list(tile_grid.tile_size),
                    },
                    indent=1,
                )
            )
            _replace_atomic(tmp, meta)
        # stale temporaries of a killed run
        for part in self.path.glob("*.part*"):
            with contextlib.suppress(OSError):
                part.unlink()

    # --- journal -------------------------------------------------------------------------
    def _done_path(self, tile: Tile) -> Path:
        return self.path / f"{tile.name}.done.pkl"

    def done(self, tile: Tile) -> bool:
        """Whether the tile is finished: its journal entry exists and is authentic (else it is removed)."""
        p = self._done_path(tile)
        try:
            raw = p.read_bytes()
        except OSError:
            return False
        if _verified_payload(raw) is None:
            with contextlib.suppress(OSError):
                p.unlink()  # not written by geocd for this user: the tile is computed again
            return False
        return True

    def n_done(self) -> int:
        return sum(1 for _ in self.path.glob("*.done.pkl"))

    def save(self, tile: Tile, arrays: Mapping[str, np.ndarray], small: Any) -> None:
        """Store a tile's core arrays and small results; the journal entry is written last."""
        for name, arr in arrays.items():
            final = self.path / f"{tile.name}.{name}.npy"
            tmp = self.path / f"{tile.name}.{name}.part.npy"
            np.save(tmp, np.ascontiguousarray(arr))
            _replace_atomic(tmp, final)
        final = self._done_path(tile)
        tmp = self.path / f"{tile.name}.done.part.pkl"
        with open(tmp, "wb") as f:
            f.write(_sign(pickle.dumps(small, protocol=pickle.HIGHEST_PROTOCOL)))
        _replace_atomic(tmp, final)

    def small(self, tile: Tile) -> Any:
        """The tile's small results; unpickled only when the entry's HMAC shows geocd wrote it for this user."""
        p = self._done_path(tile)
        payload = _verified_payload(p.read_bytes())
        if payload is None:
            raise ProcessingError(
                f"the journal entry {p} was not written by geocd for this user (or is damaged) "
                "and is not read; delete the work folder and run the command again"
            )
        return pickle.loads(payload)

    # --- arrays ---------------------------------------------------------------------------
    def tile_array(self, tile: Tile, name: str, mmap: bool = True) -> np.ndarray:
        p = self.path / f"{tile.name}.{name}.npy"
        if not p.exists():
            raise ProcessingError(f"tile {tile.name} has no array {name!r} in {self.path}")
        return np.load(p, mmap_mode="r" if mmap else None)

    def read(self, name: str, window: tuple[int, int, int, int], fill: float = np.nan) -> np.ndarray:
        """Array ``name`` on ``window`` (row0, col0, h, w) of the grid, assembled from the tiles' cores.

        Cells of tiles the pass did not process (a :class:`TileGrid` with a selection) hold ``fill``
        (NaN by default; 0 for integer arrays when ``fill`` is NaN)."""
        r0, c0, h, w = window
        out = None
        tg = self.tile_grid
        skipped = [t for t in tg.tiles_in(window) if not tg.is_selected(t)]
        for t in tg.units_in(window):
            a = self.tile_array(t, name)
            tr0, tc0, th, tw = t.core
            rr0, cc0 = max(r0, tr0), max(c0, tc0)
            rr1, cc1 = min(r0 + h, tr0 + th), min(c0 + w, tc0 + tw)
            if out is None:
                out = np.empty(a.shape[:-2] + (h, w), a.dtype)
                if skipped:
                    ok = np.issubdtype(a.dtype, np.floating) or np.isfinite(fill)
                    out[...] = fill if ok else 0
            out[..., rr0 - r0 : rr1 - r0, cc0 - c0 : cc1 - c0] = a[..., rr0 - tr0 : rr1 - tr0, cc0 - tc0 : cc1 - tc0]
        if out is None:
            if skipped:  # only unprocessed tiles under the window
                return np.full((h, w), fill, np.float32)
            raise ProcessingError(f"window {window} is outside the grid {self.tile_grid.grid.shape}")
        return out

    def source(self, name: str) -> "StoreSource":
        """A lazy source (for a later pass) of array ``name`` of this pass."""
        return StoreSource(str(self.path), self.tile_grid, name)

    def remove(self) -> None:
        shutil.rmtree(self.path, ignore_errors=True)


@dataclass(frozen=True)
class StoreSource:
    """Reads windows of an array that an earlier pass stored tile by tile (any overlap)."""

    path: str
    tile_grid: TileGrid
    name: str

    def read(self, grid: AOIGrid, window: tuple[int, int, int, int]) -> np.ndarray:
        st = TileStore.__new__(TileStore)
        st.path = Path(self.path)
        st.tile_grid = self.tile_grid
        return np.array(st.read(self.name, window))

    def identity(self) -> dict[str, Any]:
        return {"store": Path(self.path).name, "name": self.name}
