"""Labelled real-data harness of the 2-D methods: ``geocd mpp`` and ``geocd screen`` on the real building-change
pairs, run through the CLI as a user would, scored per pair, per data set and pooled.

Data (``../shared/data``; read-only, see the SOURCE.md files there):

* ``levircd_samples`` — five LEVIR-CD 256² crops, 0.5 m (``train_386`` has no change: the control pair);
* ``levircd`` — four LEVIR-CD 1024² tiles, 0.5 m;
* ``whucd`` — two WHU-CD 1024² tiles, 0.3 m;
* ``dsifn`` — six DSIFN-CD 256² crops, ~2 m: general land-cover change, so scored for the screen only.

Labels are 0/255 PNGs, 255 = change (buildings built or demolished; DSIFN: any land-cover change).

Methods and products:

* ``mpp``: ``geocd mpp --image-a A --image-b B --pixel-size S --out DIR``; the change mask is the new (3) ∪
  demolished (2) cells of ``mpp_buildings.tif``;
* ``screen``: ``geocd screen A B --pixel-size S --out DIR`` plus a threshold rule that uses no label of the set
  being scored (:data:`SCREEN_RULES`); the change mask is ``screen_change_mask.tif`` = 1 (its no-data cells count
  as unchanged).

Scores (:func:`score_pair`, pooled by :func:`pool`):

* pixel precision / recall / F1 of the change mask against the label (pooled: the pixel counts summed);
* objects as :func:`geocd.mpp.evaluate.table2_change_only` counts them (the paper's Table 2, change-only
  labels): a changed object of the label is an 8-connected component of ≥ 40 label cells, **missed** (HV)
  when the change mask covers less than half of it, else found; a detected change object is an 8-connected
  component of the change mask, **false** (FV) when less than half of it lies on label change, else true.
  Object F1 = F1 of (true detected / detected, found / label objects);
* run time per pair: CPU seconds of the child process (user + system, from ``getrusage``) and wall seconds.
  numba kernels are cached after the first ``geocd mpp`` of a checkout (that first run compiles, ~20 s more).

Usage::

    nice -n 10 .venv/bin/python bench/eval_building_change.py --json bench/results/building_change.json
    # --sets levircd_samples,levircd,whucd,dsifn  --methods mpp,screen  --quick (one pair per set)
    # --dry-run (list the commands)  --markdown (print the tables of --json and stop)  --resume
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.bench_mpp import _png  # noqa: E402
from geocd.mpp.evaluate import _f, table2_change_only  # noqa: E402

DATA = ROOT.parent / "shared" / "data"
TILES = DATA / "building_change_tiles"
SAMPLES = DATA / "levircd_building_change_samples"

#: name -> (folder, pixel size m (SOURCE.md), building labels: scored by mpp too)
SETS: dict[str, tuple[Path, float, bool]] = {
    "levircd_samples": (SAMPLES, 0.5, True),
    "levircd": (TILES / "levircd", 0.5, True),
    "whucd": (TILES / "whucd", 0.3, True),
    "dsifn": (TILES / "dsifn", 2.0, False),
}
METHODS = ("mpp", "screen")
MIN_CELLS = 40
CONTROL = "train_386_0512_0768.png"  # the LEVIR-CD no-change control crop of levircd_samples


def _pair_files(folder: Path, name: str) -> tuple[Path, Path, Path]:
    return folder / "A" / name, folder / "B" / name, folder / "label" / name


#: the screen's threshold rule per set: never a label of the scored set.
#: levircd_samples: the best-F1 threshold of a labelled pair of another set (LEVIR-CD tile test_1, which no crop
#: of levircd_samples comes from); the others: the no-change rule (geocd's default, 99 % quantile) on the LEVIR-CD
#: control crop train_386 of levircd_samples, read at the scored set's pixel size.
SCREEN_RULES: dict[str, dict] = {
    "levircd_samples": {
        "labelled": _pair_files(TILES / "levircd", "test_1.png"),
        "text": "--labelled LEVIR-CD tile test_1 (set levircd): threshold of its best F1",
    },
    **{
        s: {
            "nochange": _pair_files(SAMPLES, CONTROL)[:2],
            "text": "--nochange LEVIR-CD control crop train_386 (set levircd_samples): 99 % quantile",
        }
        for s in ("levircd", "whucd", "dsifn")
    },
}


def list_pairs(sets: list[str], quick: bool = False) -> list[dict]:
    """The labelled pairs of ``sets``: dicts with set, name, a, b, label, pixel, mpp (building labels)."""
    out = []
    for s in sets:
        folder, px, buildings = SETS[s]
        names = sorted(p.name for p in (folder / "A").glob("*.png"))
        if quick:
            # one pair with change (not the control crop)
            names = [n for n in names if n != CONTROL][:1]
        for n in names:
            a, b, lab = _pair_files(folder, n)
            out.append({"set": s, "name": Path(n).stem, "a": a, "b": b, "label": lab, "pixel": px, "mpp": buildings})
    return out


def command(pair: dict, method: str, out: Path) -> list[str]:
    """The CLI call of ``method`` on ``pair`` writing to ``out`` (argv, without the interpreter)."""
    px = str(pair["pixel"])
    common = ["--pixel-size", px, "--out", str(out), "--progress", "none"]
    if method == "mpp":
        return ["geocd", "mpp", "--image-a", str(pair["a"]), "--image-b", str(pair["b"]), *common]
    rule = SCREEN_RULES[pair["set"]]
    extra: list[str] = []
    if "labelled" in rule:
        extra = ["--labelled", *map(str, rule["labelled"])]
    else:
        for p in rule["nochange"]:
            extra += ["--nochange", str(p)]
    return ["geocd", "screen", str(pair["a"]), str(pair["b"]), *extra, *common]


def read_label(path: Path) -> np.ndarray:
    """A 0/255 label PNG as a bool mask (True = change)."""
    lab = _png(path)
    return lab[0] > 0


def read_change_mask(method: str, out: Path) -> np.ndarray:
    """The change mask of a method's products in ``out``."""
    if method == "mpp":
        cls = _png(out / "mpp_buildings.tif")[0]
        return (cls == 2) | (cls == 3)
    return _png(out / "screen_change_mask.tif")[0] == 1


def score_pair(mask: np.ndarray, label: np.ndarray, min_cells: int = MIN_CELLS) -> dict:
    """Pixel counts and Table 2 change-object counts of one change mask against its label.

    Parameters
    ----------
    mask : bool array, the detected change
    label : bool array of the same shape, the label's change
    min_cells : int, the smallest label component that is an object

    Returns
    -------
    dict
        tp, fp, fn (pixels), precision, recall, f1, and objects: ``label_objects``, ``missed`` (HV), ``found``,
        ``detected``, ``false`` (FV), ``true``.
    """
    if mask.shape != label.shape:
        raise ValueError(f"change mask {mask.shape} and label {label.shape} differ")
    mask, label = mask.astype(bool), label.astype(bool)
    t2 = table2_change_only({"new": mask, "demolished": np.zeros_like(mask)}, label, min_cells)
    tp, fp, fn = int((mask & label).sum()), int((mask & ~label).sum()), int((~mask & label).sum())
    f = _f(tp, fp, fn)
    return {
        "tp": tp,
        "fp": fp,
        "fn": fn,
        "precision": f["precision"],
        "recall": f["recall"],
        "f1": f["f"],
        "label_objects": t2["changes"],
        "missed": t2["HV"],
        "found": t2["changes"] - t2["HV"],
        "detected": t2["detected_changes"],
        "false": t2["FV"],
        "true": t2["detected_changes"] - t2["FV"],
    }


def pool(rows: list[dict]) -> dict:
    """Pixel and object counts summed over ``rows`` (from :func:`score_pair`), their P/R/F1 and object F1."""
    keys = ("tp", "fp", "fn", "label_objects", "missed", "found", "detected", "false", "true")
    s = {k: int(sum(r[k] for r in rows)) for k in keys}
    f = _f(s["tp"], s["fp"], s["fn"])
    op = s["true"] / s["detected"] if s["detected"] else 0.0
    orc = s["found"] / s["label_objects"] if s["label_objects"] else 0.0
    s.update(
        pairs=len(rows),
        precision=f["precision"],
        recall=f["recall"],
        f1=f["f"],
        object_precision=round(op, 4),
        object_recall=round(orc, 4),
        object_f1=round(2 * op * orc / (op + orc), 4) if op + orc else 0.0,
    )
    for k in ("cpu_s", "wall_s"):
        if all(k in r for r in rows) and rows:
            s[f"{k}_mean"] = round(float(np.mean([r[k] for r in rows])), 1)
    return s


def run_pair(pair: dict, method: str, work: Path) -> dict:
    """Run ``method`` on ``pair`` through the CLI (a child process), read its products and score them."""
    out = work / method / pair["set"] / pair["name"]
    if out.exists():
        shutil.rmtree(out)
    argv = command(pair, method, out)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]).rstrip(":"))
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    p = subprocess.run([sys.executable, "-m", *argv], env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)
    if p.returncode:
        raise RuntimeError(f"{' '.join(argv)} failed ({p.returncode}):\n{p.stderr[-2000:]}")
    row = {"set": pair["set"], "pair": pair["name"], "method": method, "pixel_m": pair["pixel"]}
    row.update(score_pair(read_change_mask(method, out), read_label(pair["label"])))
    row.update(cpu_s=round(cpu, 1), wall_s=round(wall, 1), cells=list(read_label(pair["label"]).shape))
    if method == "screen":
        summ = json.loads((out / "screen_summary.json").read_text())
        row["threshold"] = summ.get("threshold")
    return row


def summarise(rows: list[dict], methods, sets) -> dict:
    """Per method: per set pooled and all sets pooled."""
    out = {}
    for m in methods:
        mr = [r for r in rows if r["method"] == m]
        if not mr:
            continue
        out[m] = {s: pool([r for r in mr if r["set"] == s]) for s in sets if any(r["set"] == s for r in mr)}
        out[m]["all"] = pool(mr)
    return out


def render(doc: dict) -> str:
    """Markdown tables of a result document: per method, per set pooled and all sets pooled."""
    lines = []
    for m, per in doc["summary"].items():
        lines += [
            f"**{m}** — `{doc['command']}`",
            "",
            "| set | pairs | pixel P | pixel R | pixel F1 | label objects: missed / found | detected: false / true "
            "| object F1 | CPU s / pair | wall s / pair |",
            "|---|---|---|---|---|---|---|---|---|---|",
        ]
        for s, p in per.items():
            name = "**pooled**" if s == "all" else s
            lines.append(
                f"| {name} | {p['pairs']} | {p['precision']:.3f} | {p['recall']:.3f} | {p['f1']:.3f} "
                f"| {p['label_objects']}: {p['missed']} / {p['found']} | {p['detected']}: {p['false']} / {p['true']} "
                f"| {p['object_f1']:.3f} | {p.get('cpu_s_mean', '')} | {p.get('wall_s_mean', '')} |"
            )
        if m == "screen":
            lines += ["", "Threshold rule per set (no label of the scored set):", ""]
            lines += [f"* {s}: {t}" for s, t in doc.get("screen_rules", {}).items()]
        lines.append("")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sets", default=",".join(SETS), help="comma-separated sets (default all)")
    ap.add_argument("--methods", default=",".join(METHODS), help="mpp,screen (default both)")
    ap.add_argument("--json", type=Path, default=ROOT / "bench" / "results" / "building_change.json")
    ap.add_argument("--markdown", action="store_true", help="print the tables of --json and stop")
    ap.add_argument("--quick", action="store_true", help="one changed pair per set")
    ap.add_argument("--dry-run", action="store_true", help="list the commands it would run and stop")
    ap.add_argument("--resume", action="store_true", help="keep the rows already in --json, run the others")
    ap.add_argument("--work", type=Path, default=None, help="folder for the products (default: a temporary one)")
    a = ap.parse_args(argv)
    if a.markdown:
        print(render(json.loads(a.json.read_text())))
        return 0
    sets = [s.strip() for s in a.sets.split(",") if s.strip()]
    methods = [m.strip() for m in a.methods.split(",") if m.strip()]
    bad = [s for s in sets if s not in SETS] + [m for m in methods if m not in METHODS]
    if bad:
        ap.error(f"unknown set or method: {', '.join(bad)}")
    pairs = list_pairs(sets, a.quick)
    # the screen first (seconds a pair), then the MPP (minutes a 1024² pair); the pairs round-robin over the sets
    # (every set's first pair, then every set's second, ...), so a run stopped early has scored each set
    rank = {id(p): sum(q["set"] == p["set"] for q in pairs[:k]) for k, p in enumerate(pairs)}
    pairs = sorted(pairs, key=lambda p: rank[id(p)])
    jobs = [(m, p) for m in sorted(methods, key=lambda m: m != "screen") for p in pairs if m == "screen" or p["mpp"]]
    work = a.work or Path(tempfile.mkdtemp(prefix="geocd_building_change_"))
    if a.dry_run:
        for m, p in jobs:
            print(" ".join(command(p, m, work / m / p["set"] / p["name"])))
        return 0
    rows: list[dict] = []
    if a.resume and a.json.exists():
        rows = json.loads(a.json.read_text()).get("pairs", [])
    done = {(r["method"], r["set"], r["pair"]) for r in rows}
    args = list(argv if argv is not None else sys.argv[1:])
    if "--work" in args:  # where the products went does not change a figure
        del args[args.index("--work") : args.index("--work") + 2]
    cmdline = "python bench/eval_building_change.py " + " ".join(args)
    doc = {
        "command": cmdline.strip(),
        "sets": {s: {"folder": str(SETS[s][0].relative_to(DATA.parent.parent)), "pixel_m": SETS[s][1]} for s in sets},
        "screen_rules": {s: SCREEN_RULES[s]["text"] for s in sets},
        "min_cells": MIN_CELLS,
        "cpu_count": os.cpu_count(),
        "load_average_start": [round(x, 2) for x in os.getloadavg()],
    }
    for m, p in jobs:
        if (m, p["set"], p["name"]) in done:
            continue
        row = run_pair(p, m, work)
        rows.append(row)
        print(json.dumps(row), flush=True)
        doc.update(
            pairs=rows, summary=summarise(rows, methods, sets), load_average_end=[round(x, 2) for x in os.getloadavg()]
        )
        a.json.parent.mkdir(parents=True, exist_ok=True)
        a.json.write_text(json.dumps(doc, indent=1) + "\n")
    doc.update(pairs=rows, summary=summarise(rows, methods, sets))
    print(render(doc))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
