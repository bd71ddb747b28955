"""Write DEM-difference products with the shared writers (atomic; QGIS styles attached).

Layout of an output folder (``prefix`` defaults to ``demdiff``)::

    <prefix>_dh.tif             COG float32, band dh_m (B co-registered − A), NaN = not compared
    <prefix>_dh.qml             diverging pseudocolour style centred on 0 (QGIS sidecar)
    <prefix>_significance.tif   COG float32, bands confidence_pct (0–100), sigma_m, z
    <prefix>_significance.qml   confidence classes (90/95/99 %)
    <prefix>_change_mask.tif    COG int8: +1 raised, −1 lowered, 0 unchanged, −128 not compared
    <prefix>_change_mask.qml
    <prefix>_changes.gpkg       layers changes (regions), buildings (with footprints: the building layer of
                                :mod:`geocd.change.building_layer`, heights above a ring around each
                                footprint, no volume σ), summary,
                                error_model, variogram (+ timeseries for series), layer_styles
    <prefix>_dh.png             dh map with regions outlined
    <prefix>_report.json        every figure, the co-registration and the error model

Confidence is a percentage in the raster, the report (``confidence_level_pct``) and the
buildings layer, as in every geocd product; the ``changes`` layer follows the shared schema
of :mod:`geocd.change.regions`.
"""

from __future__ import annotations

import json
import math
import os
import re
from pathlib import Path
from typing import Any

import numpy as np

from ..io.raster import write_cog
from ..io.vector import qml_for, write_gpkg
from .pipeline import CHANGE_NODATA, DEMDiffResult, summary_table

_STOPS = (
    (-1.0, "#2166ac"),
    (-0.6, "#67a9cf"),
    (-0.25, "#d1e5f0"),
    (0.0, "#f7f7f7"),
    (0.25, "#fddbc7"),
    (0.6, "#ef8a62"),
    (1.0, "#b2182b"),
)


def nice_limit(v: float) -> float:
    """Round a colour limit up to 1, 2, 2.5 or 5 × 10^k."""
    if not (math.isfinite(v) and v > 0):
        return 1.0
    k = math.floor(math.log10(v))
    for m in (1, 2, 2.5, 5, 10):
        if m * 10**k >= v:
            return float(m * 10**k)
    return float(10 ** (k + 1))


def dh_qml(vmax: float) -> str:
    """The shipped ``dh.qml`` style with its colour ramp spanning [−vmax, +vmax]."""
    q = qml_for("dh")
    v = float(vmax)

    def fmt(x):
        return f"{x:.6g}"

    q = re.sub(r'classificationMin="[^"]*"', f'classificationMin="{fmt(-v)}"', q)
    q = re.sub(r'classificationMax="[^"]*"', f'classificationMax="{fmt(v)}"', q)
    q = re.sub(r'minimumValue="[^"]*"', f'minimumValue="{fmt(-v)}"', q)
    q = re.sub(r'maximumValue="[^"]*"', f'maximumValue="{fmt(v)}"', q)
    items = []
    for f, c in _STOPS:
        lab = fmt(f * v) + (" m (lowered)" if f == -1 else " m (raised)" if f == 1 else "")
        items.append(f'          <item value="{fmt(f * v)}" color="{c}" alpha="255" label="{lab}"/>')
    q = re.sub(r"( *<item [^\n]*\n)+", "\n".join(items) + "\n", q, count=1)
    return q


def significance_qml() -> str:
    """Confidence classes (percent) on band 1 (the shared confidence style, re-targeted)."""
    return qml_for("confidence").replace('band="4"', 'band="1"')


def _jsonable(o: Any):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, float) and not math.isfinite(o):
        return None
    return str(o)


def _clean(o: Any):
    if isinstance(o, dict):
        return {k: _clean(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_clean(v) for v in o]
    if isinstance(o, (float, np.floating)):
        f = float(o)
        return f if math.isfinite(f) else None
    if isinstance(o, np.integer):
        return int(o)
    return o


def write_json(path: os.PathLike | str, obj: Any) -> Path:
    from ..io.atomic import write_text_atomic

    return write_text_atomic(path, json.dumps(_clean(obj), indent=2, default=_jsonable))


def tables(result: DEMDiffResult) -> dict[str, Any]:
    """The attribute tables of one result (summary, error_model, variogram)."""
    import pandas as pd

    out: dict[str, Any] = {"summary": pd.DataFrame(summary_table([result]))}
    u = result.uncertainty
    if u is not None:
        em = (
            pd.DataFrame(list(u.error_model.table))
            if u.error_model.table
            else pd.DataFrame(
                {"slope_lo_deg": [], "slope_hi_deg": [], "q_lo": [], "q_hi": [], "n": [], "nmad_m": [], "model_m": []}
            )
        )
        out["error_model"] = em
        vg = u.variogram
        lags = np.asarray(vg.lags_m, float)
        out["variogram"] = pd.DataFrame(
            {
                "lag_m": lags,
                "gamma": np.asarray(vg.gamma, float),
                "pairs": np.asarray(vg.counts, np.int64),
                "model": vg.semivariance(lags) if lags.size else lags,
            }
        )
    return out


def write_demdiff_products(
    out_dir: os.PathLike | str,
    result: DEMDiffResult,
    *,
    footprints=None,
    prefix: str = "demdiff",
    plots: bool = True,
    extra_layers: dict | None = None,
    provenance: dict | None = None,
    overwrite: bool = True,
) -> dict[str, Path]:
    """Write every product of one DEM pair; returns {product name: path}."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    g = result.grid
    tags = {
        "method": "demdiff",
        "epoch_a": result.epoch_a,
        "epoch_b": result.epoch_b,
        "units": "m",
        "confidence_level_pct": f"{result.level:g}",
        "coreg": result.coreg.summary(),
    }
    if provenance:
        tags["provenance"] = json.dumps(_clean(provenance), default=_jsonable)
    paths: dict[str, Path] = {}
    paths["dh"] = write_cog(
        out / f"{prefix}_dh.tif", {"dh_m": result.dh_m.astype(np.float32)}, g, tags=tags, overwrite=overwrite
    )
    fin = np.isfinite(result.dh_m)
    vmax = nice_limit(float(np.nanpercentile(np.abs(result.dh_m[fin]), 98)) if fin.any() else 1.0)
    from ..change.styles import write_raster_style

    write_raster_style(paths["dh"], dh_qml(vmax))
    conf_pct = np.where(np.isfinite(result.confidence), result.confidence, np.nan).astype(np.float32)
    paths["significance"] = write_cog(
        out / f"{prefix}_significance.tif",
        {"confidence_pct": conf_pct, "sigma_m": result.sigma_m.astype(np.float32), "z": result.z.astype(np.float32)},
        g,
        tags=tags,
        overwrite=overwrite,
    )
    write_raster_style(paths["significance"], significance_qml())
    paths["change_mask"] = write_cog(
        out / f"{prefix}_change_mask.tif",
        result.sign.astype(np.int8),
        g,
        nodata=CHANGE_NODATA,
        dtype="int8",
        tags=tags,
        overview_resampling="nearest",
        overwrite=overwrite,
    )
    write_raster_style(paths["change_mask"], qml_for("change_mask"))

    layers: dict[str, Any] = {"changes": result.regions}
    styles = {"changes": qml_for("changes")}
    if footprints is not None:
        from ..change.building_layer import buildings_qml
        from ..change.dsm_buildings import LevelMasks, footprint_layer

        layers["buildings"] = footprint_layer(
            footprints,
            LevelMasks(result.dh_m, {float(result.level): result.sign}),
            g,
            z_a=result.height_a_m,
            z_b=result.height_b_m,
            report_confidence=float(result.level),
            id_field=next((c for c in ("building_id", "id", "fid") if c in footprints.columns), None),
        )
        styles["buildings"] = buildings_qml()
    layers.update(tables(result))
    if extra_layers:
        layers.update(extra_layers)
    paths["changes"] = write_gpkg(out / f"{prefix}_changes.gpkg", layers, styles=styles, overwrite=overwrite)
    if plots:
        from ..change.plots import plot_dh_map

        s = result.summary
        note = f"stable NMAD {s['stable_nmad_m']:.2f} m; coreg {result.coreg.status} ({result.coreg.applied})"
        if result.status == "degenerate_stable_terrain":
            note += "\nWARNING: degenerate stable terrain (DEMs identical there): σ is not credible"
        if math.isfinite(s.get("volume_changed_sigma_m3", float("nan"))):
            note += (
                f"\nchanged {s['changed_area_m2'] / 1e6:.3f} km², "
                f"{s['volume_changed_m3'] / 1e6:+.3f} ± {s['volume_changed_sigma_m3'] / 1e6:.3f} Mm³ (1σ)"
            )
        paths["dh_png"] = plot_dh_map(
            result.dh_m,
            g,
            out / f"{prefix}_dh.png",
            sign=result.sign,
            backdrop_m=result.height_a_m,
            backdrop_posting_xy_m=result.posting_xy_m,
            title=f"{result.epoch_a} → {result.epoch_b}: Δh after co-registration, changed at {result.level:g}%",
            vmax=vmax,
            note=note,
        )
    rep = result.to_dict()
    if provenance:
        rep["provenance"] = provenance
    paths["report"] = write_json(out / f"{prefix}_report.json", rep)
    return paths


def series_for_plot(ts) -> tuple[list[dict], list[dict]]:
    """(series, bars) definitions for :func:`geocd.change.plots.plot_volume_series` from a TimeSeriesResult."""
    import datetime as dt

    def d(s):
        return dt.date.fromisoformat(s) if s else None

    iv = [r for r in ts.table if r["kind"] == "interval" and "cumulative_net_m3" in r and r.get("date_b")]
    vb = [r for r in ts.table if r["kind"] == "vs_base" and "volume_net_m3" in r and r.get("date_b")]
    series, bars = [], []
    if iv:
        first = d(iv[0]["date_a"])
        series.append(
            {
                "label": "chained intervals, cumulative net volume (common survey areas)",
                "dates": [first] + [d(r["date_b"]) for r in iv],
                "values": [0.0] + [r["cumulative_net_m3"] for r in iv],
                "sigmas": [0.0] + [r["cumulative_net_sigma_m3"] for r in iv],
                "style": "o-",
            }
        )
        bars.append(
            {
                "label": "per-interval net volume",
                "dates_a": [d(r["date_a"]) for r in iv],
                "dates": [d(r["date_b"]) for r in iv],
                "values": [r["volume_net_m3"] for r in iv],
            }
        )
    if vb:
        series.append(
            {
                "label": f"net volume vs base ({vb[0]['epoch_a']}) over each survey area",
                "dates": [d(r["date_b"]) for r in vb],
                "values": [r["volume_net_m3"] for r in vb],
                "sigmas": [r.get("volume_net_sigma_m3", float("nan")) for r in vb],
                "style": "s--",
            }
        )
    return series, bars


def write_timeseries_products(
    out_dir: os.PathLike | str,
    ts,
    *,
    prefix: str = "demdiff",
    title: str = "",
    plots: bool = True,
    reference: list | None = None,
) -> dict[str, Path]:
    """Table (CSV + GeoPackage layer ``timeseries``), volume plot (PNG) and JSON of a time series."""
    import pandas as pd

    from ..io.atomic import write_text_atomic

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    df = pd.DataFrame(ts.table)
    paths: dict[str, Path] = {}
    paths["timeseries_csv"] = write_text_atomic(out / f"{prefix}_timeseries.csv", df.to_csv(index=False))
    paths["timeseries_gpkg"] = write_gpkg(out / f"{prefix}_timeseries.gpkg", {"timeseries": df})
    paths["timeseries_json"] = write_json(out / f"{prefix}_timeseries.json", {"table": ts.table, "notes": ts.notes})
    if plots:
        from ..change.plots import plot_volume_series

        series, bars = series_for_plot(ts)
        if series:
            paths["timeseries_png"] = plot_volume_series(
                series,
                out / f"{prefix}_timeseries.png",
                title=title or "Volume change (1σ error bars)",
                reference=reference or (),
                bars=bars,
            )
    return paths
