"""sample_aoi's pair-DEMs and its ``geocd run`` answer, computed once and cached (pytest's cache folder, keyed by
what makes them).

The change-detection figures of the README and docs are pinned by fast tests: everything after the
stereo (a few seconds per run) runs on the committed scene's pair-DEMs. Both come from one call of
:func:`geocd.pipeline.run` on the scene with the default configuration (about a minute and a half), whose
pair-DEMs are kept until the stereo or camera code, the images or the manifest change, and whose answer
(grid, change result, building layer) until anything of the package or the scene changes.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import os
import pickle
import platform
import shutil
from importlib import metadata
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
#: what the pair-DEMs depend on
_INPUTS = (
    "geocd/stereo",
    "geocd/camera",
    "geocd/io",
    "geocd/orientation",
    "geocd/geodesy.py",
    "geocd/pipeline.py",  # RunConfig's stereo
    "tests/sample_aoi_cache.py",
    "sample_aoi/scene.yaml",
    "sample_aoi/images",
    "sample_aoi/truth/dem_prior.tif",
)
#: what the run's answer depends on: the whole package and scene
_RUN_INPUTS = ("geocd", "sample_aoi", "tests/sample_aoi_cache.py")
#: libraries whose versions are part of the keys
_LIBRARIES = ("numpy", "scipy", "numba", "rasterio", "shapely", "geopandas", "pyproj", "pyogrio", "scikit-image")
#: the run's answer kept: what the end-to-end test reads of it
_ANSWER = ("grid", "result", "buildings")


def _key(items) -> str:
    h = hashlib.sha1()
    for name in _LIBRARIES:
        try:
            h.update(f"{name}=={metadata.version(name)}".encode())
        except metadata.PackageNotFoundError:
            h.update(f"{name} absent".encode())
    h.update(platform.python_version().encode())
    for item in items:
        p = REPO / item
        files = sorted(p.rglob("*")) if p.is_dir() else [p]
        for f in files:
            if f.is_file() and "__pycache__" not in f.parts and f.suffix not in (".pyc", ".nbi", ".nbc"):
                h.update(str(f.relative_to(REPO)).encode())
                h.update(f.read_bytes())
    return h.hexdigest()[:16]


def cache_key() -> str:
    """Key of the pair-DEMs."""
    return _key(_INPUTS)


def run_key() -> str:
    """Key of the run's answer."""
    return "run-" + _key(_RUN_INPUTS)


@contextlib.contextmanager
def _locked(cache_root: Path):
    # one process computes, the others (pytest-xdist workers) wait for it and read its result
    with open(Path(cache_root) / ".lock", "a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)


def _compute(cache_root: Path) -> None:
    """``geocd run`` of sample_aoi (default configuration): its answer under :func:`run_key`, its pair-DEMs
    under :func:`cache_key` (the same stereo as ``run_stereo`` with ``RunConfig()``'s parameters gives)."""
    from geocd.pipeline import run

    cache_root = Path(cache_root)
    tmp = cache_root / f".tmp-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    res = run(REPO / "sample_aoi", out_dir=tmp / "run")
    with open(tmp / "answer.pkl", "wb") as f:
        pickle.dump({k: res[k] for k in _ANSWER}, f)
    stereo_dir = cache_root / cache_key()
    if not (stereo_dir / "done").is_file():
        st = cache_root / f".tmp-stereo-{os.getpid()}"
        shutil.rmtree(st, ignore_errors=True)
        st.mkdir()
        shutil.copytree(tmp / "run" / "stereo", st / "stereo")
        (st / "done").write_text("ok")
        shutil.rmtree(stereo_dir, ignore_errors=True)
        os.replace(st, stereo_dir)
    shutil.rmtree(tmp / "run")
    (tmp / "done").write_text("ok")
    for old in cache_root.glob("run-*"):  # answers of earlier versions (about 13 MB each)
        shutil.rmtree(old, ignore_errors=True)
    os.replace(tmp, cache_root / run_key())


def sample_aoi_pairs(cache_root: Path):
    """(manifest, {epoch: [PairDEM]}, grid) of sample_aoi with ``geocd run``'s default stereo."""
    from geocd.io.manifest import load_manifest
    from geocd.stereo import read_pair_dem

    m = load_manifest(REPO / "sample_aoi")
    key_dir = Path(cache_root) / cache_key()
    with _locked(cache_root):
        if not (key_dir / "done").is_file():
            _compute(cache_root)
    by: dict[str, list] = {}
    for f in sorted((key_dir / "stereo").rglob("*.tif")):
        p = read_pair_dem(f)
        by.setdefault(p.epoch, []).append(p)
    return m, by, next(iter(by.values()))[0].grid


def sample_aoi_run(cache_root: Path) -> dict:
    """``geocd.pipeline.run(sample_aoi)``'s answer with the default configuration: {grid, result, buildings}."""
    run_dir = Path(cache_root) / run_key()
    with _locked(cache_root):
        if not (run_dir / "done").is_file():
            _compute(cache_root)
    with open(run_dir / "answer.pkl", "rb") as f:
        return pickle.load(f)
