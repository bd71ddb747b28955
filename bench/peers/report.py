"""The figures of ``python -m bench.peers``: the JSON (``bench/results/peers.json``), the console table, and the
README's table block rendered from the JSON (between ``<!-- peers:begin -->`` and ``<!-- peers:end -->``)."""

from __future__ import annotations

import datetime as _dt
import json
import os
import platform
import statistics
import subprocess
from pathlib import Path

from bench._memwatch import REPO

from .rows import ROWS, Row, by_name

JSON = REPO / "bench" / "results" / "peers.json"
README = REPO / "README.md"
BEGIN = "<!-- peers:begin -->"
END = "<!-- peers:end -->"
SCHEMA = 1


def machine(load_start: tuple[float, float, float]) -> dict:
    """The machine: cores, CPU model, load average at the start, Python, the commit of this repository."""
    model = ""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    r = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True)
    return {
        "cores": os.cpu_count(),
        "cpu": model,
        "loadavg_start": [round(v, 2) for v in load_start],
        "python": platform.python_version(),
        "platform": platform.platform(terse=True),
        "geocd_commit": r.stdout.strip(),
    }


def load(path: Path = JSON) -> dict:
    """The JSON (an empty document when there is none)."""
    if path.is_file():
        return json.loads(path.read_text(encoding="utf-8"))
    return {"schema": SCHEMA, "rows": []}


def merge(doc: dict, records: dict[str, dict]) -> dict:
    """``doc`` with the rows of ``records`` replaced or added, in the table's order."""
    rows = {r["name"]: r for r in doc.get("rows", [])}
    rows.update(records)
    return {
        "schema": SCHEMA,
        "about": "python -m bench.peers: geocd against its peers, side by side; paths in commands are "
        "{data} (../shared/data), {work} (the work folder), {peers} (the peers' venvs: ~/.cache/geocd/peers "
        "or $GEOCD_PEERS), . (the repository)",
        "rows": [rows[r.name] for r in ROWS if r.name in rows],
    }


def save(doc: dict, path: Path = JSON) -> None:
    """Write the JSON."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(doc, indent=1, ensure_ascii=False, default=float) + "\n", encoding="utf-8")


def _stats(values: list[float]) -> dict | None:
    return {"min": min(values), "median": statistics.median(values)} if values else None


def series(runs: list[dict], label: str) -> dict:
    """A series of runs of one contender: min and median CPU and wall seconds of the runs that succeeded, peak RSS."""
    ok = [r for r in runs if r.get("returncode", 0) == 0]
    rss = [r["peak_rss_mb"] for r in ok if r.get("peak_rss_mb")]
    keep = ("wall_s", "cpu_s", "cpu_s_rusage", "cpu_s_sampled", "peak_rss_mb", "returncode", "error_tail", "localize_s")
    return {
        "label": label,
        "n": len(ok),
        "failed": len(runs) - len(ok),
        "cpu_s": _stats([r["cpu_s"] for r in ok]),
        "wall_s": _stats([r["wall_s"] for r in ok]),
        "peak_rss_mb": max(rss) if rss else None,
        "runs": [{k: v for k, v in r.items() if k in keep} for r in runs],
    }


def ratio(num: dict | None, den: dict | None) -> dict | None:
    """``num`` over ``den`` of median CPU seconds (and of median wall seconds), None when either is missing."""
    if not num or not den or not num["cpu_s"] or not den["cpu_s"]:
        return None
    return {
        "cpu": num["cpu_s"]["median"] / max(den["cpu_s"]["median"], 1e-9),
        "wall": num["wall_s"]["median"] / max(den["wall_s"]["median"], 1e-9),
    }


def short_of(row: Row, rec: dict) -> list[str]:
    """What a row with a ratio falls short of: ``speed`` (the ratio against the goal), ``accuracy``."""
    out = []
    r = rec.get("ratio")
    if r is not None and row.op is not None:
        if not (r["cpu"] >= row.target if row.op == ">=" else r["cpu"] <= row.target):
            out.append("speed")
    if (rec.get("accuracy") or {}).get("ok") is False:
        out.append("accuracy")
    return out


def verdict(row: Row, rec: dict) -> str:
    """``goal met``, ``short``, ``no goal`` or ``blocked`` (no peer figure: the row's ``reason`` says why)."""
    if rec.get("ratio") is None:
        return "blocked"
    if row.op is None:
        return "no goal"
    return "short" if short_of(row, rec) else "goal met"


# ---------------------------------------------------------------------------------------------------- formatting
def secs(x: float) -> str:
    """Seconds with 2–3 significant digits."""
    if x >= 100:
        return f"{x:.0f}"
    if x >= 10:
        return f"{x:.1f}"
    if x >= 1:
        return f"{x:.2f}"
    return f"{x:.3f}"


def times(s: dict | None) -> str:
    """``12.9 s CPU (22.5 s wall, 0.67 GB)``: medians, and the peak RSS of the process tree when known."""
    if not s or not s.get("cpu_s"):
        return "—"
    rss = f", {s['peak_rss_mb'] / 1024:.2f} GB" if s.get("peak_rss_mb") else ""
    # the kernel counts only the descendants that were waited for (not a fork server's workers): say so when the
    # sampled tree's CPU is well above that account
    ru = [r["cpu_s_rusage"] for r in s.get("runs", []) if r.get("returncode", 0) == 0 and "cpu_s_rusage" in r]
    if ru and s["cpu_s"]["median"] > 1.2 * statistics.median(ru):
        rss += f"; {secs(statistics.median(ru))} s of it in the processes it waits for"
    return f"{secs(s['cpu_s']['median'])} s CPU ({secs(s['wall_s']['median'])} s wall{rss})"


def ratio_text(rec: dict) -> str:
    """The ratio of median CPU seconds: ``6.52×``."""
    r = rec.get("ratio")
    return f"{r['cpu']:.3g}×" if r else "—"


def peer_cell(rec: dict) -> str:
    """The peer's figure, or why there is none."""
    if rec.get("peer"):
        return f"{rec['peer']['label']}: {times(rec['peer'])}"
    return f"none: {rec.get('reason') or 'not measured'}"


def accuracy_cell(rec: dict) -> str:
    """geocd's accuracy figure; the peer's after a semicolon."""
    a = rec.get("accuracy") or {}
    parts = [a["geocd_text"]] if a.get("geocd_text") else []
    if a.get("peer_text"):
        parts.append(f"{(rec.get('peer') or {}).get('label', 'peer').split(' (')[0]} {a['peer_text']}")
    return "; ".join(parts) or "—"


def goal_cell(rec: dict) -> str:
    """The goal and whether this run met it."""
    v = rec["verdict"]
    if v == "no goal":
        return "—"
    why = short_of(by_name()[rec["name"]], rec) if v == "short" else []
    return f"{rec['goal']}: **{v}**" + (f" ({' and '.join(why)})" if why else "")


# ---------------------------------------------------------------------------------------------------- console
def console(records: list[dict]) -> str:
    """The table as printed at the end of a run: every row, min and median of CPU and wall, ratio, goal, accuracy."""
    lines = []
    for rec in records:
        lines.append(f"{rec['name']}: {rec['what']}")
        for key in ("geocd", "peer", "geocd_cold"):
            s = rec.get(key)
            if not s or not s.get("cpu_s"):
                continue
            rss = f", peak RSS {s['peak_rss_mb'] / 1024:.2f} GB" if s.get("peak_rss_mb") else ""
            lines.append(
                f"    {s['label']:<44s} CPU min {secs(s['cpu_s']['min']):>6s} median {secs(s['cpu_s']['median']):>6s} s"
                f" | wall min {secs(s['wall_s']['min']):>6s} median {secs(s['wall_s']['median']):>6s} s"
                f" ({s['n']} runs{', ' + str(s['failed']) + ' failed' if s['failed'] else ''}){rss}"
            )
        if not rec.get("peer"):
            lines.append(f"    peer: none: {rec.get('reason')}")
        r = rec.get("ratio")
        rt = f"ratio {r['cpu']:.3g}× CPU, {r['wall']:.3g}× wall ({rec['ratio_of']})" if r else "ratio —"
        lines.append(f"    {rt}; goal {rec['goal']}: {rec['verdict'].upper()}")
        rc = rec.get("ratio_to_geocd_cold")
        if rc:
            lines.append(f"    against geocd cold: {rc['cpu']:.3g}× CPU, {rc['wall']:.3g}× wall")
        lines.append(f"    accuracy: {accuracy_cell(rec)}")
    return "\n".join(lines)


# ---------------------------------------------------------------------------------------------------- README
def render(doc: dict) -> str:
    """The README's block (the lines between the markers) from the JSON."""
    recs = [r for r in doc.get("rows", []) if r["name"] in by_name()]
    if not recs:
        return "No figures yet: run `python -m bench.peers --install --readme`."
    dates = sorted({r["date"] for r in recs})
    loads = [r["machine"]["loadavg_start"][0] for r in recs]
    cores = sorted({r["machine"]["cores"] for r in recs})
    repeats = sorted({r["repeat"] for r in recs})
    cmds = sorted({r["command"] for r in recs})
    head = (
        f"Measured by {' and '.join(f'`{c}`' for c in cmds)} ({', '.join(dates)}; "
        f"{'/'.join(map(str, cores))} cores shared with other work, load {min(loads):.1f}–{max(loads):.1f} at the "
        f"start of each group): geocd and the peer in turn, {'/'.join(map(str, repeats))} runs each; median CPU "
        "seconds of the whole process tree (in-process rows: of the computation), with wall time and peak memory; "
        "the ratio is of median CPU seconds against the peer measured in the same run. Min, median, every run and "
        "the command lines: `bench/results/peers.json`."
    )
    out = [head, "", "| what | geocd | peer (same run) | ratio | goal | accuracy |", "|---|---|---|---|---|---|"]
    for rec in recs:
        cells = [rec["what"], times(rec["geocd"]), peer_cell(rec), ratio_text(rec), goal_cell(rec), accuracy_cell(rec)]
        out.append("| " + " | ".join(c.replace("|", "/") for c in cells) + " |")
    return "\n".join(out)


def readme_block(text: str) -> str | None:
    """The lines between the markers of a README's text (None when the markers are absent)."""
    if BEGIN not in text or END not in text:
        return None
    return text.split(BEGIN, 1)[1].split(END, 1)[0].strip("\n")


def rewrite_readme(doc: dict, path: Path = README) -> bool:
    """Replace the README's block by :func:`render`; True when the file changed."""
    text = path.read_text(encoding="utf-8")
    if readme_block(text) is None:
        raise SystemExit(f"{path} has no {BEGIN} … {END} block")
    before, rest = text.split(BEGIN, 1)
    after = rest.split(END, 1)[1]
    new = f"{before}{BEGIN}\n{render(doc)}\n{END}{after}"
    if new != text:
        path.write_text(new, encoding="utf-8")
    return new != text


def today() -> str:
    """The date of a run."""
    return _dt.date.today().isoformat()
