"""Atomic output: write to a temporary file next to the target, then rename.

A failed or cancelled run leaves no half-written product, and geocd never
overwrites a user's input (see :func:`check_output_path`).
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from pathlib import Path
from typing import Iterator

from ..errors import OutputError

#: input files registered by the current run; outputs must not replace them
_PROTECTED: set[Path] = set()


def protect_inputs(*paths: os.PathLike | str) -> None:
    """Register input files so that no output path may replace them."""
    for p in paths:
        try:
            _PROTECTED.add(Path(p).resolve())
        except OSError:
            pass


def check_output_path(path: os.PathLike | str, overwrite: bool = True) -> Path:
    """Validate an output path: parent exists (created), not a protected input."""
    p = Path(path)
    rp = p.resolve()
    if rp in _PROTECTED:
        raise OutputError(f"refusing to overwrite the input file {p}; choose another output folder")
    if p.exists() and p.is_dir():
        raise OutputError(f"output path {p} is a folder; give a file name")
    if p.exists() and not overwrite:
        raise OutputError(f"{p} exists; remove it or pass --overwrite")
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"cannot create the output folder {p.parent}: {exc}") from exc
    return p


@contextlib.contextmanager
def atomic_path(path: os.PathLike | str, overwrite: bool = True) -> Iterator[Path]:
    """Yield a temporary path in the target's folder; rename it onto ``path`` on success.

    The temporary file keeps the target's suffix (drivers pick formats by
    extension). On any exception the temporary file is removed and the target is
    left as it was.
    """
    target = check_output_path(path, overwrite=overwrite)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.stem}.", suffix=f".part{target.suffix}", dir=target.parent)
    os.close(fd)
    os.unlink(tmp)  # drivers want to create the file themselves
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        if not tmp_path.exists():
            raise OutputError(f"nothing was written for {target}")
        os.replace(tmp_path, target)
    except BaseException:
        with contextlib.suppress(OSError):
            if tmp_path.is_dir():
                shutil.rmtree(tmp_path)
            else:
                tmp_path.unlink()
        # GDAL side files (e.g. .aux.xml) of the temporary
        for side in target.parent.glob(tmp_path.name + ".*"):
            with contextlib.suppress(OSError):
                side.unlink()
        raise


@contextlib.contextmanager
def atomic_dir(path: os.PathLike | str) -> Iterator[Path]:
    """Yield a temporary folder; on success, swap it into place (old one removed after).

    Used for multi-file products (e.g. a saved volumetric model): a crash keeps
    the previous version intact.
    """
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.", suffix=".part", dir=target.parent))
    try:
        yield tmp
        old = None
        if target.exists():
            old = target.with_name(f".{target.name}.old")
            if old.exists():
                shutil.rmtree(old)
            os.replace(target, old)
        os.replace(tmp, target)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def write_text_atomic(path: os.PathLike | str, text: str) -> Path:
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)
