"""Shared fixtures.

Real data lives in ``../shared/data`` beside the repository (never copied in).
Tests that read it carry ``@pytest.mark.realdata`` and use :func:`shared_data`,
which skips with a clear reason when the folder (or the file) is absent.
"""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

import pytest

if os.environ.get("PYTEST_XDIST_WORKER"):
    # one pytest-xdist worker per core: each runs its kernels and BLAS on one thread (no oversubscription);
    # set before numba or numpy is imported by a test module
    for _var in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(_var, "1")

# pytest caches its assertion-rewritten test modules (and Python the package's bytecode) in __pycache__, which
# PYTHONDONTWRITEBYTECODE (set in some containers) forbids: every later run then rewrites ~230 modules again,
# about 9 s per process. The test run writes them, as it writes numba's cache there.
sys.dont_write_bytecode = False

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("GEOCD_SHARED_DATA", REPO.parent / "shared" / "data"))


def shared_data(*parts: str) -> Path:
    """Path under ../shared/data; skips the test when it is missing."""
    p = SHARED_DATA.joinpath(*parts)
    if not p.exists():
        pytest.skip(
            f"real data not available: {p} is absent (set GEOCD_SHARED_DATA or place ../shared beside the repo)"
        )
    return p


@pytest.fixture(scope="session")
def shared() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real data folder {SHARED_DATA} is absent")
    return SHARED_DATA


@pytest.fixture(scope="session")
def sample_aoi() -> Path:
    p = REPO / "sample_aoi"
    if not (p / "scene.yaml").is_file():
        pytest.fail("sample_aoi/scene.yaml is missing: the committed sample AOI must be present")
    return p


def _session_env(name: str, value: str):
    """Set the environment variable ``name`` for the test session, then put back what it was."""
    old = os.environ.get(name)
    os.environ[name] = value
    yield
    if old is None:
        os.environ.pop(name, None)
    else:
        os.environ[name] = old


@pytest.fixture(scope="session", autouse=True)
def _trusted_models_list(tmp_path_factory):
    """Land-cover models trained by the tests are trusted in a list of the test run, not the user's cache."""
    from geocd.landcover.trust import TRUST_ENV

    yield from _session_env(TRUST_ENV, str(tmp_path_factory.mktemp("trust") / "trusted_models"))


@pytest.fixture(scope="session", autouse=True)
def _work_key_file(tmp_path_factory):
    """Tiled runs of the tests sign their journal with a key of the test run, not the user's cache."""
    from geocd.tiling.store import WORK_KEY_ENV

    yield from _session_env(WORK_KEY_ENV, str(tmp_path_factory.mktemp("workkey") / "work_key"))


# --- longest files first -------------------------------------------------------------------------------------
# pytest-xdist hands whole files to its workers (``--dist loadfile``) in collection order
# (``--no-loadscope-reorder``): starting with the files that take longest keeps both workers busy to the end
# instead of leaving one of them alone with a long file. The seconds per file come from a full run with
# GEOCD_STORE_DURATIONS=1 (``tests/durations.json``); a file it does not name keeps its place after them.
DURATIONS_FILE = REPO / "tests" / "durations.json"
_seconds_per_file: dict[str, float] = {}


def _file_of(nodeid: str) -> str:
    return nodeid.split("::", 1)[0]


def pytest_collection_modifyitems(config, items):
    try:
        seconds = json.loads(DURATIONS_FILE.read_text())
    except (OSError, ValueError):
        return
    items.sort(key=lambda item: -float(seconds.get(_file_of(item.nodeid), 0.0)))  # stable: a file's order kept


def pytest_runtest_logreport(report):
    if os.environ.get("GEOCD_STORE_DURATIONS") and not os.environ.get("PYTEST_XDIST_WORKER"):
        f = _file_of(report.nodeid)
        _seconds_per_file[f] = _seconds_per_file.get(f, 0.0) + float(report.duration)


# --- numba compile time (with GEOCD_STORE_DURATIONS=1) --------------------------------------------------------
# How much of a run is numba compiling kernels (a fresh clone compiles every kernel the tests call once, into
# numba's cache). Counted once numba is imported, so that tests that check a command never imports it still can.
_compile = {"seconds": 0.0, "kernels": 0}


def _count_numba_compiles() -> None:
    from numba.core import event

    class _Timer(event.Listener):
        depth, t0 = 0, 0.0

        def on_start(self, ev):
            if self.depth == 0:
                self.t0 = time.perf_counter()
            self.depth += 1

        def on_end(self, ev):
            self.depth -= 1
            if self.depth == 0:
                _compile["seconds"] += time.perf_counter() - self.t0
                _compile["kernels"] += 1

    event.register("numba:compile", _Timer())


if os.environ.get("GEOCD_STORE_DURATIONS"):
    from geocd._jit import _AfterNumbaImport

    sys.meta_path.insert(0, _AfterNumbaImport(_count_numba_compiles))


def _compile_report_dir(config) -> Path:
    base = config._tmp_path_factory.getbasetemp()
    return base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    if not os.environ.get("GEOCD_STORE_DURATIONS"):
        return
    parts = [json.loads(f.read_text()) for f in sorted(_compile_report_dir(config).glob("numba_compile_*.json"))]
    if not parts and _compile["kernels"]:
        parts = [{"worker": "main", **_compile}]
    if parts:
        total = sum(p["seconds"] for p in parts)
        each = ", ".join(f"{p['worker']} {p['kernels']} in {p['seconds']:.0f} s" for p in parts)
        terminalreporter.write_line(f"numba compiled kernels (cache misses) for {total:.0f} s of worker time: {each}")


def pytest_sessionfinish(session, exitstatus):
    worker = os.environ.get("PYTEST_XDIST_WORKER")
    if worker and os.environ.get("GEOCD_STORE_DURATIONS"):
        (_compile_report_dir(session.config) / f"numba_compile_{worker}.json").write_text(
            json.dumps({"worker": worker, "seconds": round(_compile["seconds"], 1), "kernels": _compile["kernels"]})
        )
    if _seconds_per_file and not os.environ.get("PYTEST_XDIST_WORKER"):
        try:
            known = json.loads(DURATIONS_FILE.read_text())
        except (OSError, ValueError):
            known = {}
        known.update({f: round(s, 1) for f, s in _seconds_per_file.items()})
        ordered = dict(sorted(known.items(), key=lambda kv: -kv[1]))
        DURATIONS_FILE.write_text(json.dumps(ordered, indent=1) + "\n")
