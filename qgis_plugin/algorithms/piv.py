"""``slipmap:piv``: the PIV job (:mod:`slipmap.app.piv`) as a Processing algorithm."""

from __future__ import annotations

from qgis.core import (
    QgsProcessing,
    QgsProcessingException,
    QgsProcessingParameterFeatureSink,
    QgsProcessingParameterFeatureSource,
    QgsProcessingParameterFileDestination,
    QgsProcessingParameterRasterDestination,
)

from ...app import piv as job
from ._base import (
    SlipMapAlgorithm,
    add_parameters,
    is_set,
    source_parts,
)
from ._fields import (
    FIELDS_GROUP,
    add_optional_file_output,
    apply_diverging_style_on_load,
    apply_style_on_load,
    file_outputs,
    help_text,
    qgs_crs,
    write_point_sink,
)

_FILES = ("dx", "dy", "dz", "summary", "plot")


class PIVAlgorithm(SlipMapAlgorithm):
    _id = "piv"
    _name = "Displacement field (PIV)"
    _group, _group_id = FIELDS_GROUP
    spec = job.SPEC

    def shortHelpString(self):  # noqa: N802 (QGIS API name)
        return help_text(
            job.SPEC,
            "vectors (points at the window centres, in the point cloud's CRS, with x, y, dx, "
            "dy, dz (m, east/north/up), snr (NULL: no second peak), valid (0 = missing or "
            "replaced outlier), magnitude (horizontal, m) and azimuth_deg (clockwise from "
            "north)); dx, dy and dz GeoTIFFs (one pixel per vector); a JSON summary; "
            "optionally a figure (PNG). Breaklines (an optional line layer of scarps, faults "
            "or slab edges, in any CRS) keep the field from being smoothed across them; the "
            "vectors whose window a line crosses have near_break = 1.",
        )

    def initAlgorithm(self, config=None):  # noqa: N802 (QGIS API name)
        add_parameters(self, job.SPEC, roles=("input",))
        lines = QgsProcessingParameterFeatureSource(
            "BREAKLINES",
            job.SPEC["breaklines"].dialog_label,
            [QgsProcessing.TypeVectorLine],
            optional=True,
        )
        lines.setHelp(job.SPEC["breaklines"].help)
        self.addParameter(lines)
        add_parameters(self, job.SPEC, roles=("setting",))
        self.addParameter(
            QgsProcessingParameterFeatureSink(
                "VECTORS", "PIV vectors", QgsProcessing.TypeVectorPoint
            )
        )
        for key in ("dx", "dy", "dz"):
            opt = job.SPEC[key]
            self.addParameter(
                QgsProcessingParameterRasterDestination(opt.name_in("qgis"), opt.dialog_label)
            )
        opt = job.SPEC["summary"]
        self.addParameter(
            QgsProcessingParameterFileDestination("SUMMARY", opt.dialog_label, opt.file_filter)
        )
        add_optional_file_output(self, job.SPEC, "plot")

    def processAlgorithm(self, parameters, context, feedback):  # noqa: N802 (QGIS API name)
        opts = self.job_options(parameters, context)
        outputs = file_outputs(self, parameters, context, job.SPEC, _FILES)
        result = self.run_job(
            job, opts, outputs, feedback, breaklines=self._breaklines(parameters, context)
        )
        cols = result.data["columns"]
        sink_id = write_point_sink(
            self,
            parameters,
            "VECTORS",
            context,
            qgs_crs(result.data["crs"]),
            cols["x"],
            cols["y"],
            cols,
        )
        if sink_id is not None:
            apply_style_on_load(context, sink_id, "piv_vectors", columns=cols, alg=self)
        for key in ("dx", "dy", "dz"):
            apply_diverging_style_on_load(context, outputs[key])
        return {
            "VECTORS": sink_id,
            "DX": outputs["dx"],
            "DY": outputs["dy"],
            "DZ": outputs["dz"],
            "SUMMARY": outputs["summary"],
            "PLOT": outputs["plot"],
        }

    def _breaklines(self, parameters, context):
        """``f(crs)`` -> the BREAKLINES layer's line parts in ``crs`` (the job's ``breaklines``
        for a face's layer, read as Fault slip reads its trace); None when none is given."""
        if not is_set(parameters, "BREAKLINES", context):
            return None
        source = self.parameterAsSource(parameters, "BREAKLINES", context)
        label = f'"{job.SPEC["breaklines"].dialog_label}"'
        if source is None:
            raise QgsProcessingException(f"{label}: the layer cannot be read")

        def parts(crs):
            return source_parts(source, qgs_crs(crs), context, parameter=label, polygons=False)

        return parts
