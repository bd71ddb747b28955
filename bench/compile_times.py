"""What a geocd command spends compiling numba kernels, kernel by kernel.

Runs one ``geocd`` command line in this process with numba's compile events recorded, by default with an
empty numba cache (a temporary ``NUMBA_CACHE_DIR``: what a fresh install pays once), and prints each kernel's
compile seconds (its callees included), their sum and the command's whole CPU time. With ``--threads 1`` the
kernels built with :func:`geocd._jit.parallel_njit` compile serial, as in a one-thread-per-core run (pytest-xdist
workers, ``NUMBA_NUM_THREADS=1``).

Usage::

    .venv/bin/python bench/compile_times.py [--threads N] [--warm] [--json OUT] -- stereo PAIR.yaml --out OUT
    .venv/bin/python bench/compile_times.py -- run sample_aoi --out geocd_out/compile_run

The Réunion pair's manifest is the one ``bench/bench_stereo.py`` writes (``pair_manifest``).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--threads", type=int, default=None, help="NUMBA_NUM_THREADS for the command (default: numba's)")
    ap.add_argument("--warm", action="store_true", help="keep numba's cache as it is (default: an empty one)")
    ap.add_argument("--json", type=Path, default=None, help="also write the figures here")
    ap.add_argument("command", nargs=argparse.REMAINDER, help="-- then the geocd command line (without 'geocd')")
    args = ap.parse_args(argv)
    cmd = [a for a in args.command if a != "--"] if args.command[:1] == ["--"] else args.command
    if not cmd:
        ap.error("give the geocd command line after --")
    # numba reads these when it is first imported: set them before anything imports it
    if args.threads is not None:
        os.environ["NUMBA_NUM_THREADS"] = str(args.threads)
    cache = None
    if not args.warm:
        cache = tempfile.TemporaryDirectory(prefix="geocd_numba_cache_")
        os.environ["NUMBA_CACHE_DIR"] = cache.name

    from numba.core import event

    seconds: dict[str, float] = defaultdict(float)
    stack: list[tuple[str, float]] = []

    class _Listener(event.Listener):
        def on_start(self, ev):
            disp = (ev.data or {}).get("dispatcher")
            name = f"{disp.py_func.__module__}.{disp.py_func.__qualname__}" if disp is not None else "?"
            stack.append((name, time.perf_counter()))

        def on_end(self, ev):
            name, t0 = stack.pop()
            if not stack:  # a kernel's own compile includes its callees'
                seconds[name] += time.perf_counter() - t0

    event.register("numba:compile", _Listener())
    from geocd.cli import main as geocd_main

    c0, t0 = time.process_time(), time.perf_counter()
    try:
        # click returns the exit code of geocd's error path (ctx.exit) when it does not exit itself
        rv = geocd_main(["--progress", "none", *cmd], standalone_mode=False)
        code = rv if isinstance(rv, int) and not isinstance(rv, bool) else 0
    except SystemExit as exc:
        code = int(exc.code or 0)
    cpu_s, wall_s = time.process_time() - c0, time.perf_counter() - t0
    rows = sorted(seconds.items(), key=lambda kv: -kv[1])
    total = sum(seconds.values())
    print(
        f"geocd {' '.join(cmd)}: exit {code}, {cpu_s:.1f} s CPU ({wall_s:.1f} s wall), of it compiling "
        f"{len(rows)} kernel(s) {total:.1f} s ({'warm' if args.warm else 'empty'} numba cache)"
    )
    for name, s in rows:
        print(f"  {s:7.2f} s  {name}")
    if args.json:
        args.json.write_text(
            json.dumps(
                {
                    "command": cmd,
                    "exit": code,
                    "cpu_s": cpu_s,
                    "wall_s": wall_s,
                    "compile_s": total,
                    "kernels": dict(rows),
                },
                indent=1,
            )
        )
    if cache is not None:
        cache.cleanup()
    return code


if __name__ == "__main__":
    sys.exit(main())
