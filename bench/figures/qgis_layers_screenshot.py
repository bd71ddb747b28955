"""Headless QGIS rendering of layers a geocd run wrote, with the styles that travel with them.

Vectors are GeoPackage layers (QGIS applies the default style stored in the GeoPackage's ``layer_styles``),
rasters are GeoTIFFs (QGIS applies the ``.qml`` sidecar). The first layer given is drawn on top. Run with the
system Python that has PyQGIS::

    QT_QPA_PLATFORM=offscreen /usr/bin/python3 bench/figures/qgis_layers_screenshot.py \\
        --layer "/tmp/kahra2/sc_changes.gpkg|layername=buildings" \\
        --layer /tmp/kahra2/orthos_ground/post_event_img1.tif \\
        --out /tmp/qgis_map.png
    .venv/bin/python bench/figures/qgis_layers_screenshot.py --legend /tmp/qgis_map.png docs/qgis_kahramanmaras.png \\
        --counts /tmp/kahra2/sc_changes.gpkg --title "Kahramanmaraş: building damage (geocd run, styled layers rendered by QGIS 3.22)"
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path


def add_legend(map_png: str, out_png: str, title: str, gpkg: str | None = None) -> None:
    """Title and the damage classes' legend around a QGIS map image (geocd's venv: matplotlib).

    ``gpkg``: a run's GeoPackage; the legend then lists the classes its building layer holds (``buildings``, else
    ``building_damage``) with the count of each, and is titled with that layer's name.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.image as mpimg
    import matplotlib.pyplot as plt
    import pyogrio
    from matplotlib.patches import Patch

    from geocd.change.dsm_buildings import DAMAGE_CLASSES
    from geocd.change.plots import QUICKLOOK_CLASSES
    from geocd.change.building_layer import read_building_layer

    entries = [(c, lab) for c, lab in DAMAGE_CLASSES.values()]
    layer_title = "buildings (class)"
    if gpkg is not None:
        layer = read_building_layer(gpkg)
        counts = layer["class"].value_counts().to_dict()
        entries = [
            (QUICKLOOK_CLASSES[k][0], f"{QUICKLOOK_CLASSES[k][1]} ({counts[k]})")
            for k in QUICKLOOK_CLASSES
            if k in counts
        ]
        names = {str(n) for n, _ in pyogrio.list_layers(gpkg)}
        layer_title = f"{'buildings' if 'buildings' in names else 'building_damage'}: class (count)"
    img = mpimg.imread(map_png)
    h, w = img.shape[:2]
    fig = plt.figure(figsize=(w / 100 + 2.6, h / 100 + 0.5), dpi=100)
    ax = fig.add_axes([0, 0, w / (w + 260), h / (h + 50)])
    ax.imshow(img)
    ax.axis("off")
    fig.legend(
        handles=[Patch(facecolor=c, edgecolor="#323232", label=lab) for c, lab in entries],
        loc="center right",
        title=layer_title,
        fontsize=9,
        frameon=False,
    )
    fig.suptitle(title, x=0.02, ha="left", fontsize=12, fontweight="bold")
    fig.savefig(out_png, dpi=70)


def main(argv=None) -> int:
    if argv is None and len(sys.argv) > 1 and sys.argv[1] == "--legend":
        ap = argparse.ArgumentParser()
        ap.add_argument("--legend", nargs=2)
        ap.add_argument("--title", default="")
        ap.add_argument("--counts", default=None, help="the run's sc_changes.gpkg: count the classes of its buildings")
        a = ap.parse_args()
        add_legend(a.legend[0], a.legend[1], a.title, a.counts)
        return 0
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--layer", action="append", required=True, help="GeoTIFF, or 'file.gpkg|layername=NAME'")
    ap.add_argument("--out", required=True)
    ap.add_argument("--size", default="1100x1000")
    ap.add_argument("--dpi", type=float, default=110.0)
    args = ap.parse_args(argv)
    os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
    os.environ.setdefault("GDAL_PAM_ENABLED", "NO")
    from qgis.core import (
        QgsApplication,
        QgsMapRendererParallelJob,
        QgsMapSettings,
        QgsProject,
        QgsRasterLayer,
        QgsRectangle,
        QgsVectorLayer,
    )
    from qgis.PyQt.QtCore import QSize
    from qgis.PyQt.QtGui import QColor

    QgsApplication.setPrefixPath("/usr", True)
    app = QgsApplication([], False)
    app.initQgis()
    project = QgsProject.instance()
    layers = []
    for uri in args.layer:
        name = uri.split("layername=")[-1] if "layername=" in uri else Path(uri).stem
        layer = QgsVectorLayer(uri, name, "ogr") if ".gpkg" in uri else QgsRasterLayer(uri, name)
        if not layer.isValid() and uri.endswith("layername=buildings"):  # a run before the layers were merged
            uri, name = uri.replace("layername=buildings", "layername=building_damage"), "building_damage"
            layer = QgsVectorLayer(uri, name, "ogr")
        if not layer.isValid():
            raise SystemExit(f"cannot load {uri}")
        project.addMapLayer(layer)
        layers.append(layer)
        print(f"loaded {name}: {layer.renderer().type() if layer.renderer() else '?'}")
    extent = QgsRectangle(layers[-1].extent())
    box_w, box_h = (int(v) for v in args.size.lower().split("x"))
    aspect = extent.width() / extent.height()
    w, h = (box_w, int(round(box_w / aspect))) if box_w / aspect <= box_h else (int(round(box_h * aspect)), box_h)
    ms = QgsMapSettings()
    ms.setLayers(layers)
    ms.setDestinationCrs(layers[-1].crs())
    ms.setOutputSize(QSize(w, h))
    ms.setOutputDpi(args.dpi)
    ms.setBackgroundColor(QColor(255, 255, 255))
    ms.setExtent(extent)
    job = QgsMapRendererParallelJob(ms)
    job.start()
    job.waitForFinished()
    # the map only: a legend drawn with QgsLegendRenderer crashed this headless session (segfault in QGIS 3.22
    # without the Processing framework loaded); --legend adds one with matplotlib from the layer's classes
    img = job.renderedImage()
    img.save(args.out, "PNG")
    print(f"wrote {args.out} ({img.width()}x{img.height()})")
    os._exit(0)


if __name__ == "__main__":
    sys.exit(main())
