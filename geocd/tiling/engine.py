"""Dask as the engine of tiled runs: one switch for every scheduler.

``scheduler`` is one of

* ``"sync"`` — tiles one after the other in this process (tests, QGIS, debugging);
* ``"threads"`` — a ``distributed.LocalCluster`` with one in-process worker and a thread
  per core (numba kernels release the GIL);
* ``"processes"`` / ``"auto"`` (the default) — a ``distributed.LocalCluster`` sized to the
  machine: one single-threaded worker process per core, each with a memory limit
  (``memory_limit`` per worker; by default 80 % of the machine's memory shared out);
* an address (``tcp://host:8786``, ``host:8786``) — a running ``dask.distributed`` scheduler
  (``dask scheduler`` + ``dask worker`` processes; every worker needs geocd installed and
  the inputs and output folder on storage it can read).

Tasks are submitted with a bounded number in flight (``as_completed``): a scene of
any size keeps at most ``max_in_flight`` tile results in memory. geocd never schedules
tiles itself beyond that window.
"""

from __future__ import annotations

import contextlib
import logging
import os
from typing import Any, Callable, Iterable, Iterator

from ..errors import CancelledError, ConfigError, ProcessingError, SchedulerError

LOCAL_KINDS = ("sync", "threads", "processes", "auto")
#: the environment of the local worker processes: one process per core, so each runs its numba kernels (and any
#: BLAS) on one thread; with numba's default of one thread per core, n workers would run n² threads on n cores
ONE_THREAD_PER_PROCESS = {
    "NUMBA_NUM_THREADS": "1",
    "OMP_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
}
SCHEDULER_HELP = (
    "sync | threads | processes | auto | ADDRESS of a running dask.distributed scheduler (e.g. tcp://127.0.0.1:8786)"
)


def usable_cores() -> int:
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


def parse_memory(v: str | int | float | None) -> int | None:
    """Bytes from ``"2GB"``, ``"1500MiB"``, a number of bytes, or None."""
    if v is None or v == "" or v == "auto":
        return None
    if isinstance(v, (int, float)):
        return int(v)
    from dask.utils import parse_bytes

    try:
        return int(parse_bytes(str(v)))
    except (ValueError, TypeError) as exc:
        raise ConfigError(f"cannot read {v!r} as a memory size; write e.g. 2GB or 1500MiB") from exc


def is_address(s: str) -> bool:
    return "://" in s or (":" in s and s.rsplit(":", 1)[-1].isdigit())


class Engine:
    """Runs a function over items with a bounded number in flight; results come back as they finish."""

    def __init__(self, kind: str, n_workers: int, client: Any = None, cluster: Any = None):
        self.kind = kind
        self.n_workers = n_workers
        self.client = client
        self.cluster = cluster
        #: the cluster was started by :func:`open_engine` for this run (it may be stopped early)
        self.owned = False

    def release_local(self) -> bool:
        """Stop a LocalCluster that :func:`open_engine` started, when no more tiles will run (the
        workers' memory goes back before the client's last whole-scene step); True when stopped.
        An engine given by the caller, or a remote cluster, is left alone."""
        if not self.owned or self.cluster is None:
            return False
        self.close()
        self.kind = "closed"
        return True

    def describe(self) -> str:
        if self.client is None:
            return "sync (this process)"
        return f"{self.kind}: {self.n_workers} worker(s) at {self.client.scheduler.address}"

    def map_unordered(
        self,
        fn: Callable[..., Any],
        items: Iterable[Any],
        *,
        shared: Any = None,
        max_in_flight: int | None = None,
        key_prefix: str = "geocd-tile",
    ) -> Iterator[tuple[Any, Any]]:
        """Yield ``(item, fn(item, shared))`` as tasks finish (in order for ``sync``).

        ``shared`` (e.g. a whole-scene model) is sent to the workers once, not with every task.
        At most ``max_in_flight`` tasks (default 2 per worker) are submitted and not yet
        consumed. Closing the generator early (cancel, error) cancels what is in flight.
        """
        if self.client is None:
            for it in items:
                yield it, fn(it, shared)
            return
        from distributed import as_completed

        limit = max(1, max_in_flight or 2 * self.n_workers)
        shared_f = self.client.scatter(shared, broadcast=True, hash=False) if shared is not None else None
        todo = iter(items)
        futs: dict = {}
        ac = as_completed()
        k = 0

        def submit_next() -> bool:
            nonlocal k
            try:
                it = next(todo)
            except StopIteration:
                return False
            k += 1
            f = self.client.submit(fn, it, shared_f, pure=False, key=f"{key_prefix}-{k}-{os.urandom(4).hex()}")
            futs[f.key] = (f, it)
            ac.add(f)
            return True

        for _ in range(limit):
            if not submit_next():
                break
        try:
            for f in ac:
                _, it = futs.pop(f.key)
                try:
                    res = f.result()
                except Exception as exc:
                    from distributed.scheduler import KilledWorker

                    if isinstance(exc, KilledWorker):
                        raise ProcessingError(
                            f"a worker died while processing a tile ({exc}); it probably ran out of memory: give "
                            "workers more memory (--memory-limit) or use smaller tiles (--tile-size)"
                        ) from exc
                    raise
                finally:
                    f.release()
                submit_next()
                yield it, res
        finally:
            if futs:
                with contextlib.suppress(Exception):
                    self.client.cancel([f for f, _ in futs.values()], force=True)
                futs.clear()
            if shared_f is not None:
                with contextlib.suppress(Exception):
                    shared_f.release()

    def close(self) -> None:
        for obj in (self.client, self.cluster):
            if obj is not None:
                with contextlib.suppress(Exception):
                    obj.close()
        self.client = self.cluster = None


@contextlib.contextmanager
def open_engine(
    scheduler: "str | Engine | None" = "auto", *, n_workers: int | None = None, memory_limit: str | int | None = None
) -> Iterator[Engine]:
    """An :class:`Engine` for ``scheduler`` (see module docstring); an Engine passes through unchanged."""
    if isinstance(scheduler, Engine):
        yield scheduler
        return
    s = (scheduler or "auto").strip()
    if s == "sync":
        yield Engine("sync", 1)
        return
    if s not in LOCAL_KINDS and not is_address(s):
        raise ConfigError(f"unknown scheduler {s!r}; use {SCHEDULER_HELP}")
    try:
        from distributed import Client, LocalCluster
    except ImportError as exc:  # pragma: no cover - a declared dependency
        raise ConfigError("the dask/distributed schedulers need `pip install 'dask[distributed]'`") from exc
    cluster = client = None
    try:
        if is_address(s):
            try:
                client = Client(s, timeout="15s")
            except (OSError, TimeoutError) as exc:
                raise SchedulerError(
                    f"cannot reach the dask scheduler at {s} ({exc}); start it with "
                    f"`dask scheduler` and workers with `dask worker {s}`, or use "
                    "--scheduler processes for this machine only"
                ) from exc
            nw = len(client.scheduler_info().get("workers", {}))
            if nw == 0:
                client.wait_for_workers(1, timeout=60)
                nw = len(client.scheduler_info().get("workers", {}))
            _check_versions(client)
            eng = Engine("cluster", max(nw, 1), client, None)
        else:
            from distributed.system import MEMORY_LIMIT

            cores = usable_cores()
            nw = int(n_workers or cores)
            if nw < 1:
                raise ConfigError(f"n_workers must be ≥ 1, got {nw}")
            mem = parse_memory(memory_limit)
            if s == "threads":
                mem = mem or int(0.8 * MEMORY_LIMIT)
                cluster = LocalCluster(
                    n_workers=1,
                    threads_per_worker=nw,
                    processes=False,
                    memory_limit=mem,
                    dashboard_address=None,
                    silence_logs=logging.ERROR,
                )
                kind = "threads"
            else:
                mem = mem or int(0.8 * MEMORY_LIMIT / nw)
                cluster = LocalCluster(
                    n_workers=nw,
                    threads_per_worker=1,
                    processes=True,
                    memory_limit=mem,
                    dashboard_address=None,
                    silence_logs=logging.ERROR,
                    env=dict(ONE_THREAD_PER_PROCESS),
                )
                kind = "processes"
            client = Client(cluster)
            eng = Engine(kind, nw, client, cluster)
            eng.owned = True
    except BaseException:
        for obj in (client, cluster):
            if obj is not None:
                with contextlib.suppress(Exception):
                    obj.close()
        raise
    try:
        yield eng
    finally:
        eng.close()


def _check_versions(client) -> None:
    from .. import __version__

    def _v():
        try:
            import geocd

            return geocd.__version__
        except ImportError:
            return None

    try:
        vs = client.run(_v)
    except Exception:  # noqa: BLE001 - a cluster that refuses run(): let tasks fail with their own errors
        return
    bad = {w: v for w, v in vs.items() if v != __version__}
    if bad:
        raise SchedulerError(
            f"the dask workers run geocd {sorted(set(map(str, bad.values())))} but this is geocd "
            f"{__version__}; install the same geocd on every worker"
        )


__all__ = [
    "Engine",
    "open_engine",
    "usable_cores",
    "parse_memory",
    "is_address",
    "LOCAL_KINDS",
    "SCHEDULER_HELP",
    "CancelledError",
]
