"""numba helpers: the decorator of the parallel kernels, and the compile notice of the CLI.

:func:`parallel_njit` compiles a kernel with ``parallel=True`` only where numba may run more than one thread.
The compile notice: a first run says once on stderr that it is compiling, and how long it took. numba compiles a kernel the first time it is called with new argument types and caches
the machine code (``cache=True``: ``__pycache__`` beside the module, or ``NUMBA_CACHE_DIR``),
so only a command's first run on a machine pays for it. The CLI calls
:func:`install_compile_notice`; library users see nothing.
"""

from __future__ import annotations

import atexit
import importlib.abc
import importlib.util
import json
import sys
import time
import types

_state = {"installed": False, "depth": 0, "t0": 0.0, "seconds": 0.0, "kernels": 0, "announced": False}


def compile_seconds() -> float:
    """Wall seconds spent compiling numba kernels in this process so far."""
    return float(_state["seconds"])


class _AfterNumbaImport(importlib.abc.MetaPathFinder):
    """Runs a callback once numba has been imported, so a command that never needs numba never imports it."""

    def __init__(self, callback):
        self.callback = callback

    def find_spec(self, name, path, target=None):
        if name != "numba":
            return None
        sys.meta_path.remove(self)
        spec = importlib.util.find_spec(name)
        if spec is None or spec.loader is None:
            return spec
        loader, callback = spec.loader, self.callback
        exec_module = loader.exec_module

        def exec_then_install(module):
            exec_module(module)
            callback()

        loader.exec_module = exec_then_install
        return spec


def install_compile_notice(stream=None, *, json_lines: bool = False) -> None:
    """Print one line when the first numba compilation of this process starts, and a summary at exit.

    Imports nothing: when numba is not imported yet, the notice is installed right after its import.
    ``json_lines``: as ``{"type": "info", "message": ...}`` lines (the QGIS plugin's protocol).
    """
    if _state["installed"] or _state.get("pending"):
        return
    if "numba" not in sys.modules:
        _state["pending"] = True
        sys.meta_path.insert(0, _AfterNumbaImport(lambda: _install(stream, json_lines)))
        return
    _install(stream, json_lines)


def _install(stream, json_lines: bool) -> None:
    if _state["installed"]:
        return
    from numba.core import event

    class _Out:
        @staticmethod
        def write(msg: str) -> None:
            if json_lines:
                msg = json.dumps({"type": "info", "message": msg.strip().removeprefix("geocd: ")}) + "\n"
            try:
                (stream if stream is not None else sys.stderr).write(msg)
            except (ValueError, OSError):  # the stream was closed before the exit summary
                pass

        @staticmethod
        def flush() -> None:
            try:
                (stream if stream is not None else sys.stderr).flush()
            except (ValueError, OSError):
                pass

    out = _Out()

    class _Notice(event.Listener):
        def on_start(self, ev):
            if _state["depth"] == 0:
                _state["t0"] = time.perf_counter()
                _state["kernels"] += 1
                if not _state["announced"]:
                    _state["announced"] = True
                    out.write(
                        "geocd: compiling numerical kernels (one-time on this machine: later runs reuse numba's "
                        "cache; usually 1-2 min of CPU for a whole run) ...\n"
                    )
                    out.flush()
            _state["depth"] += 1

        def on_end(self, ev):
            _state["depth"] -= 1
            if _state["depth"] == 0:
                _state["seconds"] += time.perf_counter() - _state["t0"]

    event.register("numba:compile", _Notice())
    _state["installed"] = True

    def _summary():
        if _state["kernels"]:
            out.write(f"geocd: compiled {_state['kernels']} kernel(s) in {_state['seconds']:.0f} s (cached now)\n")

    atexit.register(_summary)


def parallel_njit(**options):
    """``numba.njit(cache=True, parallel=True, **options)``, compiled serial where numba runs one thread.

    With ``NUMBA_NUM_THREADS=1`` (set for one process per core, as the test suite does for its pytest-xdist
    workers) the parallel build runs on one thread anyway, and costs about three times the compile time of the same kernel
    compiled serial (71.6 against 23.3 CPU-s for the stereo and probchange kernels, measured here). There the
    kernel is compiled without ``parallel`` (``prange`` is then ``range``, the same loop in order) and cached
    under its own name (``<name>__serial``), so that the two builds never replace each other in numba's cache.

    Parameters
    ----------
    **options : further ``numba.njit`` options (``error_model``, ``fastmath`` ...)

    Returns
    -------
    a decorator, like ``numba.njit(...)``
    """
    import numba

    def decorate(fn):
        if numba.config.NUMBA_NUM_THREADS > 1:
            return numba.njit(cache=True, parallel=True, **options)(fn)
        serial = types.FunctionType(fn.__code__, fn.__globals__, fn.__name__, fn.__defaults__, fn.__closure__)
        serial.__qualname__ = fn.__qualname__ + "__serial"  # numba names its cache files after the qualname
        serial.__module__, serial.__doc__ = fn.__module__, fn.__doc__
        serial.__kwdefaults__ = fn.__kwdefaults__
        return numba.njit(cache=True, **options)(serial)

    return decorate
