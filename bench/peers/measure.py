"""The measuring groups of ``python -m bench.peers``: each runs geocd and its peer in turn (geocd, peer, geocd,
peer …), ``repeat`` rounds, and returns the records of its rows.

Everything is a call into the existing benchmarks (one code path): :mod:`bench.bench_stereo` (geocd's stereo
command, CARS's configuration and run, both DSMs against s2p's), :mod:`bench.bench_demdiff` (the MSH cases, masks,
geocd in process, the xDEM worker, ``geocd demdiff``), :mod:`bench.bench_rpc` (the points, one first localization
per process) and :func:`bench._memwatch.run_process` (wall, CPU and peak RSS of a process tree). A cold run gets a
new empty ``NUMBA_CACHE_DIR``; the warm run after it reuses that folder.
"""

from __future__ import annotations

import json
import shlex
import shutil
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from geocd.io.rpc import load_rpc_for_image

from bench import bench_demdiff, bench_rpc, bench_stereo
from bench._memwatch import REPO, geocd_command, geocd_env, run_process

from .install import PEERS, executable, status, version
from .report import ratio, series, verdict
from .rows import PAIR, Row, by_name, rows_of

#: points of the RPC rows
N_RPC = 1_000_000


@dataclass
class Context:
    """What every group needs.

    Attributes
    ----------
    repeat : int
        Rounds (each runs geocd and its peer once).
    work : Path
        Work folder (each group under ``work/<group>``, removed at the end).
    peers : Path
        The peers folder.
    data : Path
        The shared data folder.
    log : callable
        Progress lines.
    """

    repeat: int
    work: Path
    peers: Path
    data: Path
    log: object = print
    commands: dict = field(default_factory=dict)

    def portable(self, cmd: list[str]) -> str:
        """A command line with this machine's folders as placeholders (``{data}``, ``{work}``, ``{peers}``)."""
        out = []
        for a in map(str, cmd):
            a = a.replace(sys.executable, "python")
            for path, name in ((self.data, "{data}"), (self.work, "{work}"), (self.peers, "{peers}"), (REPO, ".")):
                a = a.replace(str(path), name)
            out.append(a)
        return shlex.join(out)


def record(row: Row, ctx: Context, geocd: dict, peer: dict | None, reason: str | None, accuracy: dict, **extra) -> dict:
    """A row's record: its figures, the peer's (or why there is none), the ratio, the goal and the verdict."""
    if row.peer is None:  # cold / warm: the ratio is cold over warm
        r = ratio(geocd, peer)
    else:  # the speed-up: the peer's CPU over geocd's
        r = ratio(peer, geocd)
    rec = {
        "name": row.name,
        "what": row.what,
        "goal": row.goal,
        "accuracy_goal": row.accuracy_goal,
        "ratio_of": "median CPU s, cold / warm" if row.peer is None else "median CPU s, peer / geocd",
        "data": list(row.data),
        "commands": ctx.commands.get(row.group, {}),
        "geocd": geocd,
        "peer": peer if peer and peer["n"] else None,
        "reason": reason if not (peer and peer["n"]) else None,
        "ratio": r,
        "accuracy": accuracy,
        **extra,
    }
    if rec["peer"] is None and not rec["reason"]:
        rec["reason"] = "every peer run failed: " + "; ".join(
            str(x.get("error_tail", ""))[-300:] for x in (peer or {}).get("runs", [])
        )
    rec["verdict"] = verdict(row, rec)
    return rec


def _pct(x: float) -> str:
    return f"{100 * x:.1f} %"


def _fresh(path: Path) -> Path:
    shutil.rmtree(path, ignore_errors=True)
    path.mkdir(parents=True)
    return path


# ------------------------------------------------------------------------------------------------------ stereo
def stereo_commands(ctx: Context, work: Path) -> dict:
    """The stereo group's command lines (geocd's, CARS's)."""
    man = work / "pair.yaml"
    return {
        "geocd": ctx.portable(bench_stereo.stereo_command(man, work / "geocd_out")),
        "peer": ctx.portable([executable(PEERS["cars"], ctx.peers), work / "cars" / "config.json"]),
        "cars_config": "bench_stereo.cars_config: flat initial elevation at s2p's median height, 0.5 m, "
        "EPSG:32740, no geoid, multiprocessing with 2 workers",
    }


def measure_stereo(ctx: Context) -> dict[str, dict]:
    """Rows ``stereo_cars`` and ``stereo_cold``: per round geocd cold (new cache), geocd warm (same cache), CARS."""
    work = _fresh(ctx.work / "stereo")
    ref, ref_grid = bench_stereo.load_s2p_dsm()
    man = bench_stereo.pair_manifest(work)
    cars = PEERS["cars"]
    why = status(cars, ctx.peers)
    runs: dict[str, list] = {"cold": [], "warm": [], "cars": []}
    acc: dict[str, list] = {"cold": [], "warm": [], "cars": []}
    for i in range(ctx.repeat):
        cache = _fresh(work / f"numba_cache_{i}")
        for label in ("cold", "warm"):
            out = work / f"geocd_{label}_{i}"
            r = run_process(bench_stereo.stereo_command(man, out), env=geocd_env(cache))
            if r["returncode"] == 0:
                acc[label].append(bench_stereo.stereo_accuracy(out, ref, ref_grid))
            runs[label].append(r)
            shutil.rmtree(out, ignore_errors=True)
            ctx.log(f"  geocd stereo {label} {i + 1}/{ctx.repeat}: {_brief(r)}")
        if why is None:
            c = bench_stereo.run_cars(str(executable(cars, ctx.peers)), work / f"cars_{i}", ref, ref_grid)
            runs["cars"].append(c)
            if "vs_s2p" in c:
                acc["cars"].append(c["vs_s2p"])
            shutil.rmtree(work / f"cars_{i}", ignore_errors=True)
            ctx.log(f"  CARS {i + 1}/{ctx.repeat}: {_brief(c)}")
        shutil.rmtree(cache, ignore_errors=True)
    shutil.rmtree(work, ignore_errors=True)
    label = f"CARS {version(cars, ctx.peers)}" if why is None else "CARS"
    g_warm, g_cold = series(runs["warm"], "geocd warm"), series(runs["cold"], "geocd cold")
    c = series(runs["cars"], label) if why is None else None
    out = {}
    w = acc["warm"][-1] if acc["warm"] else None
    k = acc["cars"][-1] if acc["cars"] else None
    a = {"geocd": w, "peer": k, "ok": None}
    if w and k:
        a["ok"] = w["vs_s2p_with_filled"]["nmad_m"] <= k["nmad_m"]
    if w:
        a["geocd_text"] = (
            f"NMAD {w['vs_s2p_with_filled']['nmad_m']:.3f} m at {_pct(w['vs_s2p_with_filled']['completeness_on_s2p'])}"
            f" (valid cells {w['vs_s2p']['nmad_m']:.3f} m at {_pct(w['vs_s2p']['completeness_on_s2p'])})"
        )
    if k:
        a["peer_text"] = f"NMAD {k['nmad_m']:.3f} m at {_pct(k['completeness_on_s2p'])}"
    row = by_name()["stereo_cars"]
    out[row.name] = record(row, ctx, g_warm, c, why, a, ratio_to_geocd_cold=ratio(c, g_cold))
    same = [x["vs_s2p_with_filled"]["nmad_m"] for x in acc["cold"] + acc["warm"]]
    a2 = {"ok": bool(same) and max(same) - min(same) < 1e-6, "nmad_m": same}
    a2["geocd_text"] = (
        f"same DSM cold and warm (NMAD {same[0]:.3f} m in all {len(same)} runs)"
        if a2["ok"]
        else f"NMAD differs between runs: {', '.join(f'{v:.4f}' for v in same)} m"
    )
    row = by_name()["stereo_cold"]
    out[row.name] = record(row, ctx, g_cold, g_warm, None, a2)
    return out


# ------------------------------------------------------------------------------------------------ run sample_aoi
def run_commands(ctx: Context, work: Path) -> dict:
    """The run group's command line."""
    return {"geocd": ctx.portable([*geocd_command(), "run", REPO / "sample_aoi", "--out", work / "run"])}


def measure_run(ctx: Context) -> dict[str, dict]:
    """Row ``run_cold``: per round ``geocd run sample_aoi`` cold (new cache), then warm (same cache)."""
    work = _fresh(ctx.work / "run")
    runs: dict[str, list] = {"cold": [], "warm": []}
    found = []
    for i in range(ctx.repeat):
        cache = _fresh(work / f"numba_cache_{i}")
        for label in ("cold", "warm"):
            out = work / "run"
            shutil.rmtree(out, ignore_errors=True)
            r = run_process(
                [*geocd_command(), "run", str(REPO / "sample_aoi"), "--out", str(out)], env=geocd_env(cache)
            )
            runs[label].append(r)
            if r["returncode"] == 0:
                s = json.loads((out / "run_summary.json").read_text())
                found.append({"buildings": s["buildings"].get("classes"), "changed_fraction": s["changed_fraction"]})
            ctx.log(f"  geocd run sample_aoi {label} {i + 1}/{ctx.repeat}: {_brief(r)}")
        shutil.rmtree(cache, ignore_errors=True)
    shutil.rmtree(work, ignore_errors=True)
    ok = bool(found) and all(f == found[0] for f in found)
    a = {"ok": ok, "found": found[0] if found else None}
    if found:
        cls = ", ".join(
            f"{n} {c}" for c, n in sorted(found[0]["buildings"].items()) if c not in ("unchanged", "unobserved") and n
        )
        a["geocd_text"] = ("same result cold and warm" if ok else "results differ between runs") + f" ({cls})"
    row = by_name()["run_cold"]
    return {row.name: record(row, ctx, series(runs["cold"], "geocd cold"), series(runs["warm"], "geocd warm"), None, a)}


# ------------------------------------------------------------------------------------------------------ demdiff
def demdiff_commands(ctx: Context, work: Path, a: int, b: int) -> dict:
    """The demdiff group's command lines."""
    xpy = executable(PEERS["xdem"], ctx.peers)
    return {
        "geocd": "in process: bench_demdiff.run_geocd (geocd.demdiff.dem_difference with the stable mask, + the "
        "volume σ of the changed mask)",
        "geocd_process": ctx.portable(bench_demdiff.demdiff_command(a, b, work / "out")),
        "peer": ctx.portable([xpy, work / "xdem_worker.py", work / "in.npz"])
        + " (bench_demdiff.XDEM_WORKER: Nuth–Kääb, dh, heteroscedasticity, variogram, error propagation)",
    }


def _finite(x) -> bool:
    return x is not None and bool(np.isfinite(x))


def _volume_text(v: float, s: float | None) -> str:
    return f"{v / 1e6:+.3f} ± {s / 1e6:.3f} Mm³" if _finite(s) else f"{v / 1e6:+.3f} Mm³ (no σ)"


def measure_demdiff(ctx: Context, a: int, b: int) -> dict[str, dict]:
    """Rows ``demdiff_A_B`` (in process) and ``demdiff_A_B_process`` (whole process): per round geocd in process,
    the xDEM worker (its chain and its whole process), ``geocd demdiff --base`` cold (new cache) and warm."""
    group = f"demdiff_{a}_{b}"
    work = _fresh(ctx.work / group)
    bench_demdiff.warm_up()
    da, db, obs = bench_demdiff.load_case(a, b)
    stable, changed = bench_demdiff.masks_for(f"{a}-{b}", da, db, obs)
    npz = bench_demdiff.xdem_inputs(work / "in.npz", da, db, obs, stable, changed)
    xdem = PEERS["xdem"]
    why = status(xdem, ctx.peers)
    runs: dict[str, list] = {k: [] for k in ("geocd", "xdem", "xdem_process", "cold", "warm")}
    g = x = report = None
    xerr = []
    for i in range(ctx.repeat):
        g = bench_demdiff.run_geocd(da, db, obs, stable, changed, 1)
        runs["geocd"].append({"wall_s": g["wall_s"], "cpu_s": g["cpu_s"], "returncode": 0})
        ctx.log(f"  geocd in process {i + 1}/{ctx.repeat}: {g['cpu_s']:.2f} s CPU, {g['wall_s']:.2f} s wall")
        if why is None:
            xi = bench_demdiff.xdem_process(str(executable(xdem, ctx.peers)), npz)
            if "error" in xi:
                xerr.append(xi["error"])
                runs["xdem"].append({"returncode": 1, "error_tail": xi["error"]})
                runs["xdem_process"].append({"returncode": 1, "error_tail": xi["error"]})
            else:
                x = xi
                runs["xdem"].append({"wall_s": x["wall_s"]["total"], "cpu_s": x["cpu_s"], "returncode": 0})
                runs["xdem_process"].append(
                    {"wall_s": x["process_s"], "cpu_s": x["process_cpu_s"], "peak_rss_mb": x["peak_rss_mb"]}
                )
            ctx.log(f"  xDEM {i + 1}/{ctx.repeat}: {xi.get('error') or _brief(runs['xdem_process'][-1])}")
        cache = _fresh(work / f"numba_cache_{i}")
        for label in ("cold", "warm"):
            out = work / f"out_{label}"
            shutil.rmtree(out, ignore_errors=True)
            r = run_process(bench_demdiff.demdiff_command(a, b, out), env=geocd_env(cache))
            runs[label].append(r)
            if r["returncode"] == 0:
                report = json.loads((out / "demdiff_report.json").read_text())["summary"]
            ctx.log(f"  geocd demdiff {label} {i + 1}/{ctx.repeat}: {_brief(r)}")
        shutil.rmtree(cache, ignore_errors=True)
    shutil.rmtree(work, ignore_errors=True)
    label = f"xDEM {version(xdem, ctx.peers)}" if why is None else "xDEM"
    reason = why or (f"xDEM failed: {xerr[-1]}" if xerr and x is None else None)
    # in process, same inputs and masks
    acc = {"geocd": _demdiff_figures(g), "peer": _demdiff_figures(x) if x else None, "ok": None}
    acc["geocd_text"] = _volume_text(g["volume_m3"], g["volume_sigma_m3"])
    if x:
        acc["peer_text"] = _volume_text(x["volume_m3"], x["volume_sigma_m3"])
        sx = x["volume_sigma_m3"]
        sc = float(np.hypot(g["volume_sigma_m3"], sx)) if _finite(sx) else g["volume_sigma_m3"]
        dv = g["volume_m3"] - x["volume_m3"]
        acc.update(difference_m3=dv, sigma_m3=sc, difference_sigma=dv / sc, ok=bool(abs(dv) <= sc))
        acc["geocd_text"] += f"; {dv / sc:+.1f}σ from xDEM"
        if x.get("failed"):
            acc["peer_failed_steps"] = x["failed"]
    out = {}
    row = by_name()[group]
    out[row.name] = record(row, ctx, series(runs["geocd"], "geocd in process"), _peer(runs["xdem"], label), reason, acc)
    # whole process: geocd demdiff --base (its own stable terrain and changed cells) vs the xDEM worker process
    acc = {"ok": None, "peer": _demdiff_figures(x) if x else None}
    if report:
        keys = ("status", "changed_area_m2", "volume_changed_m3", "volume_changed_sigma_m3", "volume_net_observed_m3")
        acc["geocd"] = {k: report.get(k) for k in keys}
        if _finite(report["volume_changed_sigma_m3"]):
            acc["geocd_text"] = "own cells: " + _volume_text(
                report["volume_changed_m3"], report["volume_changed_sigma_m3"]
            )
        else:  # no stable terrain of its own: nothing significant, the net volume without σ
            acc["geocd_text"] = (
                f"{report['status'].replace('_', ' ')}: net {report['volume_net_observed_m3'] / 1e6:+.3f} Mm³ "
                "over the common area, no σ"
            )
    if x:
        acc["peer_text"] = "masks given: " + _volume_text(x["volume_m3"], x["volume_sigma_m3"])
    row = by_name()[f"{group}_process"]
    out[row.name] = record(
        row,
        ctx,
        series(runs["warm"], "geocd warm"),
        _peer(runs["xdem_process"], label),
        reason,
        acc,
        geocd_cold=series(runs["cold"], "geocd cold"),
    )
    return out


def _peer(runs: list[dict], label: str) -> dict | None:
    return series(runs, label) if runs else None


def _demdiff_figures(r: dict | None) -> dict | None:
    if r is None:
        return None
    keys = ("shift_m", "stable_nmad_m", "changed_area_m2", "volume_m3", "volume_sigma_m3")
    return {k: r[k] for k in keys if k in r}


# ------------------------------------------------------------------------------------------------------ RPC
def rpc_commands(ctx: Context, work: Path) -> dict:
    """The RPC group's command lines (one process each)."""

    def cmd(tool):
        return [sys.executable, REPO / "bench" / "bench_rpc.py", "--first", tool, "--image", ctx.data / PAIR[0]] + [
            "--points",
            work / "points.npz",
            "--out",
            work / f"{tool}.npz",
        ]

    return {"geocd": ctx.portable(cmd("geocd")), "peer": ctx.portable(cmd("gdal")), "n": N_RPC}


def measure_rpc(ctx: Context) -> dict[str, dict]:
    """Rows ``rpc_cold`` and ``rpc_warm``: per round a geocd process cold (new cache), one warm, one GDAL process;
    each imports its tool, reads the RPC and localizes the same 1e6 points once."""
    work = _fresh(ctx.work / "rpc")
    image = ctx.data / PAIR[0]
    model = load_rpc_for_image(image)
    lon, lat, h, col, row = bench_rpc.sample_points(model, N_RPC)
    pts = work / "points.npz"
    np.savez(pts, col=col, row=row, h=h)
    runs: dict[str, list] = {"cold": [], "warm": [], "gdal": []}
    err: dict[str, float] = {}
    versions = {}
    for i in range(ctx.repeat):
        cache = _fresh(work / f"numba_cache_{i}")
        for label, tool in (("cold", "geocd"), ("warm", "geocd"), ("gdal", "gdal")):
            res = work / f"{label}.npz"
            cmd = [sys.executable, str(REPO / "bench" / "bench_rpc.py"), "--first", tool, "--image", str(image)]
            r = run_process([*cmd, "--points", str(pts), "--out", str(res)], env=geocd_env(cache))
            if r["returncode"] == 0:
                inner = json.loads(r["stdout_tail"].strip().splitlines()[-1])
                r["localize_s"] = inner["localize_s"]
                versions[tool] = inner["tool_version"]
                d = np.load(res)
                x, y = d["lon"], d["lat"]
                ok = np.isfinite(x) & np.isfinite(y)
                c2, r2 = model.project(x[ok], y[ok], h[ok])
                e = float(np.max(np.hypot(c2 - col[ok], r2 - row[ok]))) if ok.any() else float("nan")
                err[label] = max(err.get(label, 0.0), e)
                err[label + "_converged"] = float(ok.mean())
            runs[label].append(r)
            ctx.log(f"  {label if tool == 'gdal' else 'geocd ' + label} {i + 1}/{ctx.repeat}: {_brief(r)}")
        shutil.rmtree(cache, ignore_errors=True)
    shutil.rmtree(work, ignore_errors=True)
    gd = series(runs["gdal"], "GDAL " + versions.get("gdal", "").rpartition("GDAL ")[2])
    out = {}
    for name, label in (("rpc_cold", "cold"), ("rpc_warm", "warm")):
        a = {"ok": None, "max_error_px": {k: v for k, v in err.items() if k in (label, "gdal")}}
        if label in err:
            a["geocd_text"] = f"max error {_px(err[label])}"
        if "gdal" in err:
            a["peer_text"] = f"max error {_px(err['gdal'])}"
        row = by_name()[name]
        out[name] = record(row, ctx, series(runs[label], f"geocd {label}"), gd, None, a, versions=versions)
    return out


def _px(e: float) -> str:
    return "0 px (exact round trip)" if e == 0 else f"{e:.1e} px"


# ------------------------------------------------------------------------------------------------------ groups
def commands(ctx: Context, group: str) -> dict:
    """The command lines of a group (recorded in the JSON; what ``--dry-run`` prints)."""
    work = ctx.work / group
    if group == "stereo":
        return stereo_commands(ctx, work)
    if group == "run":
        return run_commands(ctx, work)
    if group.startswith("demdiff_"):
        a, b = map(int, group.split("_")[1:])
        return demdiff_commands(ctx, work, a, b)
    return rpc_commands(ctx, work)


def measure(ctx: Context, group: str) -> dict[str, dict]:
    """Measure a group; the records of its rows."""
    ctx.commands[group] = commands(ctx, group)
    if group == "stereo":
        return measure_stereo(ctx)
    if group == "run":
        return measure_run(ctx)
    if group.startswith("demdiff_"):
        a, b = map(int, group.split("_")[1:])
        return measure_demdiff(ctx, a, b)
    return measure_rpc(ctx)


def group_data(group: str) -> list[str]:
    """The data files a group reads (relative to the shared data folder)."""
    return sorted({d for r in rows_of(group) for d in r.data})


def _brief(r: dict) -> str:
    if r.get("returncode", 0) != 0:
        return f"FAILED (exit {r.get('returncode')}): {str(r.get('error_tail', ''))[-300:]}"
    rss = f", {r['peak_rss_mb'] / 1024:.2f} GB" if r.get("peak_rss_mb") else ""
    return f"{r['cpu_s']:.1f} s CPU, {r['wall_s']:.1f} s wall{rss}"
