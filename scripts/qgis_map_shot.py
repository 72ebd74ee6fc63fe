"""Screenshot of the Fault slip outputs in the QGIS desktop (docs/img/qgis_slip_outputs.png).

Run inside the desktop, e.g. under Xvfb with the plugin enabled in a throw-away profile (as
tests/qgis/test_gui_smoke.py starts it)::

    SLIPMAP_SHOT=docs/img/qgis_slip_outputs.png SLIPMAP_DEMO=demo_output \\
      xvfb-run -a -s "-screen 0 1400x1000x24" qgis.bin --profiles-path PROFILES \\
      --nologo --noversioncheck --code scripts/qgis_map_shot.py

It runs ``slipmap:displacement`` on the demo's epochs (``make demo``) with tiles, strips and
moving windows, loads the outputs as an analyst's "Open output file after running" does, and
saves the map canvas.
"""

import os

from qgis.core import QgsProject, QgsRectangle, QgsVectorLayer
from qgis.PyQt.QtCore import QTimer
from qgis.utils import iface

OUT = os.environ["SLIPMAP_SHOT"]
DEMO = os.environ.get("SLIPMAP_DEMO", "demo_output")


def _run():
    from qgis import processing

    fault = QgsVectorLayer(os.path.join(DEMO, "demo_fault.geojson"), "Fault trace", "ogr")
    QgsProject.instance().addMapLayer(fault)
    processing.runAndLoadResults(
        "slipmap:displacement",
        {
            "BEFORE": os.path.join(DEMO, "demo_before.laz"),
            "AFTER": os.path.join(DEMO, "demo_after.laz"),
            "FAULT": fault,
            "TILE_SIZE": 25.0,
            "STRIP_WIDTH": 25.0,
            "WINDOW_SIZE": 30.0,
            "WINDOW_STEP": 15.0,
            "SUMMARY": "TEMPORARY_OUTPUT",
            "PLANES": "TEMPORARY_OUTPUT",
            "TILES": "TEMPORARY_OUTPUT",
            "STRIPS": "TEMPORARY_OUTPUT",
            "WINDOWS": "TEMPORARY_OUTPUT",
        },
    )

    def shot():
        canvas = iface.mapCanvas()
        extent = QgsRectangle()
        for layer in QgsProject.instance().mapLayers().values():
            if layer.name().startswith("Tiles"):
                extent.combineExtentWith(layer.extent())
        canvas.setExtent(extent.buffered(5.0))
        canvas.refreshAllLayers()
        QTimer.singleShot(4000, save)

    def save():
        iface.layerTreeView().collapseAllNodes()
        root = QgsProject.instance().layerTreeRoot()
        for layer in QgsProject.instance().mapLayers().values():
            if layer.name().startswith("Tiles"):
                root.findLayer(layer.id()).setExpanded(True)  # its legend: classes in mm
        iface.mainWindow().grab().save(OUT)
        os._exit(0)

    QTimer.singleShot(3000, shot)


def _guarded():
    try:
        _run()
    except Exception:  # noqa: BLE001 - the picture's script reports and ends the desktop
        import traceback

        with open(OUT + ".error.txt", "w") as f:
            f.write(traceback.format_exc())
        os._exit(1)


QTimer.singleShot(3000, _guarded)
