"""The floor under the issue's stable-ground false alarms on Kahramanmaraş: flagged cells that are not buildings.

The issue's figure counts every cell flagged at 99 % outside the buildings the damage layer calls changed.
This script splits those cells (region test, calibrated: the default) into

* **non-building objects** by the layer's own extraction: cells in no building object that lie in a tree
  object of either epoch's DSM (the plane tree rule's trees) or stand ≥ ``min_height_m`` above the ground model
  in either epoch (``bench/eval_kahramanmaras.py``'s categories);
* **changed parts inside unchanged building objects** (8-connected same-sign flagged cells of at least the
  change map's mapping unit), grouped by what they were judged to be **by eye** on the pre | post orthos
  (docs/kahramanmaras.md, "The changed-part rule", and its picture ``kahramanmaras_changed_part.png``): the 18
  objects the changed-part option moves plus the 4 parts its tree test removed. The labels were made before
  this count, for that section, and no constant depends on them. They name objects of the layer made without
cutting changed parts out of merged objects (``split_changed=False``), so the split is made on that layer.

A perfect building layer (every demolished, rebuilt or raised building its own changed object, exact
outlines) would still leave the first group and the by-eye trees and roadworks in "stable": that sum is the
lowest figure the issue's definition allows without the change test hiding real surface change.

Usage::

    .venv/bin/python bench/figures/kahramanmaras_floor.py --run RUN [--json OUT.json]

(``RUN``: a ``geocd run`` of ``examples/kahramanmaras/scene.yaml``; ~15 s.)
"""

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from rasterio.features import rasterize
from scipy import ndimage as ndi

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # bench/, where eval_kahramanmaras.py lives
import eval_kahramanmaras as E  # noqa: E402

from geocd.change.dsm_buildings import CHANGED  # noqa: E402

#: building_id of the damage layer's objects (the default layer of a run of the example manifest), by what
#: their changed part is on the orthos (docs/kahramanmaras.md, "The changed-part rule")
BY_EYE = {
    "trees or roadworks": [64, 92, 110, 111, 117, 121, 123, 132, 133, 82, 89, 118, 119],
    "building changes": [188, 19, 116],
    "unclear": [4, 29, 38, 57, 128, 140],
}


def _part_cells(labels: np.ndarray, sign: np.ndarray, ids, mmu: int) -> int:
    """Cells of the same-sign flagged parts of at least ``mmu`` cells inside the objects ``ids``."""
    n = 0
    for i in ids:
        for s in (-1, 1):
            lab, k = ndi.label((labels == i) & (sign == s), structure=np.ones((3, 3), bool))
            if k:
                sizes = np.bincount(lab.ravel())[1:]
                n += int(sizes[sizes >= mmu].sum())
    return n


def floor_figures(run: Path) -> dict:
    """The split of the stable cells flagged at 99 % (shares of the stable cells; module doc)."""
    recs = E._recs(run)
    _, damage, res, dtm = E.evaluate(run, run / "self_consistency_model.json", "region", recs=recs, split_changed=False)
    grid = recs["pre_event"][0].grid
    m = E.false_alarm_masks(res, damage, grid, recs, dtm)
    stable, flag, in_building, trees = m["stable"], m["flag"], m["in_building"], m["trees"]
    non_building = ~in_building & (trees | m["up_a"] | m["up_b"])
    n_stable = int(stable.sum())
    sign = np.sign(np.nan_to_num(res.dz_m)).astype(int) * flag
    mmu = int(res.min_region_cells)
    labels = rasterize(
        [(g, int(i)) for g, i in zip(damage.geometry, damage["building_id"])],
        out_shape=grid.shape,
        transform=grid.transform,
        fill=0,
        dtype="int32",
    )
    ids = sum(BY_EYE.values(), [])
    missing = sorted(set(ids) - set(int(i) for i in damage["building_id"]))
    listed = damage[damage["building_id"].isin(ids)]
    moved = sorted(int(i) for i in listed[listed["class"].isin(CHANGED)]["building_id"])
    if missing or moved:
        raise ValueError(
            f"building_id {missing or moved} {'not in' if missing else 'changed in'} this run's damage "
            "layer: the by-eye labels belong to the default layer of examples/kahramanmaras/scene.yaml"
        )

    def share(n: int) -> float:
        return round(n / max(n_stable, 1), 5)

    out = {
        "run": str(run),
        "stable_cells": n_stable,
        "stable_false_alarms_99": share(int(flag.sum())),
        "non_building_objects": share(int((flag & non_building).sum())),
        "tree_objects": share(int((flag & ~in_building & trees).sum())),
        "inside_unchanged_building_objects": share(int((flag & in_building).sum())),
        "by_eye_parts": {k: share(_part_cells(labels, sign, v, mmu)) for k, v in BY_EYE.items()},
        "min_region_cells": mmu,
    }
    out["floor"] = round(out["non_building_objects"] + out["by_eye_parts"]["trees or roadworks"], 5)
    out["floor_tree_objects_and_by_eye_trees"] = round(
        out["tree_objects"] + out["by_eye_parts"]["trees or roadworks"], 5
    )
    return out


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", required=True, type=Path)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    result = floor_figures(args.run)
    print(json.dumps(result, indent=1))
    if args.json:
        args.json.write_text(json.dumps(result, indent=1) + "\n")
