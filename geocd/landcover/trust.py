"""Which land-cover model files may be unpickled.

A model file is a joblib pickle, and unpickling a file can run any code its author put in it. geocd
therefore loads a model only when its sha256 is on this user's trust list — every model ``geocd
landcover train`` (:func:`~geocd.landcover.classifier.save_model`) writes is added — or when the
caller says it trusts the file (``--trust-model``, ``trust=True``), which prints a warning.

The list is one ``<sha256> <path>`` line per model, in ``$GEOCD_TRUSTED_MODELS`` when set, else
``$XDG_CACHE_HOME/geocd/trusted_models`` (``~/.cache/geocd/trusted_models``).
"""

from __future__ import annotations

import hashlib
import os
import warnings
from pathlib import Path

from ..errors import UntrustedFileError

#: environment variable naming the trust list file (tests, shared machines)
TRUST_ENV = "GEOCD_TRUSTED_MODELS"


def trust_list_path() -> Path:
    """The trust list file of this user (it need not exist yet)."""
    env = os.environ.get(TRUST_ENV)
    if env:
        return Path(env)
    cache = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(cache) / "geocd" / "trusted_models"


def sha256_of(data: bytes) -> str:
    """Hex sha256 of ``data``."""
    return hashlib.sha256(data).hexdigest()


def trusted_digests() -> set[str]:
    """The sha256 digests on the trust list (empty when there is no readable list)."""
    try:
        text = trust_list_path().read_text(encoding="utf-8", errors="replace")
    except OSError:
        return set()
    out = set()
    for line in text.splitlines():
        word = line.split(" ", 1)[0].strip().lower()
        if len(word) == 64 and all(c in "0123456789abcdef" for c in word):
            out.add(word)
    return out


def record_trusted(path: os.PathLike | str) -> bool:
    """Add the file ``path`` (just written by geocd) to the trust list; False, with a warning, if it cannot."""
    p = Path(path)
    lst = trust_list_path()
    try:
        line = f"{sha256_of(p.read_bytes())} {p.resolve()}\n".replace("\r", " ")
        lst.parent.mkdir(parents=True, exist_ok=True)
        # one short append: concurrent trainings do not interleave their lines
        fd = os.open(lst, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o600)
        try:
            os.write(fd, line.encode("utf-8", errors="replace"))
        finally:
            os.close(fd)
    except OSError as exc:
        warnings.warn(
            f"could not add {p} to the trusted-model list {lst} ({exc}); 'geocd landcover predict' "
            "will ask for --trust-model with it",
            stacklevel=2,
        )
        return False
    return True


def check_trusted(path: os.PathLike | str, digest: str, trust: bool = False) -> None:
    """Refuse a pickled model whose ``digest`` is not on the trust list, unless ``trust`` (then warn).

    Raises
    ------
    UntrustedFileError
        The file was not written by geocd for this user and ``trust`` is False.
    """
    if digest in trusted_digests():
        return
    risk = "a model file is a pickle, and loading it runs whatever code its author put in it"
    if trust:
        warnings.warn(
            f"loading the model {path}, which geocd did not write here, because it is trusted "
            f"explicitly (--trust-model): {risk}",
            stacklevel=2,
        )
        return
    raise UntrustedFileError(
        f"the model {path} was not written by 'geocd landcover train' for this user (its sha256 is not on the "
        f"trusted-model list {trust_list_path()}); {risk}: retrain it with 'geocd landcover train', or pass "
        "--trust-model (Python: trust=True) only if you trust whoever made the file"
    )


def check_model_file(path: os.PathLike | str, trust: bool = False) -> None:
    """:func:`check_trusted` of the file at ``path`` as it is now (a cheap check before any heavy work)."""
    check_trusted(path, sha256_of(Path(path).read_bytes()), trust)
