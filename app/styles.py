"""The style of every output SlipMap writes, declared once, fitted to the output's data.

The QML templates live in :mod:`slipmap.styles` (written by ``scripts/make_styles.py`` and
``scripts/make_slip_styles.py``). A template's data-dependent numbers are tokens
``{slipmap.NAME}`` (class limits and labels, the arrow scale, the sigma above which a cell is
flagged); its raster ramp is stored on [-1, 1]. :func:`vector_qml` and :func:`raster_qml`
fill them in from the data: symmetric classes / ramp limits ``[-M, M]`` with M = max |value|
(white stays at 0, colours mean the same sign on every map), legend labels in mm
stating the sign convention (+ = right-lateral, + = up, + = east / north).

Every face stores the fitted style with the data, so an output opens styled wherever it is
opened: the job's GeoPackages carry it in their ``layer_styles`` table
(:func:`gpkg_styles`, passed to :func:`~slipmap.core.io.vector.write_gpkg_layers`), its
GeoTIFFs a ``.qml`` beside them (:func:`write_raster_style`, staged in the job's
:class:`~slipmap.app.outputs.OutputPlan`); the QGIS algorithms store the same text into the
GeoPackages QGIS writes for them and apply it on load.

Nothing here needs QGIS.
"""

from __future__ import annotations

import logging
import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from typing import Any, Dict, Mapping, Optional, Tuple
from xml.sax.saxutils import escape

import numpy as np

log = logging.getLogger("slipmap.app")

__all__ = [
    "OUTPUT_STYLES",
    "VECTOR_STYLES",
    "Classes",
    "RasterStyle",
    "VectorStyle",
    "gpkg_styles",
    "raster_qml",
    "vector_qml",
    "write_raster_style",
]

_DOCTYPE = "<!DOCTYPE qgis PUBLIC 'http://mrcc.com/qgis.dtd' 'SYSTEM'>\n"


@dataclass(frozen=True)
class Classes:
    """Diverging classes of one column (metres), symmetric about 0.

    Attributes
    ----------
    column : str
        The classed column.
    scale, unit : float, str
        Legend values are ``value * scale`` in ``unit`` (default mm).
    ends : (str, str)
        What the low (negative) and high (positive) end mean, appended to the end classes'
        labels as ``(- = ...)`` and ``(+ = ...)``.
    where : (str, value), optional
        Only the rows whose column ``where[0]`` equals ``where[1]`` set the range.
    """

    column: str
    scale: float = 1000.0
    unit: str = "mm"
    ends: Tuple[str, str] = ("", "")
    where: Optional[Tuple[str, Any]] = None


@dataclass(frozen=True)
class VectorStyle:
    """A vector layer's template ``styles/<name>.qml`` and what of it the data fills in:
    ``classes`` (tokens lo/hi/label), ``arrows`` (the arrow scale from ``magnitude``),
    ``sigma`` (the flag of uncertain cells from ``sigma_dx``, ``sigma_dy``)."""

    name: str
    classes: Optional[Classes] = None
    arrows: bool = False
    sigma: bool = False


@dataclass(frozen=True)
class RasterStyle:
    """A single-band pseudocolor template ``styles/<name>.qml`` on ``band`` (1-based), its
    ramp spread over ``[-max|v|, max|v|]`` (``sequential``: over ``[0, max|v|]``, for a
    quantity that is never negative, e.g. roughness), legend in ``value * scale`` ``unit``
    with the meaning of the low and high end (``ends``)."""

    name: str
    band: int = 1
    scale: float = 1000.0
    unit: str = "mm"
    ends: Tuple[str, str] = ("", "")
    sequential: bool = False


RIGHT_LATERAL = Classes(
    "right_lateral", ends=("left-lateral", "right-lateral"), where=("status", "ok")
)
DZ_UP = Classes("dz", ends=("down", "up"))

TILES = VectorStyle("slip_tiles", RIGHT_LATERAL)
STRIPS = VectorStyle("slip_strips", RIGHT_LATERAL)
PLANES = VectorStyle("slip_planes")
TRACE = VectorStyle("fault_trace")
BREAKLINES = VectorStyle("icp_breaklines")  # given or detected breaklines of the ICP field
ICP_CELLS = VectorStyle("icp_cells", DZ_UP, sigma=True)
ICP_VECTORS = VectorStyle("icp_vectors", arrows=True, sigma=True)  # points (QGIS's sinks)
ICP_VECTOR_LINES = VectorStyle("icp_vectors_lines", arrows=True, sigma=True)  # lines (gpkg)
PIV_VECTORS = VectorStyle(
    "piv_vectors", Classes("dz", ends=("down", "up"), where=("valid", 1)), arrows=True
)

#: the vector styles by template name (the QGIS algorithms name the style of each sink)
VECTOR_STYLES = {
    s.name: s
    for s in (
        TILES,
        STRIPS,
        PLANES,
        TRACE,
        BREAKLINES,
        ICP_CELLS,
        ICP_VECTORS,
        ICP_VECTOR_LINES,
        PIV_VECTORS,
    )
}

WINDOWS = RasterStyle("slip_windows", ends=("left-lateral", "right-lateral"))
DX = RasterStyle("diverging", ends=("west", "east"))
DY = RasterStyle("diverging", ends=("south", "north"))
DZ = RasterStyle("vertical", ends=("down", "up"))
STRAIN = RasterStyle("strain", scale=1.0, unit="", ends=("shortening", "extension"))
#: roughness (band 1, theta_ODR, m): viridis from 0 to the largest cell
ROUGHNESS = RasterStyle("roughness", ends=("smooth", "rough"), sequential=True)

#: the style of each output: ``{job: {output key: RasterStyle or {layer: VectorStyle}}}``
#: (the job's output keys of :class:`~slipmap.app.outputs.OutputPlan`)
OUTPUT_STYLES: Dict[str, Dict[str, Any]] = {
    "slip": {
        "layers": {
            "planes_left": PLANES,
            "planes_right": PLANES,
            "tiles": TILES,
            "strips": STRIPS,
            "fault_trace": TRACE,
        },
        "windows": WINDOWS,
        "windows_dx": DX,
        "windows_dy": DY,
    },
    "icp": {
        "layers": {"cells": ICP_CELLS, "vectors": ICP_VECTOR_LINES, "breaklines": BREAKLINES},
        "raster": RasterStyle("vertical", band=3, ends=("down", "up")),  # bands dx, dy, dz, ..
    },
    "piv": {"dx": DX, "dy": DY, "dz": DZ},
    "dem_diff": {"raster": DZ},
    "strain": {"raster": STRAIN},
    "roughness": {"geotiff": ROUGHNESS},
}


# --------------------------------------------------------------------------- fitting


def template(name: str) -> str:
    """The text of the bundled template ``styles/<name>.qml``."""
    from ..styles import style_path

    path = style_path(name)
    if path is None:
        raise KeyError(f"no bundled style {name!r}")  # programming error
    with open(path, encoding="utf-8") as f:
        return f.read()


def nice_down(value: float) -> float:
    """The largest 1, 2 or 5 times a power of ten not above ``value`` (> 0)."""
    if not (value > 0 and math.isfinite(value)):
        return 0.01
    e = 10.0 ** math.floor(math.log10(value))
    for k in (5.0, 2.0, 1.0):
        if k * e <= value * (1 + 1e-9):
            return k * e
    return e


def value_label(value: float, unit: str = "") -> str:
    """``+18.1 mm``: 3 significant digits with the sign (0 as ``0``)."""
    text = "0" if value == 0 else f"{value:+.3g}".replace("-", "\u2212")
    return f"{text} {unit}".strip()


def _finite(values) -> np.ndarray:
    a = np.asarray(values, dtype=np.float64).ravel() if values is not None else np.empty(0)
    return a[np.isfinite(a)]


def _column(columns: Mapping[str, Any], name: str) -> Optional[np.ndarray]:
    if name not in columns:
        return None
    try:
        return np.asarray(columns[name], dtype=np.float64)
    except (TypeError, ValueError):
        return None


def class_tokens(classes: Classes, columns: Mapping[str, Any], n: int) -> Dict[str, str]:
    """The tokens lo0..hi(n-1), label0.. of ``n`` equal classes over ``[-M, M]``."""
    values = _column(columns, classes.column)
    if values is not None and classes.where is not None and classes.where[0] in columns:
        keep = np.asarray(columns[classes.where[0]], dtype=object) == classes.where[1]
        values = values[keep]
    v = _finite(values)
    m = float(np.max(np.abs(v))) * classes.scale if v.size else 0.0
    big = m if m > 0 else 1.0  # display units
    edges = np.linspace(-big, big, n + 1)
    tokens = {}
    for i in range(n):
        lo, hi = edges[i], edges[i + 1]
        label = f"{value_label(lo)} to {value_label(hi)} {classes.unit}".strip()
        if i == 0 and classes.ends[0]:
            label += f" (\u2212 = {classes.ends[0]})"
        if i == n - 1 and classes.ends[1]:
            label += f" (+ = {classes.ends[1]})"
        tokens[f"lo{i}"] = repr(float(lo / classes.scale))
        tokens[f"hi{i}"] = repr(float(hi / classes.scale))
        tokens[f"label{i}"] = escape(label, {'"': "&quot;"})
    return tokens


#: page length (mm) of the arrow shown in the legend as the scale
ARROW_LEGEND_MM = 6.0


def arrow_tokens(columns: Mapping[str, Any]) -> Dict[str, str]:
    """The arrow scale: a round length R (1, 2 or 5 times a power of ten, at most the 95th
    percentile of ``magnitude``) is drawn ``ARROW_LEGEND_MM`` long, every arrow in proportion;
    the legend says so."""
    mag = _finite(_column(columns, "magnitude"))
    mag = mag[mag > 0]
    ref = nice_down(float(np.percentile(mag, 95))) if mag.size else 0.01
    mm = ref * 1000.0
    text = f"{mm:.3g} mm" if mm >= 1 else f"{mm * 1000:.3g} \u00b5m"
    label = f"scale: this arrow ({ARROW_LEGEND_MM:g} mm) = {text} horizontal"
    return {
        "arrow_mm_per_m": repr(ARROW_LEGEND_MM / ref),
        "arrow_label": escape(label, {'"': "&quot;"}),
    }


#: a cell whose horizontal sigma exceeds this many times the median is flagged uncertain
SIGMA_FLAG_FACTOR = 3.0


def sigma_tokens(columns: Mapping[str, Any]) -> Dict[str, str]:
    """The flag of uncertain cells: horizontal sigma above ``SIGMA_FLAG_FACTOR`` times the
    median (``sigma_flag`` in m, ``sigma_label`` for the legend)."""
    sx, sy = _column(columns, "sigma_dx"), _column(columns, "sigma_dy")
    s = _finite(np.hypot(sx, sy)) if sx is not None and sy is not None else np.empty(0)
    if not s.size:
        return {"sigma_flag": "1e300", "sigma_label": "horizontal \u03c3 unknown"}
    flag = SIGMA_FLAG_FACTOR * float(np.median(s))
    label = f"horizontal \u03c3 > {flag * 1000:.3g} mm ({SIGMA_FLAG_FACTOR:g} \u00d7 median)"
    return {"sigma_flag": repr(flag), "sigma_label": escape(label, {'"': "&quot;"})}


def _fill(text: str, tokens: Mapping[str, str]) -> str:
    for key, value in tokens.items():
        text = text.replace("{slipmap." + key + "}", value)
    if "{slipmap." in text:
        start = text.index("{slipmap.")
        raise ValueError(f"unfilled style token {text[start : start + 30]!r}")  # programming error
    return text


def vector_qml(style: VectorStyle, columns: Optional[Mapping[str, Any]] = None) -> str:
    """The QML text of ``style`` fitted to a layer's ``columns`` (``{name: (K,) array}``)."""
    columns = columns or {}
    text = template(style.name)
    tokens: Dict[str, str] = {}
    if style.classes is not None:
        n = text.count("{slipmap.label")
        tokens.update(class_tokens(style.classes, columns, n))
    if style.arrows:
        tokens.update(arrow_tokens(columns))
    if style.sigma:
        tokens.update(sigma_tokens(columns))
    return _fill(text, tokens)


def raster_qml(style: RasterStyle, values=None, *, limit: Optional[float] = None) -> str:
    """The QML text of ``style`` with its ramp over ``[-M, M]``: M = ``limit`` or max |v| of
    ``values`` (the band's array; 1 legend unit when there is none)."""
    if limit is None:
        v = _finite(values)
        limit = float(np.max(np.abs(v))) if v.size else 0.0
    big = limit if limit > 0 and math.isfinite(limit) else 1.0 / style.scale
    root = ET.fromstring(template(style.name).split("\n", 1)[1])
    renderer = root.find(".//rasterrenderer")
    renderer.set("band", str(style.band))
    low = 0.0 if style.sequential else -big
    renderer.set("classificationMin", repr(low))
    renderer.set("classificationMax", repr(big))
    shader = renderer.find(".//colorrampshader")
    old = max(abs(float(shader.get("minimumValue"))), abs(float(shader.get("maximumValue"))))
    shader.set("minimumValue", repr(low))
    shader.set("maximumValue", repr(big))
    items = shader.findall("item")
    for item in items:
        t = float(item.get("value")) / old  # the template's ramp lies on [-1, 1]
        value = (t + 1.0) / 2.0 * big if style.sequential else t * big
        item.set("value", repr(value))
        if style.sequential:
            item.set("label", f"{value * style.scale:.3g} {style.unit}".strip())
        else:
            item.set("label", value_label(value * style.scale, style.unit))
    if style.sequential:
        items[0].set("label", items[0].get("label") + f" ({style.ends[0]})" * bool(style.ends[0]))
        items[-1].set("label", items[-1].get("label") + f" ({style.ends[1]})" * bool(style.ends[1]))
    else:
        if style.ends[0]:
            items[0].set("label", items[0].get("label") + f" (\u2212 = {style.ends[0]})")
        if style.ends[1]:
            items[-1].set("label", items[-1].get("label") + f" (+ = {style.ends[1]})")
    legend = shader.find("rampLegendSettings")
    if legend is not None:
        legend.set("minimumLabel", items[0].get("label"))
        legend.set("maximumLabel", items[-1].get("label"))
    return _DOCTYPE + ET.tostring(root, encoding="unicode")


# --------------------------------------------------------------------------- writing


def gpkg_styles(job: str, layers) -> Dict[str, str]:
    """``{layer name: QML}`` for the layers of ``job``'s GeoPackage (``layers``:
    :class:`~slipmap.core.io.vector.VectorLayer`), each fitted to its own columns; for
    ``write_gpkg_layers(..., styles=...)``."""
    table = OUTPUT_STYLES.get(job, {}).get("layers", {})
    return {
        layer.name: vector_qml(table[layer.name], layer.fields)
        for layer in layers
        if layer.name in table
    }


def write_raster_style(plan, job: str, key: str, values=None) -> Optional[str]:
    """Write the fitted style of raster output ``key`` of ``job`` as the ``.qml`` QGIS reads
    beside it, staged in ``plan`` (moved in with the raster). ``values``: the styled band's
    array (None: read from the written file). Returns the sidecar's final name (None when the
    output is not written or has no style)."""
    from ..core.io.raster import band_range, style_sidecar
    from ..core.io.raster import write_raster_style as write_sidecar

    style = OUTPUT_STYLES.get(job, {}).get(key)
    if not isinstance(style, RasterStyle) or not plan.wants(key) or not plan.file(key).exists():
        return None
    if values is None:
        lo, hi = band_range(plan.file(key), style.band)
        qml = raster_qml(style, limit=max(abs(lo), abs(hi)) if math.isfinite(lo) else 0.0)
    else:
        qml = raster_qml(style, values)
    sidecar = plan.beside(key, ".qml")  # staged beside the staged raster, moved in with it
    assert sidecar == style_sidecar(plan.file(key)), sidecar
    write_sidecar(plan.file(key), qml)
    return sidecar.name
