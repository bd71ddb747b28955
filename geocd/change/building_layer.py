"""The ``buildings`` layer: one schema for every building layer geocd writes.

``geocd run``, ``geocd change`` (in memory and ``--tiled``), ``geocd demdiff`` and ``geocd mpp`` each write one
layer named ``buildings``. Its columns, class vocabulary, source vocabulary and the coding of a building that
could not be observed are defined here, once, and :func:`check_building_layer` tells whether a layer follows them
(the tests run it on every writer's output).

Columns (in this order; :data:`COLUMNS` holds name, type, unit, meaning and the coding of unobserved buildings):
``building_id, source, class, confidence_pct, rule, frac_observed, frac_changed, frac_lowered, frac_raised,
height_before_m, height_after_m, mean_dz_m, volume_change_m3, volume_sigma_m3, volume_lost_m3, area_m2``, then
``frac_examined`` when a screen ran (a tiered ``geocd run``), then a method's own columns (``geocd mpp``), then the
source's attributes as ``src_*``. The first four (:data:`SHARED`) are in every building layer; the self-consistency
layers (``geocd run``, ``geocd change``) and ``geocd demdiff`` carry all of them.

Classes (:data:`CLASSES`): ``collapsed`` (lowered, at ground level after — or at most ``collapse_ratio`` of its
height before), ``partly collapsed``, ``lowered``, ``raised``, ``new`` (raised, at ground level before),
``unchanged``, ``unobserved`` (too little of it observed in both epochs) and ``not examined`` (a tiered run's
screen did not flag its tiles).

``confidence_pct``: of a changed building, the highest tested confidence level (percent) at which it counts as
changed; of an observed building that is not changed, 0 — it is "not changed at the reported level", not a
confidence that the building is unchanged; of an ``unobserved`` or ``not examined`` building, empty (NaN in
Python, NULL in the GeoPackage). Every measure of the change (``frac_changed`` … ``volume_lost_m3``) of an
unobserved building is empty too; ``frac_observed`` says how little was seen.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from .styles import categorized_polygon_qml

#: building classes → (fill colour, label), in the order a summary lists them
CLASSES = {
    "collapsed": ("#67000d", "collapsed"),
    "partly collapsed": ("#ef3b2c", "partly collapsed"),
    "lowered": ("#fc9272", "lowered"),
    "raised": ("#fdae61", "raised"),
    "new": ("#2c7bb6", "new"),
    "unchanged": ("#bdbdbd", "unchanged"),
    "unobserved": ("#ffffff", "unobserved"),
    "not examined": ("#737373", "not examined (screened out)"),
}
#: the classes of a changed building
CHANGED = ("collapsed", "partly collapsed", "lowered", "raised", "new")
#: the classes of a building lowered at the reported level: the ones whose lost volume the summary adds up
LOWERED = ("collapsed", "partly collapsed", "lowered")
#: the classes of a building the change test did not see: ``confidence_pct`` and the change measures are empty
NOT_OBSERVED = ("unobserved", "not examined")

#: ``source`` of a building given as a footprint
SOURCE_FOOTPRINTS = "footprints"
#: ``source`` of a new building found as a raised region of the change map outside every footprint
SOURCE_CHANGE_MAP = "change map"


def source_dsm(epoch: str) -> str:
    """``source`` of a building object extracted from an epoch's DSM."""
    return f"{epoch} DSM"


def source_new_dsm(epoch_b: str, epoch_a: str) -> str:
    """``source`` of a new building: the part of a later DSM's object standing on the earlier DSM's ground."""
    return f"{epoch_b} DSM (ground in {epoch_a})"


def source_images(epoch_a: str, epoch_b: str) -> str:
    """``source`` of a building detected on the two epochs' images (``geocd mpp``)."""
    return f"{epoch_a} and {epoch_b} images"


_SOURCE_RE = re.compile(r"^(footprints|change map|.+ DSM|.+ DSM \(ground in .+\)|.+ and .+ images)$")


@dataclass(frozen=True)
class Column:
    """One column of the building layer (documented in docs/reference/products.md)."""

    name: str
    dtype: str
    unit: str
    meaning: str
    unobserved: str


COLUMNS = (
    Column(
        "building_id",
        "integer",
        "",
        "the footprint's id (its `building_id`, `id` or `fid` attribute, else its 1-based row); of a DSM object "
        "its number; a new building found in the change map: −1, −2, … (by decreasing area)",
        "set",
    ),
    Column("source", "text", "", "where the outline comes from (see the sources below)", "set"),
    Column("class", "text", "", "change class (see the classes below)", "`unobserved` or `not examined`"),
    Column(
        "confidence_pct",
        "real",
        "%",
        "changed building: the highest tested confidence level at which it counts as changed; observed and not "
        "changed: 0 (not changed at the reported level — not a confidence that it is unchanged)",
        "empty (NULL)",
    ),
    Column("rule", "text", "", "the rule that set the class, in words", "says why (e.g. the observed share)"),
    Column("frac_observed", "real", "0–1", "share of the outline observed in both epochs", "set (it says how little)"),
    Column("frac_changed", "real", "0–1", "share of its observed cells changed at the reported level", "empty"),
    Column("frac_lowered", "real", "0–1", "share of its observed cells lowered at the reported level", "empty"),
    Column("frac_raised", "real", "0–1", "share of its observed cells raised at the reported level", "empty"),
    Column(
        "height_before_m",
        "real",
        "m",
        "median height above the ground in the earlier epoch (ground: the earlier DSM's ground model; "
        "`geocd change --tiled` beyond its exact size and `geocd demdiff`: the median of a 4 m ring around the "
        "outline)",
        "set where that epoch has heights, else empty",
    ),
    Column("height_after_m", "real", "m", "the same in the later epoch", "set where that epoch has heights"),
    Column("mean_dz_m", "real", "m", "mean height change (later − earlier) over its observed cells", "empty"),
    Column("volume_change_m3", "real", "m³", "mean_dz_m × the outline's area (unobserved cells at the mean)", "empty"),
    Column(
        "volume_sigma_m3",
        "real",
        "m³",
        "1σ of volume_change_m3 from the self-consistency error model (empty without one: `geocd demdiff`)",
        "empty",
    ),
    Column("volume_lost_m3", "real", "m³", "max(−volume_change_m3, 0)", "empty"),
    Column("area_m2", "real", "m²", "area of the outline's grid cells", "set"),
)
#: every column, in order
NAMES = tuple(c.name for c in COLUMNS)
#: the columns every building layer (of any method) starts with
SHARED = NAMES[:4]
#: the measures of the change, empty for a building the test did not see
CHANGE_MEASURES = (
    "frac_changed",
    "frac_lowered",
    "frac_raised",
    "mean_dz_m",
    "volume_change_m3",
    "volume_sigma_m3",
    "volume_lost_m3",
)
#: the column a tiered run adds after :data:`NAMES`: share of the outline's cells in examined tiles
FRAC_EXAMINED = "frac_examined"


def order_columns(layer):
    """The layer with its columns in the schema's order: :data:`NAMES` (those present), ``frac_examined``, the
    method's own columns, ``src_*``, geometry."""
    cols = [c for c in layer.columns if c != layer.geometry.name]
    head = [c for c in (*NAMES, FRAC_EXAMINED) if c in cols]
    src = [c for c in cols if c.startswith("src_") and c not in head]
    rest = [c for c in cols if c not in head and c not in src]
    return layer[[*head, *rest, *src, layer.geometry.name]]


def code_unobserved(layer):
    """``confidence_pct`` and the change measures empty (NaN) for ``unobserved`` / ``not examined`` buildings."""
    out = layer.copy()
    hit = out["class"].isin(NOT_OBSERVED).to_numpy()
    if hit.any():
        for c in ("confidence_pct", *CHANGE_MEASURES):
            if c in out:
                out[c] = out[c].astype(float)
                out.loc[hit, c] = np.nan
    return out


def empty_layer(crs=None, extra: tuple[str, ...] = ()):
    """A building layer with no row (the schema's columns)."""
    import geopandas as gpd
    import pandas as pd

    kinds = {"integer": "int64", "text": "object", "real": "float64"}
    df = pd.DataFrame({c.name: pd.Series(dtype=kinds[c.dtype]) for c in COLUMNS})
    for c in extra:
        df[c] = pd.Series(dtype="float64")
    return gpd.GeoDataFrame(df, geometry=gpd.GeoSeries([], crs=crs), crs=crs)


def footprint_id_field(footprints) -> str | None:
    """The footprints' id attribute: ``building_id``, ``id`` or ``fid``, the first present (None: none)."""
    return next((c for c in ("building_id", "id", "fid") if c in footprints.columns), None)


def footprints_with_ids(footprints, crs, id_field: str | None = None):
    """Footprints in ``crs`` (index reset) whose ``building_id`` is their ``id_field`` (default: their 1-based
    row); a ``building_id`` or ``source`` column of the file that is not the id is dropped (the layer sets both)."""
    fp = footprints.to_crs(crs).reset_index(drop=True)
    ids = fp[id_field].to_numpy() if id_field and id_field in fp else np.arange(1, len(fp) + 1)
    fp = fp.drop(columns=[c for c in ("building_id", "source") if c in fp.columns and c != id_field])
    if id_field != "building_id":
        fp.insert(0, "building_id", ids)
    return fp


def building_layer_problems(layer, *, shared_only: bool = False) -> list[str]:
    """What in ``layer`` breaks the schema (empty list: it follows it).

    Parameters
    ----------
    layer : GeoDataFrame (as written, or read back from the GeoPackage)
    shared_only : bool
        Check the columns every method's layer has (:data:`SHARED`) and the coding of classes, sources and
        unobserved buildings only (``geocd mpp``); otherwise the whole column list (:data:`NAMES`) first, in order.
    """
    out: list[str] = []
    cols = [c for c in layer.columns if c != layer.geometry.name]
    want = SHARED if shared_only else NAMES
    if tuple(cols[: len(want)]) != want:
        out.append(f"columns start {cols[: len(want)]}, not {list(want)}")
    if "class" not in layer or "confidence_pct" not in layer:
        return out
    cls = layer["class"].astype(str).to_numpy()
    bad = sorted(set(cls) - set(CLASSES))
    if bad:
        out.append(f"classes {bad} are not in the vocabulary {list(CLASSES)}")
    if "source" in layer:
        bad_src = sorted({str(s) for s in layer["source"] if not _SOURCE_RE.match(str(s))})
        if bad_src:
            out.append(f"sources {bad_src} are not in the vocabulary")
    if "building_id" in layer and layer["building_id"].isna().any():
        out.append("building_id is empty in some rows")
    conf = layer["confidence_pct"].to_numpy(dtype=float)
    unseen = np.isin(cls, NOT_OBSERVED)
    changed = np.isin(cls, CHANGED)
    if np.isfinite(conf[unseen]).any():
        out.append("unobserved / not examined buildings with a confidence_pct (it must be empty)")
    if (~np.isfinite(conf[~unseen])).any():
        out.append("observed buildings without a confidence_pct")
    if (conf[cls == "unchanged"] != 0).any():
        out.append("unchanged buildings with a confidence_pct other than 0")
    cc = conf[changed]
    if ((cc <= 0) | (cc > 100) | ~np.isfinite(cc)).any():
        out.append("changed buildings with a confidence_pct outside (0, 100]")
    for c in CHANGE_MEASURES:
        if c in layer and np.isfinite(layer[c].to_numpy(dtype=float)[unseen]).any():
            out.append(f"unobserved / not examined buildings with a {c} (it must be empty)")
    return out


def check_building_layer(layer, *, shared_only: bool = False) -> None:
    """Raise ValueError naming every way ``layer`` breaks the schema (:func:`building_layer_problems`)."""
    bad = building_layer_problems(layer, shared_only=shared_only)
    if bad:
        raise ValueError("the building layer does not follow the schema: " + "; ".join(bad))


def summarize(layer, source: str | None = None) -> dict:
    """The run summary's ``buildings`` entry: sources (joined by " + "; ``source`` when the layer has no row),
    counts per class (vocabulary order), volume lost (m³) by the buildings lowered at the reported level
    (:data:`LOWERED`) — an unchanged building's Δz is the reconstructions' noise, not a loss."""
    counts = layer["class"].value_counts().to_dict()
    classes = {c: int(counts[c]) for c in CLASSES if c in counts}
    sources = list(dict.fromkeys(str(s) for s in layer["source"])) if "source" in layer else []
    lost = 0.0
    if "volume_lost_m3" in layer:
        lowered = layer["class"].isin(LOWERED).to_numpy()
        lost = float(np.nansum(layer["volume_lost_m3"].to_numpy(dtype=float)[lowered]))
    return {"source": " + ".join(sources) or source, "classes": classes, "volume_lost_m3": round(lost, 1)}


def summary_line(entry: dict | None) -> str:
    """One line for a run's stdout: the building counts per class of a :func:`summarize` entry, or why there is
    no building layer (``entry`` None or without a source)."""
    if not entry or entry.get("source") is None:
        why = (entry or {}).get("reason")
        return "buildings: no building layer" + (f" ({why})" if why else "")
    counts = ", ".join(f"{n} {k}" for k, n in entry.get("classes", {}).items())
    if not counts:
        return f"buildings ({entry['source']}): none found"
    lost = entry.get("volume_lost_m3")
    return f"buildings ({entry['source']}): {counts}" + (f"; {lost:,.0f} m³ lost" if lost else "")


def read_building_layer(gpkg, layer: str | None = None):
    """A run's building layer from its GeoPackage: ``layer``, else ``buildings``, else — a run folder written
    before the one building layer — its ``building_damage`` (the same classes and confidences)."""
    import geopandas as gpd
    import pyogrio

    if layer is None:
        names = [str(n) for n, _ in pyogrio.list_layers(gpkg)]
        layer = "building_damage" if "building_damage" in names else "buildings"
    return gpd.read_file(gpkg, layer=layer)


def buildings_qml() -> str:
    """QGIS style of the building layer (categorized on ``class``)."""
    return categorized_polygon_qml("class", CLASSES)
