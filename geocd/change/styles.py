"""QGIS styles (QML) for geocd's layers.

Static styles live in ``geocd/styles/*.qml``; categorized polygon styles are
generated here so the categories stay in one place with the code that writes
the attribute. Raster styles are written as ``<raster>.qml`` sidecars, which
QGIS loads automatically; vector styles go into the GeoPackage's
``layer_styles`` table.
"""

from __future__ import annotations

from xml.sax.saxutils import quoteattr


def _symbol(i: int, fill: str, outline: str = "#323232", fill_alpha: int = 200, style: str = "solid") -> str:
    r, g, b = (int(fill[k : k + 2], 16) for k in (1, 3, 5))
    ro, go, bo = (int(outline[k : k + 2], 16) for k in (1, 3, 5))
    return f"""      <symbol type="fill" name="{i}" alpha="1" clip_to_extent="1" force_rhr="0">
        <layer class="SimpleFill" enabled="1" locked="0" pass="0">
          <Option type="Map">
            <Option type="QString" name="color" value="{r},{g},{b},{fill_alpha}"/>
            <Option type="QString" name="outline_color" value="{ro},{go},{bo},255"/>
            <Option type="QString" name="outline_style" value="solid"/>
            <Option type="QString" name="outline_width" value="0.4"/>
            <Option type="QString" name="outline_width_unit" value="MM"/>
            <Option type="QString" name="style" value="{style}"/>
            <Option type="QString" name="joinstyle" value="bevel"/>
          </Option>
          <prop k="color" v="{r},{g},{b},{fill_alpha}"/>
          <prop k="outline_color" v="{ro},{go},{bo},255"/>
          <prop k="outline_style" v="solid"/>
          <prop k="outline_width" v="0.4"/>
          <prop k="outline_width_unit" v="MM"/>
          <prop k="style" v="{style}"/>
          <prop k="joinstyle" v="bevel"/>
        </layer>
      </symbol>
"""


def discrete_pseudocolor_qml(items, *, band: int = 1, maximum: float = 1.0) -> str:
    """A QGIS discrete pseudocolour raster style.

    ``items``: (upper value or ``"inf"``, ``#rrggbb`` colour, alpha 0–255, label), in increasing order.
    """
    rows = "\n".join(f'          <item value="{v}" color="{c}" alpha="{a}" label="{lab}"/>' for v, c, a, lab in items)
    return f"""<!DOCTYPE qgis PUBLIC 'http://mrcc.com/qgis.dtd' 'SYSTEM'>
<qgis version="3.22.16-Białowieża" styleCategories="AllStyleCategories">
  <pipe>
    <rasterrenderer type="singlebandpseudocolor" band="{band}" opacity="1" alphaBand="-1" nodataColor="">
      <rasterTransparency/>
      <rastershader>
        <colorrampshader colorRampType="DISCRETE" classificationMode="1" minimumValue="0" maximumValue="{maximum:g}"
                         clip="0" labelPrecision="2">
{rows}
        </colorrampshader>
      </rastershader>
    </rasterrenderer>
    <brightnesscontrast brightness="0" contrast="0" gamma="1"/>
    <huesaturation saturation="0" colorizeOn="0" grayscaleMode="0" invertColors="0"/>
    <rasterresampler maxOversampling="2"/>
  </pipe>
  <blendMode>0</blendMode>
</qgis>
"""


def categorized_polygon_qml(attribute: str, categories: dict, label_field: str | None = None) -> str:
    """QML for a polygon layer categorized on ``attribute``.

    Parameters
    ----------
    categories : mapping value → (fill colour "#rrggbb", label)
    label_field : optional attribute shown as a label
    """
    cats = []
    syms = []
    for i, (value, (colour, label)) in enumerate(categories.items()):
        cats.append(
            f'      <category render="true" symbol="{i}" value={quoteattr(str(value))} label={quoteattr(label)}/>'
        )
        style = "no" if colour.lower() == "#ffffff" else "solid"
        syms.append(_symbol(i, colour, style=style))
    labeling = ""
    if label_field:
        labeling = f"""  <labeling type="simple">
    <settings calloutType="simple">
      <text-style fieldName={quoteattr(label_field)} fontSize="8" fontFamily="Sans Serif" textColor="0,0,0,255" isExpression="0">
        <text-buffer bufferDraw="1" bufferSize="0.8" bufferColor="255,255,255,255"/>
      </text-style>
      <placement placement="0"/>
    </settings>
  </labeling>
"""
    return f"""<!DOCTYPE qgis PUBLIC 'http://mrcc.com/qgis.dtd' 'SYSTEM'>
<qgis version="3.22.16-Białowieża" styleCategories="AllStyleCategories" labelsEnabled="{1 if label_field else 0}">
  <renderer-v2 type="categorizedSymbol" attr={quoteattr(attribute)} forceraster="0" symbollevels="0" enableorderby="0" referencescale="-1">
    <categories>
{chr(10).join(cats)}
    </categories>
    <symbols>
{"".join(syms)}    </symbols>
  </renderer-v2>
{labeling}  <blendMode>0</blendMode>
  <featureBlendMode>0</featureBlendMode>
  <layerOpacity>1</layerOpacity>
</qgis>
"""


def write_raster_style(raster_path, qml: str):
    """Write ``<raster>.qml`` beside a raster (QGIS loads it as the default style)."""
    from pathlib import Path

    from ..io.atomic import write_text_atomic

    p = Path(raster_path)
    return write_text_atomic(p.with_suffix(".qml"), qml)
