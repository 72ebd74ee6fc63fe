"""Write the QML style templates of SlipMap's outputs with PyQGIS (the displacement fields'
here, the fault slip's in make_slip_styles.py).

Run from the repository root with QGIS's Python (headless is fine)::

    QT_QPA_PLATFORM=offscreen .venv/bin/python scripts/make_styles.py
    QT_QPA_PLATFORM=offscreen .venv/bin/python scripts/make_slip_styles.py

and commit the files they write to ``styles/``. The files are *templates*: the numbers that
depend on the data (the class limits of a diverging legend, the arrow scale, the sigma above
which a cell counts as uncertain) are tokens ``{slipmap.NAME}`` that
:func:`slipmap.app.styles.fit_style` replaces when SlipMap writes an output (the GeoPackage's
``layer_styles`` row, the ``.qml`` beside a GeoTIFF) or QGIS loads one; the raster ramps are
stored on [-1, 1] and rescaled to ``[-max|v|, max|v|]`` the same way (white stays at 0).

* ``piv_vectors.qml`` -- arrows (points) rotated by ``azimuth_deg`` (clockwise from north),
  ``{slipmap.arrow_mm_per_m}`` page millimetres long per metre of horizontal motion (a legend
  entry shows the arrow of a round length), filled by dz in classes (purple down, orange up,
  white 0); grey where ``valid = 0``.
* ``icp_vectors.qml`` (points, QGIS's sinks) and ``icp_vectors_lines.qml`` (the GeoPackage's
  lines from the cell centre): the same arrows, black; faded where the cell is uncertain
  (horizontal sigma above ``{slipmap.sigma_flag}``).
* ``icp_cells.qml`` -- cells filled by dz in classes (semi-transparent), hatched where
  uncertain, labelled with the horizontal motion and its sigma (``12.3 ± 2.1 mm``) below the
  centre, only where a cell is at least 12 mm wide on the page.
* ``diverging.qml`` / ``vertical.qml`` / ``strain.qml`` -- single-band pseudocolor rasters
  (RdBu, PuOr, PRGn) symmetric about 0, stored on [-1, 1].
"""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path

STYLES = Path(__file__).resolve().parents[1] / "styles"

#: ColorBrewer, 7 classes, negative first: RdBu reversed (blue -, red +), PuOr reversed
#: (purple - = down, orange + = up), PRGn
RDBU = ("#2166ac", "#67a9cf", "#d1e5f0", "#f7f7f7", "#fddbc7", "#ef8a62", "#b2182b")
PUOR = ("#542788", "#998ec3", "#d8daeb", "#f7f7f7", "#fee0b6", "#f1a340", "#b35806")
PRGN = ("#762a83", "#af8dc3", "#e7d4e8", "#f7f7f7", "#d9f0d3", "#7fbf7b", "#1b7837")
N_CLASSES = len(RDBU)

#: size (page mm) of an arrow: its horizontal motion times the scale SlipMap writes in
ARROW_SIZE = 'min(coalesce("magnitude", 0) * {slipmap.arrow_mm_per_m}, 25)'
ARROW_ANGLE = 'coalesce("azimuth_deg", 0)'
#: the horizontal 1-sigma of a cell (m) and whether it is flagged as uncertain
SIGMA_H = 'sqrt(coalesce("sigma_dx", 0)^2 + coalesce("sigma_dy", 0)^2)'
UNCERTAIN = f"{SIGMA_H} > {{slipmap.sigma_flag}}"


def token(name, i=None):
    """The template token ``{slipmap.NAME}`` (``{slipmap.NAMEi}`` for class ``i``)."""
    return "{slipmap." + name + ("" if i is None else str(i)) + "}"


def _app():
    os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
    os.environ.setdefault("QT_HASH_SEED", "0")  # stable XML attribute order: small diffs
    from qgis.core import QgsApplication

    app = QgsApplication([], False)
    app.initQgis()
    return app


# ----------------------------------------------------------------------------- building blocks


def rule(parent, label, expression=None, symbol=None, *, description=""):
    """Append a rule (``expression`` None: no filter) to ``parent``; returns it."""
    from qgis.core import QgsRuleBasedRenderer

    r = QgsRuleBasedRenderer.Rule(symbol, 0, 0, expression or "", label, description)
    parent.appendChild(r)
    return r


def class_rules(parent, column, colours, make_symbol, *, extra=""):
    """One rule per class of ``column`` (limits ``{slipmap.loI}``..``{slipmap.hiI}``, the
    last class closed), symbol ``make_symbol(colour)``, legend label ``{slipmap.labelI}``."""
    n = len(colours)
    for i, colour in enumerate(colours):
        upper = "<=" if i == n - 1 else "<"
        expr = f'"{column}" >= {token("lo", i)} AND "{column}" {upper} {token("hi", i)}'
        if extra:
            expr = f"({extra}) AND {expr}"
        rule(parent, token("label", i), expr, make_symbol(colour), description=f"class {i}")


def text_format(size=7.5, colour="#202020", italic=False):
    from qgis.core import QgsTextBufferSettings, QgsTextFormat
    from qgis.PyQt.QtGui import QColor, QFont

    fmt = QgsTextFormat()
    font = QFont("DejaVu Sans")
    font.setItalic(italic)
    fmt.setFont(font)
    fmt.setSize(size)
    fmt.setColor(QColor(colour))
    buf = QgsTextBufferSettings()
    buf.setEnabled(True)
    buf.setSize(0.8)
    buf.setColor(QColor(255, 255, 255, 220))
    fmt.setBuffer(buf)
    return fmt


def labels(layer, expression, *, properties=None, placement=None, size=7.5, priority=5):
    """Expression labels (``properties``: {QgsPalLayerSettings property: expression})."""
    from qgis.core import QgsPalLayerSettings, QgsProperty, QgsVectorLayerSimpleLabeling

    pal = QgsPalLayerSettings()
    pal.isExpression = True
    pal.fieldName = expression
    pal.placement = QgsPalLayerSettings.OverPoint if placement is None else placement
    pal.setFormat(text_format(size))
    pal.priority = priority
    pal.displayAll = False  # labels never overlap: the lower priority one is left out
    pal.autoWrapLength = 18  # "R skipped: no planes (...)" on a few short lines
    if properties:
        props = pal.dataDefinedProperties()
        for key, expr in properties.items():
            props.setProperty(key, QgsProperty.fromExpression(expr))
        pal.setDataDefinedProperties(props)
    layer.setLabeling(QgsVectorLayerSimpleLabeling(pal))
    layer.setLabelsEnabled(True)


def arrow_marker(fill, *, outline="#202020", size_expression=ARROW_SIZE, size=8.0, angle=None):
    """An arrow marker pointing along ``azimuth_deg`` (or the fixed ``angle``), its length
    ``size_expression`` (None: the fixed ``size``, page mm)."""
    from qgis.core import (
        QgsMarkerSymbol,
        QgsProperty,
        QgsSimpleMarkerSymbolLayer,
        QgsSimpleMarkerSymbolLayerBase,
        QgsSymbolLayer,
    )
    from qgis.PyQt.QtGui import QColor

    arrow = QgsSimpleMarkerSymbolLayer(QgsSimpleMarkerSymbolLayerBase.Arrow, size)
    arrow.setColor(QColor(fill))
    arrow.setStrokeColor(QColor(outline))
    arrow.setStrokeWidth(0.15)
    if angle is None:
        arrow.setDataDefinedProperty(
            QgsSymbolLayer.PropertyAngle, QgsProperty.fromExpression(ARROW_ANGLE)
        )
    else:
        arrow.setAngle(angle)
    if size_expression:
        arrow.setDataDefinedProperty(
            QgsSymbolLayer.PropertySize, QgsProperty.fromExpression(size_expression)
        )
    symbol = QgsMarkerSymbol()
    symbol.changeSymbolLayer(0, arrow)
    return symbol


def arrow_line(fill, **kw):
    """:func:`arrow_marker` drawn at the first vertex of a line (the GeoPackage's vectors run
    from the cell centre)."""
    from qgis.core import QgsLineSymbol, QgsMarkerLineSymbolLayer, QgsTemplatedLineSymbolLayerBase

    line = QgsMarkerLineSymbolLayer(False)
    line.setPlacement(QgsTemplatedLineSymbolLayerBase.FirstVertex)
    line.setSubSymbol(arrow_marker(fill, **kw))
    symbol = QgsLineSymbol()
    symbol.changeSymbolLayer(0, line)
    return symbol


def fill(colour, alpha=255, *, outline="#606060", width=0.2, style="solid", line="solid"):
    from qgis.core import QgsFillSymbol
    from qgis.PyQt.QtGui import QColor

    c = QColor(colour)
    return QgsFillSymbol.createSimple(
        {
            "color": f"{c.red()},{c.green()},{c.blue()},{alpha}",
            "style": style,
            "outline_color": outline,
            "outline_width": str(width),
            "outline_style": line,
        }
    )


def hatch(colour="#505050", *, outline=None, angle=45.0, spacing=1.6, width=0.25):
    """A line-pattern fill (hatching) with an optional dashed outline."""
    from qgis.core import QgsFillSymbol, QgsLinePatternFillSymbolLayer, QgsSimpleFillSymbolLayer
    from qgis.PyQt.QtGui import QColor

    pattern = QgsLinePatternFillSymbolLayer()
    pattern.setLineAngle(angle)
    pattern.setDistance(spacing)
    pattern.setLineWidth(width)
    pattern.setColor(QColor(colour))
    symbol = QgsFillSymbol()
    symbol.changeSymbolLayer(0, pattern)
    if outline:
        border = QgsSimpleFillSymbolLayer.create(
            {
                "style": "no",
                "outline_color": outline,
                "outline_style": "dash",
                "outline_width": "0.3",
            }
        )
        symbol.appendSymbolLayer(border)
    return symbol


def rule_renderer(layer, root):
    from qgis.core import QgsRuleBasedRenderer

    layer.setRenderer(QgsRuleBasedRenderer(root))


def memory_layer(geometry, fields, name):
    from qgis.core import QgsVectorLayer

    spec = "&".join(f"field={f}" for f in fields)
    layer = QgsVectorLayer(f"{geometry}?crs=EPSG:32612&{spec}", name, "memory")
    assert layer.isValid(), spec
    return layer


def root_rule():
    from qgis.core import QgsRuleBasedRenderer

    return QgsRuleBasedRenderer.Rule(None)


# ----------------------------------------------------------------------------- field styles

_VECTOR_FIELDS = (
    "dx:double",
    "dy:double",
    "dz:double",
    "sigma_dx:double",
    "sigma_dy:double",
    "sigma_dz:double",
    "magnitude:double",
    "azimuth_deg:double",
    "valid:integer",
)


def piv_vectors():
    layer = memory_layer("Point", _VECTOR_FIELDS, "vectors")
    root = root_rule()
    group = rule(root, "arrow colour: dz (mm)", '"valid" = 1 AND "dz" IS NOT NULL')
    class_rules(group, "dz", PUOR, lambda c: arrow_marker(c))
    rule(root, "no dz", '"valid" = 1 AND "dz" IS NULL', arrow_marker("#404040"))
    rule(
        root,
        "missing or replaced (valid = 0)",
        '"valid" = 0',
        arrow_marker("#c8c8c8", outline="#909090"),
    )
    rule(
        root,
        token("arrow_label"),
        "FALSE",
        arrow_marker("#ffffff", size_expression=None, angle=90.0),
    )
    rule_renderer(layer, root)
    return layer


def _icp_arrows(make):
    root = root_rule()
    certain = f'"magnitude" IS NOT NULL AND NOT ({UNCERTAIN})'
    rule(root, "horizontal motion (label: value ± σ)", certain, make("#1a1a1a"))
    rule(
        root,
        "uncertain: " + token("sigma_label"),
        f'"magnitude" IS NOT NULL AND {UNCERTAIN}',
        make("#d0d0d0", outline="#a0a0a0"),
    )
    rule(root, token("arrow_label"), "FALSE", make("#1a1a1a", size_expression=None, angle=90.0))
    return root


def icp_vectors():
    layer = memory_layer("Point", _VECTOR_FIELDS, "vectors")
    rule_renderer(layer, _icp_arrows(arrow_marker))
    return layer


def icp_vectors_lines():
    layer = memory_layer("LineString", _VECTOR_FIELDS, "vectors")
    rule_renderer(layer, _icp_arrows(arrow_line))
    return layer


#: a cell's horizontal motion and its sigma along it, mm ("12.3 ± 2.1 mm")
def _mm(expr):
    return f"format_number({expr} * 1000, if(abs({expr}) < 0.01, 1, 0))"


SIGMA_ALONG = (
    'CASE WHEN "magnitude" > 0 THEN sqrt(("dx" * "sigma_dx")^2 + ("dy" * "sigma_dy")^2) '
    f'/ "magnitude" ELSE {SIGMA_H} END'
)
CELL_LABEL = (
    f'CASE WHEN "magnitude" IS NOT NULL THEN {_mm(chr(34) + "magnitude" + chr(34))} '
    f"|| ' ± ' || {_mm('(' + SIGMA_ALONG + ')')} || ' mm' END"
)


def icp_cells():
    from qgis.core import QgsPalLayerSettings

    layer = memory_layer("Polygon", _VECTOR_FIELDS, "cells")
    root = root_rule()
    group = rule(root, "cell colour: vertical motion dz (mm)", '"dz" IS NOT NULL')
    class_rules(group, "dz", PUOR, lambda c: fill(c, 150, outline="#8a8a8a", width=0.15))
    rule(root, "not fitted", '"dz" IS NULL', fill("#ffffff", 0, outline="#9a9a9a", line="dot"))
    rule(root, "uncertain: " + token("sigma_label"), UNCERTAIN, hatch("#6a6a6a"))
    rule_renderer(layer, root)
    labels(
        layer,
        CELL_LABEL,
        properties={
            # along the cell's bottom edge (offset in map units: at every scale), clear of
            # the arrow drawn about the centre (at most the legend arrow's length each way)
            QgsPalLayerSettings.OffsetQuad: "1",
            QgsPalLayerSettings.OffsetXY: "'0,' || to_string(0.46 * bounds_height($geometry))",
            QgsPalLayerSettings.OffsetUnits: "'MapUnit'",
            # only where a cell is at least 12 mm wide on the page (1 m cells at 1:80)
            QgsPalLayerSettings.Show: "bounds_width($geometry) * 1000 / @map_scale >= 12",
        },
        size=7,
        priority=3,
    )
    return layer


def fault_trace():
    from qgis.core import QgsLineSymbol, QgsSingleSymbolRenderer

    layer = memory_layer("LineString", ("part:integer",), "fault_trace")
    symbol = QgsLineSymbol.createSimple(
        {"line_color": "#1a1a1a", "line_width": "0.8", "capstyle": "round"}
    )
    layer.setRenderer(QgsSingleSymbolRenderer(symbol))
    return layer


def raster_layer(tmp, colours, label):
    """A single-band pseudocolor raster style, ramp on [-1, 1], white at 0, 80 % opacity."""
    import numpy as np
    from osgeo import gdal, osr
    from qgis.core import (
        QgsColorRampShader,
        QgsRasterLayer,
        QgsRasterMinMaxOrigin,
        QgsRasterShader,
        QgsSingleBandPseudoColorRenderer,
    )
    from qgis.PyQt.QtGui import QColor

    path = str(Path(tmp) / f"{label}.tif")
    ds = gdal.GetDriverByName("GTiff").Create(path, 4, 4, 1, gdal.GDT_Float64)
    ds.SetGeoTransform((500000.0, 1.0, 0.0, 4200000.0, 0.0, -1.0))
    srs = osr.SpatialReference()
    srs.ImportFromEPSG(32612)
    ds.SetProjection(srs.ExportToWkt())
    ds.GetRasterBand(1).WriteArray(np.linspace(-1, 1, 16).reshape(4, 4))
    ds.GetRasterBand(1).SetNoDataValue(float("nan"))
    ds = None
    layer = QgsRasterLayer(path, label)
    assert layer.isValid(), path
    values = np.linspace(-1.0, 1.0, len(colours))
    items = [
        QgsColorRampShader.ColorRampItem(float(v), QColor(c), f"{v:+.2f}")
        for v, c in zip(values, colours)
    ]
    ramp = QgsColorRampShader(-1.0, 1.0)
    ramp.setColorRampType(QgsColorRampShader.Interpolated)
    ramp.setColorRampItemList(items)
    ramp.setClip(False)
    shader = QgsRasterShader(-1.0, 1.0)
    shader.setRasterShaderFunction(ramp)
    renderer = QgsSingleBandPseudoColorRenderer(layer.dataProvider(), 1, shader)
    renderer.setClassificationMin(-1.0)
    renderer.setClassificationMax(1.0)
    renderer.setOpacity(0.8)
    origin = QgsRasterMinMaxOrigin()
    origin.setLimits(QgsRasterMinMaxOrigin.None_)
    renderer.setMinMaxOrigin(origin)
    layer.setRenderer(renderer)
    return layer


def save(layer, name, styles=STYLES):
    out = Path(styles) / f"{name}.qml"
    message, ok = layer.saveNamedStyle(str(out))
    if not ok:
        raise RuntimeError(f"{out}: {message}")
    sys.stdout.write(f"wrote {out}\n")


def main() -> int:
    app = _app()
    STYLES.mkdir(parents=True, exist_ok=True)
    save(piv_vectors(), "piv_vectors")
    save(icp_vectors(), "icp_vectors")
    save(icp_vectors_lines(), "icp_vectors_lines")
    save(icp_cells(), "icp_cells")
    save(fault_trace(), "fault_trace")
    with tempfile.TemporaryDirectory() as tmp:
        save(raster_layer(tmp, RDBU, "diverging"), "diverging")
        save(raster_layer(tmp, PUOR, "vertical"), "vertical")
        save(raster_layer(tmp, PRGN, "strain"), "strain")
        save(raster_layer(tmp, RDBU, "slip_windows"), "slip_windows")
    app.exitQgis()
    return 0


if __name__ == "__main__":
    sys.exit(main())
