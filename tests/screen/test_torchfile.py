"""geocd's PyTorch file reader runs no code from the file, whatever pickle position carries it."""

from __future__ import annotations

import io
import os
import pickle
import struct
import zipfile
from pathlib import Path

import numpy as np
import pytest

from geocd.errors import GeoCDError, UnsupportedFormatError, WeightsMismatchError
from geocd.screen import cnn
from geocd.screen.torchfile import TorchFileError, _PlainUnpickler, _Unpickler, read_torch_file

from .torch_reference import PTH_LEGACY


def _payloads(marker: Path) -> dict[str, object]:
    """Objects whose unpickling would create ``marker`` (three different ways of running code)."""

    class ViaOpen:
        def __reduce__(self):
            return (open, (str(marker), "w"))

    class ViaSystem:
        def __reduce__(self):
            return (os.system, (f"touch {marker}",))

    class ViaEval:
        def __reduce__(self):
            return (eval, (f"open({str(marker)!r}, 'w')",))

    return {"open": ViaOpen(), "system": ViaSystem(), "eval": ViaEval()}


def _legacy_parts(path: Path) -> list[bytes]:
    """The legacy stream cut into its five pickles (magic, protocol, sys info, object, keys) and the storages."""
    raw = path.read_bytes()
    f = io.BytesIO(raw)
    cuts = [0]
    for i in range(5):
        (_Unpickler(f, {}) if i == 3 else _PlainUnpickler(f)).load()
        cuts.append(f.tell())
    return [raw[a:b] for a, b in zip(cuts, cuts[1:])] + [raw[cuts[-1] :]]


def test_the_legacy_file_cuts_into_five_pickles():
    parts = _legacy_parts(PTH_LEGACY)
    assert b"".join(parts) == PTH_LEGACY.read_bytes()
    assert pickle.loads(parts[0]) == 0x1950A86A20F9469CFC6C


@pytest.mark.parametrize("how", ["open", "system", "eval"])
@pytest.mark.parametrize(
    "where",
    ["zip data.pkl", "legacy magic", "legacy protocol", "legacy sys info", "legacy object", "legacy storage keys"],
)
def test_a_pickle_that_would_run_code_is_refused_before_it_runs(tmp_path, where, how):
    marker = tmp_path / "pwned"
    evil = pickle.dumps(_payloads(marker)[how], protocol=2)
    path = tmp_path / "evil.pth"
    if where == "zip data.pkl":
        with zipfile.ZipFile(path, "w") as z:
            z.writestr("archive/data.pkl", pickle.dumps({"w": _payloads(marker)[how]}, protocol=2))
    else:
        parts = _legacy_parts(PTH_LEGACY)
        i = ["legacy magic", "legacy protocol", "legacy sys info", "legacy object", "legacy storage keys"].index(where)
        parts[i] = evil
        path.write_bytes(b"".join(parts))
    with pytest.raises(TorchFileError) as ei:
        read_torch_file(path)
    assert isinstance(ei.value, GeoCDError) and isinstance(ei.value, UnsupportedFormatError)
    assert not marker.exists()


def test_weights_loading_refuses_code_as_a_geocd_error(tmp_path, monkeypatch):
    monkeypatch.setattr(cnn, "torch_available", lambda: False)
    marker = tmp_path / "pwned"
    parts = _legacy_parts(PTH_LEGACY)
    parts[0] = pickle.dumps(_payloads(marker)["system"], protocol=2)
    (tmp_path / "evil.pth").write_bytes(b"".join(parts))
    with pytest.raises(WeightsMismatchError, match=r"without PyTorch.*asks for (posix|os)\.system"):
        cnn.load_weights(tmp_path / "evil.pth")
    assert not marker.exists()


# --- hand-made pickles that use only the allowed names, with hostile arguments ----------------------------------
def _s(text: str) -> bytes:
    b = text.encode()
    return b"X" + struct.pack("<I", len(b)) + b


def _i(n: int) -> bytes:
    return b"J" + struct.pack("<i", n)


def _tensor_pickle(offset: int, size: tuple, stride: tuple, key: str = "0") -> bytes:
    """{"w": _rebuild_tensor_v2(storage key, offset, size, stride)} as torch writes it (protocol 2)."""
    pid = b"(" + _s("storage") + b"ctorch\nFloatStorage\n" + _s(key) + _s("cpu") + _i(4) + b"tQ"
    tup = lambda xs: b"(" + b"".join(_i(x) for x in xs) + b"t"  # noqa: E731
    tensor = b"ctorch._utils\n_rebuild_tensor_v2\n(" + pid + _i(offset) + tup(size) + tup(stride) + b"\x89tR"
    return b"\x80\x02}" + _s("w") + tensor + b"s."


def _zip(path: Path, pkl: bytes, storage: bytes = np.arange(4, dtype="<f4").tobytes()) -> Path:
    with zipfile.ZipFile(path, "w") as z:
        z.writestr("archive/data.pkl", pkl)
        z.writestr("archive/data/0", storage)
    return path


def test_the_hand_made_tensor_pickle_reads(tmp_path):
    got = read_torch_file(_zip(tmp_path / "ok.pth", _tensor_pickle(0, (2, 2), (1, 2))))
    assert np.array_equal(got["w"], np.arange(4, dtype=np.float32).reshape(2, 2).T)


@pytest.mark.parametrize(
    "offset,size,stride,match",
    [
        (0, (2, 2), (-1, 2), "stride"),  # negative strides would read before the storage
        (-3, (2,), (1,), "offset"),
        (3, (2,), (1,), "does not fit"),
        (0, (2, 2), (1000, 1), "does not fit"),  # reads past the end
        (0, (2, 2), (1,), "size .* but stride"),
        (4, (), (), "does not fit"),
    ],
)
def test_a_tensor_outside_its_storage_is_refused(tmp_path, offset, size, stride, match):
    with pytest.raises(TorchFileError, match=match):
        read_torch_file(_zip(tmp_path / "bad.pth", _tensor_pickle(offset, size, stride)))


def test_garbled_files_are_geocd_errors(tmp_path):
    good = _tensor_pickle(0, (2, 2), (1, 2))
    cases = {
        "truncated pickle": _zip(tmp_path / "a.pth", good[:-9]),
        "storage of 3.5 floats": _zip(tmp_path / "b.pth", good, storage=b"\0" * 14),
        "state of a tensor rewritten": _zip(tmp_path / "c.pth", good[:-2] + b"}" + _s("offset") + _i(-5) + b"sbs."),
    }
    legacy = _legacy_parts(PTH_LEGACY)
    (tmp_path / "d.pth").write_bytes(b"".join(legacy)[:-5])
    cases["truncated legacy storage"] = tmp_path / "d.pth"
    (tmp_path / "e.pth").write_bytes(b"".join(legacy[:5]) + struct.pack("<q", 1 << 60))
    cases["legacy storage of 2^60 values"] = tmp_path / "e.pth"
    for name, path in cases.items():
        with pytest.raises(TorchFileError):
            read_torch_file(path)
