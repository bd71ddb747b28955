"""Read a PyTorch ``state_dict`` file (``torch.save``) into numpy arrays without PyTorch.

Both of PyTorch's formats are read: the zip archive of PyTorch ≥ 1.6 (``data.pkl`` plus one
member per storage) and the legacy stream of older versions (pickles followed by the raw
storages). The pickle is read with a restricted unpickler that builds nothing but
dictionaries, lists, tuples and tensors (as numpy arrays): a file that asks for any other
class is refused, so loading a weights file cannot run code.
"""

from __future__ import annotations

import collections
import io
import pickle
import struct
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

#: torch storage classes → numpy dtypes
_STORAGE_DTYPES = {
    "FloatStorage": np.float32, "DoubleStorage": np.float64, "HalfStorage": np.float16,
    "BFloat16Storage": None,  # no numpy dtype: refused with a clear message
    "LongStorage": np.int64, "IntStorage": np.int32, "ShortStorage": np.int16, "CharStorage": np.int8,
    "ByteStorage": np.uint8, "BoolStorage": np.bool_,
}
_LEGACY_MAGIC = 0x1950A86A20F9469CFC6C


class TorchFileError(ValueError):
    """The file is not a PyTorch file this reader can take (the message says why)."""


class _Storage:
    def __init__(self, key: str, dtype, numel: int | None) -> None:
        self.key, self.dtype, self.numel = key, dtype, numel
        self.data: np.ndarray | None = None


class _LazyTensor:
    def __init__(self, storage: _Storage, offset: int, size: tuple, stride: tuple) -> None:
        self.storage, self.offset, self.size, self.stride = storage, int(offset), tuple(size), tuple(stride)

    def materialise(self) -> np.ndarray:
        d = self.storage.data
        if d is None:
            raise TorchFileError(f"storage {self.storage.key!r} is referenced but not in the file")
        item = d.itemsize
        if not self.size:
            return np.array(d[self.offset])
        need = self.offset + 1 + sum((n - 1) * s for n, s in zip(self.size, self.stride) if n > 0)
        if need > d.size:
            raise TorchFileError(f"a tensor of shape {self.size} does not fit its storage ({d.size} elements)")
        return np.lib.stride_tricks.as_strided(d[self.offset:], shape=self.size,
                                               strides=tuple(s * item for s in self.stride)).copy()


def _rebuild_tensor(storage, storage_offset, size, stride, *_rest):
    return _LazyTensor(storage, storage_offset, size, stride)


class _Marker:
    """A storage class named in the pickle (its name carries the dtype)."""

    def __init__(self, name: str) -> None:
        self.name = name


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
        raise TorchFileError(f"the file asks for {module}.{name}: only a state_dict of tensors can be read "
                             "without PyTorch (save model.state_dict(), or install geocd[cnn])")

    def persistent_load(self, pid) -> _Storage:
        if not (isinstance(pid, tuple) and pid and pid[0] == "storage"):
            raise TorchFileError(f"unknown persistent id {pid!r:.60}")
        marker, key = pid[1], str(pid[2])
        numel = int(pid[4]) if len(pid) > 4 else None
        if not isinstance(marker, _Marker):
            raise TorchFileError(f"unknown storage type {marker!r:.60}")
        dtype = _STORAGE_DTYPES[marker.name]
        if dtype is None:
            raise TorchFileError(f"{marker.name} tensors have no numpy type: save the weights as float32")
        if key not in self.storages:
            self.storages[key] = _Storage(key, np.dtype(dtype), numel)
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
            st.data = np.frombuffer(z.read(member), dtype=st.dtype.newbyteorder("<"))
    return _resolve(obj)


def _read_legacy(path: Path) -> Any:
    with open(path, "rb") as f:
        try:
            magic = pickle.load(f)
        except Exception as exc:  # noqa: BLE001 - any unreadable start is the same error
            raise TorchFileError(f"{path} is neither a zip archive nor a legacy torch.save stream") from exc
        if magic != _LEGACY_MAGIC:
            raise TorchFileError(f"{path} is not a torch.save file (wrong magic number)")
        pickle.load(f)  # protocol version
        sys_info = pickle.load(f)
        if isinstance(sys_info, dict) and not sys_info.get("little_endian", True):
            raise TorchFileError(f"{path} was written on a big-endian machine")
        storages: dict[str, _Storage] = {}
        obj = _Unpickler(f, storages).load()
        keys = pickle.load(f)
        for key in keys:
            st = storages.get(str(key))
            if st is None:
                raise TorchFileError(f"{path}: storage {key!r} is listed but never used")
            (n,) = struct.unpack("<q", f.read(8))
            raw = f.read(n * st.dtype.itemsize)
            if len(raw) != n * st.dtype.itemsize:
                raise TorchFileError(f"{path} is truncated (storage {key!r})")
            st.data = np.frombuffer(raw, dtype=st.dtype.newbyteorder("<"))
    return _resolve(obj)


def read_torch_file(path: str | Path) -> Any:
    """The object a ``torch.save`` file holds, tensors as numpy arrays (no PyTorch needed).

    Raises
    ------
    TorchFileError
        The file is not a torch.save file, is truncated, or holds anything but containers of tensors.
    """
    p = Path(path)
    return _read_zip(p) if zipfile.is_zipfile(p) else _read_legacy(p)
