"""numba compile notice: a first run says once on stderr that it is compiling, and how long it took.

numba compiles a kernel the first time it is called with new argument types and caches
the machine code (``cache=True``: ``__pycache__`` beside the module, or ``NUMBA_CACHE_DIR``),
so only a command's first run on a machine pays for it. The CLI calls
:func:`install_compile_notice`; library users see nothing.
"""

from __future__ import annotations

import atexit
import json
import sys
import time

_state = {"installed": False, "depth": 0, "t0": 0.0, "seconds": 0.0, "kernels": 0, "announced": False}


def compile_seconds() -> float:
    """Wall seconds spent compiling numba kernels in this process so far."""
    return float(_state["seconds"])


def install_compile_notice(stream=None, *, json_lines: bool = False) -> None:
    """Print one line when the first numba compilation of this process starts, and a summary at exit.

    ``json_lines``: as ``{"type": "info", "message": ...}`` lines (the QGIS plugin's protocol).
    """
    if _state["installed"]:
        return
    from numba.core import event

    stream = stream if stream is not None else sys.stderr

    class _Out:
        @staticmethod
        def write(msg: str) -> None:
            if json_lines:
                msg = json.dumps({"type": "info", "message": msg.strip().removeprefix("geocd: ")}) + "\n"
            stream.write(msg)

        @staticmethod
        def flush() -> None:
            stream.flush()

    out = _Out()

    class _Notice(event.Listener):
        def on_start(self, ev):
            if _state["depth"] == 0:
                _state["t0"] = time.perf_counter()
                _state["kernels"] += 1
                if not _state["announced"]:
                    _state["announced"] = True
                    out.write("geocd: compiling numerical kernels (one-time on this machine: later runs reuse numba's "
                              "cache; usually 1-2 min of CPU for a whole run) ...\n")
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
