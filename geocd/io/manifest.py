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
import math
import os
import reprlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

from ..errors import ConfigError, InputFileNotFoundError, ManifestError, UnsupportedFormatError
from .atomic import refuse_special_file
from .safe_yaml import YAMLLimitError, load_json, load_yaml

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
    extras: dict = field(default_factory=dict)


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
    extras: dict = field(default_factory=dict)

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

    def input_paths(self) -> list[Path]:
        """Every file the manifest names (and the manifest itself): inputs no output may replace."""
        out: list[Path] = [self.path] if self.path is not None else []
        for d in (self.dem, self.footprints):
            if d is not None:
                out.append(d.path)
        if self.aoi is not None and self.aoi.vector is not None:
            out.append(self.aoi.vector)
        for e in self.epochs:
            for im in e.images:
                out += [im.path] + ([im.camera] if im.camera is not None else [])
            if e.dem is not None:
                out.append(e.dem.path)
        for v in self.truth.values():
            if isinstance(v, (str, os.PathLike)):
                out.append(self.root / v)
        return out


def _err(where: str, what: str) -> ManifestError:
    return ManifestError(f"manifest {where}: {what}")


# =====================================================================================================
# the schema: ONE place that says which keys exist, at every depth, and what their values are.
# To add a key, add one line here; a key the parser below does not model is kept, validated, in
# ``Manifest.extras`` (top level) or ``Epoch.extras`` (an epoch).
# =====================================================================================================
class _Spec:
    """A value's expected form. ``check`` returns the (possibly converted) value or appends errors."""

    what = "a value"

    def check(self, v: Any, where: str, errs: list[str]) -> Any:  # pragma: no cover - overridden
        return v


class _Scalar(_Spec):
    what = "a text or a number"

    def check(self, v, where, errs):
        if isinstance(v, (dict, list, tuple)):
            errs.append(f"{where}: expected {self.what}, got a {type(v).__name__}")
        return v


class _Str(_Scalar):
    def __init__(self, choices: Sequence[str] | None = None, what: str = "a text") -> None:
        self.choices = tuple(choices) if choices else None
        self.what = what

    def check(self, v, where, errs):
        v = super().check(v, where, errs)
        if self.choices is not None and isinstance(v, str):
            norm = v.strip().lower().replace("-", "").replace(" ", "")
            if norm not in {c.lower().replace("-", "") for c in self.choices}:
                errs.append(f"{where}: {_r(v)} is not one of {', '.join(self.choices)}{_did_you_mean(v, self.choices)}")
        return v


class _Path(_Spec):
    what = "a file path"

    def check(self, v, where, errs):
        if not isinstance(v, (str, os.PathLike)) or not str(v).strip():
            errs.append(f"{where}: expected {self.what}, got {_r(v)}")
        return v


class _Num(_Spec):
    def __init__(self, positive: bool = False, unit: str = "", integer: bool = False) -> None:
        self.positive, self.unit, self.integer = positive, unit, integer
        self.what = ("an integer" if integer else "a number") + (f" ({unit})" if unit else "")

    def check(self, v, where, errs):
        x = v
        if isinstance(v, str):
            try:
                x = float(v.strip())
            except ValueError:
                x = None
        if isinstance(x, bool) or not isinstance(x, (int, float)):
            errs.append(f"{where}: expected {self.what}, got {_short(v)}")
            return None
        x = float(x)
        if not math.isfinite(x):
            errs.append(f"{where}: expected a finite number, got {_r(v)}")
            return None
        if self.integer and x != int(x):
            errs.append(f"{where}: expected an integer, got {_r(v)}")
            return None
        if self.positive and not x > 0:
            errs.append(f"{where}: must be positive, got {_r(v)}")
            return None
        return int(x) if self.integer else x


class _Date(_Spec):
    what = "a date (YYYY-MM-DD)"

    def check(self, v, where, errs):
        if isinstance(v, (dict, list, tuple, bool)):
            errs.append(f"{where}: expected {self.what}, got {_short(v)}")
        return v


class _List(_Spec):
    def __init__(self, item: _Spec, length: int | None = None, what: str = "") -> None:
        self.item, self.length = item, length
        self.what = what or (f"a list of {length} values" if length else "a list")

    def check(self, v, where, errs):
        if not isinstance(v, (list, tuple)):
            errs.append(f"{where}: expected {self.what}, got {_short(v)}")
            return v
        if self.length is not None and len(v) != self.length:
            errs.append(f"{where}: expected {self.what}, got {len(v)}")
            return v
        return [self.item.check(x, f"{where}[{i}]", errs) for i, x in enumerate(v)]


class _Map(_Spec):
    def __init__(
        self,
        fields: dict[str, _Spec] | None = None,
        required: Sequence[str] = (),
        free: bool = False,
        what: str = "a mapping",
    ) -> None:
        self.fields, self.required, self.free, self.what = dict(fields or {}), tuple(required), free, what

    def check(self, v, where, errs):
        if not isinstance(v, dict):
            errs.append(f"{where}: expected {self.what}, got {_short(v)}")
            return v
        if self.free:
            return v
        out = {}
        for k, x in v.items():
            w = f"{where}.{k}" if where else str(k)
            spec = self.fields.get(k)
            if spec is None:
                errs.append(
                    f"{w}: unknown key{_did_you_mean(str(k), self.fields)} (allowed here: {', '.join(self.fields)})"
                )
                continue
            out[k] = None if x is None else spec.check(x, w, errs)
        for k in self.required:
            if v.get(k) is None:
                errs.append(f"{where + '.' if where else ''}{k}: missing (required)")
        return out


class _Either(_Spec):
    """A path given directly, or a mapping with more detail (``dem: file.tif`` or ``dem: {path: ...}``)."""

    def __init__(self, *options: _Spec) -> None:
        self.options = options
        self.what = " or ".join(o.what for o in options)

    def check(self, v, where, errs):
        kinds = [o for o in self.options if isinstance(o, _Map) == isinstance(v, dict)]
        if not kinds:
            errs.append(f"{where}: expected {self.what}, got {_short(v)}")
            return v
        return kinds[0].check(v, where, errs)


class _OnOffOr(_Spec):
    """true / false / auto, or a mapping (``orientation: {model: shift}``)."""

    def __init__(self, mapping: "_Map") -> None:
        self.mapping = mapping
        self.what = f"true, false, auto or {mapping.what}"

    def check(self, v, where, errs):
        if isinstance(v, bool) or v == "auto":
            return v
        if isinstance(v, dict):
            n = len(errs)
            out = self.mapping.check(v, where, errs)
            if len(errs) == n:  # the keys are right: check the values where they are defined
                from ..errors import ConfigError
                from ..orientation.params import OrientationParams

                try:
                    OrientationParams.from_dict(out)
                except (ConfigError, TypeError, ValueError) as exc:
                    errs.append(f"{where}: {exc}")
            return out
        errs.append(f"{where}: expected {self.what}, got {_short(v)}")
        return v


_REPR = reprlib.Repr()
_REPR.maxstring = _REPR.maxother = 60
_REPR.maxlist = _REPR.maxtuple = _REPR.maxdict = 4
_REPR.maxlevel = 2


def _short(v: Any, n: int = 40) -> str:
    """A value for a message: never longer than ``n`` characters, never a walk of the whole value."""
    s = _clip(_REPR.repr(v), n)
    return s + (f" ({type(v).__name__})" if not isinstance(v, str) else "")


def _r(v: Any) -> str:
    """``repr(v)`` for a message, bounded (a value from a user's file can be arbitrarily large)."""
    return _clip(_REPR.repr(v), 80)


def _clip(s: str, n: int) -> str:
    return s if len(s) <= n else s[: n - 3] + "..."


def _did_you_mean(word: str, options) -> str:
    import difflib

    m = difflib.get_close_matches(word, list(options), n=1, cutoff=0.6)
    if not m:
        low = {o.lower(): o for o in options}
        m = [low[word.lower()]] if word.lower() in low else []
    return f"; did you mean {m[0]!r}?" if m else ""


VERTICAL_DATUMS = ("ellipsoid", "egm96", "egm2008")
ORIENTATION_KEYS = (
    "enabled",
    "model",
    "gauge",
    "prior_shift_px",
    "prior_linear_px",
    "max_offset_m",
    "height_span_m",
    "patch_px",
    "block_px",
    "min_ncc",
    "min_points",
    "min_spread",
    "min_correction_px",
    "reject_k",
    "max_ortho_px",
)
_DEM_MAP = _Map(
    {"path": _Path(), "vertical_datum": _Str(what="a vertical datum name"), "layer": _Scalar()},
    required=("path",),
    what="a mapping with 'path'",
)
_VECTOR_MAP = _Map({"path": _Path(), "layer": _Scalar()}, required=("path",), what="a mapping with 'path'")
_IMAGE = _Either(
    _Path(),
    _Map({"path": _Path(), "camera": _Path(), "name": _Scalar()}, required=("path",), what="a mapping with 'path'"),
)

#: every key a manifest may hold (see the module docstring for their meaning)
SCHEMA = _Map(
    {
        "geocd_manifest": _Num(integer=True),
        "name": _Scalar(),
        "description": _Scalar(),
        "scene_class": _Scalar(),
        "aoi": _Map(
            {
                "crs": _Scalar(),
                "bounds": _List(_Num(), length=4, what="[left, bottom, right, top] (4 numbers)"),
                "posting_m": _Num(positive=True, unit="metres"),
                "vector": _Path(),
            }
        ),
        "output": _Path(),
        "dem": _Either(_Path(), _DEM_MAP),
        "footprints": _Either(_Path(), _VECTOR_MAP),
        "epochs": _List(
            _Map(
                {
                    "name": _Scalar(),
                    "date": _Date(),
                    "sensor": _Scalar(),
                    "images": _List(_IMAGE),
                    "dem": _Either(_Path(), _DEM_MAP),
                },
                what="a mapping with name, date, images",
            )
        ),
        "truth": _Map(free=True),
        # cross-image relative orientation (geocd.orientation.OrientationParams fields)
        "orientation": _OnOffOr(
            _Map({k: _Scalar() for k in ORIENTATION_KEYS}, what="a mapping of orientation settings")
        ),
    },
    what="a mapping",
)


def validate_manifest_data(data: Any, path: Path | None = None) -> dict:
    """Check a parsed manifest against :data:`SCHEMA`; every problem is reported at once.

    Unknown keys at any depth are errors with a "did you mean" suggestion; numbers must be numbers.

    Raises
    ------
    ManifestError
    """
    errs: list[str] = []
    if not isinstance(data, dict):
        raise ManifestError(f"manifest {path or ''} must be a mapping at the top level, got {type(data).__name__}")
    out = SCHEMA.check(data, "", errs)
    if errs:
        head = f"manifest {path}" if path is not None else "manifest"
        n = len(errs)
        shown = "; ".join(errs[:6]) + (f"; and {n - 6} more" if n > 6 else "")
        raise ManifestError(f"{head}: {shown}" if n == 1 else f"{head} has {n} problems: {shown}")
    return out


def _path(root: Path, value: Any, where: str, must_exist: bool = True) -> Path:
    if not isinstance(value, (str, os.PathLike)) or not str(value).strip():
        raise _err(where, f"expected a file path, got {_r(value)}")
    p = Path(value)
    p = p if p.is_absolute() else root / p
    if must_exist and not p.exists():
        raise _err(
            where, f"file {p} does not exist; fix the path (relative paths are relative to the manifest's folder)"
        )
    try:
        refuse_special_file(p, "file")
    except UnsupportedFormatError as exc:
        raise _err(where, str(exc)) from None
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
        raise _err(where, f"date {_r(value)} is not ISO 8601 (YYYY-MM-DD)") from exc


def _datum(value: Any, where: str) -> str | None:
    if value is None:
        return None
    from ..geodesy import normalize_datum_name

    n = normalize_datum_name(str(value))
    if n not in VERTICAL_DATUMS:
        raise _err(
            where,
            f"unknown vertical datum {_r(value)}; use one of {', '.join(VERTICAL_DATUMS)}"
            f"{_did_you_mean(str(value).lower(), VERTICAL_DATUMS)}",
        )
    return str(value)


def _dem_spec(root: Path, value: Any, where: str) -> DEMSpec | None:
    if value is None:
        return None
    if isinstance(value, (str, os.PathLike)):
        return DEMSpec(_path(root, value, where))
    return DEMSpec(
        _path(root, value["path"], f"{where}.path"),
        _datum(value.get("vertical_datum"), f"{where}.vertical_datum"),
        None if value.get("layer") is None else str(value["layer"]),
    )


_MODELLED_TOP = {
    "geocd_manifest",
    "name",
    "description",
    "scene_class",
    "aoi",
    "output",
    "dem",
    "footprints",
    "epochs",
    "truth",
}
_MODELLED_EPOCH = {"name", "date", "sensor", "images", "dem"}


def parse_manifest(data: Any, root: Path, path: Path | None = None) -> Manifest:
    """Validate a manifest mapping (already parsed from YAML/JSON)."""
    data = validate_manifest_data(data, path)
    version = data.get("geocd_manifest", 1)
    if version != 1:
        raise ManifestError(f"manifest version {_r(version)} is not supported by this geocd (expects 1); upgrade geocd")
    epochs_raw = data.get("epochs")
    if not isinstance(epochs_raw, list) or not epochs_raw:
        raise ManifestError("manifest needs 'epochs': a non-empty list of {name, date, images}")
    epochs = []
    names = set()
    for i, e in enumerate(epochs_raw):
        where = f"epochs[{i}]"
        name = str(e.get("name") if e.get("name") is not None else f"epoch{i + 1}")
        if name in names:
            raise _err(where, f"duplicate epoch name {_r(name)}")
        names.add(name)
        imgs = []
        for j, im in enumerate(e.get("images") or []):
            w = f"{where}.images[{j}]"
            if isinstance(im, (str, os.PathLike)):
                im = {"path": im}
            p = _path(root, im["path"], f"{w}.path")
            cam = _path(root, im["camera"], f"{w}.camera") if im.get("camera") else None
            imgs.append(ImageSpec(p, cam, str(im.get("name") if im.get("name") is not None else p.stem)))
        dem = _dem_spec(root, e.get("dem"), f"{where}.dem")
        if not imgs and dem is None:
            raise _err(where, "has neither images nor a DEM; give at least one")
        extras = {k: v for k, v in e.items() if k not in _MODELLED_EPOCH}
        epochs.append(
            Epoch(
                name,
                _date(e.get("date"), f"{where}.date"),
                tuple(imgs),
                str(e.get("sensor") if e.get("sensor") is not None else ""),
                dem,
                extras,
            )
        )
    _check_epoch_order(epochs)
    _check_unique_images(epochs)
    aoi = None
    if data.get("aoi") is not None:
        a = data["aoi"]
        bounds = a.get("bounds")
        if bounds is not None:
            bounds = tuple(float(b) for b in bounds)
            if not (bounds[2] > bounds[0] and bounds[3] > bounds[1]):
                raise _err("aoi.bounds", f"{bounds} is empty: right must exceed left and top bottom")
        posting = a.get("posting_m")
        vec = _path(root, a["vector"], "aoi.vector") if a.get("vector") else None
        crs = a.get("crs")
        if crs is not None:
            from ..errors import CRSError
            from ..geodesy import as_crs

            try:
                as_crs(crs)
            except (CRSError, ValueError, TypeError) as exc:
                raise _err(
                    "aoi.crs", f"{_r(crs)} is not a coordinate reference system ({exc}); use e.g. EPSG:32631"
                ) from None
        aoi = AOISpec(None if crs is None else str(crs), bounds, float(posting) if posting is not None else None, vec)
    output = data.get("output")
    out = (root / output) if output else None
    fp = data.get("footprints")
    return Manifest(
        path=path,
        name=str(data.get("name") if data.get("name") is not None else root.name),
        epochs=tuple(epochs),
        aoi=aoi,
        output=None if out is None else (out if out.is_absolute() else out.resolve()),
        dem=_dem_spec(root, data.get("dem"), "dem"),
        footprints=_dem_spec(root, fp, "footprints"),
        scene_class=str(data.get("scene_class") or ""),
        truth=dict(data.get("truth") or {}),
        extras={k: v for k, v in data.items() if k not in _MODELLED_TOP},
    )


def _check_epoch_order(epochs: Sequence[Epoch]) -> None:
    """Epochs listed against their dates are refused: which one is "before" would be a guess."""
    dated = [e for e in epochs if e.date is not None]
    for prev, nxt in zip(dated, dated[1:]):
        if nxt.date < prev.date:
            raise ManifestError(
                f"manifest epochs: {nxt.name!r} ({nxt.date}) is listed after {prev.name!r} ({prev.date}) but dated "
                "before it; list the epochs in date order (earliest first), or fix the dates"
            )


def _check_unique_images(epochs: Sequence[Epoch]) -> None:
    """Each image name once per epoch (products such as pair DEMs are named after the images: a second
    image of the same name would overwrite the first's) and each image file once in the whole manifest
    (the same file as two images, or in two epochs, compares an image with itself)."""
    files: dict[Any, str] = {}
    for i, e in enumerate(epochs):
        names: dict[str, str] = {}
        for j, im in enumerate(e.images):
            where = f"epochs[{i}].images[{j}] ({im.path.name})"
            if im.name in names:
                raise ManifestError(
                    f"manifest: {where} and {names[im.name]} of epoch {e.name!r} have the same image name "
                    f"{_r(im.name)}; products are named after the images, so give each a distinct 'name:'"
                )
            names[im.name] = where
            key = _file_key(im.path)
            if key in files:
                raise ManifestError(
                    f"manifest: {where} and {files[key]} are the same file {im.path}; list each image once (an "
                    "image compared with itself shows no change)"
                )
            files[key] = f"epochs[{i}].images[{j}]"


def _file_key(p: Path) -> Any:
    """What identifies a file: device and inode (hard links, symlinks, ``a/../b``), else the resolved path."""
    try:
        st = p.stat()
        return (st.st_dev, st.st_ino)
    except OSError:
        return str(p.resolve())


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
    refuse_special_file(p, "manifest")
    if p.is_dir():
        for name in ("scene.yaml", "scene.yml", "manifest.yaml", "manifest.yml", "scene.json", "manifest.json"):
            if (p / name).is_file():
                return load_manifest(p / name)
        return discover_manifest(p)
    raw = p.read_bytes()
    if b"\x00" in raw[:4096]:
        raise ManifestError(
            f"{p} is not a manifest: it is a binary file (an image?); give a scene manifest "
            "(scene.yaml) or a folder of images"
        )
    text = raw.decode("utf-8", errors="replace")
    try:
        data = load_json(text) if p.suffix.lower() == ".json" else load_yaml(text)
    except YAMLLimitError as exc:
        raise ManifestError(f"manifest {p}: {_clip(str(exc), 300)}") from None
    except Exception as exc:
        first = _clip(" ".join(str(exc).split()), 200)
        raise ManifestError(f"manifest {p} is not valid YAML/JSON ({first}); fix the syntax") from None
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
    # a folder of geocd products (an earlier run's output) is not an epoch of images
    for sub in sorted(
        d
        for d in root.iterdir()
        if d.is_dir() and not d.name.startswith(".") and not (d / "geocd_products.json").exists()
    ):
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
    if epochs:
        _check_unique_images(epochs)
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
        a = {
            k: v
            for k, v in (
                ("crs", m.aoi.crs),
                ("bounds", list(m.aoi.bounds) if m.aoi.bounds else None),
                ("posting_m", m.aoi.posting_m),
                ("vector", rel(m.aoi.vector)),
            )
            if v is not None
        }
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
        ed["images"] = [
            ({"path": rel(i.path), "camera": rel(i.camera)} if i.camera else {"path": rel(i.path)}) for i in e.images
        ]
        if e.dem is not None:
            ed["dem"] = dem(e.dem)
        d["epochs"].append(ed)
    if m.truth:
        d["truth"] = m.truth
    return d


def pick_epochs(manifest, epoch_a: str | None = None, epoch_b: str | None = None):
    """The two epochs to compare (explicit, else first and last by date/order)."""
    eps = list(manifest.epochs)
    if len(eps) < 2 and not (epoch_a and epoch_b):
        raise ConfigError(f"change detection needs two epochs; the manifest has {len(eps)}")
    if all(e.date for e in eps):
        eps = sorted(eps, key=lambda e: e.date)
    a = manifest.epoch(epoch_a) if epoch_a else eps[0]
    b = manifest.epoch(epoch_b) if epoch_b else eps[-1]
    if a.name == b.name:
        raise ConfigError(f"epoch_a and epoch_b are both {a.name!r}; pick two different epochs")
    if a.date is not None and b.date is not None and a.date > b.date:
        raise ConfigError(
            f"epoch_a {a.name!r} ({a.date}) is dated after epoch_b {b.name!r} ({b.date}): the change "
            "would be computed backwards; swap --epoch-a and --epoch-b, or fix the dates"
        )
    return a, b
