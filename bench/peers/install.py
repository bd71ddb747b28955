"""The peers' own virtual environments (never geocd's): where they live, whether they work, how to make them.

Each peer is installed once, with the ordinary ``pip`` of a fresh ``python -m venv``, under the peers folder
(``--peers-dir``, else ``$GEOCD_PEERS``, else ``~/.cache/geocd/peers``). GDAL is not installed: it is rasterio's
(geocd's own environment has it).
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path


@dataclass(frozen=True)
class Peer:
    """A peer installed in a virtual environment of its own.

    Attributes
    ----------
    name : str
        The peer's key (``cars``, ``xdem``).
    label : str
        How tables name it.
    venv : str
        Folder under the peers folder.
    requirements : tuple of str
        What ``pip install`` gets.
    package : str
        The distribution whose version is reported.
    exe : str
        The program run from the venv's ``bin/`` (``python`` for a library).
    """

    name: str
    label: str
    venv: str
    requirements: tuple[str, ...]
    package: str
    exe: str


PEERS: dict[str, Peer] = {
    "cars": Peer("cars", "CARS", "cars-1.3", ("cars==1.3.*",), "cars", "cars"),
    "xdem": Peer("xdem", "xDEM", "xdem", ("xdem", "scikit-gstat"), "xdem", "python"),
}


def peers_dir(arg: str | Path | None = None) -> Path:
    """The peers folder: ``arg``, else ``$GEOCD_PEERS``, else ``~/.cache/geocd/peers``."""
    if arg:
        return Path(arg).expanduser().resolve()
    env = os.environ.get("GEOCD_PEERS")
    return Path(env).expanduser().resolve() if env else Path.home() / ".cache" / "geocd" / "peers"


def executable(peer: Peer, root: Path) -> Path:
    """The peer's program in its venv (may not exist)."""
    return root / peer.venv / "bin" / peer.exe


@lru_cache(maxsize=None)
def version(peer: Peer, root: Path) -> str | None:
    """The installed version of the peer's package, None when the venv does not have it (cached: ask once)."""
    py = root / peer.venv / "bin" / "python"
    if not py.exists():
        return None
    r = subprocess.run(
        [str(py), "-c", f"import importlib.metadata as m; print(m.version({peer.package!r}))"],
        capture_output=True,
        text=True,
    )
    return r.stdout.strip() if r.returncode == 0 else None


def status(peer: Peer, root: Path) -> str | None:
    """Why the peer cannot run (None: it can)."""
    if not executable(peer, root).exists():
        return f"not installed ({executable(peer, root)} missing; `python -m bench.peers --install`)"
    if version(peer, root) is None:
        return f"{peer.package} does not import in {root / peer.venv}"
    return None


def base_python() -> str:
    """The interpreter the peers' venvs are made from (the one under geocd's venv, not the venv)."""
    base = getattr(sys, "_base_executable", None)
    return base if base and Path(base).exists() else sys.executable


def install(peer: Peer, root: Path, log=print) -> dict:
    """Create the peer's venv and ``pip install`` it (once: an existing working venv is kept).

    Returns
    -------
    dict
        ``status`` (``installed``, ``present`` or ``failed: ...``), ``seconds``, ``version``, the commands run.
    """
    if status(peer, root) is None:
        return {"status": "present", "version": version(peer, root)}
    venv = root / peer.venv
    root.mkdir(parents=True, exist_ok=True)
    cmds = [
        [base_python(), "-m", "venv", str(venv)],
        [str(venv / "bin" / "pip"), "install", "-q", "--upgrade", "pip"],
        [str(venv / "bin" / "pip"), "install", "-q", *peer.requirements],
    ]
    t = time.perf_counter()
    for c in cmds:
        log("  $ " + " ".join(c))
        r = subprocess.run(c, capture_output=True, text=True)
        if r.returncode != 0:
            tail = (r.stdout + r.stderr).strip()[-1500:]
            return {"status": f"failed (exit {r.returncode}): {tail}", "seconds": time.perf_counter() - t}
    version.cache_clear()
    why = status(peer, root)
    return {
        "status": "installed" if why is None else f"failed: {why}",
        "seconds": time.perf_counter() - t,
        "version": version(peer, root),
        "commands": [" ".join(c) for c in cmds],
    }
