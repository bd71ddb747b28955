"""GP integration cost: exact GP vs the sparse inducing-point approximation, side by side in one run.

    nice -n 10 python bench/bench_gp.py                 # 1e4, 1e5, 1e6 cells → bench/bench_gp.json
    python bench/bench_gp.py --sizes 10000 --inducing 400

Each case runs in its own child process so its peak memory (ru_maxrss) is its own. A synthetic field of
n cells with the five inputs of ``geocd landcover integrate`` (x, y, DEM height, coarse probability, building
occupancy) is observed on a random third of the cells; the GP is trained on the observed cells and predicts
every cell. The ARD hyperparameters are fitted once (exact GP on 500 observed cells, timed separately) and
shared by both methods, so the two differ only in how they solve (the default additive kernel: an ARD
squared exponential over x, y plus one over the other inputs). The exact GP runs only where its n_obs²
kernel matrix fits the memory budget (--exact-max-gb): beyond it, it is reported as skipped with the memory
it would need. No numba kernel is involved (BLAS/LAPACK through numpy/scipy): there is no compile time.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent


def field(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Inputs (n, 5), target (n,) and the observed mask of a synthetic square area of n cells."""
    rng = np.random.default_rng(seed)
    side = int(round(np.sqrt(n)))
    r, c = np.divmod(np.arange(n), side)
    x, y = c.astype(float), r.astype(float)
    s = side / 10.0
    dem = 5.0 * np.sin(x / (3 * s)) + 3.0 * np.cos(y / (4 * s))
    blocks = ((x // s + y // s) % 5 == 0).astype(float)
    truth = 0.5 + 0.4 * np.sin(x / s) * np.cos(y / (1.5 * s)) - 0.5 * blocks
    coarse = np.clip(truth + 0.2 * rng.normal(size=n), 0, 1)
    y_obs = np.clip(truth + 0.05 * rng.normal(size=n), 0, 1)
    X = np.stack([x, y, dem, coarse, blocks], axis=1)
    obs = rng.random(n) < 1.0 / 3.0
    return X, y_obs, obs


def child(args) -> dict:
    from geocd.landcover.gp import GPHyper, SparseGP, choose_inducing, exact_gp

    X, y, obs = field(args.n)
    h = json.loads(Path(args.hyper).read_text())
    hyper = GPHyper(
        length_scales=np.array(h["ls"]),
        signal_var=h["s2"],
        noise_var=h["n2"],
        x_mean=np.array(h["xm"]),
        x_std=np.array(h["xs"]),
        y_mean=h["ym"],
        names=h["names"],
        groups=h["groups"],
        signal_vars=h["svs"],
    )
    Xo, yo = X[obs], y[obs]
    out: dict = {"method": args.case, "cells": int(args.n), "observed": int(obs.sum())}
    t0 = time.perf_counter()
    if args.case == "exact":
        t_fit0 = time.perf_counter()
        mean, sd = exact_gp(Xo, yo, X, hyper, batch=args.batch // 4)
        out["fit_predict_s"] = round(time.perf_counter() - t_fit0, 2)
    else:
        Z = choose_inducing(Xo, hyper, args.inducing, seed=0)
        gp = SparseGP(hyper, Z).fit(Xo, yo, batch=args.batch)
        out["fit_s"] = round(time.perf_counter() - t0, 2)
        t1 = time.perf_counter()
        mean, sd = gp.predict(X, batch=args.batch)
        out["predict_s"] = round(time.perf_counter() - t1, 2)
        out["inducing"] = int(Z.shape[0])
    out["total_s"] = round(time.perf_counter() - t0, 2)
    out["peak_rss_gb"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2, 3)
    if args.save:
        np.savez(args.save, mean=mean, sd=sd)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", default="10000,100000,1000000")
    ap.add_argument("--inducing", type=int, default=400)
    ap.add_argument("--batch", type=int, default=20000)
    ap.add_argument("--exact-max-gb", type=float, default=3.0, help="memory budget of the exact GP's kernel matrix")
    ap.add_argument("--out", default=str(HERE / "bench_gp.json"))
    ap.add_argument("--case", help=argparse.SUPPRESS)
    ap.add_argument("--n", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--hyper", help=argparse.SUPPRESS)
    ap.add_argument("--save", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.case:
        print(json.dumps(child(args)))
        return

    from geocd.landcover.gp import GPParams, fit_hyperparameters

    sizes = [int(s) for s in args.sizes.split(",")]
    X, y, obs = field(min(sizes))
    t0 = time.perf_counter()
    hyper = fit_hyperparameters(X[obs], y[obs], GPParams(n_fit=500), names=["x", "y", "dem", "coarse", "buildings"])
    hyper_s = time.perf_counter() - t0
    tmp = Path("/tmp") / f"bench_gp_{int(time.time())}"
    tmp.mkdir(exist_ok=True)
    hp = tmp / "hyper.json"
    hp.write_text(
        json.dumps(
            {
                "ls": hyper.length_scales.tolist(),
                "s2": hyper.signal_var,
                "n2": hyper.noise_var,
                "xm": hyper.x_mean.tolist(),
                "xs": hyper.x_std.tolist(),
                "ym": hyper.y_mean,
                "names": hyper.names,
                "groups": hyper.groups,
                "svs": hyper.signal_vars,
            }
        )
    )
    rows = []
    base = [sys.executable, __file__, "--hyper", str(hp), "--inducing", str(args.inducing), "--batch", str(args.batch)]
    for n in sizes:
        n_obs = int(field(n)[2].sum())
        need_gb = 2 * 8 * n_obs**2 / 1024**3
        for case in ("exact", "sparse"):
            if case == "exact" and need_gb > args.exact_max_gb:
                rows.append(
                    {
                        "method": "exact",
                        "cells": n,
                        "observed": n_obs,
                        "skipped": f"K and its Cholesky factor need {need_gb:.0f} GB > {args.exact_max_gb} GB",
                    }
                )
                print(rows[-1], flush=True)
                continue
            save = tmp / f"{case}_{n}.npz"
            r = subprocess.run(
                base + ["--case", case, "--n", str(n), "--save", str(save)], capture_output=True, text=True
            )
            if r.returncode != 0:
                rows.append({"method": case, "cells": n, "error": r.stderr.strip().splitlines()[-1:]})
            else:
                rows.append(json.loads(r.stdout.strip().splitlines()[-1]))
            print(rows[-1], flush=True)
        ex, sp = tmp / f"exact_{n}.npz", tmp / f"sparse_{n}.npz"
        if ex.exists() and sp.exists():
            a, b = np.load(ex), np.load(sp)
            rows.append(
                {
                    "cells": n,
                    "sparse_vs_exact": {
                        "rmse_mean": round(float(np.sqrt(np.mean((a["mean"] - b["mean"]) ** 2))), 5),
                        "max_abs_mean": round(float(np.max(np.abs(a["mean"] - b["mean"]))), 5),
                        "median_sd_exact": round(float(np.median(a["sd"])), 5),
                        "median_sd_sparse": round(float(np.median(b["sd"])), 5),
                    },
                }
            )
            print(rows[-1], flush=True)
    res = {
        "hyperparameter_fit": {"cells": 500, "seconds": round(hyper_s, 2), "hyper": hyper.to_dict()},
        "inducing": args.inducing,
        "batch": args.batch,
        "rows": rows,
        "machine": "2 cores shared with other sessions; times are wall clock",
    }
    Path(args.out).write_text(json.dumps(res, indent=1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
