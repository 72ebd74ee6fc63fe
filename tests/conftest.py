"""Test-wide settings: reproducible, deadline-free property tests (CI machines are slow); the
OpenCL tests skip, with the reason, when the OpenCL runtime cannot start."""

import logging
import os
import sys

import pytest
from hypothesis import HealthCheck, settings

settings.register_profile(
    "slipmap",
    derandomize=True,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow],
)
settings.load_profile("slipmap")


@pytest.fixture
def drop_cli_log_handlers():
    """main() points the "slipmap" logger at the stderr of its test; drop that handler before
    and after (CLI tests: ``pytestmark = pytest.mark.usefixtures("drop_cli_log_handlers")``)."""
    logging.getLogger("slipmap").handlers.clear()
    yield
    logging.getLogger("slipmap").handlers.clear()


def pytest_collection_modifyitems(config, items):
    """Skip the ``opencl`` tests when the runtime cannot start. Some drivers abort the process
    rather than raise (PoCL in a root without /sys), which would end the whole run, so the
    runtime is first tried in a child process (once, only when an OpenCL test is collected)."""
    opencl = [item for item in items if item.get_closest_marker("opencl")]
    if not opencl:
        return
    from slipmap.core.opencl.backend import probe_runtime

    reason = probe_runtime()
    if reason is not None:
        skip = pytest.mark.skip(reason=f"the OpenCL runtime cannot start: {reason}")
        for item in opencl:
            item.add_marker(skip)


# ---------------------------------------------------------------- headless QGIS (one per process)


@pytest.fixture(scope="session")
def qgis_app():
    os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
    pytest.importorskip("qgis.core", reason="QGIS Python bindings (python3-qgis) missing")
    from qgis.core import QgsApplication

    app = QgsApplication([], False)
    app.initQgis()
    plugins = "/usr/share/qgis/python/plugins"
    if plugins not in sys.path:
        sys.path.append(plugins)
    from processing.core.Processing import Processing

    Processing.initialize()
    yield app


@pytest.fixture(scope="module")
def provider(qgis_app):
    """The SlipMap provider registered in Processing (the plugin as QGIS loads it), for one
    test module."""
    import slipmap

    plugin = slipmap.classFactory(None)
    plugin.initProcessing()
    yield
    plugin.unload()


def _write_line(path, xy, crs, *, driver="GPKG", layer="fault"):
    """A one-line vector file (a fault trace, a breakline) through OGR, as users make them."""
    from osgeo import ogr, osr

    ds = ogr.GetDriverByName(driver).CreateDataSource(str(path))
    srs = osr.SpatialReference()
    srs.ImportFromWkt(crs.to_wkt())
    out = ds.CreateLayer(layer, srs, ogr.wkbLineString)
    line = ogr.Geometry(ogr.wkbLineString)
    for x, y in xy:
        line.AddPoint_2D(float(x), float(y))
    f = ogr.Feature(out.GetLayerDefn())
    f.SetGeometry(line)
    out.CreateFeature(f)
    ds = None


@pytest.fixture(scope="session")
def line_file():
    """``line_file(path, xy, crs, driver="GPKG", layer="fault")`` writes a one-line vector
    file through OGR (skips without GDAL)."""
    pytest.importorskip("osgeo.ogr", reason="GDAL/OGR (python3-gdal) missing")
    return _write_line
