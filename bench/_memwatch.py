"""Peak resident memory of a process tree (this process and all its descendants), sampled by a thread."""

from __future__ import annotations

import threading

import psutil


def tree_rss(pid: int | None = None) -> int:
    """Sum of the RSS of a process and all its descendants (bytes)."""
    try:
        p = psutil.Process(pid)
        procs = [p] + p.children(recursive=True)
    except psutil.NoSuchProcess:
        return 0
    tot = 0
    for q in procs:
        try:
            tot += q.memory_info().rss
        except psutil.NoSuchProcess:
            pass
    return tot


class TreeMemory:
    """``with TreeMemory() as m: ...`` then ``m.peak`` (bytes): peak of the summed RSS of the tree."""

    def __init__(self, pid: int | None = None, interval_s: float = 0.2):
        self.pid = pid
        self.interval_s = interval_s
        self.peak = 0
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self._stop.is_set():
            self.peak = max(self.peak, tree_rss(self.pid))
            self._stop.wait(self.interval_s)

    def __enter__(self) -> "TreeMemory":
        self._t.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._t.join()
        self.peak = max(self.peak, tree_rss(self.pid))
