"""sample_aoi end to end at 1 m (slow): vegetation from one aerial frame and one satellite view, labels from
examples/sample_aoi_vegetation_labels.gpkg (hand-drawn; their cells are never scored), truth from cover_A.tif.

Pins the classifier + projection quality and the GP ordering measured by ``python -m tests.landcover.test_sample_aoi``
(docs/landcover.md has the full-scale figures from bench/figures/landcover_show.py).
"""

from __future__ import annotations

import numpy as np
import pytest

pytestmark = pytest.mark.slow


def run(sample_aoi_path) -> dict:
    import warnings

    from geocd.io.raster import read_band, reproject_array
    from geocd.landcover.classifier import train
    from geocd.landcover.features import FeatureSpec
    from geocd.landcover.gp import GPParams, integrate
    from geocd.landcover.labels import class_list, rasterize_labels, read_labels
    from geocd.landcover.pipeline import (
        gp_inputs,
        load_image,
        load_scene,
        predict_image,
        project_probability,
        training_set,
    )
    from geocd.landcover.report import f1_at_recall
    from geocd.synth.truth import VEGETATION_CODES

    warnings.simplefilter("ignore")
    root = sample_aoi_path
    scene = load_scene(
        manifest=root / "scene.yaml", footprints=str(root / "truth" / "footprints_A.gpkg"), posting_m=1.0
    )
    g = scene.grid
    cover, g05 = read_band(root / "truth" / "cover_A.tif")
    truth = reproject_array(np.isin(cover, VEGETATION_CODES).astype(np.float32), g05, g, "average")
    labels = read_labels(root.parent / "examples" / "sample_aoi_vegetation_labels.gpkg")
    classes = class_list(labels, "vegetation")
    lab, _ = rasterize_labels(labels.to_crs(g.crs), g.shape, g.transform, classes)
    ev = (lab < 0) & np.isfinite(truth)
    y = truth >= 0.5
    out = {}
    maps = {}
    for name, nb in (("A_air2", 3), ("A_sat2", 1)):
        im = load_image(root / "images" / f"{name}.tif")
        X, yy, _, _ = training_set(labels, [im], classes, FeatureSpec(), scene)
        model = train(X, yy, classes, FeatureSpec(), nb)
        v = project_probability(predict_image(model, im, scene)[1], im, scene)
        ok = ev & v.observed
        out[name] = {"observed": float(v.observed.mean()), **f1_at_recall(y[ok], v.values[ok])}
        maps[name] = v.values
    # the detailed view sees the western 40 % of the AOI only
    det = maps["A_air2"].copy()
    det[:, int(0.4 * g.width) :] = np.nan
    unobs = ev & ~np.isfinite(det)
    p = GPParams(n_fit=200, n_inducing=200)
    for key, use in (("gp_xy", ("xy",)), ("gp_all", ("xy", "coarse", "dem", "buildings"))):
        res = integrate(det, gp_inputs(scene, maps["A_sat2"], use), p)
        out[key] = f1_at_recall(y[unobs], res.mean[unobs])
    out["coarse_unobserved"] = f1_at_recall(y[unobs], maps["A_sat2"][unobs])
    return out


def test_vegetation_on_sample_aoi(sample_aoi):
    from pathlib import Path

    r = run(Path(sample_aoi))
    # measured: A_air2 observes 60 % of the cells, AP 0.997; A_sat2 AP 0.987; on the unobserved 60 %:
    # GP xy 0.738, GP all inputs 0.928 (the coarse map alone 0.986 there: with one contiguous detailed block the
    # DEM extrapolates badly, see docs/landcover.md)
    assert 0.55 < r["A_air2"]["observed"] < 0.65
    assert r["A_air2"]["average_precision"] > 0.99
    assert r["A_sat2"]["average_precision"] > 0.975
    assert r["gp_xy"]["average_precision"] < 0.80
    assert r["gp_all"]["average_precision"] > 0.90
    assert r["gp_all"]["average_precision"] > r["gp_xy"]["average_precision"] + 0.15


if __name__ == "__main__":
    import json
    from pathlib import Path

    print(json.dumps(run(Path(__file__).resolve().parents[2] / "sample_aoi"), indent=1))
