"""Read RPC camera models from every vendor format.

Every reader returns a :class:`geocd.camera.RPCModel` (RPC00B term order, pixel
origin at the upper-left *corner*, see :mod:`geocd.camera.rpc`) whose ``source``
says which file and which format it came from.

Formats (recognised by their content; the extension is only a fallback):

* GeoTIFF / NITF (RPC00B or RPC00A TRE) / any GDAL raster with RPC metadata, via rasterio;
* IKONOS, Planet, SkySat ``_rpc.txt`` / ``_RPC.TXT`` (``LINE_OFF: ...`` lines);
* DigitalGlobe ``.RPB`` (``lineOffset = ...;``, lists in parentheses);
* DigitalGlobe / Maxar XML (``<RPB><IMAGE>`` with ``LINENUMCOEFList``; coefficients either
  as one space-separated list or one element each);
* Pléiades / SPOT-6/7 DIMAP v2 ``RPC_*.XML`` (``Global_RFM/Inverse_Model`` = ground → image;
  DIMAP pixels are 1-based, so 1 is subtracted from the line/sample offsets);
* OSSIM keyword-list ``.geom`` (``polynomial_format`` A or B, ``line_num_coeff_00`` ...);
* Sat-NeRF / DFC2019 JSON (``{"rpc": {"row_offset": ..., "row_num": [...]}}``, rpcm's dict);
* orthority YAML/JSON (``{image_name: {im_size: [w, h], rpc: {line_num_coeff: [...], ...}}}``);
* geocd's own JSON/YAML (:meth:`RPCModel.to_dict`).

RPC00A polynomials (``specId = RPC00A``, ``polynomial_format: A``, ``RESOURCE_ID RPC00A``)
are reordered to RPC00B on read.

Garbled or truncated files raise :class:`~geocd.errors.RPCParseError` naming the file and
what is missing or wrong; no other exception escapes a parser.
"""

from __future__ import annotations

import json
import os
import re
import warnings
from pathlib import Path
from typing import Any, Callable, Mapping
from xml.etree import ElementTree as ET

import numpy as np

from ..camera.rpc import RPCModel, rpc00a_to_rpc00b
from ..errors import GeoCDError, InputFileNotFoundError, RPCNotFoundError, RPCParseError, UnsupportedFormatError
from .safe_yaml import YAMLLimitError, load_json, load_yaml

__all__ = [
    "read_rpc",
    "find_rpc_sidecar",
    "load_rpc_for_image",
    "detect_rpc_format",
    "SIDECAR_PATTERNS",
    "check_rpc_plausible",
]

#: sidecar names tried next to an image, in this order ({stem} = image name without extension)
SIDECAR_PATTERNS = (
    "{stem}_rpc.txt",
    "{stem}.rpb",
    "{stem}_rpc.rpb",
    "{stem}.geom",
    "{stem}.rpc.json",
    "{stem}.rpc.yaml",
    "{stem}.rpc.yml",
    "{stem}.rpc",
    "{stem}.xml",
    "{stem}.json",
    "rpc_{base}.xml",
    "RPC_*.XML (unique)",
    "*rpc*.yaml (orthority, with an entry for the image)",
)

_COEF_NAMES = ("line_num", "line_den", "samp_num", "samp_den")
_SCALAR_NAMES = (
    "line_off",
    "samp_off",
    "lat_off",
    "lon_off",
    "height_off",
    "line_scale",
    "samp_scale",
    "lat_scale",
    "lon_scale",
    "height_scale",
)
#: normalised key (lower case, only letters and digits) → canonical field
_ALIASES: dict[str, str] = {}
for _canon, _names in {
    "line_off": ("lineoff", "lineoffset", "rowoffset", "rowoff"),
    "samp_off": ("sampoff", "sampoffset", "coloffset", "coloff"),
    "lat_off": ("latoff", "latoffset"),
    "lon_off": ("longoff", "lonoff", "longoffset", "lonoffset"),
    "height_off": ("heightoff", "heightoffset", "altoffset", "altoff"),
    "line_scale": ("linescale", "rowscale"),
    "samp_scale": ("sampscale", "colscale"),
    "lat_scale": ("latscale",),
    "lon_scale": ("longscale", "lonscale"),
    "height_scale": ("heightscale", "altscale"),
    "line_num": ("linenumcoeff", "linenumcoef", "rownum", "linenum"),
    "line_den": ("linedencoeff", "linedencoef", "rowden", "lineden"),
    "samp_num": ("sampnumcoeff", "sampnumcoef", "colnum", "sampnum"),
    "samp_den": ("sampdencoeff", "sampdencoef", "colden", "sampden"),
    "err_bias": ("errbias", "biaserror"),
    "err_rand": ("errrand", "randerror"),
}.items():
    for _n in _names:
        _ALIASES[_n] = _canon
_INDEXED = re.compile(r"^(line|samp|row|col)(num|den)coef+(\d+)$")
_VENDOR_KEY = {  # how each format spells the fields, for error messages
    "line_off": "LINE_OFF",
    "samp_off": "SAMP_OFF",
    "lat_off": "LAT_OFF",
    "lon_off": "LONG_OFF",
    "height_off": "HEIGHT_OFF",
    "line_scale": "LINE_SCALE",
    "samp_scale": "SAMP_SCALE",
    "lat_scale": "LAT_SCALE",
    "lon_scale": "LONG_SCALE",
    "height_scale": "HEIGHT_SCALE",
    "line_num": "LINE_NUM_COEFF",
    "line_den": "LINE_DEN_COEFF",
    "samp_num": "SAMP_NUM_COEFF",
    "samp_den": "SAMP_DEN_COEFF",
}
# what a parser may raise on malformed input; turned into RPCParseError naming the file
_PARSE_FAILURES: tuple[type[BaseException], ...] = (
    KeyError,
    IndexError,
    ValueError,
    TypeError,
    AttributeError,
    OverflowError,
    ZeroDivisionError,
    ArithmeticError,
    RecursionError,
    ET.ParseError,
    UnicodeError,
    np.linalg.LinAlgError,
    LookupError,
)


def _normkey(key: Any) -> str:
    return re.sub(r"[^a-z0-9]", "", str(key).lower())


# =====================================================================================
# small parsing helpers
# =====================================================================================
class _Fields:
    """Collects the 90 RPC parameters of one file, remembering what was unreadable."""

    def __init__(self, path: Path, label: str, index_base: int = 1) -> None:
        self.path = path
        self.label = label
        self.index_base = index_base
        self.values: dict[str, Any] = {}
        self.indexed: dict[str, dict[int, str]] = {n: {} for n in _COEF_NAMES}
        self.bad: list[str] = []
        self.order = "B"
        self.width: Any = None
        self.height: Any = None

    # -- filling ------------------------------------------------------------------
    def put(self, key: Any, value: Any) -> bool:
        """Store ``value`` under the canonical field ``key`` maps to; False if unknown."""
        nk = _normkey(key)
        m = _INDEXED.match(nk)
        if m:
            canon = {"line": "line", "row": "line", "samp": "samp", "col": "samp"}[m.group(1)] + "_" + m.group(2)
            self.indexed[canon][int(m.group(3))] = value
            return True
        canon = _ALIASES.get(nk)
        if canon is None:
            return False
        self.values[canon] = value
        return True

    # -- conversion ---------------------------------------------------------------------
    def _float(self, name: str, value: Any) -> float | None:
        try:
            return _to_float(value)
        except (TypeError, ValueError, OverflowError):
            self.bad.append(f"{_VENDOR_KEY.get(name, name)}={_short(value)} is not a number")
            return None

    def build(self, **extra: Any) -> RPCModel:
        kw: dict[str, Any] = {}
        missing: list[str] = []
        for name in _COEF_NAMES:
            if name in self.values:
                try:
                    kw[name] = _to_floats(self.values[name])
                except (TypeError, ValueError, OverflowError):
                    self.bad.append(f"{_VENDOR_KEY[name]} is not a list of numbers ({_short(self.values[name])})")
                    continue
                if len(kw[name]) != 20:
                    self.bad.append(f"{_VENDOR_KEY[name]} has {len(kw[name])} coefficients instead of 20")
                continue
            idx = self.indexed[name]
            if not idx:
                missing.append(_VENDOR_KEY[name])
                continue
            want = range(self.index_base, self.index_base + 20)
            lost = [i for i in want if i not in idx]
            if lost:
                missing.append(
                    f"{_VENDOR_KEY[name]}_{{{','.join(map(str, lost))}}}"
                    f" (indices {self.index_base}..{self.index_base + 19})"
                )
                continue
            vals = [self._float(f"{_VENDOR_KEY[name]}_{i}", idx[i]) for i in want]
            if all(v is not None for v in vals):
                kw[name] = vals
        for name in _SCALAR_NAMES:
            if name not in self.values:
                missing.append(_VENDOR_KEY[name])
                continue
            v = self._float(name, self.values[name])
            if v is not None:
                kw[name] = v
        if missing or self.bad:
            parts = []
            if missing:
                parts.append("lacks " + ", ".join(missing))
            if self.bad:
                more = f"; and {len(self.bad) - 4} more unreadable values" if len(self.bad) > 5 else ""
                parts.append("; ".join(self.bad[:4] if more else self.bad) + more)
            raise RPCParseError(
                f"{self.path}: this {self.label} file {'; '.join(parts)}. The file is truncated, garbled or not "
                "an RPC file; re-export it from the original product (an RPC needs 10 offsets/scales and "
                "4 x 20 coefficients)"
            )
        if self.order == "A":
            for name in _COEF_NAMES:
                kw[name] = rpc00a_to_rpc00b(np.asarray(kw[name], float))
        for name in ("err_bias", "err_rand"):
            if name in self.values:
                try:
                    v = _to_float(self.values[name])
                    if np.isfinite(v) and v >= 0:
                        kw[name] = v
                except (TypeError, ValueError, OverflowError):
                    pass  # optional vendor error estimates: ignore when unreadable
        w, h = _size(self.width), _size(self.height)
        if w is not None and h is not None:
            kw["width"], kw["height"] = w, h
        kw.update(extra)
        kw.setdefault("source", f"{self.path} [{self.label}{', RPC00A reordered' if self.order == 'A' else ''}]")
        return _model(self.path, kw)


def _model(path: Path, kw: dict[str, Any]) -> RPCModel:
    try:
        model = RPCModel(**kw)
    except RPCParseError as exc:
        bad = _start_failure_cause(kw)
        if bad:
            raise _implausible(f"{path}: ", bad) from None
        msg = str(exc)
        raise RPCParseError(msg if str(path) in msg else f"{path}: {msg}") from None
    check_rpc_plausible(model, path)
    return model


#: physical ranges of an RPC's offsets and scales (degrees, metres, pixels): (field, low, high, what)
PLAUSIBLE_RANGES = (
    ("lat_off", -90.0, 90.0, "a latitude (degrees)"),
    ("lon_off", -180.0, 360.0, "a longitude (degrees, -180..180 or 0..360)"),
    ("height_off", -12_000.0, 30_000.0, "a ground height (m)"),
    ("line_off", -1e7, 1e7, "a pixel offset"),
    ("samp_off", -1e7, 1e7, "a pixel offset"),
)
PLAUSIBLE_SCALES = (
    ("lat_scale", 1e-8, 90.0, "degrees of latitude"),
    ("lon_scale", 1e-8, 180.0, "degrees of longitude"),
    ("height_scale", 1e-3, 1e5, "metres"),
    ("line_scale", 1e-3, 1e7, "pixels"),
    ("samp_scale", 1e-3, 1e7, "pixels"),
)
#: scales a vendor may write negative (Planet's L1A/L1B RPCs have LAT_SCALE < 0, the sign folded into the
#: coefficients); the pixel and height scales are half-extents and must be positive
SIGNED_SCALES = ("lat_scale", "lon_scale")
#: RPC00B coefficients act on offsets normalised to [-1, 1]; real models stay below ~250 (measured on the
#: 29 vendor RPCs of ../shared/data: SkySat 225, Pléiades 46, others ~1): 1e6 leaves four orders of margin
MAX_ABS_COEFFICIENT = 1e6


def check_rpc_plausible(model: RPCModel, path: os.PathLike | str | None = None) -> RPCModel:
    """Refuse an RPC whose offsets/scales are outside physical ranges or whose coefficients are absurd.

    Latitude offset within ±90°, longitude within -180..360°, ground height offset within
    -12..30 km, scales between a millimetre / a thousandth of a pixel and a hemisphere / 100 km /
    10⁷ px, every coefficient finite and below :data:`MAX_ABS_COEFFICIENT` in magnitude, and the
    model's centre projecting to a finite pixel.

    Raises
    ------
    RPCParseError
    """
    where = f"{path}: " if path is not None else ""
    bad = _field_problems(lambda name: getattr(model, name))
    if not bad:
        with np.errstate(all="ignore"):
            c, r = model.project_reference(model.lon_off, model.lat_off, model.height_off)  # no compile
        if not (np.isfinite(c) and np.isfinite(r) and abs(float(c)) < 1e9 and abs(float(r)) < 1e9):
            bad.append(f"the model's own centre projects to a non-finite pixel ({float(c):g}, {float(r):g})")
    if bad:
        raise _implausible(where, bad)
    return model


def _field_problems(get: Callable[[str], Any]) -> list[str]:
    """What is implausible in an RPC's offsets, scales and coefficients (``get(field name)`` reads a field):
    one sentence each, empty when nothing is."""
    bad = []
    for name, lo, hi, what in PLAUSIBLE_RANGES:
        v = float(get(name))
        if not (lo <= v <= hi):
            bad.append(f"{_VENDOR_KEY[name]}={v:g} is not {what} (expected {lo:g}..{hi:g})")
    for name, lo, hi, unit in PLAUSIBLE_SCALES:
        v = float(get(name))
        if name not in SIGNED_SCALES and v < 0:
            bad.append(f"{_VENDOR_KEY[name]}={v:g} is negative; it must be {lo:g}..{hi:g} {unit}")
        elif not (lo <= abs(v) <= hi):
            bad.append(f"{_VENDOR_KEY[name]}={v:g} is outside {lo:g}..{hi:g} {unit}")
    for name in _COEF_NAMES:
        c = np.asarray(get(name), float).reshape(-1)
        if (np.abs(c) > MAX_ABS_COEFFICIENT).any():
            k = int(np.argmax(np.abs(c)))
            bad.append(
                f"{_VENDOR_KEY[name]}_{k + 1}={c[k]:g} is not a plausible coefficient (|c| > {MAX_ABS_COEFFICIENT:g})"
            )
    return bad


def _start_failure_cause(kw: dict[str, Any]) -> list[str]:
    """Why a model whose fields are all finite numbers (they passed the model's own checks) failed its
    numerical start: an implausible field (a coefficient of 1e300) makes the affine part singular or not by
    the last bits of the BLAS, so the field, the cause, is named. Empty when a field is missing, not a
    number, not finite or a zero scale: the model's own message names that field."""
    norm = [n for n, *_ in (*PLAUSIBLE_RANGES, *PLAUSIBLE_SCALES)]
    try:
        values = [np.asarray(kw[n], float) for n in (*_COEF_NAMES, *norm)]
        if not all(np.all(np.isfinite(v)) for v in values) or any(float(kw[n]) == 0 for n, *_ in PLAUSIBLE_SCALES):
            return []
        return _field_problems(kw.__getitem__)
    except (KeyError, TypeError, ValueError, OverflowError):
        return []


def _implausible(where: str, bad: list[str]) -> RPCParseError:
    return RPCParseError(
        f"{where}implausible RPC: {'; '.join(bad[:4])}"
        f"{f'; and {len(bad) - 4} more' if len(bad) > 4 else ''}. The file is corrupt or not this "
        "image's camera; re-export it from the original product"
    )


#: NITF RPC00A/RPC00B TRE layout (STDI-0002): field widths after SUCCESS, ERR_BIAS, ERR_RAND
_TRE_FIELDS = (
    ("LINE_OFF", 6),
    ("SAMP_OFF", 5),
    ("LAT_OFF", 8),
    ("LONG_OFF", 9),
    ("HEIGHT_OFF", 5),
    ("LINE_SCALE", 6),
    ("SAMP_SCALE", 5),
    ("LAT_SCALE", 8),
    ("LONG_SCALE", 9),
    ("HEIGHT_SCALE", 5),
)


def _check_nitf_tre(path: Path, tres: Mapping[str, Any]) -> None:
    """GDAL parses the RPC TRE's fixed-width fields with atof (letters → 0): check them as text."""
    for key in ("RPC00B", "RPC00A"):
        raw = tres.get(key)
        if not isinstance(raw, str) or len(raw) < 1041:
            continue
        pos, bad = 15, []
        for name, width in _TRE_FIELDS:
            txt = raw[pos : pos + width]
            pos += width
            try:
                float(txt)
            except ValueError:
                bad.append(f"{name}={txt!r}")
        for k in range(80):
            txt = raw[pos : pos + 12]
            pos += 12
            try:
                float(txt)
            except ValueError:
                poly = ("LINE_NUM_COEFF", "LINE_DEN_COEFF", "SAMP_NUM_COEFF", "SAMP_DEN_COEFF")[k // 20]
                bad.append(f"{poly}_{k % 20 + 1}={txt!r}")
        if bad:
            raise RPCParseError(
                f"{path}: the {key} TRE holds non-numeric fields ({', '.join(bad[:4])}"
                f"{f' and {len(bad) - 4} more' if len(bad) > 4 else ''}); GDAL would read them as 0. "
                "The file is corrupt: re-export it from the original product"
            )


def _check_raw_rpc_strings(path: Path, raw: Mapping[str, Any]) -> None:
    """GDAL reads a non-numeric RPC value as 0: refuse those (an .aux.xml or sidecar edited by hand)."""
    bad = []
    for key, val in raw.items():
        canon = _ALIASES.get(_normkey(key))
        if canon is None or val is None:
            continue
        try:
            vals = _to_floats(val) if canon in _COEF_NAMES else [_to_float(val)]
        except (TypeError, ValueError, OverflowError):
            bad.append(f"{key}={_short(val)} is not a number")
            continue
        if canon in _COEF_NAMES and len(vals) != 20:
            bad.append(f"{key} has {len(vals)} values instead of 20")
    if bad:
        raise RPCParseError(
            f"{path}: the RPC metadata holds non-numeric values ({'; '.join(bad[:4])}); GDAL would "
            "read them as 0. Re-export the RPC from the original product"
        )


def _short(v: Any, n: int = 40) -> str:
    s = repr(v)
    return s if len(s) <= n else s[: n - 3] + "..."


_UNIT_TAIL = re.compile(r"^([^\s;,]+)")


def _to_float(v: Any) -> float:
    """A number from a number or a string such as ``'+005124.00 pixels'`` or ``'12.3;'``."""
    if isinstance(v, bool):
        raise TypeError("boolean is not a number")
    if isinstance(v, (int, float, np.floating, np.integer)):
        return float(v)
    if isinstance(v, (list, tuple)) and len(v) == 1:
        return _to_float(v[0])
    if not isinstance(v, str):
        raise TypeError(f"{type(v).__name__} is not a number")
    s = v.strip().strip("\"'").strip()
    m = _UNIT_TAIL.match(s)
    if not m:
        raise ValueError("empty value")
    return float(m.group(1).replace("D", "E").replace("d", "e"))


def _to_floats(v: Any) -> list[float]:
    if isinstance(v, str):
        toks = [t for t in re.split(r"[\s,;()\[\]\"']+", v) if t]
        return [float(t.replace("D", "E").replace("d", "e")) for t in toks]
    if isinstance(v, (list, tuple, np.ndarray)):
        return [_to_float(x) for x in v]
    raise TypeError(f"{type(v).__name__} is not a list of numbers")


def _size(v: Any) -> int | None:
    """A positive image dimension, or None (size is optional metadata: never an error)."""
    try:
        f = _to_float(v)
    except (TypeError, ValueError, OverflowError):
        return None
    if not np.isfinite(f) or f < 1 or f > 1e8 or f != round(f):
        return None
    return int(f)


def _local(tag: Any) -> str:
    """XML tag without namespace."""
    return tag.rsplit("}", 1)[-1] if isinstance(tag, str) else ""


def _children(el: ET.Element) -> dict[str, ET.Element]:
    return {_local(c.tag).upper(): c for c in el}


def _text(el: ET.Element | None) -> str | None:
    return None if el is None or el.text is None else el.text.strip()


# =====================================================================================
# format detection
# =====================================================================================
_TIFF_MAGIC = (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+")
_RE_RPB = re.compile(r"(?im)^\s*(lineoffset|linenumcoef|begin_group)\s*=")
_RE_GEOM = re.compile(r"(?m)^\s*([\w.]+\.)?(line_num_coeff?_\d\d|polynomial_format)\s*:")
_RE_TXT = re.compile(r"(?m)^\s*(LINE_OFF|LINE_NUM_COEFF(_\d+)?|SAMP_OFF)\s*:")
_EXT_FALLBACK = {
    ".rpb": "rpb",
    ".geom": "geom",
    ".txt": "txt",
    ".xml": "xml",
    ".json": "json",
    ".yaml": "yaml",
    ".yml": "yaml",
    ".tif": "gdal",
    ".tiff": "gdal",
    ".ntf": "gdal",
    ".nitf": "gdal",
    ".r0": "gdal",
    ".jp2": "gdal",
    ".rpc": "txt",
}
_MAX_TEXT_BYTES = 64 * 2**20


def _read_head(path: Path, n: int) -> bytes:
    with open(path, "rb") as f:
        return f.read(n)


def _read_text(path: Path) -> str:
    size = path.stat().st_size
    if size > _MAX_TEXT_BYTES:
        raise RPCParseError(f"{path}: {size / 2**20:.0f} MiB is too large for an RPC text file; is it an image?")
    data = path.read_bytes()
    if data.startswith(b"\xef\xbb\xbf"):
        data = data[3:]
    for enc in ("utf-8", "latin-1"):
        try:
            return data.decode(enc)
        except UnicodeDecodeError:
            continue
    return data.decode("utf-8", errors="replace")  # pragma: no cover - latin-1 decodes anything


def detect_rpc_format(path: os.PathLike | str) -> str:
    """The RPC format of a file, from its content (extension as a fallback).

    Returns one of ``"gdal"`` (GeoTIFF, NITF or another raster: rasterio reads the tags),
    ``"txt"``, ``"rpb"``, ``"geom"``, ``"xml"`` (DigitalGlobe or DIMAP), ``"json"``,
    ``"yaml"``, or ``""`` when nothing fits.
    """
    p = Path(path)
    head = _read_head(p, 4096)
    if head[:4] in _TIFF_MAGIC or head[:4] in (b"NITF", b"NSIF") or head[:12] == b"\x00\x00\x00\x0cjP  \r\n\x87\n":
        return "gdal"
    if b"\x00" in head:  # binary: a raster GDAL may know, unless the extension says text
        return _EXT_FALLBACK.get(p.suffix.lower(), "gdal")
    txt = head.decode("utf-8", errors="replace").lstrip("\ufeff \t\r\n")
    if txt.startswith("<"):
        return "xml"
    if txt.startswith("{") or txt.startswith("["):
        return "json"
    if _RE_GEOM.search(txt):
        return "geom"
    if _RE_RPB.search(txt):
        return "rpb"
    if _RE_TXT.search(txt):
        return "txt"
    first = next((ln for ln in txt.splitlines() if ln.strip() and not ln.lstrip().startswith("#")), "")
    if (
        first == "---"
        or re.match(r"^(kind|rpc|im_size)\s*:", first)
        or re.search(r"(?m)^[^\s:#][^:]*:\s*$", txt)
        or re.search(r"(?m)^\s*-\s+\S", txt)
    ):
        return "yaml"  # YAML with nested mappings or lists (orthority, geocd)
    return _EXT_FALLBACK.get(p.suffix.lower(), "")


# =====================================================================================
# readers, one per format; each gets (path, image_path) and returns an RPCModel
# =====================================================================================
def _open_raster(path: Path, *, own_metadata_only: bool = False):
    """rasterio dataset; ``own_metadata_only`` hides sibling files from GDAL.

    GDAL's metadata readers fill the RPC domain from sidecars (.RPB, _rpc.txt, DigitalGlobe
    .XML, Pléiades RPC_*.XML, ...) and prefer them to the file's own tags. geocd reads the
    tags alone (``GDAL_DISABLE_READDIR_ON_OPEN=EMPTY_DIR``) and finds sidecars itself, with
    its own parsers (DIMAP 1-based offsets, crops), so that ``source`` says the truth.
    """
    import rasterio
    from rasterio.errors import NotGeoreferencedWarning

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NotGeoreferencedWarning)
        if own_metadata_only:
            with rasterio.Env(GDAL_DISABLE_READDIR_ON_OPEN="EMPTY_DIR"):
                return rasterio.open(path)
        return rasterio.open(path)


def _read_gdal(path: Path, image_path: Path | None, *, own_metadata_only: bool = True) -> RPCModel:
    from rasterio.errors import RasterioError

    try:
        ds = _open_raster(path, own_metadata_only=own_metadata_only)
    except RasterioError as exc:
        raise RPCParseError(
            f"{path}: GDAL cannot open this file as a raster ({exc}); it is truncated, garbled or not an "
            "image. If it is an RPC text file, give it a matching extension (_rpc.txt, .RPB, .XML, .geom)"
        ) from None
    with ds:
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                rpc = ds.rpcs
        except (RasterioError, *_PARSE_FAILURES) as exc:
            raise RPCParseError(f"{path}: the RPC metadata of this {ds.driver} file is unreadable ({exc})") from None
        if rpc is None:
            raise RPCNotFoundError(
                f"{path} ({ds.driver}) has no RPC metadata (no RPC tags / RPC00B TRE); give its RPC sidecar "
                "file instead (_rpc.txt, .RPB, RPC_*.XML, .geom, ...) or put it next to the image"
            )
        try:
            raw = ds.tags(ns="RPC") or {}
        except (RasterioError, *_PARSE_FAILURES):
            raw = {}
        _check_raw_rpc_strings(path, raw)
        if ds.driver == "NITF":
            try:
                tres = ds.tags(ns="TRE") or {}
            except (RasterioError, *_PARSE_FAILURES):
                tres = {}
            _check_nitf_tre(path, tres)
        sidecars = [] if own_metadata_only else [f for f in (ds.files or [])[1:] if not f.lower().endswith(".aux.xml")]
        if ds.driver == "NITF":
            label = "NITF RPC00B TRE"
            try:
                if "RPC00A" in (ds.tags(ns="TRE") or {}):
                    label = "NITF RPC00A TRE (reordered by GDAL)"
            except Exception:  # noqa: BLE001 - TRE listing is cosmetic
                pass
        elif ds.driver == "GTiff":
            label = "GeoTIFF RPC tags"
            if Path(f"{path}.aux.xml").is_file():
                label += " (or its .aux.xml)"
        else:
            label = f"{ds.driver} RPC metadata"
        if not own_metadata_only:
            label = (
                f"RPC found by GDAL's metadata readers in {', '.join(Path(s).name for s in sidecars)}"
                if sidecars
                else label
            )
        try:
            kw = dict(
                line_num=rpc.line_num_coeff,
                line_den=rpc.line_den_coeff,
                samp_num=rpc.samp_num_coeff,
                samp_den=rpc.samp_den_coeff,
                line_off=rpc.line_off,
                samp_off=rpc.samp_off,
                lat_off=rpc.lat_off,
                lon_off=rpc.long_off,
                height_off=rpc.height_off,
                line_scale=rpc.line_scale,
                samp_scale=rpc.samp_scale,
                lat_scale=rpc.lat_scale,
                lon_scale=rpc.long_scale,
                height_scale=rpc.height_scale,
                width=int(ds.width),
                height=int(ds.height),
                source=f"{path} [{label}]",
            )
            for ours, theirs in (("err_bias", rpc.err_bias), ("err_rand", rpc.err_rand)):
                if theirs is not None and np.isfinite(theirs) and theirs >= 0:
                    kw[ours] = float(theirs)
        except _PARSE_FAILURES as exc:
            raise RPCParseError(f"{path}: the RPC metadata of this {ds.driver} file is incomplete ({exc})") from None
    return _model(path, kw)


def _read_txt(path: Path, image_path: Path | None) -> RPCModel:
    """IKONOS / Planet / SkySat ``KEY: value [unit]`` lines (coefficients ``_1`` .. ``_20``
    or one ``LINE_NUM_COEFF: c1 c2 ...`` line)."""
    text = _read_text(path)
    f = _Fields(path, "RPC text (IKONOS/Planet/SkySat _rpc.txt)", index_base=1)
    for line in text.splitlines():
        if ":" in line:
            k, v = line.split(":", 1)
        elif "=" in line:
            k, v = line.split("=", 1)
        else:
            continue
        f.put(k.strip(), v.strip())
    m = re.search(r"(?i)rpc00([ab])", text)
    f.order = m.group(1).upper() if m else "B"
    return f.build()


def _read_rpb(path: Path, image_path: Path | None) -> RPCModel:
    """DigitalGlobe ``.RPB``: ``key = value;`` with coefficient lists in parentheses."""
    text = _read_text(path)
    f = _Fields(path, "DigitalGlobe RPB", index_base=1)
    spec = None
    for m in re.finditer(r"(\w+)\s*=\s*(\([^)]*\)?|[^;\n]*)", text):
        key, val = m.group(1), m.group(2)
        if _normkey(key) == "specid":
            spec = val.strip().strip('"').upper()
        else:
            f.put(key, val)
    f.order = "A" if spec and spec.endswith("A") else "B"
    return f.build()


def _read_xml(path: Path, image_path: Path | None) -> RPCModel:
    text = _read_text(path)
    try:
        root = ET.fromstring(text)
    except ET.ParseError as exc:
        raise RPCParseError(f"{path}: not well-formed XML ({exc}); the file is truncated or garbled") from None
    if (
        _local(root.tag) == "Dimap_Document"
        or root.find(".//Global_RFM") is not None
        or any(_local(e.tag) == "Global_RFM" for e in root.iter())
    ):
        return _read_dimap(path, root)
    for el in root.iter():
        if _local(el.tag).upper() == "IMAGE" and any(
            _local(c.tag).upper() in ("LINEOFFSET", "LINENUMCOEFLIST") for c in el
        ):
            return _read_dg_xml(path, root, el)
    if _local(root.tag).upper() == "IMAGE":
        return _read_dg_xml(path, root, root)
    raise RPCParseError(
        f"{path}: XML file without an RPC: neither a DigitalGlobe <RPB><IMAGE> block (LINEOFFSET, "
        "LINENUMCOEFList, ...) nor a DIMAP Rational_Function_Model/Global_RFM; give the RPC XML of the product "
        "(DigitalGlobe: the .XML next to the .TIF/.NTF; Pléiades/SPOT: RPC_*.XML)"
    )


def _read_dg_xml(path: Path, root: ET.Element, image: ET.Element) -> RPCModel:
    """DigitalGlobe/Maxar XML: ``<RPB><SPECID>RPC00B</SPECID><IMAGE>LINEOFFSET ... LINENUMCOEFList``."""
    f = _Fields(path, "DigitalGlobe XML", index_base=1)
    for child in image:
        tag = _local(child.tag)
        if tag.upper().endswith("LIST"):
            # <LINENUMCOEFList><LINENUMCOEF>c1 c2 ... c20</LINENUMCOEF></LINENUMCOEFList>, or 20 elements
            vals = " ".join(_text(c) or "" for c in child)
            f.put(tag[:-4], vals)
        else:
            f.put(tag, _text(child))
    spec = None
    for el in root.iter():
        if _local(el.tag).upper() == "SPECID":
            spec = (_text(el) or "").upper()
            break
    f.order = "A" if spec and spec.endswith("A") else "B"
    for el in root.iter():
        t = _local(el.tag).upper()
        if t == "NUMCOLUMNS" and f.width is None:
            f.width = _text(el)
        elif t == "NUMROWS" and f.height is None:
            f.height = _text(el)
    return f.build()


def _read_dimap(path: Path, root: ET.Element) -> RPCModel:
    """Pléiades / SPOT DIMAP v2 ``RPC_*.XML``.

    ``Inverse_Model`` maps ground to image (the usual RPC); ``Direct_Model`` (image to
    ground) is not needed. DIMAP's first pixel centre is (1, 1): the line/sample offsets
    are reduced by 1 to the RPC00B convention (first pixel centre at (0, 0)), which makes
    them equal to the GeoTIFF tags GDAL writes for the same image.
    """
    label = "DIMAP v2 RPC XML (Inverse_Model, 1-based offsets made 0-based)"
    f = _Fields(path, label, index_base=1)
    inv = next((e for e in root.iter() if _local(e.tag) == "Inverse_Model"), None)
    val = next((e for e in root.iter() if _local(e.tag) == "RFM_Validity"), None)
    missing = [n for n, e in (("Global_RFM/Inverse_Model", inv), ("Global_RFM/RFM_Validity", val)) if e is None]
    if missing:
        raise RPCParseError(
            f"{path}: this DIMAP XML lacks {', '.join(missing)}; it is truncated or not an RPC_*.XML "
            "(give the RPC_*.XML of the product, not DIM_*.XML)"
        )
    for child in inv:
        f.put(_local(child.tag), _text(child))
    for child in val:
        tag = _local(child.tag)
        if tag.endswith("_Domain"):
            continue
        f.put(tag, _text(child))
    for el in root.iter():
        if _local(el.tag) == "RESOURCE_ID" and (_text(el) or "").upper() == "RPC00A":
            f.order = "A"
    dom = next((e for e in val if _local(e.tag) == "Direct_Model_Validity_Domain"), None)
    if dom is not None:
        c = _children(dom)
        try:
            if _to_float(_text(c.get("FIRST_ROW"))) == 1 and _to_float(_text(c.get("FIRST_COL"))) == 1:
                f.width, f.height = _text(c.get("LAST_COL")), _text(c.get("LAST_ROW"))
        except (TypeError, ValueError, OverflowError):
            pass
    for name in ("line_off", "samp_off"):
        if name in f.values:
            try:
                f.values[name] = _to_float(f.values[name]) - 1.0
            except (TypeError, ValueError, OverflowError):
                pass  # reported by build()
    return f.build()


def _read_geom(path: Path, image_path: Path | None) -> RPCModel:
    """OSSIM keyword list (``.geom``): ``line_num_coeff_00: ...`` (0-based), ``polynomial_format: A|B``."""
    text = _read_text(path)
    f = _Fields(path, "OSSIM .geom", index_base=0)
    kv: dict[str, str] = {}
    for line in text.splitlines():
        if ":" not in line:
            continue
        k, v = line.split(":", 1)
        kv[k.strip()] = v.strip().strip('"').strip()
    # unprefixed keys win; otherwise take the key after the last '.' (prefixed keyword lists)
    order = sorted(kv, key=lambda k: k.count("."), reverse=True)
    for k in order:
        name = k.rsplit(".", 1)[-1]
        if k.startswith("support_data.") or k.startswith("adjustment_"):
            continue
        f.put(name, kv[k])
        if _normkey(name) == "numbersamples":
            f.width = kv[k]
        elif _normkey(name) == "numberlines":
            f.height = kv[k]
    fmt = next((kv[k] for k in order if k.rsplit(".", 1)[-1] == "polynomial_format"), "B").strip().upper()
    if fmt not in ("A", "B"):
        raise RPCParseError(f"{path}: polynomial_format is {fmt!r}; an OSSIM RPC .geom says A or B")
    f.order = fmt
    f.label = f"OSSIM .geom, polynomial_format {fmt}"
    return f.build()


def _from_mapping(path: Path, d: Mapping[str, Any], label: str, *, width: Any = None, height: Any = None) -> RPCModel:
    f = _Fields(path, label, index_base=1)
    for k, v in d.items():
        f.put(k, v)
    spec = next((str(v) for k, v in d.items() if _normkey(k) in ("specid", "polynomialformat", "format")), "B")
    f.order = "A" if spec.strip().upper().endswith("A") else "B"
    f.width, f.height = (
        width if width is not None else d.get("width"),
        height if height is not None else d.get("height"),
    )
    return f.build()


def _read_structured(path: Path, d: Any, kind: str, image_path: Path | None) -> RPCModel:
    """A parsed JSON/YAML document: geocd, Sat-NeRF/DFC2019, orthority, or a flat RPC dict."""
    if not isinstance(d, Mapping):
        raise RPCParseError(f"{path}: this {kind} holds a {type(d).__name__}, not an RPC description (a mapping)")
    if d.get("kind") == "rpc" or ("line_num" in d and "samp_den" in d):
        model = _from_mapping(path, d, f"geocd {kind}")
        src = d.get("source")
        return model.replace(source=f"{path} [geocd {kind}]" + (f" from {src}" if src else ""))
    if isinstance(d.get("rpc"), Mapping):
        return _from_mapping(path, d["rpc"], f"Sat-NeRF/DFC2019 {kind}", width=d.get("width"), height=d.get("height"))
    entries = {k: v for k, v in d.items() if isinstance(v, Mapping) and isinstance(v.get("rpc"), Mapping)}
    if entries:
        key = _pick_entry(path, entries, image_path)
        e = entries[key]
        size = e.get("im_size")
        w = h = None
        if isinstance(size, (list, tuple)) and len(size) == 2:
            w, h = size
        return _from_mapping(path, e["rpc"], f"orthority {kind}, entry {key!r}", width=w, height=h)
    if any(_normkey(k) in _ALIASES for k in d):
        return _from_mapping(path, d, f"RPC {kind}")
    raise RPCParseError(
        f"{path}: this {kind} holds no RPC: expected geocd's form (kind: rpc, line_num, ...), a Sat-NeRF/DFC2019 "
        "'rpc' object, orthority's {image: {rpc: {...}}} or GDAL-style keys (LINE_OFF, LINE_NUM_COEFF, ...)"
    )


def _pick_entry(path: Path, entries: Mapping[str, Any], image_path: Path | None) -> str:
    if image_path is not None:
        name = Path(image_path).name
        for k in entries:
            if Path(str(k)).name == name:
                return k
        for k in entries:
            if Path(str(k)).stem == Path(name).stem:
                return k
        raise RPCNotFoundError(
            f"{path} has RPCs for {sorted(map(str, entries))} but none for {name}; check the image name "
            "or give the right RPC file"
        )
    if len(entries) == 1:
        return next(iter(entries))
    raise RPCNotFoundError(
        f"{path} holds the RPCs of {len(entries)} images ({', '.join(sorted(map(str, entries))[:5])}...); "
        "say which image (read_rpc(path, image_path=...) or the manifest's image)"
    )


def _read_json(path: Path, image_path: Path | None) -> RPCModel:
    try:
        d = load_json(_read_text(path))
    except YAMLLimitError as exc:
        raise RPCParseError(f"{path}: {_short(str(exc), 200)}") from None
    except json.JSONDecodeError as exc:
        raise RPCParseError(f"{path}: not valid JSON ({exc}); the file is truncated or garbled") from None
    return _read_structured(path, d, "JSON", image_path)


def _read_yaml(path: Path, image_path: Path | None) -> RPCModel:
    import yaml

    try:
        d = load_yaml(_read_text(path))
    except YAMLLimitError as exc:
        raise RPCParseError(f"{path}: {_short(str(exc), 200)}") from None
    except yaml.YAMLError as exc:
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise RPCParseError(f"{path}: not valid YAML ({first}); the file is truncated or garbled") from None
    return _read_structured(path, d, "YAML", image_path)


_READERS: dict[str, Callable[[Path, Path | None], RPCModel]] = {
    "gdal": _read_gdal,
    "txt": _read_txt,
    "rpb": _read_rpb,
    "xml": _read_xml,
    "geom": _read_geom,
    "json": _read_json,
    "yaml": _read_yaml,
}


# =====================================================================================
# public API
# =====================================================================================
def read_rpc(
    path: os.PathLike | str, image_path: os.PathLike | str | None = None, *, apply_crop: bool = True
) -> RPCModel:
    """Read an RPC camera model from any supported vendor format.

    Parameters
    ----------
    path : path of the RPC file, or of an image holding RPC tags (GeoTIFF, NITF).
    image_path : optional image the RPC file belongs to. Its size becomes the model's
        ``width``/``height`` and, when ``path`` is a sidecar (not the image itself) and the
        image's geotransform is ``(1, 0, x0, 0, 1, y0)`` with no CRS and ``(x0, y0) != (0, 0)``
        (the way CNES/OTB tools mark a crop of a full scene), the model is
        :meth:`~geocd.camera.RPCModel.cropped` at ``(x0, y0)``. It also selects the entry of
        multi-image files (orthority YAML).
    apply_crop : set False to ignore such crop offsets.

    Returns
    -------
    RPCModel with ``source`` naming the file and the format.

    Raises
    ------
    InputFileNotFoundError
        ``path`` does not exist.
    RPCParseError
        The file is truncated, garbled, or in no known RPC format.
    RPCNotFoundError
        ``path`` is an image without RPC metadata, or a multi-image file without an entry
        for ``image_path``.
    """
    p = Path(path)
    if not p.is_file():
        raise InputFileNotFoundError(f"RPC file {p} does not exist; check the path")
    img = Path(image_path) if image_path is not None else None
    try:
        fmt = detect_rpc_format(p)
    except OSError as exc:
        raise RPCParseError(f"{p}: cannot read the file ({exc})") from None
    if not fmt:
        raise RPCParseError(
            f"{p}: not an RPC file in any known format (GeoTIFF/NITF tags, _rpc.txt, .RPB, DigitalGlobe XML, "
            "DIMAP RPC_*.XML, OSSIM .geom, Sat-NeRF/orthority/geocd JSON or YAML); check that it is the "
            "camera file of the image"
        )
    try:
        model = _READERS[fmt](p, img)
    except GeoCDError:
        raise
    except OSError as exc:
        raise RPCParseError(f"{p}: cannot read the file ({exc})") from None
    except _PARSE_FAILURES as exc:
        raise RPCParseError(
            f"{p}: malformed RPC file ({type(exc).__name__}: {_short(str(exc), 120)}); the file is truncated or "
            "garbled, re-export it from the original product"
        ) from None
    if img is not None and not (fmt == "gdal" and _same_file(p, img)):
        model = _fit_to_image(model, img, apply_crop=apply_crop)
    return model


def _same_file(a: Path, b: Path) -> bool:
    try:
        return a.resolve() == b.resolve() or os.path.samefile(a, b)
    except OSError:
        return False


def _image_geometry(image: Path) -> tuple[int, int, Any, Any]:
    from rasterio.errors import RasterioError

    if not image.exists():
        raise InputFileNotFoundError(f"image {image} does not exist; check the path")
    try:
        with _open_raster(image) as ds:
            return ds.width, ds.height, ds.transform, ds.crs
    except RasterioError as exc:
        raise UnsupportedFormatError(
            f"cannot open image {image} ({exc}); give a GeoTIFF or another GDAL raster"
        ) from None


def crop_offset_of(transform: Any, crs: Any) -> tuple[float, float] | None:
    """``(x0, y0)`` when a geotransform is the crop marker ``(1, 0, x0, 0, 1, y0)`` without CRS."""
    if crs is not None or transform is None:
        return None
    a, b, c, d, e, f = (float(v) for v in tuple(transform)[:6])
    if (a, b, d, e) != (1.0, 0.0, 0.0, 1.0) or (c == 0.0 and f == 0.0):
        return None
    return c, f


def _fit_to_image(model: RPCModel, image: Path, *, apply_crop: bool) -> RPCModel:
    width, height, transform, crs = _image_geometry(image)
    off = crop_offset_of(transform, crs) if apply_crop else None
    if off is not None:
        return model.cropped(off[0], off[1], width=width, height=height).replace(
            source=f"{model.source} cropped at col={off[0]:g} row={off[1]:g} (geotransform of {image.name})"
        )
    return model.replace(width=width, height=height)


def _sidecar_candidates(image: Path) -> list[str]:
    stem = image.stem
    base = stem[4:] if stem.upper().startswith("IMG_") else stem
    base = re.sub(r"_R\d+C\d+$", "", base, flags=re.I)
    names = [pat.format(stem=stem, base=base) for pat in SIDECAR_PATTERNS if "{" in pat]
    # GDAL's own convention keeps the full name too (image.tif.rpb is rare but seen)
    return names


def find_rpc_sidecar(image_path: os.PathLike | str) -> Path | None:
    """The RPC sidecar of an image, or None.

    Tries, case-insensitively, next to the image: ``{stem}_rpc.txt`` (IKONOS, Planet, SkySat
    ``_RPC.TXT``), ``{stem}.RPB``, ``{stem}.geom`` (OSSIM), ``{stem}.rpc.json``/``.rpc.yaml``,
    ``{stem}.XML`` (DigitalGlobe), ``{stem}.json`` (Sat-NeRF/DFC2019), ``RPC_{stem without IMG_
    and tile suffix}.XML`` (DIMAP), then the folder's only ``RPC_*.XML`` (not for tiles other
    than R1C1, whose pixel offsets differ), then an orthority ``*rpc*.yaml`` with an entry for the
    image. Files with a generic name (``{stem}.xml``, ``{stem}.json``) count only when their content is
    an RPC; a file whose name says RPC (``{stem}.rpc.json``, ``{stem}_rpc.txt``, ...) is returned even
    when garbled, so that reading it raises :class:`~geocd.errors.RPCParseError` naming it.
    """
    image = Path(image_path)
    folder = image.parent if str(image.parent) else Path(".")
    try:
        listing = {p.name.lower(): p for p in folder.iterdir() if p.is_file()}
    except OSError:
        return None
    me = image.name.lower()
    generic = {f"{image.stem}.xml".lower(), f"{image.stem}.json".lower()}
    for name in _sidecar_candidates(image):
        p = listing.get(name.lower())
        if p is None or p.name.lower() == me:
            continue
        # a generic name (image.xml, image.json) may hold other metadata: it counts only when it reads as an
        # RPC; a name that says RPC (image_rpc.txt, image.rpc.json, ...) is read, and a garbled one is an error
        if name.lower() in generic and not _holds_rpc(p):
            continue
        return p
    tile = re.search(r"_R(\d+)C(\d+)$", image.stem, flags=re.I)
    if not tile or (tile.group(1), tile.group(2)) == ("1", "1"):
        dimap = [p for n, p in listing.items() if n.startswith("rpc_") and n.endswith(".xml") and _holds_rpc(p)]
        if len(dimap) == 1:
            return dimap[0]
    for n, p in sorted(listing.items()):
        if "rpc" in n and n.endswith((".yaml", ".yml")) and _holds_rpc(p, image):
            return p
    return None


def _holds_rpc(p: Path, image: Path | None = None) -> bool:
    """Whether ``p`` reads as an RPC (of ``image`` for multi-image files)."""
    try:
        read_rpc(p, image_path=image, apply_crop=False)
        return True
    except (GeoCDError, OSError):
        return False


def load_rpc_for_image(image_path: os.PathLike | str) -> RPCModel:
    """The RPC of an image: its own tags first (GeoTIFF/NITF), then a sidecar file.

    The model's ``width``/``height`` are the image's; a sidecar RPC of a full scene is
    cropped when the image's geotransform marks a crop (see :func:`read_rpc`).

    Raises
    ------
    InputFileNotFoundError
        The image does not exist.
    RPCNotFoundError
        Neither tags nor a sidecar (the message lists the names tried).
    RPCParseError
        Tags or sidecar exist but are garbled.
    """
    image = Path(image_path)
    if not image.is_file():
        raise InputFileNotFoundError(f"image {image} does not exist; check the path")
    from rasterio.errors import RasterioError

    try:
        with _open_raster(image, own_metadata_only=True) as ds:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                has_tags = ds.rpcs is not None
    except RasterioError as exc:
        raise UnsupportedFormatError(
            f"cannot open image {image} ({exc}); give a GeoTIFF or another GDAL raster"
        ) from None
    except _PARSE_FAILURES as exc:
        raise RPCParseError(f"{image}: its RPC tags are unreadable ({exc})") from None
    if has_tags:
        return read_rpc(image)
    side = find_rpc_sidecar(image)
    if side is not None:
        return read_rpc(side, image_path=image)
    # last resort: GDAL's metadata readers know a few more vendor layouts (DIM_*.XML, ...)
    try:
        model = _read_gdal(image, None, own_metadata_only=False)
    except RPCNotFoundError:
        model = None
    if model is not None:
        return _fit_to_image(model, image, apply_crop=True)
    tried = ", ".join(_sidecar_candidates(image)[:8])
    raise RPCNotFoundError(
        f"{image} has no RPC: no RPC tags in the file and no sidecar next to it (tried {tried}, a unique "
        "RPC_*.XML, ...). Put the vendor RPC file beside the image under one of these names, or name it "
        "explicitly (manifest 'camera:' / geocd.io.rpc.read_rpc(rpc_file, image_path=image))"
    )
