"""Helpers shared by the SlipMap algorithms: base class, progress adapter, error wrapping."""

from __future__ import annotations

import contextlib
import logging

from qgis.core import (
    QgsProcessingAlgorithm,
    QgsProcessingException,
    QgsProcessingParameterDefinition,
)

from ..compat import band_statistics, can_execute, renderer_band, set_renderer_band

LAS_FILTER = "LAS/LAZ (*.las *.laz)"
LAS_OUTPUT_FILTER = "LAS (*.las);;LAZ (*.laz)"


def progress_callback(feedback, *, text_every_s=2.0):
    """A SlipMap ``callback(fraction, message)`` that drives ``feedback`` and cancels.

    Raises :class:`~slipmap.core.errors.CancelledError` as soon as ``feedback.isCanceled()``.
    The progress bar follows every call; the progress *text* (the dialog also writes it as a
    line of the Processing log) is shown for the first call, then at most every
    ``text_every_s`` seconds, and for the last (fraction 1), so a loop over 90 windows or the
    sub-stages of 16 plane extractions write a few lines, not 90.
    """
    import time

    from ...core.errors import CancelledError

    state = {"t": -1e9}

    def callback(fraction, message=""):
        if feedback is None:
            return
        if feedback.isCanceled():
            raise CancelledError("cancelled by the user")
        feedback.setProgress(100.0 * float(fraction))
        if message:
            now = time.monotonic()
            if now - state["t"] >= text_every_s or fraction >= 1:
                feedback.setProgressText(str(message))
                state["t"] = now

    return callback


class _FeedbackHandler(logging.Handler):
    """Routes the ``slipmap`` logger to the running algorithm's feedback, a few lines a job:

    * errors to ``reportError``;
    * warnings to ``pushWarning`` (the Processing log, in orange), each kind once: a warning
      that differs from an earlier one only in its numbers ("no planes found (56 leaves, 4
      planar)" per tile) goes to ``pushDebugInfo``, and :meth:`flush_repeats` then writes one line
      with the count;
    * info of the application layer (the job's lines) to ``pushInfo``, a line repeated word
      for word once; info of the core (per tile, per side, per window: "point spacing …",
      "7 of 7 planes matched") and debug to ``pushDebugInfo``.

    Nothing goes to QGIS's Python console."""

    def __init__(self):
        super().__init__(logging.DEBUG)
        self.feedback = None
        self.reset()

    def reset(self):
        self.kinds, self.last_info = {}, None

    @staticmethod
    def kind(record, text):
        import re

        return record.name, re.sub(r"[-+]?(\d+\.?\d*(e[-+]?\d+)?|nan|inf)", "#", text)

    def emit(self, record):
        fb = self.feedback
        if fb is None:
            return
        try:
            text = self.format(record)
            if record.levelno >= logging.ERROR:
                fb.reportError(text)
            elif record.levelno >= logging.WARNING:
                key = self.kind(record, text)
                first, n = self.kinds.get(key, (text, 0))
                self.kinds[key] = (first, n + 1)
                if n == 0:
                    push = getattr(fb, "pushWarning", None) or fb.pushInfo  # pushWarning: 3.20+
                    push(text)
                else:
                    fb.pushDebugInfo(text)
            elif record.levelno >= logging.INFO and not record.name.startswith("slipmap.core"):
                if text != self.last_info:
                    fb.pushInfo(text)
                self.last_info = text
            else:
                fb.pushDebugInfo(text)
        except Exception:  # noqa: BLE001 - logging must never fail the algorithm
            pass

    def flush_repeats(self):
        """One line per kind of warning that came more than once (then start afresh)."""
        fb = self.feedback
        if fb is not None:
            push = getattr(fb, "pushWarning", None) or fb.pushInfo
            for first, n in self.kinds.values():
                if n > 1:
                    push(f"{n} warnings like: {first}")
        self.reset()


_HANDLER = _FeedbackHandler()


def attach_feedback(feedback):
    """Send the ``slipmap`` logger (and Python warnings) to ``feedback`` until the next call."""
    import warnings

    logger = logging.getLogger("slipmap")
    if _HANDLER not in logger.handlers:
        logger.addHandler(_HANDLER)
        logger.setLevel(min(logger.level or logging.INFO, logging.INFO))
    _HANDLER.feedback = feedback
    _HANDLER.reset()
    if feedback is not None and warnings.showwarning is not _warning_to_feedback:
        _ORIGINAL_SHOWWARNING[0] = warnings.showwarning
        warnings.showwarning = _warning_to_feedback
    return _HANDLER


_ORIGINAL_SHOWWARNING = [None]
_PACKAGE_DIR = str(__import__("pathlib").Path(__file__).resolve().parents[2])


def _warning_to_feedback(message, category, filename, lineno, file=None, line=None):
    """SlipMap's own Python warnings go to the Processing log; others where they went."""
    if str(filename).startswith(_PACKAGE_DIR) and _HANDLER.feedback is not None:
        logging.getLogger("slipmap.warnings").warning("%s", message)
    elif _ORIGINAL_SHOWWARNING[0] is not None:
        _ORIGINAL_SHOWWARNING[0](message, category, filename, lineno, file, line)


@contextlib.contextmanager
def slipmap_errors(spec=None):
    """Turn SlipMap errors into ``QgsProcessingException``; with ``spec`` (the job's
    :class:`~slipmap.app.options.JobSpec`) an option error names the option by its dialog
    label."""
    from ...app.options import OptionError
    from ...core.errors import CancelledError, SlipMapError

    try:
        yield
    except CancelledError as exc:
        raise QgsProcessingException("Run cancelled.") from exc
    except OptionError as exc:
        text = spec.render_error(exc, "qgis") if spec is not None else str(exc)
        raise QgsProcessingException(text) from exc
    except SlipMapError as exc:
        raise QgsProcessingException(str(exc)) from exc


# --------------------------------------------------------------------------- job options


def _parameter(opt):
    """The Processing parameter of one job option (see ``slipmap.app.options``)."""
    from qgis.core import (
        QgsProcessingParameterBoolean,
        QgsProcessingParameterCrs,
        QgsProcessingParameterEnum,
        QgsProcessingParameterFile,
        QgsProcessingParameterNumber,
        QgsProcessingParameterString,
    )

    name, label = opt.name_in("qgis"), opt.dialog_label
    optional = not opt.required
    t = opt.type
    if t in ("float", "int"):
        kind = (
            QgsProcessingParameterNumber.Integer
            if t == "int"
            else QgsProcessingParameterNumber.Double
        )
        p = QgsProcessingParameterNumber(
            name, label, kind, defaultValue=opt.default, optional=optional
        )
        if opt.minimum is not None:
            lo = opt.minimum
            if opt.exclusive and t == "int":
                lo = int(opt.minimum) + 1
            p.setMinimum(lo)
        if opt.maximum is not None:
            p.setMaximum(opt.maximum)
    elif t == "bool":
        p = QgsProcessingParameterBoolean(name, label, defaultValue=bool(opt.default))
    elif t == "choice":
        default = list(opt.choices).index(opt.default) if opt.default in opt.choices else None
        p = QgsProcessingParameterEnum(
            name,
            label,
            options=[str(c) for c in opt.choices],
            defaultValue=default,
            optional=optional or default is not None,
        )
    elif t == "path":
        p = QgsProcessingParameterFile(
            name, label, fileFilter=opt.file_filter or "", optional=optional
        )
    elif t == "crs":
        p = QgsProcessingParameterCrs(name, label, optional=True)
    else:  # lists, vector3, key=value text: a string the option's conversion reads
        default = opt.default
        if isinstance(default, (list, tuple)):
            default = " ".join(str(v) for v in default)
        elif isinstance(default, dict):
            default = ",".join(f"{k}={v}" for k, v in default.items())
        p = QgsProcessingParameterString(name, label, defaultValue=default, optional=optional)
    p.setHelp(opt.help)
    if opt.advanced:
        p.setFlags(p.flags() | QgsProcessingParameterDefinition.FlagAdvanced)
    return p


def add_parameters(alg, spec, *, skip=(), roles=("setting",)):
    """Add the Processing parameters of ``spec``'s options that QGIS shows (``qgis`` not
    None), skipping the keys in ``skip`` (the algorithm declares those itself)."""
    for opt in spec.for_face("qgis", roles=roles):
        if opt.key not in skip:
            alg.addParameter(_parameter(opt))


def options_from(alg, parameters, context, spec, *, extra=None, run_check=True):
    """The job's options (converted, defaults in, cross-checks run) from ``parameters``.

    ``extra`` gives values the algorithm reads itself (layers, destinations). Raises
    ``QgsProcessingException`` naming the option by its dialog label.
    """
    from ...app.options import OptionError

    raw = {}
    for opt in spec.for_face("qgis"):
        name = opt.name_in("qgis")
        if not is_set(parameters, name, context):
            continue
        t = opt.type
        if t in ("float", "int"):
            value = (
                alg.parameterAsInt(parameters, name, context)
                if t == "int"
                else alg.parameterAsDouble(parameters, name, context)
            )
        elif t == "bool":
            value = alg.parameterAsBoolean(parameters, name, context)
        elif t == "choice":
            value = opt.choices[alg.parameterAsEnum(parameters, name, context)]
        elif t == "path":
            value = _path_value(alg, parameters, name, context)
        elif t == "crs":
            crs = alg.parameterAsCrs(parameters, name, context)
            value = crs.toWkt() if crs.isValid() else None
        else:
            value = alg.parameterAsString(parameters, name, context)
            if not str(value).strip():
                value = None
        raw[opt.key] = value
    raw.update(extra or {})
    try:
        return spec.parse(raw, face="qgis", run_check=run_check)
    except OptionError as exc:
        raise QgsProcessingException(spec.render_error(exc, "qgis")) from exc


def cloud_path(alg, parameters, name, context):
    """An input file parameter's path. A value that is not a file but the id or name of a
    point-cloud layer of the project (QGIS >= 3.18 with its PDAL provider) resolves to that
    layer's source file, so an analyst can pick the layer already loaded."""
    import os

    from qgis.core import QgsMapLayerType, QgsProcessingUtils

    path = alg.parameterAsFile(parameters, name, context)
    if path and not os.path.isfile(path):
        layer = QgsProcessingUtils.mapLayerFromString(path, context)
        kind = getattr(QgsMapLayerType, "PointCloudLayer", None)
        if layer is not None and kind is not None and layer.type() == kind:
            return layer.source().split("|")[0]
    return path


def _path_value(alg, parameters, name, context):
    """A path parameter's value: an input file, or the file a destination writes (the dialog
    gives destinations as ``QgsProcessingOutputLayerDefinition``, which ``parameterAsFile``
    reads as empty)."""
    p = alg.parameterDefinition(name)
    if p is None or not p.isDestination():
        return cloud_path(alg, parameters, name, context)
    if p.type() == "fileDestination":
        return alg.parameterAsFileOutput(parameters, name, context)
    if p.type() == "rasterDestination":
        return raster_output(alg, parameters, name, context)
    return destination_path(parameters.get(name), context)


def is_set(parameters, name, context=None):
    """True when the optional parameter ``name`` was given a value.

    The one place that says what "not given" is, for every caller and QGIS version:
    absent, ``None``, a NULL ``QVariant`` (what the real dialog passes for an empty optional
    file or number field), an empty or blank string, an empty list, a ``QgsProperty`` that is
    invalid or whose static value (or, with ``context``, evaluated value) is one of these, and
    a destination or feature-source definition whose sink or source is. A layer, a number
    (0 included), a boolean and a non-blank text are given. See :func:`is_empty_value`.
    """
    return not is_empty_value(parameters.get(name), context)


def is_empty_value(value, context=None):
    """True when a Processing parameter value stands for "nothing given" (see :func:`is_set`)."""
    if value is None:
        return True
    from qgis.core import (
        QgsProcessingFeatureSourceDefinition,
        QgsProcessingOutputLayerDefinition,
        QgsProperty,
    )
    from qgis.PyQt.QtCore import QVariant

    if isinstance(value, QVariant):
        return value.isNull() or not value.isValid() or is_empty_value(value.value(), context)
    if isinstance(value, QgsProperty):
        kind = value.propertyType()
        if kind == QgsProperty.InvalidProperty:
            return True
        if kind == QgsProperty.StaticProperty:
            return is_empty_value(value.staticValue(), context)
        if context is None:
            return False  # an expression or a field: a value, known only when evaluated
        text, ok = value.valueAsString(context.expressionContext())
        return not ok or is_empty_value(text)
    if isinstance(value, QgsProcessingOutputLayerDefinition):
        return is_empty_value(value.sink, context)
    if isinstance(value, QgsProcessingFeatureSourceDefinition):
        return is_empty_value(value.source, context)
    if isinstance(value, str):
        return not value.strip()
    if isinstance(value, (list, tuple, set)):
        return all(is_empty_value(v, context) for v in value)
    return False


def advanced(param):
    """``param`` flagged as advanced (shown under "Advanced parameters")."""
    param.setFlags(param.flags() | QgsProcessingParameterDefinition.FlagAdvanced)
    return param


#: group id -> icon file (qgis_plugin/icons); the provider's own icon is slipmap.svg
GROUP_ICONS = {
    "slip": "slip.svg",
    "segmentation": "segmentation.svg",
    "roughness": "roughness.svg",
    "accuracy": "accuracy.svg",
    "fields": "fields.svg",
}
#: words the Processing toolbox search finds every SlipMap algorithm by, plus per group
COMMON_TAGS = ("slipmap", "lidar", "point cloud", "las", "laz", "geodesy")
GROUP_TAGS = {
    "slip": ("fault", "slip", "earthquake", "registration", "planes", "displacement", "offset"),
    "segmentation": ("planes", "segmentation", "octree", "region growing", "buildings"),
    "roughness": ("roughness", "odr", "surface", "texture"),
    "accuracy": ("accuracy", "uncertainty", "covariance", "error", "trajectory", "tpu"),
    "fields": ("displacement", "landslide", "piv", "icp", "strain", "deformation", "dem"),
}
HELP_URL = "https://github.com/slipmap/slipmap/blob/main/docs/qgis.md"


def icon_path(name):
    """Path of a bundled icon ``qgis_plugin/icons/<name>``."""
    from pathlib import Path

    return str(Path(__file__).resolve().parents[1] / "icons" / name)


class SlipMapAlgorithm(QgsProcessingAlgorithm):
    """Base of the SlipMap algorithms: no state is kept on ``self`` between runs.

    Gives every algorithm its group's icon, search tags, a one-line description (the job's),
    a help URL (docs/qgis.md, at the algorithm's section) and the ``slipmap`` logger routed
    to the Processing log while it runs.
    """

    _id = ""
    _name = ""
    _group = ""
    _group_id = ""
    _tags = ()
    spec = None  # the job's JobSpec, where the algorithm runs one

    def name(self):
        return self._id

    def displayName(self):  # noqa: N802 (QGIS API name)
        return self._name

    def group(self):
        return self._group

    def groupId(self):  # noqa: N802 (QGIS API name)
        return self._group_id

    def createInstance(self):  # noqa: N802 (QGIS API name)
        return type(self)()

    def canExecute(self):  # noqa: N802 (QGIS API name)
        return can_execute()

    def icon(self):
        from qgis.PyQt.QtGui import QIcon

        return QIcon(icon_path(GROUP_ICONS.get(self._group_id, "slipmap.svg")))

    def svgIconPath(self):  # noqa: N802 (QGIS API name)
        return icon_path(GROUP_ICONS.get(self._group_id, "slipmap.svg"))

    def tags(self):
        return list(dict.fromkeys(COMMON_TAGS + GROUP_TAGS.get(self._group_id, ()) + self._tags))

    def shortDescription(self):  # noqa: N802 (QGIS API name)
        if self.spec is not None:
            return self.spec.description.split(". ")[0].rstrip(".") + "."
        return self._name

    def helpUrl(self):  # noqa: N802 (QGIS API name)
        return f"{HELP_URL}#{self._id}"

    def prepareAlgorithm(self, parameters, context, feedback):  # noqa: N802 (QGIS API name)
        attach_feedback(feedback)
        return True

    def postProcessAlgorithm(self, context, feedback):  # noqa: N802 (QGIS API name)
        _HANDLER.flush_repeats()
        unique_layer_names(self, context)
        return {}

    # ------------------------------------------------------------------ the job

    def job_extra(self, parameters, context):
        """Options the algorithm gives its job itself (paths it resolves; ``out`` stands for
        the outputs, which the algorithm maps from its destinations)."""
        return {"out": "-"}

    def job_options(self, parameters, context):
        """The job's options from the parameters (:func:`options_from` with
        :meth:`job_extra`); errors name the dialog's labels."""
        extra = self.job_extra(parameters, context)
        return options_from(self, parameters, context, self.spec, extra=extra)

    def checkParameterValues(self, parameters, context):  # noqa: N802 (QGIS API name)
        if self.spec is not None:
            try:
                self.job_options(parameters, context)
            except QgsProcessingException as exc:
                return False, str(exc)
        problem = output_folder_problem(self, parameters, context)
        if problem:
            return False, problem
        return super().checkParameterValues(parameters, context)

    def run_job(self, job, opts, outputs, feedback, **kwargs):
        """``job.run`` with the feedback's progress and cancel, its errors as
        ``QgsProcessingException`` in the dialog's words and its lines in the log."""
        with slipmap_errors(self.spec):
            result = job.run(opts, outputs, progress=progress_callback(feedback), **kwargs)
        for line in result.lines:
            feedback.pushInfo(line)
        return result


# --------------------------------------------------------------------------- destinations

#: destination values that are not files (QGIS writes them itself)
_NOT_FILES = ("TEMPORARY_OUTPUT", "memory:", "ogr:", "postgis:", "postgres:", "spatialite:")
#: suffixes of the GeoTIFF every SlipMap raster output is
GEOTIFF_SUFFIXES = (".tif", ".tiff")


def destination_path(value, context):
    """The file a destination parameter's ``value`` names (a path, a ``QgsProperty`` or a
    ``QgsProcessingOutputLayerDefinition``); None for a temporary, memory or database output."""
    from qgis.core import QgsProcessingOutputLayerDefinition, QgsProperty

    if isinstance(value, QgsProcessingOutputLayerDefinition):
        value = value.sink
    if isinstance(value, QgsProperty):
        value = value.valueAsString(context.expressionContext())[0]
    text = str(value or "").strip()
    if not text or text.startswith(_NOT_FILES):
        return None
    return text.split("|")[0]


def output_folder_problem(alg, parameters, context):
    """The message for the first destination whose folder does not exist, or whose raster
    is not named as the GeoTIFF it is, in the dialog's words (None when all is well):
    checked before running, so nothing is computed for an output that cannot be written."""
    from pathlib import Path

    for p in alg.destinationParameterDefinitions():
        path = destination_path(parameters.get(p.name()), context)
        if path is None:
            continue
        target = Path(path).expanduser()
        label = f'"{p.description()}"'
        if not target.parent.is_dir():
            return (
                f"{label}: the folder {target.parent} does not exist; create it or choose "
                "another place for the file"
            )
        suffix = target.suffix.lower()
        if p.type() == "rasterDestination" and suffix and suffix not in GEOTIFF_SUFFIXES:
            return f"{label}: the raster is a GeoTIFF; name the file .tif (not {target.suffix})"
    return None


def raster_output(alg, parameters, name, context):
    """The path of raster destination ``name`` (None when not asked for), ``.tif`` added
    when the name has no suffix, so that the GeoTIFF written there opens as one."""
    from pathlib import Path

    path = alg.parameterAsOutputLayer(parameters, name, context)
    if not path or Path(path).suffix:
        return path or None
    layers = context.layersToLoadOnCompletion()
    if path in layers:  # load the file that is written, under the name it gets
        layers[path + ".tif"] = layers.pop(path)
        context.setLayersToLoadOnCompletion(layers)
    return path + ".tif"


# --------------------------------------------------------------------------- styles

#: post-processors must outlive processAlgorithm (QGIS keeps only a C++ pointer)
_POST_PROCESSORS = []


def style_path(name):
    """Path of a bundled QML style ``styles/<name>.qml`` (None when missing)."""
    from ...styles import style_path as _style_path

    return _style_path(name)


def apply_style_on_load(
    context, output, style_name, symmetric_band=None, *, scale=1.0, unit="", ends=None
):
    """Style ``output`` (an output layer path or id) with a bundled QML when QGIS loads it.

    With ``symmetric_band`` (a raster band number) the pseudocolor ramp is then rescaled to
    ``±max|value|`` of that band (:func:`symmetric_limits`; legend labels in the band's values
    times ``scale``, with ``unit``, and ``ends`` = (name of the low end, of the high end)), so
    a diverging ramp keeps white at zero whatever the data's range. A graduated vector style
    gets the same symmetric classes (:func:`symmetric_classes`). A raster is drawn at 80 %
    opacity below the vectors of its group (:func:`raster_below_vectors`). Does nothing when
    the output is not loaded on completion (e.g. ``processing.run`` from a script) or the
    style is missing; never fails the algorithm.
    """
    from qgis.core import QgsProcessingLayerPostProcessorInterface

    qml = style_path(style_name)
    if qml is None or not context.willLoadLayerOnCompletion(output):
        return

    class _Style(QgsProcessingLayerPostProcessorInterface):
        def postProcessLayer(self, layer, context, feedback):  # noqa: N802 (QGIS API name)
            if layer is None or not layer.isValid():
                return
            try:
                layer.loadNamedStyle(qml)
                if symmetric_band is not None:
                    symmetric_limits(layer, symmetric_band, scale=scale, unit=unit, ends=ends)
                symmetric_classes(layer)
                raster_below_vectors(layer, context)
                layer.triggerRepaint()
            except Exception as exc:  # noqa: BLE001 - styling must never fail the run
                if feedback is not None:
                    feedback.pushInfo(f"style {style_name} not applied: {exc}")

    post = _Style()
    _POST_PROCESSORS.append(post)
    context.layerToLoadOnCompletionDetails(output).setPostProcessor(post)


def apply_diverging_style_on_load(context, output, style_name="diverging", band=1, **legend):
    """:func:`apply_style_on_load` with the ramp made symmetric about zero on ``band``
    (``legend``: ``scale``, ``unit``, ``ends`` of the legend labels)."""
    apply_style_on_load(context, output, style_name, symmetric_band=band, **legend)


def value_label(value, scale=1.0, unit=""):
    """A legend label: ``value * scale`` to 3 significant digits with its sign, then ``unit``
    (``+18.1 mm``, ``-0.00215``)."""
    text = f"{value * scale:+.3g}"
    return f"{text} {unit}" if unit else text


def symmetric_limits(layer, band=1, *, scale=1.0, unit="", ends=None):
    """Rescale a single-band pseudocolor renderer to ``[-m, m]``, m = max |value| of ``band``.

    The bundled diverging styles store a ramp symmetric about 0 (white at 0); scaling every
    colour stop by ``m / old_max`` keeps white at 0 for the layer's own range. Every colour
    stop and the continuous legend's end labels then read the values they stand for
    (:func:`value_label`; ``ends`` appended to the low and high end's label, e.g.
    ``("left-lateral", "right-lateral")``). Returns m (None when the renderer is not
    pseudocolor or the band has no finite value).
    """
    import math

    from qgis.core import QgsColorRampShader, QgsSingleBandPseudoColorRenderer

    renderer = layer.renderer()
    if not isinstance(renderer, QgsSingleBandPseudoColorRenderer):
        return None
    if band != renderer_band(renderer):
        set_renderer_band(renderer, band)
    stats = band_statistics(layer.dataProvider(), band, ("Min", "Max"))
    m = max(abs(stats.minimumValue), abs(stats.maximumValue))
    if not math.isfinite(m) or m <= 0:
        return None
    shader = renderer.shader()
    ramp = shader.rasterShaderFunction() if shader is not None else None
    if not isinstance(ramp, QgsColorRampShader):
        return None
    old = max(abs(ramp.minimumValue()), abs(ramp.maximumValue()))
    if not old > 0:
        return None
    items = ramp.colorRampItemList()
    for item in items:
        item.value = item.value * m / old
        item.label = value_label(item.value, scale, unit)
    if ends:
        items[0].label += f" ({ends[0]})"
        items[-1].label += f" ({ends[1]})"
    ramp.setColorRampItemList(items)
    ramp.setMinimumValue(-m)
    ramp.setMaximumValue(m)
    if hasattr(ramp, "legendSettings"):  # QGIS >= 3.18: the continuous legend's end labels
        legend = ramp.legendSettings()
        legend.setMinimumLabel(items[0].label)
        legend.setMaximumLabel(items[-1].label)
        ramp.setLegendSettings(legend)
    renderer.setClassificationMin(-m)
    renderer.setClassificationMax(m)
    new = renderer.clone()  # set anew (rendererChanged): the legend is rebuilt from it
    new.setClassificationMin(-m)  # clone() does not carry the classification range
    new.setClassificationMax(m)
    layer.setRenderer(new)
    return m


def symmetric_classes(layer):
    """Rescale a graduated vector renderer's classes to equal steps over ``[-m, m]``,
    m = max |class expression| over the layer's features (the bundled slip styles: a
    diverging ramp, white about zero, values in mm); labels read ``+6.03 to +12.1 mm``.
    Returns m (None when the renderer is not graduated or no value is finite)."""
    import math

    from qgis.core import (
        QgsExpression,
        QgsExpressionContext,
        QgsExpressionContextUtils,
        QgsGraduatedSymbolRenderer,
    )

    renderer = layer.renderer() if hasattr(layer, "renderer") else None
    if not isinstance(renderer, QgsGraduatedSymbolRenderer) or not renderer.ranges():
        return None
    expression = QgsExpression(renderer.classAttribute())
    ctx = QgsExpressionContext(QgsExpressionContextUtils.globalProjectLayerScopes(layer))
    expression.prepare(ctx)
    values = []
    for feature in layer.getFeatures():
        ctx.setFeature(feature)
        v = expression.evaluate(ctx)
        try:
            v = float(v)
        except (TypeError, ValueError):
            continue
        if math.isfinite(v):
            values.append(abs(v))
    m = max(values, default=0.0)
    if not m > 0:
        return None
    n = len(renderer.ranges())
    edges = [-m + 2.0 * m * i / n for i in range(n + 1)]
    for i in range(n):
        renderer.updateRangeLowerValue(i, edges[i])
        renderer.updateRangeUpperValue(i, edges[i + 1])
        lo, hi = value_label(edges[i]), value_label(edges[i + 1])
        renderer.updateRangeLabel(i, f"{lo} to {hi} mm")
    layer.setRenderer(renderer.clone())  # rendererChanged: the legend is rebuilt from it
    return m


def raster_below_vectors(layer, context=None):
    """Draw a raster output at 80 % opacity (the bundled raster styles say so) and move it
    below every vector layer of its layer-tree group, so a new raster never hides the
    vectors (QGIS loads a run's outputs in file-name order, each on top)."""
    from qgis.core import QgsLayerTree, QgsMapLayerType, QgsProject

    if layer.type() != QgsMapLayerType.RasterLayer:
        return
    project = (layer.project() if hasattr(layer, "project") else None) or QgsProject.instance()
    node = project.layerTreeRoot().findLayer(layer.id())
    if node is None or node.parent() is None:
        return
    parent = node.parent()
    children = parent.children()
    vectors = [
        i
        for i, c in enumerate(children)
        if QgsLayerTree.isLayer(c)
        and c.layer() is not None
        and c.layer().type() == QgsMapLayerType.VectorLayer
    ]
    here = children.index(node)
    if vectors and vectors[-1] > here:
        parent.insertChildNode(vectors[-1] + 1, node.clone())
        parent.removeChildNode(node)


_USED_NAMES = set()


def unique_layer_names(alg, context):
    """Give the layers this run loads names of its own: the output's label and the run's
    time (``Tiles 14:03:22``; a counter is added within the same second), so a second run
    does not add a second "Tiles" (QGIS may still prefer the file name of a named file,
    its setting "Prefer output filename for layer names")."""
    import time

    labels = {p.description() for p in alg.destinationParameterDefinitions()}
    layers = context.layersToLoadOnCompletion()
    stamp = time.strftime("%H:%M:%S")
    changed = False
    for details in layers.values():
        if details.name not in labels:
            continue
        name, k = f"{details.name} {stamp}", 1
        while name in _USED_NAMES:
            k += 1
            name = f"{details.name} {stamp} #{k}"
        _USED_NAMES.add(name)
        details.name = name
        changed = True
    if changed:
        context.setLayersToLoadOnCompletion(layers)


# --------------------------------------------------------------------------- vector inputs


def source_parts(source, target_crs, context, *, parameter, polygons):
    """Vertex arrays (K, 2) of every line part (``polygons=False``) or polygon exterior ring
    (``polygons=True``, holes ignored as ``core.io.vector.read_polygons``) of the feature
    source ``source``, transformed to ``target_crs`` with QGIS's own transform context.

    Raises ``QgsProcessingException`` naming ``parameter`` for a layer of the wrong geometry
    type or one without a usable part.
    """
    import numpy as np
    from qgis.core import QgsCoordinateTransform, QgsGeometry, QgsWkbTypes

    want = QgsWkbTypes.PolygonGeometry if polygons else QgsWkbTypes.LineGeometry
    kind = "polygon" if polygons else "line"
    if QgsWkbTypes.geometryType(source.wkbType()) != want:
        raise QgsProcessingException(
            f"{parameter} must be a {kind} layer, got {QgsWkbTypes.displayString(source.wkbType())}"
        )
    transform = None
    if target_crs.isValid() and source.sourceCrs().isValid():
        transform = QgsCoordinateTransform(
            source.sourceCrs(), target_crs, context.transformContext()
        )
    parts = []
    for feature in source.getFeatures():
        geom = QgsGeometry(feature.geometry())
        if geom.isEmpty():
            continue
        if transform is not None:
            geom.transform(transform)
        if polygons:
            polys = geom.asMultiPolygon() if geom.isMultipart() else [geom.asPolygon()]
            vertex_lists = [poly[0] for poly in polys if poly and len(poly[0]) >= 3]
        else:
            lines = geom.asMultiPolyline() if geom.isMultipart() else [geom.asPolyline()]
            vertex_lists = [line for line in lines if len(line) > 1]
        parts += [np.array([[p.x(), p.y()] for p in v]) for v in vertex_lists]
    if not parts:
        need = "three" if polygons else "two"
        raise QgsProcessingException(f"{parameter} has no {kind} with {need} or more vertices")
    return parts
