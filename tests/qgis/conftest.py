"""Headless QGIS for the plugin tests: the ``qgis_app`` and ``provider`` fixtures live in
tests/conftest.py (one QgsApplication per process, shared with tests/hostile/)."""
