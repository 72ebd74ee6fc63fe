"""Write the QML styles of the displacement-field outputs with PyQGIS.

Run from the repository root with QGIS's Python (headless is fine)::

    QT_QPA_PLATFORM=offscreen .venv/bin/python scripts/make_styles.py

and commit the files it writes to ``styles/``:

* ``piv_vectors.qml`` -- points drawn as arrows rotated by ``azimuth_deg`` (clockwise from
  north, QGIS's marker rotation convention) and sized by ``magnitude`` relative to the layer's
  largest magnitude; blue where ``valid = 1``, grey otherwise (missing or replaced outliers).
* ``icp_vectors.qml`` -- the same arrows, dark red, for the windowed-ICP cell centres.
* ``icp_cells.qml`` -- cell outlines labelled with the horizontal 1-sigma
  ``sqrt(sigma_dx^2 + sigma_dy^2)`` in millimetres.
* ``diverging.qml`` / ``strain.qml`` -- single-band (band 1) pseudocolor rasters with a
  diverging ramp symmetric about 0 (white at 0, blue/purple negative, red/green positive)
  stored on [-1, 1]; the algorithms rescale it to the layer's own ``[-max|v|, max|v|]`` when
  they load it. ``diverging`` also styles slipmap:displacement's moving-window raster.
"""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path

STYLES = Path(__file__).resolve().parents[1] / "styles"

#: ColorBrewer RdBu (reversed: blue negative) and PRGn, 7 classes
RDBU = ("#2166ac", "#67a9cf", "#d1e5f0", "#f7f7f7", "#fddbc7", "#ef8a62", "#b2182b")
PRGN = ("#762a83", "#af8dc3", "#e7d4e8", "#f7f7f7", "#d9f0d3", "#7fbf7b", "#1b7837")

ARROW_SIZE = 'coalesce(scale_linear("magnitude", 0, maximum("magnitude"), 1.5, 9), 0)'


def _app():
    os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
    os.environ.setdefault("QT_HASH_SEED", "0")  # stable XML attribute order: small diffs
    from qgis.core import QgsApplication

    app = QgsApplication([], False)
    app.initQgis()
    return app


def _arrow_layer(colour_expression):
    from qgis.core import (
        QgsMarkerSymbol,
        QgsProperty,
        QgsSimpleMarkerSymbolLayer,
        QgsSimpleMarkerSymbolLayerBase,
        QgsSingleSymbolRenderer,
        QgsSymbolLayer,
        QgsVectorLayer,
    )

    layer = QgsVectorLayer(
        "Point?crs=EPSG:32612&field=magnitude:double&field=azimuth_deg:double&field=valid:integer",
        "vectors",
        "memory",
    )
    arrow = QgsSimpleMarkerSymbolLayer(QgsSimpleMarkerSymbolLayerBase.Arrow, 4.0)
    arrow.setStrokeWidth(0.1)
    arrow.setDataDefinedProperty(
        QgsSymbolLayer.PropertyAngle, QgsProperty.fromExpression('coalesce("azimuth_deg", 0)')
    )
    arrow.setDataDefinedProperty(
        QgsSymbolLayer.PropertySize, QgsProperty.fromExpression(ARROW_SIZE)
    )
    arrow.setDataDefinedProperty(
        QgsSymbolLayer.PropertyFillColor, QgsProperty.fromExpression(colour_expression)
    )
    arrow.setDataDefinedProperty(
        QgsSymbolLayer.PropertyStrokeColor, QgsProperty.fromExpression(colour_expression)
    )
    symbol = QgsMarkerSymbol()
    symbol.changeSymbolLayer(0, arrow)
    layer.setRenderer(QgsSingleSymbolRenderer(symbol))
    return layer


def _cells_layer():
    from qgis.core import (
        QgsFillSymbol,
        QgsPalLayerSettings,
        QgsSingleSymbolRenderer,
        QgsTextBufferSettings,
        QgsTextFormat,
        QgsVectorLayer,
        QgsVectorLayerSimpleLabeling,
    )
    from qgis.PyQt.QtGui import QColor

    layer = QgsVectorLayer(
        "Polygon?crs=EPSG:32612&field=sigma_dx:double&field=sigma_dy:double",
        "cells",
        "memory",
    )
    symbol = QgsFillSymbol.createSimple(
        {"style": "no", "outline_color": "#404040", "outline_width": "0.3"}
    )
    layer.setRenderer(QgsSingleSymbolRenderer(symbol))
    pal = QgsPalLayerSettings()
    pal.isExpression = True
    pal.fieldName = "'±' || round(sqrt(\"sigma_dx\"^2 + \"sigma_dy\"^2) * 1000, 1) || ' mm'"
    pal.placement = QgsPalLayerSettings.OverPoint
    fmt = QgsTextFormat()
    fmt.setSize(7)
    fmt.setColor(QColor("#202020"))
    buf = QgsTextBufferSettings()
    buf.setEnabled(True)
    buf.setSize(0.7)
    buf.setColor(QColor("white"))
    fmt.setBuffer(buf)
    pal.setFormat(fmt)
    layer.setLabeling(QgsVectorLayerSimpleLabeling(pal))
    layer.setLabelsEnabled(True)
    return layer


def _raster_layer(tmp, colours, label):
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
    n = len(colours)
    values = np.linspace(-1.0, 1.0, n)
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
    origin = QgsRasterMinMaxOrigin()
    origin.setLimits(QgsRasterMinMaxOrigin.None_)
    renderer.setMinMaxOrigin(origin)
    layer.setRenderer(renderer)
    return layer


def _save(layer, name, styles=STYLES):
    out = Path(styles) / f"{name}.qml"
    message, ok = layer.saveNamedStyle(str(out))
    if not ok:
        raise RuntimeError(f"{out}: {message}")
    sys.stdout.write(f"wrote {out}\n")


def main() -> int:
    app = _app()
    STYLES.mkdir(parents=True, exist_ok=True)
    _save(_arrow_layer("if(\"valid\" = 1, '#1f4e9c', '#9a9a9a')"), "piv_vectors")
    _save(_arrow_layer("'#a01818'"), "icp_vectors")
    _save(_cells_layer(), "icp_cells")
    with tempfile.TemporaryDirectory() as tmp:
        _save(_raster_layer(tmp, RDBU, "diverging"), "diverging")
        _save(_raster_layer(tmp, PRGN, "strain"), "strain")
    app.exitQgis()
    return 0


if __name__ == "__main__":
    sys.exit(main())
