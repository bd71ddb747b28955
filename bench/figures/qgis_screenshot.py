"""Headless screenshot of geocd's change layers as QGIS renders them, after a run through the QGIS plugin.

Runs one algorithm of the geocd Processing provider in a standalone PyQGIS session (the plugin starts geocd as a
child process), loads the layers the algorithm queues for loading with their styles (exactly as the QGIS GUI
does), and renders them with QgsMapSettings + QgsMapRendererParallelJob, with a legend, into a PNG.

Run it with the system Python that has PyQGIS (not geocd's venv), e.g.::

    QT_QPA_PLATFORM=offscreen GEOCD_EXECUTABLE=$PWD/.venv/bin/geocd /usr/bin/python3 bench/figures/qgis_screenshot.py \\
        --alg geocd:demdiff --param DEM_A=../shared/data/usgs_msh_dome_dems/geotiff_utm10n/2.tif \\
        --param DEM_B=../shared/data/usgs_msh_dome_dems/geotiff_utm10n/27.tif \\
        --backdrop ../shared/data/usgs_msh_dome_dems/geotiff_utm10n/27.tif \\
        --hide "Change mask (raised / lowered / unchanged)" --hide "Significance: confidence %, sigma (m), z" \\
        --title "Mount St Helens dome growth, 2004-10-04 → 2007-07-05 (geocd:demdiff run in QGIS)" --out docs/qgis_msh_demdiff.png

    # sample_aoi, a 100 m crop with three images per epoch (the full AOI works the same, with geocd:run):
    S=sample_aoi; QT_QPA_PLATFORM=offscreen GEOCD_EXECUTABLE=$PWD/.venv/bin/geocd /usr/bin/python3 \\
        bench/figures/qgis_screenshot.py --alg geocd:runlayers \\
        --param IMAGES_A=$S/images/A_sat1.tif --param IMAGES_A=$S/images/A_sat2.tif --param IMAGES_A=$S/images/A_sat3.tif \\
        --param IMAGES_B=$S/images/B_sat1.tif --param IMAGES_B=$S/images/B_sat2.tif --param IMAGES_B=$S/images/B_sat3.tif \\
        --param DEM=$S/truth/dem_prior.tif --param DEM_DATUM=1 --param FOOTPRINTS=$S/truth/footprints_all.gpkg \\
        --param "AOI=374344,374444,4824244,4824344 [EPSG:32631]" \\
        --hide "Change mask (raised / lowered / unchanged)" \\
        --title "sample_aoi, 100 m crop: 3-D change A → B (geocd:runlayers run in QGIS)" --out docs/qgis_sample_aoi_change.png

    # sample_aoi, the whole AOI through the manifest (docs/qgis_sample_aoi_full.png):
    QT_QPA_PLATFORM=offscreen GEOCD_EXECUTABLE=$PWD/.venv/bin/geocd /usr/bin/python3 bench/figures/qgis_screenshot.py \\
        --alg geocd:run --param MANIFEST=sample_aoi/scene.yaml --hide "Change mask (raised / lowered / unchanged)" \\
        --title "sample_aoi: 3-D change A → B (geocd:run in QGIS)" --out docs/qgis_sample_aoi_full.png

``--workdir`` keeps the products (default: a temporary folder).
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def parse_args(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--alg", required=True, help="algorithm id, e.g. geocd:demdiff")
    ap.add_argument(
        "--param",
        action="append",
        default=[],
        help="NAME=VALUE (repeatable; repeat a NAME for a list, e.g. several image layers)",
    )
    ap.add_argument("--out", required=True, help="PNG to write")
    ap.add_argument("--title", default="")
    ap.add_argument("--backdrop", help="a DEM drawn as a hillshade under the layers")
    ap.add_argument("--backdrop-title", default="Hillshade (DEM B)")
    ap.add_argument(
        "--extent",
        choices=["rasters", "all"],
        default="rasters",
        help="map extent: the rasters' (default) or every layer's",
    )
    ap.add_argument("--hide", action="append", default=[], help="name of a loaded layer to leave out (repeatable)")
    ap.add_argument("--workdir", help="output folder of the run (default: temporary)")
    ap.add_argument("--size", default="1400x1000", help="map size in pixels, WxH")
    ap.add_argument("--dpi", type=float, default=110.0)
    ap.add_argument("--raster-opacity", type=float, default=0.8, help="opacity of the rasters over the backdrop")
    return ap.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
    os.environ.setdefault("QGIS_PLUGINPATH", str(REPO / "qgis_plugin"))
    # QGIS computes statistics of raster parameter layers; GDAL would store them beside the inputs (.aux.xml)
    os.environ.setdefault("GDAL_PAM_ENABLED", "NO")
    from qgis.core import (
        QgsApplication,
        QgsHillshadeRenderer,
        QgsLayerTree,
        QgsLayerTreeModel,
        QgsLegendRenderer,
        QgsLegendSettings,
        QgsMapRendererParallelJob,
        QgsMapSettings,
        QgsProcessingContext,
        QgsProcessingFeedback,
        QgsProject,
        QgsRasterLayer,
        QgsRectangle,
        QgsRenderContext,
        QgsVectorLayer,
    )
    from qgis.PyQt.QtCore import QSize, Qt, QRectF, QPointF
    from qgis.PyQt.QtGui import QColor, QFont, QImage, QPainter

    QgsApplication.setPrefixPath("/usr", True)
    app = QgsApplication([], False)
    app.initQgis()
    sys.path.append("/usr/share/qgis/python/plugins")
    from processing.core.Processing import Processing

    Processing.initialize()
    sys.path.insert(0, os.environ["QGIS_PLUGINPATH"])
    import geocd_qgis
    import processing

    plugin = geocd_qgis.classFactory(None)
    plugin.initProcessing()

    workdir = Path(args.workdir) if args.workdir else Path(tempfile.mkdtemp(prefix="geocd_qgis_shot_"))
    params: dict = {}
    for kv in args.param:  # a name given twice or more becomes a list (multiple-layer parameters)
        k, v = kv.split("=", 1)
        params[k] = [*params[k], v] if isinstance(params.get(k), list) else ([params[k], v] if k in params else v)
    params.setdefault("OUTPUT", str(workdir))
    project = QgsProject.instance()
    context = QgsProcessingContext()
    context.setProject(project)
    feedback = QgsProcessingFeedback()
    res = processing.run(args.alg, params, context=context, feedback=feedback)
    print(f"{args.alg} → {res.get('OUTPUT')}")

    # load the queued layers as the GUI does: create, add, apply the algorithm's post-processor (styles)
    layers = []
    for uri, details in context.layersToLoadOnCompletion().items():
        if details.name in args.hide:
            continue
        raster = details.layerTypeHint == details.layerTypeHint.Raster
        layer = QgsRasterLayer(uri, details.name) if raster else QgsVectorLayer(uri, details.name, "ogr")
        if not layer.isValid():
            raise SystemExit(f"cannot load {uri}")
        project.addMapLayer(layer)
        if details.postProcessor() is not None:
            details.postProcessor().postProcessLayer(layer, context, feedback)
        layers.append(layer)
        print(f"  loaded {details.name!r}: {layer.renderer().type() if layer.renderer() else '?'}")

    # vectors above rasters, masks above continuous rasters
    def order(l):
        if isinstance(l, QgsVectorLayer):
            return 0
        return 1 if "mask" in l.source().lower() else 2

    layers.sort(key=order)
    if args.backdrop:
        bd = QgsRasterLayer(args.backdrop, args.backdrop_title)
        hs = QgsHillshadeRenderer(bd.dataProvider(), 1, 315, 45)
        bd.setRenderer(hs)
        bd.setOpacity(0.7)
        project.addMapLayer(bd)
        for l in layers:
            if isinstance(l, QgsRasterLayer):
                l.setOpacity(args.raster_opacity)
        layers.append(bd)

    extent = QgsRectangle()
    rasters = [l for l in layers if isinstance(l, QgsRasterLayer) and l.name() != args.backdrop_title]
    for l in rasters if args.extent == "rasters" and rasters else layers:
        if extent.isEmpty():
            extent = QgsRectangle(l.extent())
        else:
            extent.combineExtentWith(l.extent())
    extent = extent.buffered(max(extent.width(), extent.height()) * 0.01)
    # the map keeps the extent's aspect inside the --size box
    box_w, box_h = (int(v) for v in args.size.lower().split("x"))
    aspect = extent.width() / extent.height()
    w, h = (box_w, int(round(box_w / aspect))) if box_w / aspect <= box_h else (int(round(box_h * aspect)), box_h)
    legend_w = 470
    title_h = 56 if args.title else 0
    ms = QgsMapSettings()
    ms.setLayers(layers)
    ms.setDestinationCrs(layers[0].crs())
    ms.setOutputSize(QSize(w, h))
    ms.setOutputDpi(args.dpi)
    ms.setBackgroundColor(QColor(255, 255, 255))
    ms.setExtent(extent)
    job = QgsMapRendererParallelJob(ms)
    job.start()
    job.waitForFinished()
    map_img = job.renderedImage()

    img = QImage(w + legend_w, h + title_h, QImage.Format_ARGB32)
    img.fill(QColor(255, 255, 255))
    p = QPainter(img)
    p.setRenderHint(QPainter.Antialiasing)
    if args.title:
        f = QFont("DejaVu Sans", 15)
        f.setBold(True)
        p.setFont(f)
        p.drawText(QRectF(14, 0, w + legend_w - 28, title_h), Qt.AlignVCenter | Qt.AlignLeft, args.title)
    p.drawImage(QPointF(0, title_h), map_img)
    # legend (QgsLegendRenderer draws in millimetres)
    root = QgsLayerTree()
    for l in layers:
        root.addLayer(l)
    model = QgsLayerTreeModel(root)
    ls = QgsLegendSettings()
    ls.setTitle("Layers")
    ls.setWrapChar("|")
    ls.setSymbolSize(ls.symbolSize() * 1.0)
    lr = QgsLegendRenderer(model, ls)
    px_per_mm = args.dpi / 25.4
    p.save()
    p.translate(w + 12, title_h + 12)
    p.scale(px_per_mm, px_per_mm)
    lr_ctx = QgsRenderContext.fromQPainter(p)
    lr_ctx.setFlag(QgsRenderContext.Antialiasing, True)
    lr.drawLegend(lr_ctx)
    p.restore()
    p.setPen(QColor(120, 120, 120))
    p.drawRect(0, title_h, w - 1, h - 1)
    p.end()
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    img.save(args.out, "PNG")
    print(f"wrote {args.out} ({img.width()}x{img.height()})")
    os._exit(0)


if __name__ == "__main__":
    sys.exit(main())
