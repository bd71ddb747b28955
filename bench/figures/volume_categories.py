"""Where the octree loses to Carlotto: pooled per-pixel AUC (3×3, DSM shadows) by category of B-image pixel.

Reads a finished ``python -m geocd.volume.evaluate SCENE --work W --shadow-dsm DSM`` (its model in
``W/volume_octree``), re-runs the 3×3 detection with the DSM's shadows and Carlotto's baseline on each B view,
and splits the pooled pixels by whether they are dark (the darkest 20 %) in the B image and in the warped A
reference (shadows, roughly), and by the edge zone. Also prints each view's relighting fits (per transition
class: ``c ≈ a + b E`` and its spread). docs/volume.md, "Where the octree loses to Carlotto".

Usage::

    .venv/bin/python bench/figures/volume_categories.py SCENE WORK DSM OUT.json
"""

import json
import sys
from pathlib import Path

import numpy as np
from geocd.io.manifest import load_manifest
from geocd.io.raster import read_dem, read_image
from geocd.volume import DetectParams, detect_change
from geocd.volume.io import geometry_from_manifest, load_model, read_shadow_dsm, read_view
from geocd.volume.evaluate import TrainConfig, _roc
from geocd.volume.baseline import carlotto_score, edge_zone, first_surface_height, nearest_view, warp_reference

scene, work, dsm = sys.argv[1], Path(sys.argv[2]), sys.argv[3]
cfg = TrainConfig()
man = load_manifest(scene)
geom, grid = geometry_from_manifest(man, finest_cell_m=cfg.finest_cell_m, max_depth=cfg.max_depth, above_m=cfg.above_m)
dem = read_dem(man.dem.path, grid=grid, vertical_datum=man.dem.vertical_datum).to_ellipsoidal().height_m
model = load_model(work / "volume_octree")
views_a = [read_view(s.path, s.camera, name=s.name) for s in man.epoch("A").images]
views_b = [read_view(s.path, s.camera, name=s.name) for s in man.epoch("B").images if "sat" in s.name]
ref_pool = [v for v in views_a if "sat" in v.name and v.name != "A_sat3"]
shadow = read_shadow_dsm(dsm, grid)
dsm_b = read_dem(man.truth_path("dsm_B"), grid=grid).height_m
P = {k: [] for k in ("oct", "carl", "truth", "dark", "zone", "darkA")}
fits = {}
for v in views_b:
    truth = read_image(man.root / man.truth["image_masks"][v.name]).data[0] > 0
    det = detect_change(
        model, v.intensity, v.camera, sun=v.sun, name=v.name, params=DetectParams(neighborhood=3), shadow_dsm=shadow
    )
    ref = ref_pool[nearest_view(v.camera, v.intensity.shape, ref_pool, geom)]
    warped = warp_reference(v.camera, v.intensity.shape, ref.intensity, ref.camera, dem, grid)
    carl = carlotto_score(v.intensity, warped)
    zone = edge_zone(first_surface_height(v.camera, v.intensity.shape, dsm_b, grid, geom))
    valid = ~det.unknown & np.isfinite(carl)
    I = v.intensity
    thr = np.nanpercentile(I[valid], 20)
    thrA = np.nanpercentile(warped[valid & np.isfinite(warped)], 20)
    P["oct"].append(det.probability[valid])
    P["carl"].append(carl[valid])
    P["truth"].append(truth[valid])
    P["dark"].append(I[valid] < thr)
    P["zone"].append(zone[valid])
    P["darkA"].append(np.nan_to_num(warped[valid], nan=1e9) < thrA)
    fits[v.name] = det.relight.get("fit") if isinstance(det.relight, dict) else None
    print(v.name, json.dumps(fits[v.name]), flush=True)
P = {k: np.concatenate(v) for k, v in P.items()}
out = {}
cats = {
    "all": np.ones(P["truth"].size, bool),
    "dark in B (20 %)": P["dark"],
    "not dark in B": ~P["dark"],
    "dark in warped A": P["darkA"],
    "dark in B not A": P["dark"] & ~P["darkA"],
    "dark in A not B": P["darkA"] & ~P["dark"],
    "lit in both": ~P["darkA"] & ~P["dark"],
    "edge zone": P["zone"],
    "not edge zone": ~P["zone"],
}
for n, m in cats.items():
    t = P["truth"][m]
    out[n] = {
        "share": round(float(m.mean()), 3),
        "changed": round(float(t.mean()), 3),
        "octree": round(_roc(P["oct"][m], t, np.ones(t.size, bool))["auc"], 3),
        "carlotto": round(_roc(P["carl"][m], t, np.ones(t.size, bool))["auc"], 3),
    }
    print(n, out[n], flush=True)
Path(sys.argv[4]).write_text(
    json.dumps(
        {
            "command": "bench/figures/volume_categories.py " + " ".join(sys.argv[1:]),
            "categories": out,
            "relight_fits": fits,
        },
        indent=1,
    )
)
