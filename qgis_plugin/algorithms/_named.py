"""The identity every SlipMap algorithm (and a stand-in for one) shows QGIS, from four class
attributes: ``_id``, ``_name``, ``_group``, ``_group_id``. Imports nothing but itself, so the
stand-in of an algorithm whose module fails to import can use it too."""

from __future__ import annotations


class NamedAlgorithm:
    """Mixin for a ``QgsProcessingAlgorithm``: ``name``, ``displayName``, ``group``,
    ``groupId`` and ``createInstance`` from the class."""

    _id = ""
    _name = ""
    _group = ""
    _group_id = ""

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
