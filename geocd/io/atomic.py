"""Atomic output: write to a temporary file next to the target, then rename.

A failed or cancelled run leaves no half-written product, and geocd never
overwrites a user's input (see :func:`check_output_path`).

Temporary names are ``.<stem>.<8 random>.part<suffix>`` (files) and
``.<name>.<8 random>.part`` (folders): :mod:`geocd.io.outputs` removes such litter
left by a killed run, and nothing ever reads a ``.part`` file as a product.
A failed write is raised as a :class:`~geocd.errors.GeoCDError` naming the fix
(no space left, file-size limit, read-only file system, permission denied).

Hooks (used by :mod:`geocd.io.outputs`): :data:`BEFORE_WRITE` callables get each
target before anything is written (they may refuse it); :data:`AFTER_WRITE`
callables get it once it is complete and in place.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import stat
import tempfile
from pathlib import Path
from typing import Callable, Iterator

from ..errors import GeoCDError, OutputError, UnsupportedFormatError

#: input files registered by the current run (resolved path → registrations); outputs must not replace them
_PROTECTED: dict[Path, int] = {}
#: (st_dev, st_ino) of protected inputs, so a hard link or another spelling of the path is refused too
_PROTECTED_IDS: dict[tuple[int, int], int] = {}

#: callables(target Path) run before a product is written (may raise OutputError)
BEFORE_WRITE: list[Callable[[Path], None]] = []
#: callables(target Path) run once a product is complete and renamed into place
AFTER_WRITE: list[Callable[[Path], None]] = []


def _input_path(p: os.PathLike | str) -> Path | None:
    s = str(p)
    if not s or "://" in s or s.startswith("/vsi"):
        return None
    s = s.split("|", 1)[0]  # QGIS/OGR "file.gpkg|layername=x"
    try:
        return Path(s).expanduser().resolve()
    except (OSError, RuntimeError, ValueError):
        return None


def _file_id(p: Path) -> tuple[int, int] | None:
    try:
        st = p.stat()
    except (OSError, ValueError):
        return None
    return (st.st_dev, st.st_ino)


def protect_inputs(*paths: os.PathLike | str) -> list[Path]:
    """Register input files so that no output path may replace them; returns the resolved paths."""
    out = []
    for p in paths:
        if p is None:
            continue
        rp = _input_path(p)
        if rp is None:
            continue
        _PROTECTED[rp] = _PROTECTED.get(rp, 0) + 1
        fid = _file_id(rp)
        if fid is not None:
            _PROTECTED_IDS[fid] = _PROTECTED_IDS.get(fid, 0) + 1
        out.append(rp)
    return out


def unprotect_inputs(*paths: os.PathLike | str) -> None:
    """Undo one :func:`protect_inputs` registration of each path."""
    for p in paths:
        rp = _input_path(p)
        if rp is None:
            continue
        if rp in _PROTECTED:
            _PROTECTED[rp] -= 1
            if _PROTECTED[rp] <= 0:
                del _PROTECTED[rp]
        fid = _file_id(rp)
        if fid is not None and fid in _PROTECTED_IDS:
            _PROTECTED_IDS[fid] -= 1
            if _PROTECTED_IDS[fid] <= 0:
                del _PROTECTED_IDS[fid]


def protected_input(path: os.PathLike | str) -> bool:
    """Whether ``path`` is (another name of) a registered input file."""
    rp = _input_path(path)
    if rp is None:
        return False
    if rp in _PROTECTED:
        return True
    fid = _file_id(rp)
    return fid is not None and fid in _PROTECTED_IDS


def protected_inputs_under(folder: os.PathLike | str) -> list[Path]:
    """Registered input files inside ``folder``."""
    rf = _input_path(folder)
    if rf is None:
        return []
    return [p for p in _PROTECTED if p == rf or rf in p.parents]


def _largest_size(tmp: Path | None) -> int:
    """Size of the largest of a temporary and its side files (journals, overviews)."""
    if tmp is None:
        return 0
    best = 0
    with contextlib.suppress(OSError):
        for p in [tmp, *tmp.parent.glob(glob_escape(tmp.name) + "[.-]*")]:
            with contextlib.suppress(OSError):
                best = max(best, p.stat().st_size if p.is_file() else 0)
    return best


def _write_error(exc: BaseException, target: Path, tmp: Path | None = None) -> GeoCDError | None:
    """The GeoCDError for a failed write of ``target`` (disk full, size limit, read-only, ...), or None.

    Libraries do not always say why a write failed (OGR: "Failed to commit transaction"): a temporary that
    reached the ``ulimit -f`` size, or a disk with (almost) no free space, is taken as the reason.
    """
    if isinstance(exc, GeoCDError) or not isinstance(exc, Exception):
        return None
    from ..errors import DiskFullError
    from ..faults import disk_full_error, free_bytes, translate

    err = disk_full_error(exc, target)
    if err is None and tmp is not None:
        try:
            import resource

            soft, _ = resource.getrlimit(resource.RLIMIT_FSIZE)
        except (ImportError, ValueError, OSError):  # pragma: no cover
            soft = None
        size = _largest_size(tmp)
        free = free_bytes(target.parent)
        if soft not in (None, getattr(resource, "RLIM_INFINITY", None)) and size >= soft - 65536:
            err = DiskFullError(
                f"file size limit reached writing {target} ({soft / 1e6:,.2f} MB, a shell `ulimit -f` "
                "or a quota); raise the limit or write to another folder (--out)"
            )
        elif free is not None and free < 1 << 20:
            err = DiskFullError(
                f"no space left on device writing {target} ({free / 1e3:,.0f} kB free there); free "
                "some space or choose an output folder on another disk (--out)"
            )
    if err is None and isinstance(exc, OSError):
        err = translate(exc, target=target)
    if err is not None:
        err.__cause__ = exc
    return err


def check_output_path(path: os.PathLike | str, overwrite: bool = True) -> Path:
    """Validate an output path: parent exists (created), not a protected input."""
    p = Path(path)
    if protected_input(p):
        raise OutputError(
            f"refusing to overwrite the input file {p}; choose another output folder (--out) or another output name"
        )
    if p.exists() and p.is_dir():
        raise OutputError(f"output path {p} is a folder; give a file name")
    if p.exists() and not overwrite:
        raise OutputError(f"{p} exists; remove it or pass --overwrite")
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
    except FileExistsError as exc:
        raise OutputError(
            f"cannot create the output folder {p.parent}: a file of that name is in the way; "
            "choose another output folder"
        ) from exc
    except OSError as exc:
        raise (
            _write_error(exc, p.parent) or OutputError(f"cannot create the output folder {p.parent}: {exc}")
        ) from exc
    for hook in BEFORE_WRITE:
        hook(p)
    return p


@contextlib.contextmanager
def atomic_path(path: os.PathLike | str, overwrite: bool = True) -> Iterator[Path]:
    """Yield a temporary path in the target's folder; rename it onto ``path`` on success.

    The temporary file keeps the target's suffix (drivers pick formats by
    extension). On any exception the temporary file is removed and the target is
    left as it was.
    """
    target = check_output_path(path, overwrite=overwrite)
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{target.stem}.", suffix=f".part{target.suffix}", dir=target.parent)
    except OSError as exc:
        raise (_write_error(exc, target) or OutputError(f"cannot write into {target.parent}: {exc}")) from exc
    os.close(fd)
    os.unlink(tmp)  # drivers want to create the file themselves
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        if not tmp_path.exists():
            raise OutputError(f"nothing was written for {target}")
        if protected_input(target):  # registered while we were writing
            raise OutputError(f"refusing to overwrite the input file {target}; choose another output folder")
        os.replace(tmp_path, target)
    except BaseException as exc:
        err = _write_error(exc, target, tmp_path)
        _remove_temporary(tmp_path, target.parent)
        if err is not None:
            raise err from exc
        raise
    for hook in AFTER_WRITE:
        hook(target)


def _remove_temporary(tmp_path: Path, folder: Path) -> None:
    with contextlib.suppress(OSError):
        if tmp_path.is_dir() and not tmp_path.is_symlink():
            shutil.rmtree(tmp_path)
        else:
            tmp_path.unlink()
    # GDAL/SQLite side files (.aux.xml, .ovr, -journal, -wal) of the temporary
    with contextlib.suppress(OSError):
        for side in folder.glob(glob_escape(tmp_path.name) + "[.-]*"):
            with contextlib.suppress(OSError):
                side.unlink()


def glob_escape(name: str) -> str:
    """``name`` with glob metacharacters escaped."""
    import glob

    return glob.escape(name)


@contextlib.contextmanager
def atomic_dir(path: os.PathLike | str) -> Iterator[Path]:
    """Yield a temporary folder; on success, swap it into place (old one removed after).

    Used for multi-file products (e.g. a saved volumetric model): a crash keeps
    the previous version intact.
    """
    target = Path(path)
    if protected_input(target) or protected_inputs_under(target):
        raise OutputError(
            f"refusing to replace the folder {target}: it holds input files of this run; choose another output folder"
        )
    if target.exists() and not target.is_dir():
        raise OutputError(f"output path {target} is a file; give a folder")
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        for hook in BEFORE_WRITE:
            hook(target)
        tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.", suffix=".part", dir=target.parent))
    except OSError as exc:
        raise (_write_error(exc, target) or OutputError(f"cannot write into {target.parent}: {exc}")) from exc
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
    except BaseException as exc:
        shutil.rmtree(tmp, ignore_errors=True)
        err = _write_error(exc, target)
        if err is not None:
            raise err from exc
        raise
    for hook in AFTER_WRITE:
        hook(target)


def write_text_atomic(path: os.PathLike | str, text: str) -> Path:
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)


def refuse_special_file(path: os.PathLike | str, what: str = "input") -> None:
    """Refuse a named pipe (FIFO), socket or device given where a file is expected, before anything opens it.

    Opening a FIFO blocks until another process writes into it (the command would hang); a device never ends.
    Paths that do not exist, directories and URLs/GDAL virtual paths pass (other checks speak for them).

    Raises
    ------
    UnsupportedFormatError
    """
    if path is None or "://" in str(path) or str(path).startswith("/vsi"):
        return
    try:
        mode = os.stat(path).st_mode
    except (OSError, ValueError):
        return
    kind = (
        "a named pipe (FIFO)"
        if stat.S_ISFIFO(mode)
        else "a socket"
        if stat.S_ISSOCK(mode)
        else "a character device"
        if stat.S_ISCHR(mode)
        else "a block device"
        if stat.S_ISBLK(mode)
        else None
    )
    if kind is not None:
        raise UnsupportedFormatError(
            f"{what} {path} is {kind}, not a regular file; geocd reads files only: save the "
            "data to a file and give that path"
        )
