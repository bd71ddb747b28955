"""Regenerate every picture README.md and docs/ show, from fresh runs: ``python -m bench.figures``.

Usage (from the repository root)::

    .venv/bin/python -m bench.figures --list                 # every entry: pictures, script, data, cost, status
    .venv/bin/python -m bench.figures --quick                # the cheap entries only (a few minutes each)
    .venv/bin/python -m bench.figures --only NAME [NAME ...] # entries by name, or by the picture they write
    .venv/bin/python -m bench.figures                        # everything (hours: the slow entries included)

Each entry (:mod:`bench.figures.registry`) runs its steps from the repository root into ``--work`` (the
entries it needs run first, once per invocation), then every picture it wrote is stamped
(:mod:`bench.figures.stamp`: a grey footer line and PNG text metadata with the command, the data and the date).
An entry whose data (``../shared/data``) or tool (QGIS, ``xvfb-run``, CARS) is absent is skipped with the reason;
one without a script is listed as such. What each entry took is recorded in ``bench/results/figures.json``.
``--reuse`` keeps the finished runs other entries need (``--work``) instead of running them again.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

from .registry import ENTRIES, Entry, by_name, pictures
from .stamp import stamp

REPO = Path(__file__).resolve().parents[2]
DOCS = REPO / "docs"
RESULTS = REPO / "bench" / "results" / "figures.json"


def data_root() -> Path:
    """``$GEOCD_SHARED_DATA``, else ``../shared/data`` beside the repository."""
    return Path(os.environ.get("GEOCD_SHARED_DATA", REPO.parent / "shared" / "data"))


def qgis_python() -> str:
    """The system Python with PyQGIS."""
    return os.environ.get("GEOCD_QGIS_PYTHON", "/usr/bin/python3")


def tool_missing(tool: str) -> str | None:
    """Why a tool is not usable here (None: it is)."""
    if tool == "qgis":
        if not Path("/usr/bin/qgis_process.bin").exists() and shutil.which("qgis_process") is None:
            return "QGIS is not installed (qgis_process not found)"
        py = qgis_python()
        ok = (
            subprocess.run([py, "-c", "import qgis.core"], capture_output=True).returncode == 0
            if Path(py).exists()
            else False
        )
        return None if ok else f"PyQGIS does not import in {py}"
    if tool == "xvfb-run":
        return None if shutil.which("xvfb-run") else "xvfb-run is not installed (apt-get install xvfb xauth)"
    if tool == "cars":
        return None if shutil.which("cars") else "CARS is not on PATH (docs/kahramanmaras.md: its own environment)"
    return None if shutil.which(tool) else f"{tool} not found"


def missing(entry: Entry, seen: set[str] | None = None) -> list[str]:
    """Why an entry cannot run here: absent data, tools or script, also of the entries it needs."""
    seen = set() if seen is None else seen
    if entry.name in seen:
        return []
    seen.add(entry.name)
    why = []
    if entry.script is None or not entry.steps:
        why.append("no script")
    for d in entry.data:
        if not (data_root() / d).is_dir():
            why.append(f"data {data_root() / d} absent")
    for t in entry.tools:
        m = tool_missing(t)
        if m:
            why.append(m)
    for n in entry.needs:
        why += [w for w in missing(by_name()[n], seen) if w not in why]
    return why


def _fill(text: str, entry: Entry, work: Path) -> str:
    return text.format(
        python=sys.executable,
        python_bin=str(Path(sys.executable).parent),
        geocd=f"{sys.executable} -m geocd --progress none",
        qgis_python=qgis_python(),
        work=str(work),
        docs=str(DOCS),
        data=str(data_root()),
        repo=str(REPO),
    )


def expand(step: tuple[str, ...], entry: Entry, work: Path) -> list[str]:
    """A step's argument list with the placeholders filled (``{geocd}`` becomes several arguments)."""
    out: list[str] = []
    for arg in step:
        filled = _fill(arg, entry, work)
        out += filled.split() if arg == "{geocd}" else [filled]
    return out


def command_line(entry: Entry) -> str:
    """The command that regenerates the entry's pictures (the stamp's)."""
    return f"python -m bench.figures --only {entry.name}"


def data_words(entry: Entry) -> str:
    """The data an entry reads, in words (the stamp's)."""
    return ", ".join(f"../shared/data/{d}" for d in entry.data) or "the repository (sample_aoi, examples)"


def git_commit() -> str:
    r = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True)
    dirty = subprocess.run(["git", "status", "--porcelain", "geocd"], cwd=REPO, capture_output=True, text=True)
    return r.stdout.strip() + ("+changes" if dirty.stdout.strip() else "")


def run_entry(entry: Entry, work: Path, log) -> dict:
    """Run an entry's steps, stamp its pictures; returns its record (status, seconds, pictures)."""
    t0 = time.time()
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), *filter(None, [env.get("PYTHONPATH")])])
    env.update({k: _fill(v, entry, work) for k, v in entry.env.items()})
    (work / entry.name).mkdir(parents=True, exist_ok=True)
    before = {p: (DOCS / p).stat().st_mtime if (DOCS / p).exists() else None for p in entry.pictures}
    for step in entry.steps:
        if step[0] == "copy":
            src, dst = (Path(_fill(s, entry, work)) for s in step[1:])
            log(f"  copy {src} → {dst}")
            shutil.copyfile(src, dst)
            continue
        argv = expand(step, entry, work)
        log("  $ " + " ".join(a if " " not in a else repr(a) for a in argv))
        with open(work / entry.name / "log.txt", "a") as out:
            out.write("$ " + " ".join(argv) + "\n")
            out.flush()
            rc = subprocess.run(argv, cwd=REPO, env=env, stdout=out, stderr=subprocess.STDOUT).returncode
        if rc != 0:
            return {
                "status": f"failed (exit {rc}; log {work / entry.name / 'log.txt'})",
                "seconds": round(time.time() - t0),
            }
    written, stale = [], []
    commit = git_commit()
    for p in entry.pictures:
        f = DOCS / p
        if f.exists() and (before[p] is None or f.stat().st_mtime > before[p]):
            stamp(f, command=command_line(entry), data=data_words(entry), shows=entry.shows, commit=commit)
            written.append(p)
        else:
            stale.append(p)
    rec = {
        "status": "done" if not stale else f"done, not written: {', '.join(stale)}",
        "seconds": round(time.time() - t0),
    }
    rec["pictures"] = written
    return rec


def print_list(out=sys.stdout) -> None:
    """The registry as a table: every picture, its entry, script, data, cost and whether it can run here."""
    rec = json.loads(RESULTS.read_text()) if RESULTS.exists() else {}
    rows = [("entry", "pictures (docs/)", "script", "cost", "minutes", "status here")]
    for e in ENTRIES:
        why = missing(e)
        last = rec.get(e.name, {})
        took = (
            f"{last['seconds'] / 60:.1f} (measured {last['date']})"
            if "seconds" in last and "date" in last
            else (f"{e.minutes:g} ({'measured' if e.measured else 'estimate'})")
        )
        rows.append(
            (
                e.name,
                ", ".join(e.pictures) or "; ".join(e.tables) or "(a run others need)",
                e.script or "NO SCRIPT",
                e.cost,
                took,
                "skipped: " + "; ".join(why) if why else "ready",
            )
        )
    w = [max(len(r[i]) for r in rows) for i in range(len(rows[0]) - 1)]
    for r in rows:
        print("  ".join(c.ljust(w[i]) for i, c in enumerate(r[:-1])) + "  " + r[-1], file=out)
    print(f"\n{len(pictures())} pictures in {len(ENTRIES)} entries; data from {data_root()}", file=out)
    for e in ENTRIES:
        if e.note:
            print(f"note on {e.name}: {e.note}", file=out)


def select(only: list[str], quick: bool) -> list[Entry]:
    """The entries asked for: by name or by picture file name; ``quick``: the quick ones of them."""
    names, pics = by_name(), pictures()
    if only:
        chosen = []
        for o in only:
            e = names.get(o) or pics.get(o) or pics.get(Path(o).name)
            if e is None:
                raise SystemExit(f"no entry or picture {o!r}: see --list")
            if e not in chosen:
                chosen.append(e)
    else:
        chosen = list(ENTRIES)
    return [e for e in chosen if e.cost == "quick"] if quick else chosen


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.figures", description=__doc__.splitlines()[0])
    ap.add_argument("--list", action="store_true", help="list the entries and whether each can run here")
    ap.add_argument("--only", nargs="+", default=[], metavar="NAME", help="entries (or pictures) to make")
    ap.add_argument("--quick", action="store_true", help="only the quick entries (of --only, if given)")
    ap.add_argument(
        "--work",
        type=Path,
        default=Path("geocd_out/figures"),
        help="work folder of the runs (default: ./geocd_out/figures)",
    )
    ap.add_argument("--dry-run", action="store_true", help="print the commands, run nothing")
    ap.add_argument(
        "--reuse",
        action="store_true",
        help="do not re-run an entry that others need when its work folder holds a finished run (default: re-run)",
    )
    args = ap.parse_args(argv)
    if args.list:
        print_list()
        return 0
    work = args.work.resolve()
    todo = select(args.only, args.quick)

    def log(msg: str) -> None:
        print(msg, flush=True)

    done: dict[str, dict] = {}
    failed = False

    def run(e: Entry, needed: bool = False) -> dict:
        if e.name in done:
            return done[e.name]
        if needed and args.reuse and (work / e.name / ".done").is_file():
            done[e.name] = {"status": "done (reused)"}
            log(f"[{e.name}] reused: {work / e.name}")
            return done[e.name]
        for n in e.needs:
            dep = run(by_name()[n], needed=True)
            if not dep["status"].startswith(("done", "dry run")):
                done[e.name] = {"status": f"skipped: {n} {dep['status']}"}
                return done[e.name]
        why = missing(e)
        if why:
            done[e.name] = {"status": "skipped: " + "; ".join(why)}
            log(f"[{e.name}] {done[e.name]['status']}")
            return done[e.name]
        log(f"[{e.name}] {', '.join(e.pictures) or '; '.join(e.tables) or '(run)'}")
        if args.dry_run:
            for s in e.steps:
                if s[0] == "copy":
                    log(f"  copy {_fill(s[1], e, work)} → {_fill(s[2], e, work)}")
                else:
                    log("  $ " + " ".join(expand(s, e, work)))
            done[e.name] = {"status": "dry run"}
            return done[e.name]
        done[e.name] = run_entry(e, work, log)
        log(f"[{e.name}] {done[e.name]['status']} in {done[e.name]['seconds']} s")
        return done[e.name]

    for e in todo:
        failed |= run(e)["status"].startswith("failed")
    if not args.dry_run:
        rec = json.loads(RESULTS.read_text()) if RESULTS.exists() else {}
        today = _dt.date.today().isoformat()
        for name, r in done.items():
            if "seconds" in r and r["status"] == "done":
                rec[name] = {"seconds": r["seconds"], "date": today, "pictures": r.get("pictures", [])}
                if by_name()[name].note:
                    rec[name]["note"] = by_name()[name].note
        RESULTS.write_text(json.dumps(dict(sorted(rec.items())), indent=1) + "\n")
    log("\nsummary:")
    for name, r in done.items():
        log(f"  {name}: {r['status']}" + (f" ({r['seconds']} s)" if "seconds" in r else ""))
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
