"""Shared fixtures.

Real data lives in ``../shared/data`` beside the repository (never copied in).
Tests that read it carry ``@pytest.mark.realdata`` and use :func:`shared_data`,
which skips with a clear reason when the folder (or the file) is absent.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

if os.environ.get("PYTEST_XDIST_WORKER"):
    # one pytest-xdist worker per core: each runs its kernels and BLAS on one thread (no oversubscription);
    # set before numba or numpy is imported by a test module
    for _var in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(_var, "1")

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
