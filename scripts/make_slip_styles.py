"""Write the QML style templates of the slipmap:displacement outputs (slip_tiles,
slip_strips, slip_planes; the moving-window raster's slip_windows and the fault trace's come
from make_styles.py) with PyQGIS. Run with QGIS's Python from the repository root:

    QT_QPA_PLATFORM=offscreen .venv/bin/python scripts/make_slip_styles.py

Sign convention (docs/methods.md): ``right_lateral`` + = right-lateral (dextral), red; - =
left-lateral, blue; white = 0. The class limits are tokens that SlipMap fills in from the
data (see make_styles.py).

* ``slip_tiles.qml`` -- adjusted tiles filled by their right-lateral motion in classes,
  semi-transparent (the planes and the windows raster below stay visible), labelled ``L +0.4
  ± 2.4 mm`` / ``R +17.8 ± 3.4 mm`` (side, value ± sigma); skipped tiles hatched grey with a
  dashed outline, labelled with their reason (the ``status``).
* ``slip_strips.qml`` -- each strip a point on the trace; the left side's drawn as a circle
  to the left of it and labelled ``L ...`` on the left, the right side's as a square to the
  right with ``R ...`` on the right, filled by the right-lateral class; skipped strips as grey
  crosses labelled with their reason.
* ``slip_planes.qml`` -- the matched planes by their weight in the adjustment.
"""

from __future__ import annotations

import sys
from pathlib import Path

# shared with the field styles (run as a script, this directory is on sys.path)
from make_styles import (
    RDBU,
    _app,
    class_rules,
    fill,
    hatch,
    labels,
    memory_layer,
    root_rule,
    rule,
    rule_renderer,
    save,
)

STYLES = Path(sys.argv[1] if len(sys.argv) > 1 else Path(__file__).resolve().parents[1] / "styles")

_FIELDS = (
    "side:string",
    "right_lateral:double",
    "sigma_right_lateral:double",
    "opening:double",
    "sigma_opening:double",
    "dz:double",
    "sigma_dz:double",
    "status:string",
)
OK = "\"status\" = 'ok'"
SKIPPED = '"status" IS NULL OR "status" <> \'ok\''


def signed_mm(expr):
    """``+17.8`` / ``-0.4``: ``expr`` (m) in mm with its sign, one decimal."""
    return f"CASE WHEN {expr} >= 0 THEN '+' ELSE '' END || format_number({expr} * 1000, 1)"


#: ``R +17.8 ± 3.4 mm`` (ok) or the reason it was skipped
LABEL = (
    f'CASE WHEN {OK} AND "right_lateral" IS NOT NULL THEN '
    "upper(left(\"side\", 1)) || ' ' || "
    + signed_mm('"right_lateral"')
    + " || ' ± ' || format_number(\"sigma_right_lateral\" * 1000, 1) || ' mm' "
    "ELSE upper(left(\"side\", 1)) || ' ' || coalesce(\"status\", 'skipped') END"
)
GROUP = "right-lateral motion (mm)"


def tiles_layer():
    layer = memory_layer("Polygon", _FIELDS, "tiles")
    root = root_rule()
    group = rule(root, GROUP, OK)
    class_rules(group, "right_lateral", RDBU, lambda c: fill(c, 120, outline="#505050", width=0.3))
    rule(root, "skipped (the label gives the reason)", SKIPPED, hatch("#9a9a9a", outline="#7a7a7a"))
    rule_renderer(layer, root)
    labels(layer, LABEL, size=7.5)
    return layer


def strips_layer():
    from qgis.core import QgsMarkerSymbol, QgsPalLayerSettings, QgsProperty, QgsSymbolLayer

    layer = memory_layer("Point", _FIELDS, "strips")
    side_shape = "if(\"side\" = 'left', 'circle', 'square')"
    side_offset = "if(\"side\" = 'left', '-2.2,0', '2.2,0')"

    def marker(colour, shape=None, size=3.6):
        sym = QgsMarkerSymbol.createSimple(
            {"name": "circle", "color": colour, "outline_color": "#202020", "outline_width": "0.25",
             "size": str(size)}
        )  # fmt: skip
        sl = sym.symbolLayer(0)
        sl.setDataDefinedProperty(
            QgsSymbolLayer.PropertyName, QgsProperty.fromExpression(shape or side_shape)
        )
        sl.setDataDefinedProperty(
            QgsSymbolLayer.PropertyOffset, QgsProperty.fromExpression(side_offset)
        )
        return sym

    root = root_rule()
    group = rule(root, GROUP, OK)
    class_rules(group, "right_lateral", RDBU, marker)
    rule(root, "skipped (the label gives the reason)", SKIPPED, marker("#b0b0b0", "'cross2'", 3.0))
    # legend entries for the two sides (never drawn: the classes above draw them)
    left = marker("#ffffff", "'circle'")
    rule(root, "left side (L): circle, left of the trace", "FALSE", left)
    right = marker("#ffffff", "'square'")
    rule(root, "right side (R): square, right of the trace", "FALSE", right)
    rule_renderer(layer, root)
    labels(
        layer,
        LABEL,
        properties={
            # left side's label to the left of its circle, right side's to the right
            QgsPalLayerSettings.OffsetQuad: "if(\"side\" = 'left', 3, 5)",
            QgsPalLayerSettings.OffsetXY: "if(\"side\" = 'left', '-4.2,0', '4.2,0')",
        },
        size=7.5,
    )
    return layer


def planes_layer():
    from qgis.core import QgsMarkerSymbol

    layer = memory_layer("Point", ("side:string", "weight:double"), "planes")

    def dot(colour, outline="#303030", name="circle", size=1.8):
        return QgsMarkerSymbol.createSimple(
            {"name": name, "color": colour, "outline_color": outline, "outline_width": "0.15",
             "size": str(size)}
        )  # fmt: skip

    root = root_rule()
    rule(root, "unused (white-noise model)", '"weight" IS NULL', dot("#bdbdbd"))
    rule(root, "full weight", '"weight" >= 1', dot("#252525"))
    rule(root, "down-weighted (weight below 1)", '"weight" > 0 AND "weight" < 1', dot("#fdae61"))
    rule(root, "rejected (weight 0)", '"weight" = 0', dot("#ffffff", "#d7191c", "cross2", 2.2))
    rule_renderer(layer, root)
    return layer


def main():
    app = _app()
    STYLES.mkdir(parents=True, exist_ok=True)
    save(tiles_layer(), "slip_tiles", STYLES)
    save(strips_layer(), "slip_strips", STYLES)
    save(planes_layer(), "slip_planes", STYLES)
    app.exitQgis()
    return 0


if __name__ == "__main__":
    sys.exit(main())
