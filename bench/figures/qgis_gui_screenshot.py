"""Screenshots of the QGIS desktop with the geocd plugin: the Processing toolbox, and an algorithm dialog after a run.

This is QGIS's own GUI (not a mock-up), started under a virtual X server with this file as its startup code.
It runs one geocd algorithm exactly as a user would (``processing.runAndLoadResults``: the layers load styled
into the project), filters the toolbox on "geocd", grabs the main window, then opens the algorithm's dialog,
runs it there and grabs the dialog with geocd's progress in its log.

    apt-get install -y --no-install-recommends xvfb xauth      # once
    D=../shared/data/usgs_msh_dome_dems/geotiff_utm10n
    GEOCD_SHOT_ALG=geocd:demdiff GEOCD_SHOT_PARAMS="DEM_A=$D/2.tif;DEM_B=$D/27.tif" \\
    GEOCD_SHOT_HIDE="Significance: confidence %, sigma (m), z;Change mask (raised / lowered / unchanged)" \\
    GEOCD_SHOT_BACKDROP=$D/27.tif \\
    GEOCD_SHOT_DIR=docs GEOCD_EXECUTABLE=$PWD/.venv/bin/geocd QGIS_PLUGINPATH=$PWD/qgis_plugin GDAL_PAM_ENABLED=NO \\
    QGIS_CUSTOM_CONFIG_PATH=$(mktemp -d) xvfb-run -a -s "-screen 0 1600x1000x24" \\
        /usr/bin/qgis.bin --nologo --noversioncheck --code bench/figures/qgis_gui_screenshot.py

(GDAL_PAM_ENABLED=NO: QGIS computes statistics of the input layers, which GDAL would otherwise store beside
them as .aux.xml.) Writes ``$GEOCD_SHOT_DIR/qgis_toolbox.png`` and ``$GEOCD_SHOT_DIR/qgis_dialog.png``; QGIS quits when done.
The script starts the plugin when the profile has not enabled it.
"""

import os
import sys
import tempfile

from qgis.core import QgsHillshadeRenderer, QgsProject, QgsRasterLayer, QgsVectorLayer
from qgis.PyQt.QtCore import Qt, QTimer
from qgis.PyQt.QtWidgets import QDockWidget, QTabWidget
from qgis.utils import iface, loadPlugin, startPlugin, plugins

OUT_DIR = os.environ.get("GEOCD_SHOT_DIR", "docs")
ALG = os.environ.get("GEOCD_SHOT_ALG", "geocd:demdiff")
PARAMS = dict(kv.split("=", 1) for kv in os.environ.get("GEOCD_SHOT_PARAMS", "").split(";") if kv)
HIDE = [n for n in os.environ.get("GEOCD_SHOT_HIDE", "").split(";") if n]
BACKDROP = os.environ.get("GEOCD_SHOT_BACKDROP", "")
WORK = tempfile.mkdtemp(prefix="geocd_gui_shot_")
state = {}


def log(msg):
    sys.stderr.write(f"[qgis_gui_screenshot] {msg}\n")
    sys.stderr.flush()


def finish(code=0):
    # QgsApplication.exit() would stop at QGIS's "save the project?" prompt; nothing here needs saving
    sys.stderr.flush()
    os._exit(code)


def safe(fn):
    """Timer callbacks: an exception must end QGIS (a Python error dialog would block a headless run)."""

    def _run():
        try:
            fn()
        except Exception:  # noqa: BLE001
            import traceback

            log(traceback.format_exc())
            finish(1)

    return _run


def step_run():
    if "geocd_qgis" not in plugins:
        loadPlugin("geocd_qgis") and startPlugin("geocd_qgis")
    import processing
    from processing.core.ProcessingConfig import ProcessingConfig

    ProcessingConfig.setSettingValue("KEEP_DIALOG_OPEN", True)
    mw = iface.mainWindow()
    mw.resize(1600, 1000)
    params = dict(PARAMS, OUTPUT=os.path.join(WORK, "toolbox_run"))
    log(f"running {ALG} {params}")
    processing.runAndLoadResults(ALG, params)
    project = QgsProject.instance()
    root = project.layerTreeRoot()
    for layer in project.mapLayers().values():
        node = root.findLayer(layer.id())
        if layer.name() in HIDE:
            node.setItemVisibilityChecked(False)
        if isinstance(layer, QgsVectorLayer):  # polygons above the rasters
            clone = node.clone()
            root.insertChildNode(0, clone)
            node.parent().removeChildNode(node)
    if BACKDROP:
        bd = QgsRasterLayer(BACKDROP, "Hillshade (DEM B)")
        bd.setRenderer(QgsHillshadeRenderer(bd.dataProvider(), 1, 315, 45))
        bd.setOpacity(0.7)
        project.addMapLayer(bd, False)
        root.addLayer(bd)
        for layer in project.mapLayers().values():
            if isinstance(layer, QgsRasterLayer) and layer is not bd:
                layer.setOpacity(0.8)
    for name in ("Browser", "Browser2", "ResultsViewer"):
        dock = mw.findChild(QDockWidget, name)
        if dock is not None:
            dock.hide()
    layers_dock = mw.findChild(QDockWidget, "Layers")
    if layers_dock is not None:
        layers_dock.show()
    toolbox = mw.findChild(QDockWidget, "ProcessingToolbox")
    toolbox.show()
    toolbox.raise_()
    mw.resizeDocks([toolbox], [430], Qt.Horizontal)
    toolbox.searchBox.setText("geocd")
    toolbox.algorithmTree.expandAll()
    for layer in project.mapLayers().values():
        if isinstance(layer, QgsVectorLayer):
            iface.setActiveLayer(layer)
    canvas = iface.mapCanvas()
    canvas.zoomToFullExtent()
    canvas.refresh()
    QTimer.singleShot(8000, safe(step_grab_main))


def step_grab_main():
    mw = iface.mainWindow()
    path = os.path.join(OUT_DIR, "qgis_toolbox.png")
    mw.grab().save(path)
    log(f"wrote {path}")
    import processing

    state["dialog_out"] = os.path.join(WORK, "dialog_run")
    dlg = processing.createAlgorithmDialog(ALG, dict(PARAMS, OUTPUT=state["dialog_out"]))
    dlg.resize(1100, 820)
    dlg.show()
    state["dlg"] = dlg
    dlg.runAlgorithm()  # runs as a task; the dialog shows geocd's progress in its log tab
    state["t"] = 0
    QTimer.singleShot(1000, safe(step_wait_dialog))


def step_wait_dialog():
    state["t"] += 1
    out = state["dialog_out"]
    done = os.path.isdir(out) and any(f.endswith(".json") for f in os.listdir(out))
    if not done and state["t"] < 400:
        QTimer.singleShot(1000, safe(step_wait_dialog))
        return
    QTimer.singleShot(4000, safe(step_grab_dialog))


def step_grab_dialog():
    dlg = state["dlg"]
    tabs = dlg.findChild(QTabWidget)
    if tabs is not None and tabs.count() > 1:
        tabs.setCurrentIndex(1)
    path = os.path.join(OUT_DIR, "qgis_dialog.png")
    dlg.grab().save(path)
    log(f"wrote {path}")
    finish(0)


QTimer.singleShot(3000, safe(step_run))
QTimer.singleShot(600000, lambda: finish(1))  # never hang a batch job
