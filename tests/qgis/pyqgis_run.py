"""Standalone PyQGIS driver for the plugin tests (run by /usr/bin/python3, not by pytest).

    pyqgis_run.py run ALG K=V ...                  run, then load the layers queued for loading (styled)
    pyqgis_run.py cancel ALG FRACTION K=V ...      cancel once geocd reports progress >= FRACTION
    pyqgis_run.py error ALG K=V ...                expect a QgsProcessingException

Prints one JSON report as its last stdout line. Needs QT_QPA_PLATFORM=offscreen, QGIS_PLUGINPATH and
QGIS_CUSTOM_CONFIG_PATH (set by tests/qgis/qgis_env.py).
"""

from __future__ import annotations

import json
import os
import re
import sys
import time


def main(argv: list[str]) -> dict:
    from qgis.core import (
        QgsApplication,
        QgsProcessingContext,
        QgsProcessingException,
        QgsProcessingFeedback,
        QgsProject,
    )

    QgsApplication.setPrefixPath("/usr", True)
    app = QgsApplication([], False)
    app.initQgis()
    sys.path.append("/usr/share/qgis/python/plugins")
    from processing.core.Processing import Processing

    Processing.initialize()
    sys.path.insert(0, os.environ["QGIS_PLUGINPATH"])
    import geocd_qgis

    plugin = geocd_qgis.classFactory(None)
    plugin.initProcessing()
    import processing

    mode, alg = argv[0], argv[1]
    rest = argv[2:]
    threshold = float(rest.pop(0)) if mode == "cancel" else None
    params: dict = {}
    for kv in rest:  # a name given twice or more becomes a list (multiple-layer parameters)
        k, v = kv.split("=", 1)
        params[k] = [*params[k], v] if isinstance(params.get(k), list) else ([params[k], v] if k in params else v)
    report: dict = {"mode": mode, "alg": alg}

    class Feedback(QgsProcessingFeedback):
        def __init__(self):
            super().__init__()
            self.pid = None
            self.infos: list[str] = []
            self.progress_seen: list[float] = []
            self.cancel_time = None

        def pushDebugInfo(self, info):  # noqa: N802
            m = re.search(r"child process id (\d+)", info)
            if m:
                self.pid = int(m.group(1))
            super().pushDebugInfo(info)

        def pushInfo(self, info):  # noqa: N802
            self.infos.append(info)
            super().pushInfo(info)

        def setProgress(self, progress):  # noqa: N802
            self.progress_seen.append(progress)
            super().setProgress(progress)
            if threshold is not None and progress >= 100 * threshold and not self.isCanceled():
                self.cancel_time = time.monotonic()
                self.cancel()

    fb = Feedback()
    context = QgsProcessingContext()
    context.setProject(QgsProject.instance())
    t0 = time.monotonic()
    try:
        res = processing.run(alg, params, context=context, feedback=fb)
        report.update(ok=True, results={k: v for k, v in res.items() if isinstance(v, (str, int, float, list))})
    except QgsProcessingException as exc:
        report.update(ok=False, exception=type(exc).__name__, message=str(exc))
    report["elapsed_s"] = time.monotonic() - t0
    report["pid"] = fb.pid
    report["infos"] = fb.infos[-20:]
    report["max_progress"] = max(fb.progress_seen) if fb.progress_seen else None
    if fb.cancel_time is not None:
        report["stop_after_cancel_s"] = time.monotonic() - fb.cancel_time
    if fb.pid is not None:
        try:
            os.kill(fb.pid, 0)
            report["pid_alive"] = True
        except ProcessLookupError:
            report["pid_alive"] = False
        except PermissionError:
            report["pid_alive"] = True
    if mode == "run" and report.get("ok"):
        report["loaded"] = load_queued(context)
    return report


def load_queued(context) -> list[dict]:
    """Load the layers the algorithm queued for loading on completion, as QGIS's GUI does; describe their styles."""
    from qgis.core import QgsProcessingFeedback, QgsProject, QgsRasterLayer, QgsVectorLayer

    out = []
    for uri, details in context.layersToLoadOnCompletion().items():
        hint = details.layerTypeHint
        layer = (
            QgsRasterLayer(uri, details.name)
            if hint == details.layerTypeHint.Raster
            else QgsVectorLayer(uri, details.name, "ogr")
        )
        QgsProject.instance().addMapLayer(layer)
        pp = details.postProcessor()
        if pp is not None:
            pp.postProcessLayer(layer, context, QgsProcessingFeedback())
        d = {"uri": uri, "name": details.name, "valid": layer.isValid(), "output": details.outputName}
        if isinstance(layer, QgsRasterLayer):
            d["renderer"] = layer.renderer().type() if layer.renderer() else None
        else:
            d["renderer"] = layer.renderer().type() if layer.renderer() else None
            d["features"] = layer.featureCount()
        out.append(d)
    return out


if __name__ == "__main__":
    try:
        rep = main(sys.argv[1:])
    except Exception as exc:  # noqa: BLE001 - reported to the test as JSON
        import traceback

        rep = {"crash": f"{type(exc).__name__}: {exc}", "traceback": traceback.format_exc()}
    sys.stdout.write("\n" + json.dumps(rep, default=str) + "\n")
    sys.stdout.flush()
    os._exit(0)  # skip QGIS's exit-time teardown (slow, and irrelevant to the report)
