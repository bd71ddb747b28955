"""The log file of a run: ``geocd_<command>.log`` in its output folder.

The CLI (:class:`geocd.cli.common.Session`) and :func:`geocd.pipeline.run` called from Python write the same
file: a header (version, command, arguments, working folder, parameters), then one timestamped line per event
(``PROGRESS``, ``NOTE``, ``WARNING``, ``OUTPUT``, ``ERROR``...). The file is appended to, one header per run.
Lines given before the folder is known are kept and written first when it is opened.

Library code logs through the standard :mod:`logging` module under the logger ``"geocd"`` (:data:`logger`);
nothing is shown unless the caller configures logging, e.g. ``logging.basicConfig(level=logging.INFO)``.
"""

from __future__ import annotations

import datetime as _dt
import json
import logging
import os
import sys
from pathlib import Path
from typing import Any, Optional

LOG_PREFIX = "geocd_"

#: the package's logger; stage and progress lines at INFO
logger = logging.getLogger("geocd")
logger.addHandler(logging.NullHandler())


def now() -> str:
    """The local date and time as the log writes it."""
    return _dt.datetime.now().strftime("%Y-%m-%d %H:%M:%S")


def log_file_name(command: str) -> str:
    """``geocd_<command>.log`` (spaces and dashes as underscores): ``run`` gives ``geocd_run.log``."""
    return LOG_PREFIX + command.replace(" ", "_").replace("-", "_") + ".log"


def _version() -> str:
    from . import __version__

    return __version__


class RunLog:
    """The log file of one run of ``command``; lines are buffered until :meth:`open` names the folder.

    Parameters
    ----------
    command : str
        The command (``"run"``, ``"demdiff"``, ``"stereo"``...): names the file and heads the run.
    params : dict, optional
        The run's parameters, written in the header as JSON.
    """

    def __init__(self, command: str, params: Optional[dict[str, Any]] = None):
        self.command = command
        self.path: Optional[Path] = None
        self._fh = None
        self._buffer: list[str] = []
        self._new = False
        self._offset = 0
        self.line(f"==== geocd {_version()} {command} — {now()}")
        self.line(f"argv: {' '.join(sys.argv)}")
        self.line(f"cwd: {Path.cwd()}")
        self.line(f"parameters: {json.dumps(params or {}, default=str)}")

    @property
    def is_open(self) -> bool:
        return self._fh is not None

    def open(self, folder: os.PathLike | str) -> Path:
        """Start writing into ``folder`` (created if missing), the buffered lines first.

        Raises
        ------
        OSError
            The folder or the file cannot be written.
        """
        if self._fh is not None:
            return self.path
        path = Path(folder) / log_file_name(self.command)
        path.parent.mkdir(parents=True, exist_ok=True)
        new = not path.exists()
        fh = open(path, "a", encoding="utf-8", buffering=1)
        self._new = new
        self._offset = fh.tell()
        if fh.tell() > 0:
            fh.write("\n")
        fh.writelines(line + "\n" for line in self._buffer)
        self._buffer = []
        self._fh = fh
        self.path = path
        return path

    def line(self, text: str) -> None:
        """One timestamped line."""
        line = f"{_dt.datetime.now().strftime('%H:%M:%S')} {text}"
        if self._fh is not None:
            try:
                self._fh.write(line + "\n")
            except (OSError, ValueError):
                pass
        else:
            self._buffer.append(line)

    def lines(self, text: str) -> None:
        """One line per line of ``text``."""
        for part in str(text).splitlines() or [""]:
            self.line(part)

    def forget(self) -> None:
        """Take this run's lines back out of the file (the whole file when this run created it); close it."""
        path = self.path
        self.close()
        if path is None:
            return
        try:
            if self._new:
                path.unlink()
            else:
                with open(path, "r+b") as fh:
                    fh.truncate(self._offset)
        except OSError:
            pass
        self.path = None

    def close(self) -> None:
        if self._fh is not None:
            try:
                self._fh.close()
            except OSError:
                pass
            self._fh = None


class LoggedProgress:
    """A progress callback that logs, then passes each call on to ``inner``.

    One INFO line on :data:`logger` (and a ``PROGRESS`` line in ``runlog``) per stage (the message up to its first
    colon), per 5 % step and at least every 30 s while calls come, and the last one.

    Parameters
    ----------
    stage : str
        Heads every line (``"run"``).
    inner : callable, optional
        The caller's progress callback; it may raise :class:`geocd.errors.CancelledError`.
    runlog : RunLog, optional
        Where the lines are written as well.
    """

    STEP = 0.05
    MAX_SILENCE_S = 30.0

    def __init__(self, stage: str, inner=None, runlog: Optional[RunLog] = None):
        self.stage = stage
        self.inner = inner
        self.runlog = runlog
        self._last_step = -1
        self._last_phase: Optional[str] = None
        self._last_t = 0.0

    def __call__(self, fraction: Optional[float], message: str = "") -> None:
        import time

        now_t = time.monotonic()
        phase = message.split(":", 1)[0].strip()
        step = self._last_step if fraction is None else int(min(max(fraction, 0.0), 1.0) / self.STEP + 1e-9)
        if (
            step > self._last_step
            or (phase and phase != self._last_phase)
            or now_t - self._last_t >= self.MAX_SILENCE_S
        ):
            self._last_step = max(step, self._last_step)
            self._last_phase = phase or self._last_phase
            self._last_t = now_t
            pct = "   " if fraction is None else f"{100 * fraction:3.0f}%"
            line = f"{self.stage} {pct} {message}".rstrip()
            logger.info(line)
            if self.runlog is not None:
                self.runlog.line(f"PROGRESS {line}")
        if self.inner is not None:
            self.inner(fraction, message)
