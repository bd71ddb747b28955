"""geocd against its peers, side by side, in one run: ``python -m bench.peers``.

Usage (from the repository root)::

    .venv/bin/python -m bench.peers --list                    # the rows, their peers and goals, whether each can run
    .venv/bin/python -m bench.peers --install                 # create the peers' venvs once, then measure every row
    .venv/bin/python -m bench.peers [--repeat 3] [--only ROW ...] [--readme]
    .venv/bin/python -m bench.peers --dry-run                 # the command lines, nothing run
    .venv/bin/python -m bench.peers --readme --no-measure     # README's table from bench/results/peers.json

Each row runs geocd and its peer in turn (geocd, peer, geocd, peer …) ``--repeat`` times and records the min and
median CPU seconds and wall of each (whole process tree, or the computation for the in-process rows), the peak
RSS of the process tree, the ratio against the peer measured in the same run, whether the goal of issue 45 is
met, and the accuracy beside (NMAD and completeness against s2p's DSM, volume ± σ against xDEM's, localization
error). Cold means a new empty ``NUMBA_CACHE_DIR`` for that process. A peer that is not installed or fails leaves
its row without a peer figure and says why. The figures go to ``--json`` (rows measured again replace theirs);
``--readme`` rewrites README.md's table block from that file. CARS and xDEM live in venvs of their own under
``--peers-dir`` (``$GEOCD_PEERS``, default ``~/.cache/geocd/peers``); GDAL is rasterio's, in geocd's venv.
"""

from __future__ import annotations

import argparse
import os
import shlex
import sys
import time
import traceback
from pathlib import Path

from bench._memwatch import REPO

from .install import PEERS, install, peers_dir, status
from .report import (
    JSON,
    README,
    console,
    load,
    machine,
    merge,
    readme_block,
    render,
    rewrite_readme,
    save,
    series,
    today,
)
from .rows import GROUPS, ROWS, groups_for, rows_of


def data_root() -> Path:
    """``$GEOCD_SHARED_DATA``, else ``../shared/data`` beside the repository."""
    return Path(os.environ.get("GEOCD_SHARED_DATA", REPO.parent / "shared" / "data"))


def print_list(root: Path, data: Path, doc: dict) -> None:
    """Every row: its group, peer (and whether it is installed), goal, rough minutes, and its last verdict."""
    last = {r["name"]: r for r in doc.get("rows", [])}
    for g in GROUPS:
        rows = rows_of(g)
        print(f"[{g}] about {sum(r.minutes for r in rows):g} min with --repeat 3")
        for r in rows:
            peer = "geocd warm (no peer)" if r.peer is None else r.peer
            why = status(PEERS[r.peer], root) if r.peer in PEERS else None
            missing = [d for d in r.data if not (data / d).exists()]
            state = "; ".join(filter(None, [why, *(f"data {data / d} absent" for d in missing)])) or "ready"
            seen = last.get(r.name)
            was = f"last: {seen['verdict']} ({seen['date']})" if seen else "not measured yet"
            print(f"  {r.name:<24s} {r.what}\n      peer {peer}; goal {r.goal}; {state}; {was}")
    print(f"\n{len(ROWS)} rows in {len(GROUPS)} groups; peers in {root}; data in {data}")


def failed_records(group: str, why: str, ctx) -> dict[str, dict]:
    """Records for a group that could not be measured (no figures, the reason)."""
    out = {}
    for r in rows_of(group):
        out[r.name] = {
            "name": r.name,
            "what": r.what,
            "goal": r.goal,
            "accuracy_goal": r.accuracy_goal,
            "data": list(r.data),
            "commands": ctx.commands.get(group, {}),
            "geocd": series([], "geocd"),
            "peer": None,
            "reason": why,
            "ratio": None,
            "accuracy": {"ok": None},
            "verdict": "blocked",
        }
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.peers", description=__doc__.splitlines()[0])
    ap.add_argument("--list", action="store_true", help="the rows and whether each can run here")
    ap.add_argument("--dry-run", action="store_true", help="print the command lines, run nothing")
    ap.add_argument("--install", action="store_true", help="create the peers' venvs that are missing (once)")
    ap.add_argument("--no-measure", action="store_true", help="measure nothing (with --install / --readme)")
    ap.add_argument("--repeat", type=int, default=3, help="rounds of geocd and peer per row (default 3)")
    ap.add_argument("--only", nargs="+", default=[], metavar="ROW", help="rows or groups to measure (default all)")
    ap.add_argument("--peers-dir", default=None, help="the peers' venvs (default $GEOCD_PEERS or ~/.cache/geocd/peers)")
    ap.add_argument("--work", type=Path, default=Path("geocd_out/peers"), help="work folder (default geocd_out/peers)")
    ap.add_argument(
        "--json", type=Path, default=JSON, help=f"the figures (default {JSON.relative_to(JSON.parents[2])})"
    )
    ap.add_argument("--readme", action="store_true", help="rewrite README.md's table block from --json")
    ap.add_argument("--check-readme", action="store_true", help="exit 1 when README.md's block differs from --json")
    args = ap.parse_args(argv)
    root, data = peers_dir(args.peers_dir), data_root()

    def log(msg: str) -> None:
        print(msg, flush=True)

    if args.list:
        print_list(root, data, load(args.json))
        return 0
    groups = groups_for(args.only)
    if args.dry_run or not args.no_measure:
        # measuring imports geocd and the benchmarks (seconds): --list, --install and --readme do without
        from .measure import Context, commands, measure

        ctx = Context(max(1, args.repeat), args.work.resolve(), root, data, log)
    if args.dry_run:
        log(f"placeholders: {{data}} = {data}, {{work}} = {ctx.work}, {{peers}} = {root}, . = {REPO}")
        for g in groups:
            log(f"[{g}] rows {', '.join(r.name for r in rows_of(g))}; {args.repeat} rounds")
            for k, v in commands(ctx, g).items():
                log(f"  {k}: {v}")
        return 0
    if args.install:
        wanted = {r.peer for g in groups for r in rows_of(g) if r.peer in PEERS}
        for name in sorted(wanted):
            log(f"[install {name}] in {root / PEERS[name].venv}")
            log(f"  {install(PEERS[name], root, log=log)}")
    if not args.no_measure:
        if args.repeat < 3:
            log(f"note: --repeat {args.repeat}: the figures for the README want at least 3 runs each")
        invocation = shlex.join(["python", "-m", "bench.peers", *(argv if argv is not None else sys.argv[1:])])
        t_all = time.perf_counter()
        measured: dict[str, dict] = {}
        for g in groups:
            load0 = os.getloadavg()
            t0 = time.perf_counter()
            log(f"[{g}] {', '.join(r.name for r in rows_of(g))}")
            missing = sorted({d for r in rows_of(g) for d in r.data if not (data / d).exists()})
            if missing:
                recs = failed_records(g, f"data absent: {', '.join(missing)}", ctx)
            else:
                try:
                    recs = measure(ctx, g)
                except Exception as exc:  # one group's failure leaves the other rows measured
                    traceback.print_exc()
                    recs = failed_records(g, f"bench.peers failed: {type(exc).__name__}: {exc}", ctx)
            m = machine(load0)
            m["loadavg_end"] = [round(v, 2) for v in os.getloadavg()]
            for rec in recs.values():
                rec.update(
                    date=today(),
                    machine=m,
                    repeat=ctx.repeat,
                    command=invocation,
                    group_minutes=round((time.perf_counter() - t0) / 60, 1),
                )
            measured.update(recs)
            save(merge(load(args.json), recs), args.json)
            log(console(list(recs.values())))
        log(f"\n===== all rows ({(time.perf_counter() - t_all) / 60:.1f} min) =====")
        log(console([measured[r.name] for r in ROWS if r.name in measured]))
        log(f"figures in {args.json}")
    if args.readme:
        changed = rewrite_readme(load(args.json))
        log(f"{README.name}: table block {'rewritten' if changed else 'unchanged'} from {args.json}")
    if args.check_readme:
        if readme_block(README.read_text(encoding="utf-8")) != render(load(args.json)):
            log(
                f"{README.name}'s table block differs from {args.json}: run python -m bench.peers --readme --no-measure"
            )
            return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
