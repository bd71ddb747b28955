"""sample_aoi's pair-DEMs, computed once and cached (pytest's cache folder, keyed by what makes them).

The change-detection figures of the README and docs are pinned by fast tests: everything after the
stereo (a few seconds per run) runs on the committed scene's pair-DEMs, which are computed with the
default ``geocd run`` stereo the first time (about a minute) and reused until the stereo or camera
code, the images or the manifest change.
"""

from __future__ import annotations

import fcntl
import hashlib
import os
import shutil
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
#: what the pair-DEMs depend on
_INPUTS = (
    "geocd/stereo",
    "geocd/camera",
    "geocd/io",
    "geocd/geodesy.py",
    "geocd/pipeline.py",  # RunConfig's stereo
    "sample_aoi/scene.yaml",
    "sample_aoi/images",
    "sample_aoi/truth/dem_prior.tif",
)


def cache_key() -> str:
    h = hashlib.sha1()
    for item in _INPUTS:
        p = REPO / item
        files = sorted(p.rglob("*")) if p.is_dir() else [p]
        for f in files:
            if f.is_file() and "__pycache__" not in f.parts and f.suffix not in (".pyc", ".nbi", ".nbc"):
                h.update(str(f.relative_to(REPO)).encode())
                h.update(f.read_bytes())
    return h.hexdigest()[:16]


def sample_aoi_pairs(cache_root: Path):
    """(manifest, {epoch: [PairDEM]}, grid) of sample_aoi with ``geocd run``'s default stereo."""
    from geocd.io.manifest import load_manifest
    from geocd.pipeline import RunConfig
    from geocd.stereo import read_pair_dem
    from geocd.stereo.pipeline import run_stereo

    m = load_manifest(REPO / "sample_aoi")
    key_dir = Path(cache_root) / cache_key()
    # one process computes, the others (pytest-xdist workers) wait for it and read its result
    with open(Path(cache_root) / ".lock", "a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            if not (key_dir / "done").is_file():
                tmp = Path(cache_root) / f".tmp-{os.getpid()}"
                shutil.rmtree(tmp, ignore_errors=True)
                cfg = RunConfig()
                run_stereo(
                    m,
                    epochs=[e.name for e in m.epochs],
                    out_dir=tmp,
                    params=cfg.stereo,
                    posting_m=cfg.posting_m,
                    pairs=cfg.pairs,
                )
                (tmp / "done").write_text("ok")
                shutil.rmtree(key_dir, ignore_errors=True)
                os.replace(tmp, key_dir)
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)
    by: dict[str, list] = {}
    for f in sorted((key_dir / "stereo").rglob("*.tif")):
        p = read_pair_dem(f)
        by.setdefault(p.epoch, []).append(p)
    return m, by, next(iter(by.values()))[0].grid
