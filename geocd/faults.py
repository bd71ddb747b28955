"""Every failure as a one-line :class:`~geocd.errors.GeoCDError` naming the fix; signals that clean up.

The CLI (:class:`geocd.cli.LazyGroup`) and the QGIS plugin meet exceptions from many
libraries (GDAL through rasterio, OGR through pyogrio, the OS, numpy). Where geocd can, it
raises the right :class:`GeoCDError` at the place the failure happens (a truncated GeoTIFF in
:mod:`geocd.io.raster`, a full disk in :mod:`geocd.io.atomic`); :func:`translate` is the
safety net for the rest, so that a user never sees a traceback:

* ``MemoryError``, and any library's failed allocation (GDAL's out of memory, an import that cannot map its
  shared library under ``ulimit -v``) → :class:`~geocd.errors.ResourceError` naming the process's limit and
  the free memory (coarser posting, smaller AOI);
* ``OSError`` ENOSPC / EDQUOT / EFBIG → :class:`~geocd.errors.DiskFullError` (free space, other folder);
  EROFS / EACCES → :class:`~geocd.errors.OutputError`; ``FileExistsError`` → ``OutputError``;
  ``FileNotFoundError`` → :class:`~geocd.errors.InputFileNotFoundError`;
* ``UnicodeDecodeError`` → :class:`~geocd.errors.UnsupportedFormatError` (a binary file where text was expected);
* rasterio / GDAL and pyogrio / OGR errors → ``UnsupportedFormatError`` (or ``DiskFullError`` when
  GDAL says a write failed and the disk is full);
* anything else → :class:`~geocd.errors.InternalError` ("a bug in geocd: rerun with --debug and report it").

Signals: inside :func:`signals_as_interrupts`, SIGTERM and SIGHUP raise :class:`Terminated`
(a ``KeyboardInterrupt``) like Ctrl-C raises ``KeyboardInterrupt``, so the same ``finally`` /
``except BaseException`` clean-up runs: atomic writers remove their ``.part`` files and the
output session records the run as interrupted. A second signal while cleaning up stops the
process at once (its litter is removed by the next run into the folder, see
:mod:`geocd.io.outputs`).
"""

from __future__ import annotations

import contextlib
import errno
import os
import re
import shutil
import signal
import threading
from pathlib import Path
from typing import Iterator

from .errors import (
    DiskFullError,
    GeoCDError,
    InputFileNotFoundError,
    InternalError,
    OutputError,
    ResourceError,
    UnsupportedFormatError,
)

#: errno values meaning "the bytes do not fit where they are written"
DISK_ERRNOS = frozenset(e for e in (getattr(errno, n, None) for n in ("ENOSPC", "EDQUOT", "EFBIG")) if e is not None)
#: phrases GDAL/OGR/SQLite use for failed writes (their exceptions carry no errno)
_WRITE_FAILURE_PHRASES = (
    "no space left",
    "write error",
    "file too large",
    "disk i/o error",
    "database or disk is full",
    "disk full",
    "short write",
    "failed to write",
    "could not write",
    "cannot write",
    "writeblock",
    "write failed",
)


class Terminated(KeyboardInterrupt):
    """Raised in the main thread by SIGTERM / SIGHUP inside :func:`signals_as_interrupts`."""

    def __init__(self, signum: int) -> None:
        self.signum = int(signum)
        super().__init__(signal_name(signum))


def signal_name(signum: int) -> str:
    try:
        return signal.Signals(signum).name
    except ValueError:  # pragma: no cover
        return f"signal {signum}"


def exit_code_for_interrupt(exc: BaseException) -> int:
    """128 + signal number (130 for Ctrl-C, 143 for SIGTERM), as shells report it."""
    return 128 + (exc.signum if isinstance(exc, Terminated) else int(signal.SIGINT))


@contextlib.contextmanager
def signals_as_interrupts() -> Iterator[None]:
    """SIGTERM/SIGHUP (and SIGINT) raise in the main thread; a second signal exits at once.

    Outside the main thread (e.g. a QGIS worker running geocd in-process) nothing changes.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    fired: list[int] = []

    def handler(signum, frame):  # noqa: ARG001
        if fired:  # clean-up after the first signal is under way: stop now
            os.write(
                2,
                f"geocd: {signal_name(signum)} again: stopping now; the next run into the output folder "
                f"removes what is left\n".encode(),
            )
            os._exit(128 + signum)
        fired.append(signum)
        if signum == signal.SIGINT:
            raise KeyboardInterrupt
        raise Terminated(signum)

    wanted = [signal.SIGINT, signal.SIGTERM] + ([signal.SIGHUP] if hasattr(signal, "SIGHUP") else [])
    old = {}
    for s in wanted:
        try:
            prev = signal.getsignal(s)
            if s == signal.SIGHUP and prev == signal.SIG_IGN:
                continue  # started with nohup: keep ignoring hang-ups
            old[s] = signal.signal(s, handler)
        except (OSError, ValueError):  # pragma: no cover - exotic platforms
            pass
    try:
        yield
    finally:
        for s, h in old.items():
            with contextlib.suppress(OSError, ValueError, TypeError):
                signal.signal(s, h)


# ---------------------------------------------------------------------------------------------------------------
# exceptions → GeoCDError
# ---------------------------------------------------------------------------------------------------------------
def _chain(exc: BaseException) -> Iterator[BaseException]:
    seen = set()
    e: BaseException | None = exc
    while e is not None and id(e) not in seen:
        seen.add(id(e))
        yield e
        e = e.__cause__ or e.__context__


def _fmt_mb(n: float) -> str:
    return f"{n / 1e6:,.0f} MB" if n >= 1e6 else f"{n / 1e3:,.1f} kB"


def free_bytes(path: os.PathLike | str) -> int | None:
    """Free bytes on the file system holding ``path`` (its nearest existing ancestor), or None."""
    p = Path(path)
    for q in (p, *p.parents):
        try:
            if q.exists():
                return shutil.disk_usage(q).free
        except OSError:
            return None
    return None


def _file_size_limited() -> bool:
    """Whether a file-size limit (``ulimit -f``) is set for this process."""
    try:
        import resource

        soft, _ = resource.getrlimit(resource.RLIMIT_FSIZE)
        return soft != resource.RLIM_INFINITY
    except (ImportError, ValueError, OSError):  # pragma: no cover - not on POSIX
        return False


def disk_full_error(exc: BaseException, target: os.PathLike | str | None = None) -> DiskFullError | None:
    """A :class:`DiskFullError` when ``exc`` (or its cause) says the disk or a size limit is full, else None."""
    code = next((e.errno for e in _chain(exc) if isinstance(e, OSError) and e.errno in DISK_ERRNOS), None)
    text = " ".join(str(e) for e in _chain(exc)).lower()
    free = free_bytes(target) if target is not None else None
    where = f" writing {target}" if target is not None else ""
    phrase = any(s in text for s in _WRITE_FAILURE_PHRASES)
    limited = phrase and code is None and _file_size_limited() and (free is None or free >= 64 * 2**20)
    if code == getattr(errno, "EFBIG", -1) or (code is None and "file too large" in text) or limited:
        return DiskFullError(
            f"file size limit reached{where} (a shell `ulimit -f`, a quota, or a FAT32 disk's 4 GB limit); raise "
            "the limit or write to another folder (--out)"
        )
    gdal = re.search(r"free disk space available is (\d+) bytes, whereas (\d+) are at least necessary", text)
    if gdal:  # GDAL's own check before writing a GeoTIFF: the file would not fit
        return DiskFullError(
            f"not enough free disk space{where}: about {_fmt_mb(int(gdal[2]))} needed, "
            f"{_fmt_mb(int(gdal[1]))} free; free some space or choose an output folder on another "
            "disk (--out)"
        )
    if code is not None or (phrase and (free is None or free < 64 * 2**20)) or "no space left" in text:
        room = f" ({_fmt_mb(free)} free there)" if free is not None else ""
        return DiskFullError(
            f"no space left on device{where}{room}; free some space or choose an output folder on another disk (--out)"
        )
    return None


def translate(exc: BaseException, *, target: os.PathLike | str | None = None) -> GeoCDError:
    """The :class:`GeoCDError` standing for ``exc`` (``exc`` itself when it is one).

    The returned error has ``exc`` as its ``__cause__`` so ``--debug`` shows the original.
    """
    if isinstance(exc, GeoCDError):
        return exc
    err = _translate(exc, target)
    err.__cause__ = exc
    return err


#: what libraries say when an allocation fails: GDAL's CPLE_OutOfMemory, the loader's failed mmap of a shared
#: library (an import under ``ulimit -v``), C++'s bad_alloc, numpy's "Unable to allocate"
_MEMORY_PHRASES = (
    "out of memory",
    "cannot allocate memory",
    "failed to map segment",
    "std::bad_alloc",
    "unable to allocate",
    "outofmemory",
    "memory allocation failed",
    "not enough memory",
)


def out_of_memory(exc: BaseException) -> bool:
    """Whether ``exc`` (or its cause) is an allocation that failed, whatever library raised it."""
    for e in _chain(exc):
        if isinstance(e, MemoryError) or (isinstance(e, OSError) and e.errno == errno.ENOMEM):
            return True
        if "OutOfMemory" in type(e).__name__ or any(s in str(e).lower() for s in _MEMORY_PHRASES):
            return True
    return False


def memory_limits() -> str:
    """The memory this process may use, for a message: its ``ulimit -v`` (when set) and what the machine has free."""
    parts = []
    try:
        import resource

        soft, _ = resource.getrlimit(resource.RLIMIT_AS)
        if soft != resource.RLIM_INFINITY:
            parts.append(f"a limit of {soft / 2**30:.1f} GiB on this process (ulimit -v)")
    except (ImportError, ValueError, OSError):  # pragma: no cover - not on POSIX
        pass
    try:
        avail = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
        parts.append(f"{avail / 2**30:.1f} GiB free on the machine")
    except (ValueError, OSError, AttributeError):  # pragma: no cover
        pass
    return "; ".join(parts)


def _translate(exc: BaseException, target) -> GeoCDError:
    msg = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    if out_of_memory(exc):
        limits = memory_limits()
        said = f" ({msg[:200]})" if msg not in ("MemoryError", "") else ""
        return ResourceError(
            f"out of memory{said}{'; ' + limits if limits else ''}; the job is too large for the memory it may use: "
            "use a coarser posting (--posting), a smaller AOI, fewer images, a tiled run (--tiled) or a machine "
            "with more memory"
        )
    disk = disk_full_error(exc, target)
    if disk is not None and not isinstance(exc, (FileNotFoundError, UnicodeError)):
        return disk
    if isinstance(exc, UnicodeDecodeError):
        return UnsupportedFormatError(
            f"a file read as text is binary or not UTF-8 ({exc.reason} at byte {exc.start}); check that each "
            "text input (manifest, model/config JSON, camera, list file) is the right file"
        )
    if isinstance(exc, UnicodeError):
        return UnsupportedFormatError(f"text encoding problem ({msg}); save text inputs as UTF-8")
    kind = _library_error_kind(exc)
    if isinstance(exc, OSError) and (exc.errno is not None or kind is None):
        name = exc.filename if getattr(exc, "filename", None) else target
        at = f" {name}" if name else ""
        if isinstance(exc, FileExistsError):
            return OutputError(f"{name or 'an output'} already exists; remove it, or choose another output path")
        if isinstance(exc, FileNotFoundError):
            return InputFileNotFoundError(f"{name or msg} does not exist; check the path")
        if isinstance(exc, IsADirectoryError):
            return OutputError(f"{name} is a folder where a file was expected; give a file path")
        if isinstance(exc, NotADirectoryError):
            return OutputError(f"{name} is a file where a folder was expected; give a folder path")
        if exc.errno == getattr(errno, "EROFS", -1):
            return OutputError(f"read-only file system:{at}; choose an output folder on a writable disk (--out)")
        if exc.errno in (errno.EACCES, errno.EPERM):
            return OutputError(
                f"permission denied:{at}; choose a folder you can write to (--out) or fix the file's permissions"
            )
        if exc.errno == getattr(errno, "ENAMETOOLONG", -1):
            return OutputError(f"file name too long:{at}; use a shorter --out or --prefix")
        if exc.errno == getattr(errno, "EIO", -1):
            return OutputError(
                f"input/output error on{at or ' a file'} (a failing disk or network share); check the disk and retry"
            )
        return OutputError(f"system error{at}: {exc.strerror or msg}; check the path and the disk")
    if kind is not None:
        return UnsupportedFormatError(
            f"{kind} could not read or write a file ({msg}); the file is truncated, corrupt or in an unsupported "
            "format: check it (e.g. `geocd info FILE`) or re-export it"
        )
    if isinstance(exc, RecursionError):
        return InternalError(
            "internal error (recursion too deep); this is a bug in geocd: rerun with --debug and report the traceback"
        )
    return InternalError(
        f"internal error ({type(exc).__name__}: {msg}); this is a bug in geocd: rerun with --debug "
        "and report the traceback"
    )


def _library_error_kind(exc: BaseException) -> str | None:
    mod = type(exc).__module__ or ""
    if mod.startswith("rasterio") or type(exc).__name__.startswith("CPLE_"):
        return "GDAL (rasterio)"
    if mod.startswith("pyogrio") or mod.startswith("fiona"):
        return "OGR (pyogrio)"
    if mod.startswith("sqlite3"):
        return "SQLite"
    if mod.startswith("yaml"):
        return "the YAML reader"
    if mod.startswith("json"):
        return "the JSON reader"
    if mod.startswith("pyproj"):
        return "PROJ (pyproj)"
    return None


def one_line(exc: BaseException) -> str:
    """The message of ``exc`` on one line (for ``geocd: error: ...``)."""
    s = " ".join(str(exc).split())
    return s or type(exc).__name__


__all__ = [
    "Terminated",
    "signals_as_interrupts",
    "translate",
    "disk_full_error",
    "free_bytes",
    "one_line",
    "exit_code_for_interrupt",
    "DISK_ERRNOS",
    "signal_name",
]
