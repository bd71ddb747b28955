"""Output folders that never lose or mix a user's data.

Every command that writes files opens an **output session** once, as soon as it knows its
inputs and its output folder, before any heavy work::

    from geocd.io.outputs import open_outputs

    open_outputs(out_dir, inputs=[dem_a, dem_b, footprints], products=[f"{prefix}_*"], prefix=prefix)

In a CLI command that is the whole job: :class:`geocd.cli.LazyGroup` closes the session when the
command ends (complete, failed, or interrupted). Library code uses the same call as a context
manager::

    with open_outputs(out_dir, inputs=[...], products=["sc_*", "stereo/*"]) as session:
        ...  # write with the shared writers (write_cog, write_gpkg, write_text_atomic, atomic_path)

What a session does
-------------------
* **Paths.** ``out`` must be a folder (an existing *file* there is refused), creatable and writable
  (read-only file system / permission denied → :class:`~geocd.errors.OutputError` naming the fix).
  File outputs outside the folder (``--plot x.png``, a model file, a model folder) are declared with
  ``files=`` (a declared file covers its side files of the same stem: ``x.json`` and ``x.qml`` beside ``x.tif``). ``prefix`` must be a plain file-name prefix (no ``/``, ``..``): products cannot escape
  the folder. While a session is open, every write through :mod:`geocd.io.atomic` must land inside
  the folder or on a declared file, and never on an input.
* **Inputs.** ``inputs`` (files or folders; ``None`` entries ignored) are protected: an input that is
  one of this command's products (it matches a ``products`` pattern, e.g. ``--footprints
  OUT/sc_changes.gpkg`` with ``--out OUT``) is refused *up front*; any later write onto an input
  (another spelling, a hard link) is refused by the writers. Inputs are never moved or deleted.
* **Lock.** The folder is locked (``OUT/.geocd.lock``, an OS file lock released by the kernel even
  when the process is killed): a second geocd run into the same folder stops at once with
  :class:`~geocd.errors.OutputLockedError` naming the run that holds it. File outputs are locked
  the same way beside them (``.NAME.geocd.lock``).
* **Litter.** Partial files of killed runs (``.NAME.XXXXXXXX.part.EXT``, ``.NAME.XXXXXXXX.part/``,
  their GDAL/SQLite side files) are removed when a session opens, and a model folder half-swapped by
  a kill (``.NAME.old`` without ``NAME``) is put back. Nothing ever reads a ``.part`` file.
* **Product manifest.** ``OUT/geocd_products.json`` lists, per run, the command line, geocd version,
  start/end times, status (``running``, ``complete``, ``failed``, ``interrupted``, ``killed``) and every
  product written (path relative to the folder, bytes, sha256). It is updated after each product, so a
  run killed with SIGKILL is recognised by the next one (status ``running`` with no lock held → ``killed``).
* **Stale products.** When a run completes, older runs it supersedes (same command and product
  patterns, or one of whose products it rewrote) have their remaining products removed — only files
  whose sha256 still matches the manifest (a file changed since is kept, with a warning). So a folder
  never holds a mix of two runs' products of the same kind; products of other commands (e.g.
  ``geocd stereo`` pair-DEMs next to ``geocd change`` layers) are kept. A failed or interrupted run
  removes nothing older.

Resources: :func:`check_resources` compares an up-front estimate of memory and disk with what the
machine has and raises :class:`~geocd.errors.ResourceError` / :class:`~geocd.errors.DiskFullError`
before the heavy step (:func:`grid_job_bytes` estimates a job on an AOI grid).

For resuming work (tiling): :func:`verify_products` re-hashes the products listed in a folder's
manifest; only files that still match are safe to reuse. Whether a folder holds whole product sets (no run
that stopped half-way, nothing changed since): :func:`check_product_set` (``geocd info FOLDER``).

* **A run that stops puts back what it replaced.** Before a run replaces a file of its folder that an earlier
  run wrote, the old file is kept (a hard link under ``OUT/.geocd-prev/<run id>/``). When the run completes the
  kept files are dropped; when it fails or is interrupted they are put back, so the earlier run's set is whole
  again (files under new names stay, listed as the stopped run's in the manifest, and a resumed tiled run
  reuses them); after a SIGKILL the next session into the folder puts them back before it writes anything.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import fnmatch
import hashlib
import json
import os
import re
import shutil
import socket
import sys
import threading
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence

from ..errors import ConfigError, DiskFullError, GeoCDError, OutputError, OutputLockedError, ResourceError
from . import atomic

MANIFEST_NAME = "geocd_products.json"
LOCK_NAME = ".geocd.lock"
#: the files a running session replaced, kept (hard links) until it completes: ``<out>/.geocd-prev/<run id>/<rel>``
PREV_DIR = ".geocd-prev"
MANIFEST_VERSION = 1
#: temporaries of geocd.io.atomic: ".<name>.<8 chars of tempfile's alphabet>.part[.<ext> or side-file tail]"
PART_RE = re.compile(r"^\..+\.[a-z0-9_]{8}\.part(?:[.\-].*)?$")
OLD_RE = re.compile(r"^\.(.+)\.old$")


class OutputFolderWarning(UserWarning):
    """Something about an output folder the user should know (litter removed, stale products replaced)."""


# =====================================================================================================
# small helpers
# =====================================================================================================
def sha256_file(path: os.PathLike | str, chunk: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(chunk), b""):
            h.update(block)
    return h.hexdigest()


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def _resolve(p: os.PathLike | str) -> Path:
    return Path(os.path.abspath(Path(p).expanduser())).resolve()


def _within(path: Path, root: Path) -> bool:
    return path == root or root in path.parents


def check_prefix(prefix: str | None, option: str = "--prefix") -> str | None:
    """A product-name prefix must be a plain name: no folder separators, no ``..``, not hidden.

    Raises
    ------
    ConfigError
    """
    if prefix is None:
        return None
    p = str(prefix)
    bad = (
        not p.strip()
        or "/" in p
        or "\\" in p
        or p.startswith(".")
        or ".." in p
        or "\x00" in p
        or any(ord(c) < 32 for c in p)
        or (len(p) > 1 and p[1] == ":")
    )
    if bad:
        raise ConfigError(
            f"{option} {p!r} is not a plain file-name prefix; products are written inside --out, so "
            "use letters, digits, '_' or '-' (e.g. 'site1'), and choose the folder with --out"
        )
    return p


def _describe_holder(lock_path: Path) -> str:
    try:
        d = json.loads(lock_path.read_text(encoding="utf-8"))
        cmd = " ".join(d.get("argv", [])[:6]) or d.get("command", "geocd")
        return f"`{cmd}` (pid {d.get('pid')} on {d.get('host')}, started {d.get('started')})"
    except (OSError, ValueError, TypeError, AttributeError):
        return "another geocd run"


# =====================================================================================================
# locks
# =====================================================================================================
class FolderLock:
    """An exclusive, non-blocking OS lock on ``lock_path`` (released by the kernel if the process dies)."""

    def __init__(self, lock_path: Path, what: str) -> None:
        self.path = lock_path
        self.what = what
        self.fd: int | None = None

    def acquire(self, info: dict) -> None:
        for _ in range(5):
            try:
                fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
            except OSError as exc:
                from ..faults import translate

                raise translate(exc, target=self.path) from exc
            try:
                _lock_fd(fd)
            except BlockingIOError:
                os.close(fd)
                raise OutputLockedError(
                    f"{self.what} is in use by {_describe_holder(self.path)}; wait for that run to finish, or "
                    "choose another output folder (--out)"
                ) from None
            except OSError:
                # file systems without locks (some network shares): go on unlocked rather than refuse all work
                os.close(fd)
                warnings.warn(
                    f"cannot lock {self.path} on this file system; do not run two geocd commands into "
                    f"{self.what} at once",
                    OutputFolderWarning,
                    stacklevel=3,
                )
                return
            # the file we locked must still be the one at the path (a releasing run unlinks it)
            try:
                same = os.path.samestat(os.fstat(fd), os.stat(self.path))
            except OSError:
                same = False
            if not same:
                os.close(fd)
                continue
            self.fd = fd
            with contextlib.suppress(OSError):
                os.ftruncate(fd, 0)
                os.write(fd, json.dumps(info).encode())
            return
        raise OutputLockedError(f"{self.what}: cannot take the lock {self.path}; retry")  # pragma: no cover

    def release(self) -> None:
        if self.fd is None:
            return
        with contextlib.suppress(OSError):
            os.unlink(self.path)
        with contextlib.suppress(OSError):
            _unlock_fd(self.fd)
        with contextlib.suppress(OSError):
            os.close(self.fd)
        self.fd = None


def lock_is_held(lock_path: Path) -> bool:
    """Whether a live process holds the lock at ``lock_path``."""
    if not lock_path.exists():
        return False
    try:
        fd = os.open(lock_path, os.O_RDWR)
    except OSError:
        return False
    try:
        _lock_fd(fd)
    except BlockingIOError:
        return True
    except OSError:
        return False
    else:
        _unlock_fd(fd)
        return False
    finally:
        os.close(fd)


if sys.platform.startswith("win"):  # pragma: no cover - not run in CI
    import msvcrt

    def _lock_fd(fd: int) -> None:
        try:
            msvcrt.locking(fd, msvcrt.LK_NBLCK, 1)
        except OSError as exc:
            raise BlockingIOError(str(exc)) from exc

    def _unlock_fd(fd: int) -> None:
        os.lseek(fd, 0, 0)
        msvcrt.locking(fd, msvcrt.LK_UNLCK, 1)
else:
    import fcntl

    def _lock_fd(fd: int) -> None:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)

    def _unlock_fd(fd: int) -> None:
        fcntl.flock(fd, fcntl.LOCK_UN)


# =====================================================================================================
# litter of killed runs
# =====================================================================================================
def clean_litter(
    folder: os.PathLike | str, *, recursive: bool = True, names: Iterable[str] | None = None
) -> list[Path]:
    """Remove partial files/folders of interrupted geocd writes under ``folder``; return what was removed.

    A model folder half-swapped by a kill (``.NAME.old`` without ``NAME``) is renamed back to ``NAME``.
    Sub-folders holding their own ``.geocd.lock`` belong to other sessions and are skipped. With
    ``names``, only temporaries of those product names are considered (for file outputs).
    """
    root = Path(folder)
    removed: list[Path] = []
    if not root.is_dir():
        return removed
    wanted = None if names is None else {f".{n}." for n in names}
    stack = [root]
    while stack:
        d = stack.pop()
        try:
            entries = list(os.scandir(d))
        except OSError:
            continue
        for e in entries:
            name = e.name
            p = Path(e.path)
            is_dir = e.is_dir(follow_symlinks=False)
            if PART_RE.match(name) and (wanted is None or any(name.startswith(w) for w in wanted)):
                with contextlib.suppress(OSError):
                    if is_dir:
                        shutil.rmtree(p)
                    else:
                        p.unlink()
                    removed.append(p)
                continue
            m = OLD_RE.match(name)
            if m and is_dir and (wanted is None or f".{m.group(1)}." in wanted):
                live = p.with_name(m.group(1))
                with contextlib.suppress(OSError):
                    if live.exists():
                        shutil.rmtree(p)
                    else:
                        os.replace(p, live)
                    removed.append(p)
                continue
            if is_dir and recursive and not name.startswith(".") and not (p / LOCK_NAME).exists():
                stack.append(p)
    return removed


# =====================================================================================================
# the product manifest
# =====================================================================================================
def read_products_manifest(folder: os.PathLike | str) -> dict:
    """``folder``'s product manifest (``{"geocd_products": 1, "runs": [...]}``); empty when absent or unreadable."""
    p = Path(folder) / MANIFEST_NAME
    try:
        d = json.loads(p.read_text(encoding="utf-8"))
        if isinstance(d, dict) and isinstance(d.get("runs"), list):
            return d
    except (OSError, ValueError, UnicodeError):
        pass
    return {"geocd_products": MANIFEST_VERSION, "runs": []}


def _write_manifest(folder: Path, doc: dict) -> None:
    """Atomic rewrite of the manifest (not through geocd.io.atomic: it is not a product)."""
    target = folder / MANIFEST_NAME
    tmp = folder / f".{MANIFEST_NAME}.{os.getpid()}.tmp"
    try:
        tmp.write_text(json.dumps(doc, indent=1, default=str), encoding="utf-8")
        os.replace(tmp, target)
    except OSError as exc:
        with contextlib.suppress(OSError):
            tmp.unlink()
        from ..faults import translate

        raise translate(exc, target=target) from exc


def verify_products(folder: os.PathLike | str, run: str | None = None) -> dict[str, bool]:
    """``{relative path: still as written}`` for the products of ``folder``'s runs (or of run id ``run``).

    A product is trusted only when it exists with the recorded size and sha256; anything else (changed,
    missing, or never recorded, like ``.part`` files) must be recomputed.
    """
    root = Path(folder)
    out: dict[str, bool] = {}
    for r in read_products_manifest(root)["runs"]:
        if run is not None and r.get("id") != run:
            continue
        for rel, info in (r.get("files") or {}).items():
            p = root / rel
            try:
                ok = p.is_file() and p.stat().st_size == info.get("bytes") and sha256_file(p) == info.get("sha256")
            except OSError:
                ok = False
            out[rel] = ok
    return out


def check_product_set(folder: os.PathLike | str) -> dict[str, Any]:
    """Whether ``folder`` holds whole product sets, each as one run wrote it: ``{"valid": bool, "runs": [...],
    "problems": [...]}``.

    Valid only when every run the manifest lists completed, every product it lists is there as written, and no
    run is still writing or left partial files or replaced files behind. A folder that mixes the products of a
    complete run with those of a run that failed, was interrupted or killed is *not* valid, although each file
    on its own may match its hash (:func:`verify_products` answers per file, for resuming).
    """
    root = Path(folder)
    doc = read_products_manifest(root)
    problems: list[str] = []
    runs = []
    if not (root / MANIFEST_NAME).is_file():
        problems.append(
            f"{root} has no product manifest ({MANIFEST_NAME}): it was not written by geocd, or by a "
            "run that wrote nothing"
        )
    held = lock_is_held(root / LOCK_NAME)
    for r in doc["runs"]:
        files = r.get("files") or {}
        ok = verify_products(root, r.get("id"))
        bad = sorted(k for k, v in ok.items() if not v)
        status = r.get("status")
        if status == "running" and not held:
            status = "killed"
        cmd = " ".join(r.get("argv", [])[:4]) or r.get("command", "geocd")
        runs.append(
            {
                "id": r.get("id"),
                "command": r.get("command"),
                "status": status,
                "products": len(files),
                "changed_or_missing": bad,
            }
        )
        if status != "complete":
            problems.append(
                f"run `{cmd}` ({r.get('started')}) is {status} after writing {len(files)} product(s): "
                "they are not a whole set; run the command again to complete the folder"
            )
        if bad:
            problems.append(
                f"{len(bad)} product(s) of run `{cmd}` changed or went missing since it wrote them: "
                + ", ".join(bad[:5])
                + (" ..." if len(bad) > 5 else "")
            )
    litter = [p for p in root.rglob("*") if PART_RE.match(p.name)] if root.is_dir() else []
    if litter:
        problems.append(f"{len(litter)} partial file(s) of an interrupted run are in the folder")
    if (root / PREV_DIR).is_dir() and not held:
        problems.append(
            f"files a stopped run replaced are kept in {PREV_DIR}: the next geocd run into this folder puts them back"
        )
    return {"valid": not problems, "runs": runs, "problems": problems}


# =====================================================================================================
# sessions
# =====================================================================================================
_ACTIVE: list["OutputSession"] = []
_RECORD_LOCK = threading.RLock()


def _on_before_write(target: Path) -> None:
    if not _ACTIVE:
        return
    t = _resolve(target)
    owner = next((s for s in reversed(_ACTIVE) if s.covers(t)), None)
    if owner is None:
        roots = ", ".join(str(r) for s in _ACTIVE for r in s.roots())
        raise OutputError(
            f"refusing to write {target}: it is outside this run's output ({roots}); check --out, "
            "--prefix and output file names"
        )
    owner.keep_previous(t)


def _on_after_write(target: Path) -> None:
    if not _ACTIVE:
        return
    t = _resolve(target)
    for s in reversed(_ACTIVE):
        if s.covers(t):
            s.record(t)
            return


atomic.BEFORE_WRITE.append(_on_before_write)
atomic.AFTER_WRITE.append(_on_after_write)


def active_sessions() -> list["OutputSession"]:
    return list(_ACTIVE)


@dataclass
class OutputSession:
    """One command's output folder (and declared output files): see the module docstring."""

    folder: Path | None
    files: tuple[Path, ...] = ()
    inputs: tuple[Path, ...] = ()
    products: tuple[str, ...] = ("*",)
    command: str = "geocd"
    argv: tuple[str, ...] = ()
    parent: "OutputSession | None" = None
    id: str = ""
    written: dict[str, dict] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    created_folder: bool = False
    status: str = "open"
    _locks: list[FolderLock] = field(default_factory=list)
    _protected: list[Path] = field(default_factory=list)
    _started: str = ""
    _kept: set[str] = field(default_factory=set)

    # -- geometry ---------------------------------------------------------------------------------------
    def roots(self) -> list[Path]:
        return ([self.folder] if self.folder is not None else []) + list(self.files)

    def covers(self, path: Path) -> bool:
        """Whether this session may write ``path``: inside its folder, a declared output (a folder output's
        contents), or a side file of a declared file (same folder, same stem: ``model.json`` beside
        ``model.joblib``, ``x.qml`` beside ``x.tif``)."""
        if self.folder is not None and _within(path, self.folder):
            return True
        return any(
            _within(path, f) or (path.parent == f.parent and path.name.startswith((f"{f.stem}.", f"{f.stem}_")))
            for f in self.files
        )

    def _rel(self, path: Path) -> str:
        if self.folder is not None and _within(path, self.folder):
            return path.relative_to(self.folder).as_posix()
        return str(path)

    # -- recording ------------------------------------------------------------------------------------
    def record(self, path: os.PathLike | str) -> None:
        """Record a complete product (a file, or every file of a folder product) with its sha256."""
        if self.parent is not None:
            self.parent.record(path)
            return
        p = _resolve(path)
        targets = [p] if p.is_file() else sorted(q for q in p.rglob("*") if q.is_file()) if p.is_dir() else []
        found = {}
        for q in targets:
            try:
                found[self._rel(q)] = {"bytes": q.stat().st_size, "sha256": sha256_file(q)}
            except OSError:
                continue
        with _RECORD_LOCK:  # writers in threads (a threaded scheduler) record one at a time
            self.written.update(found)
            if self.folder is not None and self.status == "open":
                self._save("running")

    def keep_previous(self, path: Path) -> None:
        """Before this run replaces a file of its folder that it did not write itself, keep the old file (a hard
        link, else a copy, under ``.geocd-prev/<run id>/``): a run that fails puts it back (:meth:`close`), and
        so does the next session after a kill (:func:`open_outputs`)."""
        if self.parent is not None:
            self.parent.keep_previous(path)
            return
        if self.folder is None or not _within(path, self.folder) or path.is_symlink() or not path.is_file():
            return
        rel = self._rel(path)
        if rel == MANIFEST_NAME or rel.split("/", 1)[0] == PREV_DIR:
            return
        with _RECORD_LOCK:
            if rel in self._kept or rel in self.written:
                return
            dst = self.folder / PREV_DIR / self.id / rel
            try:
                dst.parent.mkdir(parents=True, exist_ok=True)
                try:
                    os.link(path, dst)
                except OSError:  # a file system without hard links
                    shutil.copy2(path, dst)
            except OSError as exc:
                from ..faults import translate

                raise translate(exc, target=dst) from exc
            self._kept.add(rel)

    # -- manifest -------------------------------------------------------------------------------------
    def _entry(self, status: str) -> dict:
        from .. import __version__

        return {
            "id": self.id,
            "command": self.command,
            "argv": list(self.argv),
            "geocd": __version__,
            "pid": os.getpid(),
            "host": socket.gethostname(),
            "started": self._started,
            "finished": None if status == "running" else _now(),
            "status": status,
            "products": list(self.products),
            "inputs": [str(p) for p in self.inputs],
            "files": {k: v for k, v in self.written.items() if not k.startswith("/")},
        }

    def _save(self, status: str, doc: dict | None = None) -> None:
        if self.folder is None:
            return
        doc = doc if doc is not None else read_products_manifest(self.folder)
        runs = [r for r in doc["runs"] if r.get("id") != self.id]
        doc = {"geocd_products": MANIFEST_VERSION, "runs": runs + [self._entry(status)]}
        _write_manifest(self.folder, doc)

    # -- closing -----------------------------------------------------------------------------------------
    def close(self, ok: bool = True, exc: BaseException | None = None) -> None:
        """End the session: commit (``ok``) or record the failure; release the locks; unprotect the inputs."""
        if self.status != "open":
            return
        try:
            if self.parent is None and self.folder is not None:
                if ok:
                    self._commit()
                else:
                    self._abort(exc)
        finally:
            self.status = "complete" if ok else "failed"
            atomic.unprotect_inputs(*self._protected)
            for lk in self._locks:
                lk.release()
            if self in _ACTIVE:
                _ACTIVE.remove(self)

    def _commit(self) -> None:
        assert self.folder is not None
        doc = read_products_manifest(self.folder)
        mine = set(self.written)
        keep, retired, kept_changed = [], [], []
        for r in doc["runs"]:
            if r.get("id") == self.id:
                continue
            files = r.get("files") or {}
            same_kind = r.get("command") == self.command and list(r.get("products") or []) == list(self.products)
            if not (same_kind or (mine & set(files))):
                keep.append(r)
                continue
            for rel, info in files.items():
                if rel in mine:
                    continue
                p = self.folder / rel
                if not p.is_file():
                    continue
                if atomic.protected_input(p):
                    kept_changed.append(rel)
                    continue
                try:
                    same = p.stat().st_size == info.get("bytes") and sha256_file(p) == info.get("sha256")
                except OSError:
                    same = False
                if same:
                    with contextlib.suppress(OSError):
                        p.unlink()
                        retired.append(rel)
                        _remove_empty_parents(p.parent, self.folder)
                else:
                    kept_changed.append(rel)
        if retired:
            self._note(
                f"removed {len(retired)} product(s) of an older run that this run replaces: "
                + ", ".join(retired[:6])
                + (" ..." if len(retired) > 6 else "")
            )
        if kept_changed:
            self._note(
                f"kept {len(kept_changed)} file(s) of an older run that changed since geocd wrote them (or "
                "are inputs of this run); they are not part of this run's products: "
                + ", ".join(kept_changed[:6])
                + (" ..." if len(kept_changed) > 6 else "")
            )
        doc["runs"] = keep
        self._save("complete", doc)
        _drop_previous(self.folder, self.id)

    def _abort(self, exc: BaseException | None) -> None:
        assert self.folder is not None
        status = "interrupted" if isinstance(exc, KeyboardInterrupt) else "failed"
        restored = _restore_previous(self.folder, self.id)
        for rel in restored:
            self.written.pop(rel, None)
        if restored:
            self._note(
                f"put back {len(restored)} file(s) of an earlier run that this run had replaced before it "
                "stopped: " + ", ".join(restored[:6]) + (" ..." if len(restored) > 6 else "")
            )
        doc = read_products_manifest(self.folder)
        if not self.written:
            # nothing of this run is in the folder: leave it as it was
            runs = [r for r in doc["runs"] if r.get("id") != self.id]
            if runs:
                _write_manifest(self.folder, {"geocd_products": MANIFEST_VERSION, "runs": runs})
            else:
                with contextlib.suppress(OSError):
                    (self.folder / MANIFEST_NAME).unlink()
            if self.created_folder:
                for lk in self._locks:
                    lk.release()
                with contextlib.suppress(OSError):
                    self.folder.rmdir()
            return
        with contextlib.suppress(GeoCDError, OSError):
            self._save(status, doc)

    def _note(self, msg: str) -> None:
        self.notes.append(msg)
        warnings.warn(msg, OutputFolderWarning, stacklevel=3)

    # -- context manager ------------------------------------------------------------------------------
    def __enter__(self) -> "OutputSession":
        return self

    def __exit__(self, et, ev, tb) -> None:
        self.close(ok=et is None, exc=ev)


def _drop_previous(folder: Path, run_id: str) -> None:
    """Forget the files run ``run_id`` replaced (it completed)."""
    with contextlib.suppress(OSError):
        shutil.rmtree(folder / PREV_DIR / run_id)
    with contextlib.suppress(OSError):
        (folder / PREV_DIR).rmdir()


def _restore_previous(folder: Path, run_id: str) -> list[str]:
    """Put back every file run ``run_id`` replaced (it did not complete); their relative paths."""
    root = folder / PREV_DIR / run_id
    if not root.is_dir():
        return []
    restored = []
    for q in sorted(p for p in root.rglob("*") if p.is_file()):
        rel = q.relative_to(root).as_posix()
        with contextlib.suppress(OSError):
            (folder / rel).parent.mkdir(parents=True, exist_ok=True)
            os.replace(q, folder / rel)
            restored.append(rel)
    _drop_previous(folder, run_id)
    return restored


def _remove_empty_parents(d: Path, stop: Path) -> None:
    while d != stop and _within(d, stop):
        try:
            d.rmdir()
        except OSError:
            return
        d = d.parent


def _command_and_argv(command: str | None) -> tuple[str, tuple[str, ...]]:
    """The command ("geocd demdiff") and its command line, from the running click command when there is one."""
    argv = tuple(sys.argv)
    name = command
    try:
        import click

        ctx = click.get_current_context(silent=True)
        if ctx is not None:
            argv = tuple(ctx.meta.get("geocd.argv") or argv)
            if name is None:
                name = " ".join(["geocd", *ctx.command_path.split()[1:]])
    except ImportError:  # pragma: no cover
        pass
    return name or (Path(argv[0]).name if argv else "python"), argv


def open_outputs(
    out: os.PathLike | str | None = None,
    *,
    inputs: Iterable[os.PathLike | str | None] = (),
    products: Sequence[str] = ("*",),
    files: Iterable[os.PathLike | str | None] = (),
    prefix: str | None = None,
    command: str | None = None,
) -> OutputSession:
    """Open the output session of a command (see the module docstring); returns it (a context manager).

    Parameters
    ----------
    out : the output folder (created), or None when the command writes only ``files``.
    inputs : every file or folder the command reads (``None`` entries are ignored).
    products : glob patterns, relative to ``out``, of what this command writes there (``"sc_*"``,
        ``"stereo/*"``, ``f"{prefix}_*"``): an input matching one is refused up front, and an older
        run of the same command with the same patterns is replaced when this one completes.
    files : output files or folders outside ``out`` (``--plot``, a model file or folder).
    prefix : the command's ``--prefix``, checked by :func:`check_prefix`.
    command : name recorded in the manifest (default: the click command path, e.g. ``geocd run``).

    Raises
    ------
    OutputError, OutputLockedError, ConfigError
    """
    check_prefix(prefix)
    cmd, argv = _command_and_argv(command)
    folder = _resolve(out) if out is not None else None
    outs = tuple(_resolve(f) for f in files if f is not None)
    ins = tuple(p for p in (atomic._input_path(i) for i in inputs if i is not None) if p is not None)
    # a second session on the same folder in this process (a command calling a pipeline that opens its own)
    for s in _ACTIVE:
        if folder is not None and s.folder == folder and s.parent is None:
            child = OutputSession(
                folder=folder,
                files=outs,
                inputs=ins,
                products=tuple(products),
                command=cmd,
                argv=argv,
                parent=s,
                id=s.id,
            )
            _check_inputs_vs_outputs(child)
            child._protected = atomic.protect_inputs(*ins)
            _ACTIVE.append(child)
            return child
    sess = OutputSession(
        folder=folder,
        files=outs,
        inputs=ins,
        products=tuple(products),
        command=cmd,
        argv=argv,
        id=f"{_dt.datetime.now(_dt.timezone.utc).strftime('%Y%m%dT%H%M%S.%fZ')}-{os.getpid()}",
        _started=_now(),
    )
    _check_inputs_vs_outputs(sess)
    info = {
        "pid": os.getpid(),
        "host": socket.gethostname(),
        "started": sess._started,
        "command": cmd,
        "argv": list(argv),
    }
    try:
        if folder is not None:
            if folder.exists() and not folder.is_dir():
                raise OutputError(f"the output folder {out} is a file; give a folder path (--out), or remove the file")
            sess.created_folder = not folder.exists()
            _mkdir(folder)
            lk = FolderLock(folder / LOCK_NAME, f"the output folder {folder}")
            lk.acquire(info)
            sess._locks.append(lk)
            _check_parent_free(folder)
        for f in outs:
            _mkdir(f.parent)
            lk = FolderLock(f.parent / f".{f.name}.geocd.lock", f"the output {f}")
            lk.acquire(info)
            sess._locks.append(lk)
            if folder is None or not _within(f, folder):
                _check_parent_free(f)
    except BaseException:
        for lk in sess._locks:
            lk.release()
        if sess.created_folder and folder is not None:
            with contextlib.suppress(OSError):
                folder.rmdir()
        raise
    # litter of killed runs, and runs the kernel's lock says are dead
    litter: list[Path] = []
    if folder is not None:
        litter += clean_litter(folder)
    for f in outs:
        stem_names = {f.name, f.stem}
        litter += clean_litter(f.parent, recursive=False, names=stem_names)
    if litter:
        sess._note(
            f"removed {len(litter)} partial file(s) left by an interrupted geocd run: "
            + ", ".join(p.name for p in litter[:5])
            + (" ..." if len(litter) > 5 else "")
        )
    if folder is not None:
        doc = read_products_manifest(folder)
        changed = False
        # this session holds the lock: every journal of replaced files is a dead run's, put them back first
        prev = folder / PREV_DIR
        dead = sorted(p.name for p in prev.iterdir() if p.is_dir()) if prev.is_dir() else []
        for run_id in dead:
            restored = _restore_previous(folder, run_id)
            for r in doc["runs"]:
                if r.get("id") == run_id:
                    for rel in restored:
                        (r.get("files") or {}).pop(rel, None)
                    changed = True
            if restored:
                sess._note(
                    f"put back {len(restored)} file(s) of an earlier run that a killed run had replaced: "
                    + ", ".join(restored[:6])
                    + (" ..." if len(restored) > 6 else "")
                )
        for r in doc["runs"]:
            if r.get("status") == "running":
                r["status"] = "killed"
                changed = True
                sess._note(
                    f"the previous run into {folder} (`{' '.join(r.get('argv', [])[:6])}`, started "
                    f"{r.get('started')}) was killed after writing {len(r.get('files') or {})} product(s); "
                    "they are incomplete as a set and are replaced by this run's products"
                )
        if changed:
            _write_manifest(folder, doc)
    sess._protected = atomic.protect_inputs(*ins)
    _ACTIVE.append(sess)
    return sess


def _mkdir(folder: Path) -> None:
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except FileExistsError as exc:
        raise OutputError(
            f"cannot create the output folder {folder}: a file is in the way; choose another folder (--out)"
        ) from exc
    except OSError as exc:
        from ..faults import disk_full_error

        err = disk_full_error(exc, folder)
        if err is not None:
            raise err from exc
        raise OutputError(
            f"cannot create the output folder {folder} ({exc.strerror or exc}); choose a folder on a "
            "writable disk that you may write to (--out)"
        ) from exc
    if not os.access(folder, os.W_OK | os.X_OK):
        ro = False
        with contextlib.suppress(OSError, AttributeError):
            ro = bool(os.statvfs(folder).f_flag & os.ST_RDONLY)
        why = "is on a read-only file system" if ro else "is not writable"
        raise OutputError(f"the output folder {folder} {why}; choose a folder you can write to (--out)")


def _check_parent_free(path: Path) -> None:
    """Refuse to write into a folder another geocd run holds (e.g. ``--plot OUT/x.png`` while a run writes OUT)."""
    for d in path.parents:
        lk = d / LOCK_NAME
        if lk.exists() and lock_is_held(lk) and not any(s.folder == d for s in _ACTIVE):
            raise OutputLockedError(
                f"{d} is in use by {_describe_holder(lk)}; wait for that run to finish, or write elsewhere"
            )


def _check_inputs_vs_outputs(s: OutputSession) -> None:
    for i in s.inputs:
        for f in s.files:
            if i == f or _within(i, f):
                raise OutputError(f"the output {f} would overwrite the input {i}; choose another output path")
            if i.exists() and f.exists():
                with contextlib.suppress(OSError):
                    if os.path.samefile(i, f):
                        raise OutputError(
                            f"the output {f} is the input {i} (another name of the same file); choose "
                            "another output path"
                        )
        if s.folder is None:
            continue
        if i == s.folder:
            if i.is_file():
                raise OutputError(f"the output folder {i} is an input file; choose another --out")
            continue
        if _within(i, s.folder) and i.is_file():
            rel = i.relative_to(s.folder).as_posix()
            hit = next((pat for pat in s.products if fnmatch.fnmatchcase(rel, pat)), None)
            if hit is not None:
                raise OutputError(
                    f"the input {i} is where this command writes its products ({s.folder}/{hit}); it would be "
                    "overwritten. Move or copy the input out of the output folder, or choose another --out"
                )
        elif _within(i, s.folder) and i.is_dir():
            rel = i.relative_to(s.folder).as_posix()
            if any(fnmatch.fnmatchcase(rel + "/x", pat) for pat in s.products):
                raise OutputError(
                    f"the input folder {i} lies where this command writes its products; choose another --out"
                )


def close_sessions(ok: bool = True, exc: BaseException | None = None) -> None:
    """Close every open session, innermost first (the CLI calls this when a command ends)."""
    while _ACTIVE:
        _ACTIVE[-1].close(ok=ok, exc=exc)


@contextlib.contextmanager
def no_sessions():  # pragma: no cover - for tests
    saved = list(_ACTIVE)
    _ACTIVE.clear()
    try:
        yield
    finally:
        _ACTIVE[:] = saved


# =====================================================================================================
# resources
# =====================================================================================================
def available_memory_bytes() -> int | None:
    """Memory this process may still use: MemAvailable, capped by a cgroup limit (containers); None if unknown."""
    avail = None
    try:
        with open("/proc/meminfo", encoding="ascii") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    avail = int(line.split()[1]) * 1024
                    break
    except (OSError, ValueError):
        pass
    if avail is None:
        with contextlib.suppress(ValueError, OSError, AttributeError):
            avail = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    for lim, cur in (
        ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory.current"),
        ("/sys/fs/cgroup/memory/memory.limit_in_bytes", "/sys/fs/cgroup/memory/memory.usage_in_bytes"),
    ):
        try:
            raw = Path(lim).read_text().strip()
            if raw != "max" and int(raw) < 1 << 60:
                room = int(raw) - int(Path(cur).read_text().strip())
                avail = room if avail is None else min(avail, room)
            break
        except (OSError, ValueError):
            continue
    env = os.environ.get("GEOCD_MEMORY_LIMIT_MB")
    if env:
        with contextlib.suppress(ValueError):
            lim = int(float(env) * 1e6)
            avail = lim if avail is None else min(avail, lim)
    return avail


def _file_size_limit() -> int | None:
    try:
        import resource

        soft, _ = resource.getrlimit(resource.RLIMIT_FSIZE)
        return None if soft == resource.RLIM_INFINITY else int(soft)
    except (ImportError, ValueError, OSError):  # pragma: no cover
        return None


def _gib(n: float) -> str:
    return f"{n / 2**30:,.1f} GiB" if n >= 2**30 else f"{n / 2**20:,.0f} MiB"


def grid_job_bytes(
    cells: int, *, memory_per_cell: float, disk_per_cell: float = 0.0, largest_file_per_cell: float = 0.0
) -> dict[str, int]:
    """Memory and disk (uncompressed) of a job on ``cells`` grid cells, from per-cell byte counts."""
    return {
        "memory": int(cells * memory_per_cell),
        "disk": int(cells * disk_per_cell),
        "largest_file": int(cells * largest_file_per_cell),
    }


def check_resources(
    what: str,
    *,
    memory_bytes: int = 0,
    disk_bytes: int = 0,
    largest_file_bytes: int = 0,
    out: os.PathLike | str | None = None,
    fix: str = "",
    compression: float = 4.0,
) -> None:
    """Refuse a job that cannot fit, before its heavy step.

    Parameters
    ----------
    what : the job, for the message ("stereo on a 200000 x 200000 grid at 0.5 m, 6 pairs").
    memory_bytes : estimated peak memory; refused when above the available memory
        (:func:`available_memory_bytes`).
    disk_bytes, largest_file_bytes : uncompressed size of the products, and of the largest one. Products are
        compressed (COG deflate); the job is refused when even ``disk_bytes / compression`` does not fit in the
        free space of ``out``'s file system (or the largest file in a ``ulimit -f`` limit), and warned about
        when the uncompressed size does not fit.
    fix : what to change, appended to the message (e.g. "use --posting 2 or a smaller AOI").

    Raises
    ------
    ResourceError, DiskFullError
    """
    from ..faults import free_bytes

    tail = f"; {fix}" if fix else ""
    avail = available_memory_bytes()
    if memory_bytes and avail is not None and memory_bytes > avail:
        raise ResourceError(
            f"{what} needs about {_gib(memory_bytes)} of memory, {_gib(max(avail, 0))} is available{tail}"
        )
    if out is not None and disk_bytes:
        free = free_bytes(out)
        if free is not None and disk_bytes / compression > free:
            raise DiskFullError(
                f"no space left on device for {what}: about {disk_bytes / compression / 1e6:,.0f} MB "
                f"needed (compressed; {disk_bytes / 1e6:,.0f} MB uncompressed), {free / 1e6:,.0f} MB "
                f"free on {out}{tail or '; free some space or choose another --out'}"
            )
        if free is not None and disk_bytes > free:
            warnings.warn(
                f"{what}: the products may need up to {disk_bytes / 1e6:,.0f} MB (uncompressed) and "
                f"{free / 1e6:,.0f} MB are free on {out}",
                OutputFolderWarning,
                stacklevel=2,
            )
    lim = _file_size_limit()
    if lim is not None and largest_file_bytes and largest_file_bytes / compression > lim:
        raise DiskFullError(
            f"{what}: the largest product needs about {largest_file_bytes / compression / 1e6:,.1f} MB "
            f"but the file-size limit (ulimit -f) is {lim / 1e6:,.1f} MB; raise the limit or use a "
            "coarser posting"
        )


__all__ = [
    "open_outputs",
    "OutputSession",
    "close_sessions",
    "check_prefix",
    "clean_litter",
    "verify_products",
    "check_product_set",
    "read_products_manifest",
    "check_resources",
    "grid_job_bytes",
    "available_memory_bytes",
    "sha256_file",
    "MANIFEST_NAME",
    "LOCK_NAME",
    "OutputFolderWarning",
    "lock_is_held",
    "active_sessions",
]


# ---------------------------------------------------------------------------------------------------------------
# output FILES named by the user (--out x.tif, --out model.json): never replace a file geocd did not write
# ---------------------------------------------------------------------------------------------------------------
def refuse_foreign_files(
    files: Iterable[os.PathLike | str | None],
    recognise: Callable[[Path], bool],
    *,
    what: str,
    force: bool = False,
    option: str = "--out",
) -> None:
    """Refuse to replace an existing output file that geocd did not write (a user's own file at that name).

    Call before any heavy work. A file counts as geocd's when ``recognise(path)`` is true (it carries the
    marks of this command's product: tags, a format key); a recogniser that fails means "not ours". Folders
    and missing paths are left to :func:`open_outputs`.

    Parameters
    ----------
    files : the output files (``None`` entries are ignored).
    recognise : whether an existing file is this command's product.
    what : what this command writes there, for the message ("a geocd ortho GeoTIFF").
    force : the user asked to replace any file (``--overwrite``).
    option : the option that named the path, for the message.

    Raises
    ------
    OutputError
    """
    if force:
        return
    for f in files:
        if f is None:
            continue
        p = Path(f)
        if not p.is_file():
            continue
        try:
            ours = bool(recognise(p))
        except Exception:  # noqa: BLE001 - unreadable as our product: then it is not ours
            ours = False
        if not ours:
            raise OutputError(
                f"{p} exists and geocd did not write it (it is not {what}); refusing to replace it. "
                f"Choose another {option}, move the file away, or pass --overwrite to replace it"
            )


def geotiff_tag_startswith(path: Path, tag: str, prefix: str) -> bool:
    """Whether a GeoTIFF's dataset tag ``tag`` starts with ``prefix`` (a recogniser for :func:`refuse_foreign_files`)."""
    import rasterio

    with rasterio.open(path) as ds:
        return str(ds.tags().get(tag, "")).startswith(prefix)


def is_qgis_style(path: Path) -> bool:
    """Whether a file is a QGIS style (``.qml``): geocd rewrites the styles beside its rasters."""
    with open(path, "rb") as fh:
        return b"<qgis" in fh.read(4096)
