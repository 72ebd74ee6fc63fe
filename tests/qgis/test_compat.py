"""QGIS API helpers: the same results on QGIS 3.22 and 3.40, no deprecation warning (issue #20)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

pytestmark = pytest.mark.qgis


@pytest.fixture
def raster(qgis_app, tmp_path):
    gdal = pytest.importorskip("osgeo.gdal")
    from qgis.core import QgsRasterLayer

    path = str(tmp_path / "r.tif")
    ds = gdal.GetDriverByName("GTiff").Create(path, 4, 3, 2, gdal.GDT_Float32)
    ds.GetRasterBand(1).WriteArray(np.arange(12, dtype=np.float32).reshape(3, 4) - 5.0)
    ds.GetRasterBand(2).WriteArray(np.full((3, 4), 7.0, dtype=np.float32))
    ds = None
    layer = QgsRasterLayer(path, "r")
    assert layer.isValid()
    return layer


def test_make_field_types(qgis_app):
    from qgis.core import QgsField
    from qgis.PyQt.QtCore import QVariant

    from slipmap.qgis_plugin.compat import make_field

    with warnings.catch_warnings():
        warnings.simplefilter("error", DeprecationWarning)
        for kind, qvariant in [
            ("double", QVariant.Double),
            ("int", QVariant.Int),
            ("longlong", QVariant.LongLong),
            ("string", QVariant.String),
            ("bool", QVariant.Bool),
        ]:
            for given in (kind, qvariant):
                field = make_field("f", given)
                assert isinstance(field, QgsField) and field.name() == "f"
                assert int(field.type()) == int(qvariant)


def test_band_statistics_and_renderer_band(raster):
    from qgis.core import QgsSingleBandPseudoColorRenderer

    from slipmap.qgis_plugin.compat import band_statistics, renderer_band, set_renderer_band

    with warnings.catch_warnings():
        warnings.simplefilter("error", DeprecationWarning)
        stats = band_statistics(raster.dataProvider(), 1, ("Min", "Max"))
        assert (stats.minimumValue, stats.maximumValue) == (-5.0, 6.0)
        stats = band_statistics(raster.dataProvider(), 2, ("Min", "Max", "Mean"))
        assert (stats.minimumValue, stats.maximumValue, stats.mean) == (7.0, 7.0, 7.0)
        renderer = QgsSingleBandPseudoColorRenderer(raster.dataProvider(), 1)
        assert renderer_band(renderer) == 1
        set_renderer_band(renderer, 2)
        assert renderer_band(renderer) == 2
