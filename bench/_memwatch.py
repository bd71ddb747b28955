"""Peak resident memory and CPU of a process tree (a process and all its descendants), sampled by a thread;
:func:`run_process` runs one command and measures its whole tree (the benchmarks' one way to time a process);
:func:`geocd_command` and :func:`geocd_env` run this repository's geocd as a user does."""

from __future__ import annotations

import os
import resource
import subprocess
import sys
import threading
import time
from pathlib import Path

import psutil

REPO = Path(__file__).resolve().parents[1]


def geocd_command() -> list[str]:
    """geocd's command line from this environment: ``python -m geocd --progress none``."""
    return [sys.executable, "-m", "geocd", "--progress", "none"]


def geocd_env(cache: Path | None = None) -> dict:
    """The environment of a geocd process: this repository's geocd first on the path.

    Parameters
    ----------
    cache : Path, optional
        Its numba cache (``NUMBA_CACHE_DIR``): a new empty folder is a cold start.
    """
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), *filter(None, [env.get("PYTHONPATH")])])
    if cache is not None:
        env["NUMBA_CACHE_DIR"] = str(cache)
    return env


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
    """``with TreeMemory() as m: ...`` then ``m.peak`` (bytes): peak of the summed RSS of the tree.

    ``m.cpu_s`` sums, over every process of the tree seen, its last sampled user + system time (a process that
    ends between two samples loses at most one interval; :func:`run_process` adds the kernel's own account).
    """

    def __init__(self, pid: int | None = None, interval_s: float = 0.2):
        self.pid = pid
        self.interval_s = interval_s
        self.peak = 0
        self._cpu: dict[int, float] = {}
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._run, daemon=True)

    @property
    def cpu_s(self) -> float:
        """User + system seconds of the tree's processes, as last sampled."""
        return sum(self._cpu.values())

    def _sample(self) -> None:
        try:
            p = psutil.Process(self.pid)
            procs = [p] + p.children(recursive=True)
        except psutil.NoSuchProcess:
            return
        tot = 0
        for q in procs:
            try:
                with q.oneshot():
                    tot += q.memory_info().rss
                    ct = q.cpu_times()
                self._cpu[q.pid] = ct.user + ct.system
            except psutil.Error:
                pass
        self.peak = max(self.peak, tot)

    def _run(self) -> None:
        while not self._stop.is_set():
            self._sample()
            self._stop.wait(self.interval_s)

    def __enter__(self) -> "TreeMemory":
        self._t.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._t.join()
        self.peak = max(self.peak, tree_rss(self.pid))


def run_process(cmd: list[str], env: dict | None = None, cwd=None, interval_s: float = 0.2) -> dict:
    """Run a command; wall seconds, CPU seconds and peak RSS of its whole process tree.

    Parameters
    ----------
    cmd : list of str
        The command.
    env : dict, optional
        Its environment (default: this process's).
    cwd : path, optional
        Its working folder.
    interval_s : float
        Sampling interval of the tree's RSS.

    Returns
    -------
    dict
        ``wall_s``; ``cpu_s`` (user + system of the tree: the kernel's account of the waited-for descendants, or
        the sampled one when larger — a process left running by the command, or one whose parent exits without
        waiting for it (a multiprocessing fork server's workers), is only in the latter; both are given too:
        ``cpu_s_rusage``, ``cpu_s_sampled``);
        ``peak_rss_mb`` (peak of the summed RSS of the tree, sampled); ``returncode``; ``error_tail`` (the last
        1500 characters of the output) when it failed; ``compile_notice`` (lines of stderr that mention compiling).
    """
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t = time.perf_counter()
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=cwd)
    with TreeMemory(p.pid, interval_s=interval_s) as mem:
        stdout, stderr = p.communicate()
    wall = time.perf_counter() - t
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)
    out = {
        "wall_s": wall,
        "cpu_s": max(cpu, mem.cpu_s),
        "cpu_s_rusage": cpu,
        "cpu_s_sampled": mem.cpu_s,
        "peak_rss_mb": mem.peak / 2**20,
        "returncode": p.returncode,
        "stdout_tail": stdout[-4000:],
    }
    if p.returncode != 0:
        out["error_tail"] = (stdout + stderr)[-1500:]
    notice = [ln for ln in stderr.splitlines() if "compil" in ln]
    if notice:
        out["compile_notice"] = notice
    return out
