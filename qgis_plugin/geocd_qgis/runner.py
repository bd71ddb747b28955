"""Run one geocd CLI call as a child process and follow its JSON-lines progress (plain Python: no ``qgis``).

The child is started with ``--progress json``; every stderr line that parses as
a JSON object is one event of geocd's protocol (see ``geocd/progress.py``)::

    {"type": "progress", "stage": ..., "fraction": 0.42, "message": ...}
    {"type": "info" | "warning", "message": ...}
    {"type": "error", "error": "RPCParseError", "message": ...}
    {"type": "result", "outputs": {"name": "path", ...}}

Other lines (stdout, tracebacks, ``geocd: error: ...``) are passed on as console text.

Cancellation: :func:`run_geocd` polls ``is_cancelled()`` ten times a second; on
cancel it interrupts the child (SIGINT, so geocd's atomic writers remove their
temporary files), waits ``grace_s``, then kills the child's whole process
group. :func:`remove_new_files` then deletes whatever the run created in its
output folder, so a cancelled run leaves no partial output.
"""

from __future__ import annotations

import json
import os
import queue
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional

_IS_WIN = sys.platform.startswith("win")


@dataclass
class RunResult:
    returncode: Optional[int]
    cancelled: bool = False
    outputs: dict = field(default_factory=dict)
    error: Optional[str] = None  # geocd's error message ({"type": "error"} or "geocd: error: ..." line)
    error_type: Optional[str] = None
    stdout: str = ""
    stderr_tail: list = field(default_factory=list)
    pid: Optional[int] = None

    @property
    def ok(self) -> bool:
        return self.returncode == 0 and not self.cancelled

    def failure_message(self) -> str:
        """The best one-paragraph explanation of a failed run (never a Python traceback)."""
        if self.cancelled:
            return "geocd was cancelled; its partial outputs were removed"
        if self.error:
            return self.error
        tail = [l for l in self.stderr_tail if l.strip()]
        if any(l.startswith("Traceback (most recent call last)") for l in tail):
            last = summarize_traceback(tail)
            return (
                f"geocd stopped unexpectedly ({last}). This is a bug or a broken installation: run the same "
                "command with --debug in a terminal (the log above has it) and report the output"
            )
        if self.returncode is not None and self.returncode < 0:
            return (
                f"geocd was killed by signal {-self.returncode} (out of memory, or stopped by the system); "
                "try a coarser posting or a smaller extent"
            )
        if tail:
            return f"geocd exited with status {self.returncode}:\n" + "\n".join(tail[-15:])
        return f"geocd exited with status {self.returncode} without a message"


def summarize_traceback(lines: list) -> str:
    """The exception line that ends a Python traceback ("ValueError: ..."), else the last line."""
    body = [l for l in lines if l.strip()]
    for l in reversed(body):
        s = l.strip()
        if not l.startswith((" ", "\t")) and not s.startswith(("Traceback", "During handling", "The above exception")):
            return s[:300]
    return body[-1].strip()[:300] if body else "no message"


def describe_exception(exc: BaseException) -> str:
    """One line for an exception raised in the plugin itself (shown instead of a traceback)."""
    import errno as _errno

    if isinstance(exc, OSError):
        name = getattr(exc, "filename", None) or ""
        if exc.errno in (_errno.ENOSPC, getattr(_errno, "EDQUOT", -1)):
            return f"no space left on device writing {name}; free some space or choose another output folder"
        if exc.errno == getattr(_errno, "EROFS", -1):
            return f"read-only file system: {name}; choose an output folder on a writable disk"
        if exc.errno in (_errno.EACCES, _errno.EPERM):
            return f"permission denied: {name}; choose a folder you can write to"
        return f"cannot access {name or 'a file'}: {exc.strerror or exc}; check the path"
    if isinstance(exc, MemoryError):
        return "out of memory; use a coarser posting or a smaller extent"
    msg = " ".join(str(exc).split())[:300]
    return (
        f"the geocd plugin failed ({type(exc).__name__}: {msg}); this is a bug: please report it with the "
        "log of this run"
    )


def _reader(stream, tag: str, q: "queue.Queue") -> None:
    try:
        for line in iter(stream.readline, ""):
            q.put((tag, line.rstrip("\r\n")))
    except (OSError, ValueError):
        pass
    finally:
        q.put((tag, None))


def _interrupt(proc: subprocess.Popen) -> None:
    try:
        if _IS_WIN:
            proc.send_signal(signal.CTRL_BREAK_EVENT)  # type: ignore[attr-defined]
        else:
            os.killpg(proc.pid, signal.SIGINT)
    except (OSError, ValueError):
        pass


def _kill(proc: subprocess.Popen) -> None:
    try:
        if _IS_WIN:
            proc.kill()
        else:
            os.killpg(proc.pid, signal.SIGKILL)
    except (OSError, ValueError):
        pass


def run_geocd(
    argv: list[str],
    *,
    on_progress: Callable[[Optional[float], str, str], None] = lambda f, m, s: None,
    on_info: Callable[[str], None] = lambda m: None,
    on_warning: Callable[[str], None] = lambda m: None,
    on_console: Callable[[str], None] = lambda m: None,
    on_start: Callable[[int], None] = lambda pid: None,
    is_cancelled: Callable[[], bool] = lambda: False,
    env: Optional[dict] = None,
    cwd: Optional[str] = None,
    poll_s: float = 0.1,
    grace_s: float = 3.0,
) -> RunResult:
    """Run ``argv`` (a full geocd command line with ``--progress json``) and stream its events.

    Callbacks run in the calling thread. Returns when the child has exited (or been killed).
    """
    kw: dict = {}
    if _IS_WIN:
        kw["creationflags"] = subprocess.CREATE_NEW_PROCESS_GROUP  # type: ignore[attr-defined]
    else:
        kw["start_new_session"] = True  # own process group: a cancel reaches its workers too
    proc = subprocess.Popen(
        argv,
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        encoding="utf-8",
        errors="replace",
        bufsize=1,
        env=env,
        cwd=cwd,
        **kw,
    )
    res = RunResult(returncode=None, pid=proc.pid)
    on_start(proc.pid)
    q: "queue.Queue" = queue.Queue()
    threads = [
        threading.Thread(target=_reader, args=(proc.stdout, "out", q), daemon=True),
        threading.Thread(target=_reader, args=(proc.stderr, "err", q), daemon=True),
    ]
    for t in threads:
        t.start()
    open_streams = 2
    stdout_lines: list[str] = []
    tail: list[str] = []
    interrupted_at: Optional[float] = None
    killed = False
    while open_streams > 0 or proc.poll() is None:
        if is_cancelled() and not res.cancelled:
            res.cancelled = True
            interrupted_at = time.monotonic()
            _interrupt(proc)
        if res.cancelled and not killed and time.monotonic() - interrupted_at > grace_s:
            _kill(proc)
            killed = True
        try:
            tag, line = q.get(timeout=poll_s)
        except queue.Empty:
            if open_streams == 0 and proc.poll() is None:
                time.sleep(poll_s)
            continue
        if line is None:
            open_streams -= 1
            continue
        if tag == "out":
            stdout_lines.append(line)
            on_console(line)
            continue
        event = None
        s = line.strip()
        if s.startswith("{") and s.endswith("}"):
            try:
                event = json.loads(s)
            except ValueError:
                event = None
        if not isinstance(event, dict) or "type" not in event:
            tail = (tail + [line])[-50:]
            if s.startswith("geocd: error:") and res.error is None:
                res.error = s[len("geocd: error:") :].strip()
            on_console(line)
            continue
        kind = event.get("type")
        msg = str(event.get("message") or "")
        if kind == "progress":
            frac = event.get("fraction")
            try:
                frac = None if frac is None else float(frac)
            except (TypeError, ValueError):
                frac = None
            on_progress(frac, msg, str(event.get("stage") or ""))
        elif kind == "info":
            on_info(msg)
        elif kind == "warning":
            on_warning(msg)
        elif kind == "error":
            res.error = msg or res.error
            res.error_type = event.get("error")
        elif kind == "result":
            outs = event.get("outputs") or {}
            if isinstance(outs, dict):
                base = Path(cwd) if cwd else Path.cwd()
                res.outputs.update(
                    {str(k): str(base / str(v)) if not Path(str(v)).is_absolute() else str(v) for k, v in outs.items()}
                )
        else:
            on_console(line)
    for t in threads:
        t.join(timeout=1.0)
    res.returncode = proc.wait()
    for stream in (proc.stdout, proc.stderr):
        try:
            stream.close()
        except OSError:
            pass
    res.stdout = "\n".join(stdout_lines)
    res.stderr_tail = tail
    return res


# ---------------------------------------------------------------------------------------------------------------
# partial outputs of a cancelled run
# ---------------------------------------------------------------------------------------------------------------


def snapshot(folder: Optional[str]) -> set:
    """Every file and folder under ``folder`` now (to tell later which ones a run created)."""
    if not folder:
        return set()
    root = Path(folder)
    if not root.exists():
        return set()
    return {str(p) for p in root.rglob("*")} | {str(root)}


def remove_new_files(folder: Optional[str], before: set) -> list[str]:
    """Delete files and folders under ``folder`` that are not in ``before`` (deepest first); return them."""
    if not folder:
        return []
    root = Path(folder)
    if not root.exists():
        return []
    removed = []
    paths = sorted(
        (p for p in [root, *root.rglob("*")] if str(p) not in before), key=lambda p: len(p.parts), reverse=True
    )
    for p in paths:
        try:
            if p.is_dir() and not p.is_symlink():
                p.rmdir()  # empty by now (children come first); a non-empty one keeps older files
            else:
                p.unlink()
            removed.append(str(p))
        except OSError:
            pass
    return removed
