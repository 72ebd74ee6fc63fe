"""GeoTIFF writer/reader (GDAL). Skipped where osgeo is not installed (the numpy-2 venv)."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("osgeo.gdal")

from slipmap.core.errors import InvalidParameterError  # noqa: E402
from slipmap.core.io.raster import (  # noqa: E402
    band_names,
    raster_metadata,
    read_geotiff,
    write_geotiff,
)

UTM12N = (
    'PROJCS["WGS 84 / UTM zone 12N",GEOGCS["WGS 84",DATUM["WGS_1984",SPHEROID["WGS 84",6378137,'
    '298.257223563]],PRIMEM["Greenwich",0],UNIT["degree",0.0174532925199433]],'
    'PROJECTION["Transverse_Mercator"],PARAMETER["latitude_of_origin",0],'
    'PARAMETER["central_meridian",-111],PARAMETER["scale_factor",0.9996],'
    'PARAMETER["false_easting",500000],PARAMETER["false_northing",0],UNIT["metre",1],'
    'AUTHORITY["EPSG","32612"]]'
)


def test_round_trip_multiband_with_crs_nodata_names_and_metadata(tmp_path):
    rng = np.random.default_rng(0)
    a = rng.random((3, 5, 7))
    a[1, 2, 3] = np.nan
    path = tmp_path / "r.tif"
    out = write_geotiff(
        path,
        a,
        origin_xy=(515_369.0, 4_918_381.0),
        pixel_size_m=0.125,
        crs_wkt=UTM12N,
        band_names=["a", "b", "c"],
        metadata={"SLIPMAP_MAP_PLANE": "xy"},
    )
    assert out == path and path.is_file()
    arr, gt, wkt = read_geotiff(path)
    np.testing.assert_array_equal(arr, a)  # float64 kept exactly, NaN included
    assert gt == (515_369.0, 0.125, 0.0, 4_918_381.0, 0.0, -0.125)
    assert "UTM zone 12N" in wkt
    assert band_names(path) == ["a", "b", "c"]
    assert raster_metadata(path)["SLIPMAP_MAP_PLANE"] == "xy"
    from osgeo import gdal

    ds = gdal.Open(str(path))
    assert np.isnan(ds.GetRasterBand(1).GetNoDataValue())
    ds = None
    assert [p.name for p in tmp_path.iterdir()] == ["r.tif"]  # no temporary left behind


def test_single_band_float32_and_rectangular_pixels(tmp_path):
    a = np.arange(12, dtype=np.float32).reshape(3, 4)
    path = write_geotiff(tmp_path / "s.tif", a, origin_xy=(0.0, 10.0), pixel_size_m=(2.0, 0.5))
    arr, gt, wkt = read_geotiff(path)
    assert arr.dtype == np.float32 and arr.shape == (3, 4)
    np.testing.assert_array_equal(arr, a)
    assert gt == (0.0, 2.0, 0.0, 10.0, 0.0, -0.5)
    assert wkt == ""


def test_integer_array_needs_integer_nodata(tmp_path):
    a = np.ones((2, 2), dtype=np.uint8)
    with pytest.raises(InvalidParameterError, match="NaN nodata"):
        write_geotiff(tmp_path / "u.tif", a, origin_xy=(0, 0), pixel_size_m=1.0)
    write_geotiff(tmp_path / "u.tif", a, origin_xy=(0, 0), pixel_size_m=1.0, nodata=255)
    arr, _, _ = read_geotiff(tmp_path / "u.tif")
    assert arr.dtype == np.uint8 and arr.sum() == 4


def test_bad_arguments_write_nothing(tmp_path):
    path = tmp_path / "bad.tif"
    with pytest.raises(InvalidParameterError, match="pixel_size_m"):
        write_geotiff(path, np.ones((2, 2)), origin_xy=(0, 0), pixel_size_m=0.0)
    with pytest.raises(InvalidParameterError, match="band names"):
        write_geotiff(
            path, np.ones((2, 2, 2)), origin_xy=(0, 0), pixel_size_m=1.0, band_names=["a"]
        )
    with pytest.raises(InvalidParameterError, match="non-empty"):
        write_geotiff(path, np.ones((0, 3)), origin_xy=(0, 0), pixel_size_m=1.0)
    assert list(tmp_path.iterdir()) == []


def test_missing_file_is_a_file_error(tmp_path):
    from slipmap.core.errors import SlipMapFileError

    with pytest.raises(SlipMapFileError, match="does not exist"):
        read_geotiff(tmp_path / "none.tif")


def test_style_sidecar_is_the_qml_qgis_reads_beside_the_raster(tmp_path):
    from slipmap.core.io.raster import band_range, style_sidecar, write_raster_style

    tif = tmp_path / "piv_dz.tif"
    a = np.array([[np.nan, -0.02], [0.05, 0.01]])
    write_geotiff(tif, a, origin_xy=(0.0, 2.0), pixel_size_m=1.0)
    assert style_sidecar(tif) == tmp_path / "piv_dz.qml"
    assert style_sidecar(tmp_path / "a.b.tif") == tmp_path / "a.b.qml"  # QGIS: completeBaseName
    written = write_raster_style(tif, "<qgis/>")
    assert written == tmp_path / "piv_dz.qml" and written.read_text() == "<qgis/>"
    assert band_range(tif) == (-0.02, 0.05)
    write_geotiff(tmp_path / "empty.tif", np.full((2, 2), np.nan), origin_xy=(0, 2), pixel_size_m=1)
    assert all(np.isnan(band_range(tmp_path / "empty.tif")))
