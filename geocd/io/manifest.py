"""Scene manifest: what a geocd run processes.

A manifest is a YAML (or JSON) file; relative paths are relative to its folder::

    geocd_manifest: 1
    name: sample_aoi
    scene_class: suburban            # optional, for self-consistency models
    aoi:                             # optional: default = overlap of the images
      crs: EPSG:32735
      bounds: [left, bottom, right, top]   # in aoi.crs
      posting_m: 0.5
    output: out                      # relative to the manifest's folder; default: ./geocd_out/<name>
    dem:                             # optional prior DEM (height search range)
      path: truth/dem_bare.tif
      vertical_datum: ellipsoid      # ellipsoid | egm96 | egm2008 (default: from the file's CRS)
    footprints: truth/footprints.gpkg   # or {path: ..., layer: ...}
    epochs:
      - name: A
        date: 2024-05-01
        sensor: pushbroom-sim        # optional
        images:
          - path: images/A_sat1.tif          # camera discovered (RPC tags or sidecar)
          - path: images/A_air1.tif
            camera: images/A_air1.camera.json
        dem: null                    # optional: a DEM standing for this epoch
      - name: B
        ...
    truth: {...}                     # optional, free-form paths (the simulator writes them)

:func:`discover_manifest` builds one from a plain folder: sub-folders are epochs
(sorted by name), or all images form one epoch.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..errors import InputFileNotFoundError, ManifestError

IMAGE_SUFFIXES = (".tif", ".tiff", ".ntf", ".nitf", ".jp2", ".img", ".vrt")


@dataclass(frozen=True)
class ImageSpec:
    path: Path
    camera: Path | None = None
    name: str = ""


@dataclass(frozen=True)
class DEMSpec:
    path: Path
    vertical_datum: str | None = None
    layer: str | None = None


@dataclass(frozen=True)
class Epoch:
    name: str
    date: _dt.date | None
    images: tuple[ImageSpec, ...]
    sensor: str = ""
    dem: DEMSpec | None = None


@dataclass(frozen=True)
class AOISpec:
    crs: str | None = None
    bounds: tuple[float, float, float, float] | None = None
    posting_m: float | None = None
    vector: Path | None = None


@dataclass(frozen=True)
class Manifest:
    path: Path | None
    name: str
    epochs: tuple[Epoch, ...]
    aoi: AOISpec | None = None
    output: Path | None = None
    dem: DEMSpec | None = None
    footprints: DEMSpec | None = None
    scene_class: str = ""
    truth: dict = field(default_factory=dict)

    @property
    def root(self) -> Path:
        return self.path.parent if self.path is not None else Path.cwd()

    def output_dir(self) -> Path:
        """Where results go when no output folder is given: the manifest's ``output:`` if it names one, else
        ``./geocd_out/<name>`` in the current directory (never inside the input folder by default)."""
        return self.output if self.output is not None else default_output_dir(self.name)

    def epoch(self, name: str) -> Epoch:
        for e in self.epochs:
            if e.name == name:
                return e
        raise ManifestError(f"epoch {name!r} is not in the manifest; epochs are {[e.name for e in self.epochs]}")

    def truth_path(self, key: str) -> Path | None:
        v = self.truth.get(key)
        return None if v is None else (self.root / v)


def _err(where: str, what: str) -> ManifestError:
    return ManifestError(f"manifest {where}: {what}")


def _path(root: Path, value: Any, where: str, must_exist: bool = True) -> Path:
    if not isinstance(value, (str, os.PathLike)) or not str(value).strip():
        raise _err(where, f"expected a file path, got {value!r}")
    p = Path(value)
    p = p if p.is_absolute() else root / p
    if must_exist and not p.exists():
        raise _err(where, f"file {p} does not exist; fix the path (relative paths are relative to the manifest's folder)")
    return p


def _date(value: Any, where: str) -> _dt.date | None:
    if value is None or value == "":
        return None
    if isinstance(value, _dt.datetime):
        return value.date()
    if isinstance(value, _dt.date):
        return value
    try:
        return _dt.date.fromisoformat(str(value)[:10])
    except ValueError as exc:
        raise _err(where, f"date {value!r} is not ISO 8601 (YYYY-MM-DD)") from exc


def _dem_spec(root: Path, value: Any, where: str) -> DEMSpec | None:
    if value is None:
        return None
    if isinstance(value, (str, os.PathLike)):
        return DEMSpec(_path(root, value, where))
    if isinstance(value, dict):
        if "path" not in value:
            raise _err(where, "needs a 'path'")
        unknown = set(value) - {"path", "vertical_datum", "layer"}
        if unknown:
            raise _err(where, f"unknown keys {sorted(unknown)}; allowed: path, vertical_datum, layer")
        return DEMSpec(_path(root, value["path"], f"{where}.path"), value.get("vertical_datum"), value.get("layer"))
    raise _err(where, f"expected a path or a mapping with 'path', got {type(value).__name__}")


def parse_manifest(data: Any, root: Path, path: Path | None = None) -> Manifest:
    """Validate a manifest mapping (already parsed from YAML/JSON)."""
    if not isinstance(data, dict):
        raise ManifestError(f"manifest {path or ''} must be a mapping at the top level, got {type(data).__name__}")
    known = {"geocd_manifest", "name", "description", "scene_class", "aoi", "output", "dem", "footprints",
             "epochs", "truth"}
    unknown = set(data) - known
    if unknown:
        raise ManifestError(f"manifest has unknown keys {sorted(unknown)}; allowed: {sorted(known)}")
    version = data.get("geocd_manifest", 1)
    if version != 1:
        raise ManifestError(f"manifest version {version!r} is not supported by this geocd (expects 1); upgrade geocd")
    epochs_raw = data.get("epochs")
    if not isinstance(epochs_raw, list) or not epochs_raw:
        raise ManifestError("manifest needs 'epochs': a non-empty list of {name, date, images}")
    epochs = []
    names = set()
    for i, e in enumerate(epochs_raw):
        where = f"epochs[{i}]"
        if not isinstance(e, dict):
            raise _err(where, "must be a mapping with name, date, images")
        name = str(e.get("name", f"epoch{i + 1}"))
        if name in names:
            raise _err(where, f"duplicate epoch name {name!r}")
        names.add(name)
        imgs_raw = e.get("images", [])
        if not isinstance(imgs_raw, list):
            raise _err(f"{where}.images", "must be a list")
        imgs = []
        for j, im in enumerate(imgs_raw):
            w = f"{where}.images[{j}]"
            if isinstance(im, (str, os.PathLike)):
                im = {"path": im}
            if not isinstance(im, dict) or "path" not in im:
                raise _err(w, "needs a 'path'")
            p = _path(root, im["path"], f"{w}.path")
            cam = _path(root, im["camera"], f"{w}.camera") if im.get("camera") else None
            imgs.append(ImageSpec(p, cam, str(im.get("name", p.stem))))
        dem = _dem_spec(root, e.get("dem"), f"{where}.dem")
        if not imgs and dem is None:
            raise _err(where, "has neither images nor a DEM; give at least one")
        epochs.append(Epoch(name, _date(e.get("date"), f"{where}.date"), tuple(imgs), str(e.get("sensor", "")), dem))
    aoi = None
    if data.get("aoi") is not None:
        a = data["aoi"]
        if not isinstance(a, dict):
            raise _err("aoi", "must be a mapping (crs, bounds, posting_m) or (vector)")
        bounds = a.get("bounds")
        if bounds is not None:
            if not (isinstance(bounds, (list, tuple)) and len(bounds) == 4):
                raise _err("aoi.bounds", "must be [left, bottom, right, top]")
            bounds = tuple(float(b) for b in bounds)
            if not (bounds[2] > bounds[0] and bounds[3] > bounds[1]):
                raise _err("aoi.bounds", f"{bounds} is empty: right must exceed left and top bottom")
        posting = a.get("posting_m")
        if posting is not None and not (float(posting) > 0):
            raise _err("aoi.posting_m", f"must be positive, got {posting}")
        vec = _path(root, a["vector"], "aoi.vector") if a.get("vector") else None
        aoi = AOISpec(a.get("crs"), bounds, float(posting) if posting is not None else None, vec)
    output = data.get("output")
    out = (root / output) if output else None
    return Manifest(
        path=path, name=str(data.get("name", root.name)), epochs=tuple(epochs), aoi=aoi,
        output=None if out is None else (out if out.is_absolute() else out.resolve()), dem=_dem_spec(root, data.get("dem"), "dem"),
        footprints=_dem_spec(root, data.get("footprints"), "footprints"),
        scene_class=str(data.get("scene_class", "")), truth=dict(data.get("truth") or {}),
    )


def default_output_dir(name: str) -> Path:
    """``./geocd_out/<name>``: the default output folder of a scene or command (in the current directory)."""
    safe = "".join(c if (c.isalnum() or c in "-_.") else "_" for c in str(name)).strip("._") or "scene"
    return Path.cwd() / "geocd_out" / safe


def load_manifest(path: os.PathLike | str) -> Manifest:
    """Read and validate a manifest file, or discover one from a folder.

    A folder with ``scene.yaml`` (or ``manifest.yaml``/``.json``) uses that file;
    another folder is discovered (:func:`discover_manifest`).
    """
    p = Path(path)
    if not p.exists():
        raise InputFileNotFoundError(f"{p} does not exist; give a manifest file (scene.yaml) or a folder of images")
    if p.is_dir():
        for name in ("scene.yaml", "scene.yml", "manifest.yaml", "manifest.yml", "scene.json", "manifest.json"):
            if (p / name).is_file():
                return load_manifest(p / name)
        return discover_manifest(p)
    text = p.read_text(encoding="utf-8", errors="replace")
    try:
        if p.suffix.lower() == ".json":
            data = json.loads(text)
        else:
            import yaml

            data = yaml.safe_load(text)
    except Exception as exc:
        raise ManifestError(f"{p} is not valid YAML/JSON ({exc}); fix the syntax") from exc
    return parse_manifest(data, p.parent.resolve(), p.resolve())


def discover_manifest(folder: os.PathLike | str) -> Manifest:
    """Build a manifest from a plain folder of images.

    Sub-folders holding images are epochs (named after the folder; a leading
    ISO date in the name becomes the epoch date); otherwise all images in the
    folder form one epoch. Images without a camera model are skipped.
    """
    root = Path(folder).resolve()

    def images_in(d: Path) -> list[ImageSpec]:
        out = []
        for f in sorted(d.iterdir()):
            if f.is_file() and f.suffix.lower() in IMAGE_SUFFIXES and not f.name.startswith("."):
                out.append(ImageSpec(f, None, f.stem))
        return out

    epochs = []
    for sub in sorted(d for d in root.iterdir() if d.is_dir() and not d.name.startswith(".")):
        imgs = images_in(sub)
        if imgs:
            date = None
            try:
                date = _dt.date.fromisoformat(sub.name[:10])
            except ValueError:
                pass
            epochs.append(Epoch(sub.name, date, tuple(imgs)))
    if not epochs:
        imgs = images_in(root)
        if imgs:
            epochs.append(Epoch(root.name, None, tuple(imgs)))
    if not epochs:
        raise ManifestError(
            f"{root} holds no manifest (scene.yaml) and no images ({', '.join(IMAGE_SUFFIXES)}); "
            "write a scene.yaml (see geocd.io.manifest) or point at a folder of images"
        )
    return Manifest(path=None, name=root.name, epochs=tuple(epochs))


def manifest_to_dict(m: Manifest) -> dict:
    """Serialisable form (paths relative to the manifest's folder when possible)."""
    root = m.root

    def rel(p: Path | None) -> str | None:
        if p is None:
            return None
        try:
            return os.path.relpath(p, root)
        except ValueError:
            return str(p)

    def dem(d: DEMSpec | None):
        if d is None:
            return None
        out = {"path": rel(d.path)}
        if d.vertical_datum:
            out["vertical_datum"] = d.vertical_datum
        if d.layer:
            out["layer"] = d.layer
        return out

    d: dict[str, Any] = {"geocd_manifest": 1, "name": m.name}
    if m.scene_class:
        d["scene_class"] = m.scene_class
    if m.aoi is not None:
        a = {k: v for k, v in (("crs", m.aoi.crs), ("bounds", list(m.aoi.bounds) if m.aoi.bounds else None),
                                 ("posting_m", m.aoi.posting_m), ("vector", rel(m.aoi.vector))) if v is not None}
        d["aoi"] = a
    if m.output is not None:
        d["output"] = rel(m.output)
    if m.dem is not None:
        d["dem"] = dem(m.dem)
    if m.footprints is not None:
        d["footprints"] = dem(m.footprints)
    d["epochs"] = []
    for e in m.epochs:
        ed: dict[str, Any] = {"name": e.name}
        if e.date:
            ed["date"] = e.date.isoformat()
        if e.sensor:
            ed["sensor"] = e.sensor
        ed["images"] = [({"path": rel(i.path), "camera": rel(i.camera)} if i.camera else {"path": rel(i.path)})
                        for i in e.images]
        if e.dem is not None:
            ed["dem"] = dem(e.dem)
        d["epochs"].append(ed)
    if m.truth:
        d["truth"] = m.truth
    return d
