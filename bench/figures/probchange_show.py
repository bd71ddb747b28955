"""Issue 8 "Show": probabilistic change (Sakurada ch. 5) against "MVS then subtract" and the self-consistency test.

Everything is computed here from the scene folders (nothing is re-implemented:
pair-DEMs come from geocd.stereo.pipeline.run_stereo, the self-consistency test
from geocd.consistency, the metrics from geocd.change.metrics):

* Table 5.2 analogue: pixel-level F1 on the AOI grid against truth/change_mask.tif
  for probchange (thesis model and robust model, object space; key frame on
  sample_aoi), the stereo-DEM differencing baseline at its best threshold, and
  the self-consistency test (learned on the same pair-DEMs) at 90/95/99 %;
* Table 5.3 analogue: F1 of probchange for p(c=1) = 0.1 … 0.9 (the posterior for
  any prior follows from the log-odds at 0.5: logit p = logit p₀.₅ + logit π);
* illumination: the same town with epoch B under a different sun vs under A's sun;
* figures: docs/probchange_sample_aoi.png, docs/probchange_sigma.png; numbers:
  bench/results/probchange_show.json.

Scenes: sample_aoi (committed) and, generated into --work when missing,
``geocd synth --n-aerial 0 --out W/sun_other``, ``... --same-sun --out W/sun_same``
and ``... --seed 1 --out W/seed1``. Only the satellite views are used (4 in A, 3 in B).

Usage::

    .venv/bin/python bench/figures/probchange_show.py [--work /tmp/probchange_show] [--scenes sample_aoi,sun_other,...]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

GENERATED = {
    "sun_other": ["--n-aerial", "0"],
    "sun_same": ["--n-aerial", "0", "--same-sun"],
    "seed1": ["--n-aerial", "0", "--seed", "1"],
}
PRIORS = [round(0.1 * k, 1) for k in range(1, 10)]


def scene_dir(name: str, work: Path) -> Path:
    if name == "sample_aoi":
        return REPO / "sample_aoi"
    d = work / name
    if not (d / "scene.yaml").is_file():
        d.parent.mkdir(parents=True, exist_ok=True)
        cmd = [
            str(REPO / ".venv" / "bin" / "geocd"),
            "--progress",
            "none",
            "synth",
            "--out",
            str(d),
            "--name",
            name,
            *GENERATED[name],
        ]
        print("generating:", " ".join(cmd), flush=True)
        subprocess.run(cmd, check=True)
    return d


def satellite_manifest(path: Path):
    """The scene's manifest restricted to its satellite views."""
    from geocd.io.manifest import load_manifest

    m = load_manifest(path / "scene.yaml")
    sats = set(m.truth.get("satellite_images") or [])
    eps = tuple(
        dataclasses.replace(e, images=tuple(i for i in e.images if not sats or i.name in sats)) for e in m.epochs
    )
    return dataclasses.replace(m, epochs=eps)


def scores(pred, truth) -> dict:
    from geocd.change.metrics import binary_scores

    s = binary_scores(pred, truth)
    return {k: (round(float(v), 4) if isinstance(v, float) else v) for k, v in s.items()}


def prior_table(res, truth) -> dict:
    """F1 for every prior from the log-odds computed at prior 0.5."""
    out = {}
    lo05 = res.log_odds.astype(np.float64) - math.log(res.params.prior_change / (1 - res.params.prior_change))
    for pi in PRIORS:
        lo = lo05 + math.log(pi / (1 - pi))
        cut = math.log(res.params.threshold / (1 - res.params.threshold))
        pred = res.observed & (np.nan_to_num(lo, nan=-np.inf) > cut)
        out[str(pi)] = scores(pred, truth)["f1"]
    return out


def run_scene(name: str, path: Path, work: Path, key: str | None, do_key: bool) -> dict:
    from geocd.change.metrics import best_threshold_f1, roc_curve
    from geocd.consistency import ChangeParams, ConsistencyParams, change_test, learn_self_consistency
    from geocd.io.raster import read_band
    from geocd.probchange import ProbChangeParams, run_probchange
    from geocd.stereo.pipeline import run_stereo

    m = satellite_manifest(path)
    truth, tgrid = read_band(path / "truth" / "change_mask.tif")
    truth = truth > 0
    out: dict = {
        "scene": name,
        "images": {e.name: [i.name for i in e.images] for e in m.epochs},
        "change_fraction": round(float(truth.mean()), 5),
        "methods": {},
        "priors": {},
        "seconds": {},
    }
    keep: dict = {"truth": truth}
    # --- probchange, object space -----------------------------------------------------------------
    for label, params in (
        ("probchange (thesis model)", ProbChangeParams()),
        ("probchange (robust model)", ProbChangeParams.robust()),
    ):
        t = time.perf_counter()
        r = run_probchange(m, variant="objectspace", params=params, write=False)
        out["seconds"][label] = round(time.perf_counter() - t, 1)
        res = r["result"]
        assert res.grid.same_as(tgrid), "the probchange grid must be the truth grid"
        s = scores(res.changed(), truth)
        s["observed_fraction"] = round(float(res.observed.mean()), 4)
        s["auc"] = round(roc_curve(np.where(res.observed, res.log_odds, -1e9), truth)[3], 4)
        s["noise_model"] = res.noise.to_dict()
        out["methods"][label] = s
        out["priors"][label] = prior_table(res, truth)
        keep[label] = res
        print(name, label, s["f1"], out["seconds"][label], flush=True)
    # --- probchange, key frame -------------------------------------------------------------------------
    if do_key:
        for label, params in (
            ("probchange key frame (thesis model)", ProbChangeParams()),
            ("probchange key frame (robust model)", ProbChangeParams.robust()),
        ):
            t = time.perf_counter()
            r = run_probchange(m, variant="keyframe", key=key, params=params, write=False)
            out["seconds"][label] = round(time.perf_counter() - t, 1)
            res, kr = r["result"], r["key_result"]
            s = scores(res.changed(), truth)
            s["observed_fraction"] = round(float(res.observed.mean()), 4)
            # in the key frame's own geometry, against the per-image truth mask
            with __import__("rasterio").open(path / "truth" / "image_masks" / f"{kr.key_name}.tif") as ds:
                im = ds.read(1)
            h, w = kr.probability.shape
            c0, r0 = int(round(kr.col0)), int(round(kr.row0))
            s["key_geometry"] = scores(kr.changed(), im[r0 : r0 + h, c0 : c0 + w] > 0)
            s["key_window"] = [c0, r0, w, h]
            out["methods"][label] = s
            out["priors"][label] = prior_table(res, truth)
            print(name, label, s["f1"], s["key_geometry"]["f1"], out["seconds"][label], flush=True)
    # --- stereo pair-DEMs: MVS then subtract, and the self-consistency test -------------------------
    t = time.perf_counter()
    st = run_stereo(m, out_dir=work / f"stereo_{name}", keep_arrays=True)
    out["seconds"]["stereo pair-DEMs (all pairs)"] = round(time.perf_counter() - t, 1)
    grid = st["grid"]
    assert grid.same_as(tgrid)
    by: dict = {}
    for k, pd in st["pairs"].items():
        by.setdefault(pd.epoch or k.split("/")[0], []).append(pd)
    ea, eb = m.epochs[0].name, m.epochs[-1].name
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        za = np.nanmedian(np.stack([np.where(p.valid, p.z_m, np.nan) for p in by[ea]]), axis=0)
        zb = np.nanmedian(np.stack([np.where(p.valid, p.z_m, np.nan) for p in by[eb]]), axis=0)
    dz = zb - za
    thr, s = best_threshold_f1(np.nan_to_num(np.abs(dz), nan=0.0), truth)
    s = {k: (round(float(v), 4) if isinstance(v, float) else v) for k, v in s.items()}
    s["threshold_m"] = round(float(thr), 3)
    s["observed_fraction"] = round(float(np.isfinite(dz).mean()), 4)
    out["methods"]["stereo DEM differencing (MVS then subtract, best threshold)"] = s
    keep["mvs"] = np.isfinite(dz) & (np.abs(np.nan_to_num(dz)) >= thr)
    t = time.perf_counter()
    model = learn_self_consistency([by[ea], by[eb]], ConsistencyParams())
    res_sc = change_test(by[ea], by[eb], model, ChangeParams())
    out["seconds"]["self-consistency (learn + test)"] = round(time.perf_counter() - t, 1)
    sc_best = None
    for conf in res_sc.confidences:
        s = scores(np.isin(res_sc.changed_at(conf), (1, -1)), truth)
        s["observed_fraction"] = round(float(res_sc.observed.mean()), 4)
        out["methods"][f"self-consistency test at {conf:g} %"] = s
        if sc_best is None or s["f1"] > sc_best[1]:
            sc_best = (conf, s["f1"])
    keep["sc"] = np.isin(res_sc.changed_at(99.0), (1, -1))
    print(
        name,
        "mvs",
        out["methods"]["stereo DEM differencing (MVS then subtract, best threshold)"]["f1"],
        "sc99",
        out["methods"]["self-consistency test at 99 %"]["f1"],
        flush=True,
    )
    return out, keep


def figures(keep: dict, path: Path, out_png: Path, sigma_png: Path, summary: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from geocd.io.raster import read_band

    dsm, _ = read_band(path / "truth" / "dsm_A.tif")
    g = (dsm - np.nanpercentile(dsm, 1)) / (np.nanpercentile(dsm, 99.5) - np.nanpercentile(dsm, 1))
    truth = keep["truth"]

    def overlay(pred, obs=None):
        rgb = np.stack([np.clip(g, 0, 1) * 0.55] * 3, -1)
        if obs is not None:
            rgb[~obs] = [0.25, 0.25, 0.1]
        rgb[pred & ~truth] = [1, 0.1, 0.1]
        rgb[pred & truth] = [0.1, 0.9, 0.1]
        rgb[~pred & truth] = [0.2, 0.4, 1]
        return rgb

    rob = keep["probchange (robust model)"]
    the = keep["probchange (thesis model)"]
    f1 = lambda k: summary["methods"][k]["f1"]  # noqa: E731
    fig, ax = plt.subplots(2, 3, figsize=(18, 12.5))
    ax[0, 0].imshow(np.clip(g, 0, 1), cmap="gray")
    ax[0, 0].contour(truth, levels=[0.5], colors="yellow", linewidths=0.8)
    ax[0, 0].set_title("truth DSM A, changed cells outlined")
    im = ax[0, 1].imshow(np.where(rob.observed, rob.probability, np.nan), vmin=0, vmax=1, cmap="magma")
    fig.colorbar(im, ax=ax[0, 1], fraction=0.046)
    ax[0, 1].set_title("probchange p(c=1 | s') (robust model; dark olive = no decision)")
    ax[0, 1].set_facecolor("#404018")
    ax[0, 2].imshow(overlay(rob.changed(), rob.observed))
    ax[0, 2].set_title(f"probchange robust, p > 0.5: F1 {f1('probchange (robust model)'):.2f}")
    ax[1, 0].imshow(overlay(the.changed(), the.observed))
    ax[1, 0].set_title(f"probchange thesis model, p > 0.5: F1 {f1('probchange (thesis model)'):.2f}")
    k_mvs = "stereo DEM differencing (MVS then subtract, best threshold)"
    ax[1, 1].imshow(overlay(keep["mvs"]))
    ax[1, 1].set_title(
        f"MVS then subtract, best threshold {summary['methods'][k_mvs]['threshold_m']:.2f} m: F1 {f1(k_mvs):.2f}"
    )
    ax[1, 2].imshow(overlay(keep["sc"]))
    ax[1, 2].set_title(f"self-consistency test at 99 %: F1 {f1('self-consistency test at 99 %'):.2f}")
    for a in ax.ravel():
        a.set_xticks([])
        a.set_yticks([])
    fig.suptitle("sample_aoi (satellite views: 4 in A, 3 in B). Green TP, red FP, blue FN", fontsize=14)
    fig.tight_layout()
    fig.savefig(out_png, dpi=70)
    plt.close(fig)
    # σ histograms (Fig. 5.10 analogue) and the prior sensitivity (Table 5.3 analogue)
    fig, ax = plt.subplots(1, 3, figsize=(18, 4.8))
    diag = the.diagnostics["sigma_samples"]
    for a, key, sig, lab in (
        (ax[0], "a_min", the.noise.sigma, "epoch A (depth): σ"),
        (ax[1], "b_min", the.noise.sigma_prime, "epoch B: σ'"),
    ):
        v = diag[key]
        v = v[np.isfinite(v)]
        hi = np.quantile(v, 0.995)
        a.hist(v, bins=120, range=(0, hi), density=True, color="#888888", label=f"min_d s_d ({v.size} cells)")
        x = np.linspace(0, hi, 300)
        a.plot(x, np.exp(-x / sig) / sig, "r-", lw=2, label=f"half-Laplace, {lab} = {sig:.2f}")
        a.set_xlabel("patch dissimilarity (0–255 scale)")
        a.legend()
    for label, st in summary["priors"].items():
        ax[2].plot([float(p) for p in st], list(st.values()), "o-", label=label)
    ax[2].set_xlabel("prior p(c = 1)")
    ax[2].set_ylabel("F1 (sample_aoi)")
    ax[2].grid(alpha=0.3)
    ax[2].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(sigma_png, dpi=70)
    plt.close(fig)


def markdown(all_res: dict) -> str:
    scenes = list(all_res)
    methods = list(all_res[scenes[0]]["methods"])
    lines = ["| method | " + " | ".join(scenes) + " |", "|---|" + "---|" * len(scenes)]
    for meth in methods:
        row = []
        for sc in scenes:
            s = all_res[sc]["methods"].get(meth)
            row.append("–" if s is None else f"{s['f1']:.2f} ({s['precision']:.2f}/{s['recall']:.2f})")
        lines.append(f"| {meth} | " + " | ".join(row) + " |")
    lines.append("")
    lines.append("| p(c=1) | " + " | ".join(f"{p}" for p in PRIORS) + " |")
    lines.append("|---|" + "---|" * len(PRIORS))
    for sc in scenes:
        for meth, st in all_res[sc]["priors"].items():
            lines.append(f"| {sc}: {meth} | " + " | ".join(f"{st[str(p)]:.2f}" for p in PRIORS) + " |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", type=Path, default=Path("/tmp/probchange_show"))
    ap.add_argument("--scenes", default="sample_aoi,sun_same,sun_other,seed1")
    ap.add_argument("--key", default="A_sat2", help="key frame of the key-frame variant (sample_aoi)")
    ap.add_argument("--json", type=Path, default=REPO / "bench" / "results" / "probchange_show.json")
    a = ap.parse_args()
    a.work.mkdir(parents=True, exist_ok=True)
    all_res: dict = {}
    if a.json.exists():
        try:
            all_res = json.loads(a.json.read_text())["scenes"]
        except Exception:
            all_res = {}
    for name in [s.strip() for s in a.scenes.split(",") if s.strip()]:
        path = scene_dir(name, a.work)
        res, keep = run_scene(name, path, a.work, a.key, do_key=(name == "sample_aoi"))
        all_res[name] = res
        if name == "sample_aoi":
            figures(
                keep, path, REPO / "docs" / "probchange_sample_aoi.png", REPO / "docs" / "probchange_sigma.png", res
            )
        a.json.write_text(
            json.dumps(
                {"command": "bench/figures/probchange_show.py " + " ".join(sys.argv[1:]), "scenes": all_res},
                indent=1,
                default=str,
            )
        )
    print(markdown(all_res))
    if "sun_same" in all_res and "sun_other" in all_res:
        print("\nillumination (false-alarm rate, F1): B under A's sun vs under its own sun")
        for meth in all_res["sun_same"]["methods"]:
            s0, s1 = all_res["sun_same"]["methods"][meth], all_res["sun_other"]["methods"].get(meth)
            if s1:
                print(
                    f"  {meth}: same sun FA {s0['false_alarm_rate']:.4f} F1 {s0['f1']:.2f} | other sun FA "
                    f"{s1['false_alarm_rate']:.4f} F1 {s1['f1']:.2f}"
                )


if __name__ == "__main__":
    main()
