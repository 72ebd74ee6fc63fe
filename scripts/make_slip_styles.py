"""Write the QML styles of the slipmap:displacement outputs (slip_tiles, slip_strips; the
moving-window raster uses make_styles.py's ``diverging``) with PyQGIS. Run with QGIS's
Python from the repository root:

    QT_QPA_PLATFORM=offscreen .venv/bin/python scripts/make_slip_styles.py
"""

from __future__ import annotations

import sys
from pathlib import Path

# shared with the field styles (run as a script, this directory is on sys.path)
from make_styles import _app, _save

STYLES = Path(sys.argv[1] if len(sys.argv) > 1 else "styles")
LABEL = (
    "CASE WHEN \"status\" = 'ok' THEN "
    "format_number(\"fault_parallel\" * 1000, 1) || ' ± ' || "
    "format_number(\"sigma_fp\" * 1000, 1) || ' mm' END"
)


def _labels(layer, offset_expression=None):
    from qgis.core import (
        QgsPalLayerSettings,
        QgsProperty,
        QgsTextBufferSettings,
        QgsTextFormat,
        QgsVectorLayerSimpleLabeling,
    )
    from qgis.PyQt.QtGui import QColor

    pal = QgsPalLayerSettings()
    pal.isExpression = True
    pal.fieldName = LABEL
    pal.placement = QgsPalLayerSettings.OverPoint
    fmt = QgsTextFormat()
    fmt.setSize(8)
    fmt.setColor(QColor("#202020"))
    buf = QgsTextBufferSettings()
    buf.setEnabled(True)
    buf.setSize(0.8)
    buf.setColor(QColor("white"))
    fmt.setBuffer(buf)
    pal.setFormat(fmt)
    if offset_expression:
        props = pal.dataDefinedProperties()
        props.setProperty(
            QgsPalLayerSettings.OffsetXY, QgsProperty.fromExpression(offset_expression)
        )
        pal.setDataDefinedProperties(props)
    layer.setLabeling(QgsVectorLayerSimpleLabeling(pal))
    layer.setLabelsEnabled(True)


def tiles_layer():
    from qgis.core import QgsFillSymbol, QgsRuleBasedRenderer, QgsVectorLayer

    layer = QgsVectorLayer(
        "Polygon?crs=EPSG:32610&field=side:string&field=fault_parallel:double"
        "&field=sigma_fp:double&field=status:string",
        "tiles",
        "memory",
    )
    root = QgsRuleBasedRenderer.Rule(None)
    for label, expr, props in (
        (
            "left side",
            "\"status\" = 'ok' AND \"side\" = 'left'",
            {"color": "103,169,207,90", "outline_color": "#2166ac", "outline_width": "0.4"},
        ),
        (
            "right side",
            "\"status\" = 'ok' AND \"side\" = 'right'",
            {"color": "239,138,98,90", "outline_color": "#b2182b", "outline_width": "0.4"},
        ),
        (
            "skipped",
            "ELSE",
            {
                "style": "no",
                "outline_color": "#8a8a8a",
                "outline_style": "dash",
                "outline_width": "0.3",
            },
        ),
    ):
        rule = QgsRuleBasedRenderer.Rule(QgsFillSymbol.createSimple(props), 0, 0, "", label)
        if expr == "ELSE":
            rule.setIsElse(True)
        else:
            rule.setFilterExpression(expr)
        root.appendChild(rule)
    layer.setRenderer(QgsRuleBasedRenderer(root))
    _labels(layer)
    return layer


def strips_layer():
    from qgis.core import (
        QgsCategorizedSymbolRenderer,
        QgsMarkerSymbol,
        QgsProperty,
        QgsRendererCategory,
        QgsSymbolLayer,
        QgsVectorLayer,
    )
    from qgis.PyQt.QtCore import QPointF

    layer = QgsVectorLayer(
        "Point?crs=EPSG:32610&field=side:string&field=fault_parallel:double"
        "&field=sigma_fp:double&field=status:string",
        "strips",
        "memory",
    )
    size = (
        'coalesce(scale_linear(abs("fault_parallel"), 0, '
        'maximum(abs("fault_parallel")), 2, 6), 1.5)'
    )
    cats = []
    for value, shape, colour in (("left", "circle", "#2166ac"), ("right", "square", "#b2182b")):
        sym = QgsMarkerSymbol.createSimple(
            {"name": shape, "color": colour, "outline_color": "#202020", "outline_width": "0.2"}
        )
        sym.symbolLayer(0).setDataDefinedProperty(
            QgsSymbolLayer.PropertySize, QgsProperty.fromExpression(size)
        )
        # both sides' strips sit at the same chainage on the trace: draw them side by side
        sym.symbolLayer(0).setOffset(QPointF(-2.0 if value == "left" else 2.0, 0.0))
        cats.append(QgsRendererCategory(value, sym, f"{value} side"))
    layer.setRenderer(QgsCategorizedSymbolRenderer("side", cats))
    # left-side labels above the point, right-side below (both sit on the trace)
    _labels(layer, "if(\"side\" = 'left', '0,-4', '0,4')")
    return layer


def main():
    app = _app()
    STYLES.mkdir(parents=True, exist_ok=True)
    _save(tiles_layer(), "slip_tiles", STYLES)
    _save(strips_layer(), "slip_strips", STYLES)
    app.exitQgis()
    return 0


if __name__ == "__main__":
    sys.exit(main())
