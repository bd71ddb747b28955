"""Output folders: one run at a time, a product manifest with hashes, stale products replaced, kills cleaned up.

Real geocd processes (``geocd demdiff`` on two tiny DEMs, the cheapest command that writes a full product set)
are paused inside a write by tests/reliability/pause_driver.py, then signalled or raced.
"""

from __future__ import annotations

import json
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from click.testing import CliRunner

from geocd.cli import main
from geocd.io.outputs import LOCK_NAME, MANIFEST_NAME, read_products_manifest, verify_products

from .scenes import error_lines, part_files, sha256_tree, write_dem_pair

DRIVER = Path(__file__).with_name("pause_driver.py")
#: the child processes skip demdiff's region test, whose noise simulation (48 fields of 512², ~4 s of CPU) is
#: most of a child's time on these tiny DEMs: these tests look at the output folder, not at the regions
NO_REGION_TEST = ("--region-test", "off")


@pytest.fixture(scope="module")
def dems(tmp_path_factory):
    return write_dem_pair(tmp_path_factory.mktemp("dems"))


def _demdiff(a, b, out, *extra):
    return CliRunner().invoke(main, ["--progress", "none", "demdiff", str(a), str(b), "--out", str(out), *extra])


def _products(out: Path) -> set[str]:
    """Files in ``out`` but the product manifest and the command's log file (not products)."""
    return {
        p.relative_to(out).as_posix()
        for p in out.rglob("*")
        if p.is_file() and not (p.name.startswith("geocd_") and p.suffix == ".log")
    } - {MANIFEST_NAME}


def _start_paused(tmp: Path, args: list[str], nth: int = 1, tag: str = "p", hangup=signal.SIG_DFL):
    """``hangup``: the SIGHUP disposition the run starts with: the default, as from a terminal, whatever the
    test session inherited (under nohup it inherits SIG_IGN, which geocd keeps on purpose)."""
    flag, go = tmp / f"{tag}.paused", tmp / f"{tag}.go"
    proc = subprocess.Popen(
        [sys.executable, str(DRIVER), str(flag), str(go), str(nth), "--progress", "none", *args, *NO_REGION_TEST],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=lambda: signal.signal(signal.SIGHUP, hangup),
    )
    t0 = time.monotonic()
    while not flag.exists():
        if proc.poll() is not None:
            out, err = proc.communicate()
            pytest.fail(f"driver ended before pausing ({proc.returncode}):\n{err}")
        if time.monotonic() - t0 > 300:
            proc.kill()
            pytest.fail("driver did not reach the write in 300 s")
        time.sleep(0.05)
    return proc, Path(flag.read_text()), go


# --------------------------------------------------------------------------------------------------------------
# the product manifest and stale products
# --------------------------------------------------------------------------------------------------------------
@pytest.mark.slow
def test_manifest_lists_every_product_with_its_hash(dems, tmp_path):
    out = tmp_path / "O"
    r = _demdiff(*dems, out, "--no-plots")
    assert r.exit_code == 0, r.output
    doc = read_products_manifest(out)
    assert len(doc["runs"]) == 1
    run = doc["runs"][0]
    assert run["status"] == "complete" and run["command"] == "geocd demdiff" and run["products"][0] == "demdiff_*"
    assert set(run["files"]) == _products(out) - {LOCK_NAME}
    assert not (out / LOCK_NAME).exists()
    assert all(verify_products(out).values())
    (out / "demdiff_report.json").write_text("{}")
    v = verify_products(out)
    assert v["demdiff_report.json"] is False and sum(v.values()) == len(v) - 1


@pytest.mark.slow
def test_stale_products_of_an_older_run_are_replaced(dems, tmp_path):
    out = tmp_path / "O"
    assert _demdiff(*dems, out).exit_code == 0
    first = _products(out)
    assert "demdiff_dh.png" in first
    r = _demdiff(*dems, out, "--no-plots")
    assert r.exit_code == 0, r.output
    assert "removed 1 product(s) of an older run" in r.stderr and "demdiff_dh.png" in r.stderr
    assert _products(out) == first - {"demdiff_dh.png"}
    doc = read_products_manifest(out)
    assert len(doc["runs"]) == 1 and set(doc["runs"][0]["files"]) == _products(out)


@pytest.mark.slow
def test_a_product_the_user_changed_is_kept(dems, tmp_path):
    out = tmp_path / "O"
    assert _demdiff(*dems, out).exit_code == 0
    with open(out / "demdiff_dh.png", "ab") as f:
        f.write(b"annotated by hand")
    r = _demdiff(*dems, out, "--no-plots")
    assert r.exit_code == 0
    assert (out / "demdiff_dh.png").is_file()
    assert "changed since geocd wrote them" in r.stderr


@pytest.mark.slow
def test_products_of_another_kind_are_kept(dems, tmp_path):
    out = tmp_path / "O"
    assert _demdiff(*dems, out, "--no-plots").exit_code == 0
    first = _products(out)
    assert _demdiff(*dems, out, "--no-plots", "--prefix", "other").exit_code == 0
    assert first <= _products(out)
    assert len(read_products_manifest(out)["runs"]) == 2


@pytest.mark.slow
def test_an_output_folder_is_not_read_as_an_epoch(dems, tmp_path):
    from geocd.errors import ManifestError
    from geocd.io.manifest import discover_manifest

    assert _demdiff(*dems, tmp_path / "O", "--no-plots").exit_code == 0
    with pytest.raises(ManifestError, match="no images"):
        discover_manifest(tmp_path)


# --------------------------------------------------------------------------------------------------------------
# one run at a time
# --------------------------------------------------------------------------------------------------------------
@pytest.mark.slow
def test_a_locked_folder_is_refused_and_freed_when_the_holder_dies(dems, tmp_path):
    out = tmp_path / "O"
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import sys, time\nfrom geocd.io.outputs import open_outputs\n"
            f"open_outputs({str(out)!r}, command='geocd run')\nprint('locked', flush=True)\n"
            "time.sleep(120)\n",
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout.readline().strip() == "locked"
        before = sha256_tree(dems)
        r = _demdiff(*dems, out)
        assert r.exit_code == 2
        errs = error_lines(r.stderr)
        assert len(errs) == 1 and "is in use by `" in errs[0] and f"pid {holder.pid}" in errs[0], r.stderr
        assert _products(out) == {LOCK_NAME} and sha256_tree(dems) == before
    finally:
        holder.kill()
        holder.wait()
    r = _demdiff(*dems, out, "--no-plots")  # the kernel released the dead holder's lock
    assert r.exit_code == 0, r.output


@pytest.mark.slow
def test_concurrent_runs_never_mix(dems, tmp_path):
    """A run paused mid-write holds the folder: a second run with other settings is refused; the first completes."""
    out = tmp_path / "O"
    a, b = map(str, dems)
    first, part, go = _start_paused(tmp_path, ["demdiff", a, b, "--out", str(out), "--no-plots"], nth=2)
    try:
        assert part.exists() and part.parent == out
        r = subprocess.run(
            [
                sys.executable,
                "-m",
                "geocd",
                "--progress",
                "none",
                "demdiff",
                a,
                b,
                "--out",
                str(out),
                "--no-plots",
                "--confidence",
                "99",
                *NO_REGION_TEST,
            ],
            capture_output=True,
            text=True,
            timeout=300,
        )
        assert r.returncode == 2, r.stderr
        assert "is in use by" in error_lines(r.stderr)[0] and "Traceback" not in r.stderr
    finally:
        go.touch()
    o, e = first.communicate(timeout=300)
    assert first.returncode == 0, e
    doc = read_products_manifest(out)
    assert [r["status"] for r in doc["runs"]] == ["complete"]
    rep = json.loads((out / "demdiff_report.json").read_text())
    assert float(rep["confidence_level_pct"]) == 95.0  # the first run's settings, not a mix
    assert set(doc["runs"][0]["files"]) == _products(out) and all(verify_products(out).values())
    assert not part_files(tmp_path)


@pytest.mark.slow
def test_two_runs_started_together(dems, tmp_path):
    """Unsynchronised: each run either completes or is refused; the folder holds one complete set."""
    out = tmp_path / "O"
    a, b = map(str, dems)
    procs = [
        subprocess.Popen(
            [
                sys.executable,
                "-m",
                "geocd",
                "--progress",
                "none",
                "demdiff",
                a,
                b,
                "--out",
                str(out),
                "--no-plots",
                "--confidence",
                c,
                *NO_REGION_TEST,
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for c in ("95", "99")
    ]
    results = [(p.wait(timeout=300), p.communicate()[1]) for p in procs]
    assert all(rc in (0, 2) for rc, _ in results) and any(rc == 0 for rc, _ in results), results
    for rc, err in results:
        assert "Traceback" not in err
        if rc == 2:
            assert "is in use by" in err
    doc = read_products_manifest(out)
    assert [r["status"] for r in doc["runs"]] == ["complete"]
    rep = json.loads((out / "demdiff_report.json").read_text())
    assert f"{float(rep['confidence_level_pct']):g}" in doc["runs"][0]["argv"]
    assert all(verify_products(out).values()) and set(doc["runs"][0]["files"]) == _products(out)


# --------------------------------------------------------------------------------------------------------------
# signals and kills
# --------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "sig, code, word",
    [
        (signal.SIGTERM, 143, "stopped by SIGTERM"),
        (signal.SIGINT, 130, "interrupted (Ctrl-C)"),
        (signal.SIGHUP, 129, "stopped by SIGHUP"),
    ],
)
@pytest.mark.slow
def test_signal_mid_write_cleans_up(dems, tmp_path, sig, code, word):
    out = tmp_path / "O"
    a, b = map(str, dems)
    before = sha256_tree(dems)
    proc, part, go = _start_paused(tmp_path, ["demdiff", a, b, "--out", str(out), "--no-plots"], nth=2)
    assert part.exists()
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == code, err
    errs = error_lines(err)
    assert len(errs) == 1 and word in errs[0] and "Traceback" not in err, err
    assert not part_files(tmp_path), "a partial file survived"
    assert not (out / LOCK_NAME).exists()
    doc = read_products_manifest(out)
    assert [r["status"] for r in doc["runs"]] == ["interrupted"]
    assert len(doc["runs"][0]["files"]) == 1 and all(verify_products(out).values())
    assert sha256_tree(dems) == before


@pytest.mark.slow
def test_a_run_started_with_nohup_ignores_a_hangup(dems, tmp_path):
    """A run started with SIGHUP ignored (nohup) keeps ignoring it and completes."""
    out = tmp_path / "O"
    a, b = map(str, dems)
    proc, part, go = _start_paused(
        tmp_path, ["demdiff", a, b, "--out", str(out), "--no-plots"], nth=2, hangup=signal.SIG_IGN
    )
    proc.send_signal(signal.SIGHUP)
    time.sleep(0.5)
    assert proc.poll() is None, proc.communicate()[1]
    go.touch()
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 0, err
    assert [r["status"] for r in read_products_manifest(out)["runs"]] == ["complete"]
    assert all(verify_products(out).values()) and not part_files(tmp_path)


@pytest.mark.slow
def test_sigkill_litter_is_removed_by_the_next_run(dems, tmp_path):
    out = tmp_path / "O"
    a, b = map(str, dems)
    proc, part, go = _start_paused(tmp_path, ["demdiff", a, b, "--out", str(out), "--no-plots"], nth=2)
    proc.kill()
    proc.wait()
    assert part.exists() and part_files(out)  # what a SIGKILL leaves
    assert read_products_manifest(out)["runs"][0]["status"] == "running"
    r = _demdiff(a, b, out, "--no-plots")
    assert r.exit_code == 0, r.output
    assert "removed 1 partial file(s) left by an interrupted geocd run" in r.stderr
    assert "was killed after writing 1 product(s)" in r.stderr
    assert not part_files(tmp_path)
    doc = read_products_manifest(out)
    assert [x["status"] for x in doc["runs"]] == ["complete"] and all(verify_products(out).values())


def test_a_half_swapped_model_folder_is_put_back(tmp_path):
    """A kill between the two renames of atomic_dir leaves `.NAME.old` and no NAME: the next session restores it."""
    from geocd.io.outputs import open_outputs

    old = tmp_path / ".model.old"
    old.mkdir()
    (old / "model.json").write_text("{}")
    with open_outputs(None, files=[tmp_path / "model"], command="test"):
        pass
    assert (tmp_path / "model" / "model.json").is_file() and not old.exists()


# --------------------------------------------------------------------------------------------------------------
# a run that stops puts back what it replaced; a mixed folder is never called whole
# --------------------------------------------------------------------------------------------------------------
def _files(out: Path) -> dict[str, str]:
    """sha256 of the products (not the manifest, the log or the lock)."""
    return {
        k: v
        for k, v in sha256_tree([out]).items()
        if Path(k).name not in (MANIFEST_NAME, LOCK_NAME) and not Path(k).name.endswith(".log")
    }


@pytest.mark.slow
def test_an_interrupted_rerun_puts_the_earlier_set_back(dems, tmp_path):
    from geocd.io.outputs import PREV_DIR, check_product_set

    out = tmp_path / "O"
    a, b = map(str, dems)
    assert _demdiff(a, b, out, "--no-plots").exit_code == 0
    first = _files(out)
    proc, part, go = _start_paused(
        tmp_path, ["demdiff", a, b, "--out", str(out), "--no-plots", "--confidence", "99"], nth=3
    )
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 143, err
    assert re.search(r"put back [2-9] file\(s\) of an earlier run", err), err
    assert _files(out) == first, "the folder is not as the complete run left it"
    assert not (out / PREV_DIR).exists() and not part_files(tmp_path)
    st = check_product_set(out)
    assert st["valid"], st["problems"]
    assert [r["status"] for r in read_products_manifest(out)["runs"]] == ["complete"]


@pytest.mark.slow
def test_a_killed_rerun_is_never_called_whole_and_the_next_run_mends_it(dems, tmp_path):
    from geocd.io.outputs import check_product_set

    out = tmp_path / "O"
    a, b = map(str, dems)
    assert _demdiff(a, b, out, "--no-plots").exit_code == 0
    first = _files(out)
    proc, part, go = _start_paused(
        tmp_path, ["demdiff", a, b, "--out", str(out), "--no-plots", "--confidence", "99"], nth=3
    )
    proc.kill()
    proc.wait()
    # each file alone matches the run that wrote it, but the folder mixes two runs: not whole
    assert all(verify_products(out).values())
    st = check_product_set(out)
    assert not st["valid"] and any("killed after writing" in p for p in st["problems"]), st
    r = CliRunner().invoke(main, ["info", str(out)])
    assert r.exit_code == 1 and "products NOT whole" in r.output, r.output
    # the next session puts back what the killed run replaced before it writes anything
    from geocd.io.outputs import open_outputs

    with open_outputs(out, command="geocd demdiff", products=["nothing_*"]) as s:
        assert _files(out) == {**first, **{k: v for k, v in _files(out).items() if k not in first}}
        assert any(re.search(r"put back [2-9] file\(s\)", n) for n in s.notes), s.notes
    assert _demdiff(a, b, out, "--no-plots").exit_code == 0
    st = check_product_set(out)
    assert st["valid"], st["problems"]
    r = CliRunner().invoke(main, ["info", str(out)])
    assert r.exit_code == 0 and "products whole" in r.output, r.output
