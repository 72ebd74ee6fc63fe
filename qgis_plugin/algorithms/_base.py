"""Helpers shared by the SlipMap algorithms: base class, progress adapter, error wrapping."""

from __future__ import annotations

import contextlib
import logging

from qgis.core import (
    QgsProcessingAlgorithm,
    QgsProcessingException,
    QgsProcessingParameterDefinition,
)

from ..compat import (
    band_statistics,
    can_execute,
    keep_proj_context,
    renderer_band,
    set_renderer_band,
)
from ._named import NamedAlgorithm

LAS_FILTER = "LAS/LAZ (*.las *.laz)"
LAS_OUTPUT_FILTER = "LAS (*.las);;LAZ (*.laz)"


#: seconds between two progress texts (the dialog writes each as a log line)
PROGRESS_TEXT_EVERY_S = 2.0


def progress_callback(feedback, *, text_every_s=None):
    """A SlipMap ``callback(fraction, message)`` that drives ``feedback`` and cancels.

    Raises :class:`~slipmap.core.errors.CancelledError` as soon as ``feedback.isCanceled()``.
    The progress bar follows every call and never goes back (the jobs give each phase its
    share of the bar by its cost, e.g. the moving windows by their number); the progress
    *text* (the dialog also writes it as a line of the Processing log) is shown for the first
    call, then at most every ``text_every_s`` seconds (default
    :data:`PROGRESS_TEXT_EVERY_S`), and for the last (fraction 1), so a
    loop over 90 windows or the sub-stages of 16 plane extractions write a few lines, not 90.
    """
    import time

    from ...core.errors import CancelledError

    state = {"t": -1e9, "max": 0.0}

    def callback(fraction, message=""):
        if feedback is None:
            return
        if feedback.isCanceled():
            raise CancelledError("cancelled by the user")
        # the bar never goes back (a phase that reports late, a tile that finishes early)
        state["max"] = max(state["max"], min(1.0, float(fraction)))
        feedback.setProgress(100.0 * state["max"])
        if message:
            now = time.monotonic()
            every = PROGRESS_TEXT_EVERY_S if text_every_s is None else text_every_s
            if now - state["t"] >= every or fraction >= 1:
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


def detach_feedback():
    """Stop sending the ``slipmap`` logger to the last run's feedback. QGIS deletes a run's
    feedback when the run ends (3.40 at once): a later log line (the check before the next
    run, which has no feedback) must not reach the deleted object, which crashes QGIS."""
    import warnings

    _HANDLER.feedback = None
    _HANDLER.reset()
    if warnings.showwarning is _warning_to_feedback and _ORIGINAL_SHOWWARNING[0] is not None:
        warnings.showwarning = _ORIGINAL_SHOWWARNING[0]


_ORIGINAL_SHOWWARNING = [None]
_PACKAGE_DIR = str(__import__("pathlib").Path(__file__).resolve().parents[2])


def _warning_to_feedback(message, category, filename, lineno, file=None, line=None):
    """SlipMap's own Python warnings go to the Processing log; others where they went."""
    if str(filename).startswith(_PACKAGE_DIR) and _HANDLER.feedback is not None:
        logging.getLogger("slipmap.warnings").warning("%s", message)
    elif _ORIGINAL_SHOWWARNING[0] is not None:
        _ORIGINAL_SHOWWARNING[0](message, category, filename, lineno, file, line)


#: what a cancelled run leaves in its context's layers to load (see :func:`watch_cancel`)
CANCELLED_MARK = "slipmap:cancelled"


def watch_cancel(feedback, context):
    """After Cancel, make the algorithm dialog stop without "Algorithm … finished".

    QGIS's dialog (``AlgorithmDialog.finish``, 3.22 to 3.40) runs ``handleAlgorithmResults``
    after every run, failed and cancelled ones too, and prints "Algorithm '…' finished" (and
    "HTML output has been generated" for an algorithm with an HTML output) unless that returns
    False, which it does for a cancelled feedback only while there is a layer to load. So when
    the user cancels (``feedback.canceled``, emitted in the thread that cancels: the dialog's),
    a mark is added to the layers to load of the run's context; nothing else reads it, and
    :meth:`SlipMapAlgorithm.postProcessAlgorithm` (a run that finished) takes it out.
    """
    if feedback is None or context is None:
        return
    from qgis.core import QgsProcessingContext, QgsProject

    def cancelled():
        try:
            if not context.willLoadLayerOnCompletion(CANCELLED_MARK):
                project = context.project() or QgsProject.instance()
                details = QgsProcessingContext.LayerDetails("", project, "")
                context.addLayerToLoadOnCompletion(CANCELLED_MARK, details)
        except RuntimeError:  # the dialog deleted its context: nothing left to say
            pass

    feedback.canceled.connect(cancelled)


def _unmark_cancelled(context):
    layers = context.layersToLoadOnCompletion()
    if CANCELLED_MARK in layers:
        del layers[CANCELLED_MARK]
        context.setLayersToLoadOnCompletion(layers)


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


def parameter_help(opt, spec=None):
    """A parameter's help (its tooltip in the dialog, its text under *Arguments* in
    ``qgis_process help``): the option's help with other options named as the dialog names
    them (:meth:`JobSpec.help_in`; no CLI flags), then its default ("Default: 0.25") or what
    leaving it empty does, unless the help says so already."""
    text = spec.help_in(opt, "qgis") if spec is not None else opt.help
    if opt.required and opt.default is None or "default" in text.lower():
        return text
    if opt.default is None:
        return f"{text}. Left empty: {opt.unset_text}" if opt.unset_text else text
    from dataclasses import replace

    return f"{text}. Default: {replace(opt, required=False).default_text()}"


def _parameter(opt, spec=None):
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
    p.setHelp(parameter_help(opt, spec))
    if opt.advanced:
        p.setFlags(p.flags() | QgsProcessingParameterDefinition.FlagAdvanced)
    return p


def add_parameters(alg, spec, *, skip=(), roles=("setting",)):
    """Add the Processing parameters of ``spec``'s options that QGIS shows (``qgis`` not
    None), skipping the keys in ``skip`` (the algorithm declares those itself)."""
    for opt in spec.for_face("qgis", roles=roles):
        if opt.key not in skip:
            alg.addParameter(_parameter(opt, spec))


def options_from(alg, parameters, context, spec, *, extra=None, run_check=True):
    """The job's options (converted, defaults in, cross-checks run) from ``parameters``.

    ``extra`` gives values the algorithm reads itself (layers, destinations). Raises
    ``QgsProcessingException`` naming the option by its dialog label.
    """
    from ...app.options import OptionError

    raw, missing = {}, []
    for opt in spec.for_face("qgis"):
        name = opt.name_in("qgis")
        if not is_set(parameters, name, context):
            definition = alg.parameterDefinition(name)
            if definition is None or is_empty_value(definition.defaultValue()):
                if opt.required and opt.key not in (extra or {}):
                    missing.append(opt)
                continue
            # a value the dialog pre-fills is the definition's default: qgis_process and
            # processing.run get it too (parameterAs* below read it)
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
            index = enum_index(alg.parameterDefinition(name), parameters.get(name))
            if isinstance(index, str):  # not one of the options: the job's error names them
                value = index
            else:
                value = opt.choices[alg.parameterAsEnum({name: index}, name, context)]
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
    if len(missing) > 1:  # every missing one at once, not one error per run
        labels = ", ".join(o.display_in("qgis") for o in missing)
        raise QgsProcessingException(f"{labels}: are required; give a value for each")
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


def enum_index(definition, value):
    """The index of enum ``value`` for ``definition``: an index (int or its text) as it is,
    the name of an option (case-insensitive; ``gps-time`` for ``gps_time``) as its index;
    anything else unchanged (QGIS then refuses it as an incorrect value)."""
    from qgis.PyQt.QtCore import QVariant

    if isinstance(value, QVariant):
        value = value.value()
    if not isinstance(value, str) or not value.strip():
        return value
    text = value.strip()
    if text.lstrip("-").isdigit():
        return int(text)
    options = [str(o) for o in definition.options()]

    def squeezed(t):
        return t.lower().replace("-", "").replace("_", "").replace(" ", "")

    for i, option in enumerate(options):
        if squeezed(option) == squeezed(text):
            return i
    for i, option in enumerate(options):  # "constant" for "constant (one sigma)"
        if squeezed(option).startswith(squeezed(text)) and [
            o for o in options if squeezed(o).startswith(squeezed(text))
        ] == [option]:
            return i
    return value


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


def _in_qgis_process():
    """Whether this is ``qgis_process`` (its ``help`` prints the short description above the
    help text; the dialog shows the help text only, the toolbox the short description)."""
    from qgis.core import QgsApplication

    return QgsApplication.platform() == "qgis_process"


class SlipMapAlgorithm(NamedAlgorithm, QgsProcessingAlgorithm):
    """Base of the SlipMap algorithms: no state is kept on ``self`` between runs.

    Gives every algorithm its group's icon, search tags, a one-line description (the job's),
    a help URL (docs/qgis.md, at the algorithm's section) and the ``slipmap`` logger routed
    to the Processing log while it runs.
    """

    _tags = ()
    spec = None  # the job's JobSpec, where the algorithm runs one

    def addParameter(self, definition, createOutput=True):  # noqa: N802, N803 (QGIS API)
        """``QgsProcessingAlgorithm.addParameter``, with every destination optional.

        QGIS 3.22's ``qgis_process`` refuses a run that does not name every mandatory
        destination (a default value does not count), so a destination the user must not be
        made to name (the summary, the matched planes) is declared optional, created by
        default; a run that leaves it out writes it to a temporary file (a memory layer for a
        vector), as the dialog's "[Save to temporary file]" does (:meth:`run_parameters`)."""
        optional = definition.flags() & QgsProcessingParameterDefinition.FlagOptional
        if definition.isDestination() and not optional:
            definition.setFlags(definition.flags() | QgsProcessingParameterDefinition.FlagOptional)
            definition.setCreateByDefault(True)
            self.__dict__.setdefault("_temporary_by_default", set()).add(definition.name())
        return super().addParameter(definition, createOutput)

    def run_parameters(self, parameters):
        """``parameters`` as the algorithm reads them: a destination that must be written
        and was left out (:meth:`addParameter`) is ``TEMPORARY_OUTPUT``, and an enum given
        by the name of its option (``STOCHASTIC_MODEL=full``, as ``qgis_process`` passes it)
        is its index. The one place for both: :meth:`checkParameterValues` and every
        ``processAlgorithm`` (wrapped by ``__init_subclass__``) read through it."""
        from qgis.core import QgsProcessing

        out = dict(parameters)
        for name in self.__dict__.get("_temporary_by_default", ()):
            if not is_set(out, name):
                out[name] = QgsProcessing.TEMPORARY_OUTPUT
        for definition in self.parameterDefinitions():
            name = definition.name()
            if definition.type() == "enum" and name in out:
                out[name] = enum_index(definition, out[name])
        return out

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        own = cls.__dict__.get("processAlgorithm")
        if own is not None and not getattr(own, "_reads_run_parameters", False):
            import functools

            @functools.wraps(own)
            def processAlgorithm(self, parameters, context, feedback):  # noqa: N802
                try:
                    return own(self, self.run_parameters(parameters), context, feedback)
                except BaseException:
                    detach_feedback()  # a failed run has no postProcessAlgorithm
                    raise
                finally:
                    keep_proj_context()  # the run's thread is QGIS's: see compat.py

            processAlgorithm._reads_run_parameters = True
            cls.processAlgorithm = processAlgorithm

    def canExecute(self):  # noqa: N802 (QGIS API name)
        """``(False, "Missing: … <the command>")`` while a package this algorithm needs is
        missing (``compat.needs``): the toolbox then refuses to open it with that text."""
        return can_execute(self._id)

    def icon(self):
        from qgis.PyQt.QtGui import QIcon

        return QIcon(icon_path(GROUP_ICONS.get(self._group_id, "slipmap.svg")))

    def svgIconPath(self):  # noqa: N802 (QGIS API name)
        return icon_path(GROUP_ICONS.get(self._group_id, "slipmap.svg"))

    def tags(self):
        return list(dict.fromkeys(COMMON_TAGS + GROUP_TAGS.get(self._group_id, ()) + self._tags))

    def shortDescription(self):  # noqa: N802 (QGIS API name)
        # the toolbox tooltip and the first line of `qgis_process help`: QGIS 3.22 and 3.40
        # grey nothing out for canExecute(), so a missing package is said here
        ok, message = self.canExecute()
        if not ok:
            return f"Cannot run yet. {message}"
        if _in_qgis_process():  # its help prints this, then the help, which starts with it
            return ""
        if self.spec is not None:
            return self.spec.description.split(". ")[0].rstrip(".") + "."
        return self._name

    def helpUrl(self):  # noqa: N802 (QGIS API name)
        return f"{HELP_URL}#{self._id}"

    def prepareAlgorithm(self, parameters, context, feedback):  # noqa: N802 (QGIS API name)
        ok, message = self.canExecute()
        if not ok:  # processing.run, models and qgis_process reach here without the toolbox
            raise QgsProcessingException(message)
        attach_feedback(feedback)
        watch_cancel(feedback, context)
        return True

    def postProcessAlgorithm(self, context, feedback):  # noqa: N802 (QGIS API name)
        _unmark_cancelled(context)
        _HANDLER.flush_repeats()
        store_sink_styles(self, feedback)
        unique_layer_names(self, context)
        detach_feedback()
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

    def check_options(self, parameters, context):
        """Raise ``QgsProcessingException`` for parameters the job refuses (the dialog's
        words); :meth:`checkParameterValues` calls it after the packages' check."""
        if self.spec is not None:
            self.job_options(parameters, context)

    def checkParameterValues(self, parameters, context):  # noqa: N802 (QGIS API name)
        detach_feedback()  # a check has no feedback: the last run's may be deleted already
        ok, message = self.canExecute()
        if not ok:  # qgis_process: refused at once, with the command that installs them
            return False, message
        parameters = self.run_parameters(parameters)
        try:
            self.check_options(parameters, context)
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
            above = target.parent
            while not above.exists() and above.parent != above:
                above = above.parent
            if above.exists() and not above.is_dir():  # e.g. …/slip.json/out.gpkg
                return (
                    f"{label}: {above} is a file, not a folder, so {target.name} cannot be "
                    "written under it; choose a folder for the file"
                )
            return (
                f"{label}: the folder {target.parent} does not exist; create it or choose "
                "another place for the file"
            )
        suffix = target.suffix.lower()
        if p.type() == "rasterDestination" and suffix and suffix not in GEOTIFF_SUFFIXES:
            return f"{label}: the raster is a GeoTIFF; name the file .tif (not {target.suffix})"
    return None


#: (id of a context, parameter name) -> the raster path resolved for it (see raster_output)
_RESOLVED_RASTERS = {}


def raster_output(alg, parameters, name, context):
    """The path of raster destination ``name`` (None when not asked for), ``.tif`` added
    when the name has no suffix, so that the GeoTIFF written there opens as one.

    Resolved once per run: ``parameterAsOutputLayer`` makes a new temporary file name at each
    call for a temporary output and adds each to the layers QGIS loads when the run ends, so
    the check before the run (``checkParameterValues``, same context in the dialog and in
    qgis_process) and the run itself would leave a second name that is never written ("The
    following layers were not correctly generated"). A path already resolved in this context
    and still waiting to be loaded is given again."""
    from pathlib import Path

    key = (id(context), name)
    cached = _RESOLVED_RASTERS.get(key)
    if cached is not None and cached in context.layersToLoadOnCompletion():
        return cached
    path = alg.parameterAsOutputLayer(parameters, name, context)
    if not path or Path(path).suffix:
        _RESOLVED_RASTERS[key] = path or None
        return path or None
    layers = context.layersToLoadOnCompletion()
    if path in layers:  # load the file that is written, under the name it gets
        layers[path + ".tif"] = layers.pop(path)
        context.setLayersToLoadOnCompletion(layers)
    _RESOLVED_RASTERS[key] = path + ".tif"
    return path + ".tif"


# --------------------------------------------------------------------------- styles

#: post-processors must outlive processAlgorithm (QGIS keeps only a C++ pointer)
_POST_PROCESSORS = []


def style_path(name):
    """Path of a bundled QML style ``styles/<name>.qml`` (None when missing)."""
    from ...styles import style_path as _style_path

    return _style_path(name)


def apply_style_on_load(
    context,
    output,
    style_name,
    symmetric_band=None,
    *,
    scale=1.0,
    unit="",
    ends=None,
    columns=None,
    alg=None,
):
    """Style ``output`` (an output layer path or id) with SlipMap's style ``style_name``.

    * With ``columns`` (the sink's ``{name: (K,) array}``) the style is the template fitted to
      them (:func:`slipmap.app.styles.vector_qml`: symmetric classes, arrow scale, sigma
      flag); with ``alg`` (the running algorithm) that QML is also stored, after the run, as
      the default style in the ``layer_styles`` table of the GeoPackage QGIS wrote the sink
      to (:meth:`SlipMapAlgorithm.postProcessAlgorithm`), so the file opens styled wherever
      it is opened later (``qgis_process`` outputs too).
    * A raster with the ``.qml`` SlipMap wrote beside it is loaded with that file.
    * Otherwise the bundled QML is loaded; with ``symmetric_band`` (a raster band number) the
      pseudocolor ramp is then rescaled to ``±max|value|`` of that band
      (:func:`symmetric_limits`, legend labels in the band's values times ``scale`` with
      ``unit`` and ``ends`` = (name of the low end, of the high end)).

    A raster is drawn below the vectors of its group (:func:`raster_below_vectors`). The
    on-load part does nothing when the output is not loaded on completion (e.g.
    ``processing.run`` from a script) or the style is missing; never fails the algorithm.
    """
    from pathlib import Path

    from qgis.core import QgsProcessingLayerPostProcessorInterface

    qml_text = None
    if columns is not None:
        from ...app.styles import VECTOR_STYLES, vector_qml

        if style_name in VECTOR_STYLES:
            qml_text = vector_qml(VECTOR_STYLES[style_name], columns)
            if alg is not None and output:
                alg.__dict__.setdefault("_sink_styles", []).append((str(output), qml_text))
    qml = style_path(style_name)
    if not output or (qml is None and qml_text is None):
        return
    if not context.willLoadLayerOnCompletion(output):
        return

    class _Style(QgsProcessingLayerPostProcessorInterface):
        def postProcessLayer(self, layer, context, feedback):  # noqa: N802 (QGIS API name)
            if layer is None or not layer.isValid():
                return
            try:
                sidecar = Path(layer.source().split("|")[0]).with_suffix(".qml")
                if qml_text is not None:
                    import_qml(layer, qml_text)
                elif layer.type() == QgsMapLayerType.RasterLayer and sidecar.is_file():
                    layer.loadNamedStyle(str(sidecar))  # SlipMap's style, fitted to the data
                else:
                    layer.loadNamedStyle(qml)
                    if symmetric_band is not None:
                        symmetric_limits(layer, symmetric_band, scale=scale, unit=unit, ends=ends)
                    symmetric_classes(layer)
                raster_below_vectors(layer, context)
                layer.triggerRepaint()
            except Exception as exc:  # noqa: BLE001 - styling must never fail the run
                if feedback is not None:
                    feedback.pushInfo(f"style {style_name} not applied: {exc}")

    from qgis.core import QgsMapLayerType

    post = _Style()
    _POST_PROCESSORS.append(post)
    context.layerToLoadOnCompletionDetails(output).setPostProcessor(post)


def import_qml(layer, qml_text):
    """Apply QML text (QGIS's style format) to ``layer``; raises ValueError when QGIS
    refuses it."""
    from qgis.PyQt.QtXml import QDomDocument

    doc = QDomDocument()
    doc.setContent(qml_text)
    ok, message = layer.importNamedStyle(doc)
    if not ok:
        raise ValueError(message)
    layer.emitStyleChanged()


def gpkg_destination(output):
    """``(GeoPackage path, layer name)`` of a sink's output id when QGIS wrote it to a
    GeoPackage file (None otherwise: memory layers, other formats, databases)."""
    from pathlib import Path

    parts = str(output or "").split("|")
    path = Path(parts[0])
    if path.suffix.lower() != ".gpkg" or not path.is_file():
        return None
    for part in parts[1:]:
        if part.lower().startswith("layername="):
            return str(path), part.split("=", 1)[1]
    from ...core.io.vector import gpkg_layer_names

    names = gpkg_layer_names(path)
    return (str(path), names[0]) if len(names) == 1 else None


def store_sink_styles(alg, feedback=None):
    """Store the styles :func:`apply_style_on_load` collected for ``alg``'s sinks into the
    GeoPackages QGIS wrote (their ``layer_styles`` table; the sinks are closed by now)."""
    from ...core.errors import SlipMapError
    from ...core.io.vector import write_gpkg_styles

    for output, qml_text in alg.__dict__.pop("_sink_styles", []):
        try:
            target = gpkg_destination(output)
            if target is not None:
                write_gpkg_styles(target[0], {target[1]: qml_text})
        except (SlipMapError, OSError) as exc:
            if feedback is not None:
                feedback.pushInfo(f"style not stored in {output}: {exc}")


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
