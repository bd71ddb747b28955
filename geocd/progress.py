"""Progress reporting and cancellation for long operations.

Long functions accept ``progress``: a callable ``progress(fraction, message)``
where ``fraction`` is in [0, 1] (or ``None`` when unknown). It may raise
:class:`geocd.errors.CancelledError` to stop the work; functions call it between
tiles, so cancellation takes effect at the next tile boundary.

The CLI passes a tqdm bar or a JSON-lines reporter (``--progress json``, used by
the QGIS plugin). Library code never prints.

JSON-lines protocol (one object per line on stderr)::

    {"type": "progress", "stage": "stereo", "fraction": 0.42, "message": "pair 1/3"}
    {"type": "info", "message": "..."}
    {"type": "warning", "message": "..."}
    {"type": "error", "message": "...", "error": "RPCParseError"}
    {"type": "result", "outputs": {"name": "path", ...}}
"""

from __future__ import annotations

import json
import sys
import time
from typing import Callable, Optional, Protocol, TextIO

from .errors import CancelledError


class Progress(Protocol):
    def __call__(self, fraction: Optional[float], message: str = "") -> None: ...


def null_progress(fraction: Optional[float], message: str = "") -> None:
    """A progress callback that does nothing."""


def ensure_progress(progress: Optional[Progress]) -> Progress:
    return null_progress if progress is None else progress


def sub_progress(progress: Optional[Progress], start: float, stop: float, prefix: str = "") -> Progress:
    """Map a sub-task's [0, 1] onto [start, stop] of ``progress``."""
    parent = ensure_progress(progress)

    def _sub(fraction: Optional[float], message: str = "") -> None:
        f = None if fraction is None else start + (stop - start) * min(max(fraction, 0.0), 1.0)
        parent(f, f"{prefix}{message}" if prefix else message)

    return _sub


class JSONLinesProgress:
    """Write progress as JSON lines (the QGIS plugin's protocol)."""

    def __init__(self, stream: TextIO | None = None, stage: str = "", min_interval_s: float = 0.2):
        self.stream = stream or sys.stderr
        self.stage = stage
        self.min_interval_s = min_interval_s
        self._last = 0.0

    def emit(self, obj: dict) -> None:
        self.stream.write(json.dumps(obj) + "\n")
        self.stream.flush()

    def __call__(self, fraction: Optional[float], message: str = "") -> None:
        now = time.monotonic()
        if fraction is not None and 0.0 < fraction < 1.0 and now - self._last < self.min_interval_s:
            return
        self._last = now
        self.emit({"type": "progress", "stage": self.stage, "fraction": fraction, "message": message})


class TqdmProgress:
    """A tqdm bar as a progress callback."""

    def __init__(self, desc: str = "", disable: bool = False):
        from tqdm import tqdm

        self.bar = tqdm(
            total=1000,
            desc=desc,
            disable=disable,
            leave=False,
            bar_format="{desc}{percentage:3.0f}%|{bar}| {elapsed}<{remaining} {postfix}",
        )
        self._n = 0

    def __call__(self, fraction: Optional[float], message: str = "") -> None:
        if fraction is not None:
            n = int(round(min(max(fraction, 0.0), 1.0) * 1000))
            if n > self._n:
                self.bar.update(n - self._n)
                self._n = n
        if message:
            self.bar.set_postfix_str(message[:60], refresh=False)

    def close(self) -> None:
        self.bar.close()


class CancelToken:
    """A flag that a progress wrapper checks; set it from another thread to cancel."""

    def __init__(self) -> None:
        self.cancelled = False

    def wrap(self, progress: Optional[Progress]) -> Progress:
        inner = ensure_progress(progress)

        def _p(fraction: Optional[float], message: str = "") -> None:
            if self.cancelled:
                raise CancelledError("operation cancelled by the user; outputs were not written")
            inner(fraction, message)

        return _p


ProgressCallback = Callable[[Optional[float], str], None]
