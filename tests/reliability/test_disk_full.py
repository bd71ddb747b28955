"""Full disks, file-size limits and read-only file systems: a one-line error naming the fix, no partial file.

* ``ulimit -f`` (always available): the file-size limit stops the GeoPackage mid-write (EFBIG; SQLite only says
  "Failed to commit transaction").
* a real 100 kB tmpfs and a read-only remount, mounted in a private user + mount namespace (``unshare -rm``, no
  root needed); skipped with the reason where the kernel does not allow unprivileged namespaces.
"""

from __future__ import annotations

import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from geocd.io.outputs import read_products_manifest, verify_products

from .scenes import error_lines, part_files, sha256_tree, write_dem_pair

GEOCD = [sys.executable, "-m", "geocd", "--progress", "none"]


@pytest.fixture(scope="module")
def dems(tmp_path_factory):
    from click.testing import CliRunner

    from geocd.cli import main

    a, b = write_dem_pair(tmp_path_factory.mktemp("dems"))
    # compile (and cache) demdiff's numba kernels first: under a 64 kB `ulimit -f` numba could not save its cache
    warm = tmp_path_factory.mktemp("warm")
    r = CliRunner().invoke(main, ["--progress", "none", "demdiff", str(a), str(b), "--out", str(warm), "--no-plots"])
    assert r.exit_code == 0, r.output
    return a, b


def _sh(script: str, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run(["bash", "-c", script], capture_output=True, text=True, timeout=timeout)


def _check_failed_run(r: subprocess.CompletedProcess, out: Path, fragment: str, inputs_before: dict, dems) -> None:
    assert r.returncode == 2, r.stderr
    errs = error_lines(r.stderr)
    assert len(errs) == 1 and fragment in errs[0], r.stderr
    assert "Traceback" not in r.stderr + r.stdout
    assert not part_files(out.parent), "a partial file survived"
    assert not (out / "demdiff_changes.gpkg").exists(), "a half-made GeoPackage was left"
    assert sha256_tree(dems) == inputs_before
    doc = read_products_manifest(out)
    assert [x["status"] for x in doc["runs"]] == ["failed"]
    assert doc["runs"][0]["files"] and all(verify_products(out).values())  # what was written is complete


@pytest.mark.slow
def test_file_size_limit_mid_write(dems, tmp_path):
    out = tmp_path / "O"
    before = sha256_tree(dems)
    cmd = " ".join(shlex.quote(str(c)) for c in [*GEOCD, "demdiff", *dems, "--out", out, "--no-plots"])
    r = _sh(f"ulimit -f 64; exec {cmd}")
    _check_failed_run(r, out, "file size limit reached writing", before, dems)
    assert "demdiff_changes.gpkg" in error_lines(r.stderr)[0]


@pytest.fixture(scope="module")
def namespaces(tmp_path_factory):
    if shutil.which("unshare") is None:
        pytest.skip("unshare (util-linux) is not installed")
    d = tmp_path_factory.mktemp("probe")
    r = _sh(f"unshare --user --map-root-user --mount sh -c 'mount -t tmpfs -o size=64k tmpfs {d}'", timeout=60)
    if r.returncode != 0:
        pytest.skip(f"unprivileged user+mount namespaces are not allowed here ({r.stderr.strip()[:120]})")
    return True


def _in_tmpfs(mnt: Path, size: str, script: str) -> subprocess.CompletedProcess:
    inner = f"mount -t tmpfs -o size={size} tmpfs {shlex.quote(str(mnt))} && {script}"
    return _sh(f"unshare --user --map-root-user --mount bash -c {shlex.quote(inner)}")


@pytest.mark.slow
def test_disk_full_on_a_small_tmpfs(dems, tmp_path, namespaces):
    mnt = tmp_path / "mnt"
    mnt.mkdir()
    out = mnt / "O"
    before = sha256_tree(dems)
    cmd = " ".join(shlex.quote(str(c)) for c in [*GEOCD, "demdiff", *dems, "--out", out, "--no-plots"])
    # inspect inside the namespace (the tmpfs vanishes with it): copy what is left out to the real disk
    keep = tmp_path / "left"
    r = _in_tmpfs(mnt, "100k", f"{cmd}; rc=$?; cp -a {shlex.quote(str(out))} {shlex.quote(str(keep))}; exit $rc")
    assert r.returncode == 2, r.stderr
    assert "no space left on device writing" in error_lines(r.stderr)[0] and "kB free there" in r.stderr
    _check_failed_run(r, keep, "no space left on device", before, dems)


def test_read_only_file_system(dems, tmp_path, namespaces):
    mnt = tmp_path / "mnt"
    mnt.mkdir()
    geocd = " ".join(shlex.quote(str(c)) for c in [*GEOCD, "demdiff", *dems, "--no-plots", "--out"])
    script = (
        f"mkdir {mnt}/existing && mount -o remount,ro {mnt} && "
        f"{geocd} {mnt}/new/out; echo rc=$?; {geocd} {mnt}/existing; echo rc=$?"
    )
    r = _in_tmpfs(mnt, "1m", script)
    errs = error_lines(r.stderr)
    assert r.stdout.split() == ["rc=2", "rc=2"], r.stdout + r.stderr
    assert len(errs) == 2 and "Traceback" not in r.stderr
    assert f"{mnt}/new/out" in errs[0] and ("cannot be created" in errs[0] or "cannot create" in errs[0])
    assert f"{mnt}/existing" in errs[1] and ("read-only file system" in errs[1] or "not writable" in errs[1])
