"""Compare two output folders product by product (rasters by pixels and georeferencing, vectors by features)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

#: keys whose values legitimately differ between two runs (clock, absolute paths of the two output folders)
VOLATILE_KEYS = {
    "created",
    "update_time",
    "elapsed_s",
    "seconds",
    "timings",
    "output",
    "manifest",
    "provenance",
    "pair_dems",
    "path",
}
RASTER_EXT = {".tif", ".tiff"}
VECTOR_EXT = {".gpkg"}


def files(root: Path, ignore: tuple = ()) -> set[str]:
    return {
        p.relative_to(root).as_posix()
        for p in root.rglob("*")
        if p.is_file() and not any(p.name.startswith(i) or p.name.endswith(i) for i in ignore)
    }


def _strip(d, a_root: str, b_root: str):
    if isinstance(d, dict):
        # keys ending in _s are run times (render_s, pixels_per_s, ...)
        return {k: _strip(v, a_root, b_root) for k, v in d.items() if k not in VOLATILE_KEYS and not k.endswith("_s")}
    if isinstance(d, list):
        return [_strip(v, a_root, b_root) for v in d]
    if isinstance(d, str):
        return d.replace(b_root, a_root)
    return d


def compare_raster(a: Path, b: Path) -> list[str]:
    import rasterio

    diffs = []
    with rasterio.open(a) as da, rasterio.open(b) as db:
        for attr in ("count", "width", "height", "dtypes", "nodata", "crs", "transform", "descriptions"):
            va, vb = getattr(da, attr), getattr(db, attr)
            if va != vb and not (
                attr == "nodata" and va is not None and vb is not None and np.isnan(va) and np.isnan(vb)
            ):
                diffs.append(f"{a.name}: {attr} {va} != {vb}")
        if not diffs:
            xa, xb = da.read(), db.read()
            if not np.array_equal(xa, xb, equal_nan=np.issubdtype(xa.dtype, np.floating)):
                diffs.append(f"{a.name}: pixel values differ")
    return diffs


def compare_vector(a: Path, b: Path) -> list[str]:
    import pyogrio

    la = [n for n, _ in pyogrio.list_layers(a)]
    lb = [n for n, _ in pyogrio.list_layers(b)]
    if sorted(la) != sorted(lb):
        return [f"{a.name}: layers {la} != {lb}"]
    diffs = []
    for name in la:
        fa = pyogrio.read_dataframe(a, layer=name)
        fb = pyogrio.read_dataframe(b, layer=name)
        drop = [c for c in fa.columns if c in VOLATILE_KEYS]
        fa, fb = fa.drop(columns=drop), fb.drop(columns=drop)
        if list(fa.columns) != list(fb.columns) or len(fa) != len(fb):
            diffs.append(f"{a.name}:{name}: schema or feature count differ ({len(fa)} vs {len(fb)})")
            continue
        for c in fa.columns:
            if c == "geometry":
                if not all(
                    (ga is None and gb is None) or (ga is not None and ga.equals_exact(gb, 1e-9))
                    for ga, gb in zip(fa.geometry, fb.geometry)
                ):
                    diffs.append(f"{a.name}:{name}: geometries differ")
            elif not fa[c].equals(fb[c]):
                diffs.append(f"{a.name}:{name}: column {c} differs")
    return diffs


def compare_trees(a: Path, b: Path, ignore: tuple = ()) -> list[str]:
    """Differences between output folders ``a`` and ``b`` (empty list = same products)."""
    fa, fb = files(a, ignore), files(b, ignore)
    diffs = []
    if fa != fb:
        diffs.append(f"file sets differ: only in {a}: {sorted(fa - fb)}; only in {b}: {sorted(fb - fa)}")
    for rel in sorted(fa & fb):
        pa, pb = a / rel, b / rel
        ext = pa.suffix.lower()
        if pa.name == "geocd_products.json":
            # the output folder's run record: same products; run ids, times, argv and hashes (GeoPackages carry a
            # write time) differ by nature
            def products(p):
                runs = json.loads(p.read_text()).get("runs", [])
                return sorted(runs[-1].get("files", {})) if runs else []

            if products(pa) != products(pb):
                diffs.append(f"{rel}: product lists differ: {products(pa)} vs {products(pb)}")
        elif ext in RASTER_EXT:
            diffs += compare_raster(pa, pb)
        elif ext in VECTOR_EXT:
            diffs += compare_vector(pa, pb)
        elif ext in (".json", ".yaml", ".yml"):
            import yaml

            load = (
                (lambda p: json.loads(p.read_text())) if ext == ".json" else (lambda p: yaml.safe_load(p.read_text()))
            )
            if _strip(load(pa), str(a), str(b)) != _strip(load(pb), str(a), str(b)):
                diffs.append(f"{rel}: contents differ")
        elif ext == ".log":
            continue  # geocd_<command>.log: both runs keep one; clock times and paths differ
        elif ext in (".png", ".qml", ".txt", ".csv"):
            if ext != ".png" and pa.read_bytes() != pb.read_bytes():
                diffs.append(f"{rel}: bytes differ")
        elif pa.read_bytes() != pb.read_bytes():
            diffs.append(f"{rel}: bytes differ")
    return diffs
