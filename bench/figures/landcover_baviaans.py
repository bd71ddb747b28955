"""Real case: vegetation over the Baviaans site from two aerial frames (2015, RGB) and the QuickBird-2 image
(Nov 2003, pan), integrated by the GP on a 20 m grid.

    python bench/figures/landcover_baviaans.py      # needs ../shared/data/orthority_baviaans_aerial_qb2
                                           # → bench/results/landcover_baviaans.json, docs/landcover_baviaans.png

Labels: examples/baviaans_vegetation_labels.gpkg, 10 squares (5 vegetation, 5 bare) drawn by hand on an
orthomosaic of the 2015 frames; the same polygons train the aerial model (4 frames) and the QB2 model.
Detailed views: frames 05_0182 and 06_0251; frames 05_0184 and 06_0253 are held out. There is no truth:
the held-out frames' own classification is the reference where only they see the ground (a proxy, and 12
years separate QB2 from the frames). Heights: the DEM's EGM2008 heights through EGM96 (no EGM2008 grid here).
"""

from __future__ import annotations

import json
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT.parent / "shared" / "data" / "orthority_baviaans_aerial_qb2"
DETAILED = ("3324c_2015_1004_05_0182_RGB", "3324c_2015_1004_06_0251_RGB")
POSTING_M = 20.0
HELD_OUT = ("3324c_2015_1004_05_0184_RGB", "3324c_2015_1004_06_0253_RGB")


def main() -> None:
    warnings.simplefilter("ignore")
    import rasterio

    from geocd.camera.rpc import RPCModel
    from geocd.geodesy import AOIGrid, from_lonlat
    from geocd.io.frame import read_orthority_cameras
    from geocd.io.raster import read_dem
    from geocd.landcover.features import FeatureSpec
    from geocd.landcover.gp import GPParams, integrate
    from geocd.landcover.labels import class_list, rasterize_labels, read_labels
    from geocd.landcover.pipeline import LoadedImage, Scene, gp_inputs, predict_image, project_probability, training_set
    from geocd.landcover.classifier import train
    from geocd.landcover.project import combine_views
    from geocd.landcover.report import f1_at_recall

    t_all = time.perf_counter()
    names = sorted(p.stem for p in (DATA / "ngi").glob("3324c_*_RGB.tif"))
    with rasterio.open(DATA / "ngi" / f"{names[0]}.tif") as ds:
        crs = ds.crs
    cams = read_orthority_cameras(
        DATA / "io/ngi_int_param.yaml",
        DATA / "ngi/camera_pos_ori.txt",
        crs=crs,
        vertical_datum="egm2008",
        allow_geoid_substitute=True,
    )
    dem0 = read_dem(DATA / "ngi/dem.tif")
    x, y = from_lonlat(np.array([24.36, 24.43]), np.array([-33.735, -33.645]), dem0.grid.crs)
    grid = AOIGrid.from_bounds(min(x), min(y), max(x), max(y), POSTING_M, dem0.grid.crs)
    dem = read_dem(DATA / "ngi/dem.tif", grid=grid).to_ellipsoidal(allow_substitute=True).height_m.astype(float)
    scene = Scene(grid=grid, dem_m=dem, surface_m=dem, occupancy=np.zeros(grid.shape, np.float32))

    def loaded(path, camera) -> LoadedImage:
        with rasterio.open(path) as ds:
            data = ds.read()
            valid = ds.read_masks(1) > 0
        return LoadedImage(Path(path), data, valid, camera, None, None)

    frames = {n: loaded(DATA / "ngi" / f"{n}.tif", cams[n]) for n in names}
    with rasterio.open(DATA / "rpc/qb2_basic1b.tif") as ds:
        rpc = RPCModel.from_rasterio(ds.rpcs, width=ds.width, height=ds.height, source="qb2_basic1b.tif")
    qb2 = loaded(DATA / "rpc/qb2_basic1b.tif", rpc)
    labels = read_labels(ROOT / "examples" / "baviaans_vegetation_labels.gpkg")
    classes = class_list(labels, "vegetation")
    spec = FeatureSpec()
    t0 = time.perf_counter()
    Xa, ya, ga, per_a = training_set(labels, list(frames.values()), classes, spec, scene)
    Xq, yq, gq, per_q = training_set(labels, [qb2], classes, spec, scene)
    m_air = train(Xa, ya, classes, spec, 3)
    m_qb = train(Xq, yq, classes, spec, 1)
    t_train = time.perf_counter() - t0
    t0 = time.perf_counter()
    views = {n: project_probability(predict_image(m_air, im, scene)[1], im, scene) for n, im in frames.items()}
    coarse_view = project_probability(predict_image(m_qb, qb2, scene)[1], qb2, scene)
    coarse = coarse_view.values
    det, _, _ = combine_views([views[n] for n in DETAILED])
    ref, _, _ = combine_views([views[n] for n in HELD_OUT])
    t_proj = time.perf_counter() - t0
    # the GP works where the coarse image has data (the QB2 footprint)
    in_qb = np.isfinite(coarse)
    det_q = np.where(in_qb, det, np.nan)
    t0 = time.perf_counter()
    res = integrate(
        det_q,
        gp_inputs(scene, np.where(in_qb, coarse, np.nan), ("xy", "dem", "coarse")),
        GPParams(n_fit=300, n_inducing=400),
    )
    res_xy = integrate(det_q, gp_inputs(scene, None, ("xy", "dem")), GPParams(n_fit=300, n_inducing=400))
    t_gp = time.perf_counter() - t0
    lab, _ = rasterize_labels(labels.to_crs(grid.crs), grid.shape, grid.transform, classes)
    # proxy truth: the held-out frames' classification where the detailed views do not see, inside QB2
    cells = in_qb & ~np.isfinite(det) & np.isfinite(ref) & (lab < 0)
    proxy = ref[cells] > 0.5
    rep = {
        "grid": {"posting_m": POSTING_M, "shape": list(grid.shape), "crs": grid.crs.name},
        "labels": {"polygons": int(len(labels)), "aerial_pixels": per_a, "qb2_pixels": per_q},
        "training_samples": {"aerial": m_air.report["samples_per_class"], "qb2": m_qb.report["samples_per_class"]},
        "observed_fraction_in_qb2": round(float(np.isfinite(det_q[in_qb]).mean()), 4),
        "reference_cells": int(cells.sum()),
        "reference_positive_rate": round(float(proxy.mean()), 4),
        "vs_held_out_frames": {
            "QB2 alone": f1_at_recall(proxy, coarse[cells]),
            "GP: detailed + xy + DEM": f1_at_recall(proxy, res_xy.mean[cells]),
            "GP: detailed + QB2 + xy + DEM": f1_at_recall(proxy, res.mean[cells]),
        },
        "agreement_at_0.5": {
            "QB2 alone": round(float(np.mean((coarse[cells] > 0.5) == proxy)), 4),
            "GP: detailed + xy + DEM": round(float(np.mean((res_xy.mean[cells] > 0.5) == proxy)), 4),
            "GP: detailed + QB2 + xy + DEM": round(float(np.mean((res.mean[cells] > 0.5) == proxy)), 4),
        },
        "hyper": res.hyper.to_dict(),
        "gp_report": {k: v for k, v in res.report.items() if k != "hyper"},
        "timings_s": {
            "train": round(t_train, 1),
            "classify_and_project": round(t_proj, 1),
            "two_gp_integrations": round(t_gp, 1),
            "total": round(time.perf_counter() - t_all, 1),
        },
    }
    (ROOT / "bench" / "results" / "landcover_baviaans.json").write_text(json.dumps(rep, indent=1))
    print(json.dumps(rep["vs_held_out_frames"], indent=1), json.dumps(rep["agreement_at_0.5"]))
    figure(frames, scene, coarse, det, res, labels, in_qb)


def figure(frames, scene, coarse, det, res, labels, in_qb) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from geocd.ortho import orthorectify

    grid = scene.grid
    acc = np.zeros((3,) + grid.shape)
    n = np.zeros(grid.shape)
    for name, im in frames.items():
        r = orthorectify(im.data.astype(np.float32), im.camera, grid, scene.dem_m, valid=im.valid)
        o = r.observed
        acc[:, o] += r.values[:, o]
        n[o] += 1
    rgb = np.where(n > 0, acc / np.maximum(n, 1), np.nan)
    rgb = np.clip(np.moveaxis(rgb, 0, -1) / np.nanpercentile(rgb, 99), 0, 1)
    l, b, r_, t = grid.bounds
    ext = (l, r_, b, t)
    fig, ax = plt.subplots(1, 5, figsize=(22, 7.5))
    panels = (
        (rgb, "2015 aerial frames (all 4) + labels", None),
        (coarse, "QB2 2003: classifier p(vegetation)", "Greens"),
        (det, "detailed: 2 frames, p(vegetation)", "Greens"),
        (np.where(in_qb, np.clip(res.mean, 0, 1), np.nan), "GP mean (detailed + QB2 + xy + DEM)", "Greens"),
        (np.where(in_qb, res.sd, np.nan), "GP σ", "magma"),
    )
    for a, (img, title, cmap) in zip(ax, panels):
        h = a.imshow(img, extent=ext, cmap=cmap, vmin=0, vmax=1 if cmap == "Greens" else None)
        a.set_title(title, fontsize=9)
        a.set_xticks([])
        a.set_yticks([])
        if cmap:
            fig.colorbar(h, ax=a, fraction=0.046)
    for geom, c in zip(labels.to_crs(grid.crs).geometry, labels["label"]):
        xx, yy = geom.exterior.xy
        ax[0].plot(xx, yy, color="lime" if c == "vegetation" else "red", lw=1)
    fig.tight_layout()
    fig.savefig(ROOT / "docs" / "landcover_baviaans.png", dpi=55)
    plt.close(fig)


if __name__ == "__main__":
    main()
