"""Write the probabilistic change products (atomically), in the same layers as the other methods.

Layout of an output folder (``prefix`` default ``probchange``)::

    <prefix>_probability.tif      COG on the AOI grid: probability p(c=1|…), log_odds, coverage,
                                  height_a_m, height_b_m, dz_m (float32, NaN = no hypothesis observed)
    <prefix>_probability.qml      QGIS style sidecar (0–1 ramp, transparent below 0.5)
    <prefix>_change_mask.tif      COG int8: +1 changed (B higher or unknown), −1 changed (B lower),
                                  0 unchanged, −128 unobserved — binary change at p > threshold
    <prefix>_change_mask.qml
    <prefix>_changes.gpkg         layer ``changes`` (schema of :mod:`geocd.change.regions`,
                                  method = "probchange") + layer_styles
    <prefix>_keyframe_<key>.tif   key-frame geometry (key-frame variant): probability, log_odds,
                                  coverage, change; GDAL RPC tags when the key camera is an RPC,
                                  and ``<...>.camera.json`` (the key camera cropped to the window, any kind)
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from ..change.styles import discrete_pseudocolor_qml
from ..io.raster import write_cog
from ..io.vector import qml_for, write_gpkg
from .keyframe import KeyFrameResult
from .objectspace import ProbChangeResult

CHANGE_NODATA = -128


def probability_qml(band: int = 1) -> str:
    """A QGIS pseudocolor style for a 0–1 probability band (transparent below 0.5)."""
    items = [
        (0.5, "#ffffff", 0, "p ≤ 0.5 (no change)"),
        (0.75, "#fed976", 255, "0.5–0.75"),
        (0.9, "#fd8d3c", 255, "0.75–0.9"),
        (0.99, "#e31a1c", 255, "0.9–0.99"),
        ("inf", "#800026", 255, "> 0.99"),
    ]
    return discrete_pseudocolor_qml(items, band=band, maximum=1.0)


def _tags(result: ProbChangeResult, method: str, epoch_a: str, epoch_b: str, provenance: dict | None) -> dict:
    t = {
        "method": method,
        "epoch_a": epoch_a,
        "epoch_b": epoch_b,
        "threshold": result.params.threshold,
        "prior_change": result.params.prior_change,
        "noise_model": json.dumps(result.noise.to_dict()),
        "pairs": json.dumps(result.pairs),
        "params": result.params.to_json(),
        "content": "p(c=1|s') of Sakurada (2015) ch. 5: probability that the scene depth changed between the "
        "epochs; heights are the most probable hypotheses (by-products, not used for the decision)",
    }
    if provenance:
        t["provenance"] = json.dumps(provenance, default=str)
    return t


def write_probchange_products(
    out_dir: os.PathLike | str,
    result: ProbChangeResult,
    *,
    method: str = "probchange",
    epoch_a: str = "A",
    epoch_b: str = "B",
    prefix: str | None = None,
    provenance: dict | None = None,
    threshold: float | None = None,
) -> dict[str, Path]:
    """Grid products of one result (see the module doc); returns {product name: path}."""
    from ..change.regions import change_regions
    from ..change.styles import write_raster_style

    if result.grid is None:
        raise ValueError("write_probchange_products needs a result on an AOI grid (KeyFrameResult.to_grid(grid))")
    grid = result.grid
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    prefix = prefix or method.replace(" ", "_").replace("-", "_")
    tags = _tags(result, method, epoch_a, epoch_b, provenance)
    paths: dict[str, Path] = {}
    paths["probability"] = write_cog(
        out / f"{prefix}_probability.tif",
        {
            "probability": result.probability,
            "log_odds": result.log_odds,
            "coverage": result.coverage,
            "height_a_m": result.height_a_m,
            "height_b_m": result.height_b_m,
            "dz_m": result.dz_m,
        },
        grid,
        tags=tags,
    )
    write_raster_style(paths["probability"], probability_qml())
    mask = result.change_mask(threshold, nodata=CHANGE_NODATA)
    paths["change_mask"] = write_cog(
        out / f"{prefix}_change_mask.tif",
        mask,
        grid,
        nodata=CHANGE_NODATA,
        dtype="int8",
        tags=tags,
        overview_resampling="nearest",
    )
    write_raster_style(paths["change_mask"], qml_for("change_mask"))
    sign = np.where(mask == CHANGE_NODATA, 0, mask).astype(np.int8)
    conf = np.where(result.observed, 100.0 * result.probability, np.nan)  # percent, the changes layer's unit
    regions = change_regions(
        sign,
        result.dz_m,
        grid,
        confidence=conf,
        method=method,
        epoch_a=epoch_a,
        epoch_b=epoch_b,
        min_cells=result.params.min_region_cells,
    )
    paths["changes"] = write_gpkg(
        out / f"{prefix}_changes.gpkg", {"changes": regions}, styles={"changes": qml_for("changes")}
    )
    return paths


def write_keyframe_products(
    out_dir: os.PathLike | str,
    result: KeyFrameResult,
    *,
    method: str = "probchange",
    epoch_a: str = "A",
    epoch_b: str = "B",
    prefix: str | None = None,
    provenance: dict | None = None,
    threshold: float | None = None,
) -> dict[str, Path]:
    """The key-frame geometry product (a GeoTIFF over the key window + its camera); returns {name: path}."""
    from ..io.atomic import write_text_atomic
    from ..io.raster import write_image

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    prefix = prefix or method.replace(" ", "_").replace("-", "_")
    h, w = result.probability.shape
    c0, r0 = int(round(result.col0)), int(round(result.row0))
    cam = result.key_camera
    crop = cam.cropped(c0, r0, w, h) if hasattr(cam, "cropped") else cam
    ch = result.changed(threshold)
    change = np.where(result.observed, ch.astype(np.float32), np.nan)
    data = np.stack([result.probability, result.log_odds, result.coverage, change]).astype(np.float32)
    tags: dict[str, Any] = _tags(result, method, epoch_a, epoch_b, provenance)
    tags.update(
        {
            "key_image": result.key_name,
            "key_window_col0": c0,
            "key_window_row0": r0,
            "bands": "probability, log_odds, coverage, change (1/0, NaN unobserved)",
        }
    )
    stem = f"{prefix}_keyframe_{result.key_name}"
    rpc = crop if hasattr(crop, "to_rasterio") else None
    path = write_image(out / f"{stem}.tif", data, rpc=rpc, nodata=float("nan"), tags=tags)
    cam_path = write_text_atomic(out / f"{stem}.camera.json", json.dumps(crop.to_dict(), indent=1, default=str))
    return {"keyframe": path, "keyframe_camera": cam_path}
