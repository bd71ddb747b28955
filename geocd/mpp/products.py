"""Layers of a marked-point-process run, written through geocd's shared writers.

``<prefix>_buildings.gpkg`` (styled in QGIS through the ``layer_styles`` table):

* ``rectangles`` — every rectangle: ``change`` (unchanged / demolished / new), ``xi`` (*, 1, 2),
  presence per date, sides (m), orientation (degrees, map sense), area, data energy A_D, φ per date,
  ``confidence`` (%), ``change_confidence`` (%), ``building_id``;
* ``buildings`` — per building, the union of its overlapping or touching rectangles: first the columns every
  building layer shares (:mod:`geocd.change.building_layer`: ``building_id``, ``source``, ``class``,
  ``confidence_pct``), then ``change`` (the rectangles' label, ``modified`` when they disagree: a building
  extended or partly demolished), area, rectangle count, area-weighted confidences (:func:`buildings_frame`).

``<prefix>_buildings.tif`` (COG uint8, paletted): 0 none, 1 unchanged building, 2 demolished, 3 new;
``<prefix>_quicklook.png``: both images with the rectangles; ``<prefix>_summary.json``.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from ..geodesy import AOIGrid
from .evaluate import rect_masks
from .model import BOTH, ONLY_1, ONLY_2, XI_NAMES

#: building change classes → (fill colour, label); "modified": rectangles of one building disagree
MPP_CLASSES = {
    "new": ("#d7191c", "new"),
    "demolished": ("#2c7bb6", "demolished"),
    "modified": ("#fdae61", "modified (part new or demolished)"),
    "unchanged": ("#bdbdbd", "unchanged"),
}
RASTER_CODES = {"unchanged": 1, "demolished": 2, "new": 3}
RASTER_COLOURS = {0: (0, 0, 0, 0), 1: (189, 189, 189, 255), 2: (44, 123, 182, 255), 3: (215, 25, 28, 255)}


def rect_corners(rects: np.ndarray) -> np.ndarray:
    """(n, 4, 2) corner (col, row) coordinates (array-index convention: cell centres at integers)."""
    c, s = np.cos(rects[:, 4]), np.sin(rects[:, 4])
    a = np.stack([c, -s], axis=1)
    b = np.stack([s, c], axis=1)
    out = []
    for su, sv in ((1, 1), (1, -1), (-1, -1), (-1, 1)):
        out.append(rects[:, :2] + su * 0.5 * rects[:, 2:3] * a + sv * 0.5 * rects[:, 3:4] * b)
    return np.stack(out, axis=1)


def rectangles_frame(detection, grid: AOIGrid, epoch_a: str = "A", epoch_b: str = "B"):
    """GeoDataFrame of the rectangles in the grid's CRS."""
    import geopandas as gpd
    from shapely.geometry import Polygon

    r = detection.result
    t = grid.transform
    corners = rect_corners(r.rects)
    xs = t.c + t.a * (corners[..., 0] + 0.5)  # north-up grid: cell centres at integer + 0.5
    ys = t.f + t.e * (corners[..., 1] + 0.5)
    polys = [Polygon(np.column_stack([x, y])) for x, y in zip(xs, ys)]
    px = grid.posting_m
    xi = np.asarray(r.xi)
    df = gpd.GeoDataFrame(
        {
            "rect_id": np.arange(len(r), dtype=np.int32),
            # the annealed object: the two rectangles of an L cut from one object share it
            "object_id": (np.arange(len(r)) if r.object_id is None else np.asarray(r.object_id)).astype(np.int32),
            "change": [XI_NAMES[int(x)] for x in xi],
            "xi": ["*" if x == BOTH else str(int(x)) for x in xi],
            f"present_{epoch_a}": xi != ONLY_2,
            f"present_{epoch_b}": xi != ONLY_1,
            "length_m": np.round(r.rects[:, 2] * px, 2),
            "width_m": np.round(r.rects[:, 3] * px, 2),
            "orientation_deg": np.round(np.degrees(r.rects[:, 4]), 1),
            "area_m2": np.round(r.rects[:, 2] * r.rects[:, 3] * px * px, 1),
            "energy": np.round(r.energy, 4),
            f"phi_{epoch_a}": np.round(r.phi[:, 0], 4) if r.phi.size else np.zeros(len(r)),
            f"phi_{epoch_b}": np.round(r.phi[:, 1], 4) if r.phi.shape[1] > 1 else np.full(len(r), np.nan),
            "confidence": np.round(r.confidence, 1),
            "change_confidence": np.round(r.xi_confidence, 1),
        },
        geometry=polys,
        crs=grid.crs,
    )
    return df


def _layer_class(changes: set) -> str:
    """The building layer's class of a building whose rectangles carry ``changes`` (mpp's labels)."""
    if changes == {"unchanged"}:
        return "unchanged"
    if changes == {"new"}:
        return "new"
    if changes == {"demolished"}:
        return "collapsed"
    # rectangles that disagree: a part gone is partly collapsed, a part added (an extension) raised
    return "partly collapsed" if "demolished" in changes else "raised"


def buildings_frame(rects_df, source: str | None = None):
    """Union of touching or overlapping rectangles → one polygon per building (ids written back).

    The columns start with the building layer's shared ones (:data:`geocd.change.building_layer.SHARED`):
    ``building_id``, ``source`` (default "A and B images"), ``class`` (mpp's ``demolished`` → ``collapsed``; a
    building whose rectangles disagree: ``partly collapsed`` when one is gone, else ``raised``) and
    ``confidence_pct`` (a changed building: the model's probability, percent, of its rectangles' change labels —
    their existence probability where the method gives none; 0 for an unchanged one), ``area_m2`` (the
    polygon's). Then mpp's own: ``change`` (the rectangles' label, ``modified`` when they disagree),
    ``n_rectangles``, ``confidence`` and ``change_confidence`` (area-weighted / mean over the rectangles, percent).
    """
    import geopandas as gpd
    from shapely.ops import unary_union

    from ..change.building_layer import order_columns, source_images

    source = source or source_images("A", "B")
    cols = [
        "building_id",
        "source",
        "class",
        "confidence_pct",
        "change",
        "n_rectangles",
        "area_m2",
        "confidence",
        "change_confidence",
    ]
    if rects_df.empty:
        rects_df["building_id"] = np.zeros(0, np.int32)
        return gpd.GeoDataFrame({c: [] for c in cols}, geometry=[], crs=rects_df.crs)
    merged = unary_union(list(rects_df.geometry.buffer(1e-6)))
    parts = list(merged.geoms) if hasattr(merged, "geoms") else [merged]
    parts_df = gpd.GeoDataFrame(
        {"building_id": np.arange(len(parts), dtype=np.int32)}, geometry=parts, crs=rects_df.crs
    )
    joined = gpd.sjoin(rects_df[["rect_id", "geometry"]], parts_df, how="left", predicate="intersects")
    bid = joined.groupby("rect_id")["building_id"].first()
    rects_df["building_id"] = rects_df["rect_id"].map(bid).astype(np.int32)
    rows = []
    for k, part in enumerate(parts):
        sub = rects_df[rects_df["building_id"] == k]
        ch = set(sub["change"])
        w = sub["area_m2"].to_numpy(float)
        cls = _layer_class(ch)
        conf_pct = 0.0
        if cls != "unchanged":
            moved = sub[sub["change"] != "unchanged"]
            cc = moved["change_confidence"].to_numpy(float)
            cc = cc[np.isfinite(cc)]
            conf_pct = round(float(np.mean(cc) if cc.size else np.mean(moved["confidence"])), 1)
        rows.append(
            {
                "building_id": k,
                "source": source,
                "class": cls,
                "confidence_pct": conf_pct,
                "change": next(iter(ch)) if len(ch) == 1 else "modified",
                "n_rectangles": int(len(sub)),
                "area_m2": round(float(part.area), 1),
                "confidence": round(float(np.average(sub["confidence"], weights=w)), 1),
                "change_confidence": round(float(np.nanmean(sub["change_confidence"])), 1)
                if np.isfinite(sub["change_confidence"]).any()
                else np.nan,
            }
        )
    return order_columns(gpd.GeoDataFrame(rows, geometry=parts, crs=rects_df.crs))


def class_raster(detection, shape: tuple[int, int]) -> np.ndarray:
    """uint8: 0 none, 1 unchanged building, 2 demolished, 3 new (later rectangles win where they overlap)."""
    m = rect_masks(detection.result.rects, detection.result.xi, shape)
    out = np.zeros(shape, np.uint8)
    out[m["date1"] & m["date2"]] = 1
    out[m["demolished"]] = 2
    out[m["new"]] = 3
    return out


def quicklook(
    path: os.PathLike | str,
    image_a: np.ndarray,
    image_b: np.ndarray,
    detection,
    *,
    titles: tuple[str, str] = ("date A", "date B"),
    valid_a=None,
    valid_b=None,
) -> Path:
    """PNG: the two images side by side with the rectangles present on each (colour = change class)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..io.atomic import atomic_path

    colours = {BOTH: "#00e000", ONLY_1: "#2c7bb6", ONLY_2: "#ff2020"}
    corners = rect_corners(detection.result.rects)
    fig, axs = plt.subplots(1, 2, figsize=(12, 6.3))
    for k, (ax, img, v, title) in enumerate(zip(axs, (image_a, image_b), (valid_a, valid_b), titles)):
        a = np.asarray(img, np.float64)
        a = a[None] if a.ndim == 2 else a
        ok = np.all(np.isfinite(a), axis=0) if v is None else np.asarray(v, bool)
        show = a[:3] if a.shape[0] >= 3 else a[:1]
        lo, hi = np.percentile(show[:, ok], [2, 98]) if ok.any() else (0.0, 1.0)
        rgb = np.clip((show - lo) / max(hi - lo, 1e-9), 0, 1).transpose(1, 2, 0)
        rgb = np.repeat(rgb, 3, axis=2) if rgb.shape[2] == 1 else rgb
        rgb[~ok] = 0.3
        ax.imshow(rgb, interpolation="nearest")
        for cs, x in zip(corners, detection.result.xi):
            if (k == 0 and x == ONLY_2) or (k == 1 and x == ONLY_1):
                continue
            q = np.vstack([cs, cs[:1]])
            ax.plot(q[:, 0], q[:, 1], color=colours[int(x)], lw=1.2)
        ax.set_title(title, fontsize=10)
        ax.set_axis_off()
    fig.suptitle("green: unchanged, blue: demolished (date A only), red: new (date B only)", fontsize=9)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=80, format="png")
    plt.close(fig)
    return Path(path)


def write_mpp_products(
    out_dir: os.PathLike | str,
    detection,
    grid: AOIGrid,
    *,
    prefix: str = "mpp",
    epoch_a: str = "A",
    epoch_b: str = "B",
    images: tuple | None = None,
    provenance: dict[str, Any] | None = None,
    overwrite: bool = True,
) -> dict[str, Path]:
    """Write the GeoPackage, the class raster, a quick-look and a JSON summary; returns {product: path}."""
    from ..change.building_layer import buildings_qml, source_images
    from ..change.styles import categorized_polygon_qml, write_raster_style
    from ..io.atomic import write_text_atomic
    from ..io.raster import write_cog
    from ..io.vector import write_gpkg

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rects = rectangles_frame(detection, grid, epoch_a, epoch_b)
    bld = buildings_frame(rects, source_images(epoch_a, epoch_b))
    qml = categorized_polygon_qml("change", MPP_CLASSES)
    paths: dict[str, Path] = {}
    paths["buildings"] = write_gpkg(
        out / f"{prefix}_buildings.gpkg",
        {"buildings": bld, "rectangles": rects},
        styles={"buildings": buildings_qml(), "rectangles": qml},
        overwrite=overwrite,
    )
    tags = {
        "method": f"geocd mpp ({detection.method})",
        "classes": json.dumps({str(v): k for k, v in RASTER_CODES.items()}),
        "epoch_a": epoch_a,
        "epoch_b": epoch_b,
    }
    paths["classes"] = write_cog(
        out / f"{prefix}_buildings.tif",
        class_raster(detection, grid.shape),
        grid,
        dtype="uint8",
        nodata=None,
        tags=tags,
        colormap=RASTER_COLOURS,
        overview_resampling="nearest",
        overwrite=overwrite,
    )
    write_raster_style(paths["classes"], _classes_qml())
    if images is not None:
        paths["quicklook"] = quicklook(
            out / f"{prefix}_quicklook.png",
            images[0],
            images[1],
            detection,
            titles=(f"{epoch_a}", f"{epoch_b}"),
            valid_a=images[2] if len(images) > 2 else None,
            valid_b=images[3] if len(images) > 3 else None,
        )
    r = detection.result
    summary = {
        "geocd_mpp": 1,
        "method": detection.method,
        "epoch_a": epoch_a,
        "epoch_b": epoch_b,
        "rectangles": int(len(r)),
        "buildings": int(len(bld)),
        "by_change": {k: int(v) for k, v in bld["change"].value_counts().items()} if len(bld) else {},
        "by_class": {k: int(v) for k, v in bld["class"].value_counts().items()} if len(bld) else {},
        "iterations": r.iterations,
        "converged": r.converged,
        "births": r.births,
        "energy": round(r.energy_total, 4),
        "texture_change_b0": None if not np.isfinite(detection.b0) else round(detection.b0, 5),
        "thresholds": detection.thresholds,
        "notes": detection.notes,
        "grid": grid.to_dict(),
        "confidence": "percent: Gibbs probability of each object given the others at unit temperature (model-based)",
        "provenance": provenance or {},
        "outputs": {k: str(v) for k, v in paths.items()},
    }
    paths["summary"] = write_text_atomic(out / f"{prefix}_summary.json", json.dumps(summary, indent=2, default=str))
    return paths


def _classes_qml() -> str:
    from ..ortho.pipeline import _QML_HEAD, _QML_TAIL

    labels = {0: "no building", 1: "unchanged building", 2: "demolished", 3: "new"}
    entries = "\n".join(
        f'        <paletteEntry value="{k}" color="#{c[0]:02x}{c[1]:02x}{c[2]:02x}" alpha="{c[3]}" '
        f'label="{labels[k]}"/>'
        for k, c in RASTER_COLOURS.items()
    )
    return (
        _QML_HEAD + '    <rasterrenderer type="paletted" band="1" opacity="1" alphaBand="-1" nodataColor="">\n'
        "      <rasterTransparency/>\n      <colorPalette>\n" + entries + "\n      </colorPalette>\n"
        '      <colorramp type="randomcolors" name="[source]"/>\n    </rasterrenderer>\n' + _QML_TAIL
    )
