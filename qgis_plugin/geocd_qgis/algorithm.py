"""One table-driven Processing algorithm per geocd CLI call (see :mod:`.specs`)."""

from __future__ import annotations

import json
import os
from pathlib import Path

from qgis.core import (
    QgsDataProvider,
    QgsProcessing,
    QgsProcessingAlgorithm,
    QgsProcessingContext,
    QgsProcessingException,
    QgsProcessingLayerPostProcessorInterface,
    QgsProcessingOutputFile,
    QgsProcessingOutputFolder,
    QgsProcessingOutputMultipleLayers,
    QgsProcessingOutputRasterLayer,
    QgsProcessingOutputString,
    QgsProcessingOutputVectorLayer,
    QgsProcessingParameterBoolean,
    QgsProcessingParameterCrs,
    QgsProcessingParameterDefinition,
    QgsProcessingParameterEnum,
    QgsProcessingParameterExtent,
    QgsProcessingParameterFeatureSource,
    QgsProcessingParameterFile,
    QgsProcessingParameterFileDestination,
    QgsProcessingParameterFolderDestination,
    QgsProcessingParameterMultipleLayers,
    QgsProcessingParameterNumber,
    QgsProcessingParameterRange,
    QgsProcessingParameterRasterLayer,
    QgsProcessingParameterString,
    QgsProcessingUtils,
    QgsRasterLayer,
    QgsVectorLayer,
)
from qgis.PyQt.QtCore import QCoreApplication

from . import locate, runner, specs
from .specs import OUTPUT_FOLDER, AlgSpec, Param

PLUGIN_DIR = Path(__file__).resolve().parent
STYLES_DIR = PLUGIN_DIR / "styles"

_RASTER_EXT = {".tif", ".tiff", ".vrt", ".img", ".nc"}
_VECTOR_EXT = {".gpkg", ".shp", ".geojson", ".json", ".fgb"}

_GEOMETRY = {
    "polygon": QgsProcessing.TypeVectorPolygon,
    "point": QgsProcessing.TypeVectorPoint,
    "line": QgsProcessing.TypeVectorLine,
    "any": QgsProcessing.TypeVectorAnyGeometry,
}

# post-processors must outlive processAlgorithm (QGIS keeps a raw pointer)
_KEEP_ALIVE: list = []


def tr(text: str) -> str:
    return QCoreApplication.translate("geocd", text)


def configured_executable() -> str:
    """The "geocd executable" Processing setting ('' when unset or when Processing is not loaded)."""
    try:
        from processing.core.ProcessingConfig import ProcessingConfig

        return ProcessingConfig.getSetting("GEOCD_EXECUTABLE") or ""
    except Exception:  # noqa: BLE001 - Processing's Python side absent (pure C++ contexts)
        return ""


class StylePostProcessor(QgsProcessingLayerPostProcessorInterface):
    """Apply the product's own style (QML sidecar / GeoPackage layer_styles), else the plugin's fallback.

    ``fallback``: a QML file, or ``auto:probability`` / ``auto:height`` (a colour ramp built for the layer).
    """

    def __init__(self, fallback: str | None):
        super().__init__()
        self.fallback = fallback

    def postProcessLayer(self, layer, context, feedback):  # noqa: N802 - Qt naming
        if layer is None or not layer.isValid():
            return
        _msg, ok = layer.loadDefaultStyle()
        if not ok and self.fallback:
            if self.fallback.startswith("auto:"):
                apply_ramp(layer, self.fallback[5:])
            elif (STYLES_DIR / self.fallback).is_file():
                layer.loadNamedStyle(str(STYLES_DIR / self.fallback))
        layer.triggerRepaint()


def apply_ramp(layer, kind: str) -> bool:
    """A pseudocolour renderer on band 1: 0–1 for ``probability``, the band's range for ``height``."""
    from qgis.core import (
        QgsColorRampShader,
        QgsRasterBandStats,
        QgsRasterShader,
        QgsSingleBandPseudoColorRenderer,
        QgsStyle,
    )

    if not isinstance(layer, QgsRasterLayer):
        return False
    if kind == "probability":
        lo, hi, ramp_name, invert = 0.0, 1.0, "YlOrRd", False
    else:
        stats = layer.dataProvider().bandStatistics(1, QgsRasterBandStats.Min | QgsRasterBandStats.Max)
        lo, hi, ramp_name, invert = stats.minimumValue, stats.maximumValue, "Spectral", True
        if not hi > lo:
            return False
    ramp = QgsStyle.defaultStyle().colorRamp(ramp_name)
    if ramp is None:
        return False
    if invert:
        ramp.invert()
    fn = QgsColorRampShader(lo, hi, ramp, QgsColorRampShader.Interpolated)
    fn.classifyColorRamp(9, -1)
    shader = QgsRasterShader(lo, hi)
    shader.setRasterShaderFunction(fn)
    renderer = QgsSingleBandPseudoColorRenderer(layer.dataProvider(), 1, shader)
    renderer.setClassificationMin(lo)
    renderer.setClassificationMax(hi)
    layer.setRenderer(renderer)
    return True


def _flag_advanced(p):
    p.setFlags(p.flags() | QgsProcessingParameterDefinition.FlagAdvanced)


class GeocdAlgorithm(QgsProcessingAlgorithm):
    """A Processing algorithm that runs ``geocd --progress json <command> ...`` as a child process."""

    def __init__(self, spec: AlgSpec):
        super().__init__()
        self.spec = spec

    # --- identity ------------------------------------------------------------------------------------------------
    def createInstance(self):  # noqa: N802
        return GeocdAlgorithm(self.spec)

    def name(self):
        return self.spec.name

    def displayName(self):  # noqa: N802
        return tr(self.spec.display)

    def group(self):
        return tr(self.spec.group)

    def groupId(self):  # noqa: N802
        return self.spec.group_id

    def shortHelpString(self):  # noqa: N802
        cmd = " ".join(["geocd", *self.spec.command])
        return (
            tr(self.spec.short_help)
            + f"\n\nRuns `{cmd}` in geocd's own Python environment (see the provider's settings)."
        )

    def tags(self):
        return ["geocd", *self.spec.tags]

    def icon(self):
        from .provider import provider_icon

        return provider_icon()

    def flags(self):
        # the child process does the work; nothing here touches the project's layers, so it runs in a thread
        return super().flags()

    def canExecute(self):  # noqa: N802
        argv, msg = locate.check_geocd(configured_executable())
        return (argv is not None), ("" if argv is not None else msg)

    # --- parameters ----------------------------------------------------------------------------------------------
    def initAlgorithm(self, config=None):  # noqa: N802
        for p in self.spec.params:
            d = self._definition(p)
            if p.help and hasattr(d, "setHelp"):
                d.setHelp(p.help)
            if p.advanced:
                _flag_advanced(d)
            self.addParameter(d)
        for o in self.spec.outputs:
            self.addOutput(self._output(o.name, o.kind, o.label))
        if any(p.name == OUTPUT_FOLDER for p in self.spec.params):
            self.addOutput(QgsProcessingOutputMultipleLayers("LAYERS", tr("All loaded layers")))
        if self.spec.writes_manifest:
            self.addOutput(QgsProcessingOutputFile("SCENE_MANIFEST", tr("Scene manifest written for geocd")))
        if self.spec.stdout_output:
            self.addOutput(QgsProcessingOutputString(self.spec.stdout_output, tr("Text printed by geocd")))

    @staticmethod
    def _output(name, kind, label):
        if kind == "raster":
            return QgsProcessingOutputRasterLayer(name, tr(label))
        if kind == "vector":
            return QgsProcessingOutputVectorLayer(name, tr(label))
        if kind == "folder":
            return QgsProcessingOutputFolder(name, tr(label))
        return QgsProcessingOutputFile(name, tr(label))

    @staticmethod
    def _definition(p: Param):
        label = tr(p.label) + (f" [{p.unit}]" if p.unit else "")
        if p.kind == "raster":
            return QgsProcessingParameterRasterLayer(p.name, label, optional=p.optional)
        if p.kind == "rasters":
            return QgsProcessingParameterMultipleLayers(p.name, label, QgsProcessing.TypeRaster, optional=p.optional)
        if p.kind in ("numbers", "pair"):
            return QgsProcessingParameterString(p.name, label, p.default, False, p.optional)
        if p.kind == "extent":
            return QgsProcessingParameterExtent(p.name, label, p.default, p.optional)
        if p.kind == "file_destination":
            return QgsProcessingParameterFileDestination(p.name, label, p.file_filter, optional=p.optional)
        if p.kind == "vector":
            return QgsProcessingParameterFeatureSource(p.name, label, [_GEOMETRY[p.geometry]], optional=p.optional)
        if p.kind == "file":
            # QGIS accepts only names ending in `extension` when one is set: a filter alone keeps .yml/.json open
            return QgsProcessingParameterFile(
                p.name,
                label,
                QgsProcessingParameterFile.File,
                "" if p.file_filter else p.extension,
                p.default,
                p.optional,
                p.file_filter,
            )
        if p.kind == "folder":
            return QgsProcessingParameterFile(
                p.name, label, QgsProcessingParameterFile.Folder, defaultValue=p.default, optional=p.optional
            )
        if p.kind in ("number", "int"):
            t = QgsProcessingParameterNumber.Double if p.kind == "number" else QgsProcessingParameterNumber.Integer
            d = QgsProcessingParameterNumber(p.name, label, t, p.default, p.optional)
            if p.min is not None:
                d.setMinimum(p.min)
            if p.max is not None:
                d.setMaximum(p.max)
            return d
        if p.kind == "range":
            return QgsProcessingParameterRange(
                p.name, label, QgsProcessingParameterNumber.Double, p.default, p.optional
            )
        if p.kind == "enum":
            return QgsProcessingParameterEnum(
                p.name, label, [tr(o[0]) for o in p.options], False, p.default, p.optional
            )
        if p.kind == "bool":
            return QgsProcessingParameterBoolean(p.name, label, bool(p.default), p.optional)
        if p.kind == "string":
            return QgsProcessingParameterString(p.name, label, p.default, False, p.optional)
        if p.kind == "crs":
            return QgsProcessingParameterCrs(p.name, label, p.default, p.optional)
        if p.kind == "folder_destination":
            return QgsProcessingParameterFolderDestination(p.name, label, optional=p.optional)
        raise ValueError(f"unknown parameter kind {p.kind!r} for {p.name}")

    # --- parameter values → plain values ---------------------------------------------------------------------------
    def _raster_path(self, layer, p: Param) -> str:
        if layer.providerType() != "gdal":
            raise QgsProcessingException(
                tr(
                    f"{p.label}: geocd reads raster files; layer {layer.name()!r} comes from the "
                    f"{layer.providerType()!r} provider. Save it as a GeoTIFF first."
                )
            )
        return _abs(layer.source())

    def _values(self, parameters, context, feedback) -> dict:
        vals: dict = {}
        for p in self.spec.params:
            given = parameters.get(p.name)
            k = p.kind
            if (given is None or given == "") and k not in ("folder_destination", "file_destination", "bool"):
                if p.default is None or k in ("raster", "rasters", "vector", "file", "folder", "extent"):
                    vals[p.name] = None
                    continue
            if k == "raster":
                layer = self.parameterAsRasterLayer(parameters, p.name, context)
                vals[p.name] = self._raster_path(layer, p) if layer is not None else None
            elif k == "rasters":
                layers = self.parameterAsLayerList(parameters, p.name, context)
                vals[p.name] = [self._raster_path(l, p) for l in layers] or None
            elif k == "vector":
                if p.manifest:  # the manifest takes {path, layer}: a GeoPackage layer need not be copied
                    path, layer_name = self.parameterAsCompatibleSourceLayerPathAndLayerName(
                        parameters, p.name, context, ["gpkg", "shp", "geojson", "fgb"], "gpkg", feedback
                    )
                    vals[p.name] = _abs(f"{path}|layername={layer_name}" if layer_name else path) or None
                else:  # the CLI takes a file (its first layer): selections, memory layers, other formats and a
                    # named layer of a GeoPackage are exported to a temporary GeoPackage by QGIS
                    vals[p.name] = (
                        _abs(
                            self.parameterAsCompatibleSourceLayerPath(
                                parameters, p.name, context, ["gpkg", "shp", "geojson", "fgb"], "gpkg", feedback
                            )
                        )
                        or None
                    )
            elif k in ("file", "folder"):
                vals[p.name] = _abs(self.parameterAsFile(parameters, p.name, context)) or None
            elif k == "number":
                vals[p.name] = self.parameterAsDouble(parameters, p.name, context)
            elif k == "int":
                vals[p.name] = self.parameterAsInt(parameters, p.name, context)
            elif k == "range":
                r = self.parameterAsRange(parameters, p.name, context)
                vals[p.name] = (r[0], r[1]) if len(r) == 2 else None
            elif k == "enum":
                vals[p.name] = self.parameterAsEnum(parameters, p.name, context)
            elif k == "bool":
                vals[p.name] = self.parameterAsBoolean(parameters, p.name, context)
            elif k in ("string", "numbers", "pair"):
                vals[p.name] = self.parameterAsString(parameters, p.name, context)
            elif k == "crs":
                crs = self.parameterAsCrs(parameters, p.name, context)
                vals[p.name] = (crs.authid() or crs.toWkt()) if crs.isValid() else None
            elif k == "extent":
                rect = self.parameterAsExtent(parameters, p.name, context)
                crs = self.parameterAsExtentCrs(parameters, p.name, context)
                if rect.isNull() or rect.isEmpty():
                    vals[p.name] = None
                elif not crs.isValid():
                    raise QgsProcessingException(tr(f"{p.label}: the extent has no CRS; pick it on a map or a layer"))
                else:
                    vals[p.name] = (
                        rect.xMinimum(),
                        rect.yMinimum(),
                        rect.xMaximum(),
                        rect.yMaximum(),
                        crs.authid() or crs.toWkt(),
                    )
            elif k == "folder_destination":
                path = self.parameterAsString(parameters, p.name, context)
                if not path or path == QgsProcessing.TEMPORARY_OUTPUT:
                    path = QgsProcessingUtils.generateTempFilename(p.name)
                vals[p.name] = _abs(path)
            elif k == "file_destination":
                path = self.parameterAsFileOutput(parameters, p.name, context)
                vals[p.name] = _abs(path) or None
        return vals

    # --- run -----------------------------------------------------------------------------------------------------
    def processAlgorithm(self, parameters, context, feedback):  # noqa: N802
        """Run geocd; every failure reaches QGIS as a one-line QgsProcessingException, never a traceback."""
        try:
            return self._process(parameters, context, feedback)
        except QgsProcessingException:
            raise
        except Exception as exc:  # noqa: BLE001 - the plugin's single error path
            feedback.pushDebugInfo(f"{type(exc).__name__}: {exc}")
            raise QgsProcessingException(tr(runner.describe_exception(exc))) from None

    def _process(self, parameters, context, feedback):
        argv, msg = locate.check_geocd(configured_executable())
        if argv is None:
            raise QgsProcessingException(msg)
        vals = self._values(parameters, context, feedback)
        out_dir = vals.get(OUTPUT_FOLDER)
        file_outs = [vals[p.name] for p in self.spec.params if p.kind == "file_destination" and vals.get(p.name)]
        watched = [d for d in {out_dir, *(str(Path(f).parent) for f in file_outs)} if d]
        before = {d: runner.snapshot(d) for d in watched}  # before creating anything: a new folder goes on cancel
        if out_dir:
            Path(out_dir).mkdir(parents=True, exist_ok=True)
        manifest_path = None
        if self.spec.writes_manifest:
            try:
                manifest = specs.build_manifest(self.spec, vals, name=f"qgis_{self.spec.name}", output=out_dir)
            except ValueError as exc:
                raise QgsProcessingException(tr(str(exc))) from exc
            manifest_path = str(Path(out_dir) / "scene_from_qgis.json")
            Path(manifest_path).write_text(json.dumps(manifest, indent=2), encoding="utf-8")
            feedback.pushInfo(tr(f"scene manifest written to {manifest_path}"))
        try:
            args = specs.build_args(self.spec, vals, manifest_path=manifest_path)
        except ValueError as exc:
            raise QgsProcessingException(tr(str(exc))) from exc
        cmd = [*argv, "--progress", "json", *args]
        feedback.pushCommandInfo(" ".join(_quote(a) for a in cmd))
        state = {"text": None}

        def on_progress(fraction, message, stage):
            if fraction is not None:
                feedback.setProgress(100.0 * min(max(fraction, 0.0), 1.0))
            text = f"{stage}: {message}" if stage and message else (message or stage)
            if text and text != state["text"]:
                state["text"] = text
                feedback.setProgressText(text)

        cwd = out_dir or (watched[0] if watched else None)
        res = runner.run_geocd(
            cmd,
            on_progress=on_progress,
            on_info=feedback.pushInfo,
            on_warning=feedback.pushWarning,
            on_console=feedback.pushConsoleInfo,
            is_cancelled=feedback.isCanceled,
            on_start=lambda pid: feedback.pushDebugInfo(f"geocd child process id {pid}"),
            env=locate.child_env(),
            cwd=cwd,
        )
        if res.cancelled:
            removed = [
                f
                for d in watched
                for f in runner.remove_new_files(d, before[d])
                if d == out_dir
                or any(Path(f).name == Path(o).name or Path(f).name.startswith(f".{Path(o).stem}.") for o in file_outs)
            ]
            feedback.pushInfo(
                tr(f"cancelled: geocd (pid {res.pid}) stopped; removed {len(removed)} partial output file(s)")
            )
            raise QgsProcessingException(tr(res.failure_message()))
        if res.returncode != 0:
            raise QgsProcessingException(res.failure_message())
        results = self._collect(res, vals, out_dir, context, feedback)
        if manifest_path:
            results["SCENE_MANIFEST"] = manifest_path
        return results

    def _collect(self, res: runner.RunResult, vals: dict, out_dir, context, feedback) -> dict:
        results: dict = {}
        if out_dir:
            results[OUTPUT_FOLDER] = out_dir
        for p in self.spec.params:
            if p.kind in ("file_destination", "folder_destination") and vals.get(p.name):
                results[p.name] = vals[p.name]
        if self.spec.stdout_output:
            results[self.spec.stdout_output] = res.stdout  # already shown line by line as console output
        named = {o.key for o in self.spec.outputs}
        loaded: list[str] = []
        for o in self.spec.outputs:
            path = res.outputs.get(o.key)
            if path is None:
                if o.kind in ("raster", "vector"):
                    feedback.pushWarning(tr(f"geocd announced no {o.key!r} output"))
                continue
            if o.kind == "vector" and o.layers:
                present = [ln for ln in o.layers if ln in _gpkg_layers(path)]
                results[o.name] = f"{path}|layername={present[0]}" if present else path
            else:
                results[o.name] = path
            if o.load:
                loaded += self._load(path, o.kind, o.label, o.name, o.layers, o.style, context)
        if self.spec.load_unlisted:
            for key, path in sorted(res.outputs.items()):
                if key in named or any(key.startswith(s) for s in self.spec.skip_prefixes):
                    continue
                ext = Path(path).suffix.lower()
                kind = "raster" if ext in _RASTER_EXT else "vector" if ext in _VECTOR_EXT else None
                if kind is not None and Path(path).exists():
                    loaded += self._load(path, kind, key, key, (), None, context)
        if out_dir:
            results["LAYERS"] = loaded
        return results

    def _load(self, path: str, kind: str, label: str, output_name: str, layers: tuple, style, context) -> list[str]:
        """Queue ``path`` (the ``layers`` of a GeoPackage that exist) to load, styled, when the run completes."""
        fallback = style or None
        uris = []
        if kind == "raster":
            uris.append((path, label, QgsProcessingUtils.LayerHint.Raster))
        elif kind == "vector":
            available = _gpkg_layers(path)
            names = [ln for ln in layers if ln in available] if layers else available
            for ln in names:
                uri = f"{path}|layername={ln}" if path.lower().endswith(".gpkg") else path
                title = specs.LAYER_TITLES.get(ln, label if len(names) == 1 else f"{label}: {ln}")
                uris.append((uri, title, QgsProcessingUtils.LayerHint.Vector))
        else:
            return []
        out = []
        for uri, name, hint in uris:
            details = QgsProcessingContext.LayerDetails(name, context.project(), output_name, hint)
            pp = StylePostProcessor(fallback)
            _KEEP_ALIVE.append(pp)
            details.setPostProcessor(pp)
            context.addLayerToLoadOnCompletion(uri, details)
            out.append(uri)
        return out


def _gpkg_layers(path: str) -> list[str]:
    """Feature layers of a vector file (GeoPackage: not layer_styles, not plain tables)."""
    layer = QgsVectorLayer(path, "probe", "ogr")
    names = []
    if layer.isValid():
        for sub in layer.dataProvider().subLayers():
            parts = sub.split(QgsDataProvider.sublayerSeparator())
            if len(parts) >= 4 and parts[1] != "layer_styles" and parts[3] not in ("NoGeometry", "None", ""):
                names.append(parts[1])
    return names or ([Path(path).stem] if layer.isValid() else [])


def _abs(source: str) -> str:
    """A layer source or path with its file part made absolute (the child runs in another folder)."""
    if not source:
        return source
    path, sep, rest = source.partition("|")
    if os.path.exists(path) and not os.path.isabs(path):
        path = os.path.abspath(path)
    elif not os.path.isabs(path) and not os.path.exists(path) and "://" not in path and ":" not in path[:2]:
        path = os.path.abspath(path)  # an output that does not exist yet
    return path + sep + rest


def _quote(a: str) -> str:
    return a if a and all(c.isalnum() or c in "-_./:=,+@" for c in a) else "'" + a.replace("'", "'\\''") + "'"
