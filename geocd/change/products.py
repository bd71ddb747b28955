"""Write the change layers analysts open (rasters, GeoPackage, plots) — atomically.

Layout of an output folder (``prefix`` defaults to the method name)::

    <prefix>_change.tif        COG, bands dz_m, dtilde, score, confidence (float32, NaN = unobserved)
    <prefix>_change.qml        QGIS style sidecar (confidence classes)
    <prefix>_change_mask.tif   COG int8 at the reported confidence (``region_confidence``, 99 % by default):
                               +1 raised, −1 lowered, 0 unchanged, −128 nodata (not observable),
                               −127 not examined (a tiered run's screen did not flag the tile)
    <prefix>_change_mask.qml   QGIS style sidecar (paletted)
    <prefix>_changes.gpkg      layers: changes (polygons), buildings (the one building layer of
                               :mod:`geocd.change.building_layer`), curves (significance curves
                               table), layer_styles
    <prefix>_scatter.png       score × |Δ̃| with significance curves (when a model is given)
    <prefix>_quicklook.png     epoch A | epoch B | the buildings by class over B, with the count of each class
                               (without a building layer: Δz of the changed cells, with the count of regions)
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from ..consistency import CHANGE_NODATA, NOT_EXAMINED, ChangeResult, SelfConsistencyModel
from ..io.raster import write_cog
from ..io.vector import qml_for, write_gpkg
from .building_layer import buildings_qml, check_building_layer
from .styles import write_raster_style


def write_change_products(
    out_dir: os.PathLike | str,
    result: ChangeResult,
    grid,
    *,
    method: str = "self-consistency",
    epoch_a: str = "A",
    epoch_b: str = "B",
    region_confidence: float = 99.0,
    model: SelfConsistencyModel | None = None,
    buildings=None,
    extra_layers: dict | None = None,
    extra_styles: dict | None = None,
    provenance: dict | None = None,
    prefix: str | None = None,
    min_region_cells: int | None = None,
    plots: bool = True,
    backdrop_m: np.ndarray | None = None,
    examined: np.ndarray | None = None,
    backdrop_a_m: np.ndarray | None = None,
    quicklook_views: tuple | None = None,
) -> dict[str, Path]:
    """Write every product of one change test; returns {product name: path}.

    ``buildings``: the building layer (:func:`geocd.change.dsm_buildings.classify_damage` or
    :func:`~geocd.change.dsm_buildings.footprint_layer`); it must follow the schema of
    :mod:`geocd.change.building_layer` (ValueError otherwise).

    ``examined`` (bool (rows, cols), a tiered run's flagged tiles): the change mask gives the other
    cells :data:`geocd.consistency.NOT_EXAMINED` (−127, "not examined"), never 0 ("unchanged").

    ``min_region_cells`` (default: the result's minimum mapping unit) is the smallest polygon of
    the ``changes`` layer; its ``confidence`` is the test's (percent), ``volume_sigma_m3`` comes
    from the error model (:func:`geocd.change.regions.correlated_volume_sigma`).
    The quick-look (``<prefix>_quicklook.png``, :func:`geocd.change.plots.change_quicklook_figure`) shows
    epoch A | epoch B | the building layer by class over B, its legend counting each class — the layer
    :func:`quicklook_buildings` picks among the GeoPackage's layers —, or without one the Δz of the
    changed cells with the count of raised and lowered regions. Its first two panels show
    ``quicklook_views`` (two :class:`geocd.change.plots.QuickLookView`, e.g. an orthoimage of each epoch),
    else hillshades of ``backdrop_a_m`` (epoch A's surface on the grid) and ``backdrop_m`` (epoch B's).
    """
    from .regions import change_regions, correlated_volume_sigma

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    prefix = prefix or method.replace(" ", "_").replace("-", "_")
    tags = {
        "method": method,
        "epoch_a": epoch_a,
        "epoch_b": epoch_b,
        "confidences": ",".join(f"{c:g}" for c in result.confidences),
        "comparisons": "; ".join(result.comparisons),
    }
    if provenance:
        import json

        tags["provenance"] = json.dumps(provenance, default=str)
    paths: dict[str, Path] = {}
    bands = {"dz_m": result.dz_m, "dtilde": result.dtilde, "score": result.score, "confidence": result.confidence}
    if result.cell_confidence is not None:
        bands["cell_confidence"] = result.cell_confidence
    if result.dz_sigma_m is not None:
        bands["dz_sigma_m"] = result.dz_sigma_m
    tags.update(significance=result.significance, min_region_cells=str(result.min_region_cells))
    if getattr(result, "calibration", None) is not None:  # the transfer calibration of the model, when applied
        import json

        tags["model_calibration"] = json.dumps(result.calibration.to_dict())
    paths["change"] = write_cog(
        out / f"{prefix}_change.tif",
        bands,
        grid,
        tags=tags,
        units=_BAND_UNITS,
        band_tags=[{"long_name": _BAND_DESCRIPTIONS[k]} for k in bands],
    )
    write_raster_style(paths["change"], qml_for("confidence"))
    # the mask is the map at the reported confidence (the level the regions, buildings and summary use)
    mask = result.changed_at(region_confidence)
    if examined is not None:
        mask = np.where(examined, mask, NOT_EXAMINED).astype(np.int8)
        tags["examined_fraction"] = f"{float(np.mean(examined)):.4f}"
    paths["change_mask"] = write_cog(
        out / f"{prefix}_change_mask.tif",
        {"change": mask},
        grid,
        nodata=CHANGE_NODATA,
        dtype="int8",
        tags={**tags, "mask_confidence_pct": f"{region_confidence:g}"},
        units={"change": "class"},
        band_tags=[
            {
                "long_name": f"change at {region_confidence:g} %: +1 raised, -1 lowered, "
                "0 unchanged, -128 not observed"
                + (", -127 not examined (screened out)" if examined is not None else "")
            }
        ],
        overview_resampling="nearest",
    )
    write_raster_style(paths["change_mask"], qml_for("change_mask"))

    sign = np.where((mask == 1) | (mask == -1), mask, 0).astype(np.int8)
    mmu = int(min_region_cells if min_region_cells is not None else result.min_region_cells)
    vfn = None
    if result.dz_sigma_m is not None:  # σ of the volume from the error model, correlated over one window
        vfn = correlated_volume_sigma(result.dz_sigma_m, max(result.min_region_cells, 1), grid.cell_area_m2)
    regions = change_regions(
        sign,
        result.dz_m,
        grid,
        confidence=result.confidence,
        volume_sigma_fn=vfn,
        volume_confidence=False,
        method=method,
        epoch_a=epoch_a,
        epoch_b=epoch_b,
        min_cells=mmu,
    )
    layers: dict[str, Any] = {"changes": regions}
    styles = {"changes": qml_for("changes")}
    if buildings is not None:
        check_building_layer(buildings)
        layers["buildings"] = buildings
        styles["buildings"] = buildings_qml()
    if model is not None:
        layers["curves"] = model.curves_table()
    if extra_layers:
        layers.update(extra_layers)
        styles.update(extra_styles or {})
    paths["changes"] = write_gpkg(out / f"{prefix}_changes.gpkg", layers, styles=styles)
    if plots:
        from .plots import QuickLookView, plot_change_quicklook, plot_scatter_curves

        if model is not None:
            paths["scatter"] = plot_scatter_curves(model, out / f"{prefix}_scatter.png")
        views = quicklook_views or (QuickLookView(surface_m=backdrop_a_m), QuickLookView(surface_m=backdrop_m))
        paths["quicklook"] = plot_change_quicklook(
            out / f"{prefix}_quicklook.png",
            grid,
            *views,
            buildings=quicklook_buildings(layers),
            dz_m=result.dz_m,
            sign=sign,
            regions=regions,
            epoch_a=epoch_a,
            epoch_b=epoch_b,
            confidence=region_confidence,
            method=method,
        )
    return paths


def quicklook_buildings(layers: dict[str, Any]):
    """The building layer the quick-look draws, from a GeoPackage's layers ({name: GeoDataFrame}).

    ``buildings`` when it has a ``class`` column, else ``building_damage`` (the damage layer of a run
    without footprints), else None.
    """
    for name in ("buildings", "building_damage"):
        gdf = layers.get(name)
        if gdf is not None and "class" in getattr(gdf, "columns", ()):
            return gdf
    return None


_BAND_UNITS = {
    "dz_m": "m",
    "dtilde": "px",
    "score": "bit/px",
    "confidence": "%",
    "cell_confidence": "%",
    "dz_sigma_m": "m",
}
_BAND_DESCRIPTIONS = {
    "dz_m": "height change B - A, median over comparisons (m)",
    "dtilde": "normalized difference, pixels of disparity",
    "score": "worst MDL match score of the comparisons (bits/pixel, lower = better)",
    "confidence": "percent that the cell changed (its region's test); 0 = no change found, NaN = not observed",
    "cell_confidence": "percent from the cell's own evidence alone, 100 (1 - p)",
    "dz_sigma_m": "1 sigma of dz from the self-consistency error model (m)",
}
