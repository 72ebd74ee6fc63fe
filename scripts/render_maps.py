"""Render SlipMap's output files as QGIS draws them when they are dragged in: each file
opened fresh (its default style: a GeoPackage's ``layer_styles`` row, a GeoTIFF's ``.qml``),
drawn headless with a legend, saved as a PNG (the maps in docs/qgis.md).

    QT_QPA_PLATFORM=offscreen .venv/bin/python scripts/render_maps.py OUT.png \\
        "displacement.gpkg|layername=strips" "displacement.gpkg|layername=tiles" windows.tif \\
        [--title TEXT] [--extent-of N] [--scale S]

Layers are listed top first. ``--extent-of N`` zooms to the N-th layer (default: all);
``--scale`` sets the map scale denominator instead.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path


def _layer(spec):
    from qgis.core import QgsRasterLayer, QgsVectorLayer

    path = spec.split("|")[0]
    name = spec.split("layername=")[-1] if "layername=" in spec else Path(path).stem
    if path.lower().endswith((".tif", ".tiff")):
        layer = QgsRasterLayer(path, name)
    else:
        layer = QgsVectorLayer(spec, name, "ogr")
    if not layer.isValid():
        raise SystemExit(f"cannot open {spec}")
    return layer


def render(out, specs, *, title="", extent_of=None, scale=None, crs=None, size_mm=(300, 225)):
    from qgis.core import (
        QgsLayoutExporter,
        QgsLayoutItemLabel,
        QgsLayoutItemLegend,
        QgsLayoutItemMap,
        QgsLayoutItemScaleBar,
        QgsLayoutPoint,
        QgsLayoutSize,
        QgsLegendStyle,
        QgsPrintLayout,
        QgsProject,
        QgsRectangle,
        QgsUnitTypes,
    )
    from qgis.PyQt.QtGui import QFont

    project = QgsProject.instance()
    project.removeAllMapLayers()
    layers = [_layer(s) for s in specs]
    if crs:  # outputs of clouds without a usable CRS (lone-star declares WGS 84 wrongly)
        from qgis.core import QgsCoordinateReferenceSystem

        for layer in layers:
            layer.setCrs(QgsCoordinateReferenceSystem(crs))
    for layer in reversed(layers):
        project.addMapLayer(layer)
    project.setCrs(layers[0].crs())
    layout = QgsPrintLayout(project)
    layout.initializeDefaults()
    page = layout.pageCollection().page(0)
    page.setPageSize(QgsLayoutSize(*size_mm, QgsUnitTypes.LayoutMillimeters))
    map_w, map_h = size_mm[0] * 0.56, size_mm[1] - 22
    item = QgsLayoutItemMap(layout)
    item.attemptResize(QgsLayoutSize(map_w, map_h, QgsUnitTypes.LayoutMillimeters))
    item.setLayers(layers)
    if extent_of is not None:
        extent = QgsRectangle(layers[extent_of].extent())
    else:
        extent = QgsRectangle(layers[0].extent())
        for layer in layers[1:]:
            extent.combineExtentWith(layer.extent())
    extent.scale(1.06)
    item.setFrameEnabled(True)
    layout.addLayoutItem(item)
    item.setCrs(layers[0].crs())
    item.zoomToExtent(extent)
    if scale:
        item.setScale(scale)
    item.attemptMove(QgsLayoutPoint(5, 15, QgsUnitTypes.LayoutMillimeters))  # after the zoom
    legend = QgsLayoutItemLegend(layout)
    legend.setLinkedMap(item)
    legend.setTitle("Legend")
    legend.setAutoUpdateModel(False)
    legend.setWrapString("\n")
    for part, size in (
        (QgsLegendStyle.Title, 10),
        (QgsLegendStyle.Group, 9),
        (QgsLegendStyle.Subgroup, 9),
        (QgsLegendStyle.SymbolLabel, 8),
    ):
        legend.setStyleFont(part, QFont("DejaVu Sans", size))
    legend.setSymbolHeight(3.2)
    root = legend.model().rootGroup()
    seen = set()
    for node in list(root.findLayers()):  # one legend per style (planes_left / _right)
        key = node.layer().name().split("_")[0]
        if key in seen:
            root.removeChildNode(node)
        seen.add(key)
    legend.attemptMove(QgsLayoutPoint(map_w + 9, 13, QgsUnitTypes.LayoutMillimeters))
    layout.addLayoutItem(legend)
    label = QgsLayoutItemLabel(layout)
    label.setText(title)
    label.setFont(QFont("DejaVu Sans", 12))
    label.attemptMove(QgsLayoutPoint(5, 3, QgsUnitTypes.LayoutMillimeters))
    label.attemptResize(QgsLayoutSize(size_mm[0] - 10, 10, QgsUnitTypes.LayoutMillimeters))
    layout.addLayoutItem(label)
    bar = QgsLayoutItemScaleBar(layout)
    bar.setStyle("Single Box")
    bar.setLinkedMap(item)
    bar.applyDefaultSize()
    bar.attemptMove(QgsLayoutPoint(8, 15 + map_h - 12, QgsUnitTypes.LayoutMillimeters))
    layout.addLayoutItem(bar)
    settings = QgsLayoutExporter.ImageExportSettings()
    settings.dpi = 110
    result = QgsLayoutExporter(layout).exportToImage(str(out), settings)
    if result != QgsLayoutExporter.Success:
        raise SystemExit(f"export failed ({result})")
    sys.stdout.write(f"wrote {out} (scale 1:{item.scale():.0f})\n")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("out")
    parser.add_argument("layers", nargs="+")
    parser.add_argument("--title", default="")
    parser.add_argument("--extent-of", type=int)
    parser.add_argument("--scale", type=float)
    parser.add_argument("--crs", help="CRS of layers that have none (e.g. EPSG:32612)")
    args = parser.parse_args(argv)
    os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
    from qgis.core import QgsApplication

    app = QgsApplication([], False)
    app.initQgis()
    render(
        args.out,
        args.layers,
        title=args.title,
        extent_of=args.extent_of,
        scale=args.scale,
        crs=args.crs,
    )
    app.exitQgis()
    return 0


if __name__ == "__main__":
    sys.exit(main())
