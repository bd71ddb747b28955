"""Land-cover integration on sample_aoi: vegetation from aerial-frame windows (sparse, detailed) and the
satellite views (coarse, full cover), fused by the GP; the thesis's ablation, F1 vs number of views, σ calibration.

    python bench/figures/landcover_show.py            # writes bench/results/landcover_show.json and docs/landcover_*.png

Training labels: the 10 polygons of examples/sample_aoi_vegetation_labels.gpkg, drawn by hand on an aerial
orthomosaic (5 vegetation, 5 other). Their cells are excluded from every score. Truth: truth/cover_A.tif
(vegetation = grass or tree crown seen from above), never used for training or fitting.
Detailed views: each aerial frame cut into 3 × 5 windows (200 × 214 px, ≈ 60 × 64 m on the ground), 45 views.
Coarse full cover: the mean over the 4 epoch-A satellite views of the satellite classifier's probability.
Building map: truth/footprints_A.gpkg (the epoch's map, extruded by height_m) — as a user's building layer.
The GP runs on a 1 m grid (the thesis's grid size); truth at 1 m = vegetated fraction of the four 0.5 m cells.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
DOCS = ROOT / "docs"


def block_mean(a: np.ndarray, k: int) -> np.ndarray:
    h, w = a.shape[0] // k * k, a.shape[1] // k * k
    b = a[:h, :w].reshape(h // k, k, w // k, k).astype(np.float64)
    with np.errstate(invalid="ignore"):
        return np.nanmean(np.nanmean(b, axis=3), axis=1) if np.isnan(b).any() else b.mean(axis=(1, 3))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--work", default="/tmp/landcover_show", help="cache of the per-image stages")
    ap.add_argument("--draws", type=int, default=2, help="random view subsets per count")
    ap.add_argument("--headline-views", type=int, default=8)
    ap.add_argument("--counts", default="1,4,16,45")
    ap.add_argument("--n-fit", type=int, default=300)
    ap.add_argument(
        "--only",
        choices=["calibration"],
        default=None,
        help="calibration: only the σ calibration with held-out spatial blocks "
        "(bench/results/landcover_calibration.json)",
    )
    args = ap.parse_args()
    import warnings

    warnings.filterwarnings("ignore", category=FutureWarning)
    warnings.filterwarnings("ignore", category=RuntimeWarning)
    from geocd.io.raster import read_band
    from geocd.landcover.classifier import METHODS, train
    from geocd.landcover.features import FeatureSpec
    from geocd.landcover.gp import GPParams, integrate
    from geocd.landcover.report import ABLATION, ablation, pr_figure
    from geocd.landcover.labels import class_list, rasterize_labels, read_labels
    from geocd.landcover.pipeline import Scene, gp_inputs, load_image, load_scene, project_probability, training_set
    from geocd.landcover.project import combine_views
    from geocd.ortho import view_geometry
    from geocd.synth.truth import VEGETATION_CODES

    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    sa = ROOT / "sample_aoi"
    labels_path = ROOT / "examples" / "sample_aoi_vegetation_labels.gpkg"
    t_all = time.perf_counter()
    timings: dict = {}
    scene = load_scene(manifest=sa / "scene.yaml", footprints=str(sa / "truth" / "footprints_A.gpkg"))
    grid = scene.grid
    cover, g2 = read_band(sa / "truth" / "cover_A.tif")
    assert g2.same_as(grid)
    veg = np.isin(cover, VEGETATION_CODES).astype(np.float64)
    labels = read_labels(labels_path)
    classes = class_list(labels, "vegetation")
    lab_cls, _ = rasterize_labels(labels.to_crs(grid.crs), grid.shape, grid.transform, classes)
    spec = FeatureSpec()
    air = [load_image(sa / "images" / f"A_air{k}.tif") for k in (1, 2, 3)]
    sat = [load_image(sa / "images" / f"A_sat{k}.tif") for k in (1, 2, 3, 4)]
    report: dict = {
        "labels": {"polygons": int(len(labels)), "labelled_cells_0.5m": int((lab_cls >= 0).sum()), "classes": classes}
    }

    # --- classifiers: RF maps of every image; RF / LR / SVM compared on sampled pixels against the truth -----
    from geocd.landcover.pipeline import image_features
    from geocd.landcover.classifier import predict_proba
    from geocd.landcover.project import cell_pixels
    from geocd.landcover.report import f1_at_recall as f1r

    cache = work / "stage1.npz"
    if cache.exists():
        z = np.load(cache, allow_pickle=True)
        air_p, sat_p = z["air_p"].item(), z["sat_p"].item()
        report["classifiers"] = json.loads(str(z["cls_report"]))
    else:
        t0 = time.perf_counter()
        Xa, ya, ga, _ = training_set(labels, air, classes, spec, scene)
        Xs, ys, gs, _ = training_set(labels, sat, classes, spec, scene)
        models = {
            (s_, m_): train(X_, y_, classes, spec, nb, method=m_)
            for s_, X_, y_, nb in (("aerial", Xa, ya, 3), ("satellite", Xs, ys, 1))
            for m_ in METHODS
        }
        air_p, sat_p = {}, {}
        samples = {("aerial", m_): ([], []) for m_ in METHODS} | {("satellite", m_): ([], []) for m_ in METHODS}
        rng = np.random.default_rng(0)
        for sensor, ims, store in (("aerial", air, air_p), ("satellite", sat, sat_p)):
            for im in ims:
                F = image_features(im, spec, scene)
                store[im.name] = predict_proba(models[(sensor, "rf")], F, im.valid)[1]
                rows, cols, obs = cell_pixels(im.camera, grid, scene.surface_m, im.shape)
                cand = np.flatnonzero((obs & (lab_cls < 0)).ravel())
                pick = rng.choice(cand, min(4000, cand.size), replace=False)
                r_, c_ = rows.ravel()[pick], cols.ravel()[pick]
                Xp = F[:, r_, c_].T
                for m_ in METHODS:
                    est = models[(sensor, m_)]
                    samples[(sensor, m_)][0].append(veg.ravel()[pick])
                    samples[(sensor, m_)][1].append(
                        predict_proba(est, Xp.T[:, :, None], np.ones((len(pick), 1), bool))[1, :, 0]
                    )
        cls_rep = {
            "note": "pixel classifiers scored on 4000 random observed, unlabelled cells per image (truth "
            "= the cell's cover; the pixel the cell is seen in)"
        }
        for (sensor, m_), (t_, s_) in samples.items():
            cls_rep.setdefault(sensor, {})[m_] = f1r(np.concatenate(t_) > 0.5, np.concatenate(s_))
        for sensor in ("aerial", "satellite"):
            cls_rep[sensor]["rf_feature_importance"] = models[(sensor, "rf")].report["feature_importance"]
            cls_rep[sensor]["training_samples"] = models[(sensor, "rf")].report["samples_per_class"]
        report["classifiers"] = cls_rep
        timings["classifiers_s"] = round(time.perf_counter() - t0, 1)
        np.savez(cache, air_p=air_p, sat_p=sat_p, cls_report=json.dumps(cls_rep))

    # --- projection --------------------------------------------------------------------------------------------
    cache = work / "stage2.npz"
    if cache.exists():
        z = np.load(cache, allow_pickle=True)
        proj = z["proj"].item()
    else:
        t0 = time.perf_counter()
        sviews = [project_probability(sat_p[im.name], im, scene) for im in sat]
        coarse, _, _ = combine_views(sviews)
        frames = []
        for im in air:
            geo = view_geometry(im.camera, grid, scene.surface_m)
            v = project_probability(air_p[im.name], im, scene)
            # detailed views: 3 × 5 windows of each frame; window id of every observed cell
            H, W = im.shape
            cid = np.floor(geo.row / (H / 5.0)) * 3 + np.floor(geo.col / (W / 3.0))
            cid = np.where(v.observed & np.isfinite(cid), cid, -1).astype(np.int32)
            frames.append((v.values, v.weight, cid))
        proj = {"coarse": coarse, "frames": frames}
        timings["projection_s"] = round(time.perf_counter() - t0, 1)
        np.savez(cache, proj=proj)

    # --- 1 m grid --------------------------------------------------------------------------------------------
    k = 2
    g1 = grid.__class__(grid.crs, grid.transform * grid.transform.scale(k), grid.width // k, grid.height // k)
    truth1 = block_mean(veg, k)
    y1 = truth1 >= 0.5
    labelled1 = block_mean((lab_cls >= 0).astype(float), k) > 0
    scene1 = Scene(
        grid=g1,
        dem_m=block_mean(scene.dem_m, k),
        surface_m=block_mean(scene.surface_m, k),
        occupancy=block_mean(scene.occupancy, k).astype(np.float32),
    )
    n_views = 45

    def detailed_map(chosen: np.ndarray) -> np.ndarray:
        num = np.zeros(grid.shape)
        den = np.zeros(grid.shape)
        for f, (vals, w, cid) in enumerate(proj["frames"]):
            sel = (cid >= 0) & np.isin(cid + 15 * f, chosen) & np.isfinite(vals) & (w > 0)
            num[sel] += w[sel] * vals[sel]
            den[sel] += w[sel]
        with np.errstate(invalid="ignore", divide="ignore"):
            d = np.where(den > 0, num / den, np.nan)
        return block_mean(d, k)

    gp_params = GPParams(n_fit=args.n_fit, n_inducing=400)
    coarse1 = block_mean(proj["coarse"], k)
    inputs_for = lambda use: gp_inputs(scene1, coarse1, use)  # noqa: E731
    rng = np.random.default_rng(0)
    headline = np.sort(rng.choice(n_views, args.headline_views, replace=False))
    t0 = time.perf_counter()
    det = detailed_map(headline)
    if args.only == "calibration":
        from geocd.landcover.report import sigma_calibration

        res = integrate(
            det,
            inputs_for(ABLATION["GP: detailed + coarse + xy + DEM + buildings"][0]),
            gp_params.replace(calibrate_folds=5),
        )
        unobs = ~labelled1 & ~np.isfinite(det)
        out = {
            "truth_on_unobserved_cells": sigma_calibration(truth1, res, unobs),
            "heldout_blocks": res.report["calibration"],
            "seconds": round(time.perf_counter() - t0, 1),
            "headline_views": [int(v) for v in headline],
            "n_fit": args.n_fit,
        }
        (ROOT / "bench" / "results" / "landcover_calibration.json").write_text(json.dumps(out, indent=1))
        print(json.dumps(out, indent=1))
        return
    scores, results = ablation(det, coarse1, inputs_for, y1, truth_value=truth1, exclude=labelled1, params=gp_params)
    for r in results.values():
        scores.setdefault("gp_report", {})[r.hyper.names.__str__()] = {
            kk: v for kk, v in r.report.items() if kk != "hyper"
        }
    report["ablation"] = scores
    report["headline_views"] = [int(v) for v in headline]
    ev = ~labelled1
    curves = {
        "coarse alone": (y1[ev], coarse1[ev]),
        "detailed alone (observed)": (y1[ev & np.isfinite(det)], det[ev & np.isfinite(det)]),
    }
    for name, r in results.items():
        curves[name] = (y1[ev], r.mean[ev])
    full = results[list(results)[-1]]
    np.savez_compressed(work / "maps.npz", truth=truth1, coarse=coarse1, detailed=det, mean=full.mean, sd=full.sd)
    timings["ablation_s"] = round(time.perf_counter() - t0, 1)
    pr_figure(
        DOCS / "landcover_pr.png",
        curves,
        scores,
        f"vegetation, sample_aoi: {args.headline_views} of 45 aerial windows "
        f"({scores['observed_fraction']:.0%} observed),\n1 m cells, label cells excluded",
    )

    # --- F1 vs number of detailed views -------------------------------------------------------------------------
    t0 = time.perf_counter()
    by_n = {}
    for n in [int(c) for c in args.counts.split(",")]:
        rows = []
        for d in range(args.draws if n < n_views else 1):
            chosen = np.sort(np.random.default_rng(100 + d).choice(n_views, n, replace=False))
            det = detailed_map(chosen)
            res = integrate(det, inputs_for(ABLATION["GP: detailed + coarse + xy + DEM + buildings"][0]), gp_params)
            obs = np.isfinite(det) & ev
            a_all, a_un, a_det = (
                f1r(y1[ev], res.mean[ev]),
                f1r(y1[ev & ~obs], res.mean[ev & ~obs]),
                f1r(y1[obs], det[obs]),
            )
            rows.append(
                {
                    "views": [int(c) for c in chosen],
                    "observed_fraction": round(float(np.isfinite(det).mean()), 4),
                    "f1_gp_all": a_all["f1_at_recall"],
                    "f1_gp_unobserved": a_un.get("f1_at_recall"),
                    "f1_detailed_observed": a_det["f1_at_recall"],
                    "ap_gp_all": a_all["average_precision"],
                    "ap_gp_unobserved": a_un.get("average_precision"),
                    "ap_detailed_observed": a_det["average_precision"],
                }
            )
            print(n, rows[-1], flush=True)
        by_n[n] = rows
    report["f1_vs_views"] = by_n
    timings["views_s"] = round(time.perf_counter() - t0, 1)
    timings["total_s"] = round(time.perf_counter() - t_all, 1)
    report["timings"] = timings
    (ROOT / "bench" / "results" / "landcover_show.json").write_text(json.dumps(report, indent=1))
    figures(by_n, work, args.headline_views)


def figures(by_n, work: Path, headline: int) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axs = plt.subplots(1, 2, figsize=(12, 4))
    ns = sorted(by_n, key=int)
    for ax, metric, ylabel in ((axs[0], "f1", "F1 at recall 0.5"), (axs[1], "ap", "average precision")):
        for key, lab in (
            (f"{metric}_gp_all", "GP, all cells"),
            (f"{metric}_gp_unobserved", "GP, unobserved cells"),
            (f"{metric}_detailed_observed", "detailed alone, observed cells"),
        ):
            if key not in by_n[ns[0]][0]:
                continue
            vals = [[r[key] for r in by_n[n] if r.get(key) is not None] for n in ns]
            mean = [np.mean(v) for v in vals]
            lo = [np.min(v) for v in vals]
            hi = [np.max(v) for v in vals]
            ax.errorbar(
                [int(n) for n in ns],
                mean,
                yerr=[np.subtract(mean, lo), np.subtract(hi, mean)],
                marker="o",
                capsize=3,
                label=lab,
            )
        ax.set_xscale("log", base=2)
        ax.set_xlabel("number of detailed views (aerial windows)")
        ax.set_ylabel(ylabel)
        ax.legend(loc="lower right", fontsize=8)
    cov = [np.mean([r["observed_fraction"] for r in by_n[n]]) for n in ns]
    axs[0].set_title("observed fraction: " + ", ".join(f"{int(n)}: {c:.0%}" for n, c in zip(ns, cov)), fontsize=8)
    fig.tight_layout()
    fig.savefig(DOCS / "landcover_views.png", dpi=80)
    plt.close(fig)

    z = np.load(work / "maps.npz")
    fig, ax = plt.subplots(1, 5, figsize=(20, 4.4))
    for a, (key, title, cmap, vmax) in zip(
        ax,
        (
            ("truth", "truth: vegetated fraction", "Greens", 1),
            ("coarse", "coarse: satellite classifier", "Greens", 1),
            ("detailed", f"detailed: {headline} aerial windows", "Greens", 1),
            ("mean", "GP mean (all inputs)", "Greens", 1),
            ("sd", "GP σ (latent)", "magma", None),
        ),
    ):
        im = a.imshow(z[key], cmap=cmap, vmin=0, vmax=vmax)
        a.set_title(title, fontsize=9)
        a.set_xticks([])
        a.set_yticks([])
        fig.colorbar(im, ax=a, fraction=0.046)
    fig.tight_layout()
    fig.savefig(DOCS / "landcover_sample_maps.png", dpi=70)
    plt.close(fig)


if __name__ == "__main__":
    main()
