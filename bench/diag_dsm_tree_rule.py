"""What the DSM building extraction's tree rule drops: roughness against the roof-planarity cue, per object.

For each DSM, the building objects are extracted with the tree rule off (every raised object ≥ 40 m²), and
each object gets the figures both rules read:

* ``rough_ratio``: its median local roughness over the DSM's noise floor (the rule ``roughness``: dropped
  above ``DSMBuildingParams.roughness_factor``);
* ``planar_frac``: the share of its cells on a planar 3 × 3 patch (:func:`geocd.mpp.features.planar_cells`:
  best of the nine fits containing the cell, residual along the normal, tolerance from the DSM's ground cells).

Scenes:

* ``kahra RUN``: the pre- and post-event DSMs of a Kahramanmaraş run (median of its pair-DEMs, as
  ``geocd run``); with ``--chips DIR`` a contact sheet per epoch of the objects either rule drops (ortho
  with the outline, and the height above ground), to label by eye;
* ``town ROOT OUT``: a generated town (``sample_aoi`` or ``geocd synth``) with the DSMs of ``geocd ortho``
  (``OUT/ortho/{A,B}/dsm_{A,B}.tif``); objects are labelled from the truth: a building (with its roof, flat or
  gabled) when over half of it lies in a footprint of that epoch, a tree when over half of it lies in tree
  crowns, else other.

Usage::

    .venv/bin/python bench/diag_dsm_tree_rule.py kahra /tmp/kahra2 --chips /tmp/i18d_diag --json /tmp/i18d_diag/kahra.json
    .venv/bin/python bench/diag_dsm_tree_rule.py town sample_aoi /tmp/i19_run --json /tmp/i18d_diag/sample_aoi.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def object_table(
    z: np.ndarray, posting_m: float, dtm: np.ndarray | None = None, ground=None
) -> tuple[list, np.ndarray]:
    """Objects of ``z`` with the tree rule off, and the figures of both rules per object."""
    import dataclasses

    from scipy import ndimage as ndi

    from geocd.change.dsm_buildings import (
        DSMBuildingParams,
        best_plane_residual,
        building_objects,
        fill_gaps,
        ground_model,
        roughness,
        tree_threshold_m,
    )
    from geocd.mpp.features import plane_residual, planar_cells

    bp = DSMBuildingParams()
    if dtm is None:
        dtm, ground = ground_model(z, posting_m, bp)
    lab = building_objects(z, dtm, posting_m, dataclasses.replace(bp, tree_rule="off"), ground=ground)
    rough = roughness(z, posting_m)
    g = ground & np.isfinite(z)
    floor = float(np.median(rough[g]))
    ndsm = fill_gaps(z) - dtm
    planar, tol = planar_cells(z, ndsm, np.isfinite(z), bp.min_height_m, posting_m)
    has = np.isfinite(z)
    res = plane_residual(z, posting_m)
    best = ndi.grey_erosion(np.where(np.isfinite(res), res, np.inf), size=3, mode="nearest")
    gres = res[g & np.isfinite(res) & (ndsm < bp.min_height_m)]
    res_floor = float(np.median(gres))
    best9 = best_plane_residual(z, posting_m)
    plane_thr = tree_threshold_m(best9, g & (ndsm < bp.min_height_m), bp)
    ero = max(1, int(round(1.0 / posting_m)))
    rows = []
    for i, sl in enumerate(ndi.find_objects(lab), start=1):
        if sl is None:
            continue
        m = lab[sl] == i
        mz = m & has[sl]
        pl = planar[sl][m]
        pl = pl[np.isfinite(pl)]
        core = ndi.binary_erosion(m, iterations=ero)
        if core.sum() < 4:
            core = m
        pc = planar[sl][core]
        pc = pc[np.isfinite(pc)]
        bc = best[sl][core]
        bc = bc[np.isfinite(bc)]
        b9 = best9[sl][m]
        b9 = b9[np.isfinite(b9)]
        rows.append(
            {
                "id": i,
                "area_m2": float(m.sum() * posting_m**2),
                "plane_med_m": round(float(np.median(b9)), 4) if b9.size else np.inf,
                "core_planar_frac": round(float(pc.mean()), 3) if pc.size else np.nan,
                "plane_ratio": round(float(np.median(bc)) / res_floor, 2) if bc.size else np.inf,
                "height_m": round(float(np.median(ndsm[sl][m])), 2),
                "rough_ratio": round(float(np.median(rough[sl][mz])) / floor, 2) if mz.any() else np.inf,
                "planar_frac": round(float(pl.mean()), 3) if pl.size else np.nan,
                "bbox": [sl[0].start, sl[0].stop, sl[1].start, sl[1].stop],
            }
        )
    return (
        rows,
        lab,
        {"noise_floor_m": floor, "planar_tol_m": tol, "plane_floor_m": res_floor, "plane_thr_m": plane_thr},
    )


#: by-eye labels of the Kahramanmaraş objects the roughness rule drops (ids of the rule-off objects of the run
#: /tmp/kahra2; contact sheets of the orthos on the ground model; docs/kahramanmaras.md, "The tree rule")
EYE = {
    "pre_event": {
        "building": [
            9,
            14,
            15,
            21,
            22,
            23,
            24,
            26,
            34,
            36,
            45,
            52,
            53,
            54,
            55,
            76,
            78,
            83,
            84,
            96,
            97,
            98,
            101,
            105,
            141,
            177,
            179,
            185,
            189,
            216,
            218,
            235,
        ],
        "tree": [
            28,
            61,
            63,
            86,
            88,
            89,
            106,
            108,
            109,
            110,
            111,
            112,
            115,
            116,
            123,
            125,
            126,
            128,
            129,
            130,
            133,
            134,
            135,
            145,
            146,
            147,
            149,
            150,
            151,
            153,
            154,
            155,
            156,
            157,
            158,
            159,
            160,
            161,
            163,
            164,
            165,
            166,
            169,
            170,
            171,
            172,
            173,
            174,
            175,
            176,
            182,
            191,
            192,
            193,
            194,
            198,
            220,
            226,
            233,
            252,
        ],
    },
    "post_event": {
        "building": [4, 8, 17, 21, 26, 30, 32, 37, 52, 56, 61, 63, 67, 107, 171, 179, 180, 185, 190, 201, 202],
        "tree": [
            14,
            39,
            42,
            76,
            77,
            80,
            86,
            91,
            95,
            96,
            97,
            99,
            116,
            117,
            119,
            121,
            130,
            133,
            135,
            139,
            142,
            149,
            150,
            151,
            155,
            157,
            158,
            162,
            164,
            178,
            182,
            184,
        ],
    },
}


def contact_sheet(rows, lab, ortho: np.ndarray, ndsm: np.ndarray, path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not rows:
        return
    n = len(rows)
    cols = 6
    nr = (n + cols - 1) // cols
    fig, axs = plt.subplots(nr * 2, cols, figsize=(cols * 2.2, nr * 4.4))
    axs = np.atleast_2d(axs)
    lo, hi = np.nanpercentile(ortho, [2, 98])
    for k, ax in enumerate(axs.ravel()):
        ax.axis("off")
    for k, r in enumerate(rows):
        r0, r1, c0, c1 = r["bbox"]
        pad = 15
        R0, R1 = max(0, r0 - pad), min(lab.shape[0], r1 + pad)
        C0, C1 = max(0, c0 - pad), min(lab.shape[1], c1 + pad)
        a = axs[2 * (k // cols), k % cols]
        b = axs[2 * (k // cols) + 1, k % cols]
        a.imshow(ortho[R0:R1, C0:C1], cmap="gray", vmin=lo, vmax=hi)
        a.contour(lab[R0:R1, C0:C1] == r["id"], levels=[0.5], colors="r", linewidths=0.7)
        a.set_title(f"#{r['id']} r{r['rough_ratio']:.1f} p{r['planar_frac']:.2f}", fontsize=7)
        b.imshow(ndsm[R0:R1, C0:C1], cmap="terrain", vmin=0, vmax=max(6, r["height_m"] * 1.5))
        b.contour(lab[R0:R1, C0:C1] == r["id"], levels=[0.5], colors="r", linewidths=0.7)
        b.set_title(f"{r['area_m2']:.0f} m², {r['height_m']:.1f} m", fontsize=7)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def kahra(run: Path, chips: Path | None) -> dict:
    import rasterio

    from geocd.change.dsm_buildings import DSMBuildingParams, fill_gaps, ground_model
    from geocd.stereo.surface import epoch_surface
    from geocd.stereo import read_pair_dem

    recs = {
        ep: [read_pair_dem(p) for p in sorted((run / "stereo" / ep).glob("*.tif"))]
        for ep in ("pre_event", "post_event")
    }
    grid = recs["pre_event"][0].grid
    out = {}
    for ep in ("pre_event", "post_event"):
        z = epoch_surface(recs[ep])
        dtm, ground = ground_model(z, grid.posting_m)
        rows, lab, info = object_table(z, grid.posting_m, dtm, ground)
        fac = DSMBuildingParams().roughness_factor
        dropped = [r for r in rows if r["rough_ratio"] > fac]
        eye = {i: k for k, ids in EYE[ep].items() for i in ids}
        for r in rows:
            r["eye"] = eye.get(r["id"], "kept by roughness" if r["rough_ratio"] <= fac else "fragment / unclear")
        thr = info["plane_thr_m"]
        by = {}
        for r in rows:
            d = by.setdefault(r["eye"], {"n": 0, "dropped_roughness": 0, "dropped_plane": 0})
            d["n"] += 1
            d["dropped_roughness"] += int(r["rough_ratio"] > fac)
            d["dropped_plane"] += int(r["plane_med_m"] > thr)
        out[ep] = {
            **info,
            "objects": len(rows),
            "dropped_by_roughness": len(dropped),
            "dropped_by_plane": sum(r["plane_med_m"] > thr for r in rows),
            "by_eye": by,
            "rows": rows,
        }
        if chips is not None:
            chips.mkdir(parents=True, exist_ok=True)
            with rasterio.open(run / "orthos" / f"{ep}_img1.tif") as ds:
                ortho = ds.read(1).astype(float)
            ortho[ortho == 0] = np.nan
            contact_sheet(
                dropped,
                lab,
                ortho,
                fill_gaps(z) - dtm,
                chips / f"{ep}_dropped.png",
                f"{ep}: objects the roughness rule drops (r = roughness / floor > {fac}; p = planar share)",
            )
            kept = [r for r in rows if r["rough_ratio"] <= fac]
            contact_sheet(
                kept,
                lab,
                ortho,
                fill_gaps(z) - dtm,
                chips / f"{ep}_kept.png",
                f"{ep}: objects the roughness rule keeps",
            )
    return out


def town(root: Path, out_dir: Path) -> dict:
    import geopandas as gpd
    import rasterio
    from rasterio.features import rasterize

    res = {}
    for ep in ("A", "B"):
        with rasterio.open(out_dir / "ortho" / ep / f"dsm_{ep}.tif") as ds:
            z = ds.read(1).astype(np.float64)
            if ds.count > 1:
                z[ds.read(2) > 0] = np.nan  # the gap-filled cells: no stereo height
            shape, tr, posting = ds.shape, ds.transform, ds.transform.a
            _TR[0] = tr
        fp = gpd.read_file(root / "truth" / f"footprints_{ep}.gpkg")
        trees = gpd.read_file(root / "truth" / "objects.gpkg", layer=f"trees_{ep}")
        roof = rasterize(
            [(g, 1 if r == "flat" else 2) for g, r in zip(fp.geometry, fp["roof"])],
            out_shape=shape,
            transform=tr,
            fill=0,
            dtype="uint8",
        )
        tree = (
            rasterize([(g, 1) for g in trees.geometry], out_shape=shape, transform=tr, fill=0, dtype="uint8").astype(
                bool
            )
            if len(trees)
            else np.zeros(shape, bool)
        )
        rows, lab, info = object_table(z, posting)
        for r in rows:
            m = lab == r["id"]
            n = m.sum()
            f_flat, f_gab, f_tree = (roof[m] == 1).sum() / n, (roof[m] == 2).sum() / n, tree[m].sum() / n
            r["truth"] = (
                "flat roof"
                if f_flat > 0.5
                else "gabled roof"
                if f_gab > 0.5
                else "building (mixed)"
                if f_flat + f_gab > 0.5
                else "tree"
                if f_tree > 0.5
                else "other"
            )
            r.pop("bbox")
        res[ep] = {**info, "objects": len(rows), "rows": rows, "detection": detection(z, posting, fp, roof, tree)}
    return res


def detection(z, posting, fp, roof, tree) -> dict:
    """Building detection against the truth footprints, per tree rule: a footprint is found when ≥ half of its
    cells lie in kept objects (recall, by roof); a kept object is a building when over half of it lies in
    footprints (precision), a tree when over half of it lies in tree crowns."""
    import dataclasses

    from rasterio.features import rasterize

    from geocd.change.dsm_buildings import TREE_RULES, DSMBuildingParams, building_objects, ground_model

    dtm, ground = ground_model(z, posting)
    fpl = rasterize(
        [(g, i + 1) for i, g in enumerate(fp.geometry)], out_shape=z.shape, transform=_TR[0], fill=0, dtype="int32"
    )
    out = {}
    for rule in TREE_RULES:
        lab = building_objects(z, dtm, posting, dataclasses.replace(DSMBuildingParams(), tree_rule=rule), ground=ground)
        found = {"flat": [0, 0], "gabled": [0, 0]}
        for i, r in enumerate(fp["roof"]):
            m = fpl == i + 1
            k = "flat" if r == "flat" else "gabled"
            found[k][1] += 1
            found[k][0] += int(m.any() and (lab[m] > 0).mean() >= 0.5)
        kinds = {"building": 0, "tree": 0, "other": 0}
        for j in range(1, lab.max() + 1):
            m = lab == j
            kinds["building" if (roof[m] > 0).mean() > 0.5 else "tree" if tree[m].mean() > 0.5 else "other"] += 1
        n = sum(kinds.values())
        out[rule] = {
            "found_flat": found["flat"],
            "found_gabled": found["gabled"],
            "recall": round((found["flat"][0] + found["gabled"][0]) / max(1, len(fp)), 3),
            "objects": kinds,
            "precision": round(kinds["building"] / max(1, n), 3),
        }
    return out


_TR: list = [None]


def summarise(rows, fac: float, thr: float, key="truth") -> dict:
    out = {}
    for r in rows:
        t = r.get(key, "?")
        d = out.setdefault(t, {"n": 0, "dropped_roughness": 0, "dropped_plane": 0, "planar_frac": []})
        d["n"] += 1
        d["dropped_roughness"] += int(r["rough_ratio"] > fac)
        d["dropped_plane"] += int(r["plane_med_m"] > thr)
        d["planar_frac"].append(r["planar_frac"])
    for d in out.values():
        p = np.asarray(d.pop("planar_frac"), float)
        d["planar_frac_min_med_max"] = [
            round(float(np.nanmin(p)), 2),
            round(float(np.nanmedian(p)), 2),
            round(float(np.nanmax(p)), 2),
        ]
    return out


def main(argv=None) -> int:
    from geocd.change.dsm_buildings import DSMBuildingParams

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene", choices=("kahra", "town"))
    ap.add_argument("paths", nargs="+")
    ap.add_argument("--chips", default=None)
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    fac = DSMBuildingParams().roughness_factor
    if a.scene == "kahra":
        res = kahra(Path(a.paths[0]), Path(a.chips) if a.chips else None)
    else:
        res = town(Path(a.paths[0]), Path(a.paths[1]))
        for ep in res:
            res[ep]["by_truth"] = summarise(res[ep]["rows"], fac, res[ep]["plane_thr_m"])
            print(ep, "detection", json.dumps(res[ep]["detection"]))
    for ep, d in res.items():
        print(ep, json.dumps({k: v for k, v in d.items() if k != "rows"}, indent=1))
    if a.json:
        Path(a.json).parent.mkdir(parents=True, exist_ok=True)
        Path(a.json).write_text(json.dumps(res, indent=1, default=float))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
