"""The stand-in for an algorithm whose module cannot be imported (see ``provider.py``)."""

from __future__ import annotations

from qgis.core import QgsProcessingAlgorithm, QgsProcessingException

from .. import compat
from ._named import NamedAlgorithm


def _reason(exc) -> str:
    """What the user must do about import error ``exc``: the install command for a missing
    package, else the error (a bug: reported with the log's details)."""
    name = getattr(exc, "name", None)
    own = __name__.split(".")[0]  # a module of SlipMap itself that is missing is a bug
    if isinstance(exc, ModuleNotFoundError) and name and name.split(".")[0] != own:
        package = name.split(".")[0]
        missing = [m for m in compat.PACKAGES if m == package or m in compat.missing_packages()]
        return compat.missing_message(missing or [package])
    return (
        f"This algorithm could not be loaded ({type(exc).__name__}: {exc}); see the SlipMap "
        "tab of the Log Messages panel and report it."
    )


class StandInAlgorithm(NamedAlgorithm, QgsProcessingAlgorithm):
    """Listed like the algorithm it stands for; ``canExecute()`` is False with the reason, and
    a run (``qgis_process``, ``processing.run``) refuses with it."""

    _id = _name = _group = _group_id = _reason_text = ""

    @classmethod
    def make(cls, alg_id, display, group, group_id, exc):
        sub = type(
            f"StandIn_{alg_id}",
            (cls,),
            {
                "_id": alg_id,
                "_name": display,
                "_group": group,
                "_group_id": group_id,
                "_reason_text": _reason(exc),
            },
        )
        return sub()

    def shortDescription(self):  # noqa: N802 (QGIS API name)
        return f"Cannot run yet. {self._reason_text}"

    def shortHelpString(self):  # noqa: N802 (QGIS API name)
        return self.shortDescription()

    def canExecute(self):  # noqa: N802 (QGIS API name)
        return False, self._reason_text

    def initAlgorithm(self, config=None):  # noqa: N802 (QGIS API name)
        pass

    def checkParameterValues(self, parameters, context):  # noqa: N802 (QGIS API name)
        return False, self._reason_text

    def prepareAlgorithm(self, parameters, context, feedback):  # noqa: N802 (QGIS API name)
        raise QgsProcessingException(self._reason_text)

    def processAlgorithm(self, parameters, context, feedback):  # noqa: N802 (QGIS API name)
        raise QgsProcessingException(self._reason_text)
