"""Read a PyTorch ``state_dict`` file (``torch.save``) into numpy arrays without PyTorch.

Both of PyTorch's formats are read: the zip archive of PyTorch ≥ 1.6 (``data.pkl`` plus one
member per storage) and the legacy stream of older versions (pickles followed by the raw
storages). Every pickle in the file (the legacy stream's magic number, protocol, system
information and storage keys too) is read with a restricted unpickler that builds nothing but
dictionaries, lists, tuples and tensors (as numpy arrays): a file that asks for any other
class or function is refused before anything is called, so loading a weights file cannot
run code.
"""

from __future__ import annotations

import collections
import io
import lzma
import pickle
import struct
import zipfile
import zlib
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import UnsupportedFormatError

#: torch storage classes → numpy dtypes
_STORAGE_DTYPES = {
    "FloatStorage": np.float32,
    "DoubleStorage": np.float64,
    "HalfStorage": np.float16,
    "BFloat16Storage": None,  # no numpy dtype: refused with a clear message
    "LongStorage": np.int64,
    "IntStorage": np.int32,
    "ShortStorage": np.int16,
    "CharStorage": np.int8,
    "ByteStorage": np.uint8,
    "BoolStorage": np.bool_,
}
_LEGACY_MAGIC = 0x1950A86A20F9469CFC6C


class TorchFileError(UnsupportedFormatError):
    """The file is not a PyTorch file this reader can take (the message says why)."""


class _Sealed:
    """The reader's own objects: a pickle's BUILD opcode must not rewrite their attributes."""

    def __setstate__(self, state: Any) -> None:
        raise TorchFileError("the pickle tries to set the state of a tensor or storage: not a torch.save file")


class _Storage(_Sealed):
    def __init__(self, key: str, dtype, numel: int | None) -> None:
        self.key, self.dtype, self.numel = key, dtype, numel
        self.data: np.ndarray | None = None


def _index_tuple(v: Any, what: str) -> tuple[int, ...]:
    """``v`` as a tuple of non-negative ints (a tensor's size or stride), else TorchFileError."""
    if not isinstance(v, (tuple, list)) or not all(
        isinstance(n, int) and not isinstance(n, bool) and n >= 0 for n in v
    ):
        raise TorchFileError(f"a tensor's {what} is {v!r:.60}, not a tuple of non-negative integers")
    return tuple(v)


class _LazyTensor(_Sealed):
    def __init__(self, storage: Any, offset: Any, size: Any, stride: Any) -> None:
        if not isinstance(storage, _Storage):
            raise TorchFileError(f"a tensor's storage is a {type(storage).__name__}, not a storage")
        if not isinstance(offset, int) or isinstance(offset, bool) or offset < 0:
            raise TorchFileError(f"a tensor's storage offset is {offset!r:.40}, not a non-negative integer")
        self.storage, self.offset = storage, offset
        self.size, self.stride = _index_tuple(size, "size"), _index_tuple(stride, "stride")
        if len(self.stride) != len(self.size):
            raise TorchFileError(f"a tensor has size {self.size} but stride {self.stride}")

    def materialise(self) -> np.ndarray:
        d = self.storage.data
        if d is None:
            raise TorchFileError(f"storage {self.storage.key!r} is referenced but not in the file")
        item = d.itemsize
        if 0 in self.size:
            return np.zeros(self.size, dtype=d.dtype)
        # the last element the strides reach must lie inside the storage (sizes and strides are >= 0)
        need = self.offset + 1 + sum((n - 1) * s for n, s in zip(self.size, self.stride))
        if need > d.size:
            raise TorchFileError(f"a tensor of shape {self.size} does not fit its storage ({d.size} elements)")
        if not self.size:
            return np.array(d[self.offset])
        return np.lib.stride_tricks.as_strided(
            d[self.offset :], shape=self.size, strides=tuple(s * item for s in self.stride)
        ).copy()


def _rebuild_tensor(storage, storage_offset, size, stride, *_rest):
    return _LazyTensor(storage, storage_offset, size, stride)


class _Marker(_Sealed):
    """A storage class named in the pickle (its name carries the dtype)."""

    def __init__(self, name: str) -> None:
        self.name = name


class _PlainUnpickler(pickle.Unpickler):
    """Plain data only (numbers, strings, containers): every global and persistent id is refused."""

    def find_class(self, module: str, name: str) -> Any:
        raise TorchFileError(
            f"the file asks for {module}.{name} where a torch.save file holds plain data, "
            "which is refused without being run: not a weights file"
        )

    def persistent_load(self, pid: Any) -> Any:
        raise TorchFileError("the file holds a persistent id where a torch.save file holds plain data")


def _load_plain(f: Any) -> Any:
    """One pickle of plain data from ``f`` (the legacy stream's header and storage keys)."""
    return _PlainUnpickler(f).load()


class _Unpickler(pickle.Unpickler):
    def __init__(self, f, storages: dict[str, _Storage]) -> None:
        super().__init__(f)
        self.storages = storages

    def find_class(self, module: str, name: str) -> Any:
        if module == "collections" and name == "OrderedDict":
            return collections.OrderedDict
        if module == "torch._utils" and name in ("_rebuild_tensor_v2", "_rebuild_tensor"):
            return _rebuild_tensor
        if module == "torch" and name in _STORAGE_DTYPES:
            return _Marker(name)
        if module == "torch" and name == "Size":
            return tuple
        raise TorchFileError(
            f"the file asks for {module}.{name}, which is refused without being run: a weights "
            "file must hold a state_dict of tensors only (save model.state_dict(), not the model)"
        )

    def persistent_load(self, pid) -> _Storage:
        if not (isinstance(pid, tuple) and len(pid) >= 3 and pid[0] == "storage"):
            raise TorchFileError(f"unknown persistent id {pid!r:.60}")
        marker, key = pid[1], pid[2]
        if not isinstance(key, (str, int)) or isinstance(key, bool):
            raise TorchFileError(f"a storage key is {key!r:.40}, not a string")
        key = str(key)
        numel = pid[4] if len(pid) > 4 and isinstance(pid[4], int) else None
        if not isinstance(marker, _Marker):
            raise TorchFileError(f"unknown storage type {marker!r:.60}")
        dtype = _STORAGE_DTYPES[marker.name]
        if dtype is None:
            raise TorchFileError(f"{marker.name} tensors have no numpy type: save the weights as float32")
        if key not in self.storages:
            self.storages[key] = _Storage(key, np.dtype(dtype), numel)
        elif self.storages[key].dtype != np.dtype(dtype):
            raise TorchFileError(f"storage {key!r} is named with two types")
        return self.storages[key]


def _resolve(obj: Any) -> Any:
    if isinstance(obj, _LazyTensor):
        return obj.materialise()
    if isinstance(obj, dict):
        return {k: _resolve(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return type(obj)(_resolve(v) for v in obj)
    return obj


def _read_zip(path: Path) -> Any:
    with zipfile.ZipFile(path) as z:
        names = z.namelist()
        pkl = [n for n in names if n.endswith("/data.pkl") or n == "data.pkl"]
        if not pkl:
            raise TorchFileError(f"{path} is a zip archive without data.pkl: not a torch.save file")
        root = pkl[0][: -len("data.pkl")]
        storages: dict[str, _Storage] = {}
        obj = _Unpickler(io.BytesIO(z.read(pkl[0])), storages).load()
        for key, st in storages.items():
            member = f"{root}data/{key}"
            if member not in names:
                raise TorchFileError(f"{path}: storage {key!r} is missing from the archive")
            raw = z.read(member)
            if len(raw) % st.dtype.itemsize:
                raise TorchFileError(f"{path}: storage {key!r} is not a whole number of {st.dtype} values")
            st.data = np.frombuffer(raw, dtype=st.dtype.newbyteorder("<"))
    return _resolve(obj)


def _read_legacy(path: Path) -> Any:
    size_b = path.stat().st_size
    with open(path, "rb") as f:
        try:
            magic = _load_plain(f)
        except TorchFileError:
            raise
        except Exception as exc:  # noqa: BLE001 - any unreadable start is the same error
            raise TorchFileError(f"{path} is neither a zip archive nor a legacy torch.save stream") from exc
        if type(magic) is not int or magic != _LEGACY_MAGIC:
            raise TorchFileError(f"{path} is not a torch.save file (wrong magic number)")
        _load_plain(f)  # protocol version
        sys_info = _load_plain(f)
        if isinstance(sys_info, dict) and not sys_info.get("little_endian", True):
            raise TorchFileError(f"{path} was written on a big-endian machine")
        storages: dict[str, _Storage] = {}
        obj = _Unpickler(f, storages).load()
        keys = _load_plain(f)
        if not isinstance(keys, (list, tuple)):
            raise TorchFileError(f"{path}: the storage keys are a {type(keys).__name__}, not a list")
        for key in keys:
            st = storages.get(str(key))
            if st is None:
                raise TorchFileError(f"{path}: storage {key!r:.40} is listed but never used")
            head = f.read(8)
            if len(head) != 8:
                raise TorchFileError(f"{path} is truncated (storage {key!r})")
            (n,) = struct.unpack("<q", head)
            # the count is checked against what is left of the file before anything is allocated
            fits = 0 <= n * st.dtype.itemsize <= size_b - f.tell()
            raw = f.read(n * st.dtype.itemsize) if fits else b""
            if not fits or len(raw) != n * st.dtype.itemsize:
                raise TorchFileError(f"{path} is truncated (storage {key!r})")
            st.data = np.frombuffer(raw, dtype=st.dtype.newbyteorder("<"))
    return _resolve(obj)


def read_torch_file(path: str | Path) -> Any:
    """The object a ``torch.save`` file holds, tensors as numpy arrays (no PyTorch needed).

    No pickle in the file can run code: every global it names is refused except the tensor-rebuild
    function and the storage types, which this module implements itself.

    Raises
    ------
    TorchFileError
        The file is not a torch.save file, is truncated, or holds anything but containers of tensors.
    """
    p = Path(path)
    try:
        return _read_zip(p) if zipfile.is_zipfile(p) else _read_legacy(p)
    except (TorchFileError, OSError):
        raise
    except (
        pickle.UnpicklingError,
        zipfile.BadZipFile,
        EOFError,
        ValueError,
        TypeError,
        KeyError,
        IndexError,
        AttributeError,
        struct.error,
        RecursionError,
        MemoryError,
        OverflowError,
        NotImplementedError,
        zlib.error,
        lzma.LZMAError,
    ) as exc:
        # a garbled pickle, archive or storage: the same user error, never an internal one
        raise TorchFileError(f"{p} is not a readable torch.save file ({type(exc).__name__}: {exc})") from exc
