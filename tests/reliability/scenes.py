"""Tiny inputs for the fault matrix: DEM pairs, a two-epoch RPC scene (no rendering: only geometry matters
for faults caught before matching), RPC files with implausible values, and the checks every case shares."""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from geocd.io.outputs import PART_RE

from tests.stereo.synthetic import LAT0, LON0, affine_rpc

REPO = Path(__file__).resolve().parents[2]


def sha256_tree(paths) -> dict[str, str]:
    """sha256 of every file among ``paths`` (files, or folders walked recursively)."""
    out = {}
    for p in map(Path, paths):
        files = [p] if p.is_file() else sorted(q for q in p.rglob("*") if q.is_file()) if p.is_dir() else []
        for f in files:
            out[str(f)] = hashlib.sha256(f.read_bytes()).hexdigest()
    return out


def part_files(root: Path) -> list[Path]:
    return [p for p in Path(root).rglob("*") if PART_RE.match(p.name)]


def error_lines(text: str) -> list[str]:
    return [ln for ln in text.splitlines() if ln.startswith("geocd: error:")]


# ------------------------------------------------------------------------------------------------------------
# DEMs
# ------------------------------------------------------------------------------------------------------------
def write_dem_pair(folder: Path, rows: int = 40, cols: int = 48) -> tuple[Path, Path]:
    from tests.demdiff.synthetic import grid, pair

    from geocd.io.raster import write_cog

    folder.mkdir(parents=True, exist_ok=True)
    a, b, _ = pair(g=grid(rows, cols), bump_m=20.0, bump_radius_px=5)
    return write_cog(folder / "a.tif", a.height_m, a.grid), write_cog(folder / "b.tif", b.height_m, b.grid)


def write_rgb(folder: Path, like: Path) -> Path:
    """A 3-band uint8 RGB image on the grid of the DEM ``like`` (what a user might pick by mistake)."""
    import rasterio

    with rasterio.open(like) as ds:
        prof = ds.profile.copy()
    prof.update(count=3, dtype="uint8", nodata=None, photometric="RGB", driver="GTiff")
    for k in ("blockxsize", "blockysize", "tiled", "interleave", "compress"):
        prof.pop(k, None)
    p = folder / "photo_rgb.tif"
    rng = np.random.default_rng(0)
    with rasterio.open(p, "w", **prof) as dst:
        dst.write(rng.integers(0, 255, size=(3, prof["height"], prof["width"])).astype(np.uint8))
    return p


def write_footprints(path: Path, dem: Path) -> Path:
    import geopandas as gpd
    import rasterio
    from shapely.geometry import box

    with rasterio.open(dem) as ds:
        l, b, r, t = ds.bounds
        crs = ds.crs
    cx, cy = 0.5 * (l + r), 0.5 * (b + t)
    gdf = gpd.GeoDataFrame(
        {"building_id": [1, 2]},
        geometry=[box(cx - 30, cy - 30, cx + 30, cy + 30), box(l + 20, b + 20, l + 60, b + 60)],
        crs=crs,
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    gdf.to_file(path)
    return path


# ------------------------------------------------------------------------------------------------------------
# a two-epoch RPC scene (geometry only)
# ------------------------------------------------------------------------------------------------------------
@dataclass
class Scene:
    root: Path
    manifest: Path
    doc: dict
    aoi_bounds: tuple
    crs: str
    files: list[Path] = field(default_factory=list)

    def write(self, name: str = "scene.yaml", **changes) -> Path:
        """A variant of the manifest (top-level keys replaced; ``None`` removes a key)."""
        doc = dict(self.doc)
        for k, v in changes.items():
            if v is None:
                doc.pop(k, None)
            else:
                doc[k] = v
        p = self.root / name
        p.write_text(yaml.safe_dump(doc, sort_keys=False))
        return p


def make_scene(root: Path, size_m: float = 40.0) -> Scene:
    """Two epochs (A 2023-06-01, B 2024-06-01) of two RPC images each (random 11-bit pixels), a flat prior DEM
    and footprints; AOI = ``size_m`` square around the cameras' centre."""
    from geocd.geodesy import AOIGrid, from_lonlat, utm_crs_for
    from geocd.io.raster import write_cog, write_image

    root.mkdir(parents=True, exist_ok=True)
    img_dir = root / "images"
    img_dir.mkdir(exist_ok=True)
    crs = utm_crs_for(LON0, LAT0)
    xc, yc = from_lonlat(LON0, LAT0, crs)
    xc, yc = float(xc), float(yc)
    bounds = (xc - size_m / 2, yc - size_m / 2, xc + size_m / 2, yc + size_m / 2)
    npx = int(size_m / 0.5) + 40
    rng = np.random.default_rng(3)
    epochs = []
    files = []
    for ep, date, pars in (
        ("A", "2023-06-01", ((0.55, 0.05), (-0.45, 0.02))),
        ("B", "2024-06-01", ((0.50, 0.04), (-0.40, 0.03))),
    ):
        imgs = []
        for k, par in enumerate(pars):
            cam = affine_rpc(0.5, par, npx, npx)
            img = rng.integers(300, 1800, size=(1, npx, npx)).astype(np.uint16)
            p = write_image(img_dir / f"{ep}_{k}.tif", img, rpc=cam, nbits=11)
            files.append(p)
            imgs.append({"path": f"images/{p.name}", "name": p.stem})
        epochs.append({"name": ep, "date": date, "images": imgs})
    g = AOIGrid.from_bounds(bounds[0] - 40, bounds[1] - 40, bounds[2] + 40, bounds[3] + 40, 2.0, crs)
    dem = write_cog(root / "dem.tif", np.full(g.shape, 200.0, np.float32), g, tags={"vertical_datum": "ellipsoid"})
    fp = write_footprints(root / "footprints.gpkg", dem)
    files += [dem, fp]
    doc = {
        "geocd_manifest": 1,
        "name": "faults",
        "aoi": {"crs": crs.to_string(), "bounds": [float(v) for v in bounds], "posting_m": 1.0},
        "dem": {"path": "dem.tif", "vertical_datum": "ellipsoid"},
        "footprints": "footprints.gpkg",
        "epochs": epochs,
    }
    sc = Scene(root, root / "scene.yaml", doc, bounds, crs.to_string(), files)
    sc.write()
    files.append(sc.manifest)
    return sc


# ------------------------------------------------------------------------------------------------------------
# RPC text files with one implausible value
# ------------------------------------------------------------------------------------------------------------
def rpc_txt(path: Path, **override) -> Path:
    """An IKONOS-style ``_rpc.txt`` of the synthetic affine camera, with fields overridden (as text)."""
    cam = affine_rpc(0.5, (0.5, 0.05), 120, 120)
    vals = {
        "LINE_OFF": cam.line_off,
        "SAMP_OFF": cam.samp_off,
        "LAT_OFF": cam.lat_off,
        "LONG_OFF": cam.lon_off,
        "HEIGHT_OFF": cam.height_off,
        "LINE_SCALE": cam.line_scale,
        "SAMP_SCALE": cam.samp_scale,
        "LAT_SCALE": cam.lat_scale,
        "LONG_SCALE": cam.lon_scale,
        "HEIGHT_SCALE": cam.height_scale,
    }
    lines = []
    for k, v in vals.items():
        lines.append(f"{k}: {override.get(k, repr(float(v)))}")
    for name, arr in (
        ("LINE_NUM_COEFF", cam.line_num),
        ("LINE_DEN_COEFF", cam.line_den),
        ("SAMP_NUM_COEFF", cam.samp_num),
        ("SAMP_DEN_COEFF", cam.samp_den),
    ):
        for i, c in enumerate(arr, start=1):
            key = f"{name}_{i}"
            lines.append(f"{key}: {override.get(key, repr(float(c)))}")
    path.write_text("\n".join(lines) + "\n")
    return path


def env_without_pam() -> dict:
    return {**os.environ, "GDAL_PAM_ENABLED": "NO"}


# ------------------------------------------------------------------------------------------------------------
# the bad-input matrices: a registry of cases, and the checks every case shares
# ------------------------------------------------------------------------------------------------------------
class Cases(dict):
    """``CASES = Cases()``; ``@CASES.case("name")`` registers ``fn(fx, tmp) -> dict`` with keys ``args`` (the
    command line), ``first`` (text of the one error line), and optionally ``inputs`` (files that must stay
    byte-identical), ``out`` (a folder that must get no new file), ``code`` (exit status, 2)."""

    def case(self, name: str):
        def reg(fn):
            self[name] = fn
            return fn

        return reg


def run_case(c: dict, root: Path, tmp_path: Path, around=None):
    """Run one matrix case in-process and check what every case must hold: the exit status, one
    ``geocd: error:`` line holding ``c["first"]``, no traceback, no ``.part`` file, every watched input unchanged
    and nothing new in ``c["out"]``. ``around``: a context manager wrapped around the run (a watchdog).
    Returns (click result, seconds)."""
    import contextlib
    import time

    from click.testing import CliRunner

    from geocd.cli import main

    watched = [root, *c.get("inputs", [])]
    before = sha256_tree(watched)
    out = c.get("out")
    existing = set(Path(out).rglob("*")) if out is not None and Path(out).exists() else set()
    t = time.perf_counter()
    with around if around is not None else contextlib.nullcontext():
        r = CliRunner().invoke(main, ["--progress", "none", *map(str, c["args"])])
    took = time.perf_counter() - t
    assert r.exit_code == c.get("code", 2), f"exit {r.exit_code}:\n{r.output}"
    errs = error_lines(r.stderr)
    assert len(errs) == 1, r.stderr
    assert c["first"] in errs[0], errs[0]
    assert c.get("absent") is None or c["absent"] not in errs[0], errs[0]
    assert "Traceback" not in r.output
    assert not part_files(tmp_path) and not part_files(root)
    assert sha256_tree(watched) == before, "an input changed"
    if out is not None and Path(out).exists():
        new = [p for p in Path(out).rglob("*") if p not in existing and p.is_file()]
        assert not new, f"files written by a failed run: {new}"
    return r, took
