"""Vector I/O (OGR): fault traces in, GeoPackage layers out. Skipped without osgeo."""

from __future__ import annotations

import logging

import numpy as np
import pytest

ogr = pytest.importorskip("osgeo.ogr")
osr = pytest.importorskip("osgeo.osr")

import pyproj  # noqa: E402

from slipmap.core.errors import InputDataError, SlipMapFileError  # noqa: E402
from slipmap.core.fault import FaultTrace  # noqa: E402
from slipmap.core.io.vector import (  # noqa: E402
    VectorLayer,
    read_fault_trace,
    read_gpkg_layer,
    read_polygons,
    write_gpkg_layers,
)

ogr.UseExceptions()
osr.UseExceptions()

LONLAT = [(-122.50, 37.70), (-122.49, 37.75, 12.0), (-122.47, 37.80)]


def _write(path, driver, features, *, epsg=4326, gtype=None):
    """Write features (lists of WKT) with OGR; coordinates in x=lon/easting order."""
    drv = ogr.GetDriverByName(driver)
    ds = drv.CreateDataSource(str(path))
    srs = None
    if epsg is not None:
        srs = osr.SpatialReference()
        srs.ImportFromEPSG(epsg)
        srs.SetAxisMappingStrategy(osr.OAMS_TRADITIONAL_GIS_ORDER)
    lyr = ds.CreateLayer("trace", srs, gtype if gtype is not None else ogr.wkbUnknown)
    for wkt in features:
        f = ogr.Feature(lyr.GetLayerDefn())
        f.SetGeometry(ogr.CreateGeometryFromWkt(wkt))
        lyr.CreateFeature(f)
    ds = None  # noqa: F841


def _linestring_wkt(coords):
    return (
        "LINESTRING Z ("
        + ", ".join(f"{c[0]} {c[1]} {c[2] if len(c) > 2 else 0}" for c in coords)
        + ")"
    )


@pytest.mark.parametrize(("driver", "name"), [("GeoJSON", "t.geojson"), ("GPKG", "t.gpkg")])
def test_geographic_trace_is_reprojected_to_utm(tmp_path, driver, name):
    path = tmp_path / name
    _write(path, driver, [_linestring_wkt(LONLAT)])
    for target in (32610, "EPSG:32610", pyproj.CRS.from_epsg(32610)):
        tr = read_fault_trace(path, target_crs=target)
        assert isinstance(tr, FaultTrace)
        assert len(tr.parts) == 1 and tr.parts[0].shape == (3, 2)
        tf = pyproj.Transformer.from_crs(4326, 32610, always_xy=True)
        for (lon, lat, *_), (x, y) in zip(LONLAT, tr.parts[0]):
            ex, ey = tf.transform(lon, lat)
            assert abs(x - ex) < 1e-3 and abs(y - ey) < 1e-3
        assert 500_000 < tr.parts[0][0, 0] < 600_000  # easting, not latitude first


def test_geographic_trace_without_target_is_refused(tmp_path):
    path = tmp_path / "t.geojson"
    _write(path, "GeoJSON", [_linestring_wkt(LONLAT)])
    with pytest.raises(InputDataError, match="geographic"):
        read_fault_trace(path)


def test_shapefile_multilinestring_parts_in_file_order(tmp_path):
    path = tmp_path / "trace.shp"
    _write(
        path,
        "ESRI Shapefile",
        [
            "MULTILINESTRING ((500000 4100000, 500010 4100100), (500020 4100120, 500030 4100200))",
            "LINESTRING (500040 4100210, 500050 4100300)",
        ],
        epsg=32610,
        gtype=ogr.wkbMultiLineString,
    )
    tr = read_fault_trace(path, target_crs=32610)
    assert len(tr.parts) == 3
    np.testing.assert_allclose(tr.parts[0], [[500000, 4100000], [500010, 4100100]])
    np.testing.assert_allclose(tr.parts[2], [[500040, 4100210], [500050, 4100300]])
    # same CRS, no target: coordinates unchanged
    tr2 = read_fault_trace(path)
    np.testing.assert_allclose(tr2.vertices, tr.vertices)


def test_file_without_crs_warns_and_assumes_target(tmp_path, caplog):
    path = tmp_path / "nocrs.gpkg"
    _write(path, "GPKG", ["LINESTRING (10 20, 30 40)"], epsg=None)
    with caplog.at_level(logging.WARNING, logger="slipmap.core.io.vector"):
        tr = read_fault_trace(path, target_crs=32610)
    assert "has no CRS" in caplog.text
    np.testing.assert_allclose(tr.parts[0], [[10, 20], [30, 40]])


@pytest.mark.parametrize(
    ("wkt", "kind"),
    [
        ("POLYGON ((0 0, 10 0, 10 10, 0 0))", "POLYGON"),
        ("POINT (1 2)", "POINT"),
    ],
)
def test_non_line_geometry_is_refused(tmp_path, wkt, kind):
    path = tmp_path / "bad.geojson"
    _write(path, "GeoJSON", [wkt])
    with pytest.raises(InputDataError, match=rf"{kind}.*bad\.geojson|bad\.geojson.*{kind}"):
        read_fault_trace(path, target_crs=32610)


def test_degenerate_line_and_missing_or_unreadable_file(tmp_path):
    path = tmp_path / "deg.geojson"
    _write(path, "GeoJSON", ["LINESTRING (1 1, 1 1)"], epsg=32610)
    with pytest.raises(InputDataError, match="2 distinct vertices"):
        read_fault_trace(path)
    with pytest.raises(SlipMapFileError, match="does not exist"):
        read_fault_trace(tmp_path / "missing.gpkg")
    junk = tmp_path / "junk.gpkg"
    junk.write_text("not a geopackage")
    with pytest.raises(SlipMapFileError):
        read_fault_trace(junk)
    with pytest.raises(SlipMapFileError):
        read_gpkg_layer(tmp_path / "missing.gpkg", "x")


def test_write_gpkg_layers_round_trip_with_crs_and_atomic(tmp_path):
    tiles = VectorLayer(
        "tiles",
        "Polygon",
        [
            np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]]),
            np.array([[10.0, 0.0], [20.0, 0.0], [20.0, 10.0], [10.0, 10.0], [10.0, 0.0]]),
        ],
        {
            "slip_m": np.array([0.25, np.nan]),
            "n_planes": np.array([12, 3]),
            "side": np.array(["left", "right"]),
            "converged": np.array([True, False]),
        },
    )
    planes = VectorLayer(
        "planes",
        "Point",
        [np.array([1.0, 2.0, 3.0]), np.array([4.0, 5.0, 6.0]), np.array([7.0, 8.0, 9.0])],
        {"sigma_m": np.array([0.01, 0.02, 0.03])},
    )
    trace = VectorLayer("trace", "LineString", [np.array([[5.0, -5.0], [5.0, 15.0]])])
    out = tmp_path / "result.gpkg"
    out.write_bytes(b"old")  # replaced
    got = write_gpkg_layers(out, [tiles, planes, trace], crs="EPSG:32610")
    assert got == out
    assert sorted(p.name for p in tmp_path.iterdir()) == ["result.gpkg"]  # no temp files

    geoms, fields = read_gpkg_layer(out, "tiles")
    assert len(geoms) == 2
    np.testing.assert_allclose(geoms[0][:-1, :2], tiles.geometries[0])
    np.testing.assert_allclose(geoms[0][-1], geoms[0][0])  # closed ring
    np.testing.assert_allclose(geoms[1][:, :2], tiles.geometries[1])
    assert fields["slip_m"][0] == 0.25 and np.isnan(fields["slip_m"][1])
    assert fields["n_planes"].dtype == np.int64
    np.testing.assert_array_equal(fields["n_planes"], [12, 3])
    assert list(fields["side"]) == ["left", "right"]
    np.testing.assert_array_equal(fields["converged"], [True, False])

    geoms, fields = read_gpkg_layer(out, "planes")
    np.testing.assert_allclose(np.stack(geoms), np.stack(planes.geometries))
    np.testing.assert_allclose(fields["sigma_m"], [0.01, 0.02, 0.03])

    geoms, fields = read_gpkg_layer(out, "trace")
    np.testing.assert_allclose(geoms[0], trace.geometries[0])
    assert fields == {}

    ds = ogr.Open(str(out))
    assert ds.GetLayerCount() == 3
    for i in range(3):
        srs = ds.GetLayer(i).GetSpatialRef()
        assert srs is not None and srs.GetAuthorityCode(None) == "32610"
    types = {ds.GetLayer(i).GetName(): ds.GetLayer(i).GetGeomType() for i in range(3)}
    assert ogr.GT_Flatten(types["tiles"]) == ogr.wkbPolygon
    assert types["planes"] == ogr.wkbPoint25D
    assert types["trace"] == ogr.wkbLineString
    ds = None

    # the trace layer of our own output reads back as a fault trace
    tr = read_fault_trace(out, layer="trace", target_crs=32610)
    np.testing.assert_allclose(tr.parts[0], trace.geometries[0])


def test_failed_write_leaves_no_file(tmp_path):
    bad = VectorLayer("x", "Point", [np.array([1.0, 2.0])], {"a": np.array([1.0, 2.0])})
    with pytest.raises(Exception, match="field 'a'"):
        write_gpkg_layers(tmp_path / "o.gpkg", [bad])
    assert list(tmp_path.iterdir()) == []


def test_read_polygons_reprojects_rings_and_refuses_lines(tmp_path):
    utm = pyproj.CRS.from_epsg(32610)
    to_geo = pyproj.Transformer.from_crs(utm, "EPSG:4326", always_xy=True)
    ring = np.array([[550000.0, 4180000.0], [550100.0, 4180000.0], [550100.0, 4180080.0]])
    lon, lat = to_geo.transform(ring[:, 0], ring[:, 1])
    # float(): under numpy 2 the repr of a numpy scalar is "np.float64(...)", not a number
    poly = "POLYGON ((" + ", ".join(f"{float(a)!r} {float(b)!r}" for a, b in zip(lon, lat))
    poly += f", {float(lon[0])!r} {float(lat[0])!r}))"
    multi = "MULTIPOLYGON (((0 0, 1 0, 1 1, 0 0)), ((5 5, 6 5, 6 6, 5 5)))"
    _write(tmp_path / "m.gpkg", "GPKG", [poly])
    rings = read_polygons(tmp_path / "m.gpkg", target_crs=utm)
    assert len(rings) == 1
    np.testing.assert_allclose(rings[0][:3], ring, atol=1e-4)
    _write(tmp_path / "mm.gpkg", "GPKG", [multi], epsg=32610)
    assert len(read_polygons(tmp_path / "mm.gpkg")) == 2
    _write(tmp_path / "l.geojson", "GeoJSON", [_linestring_wkt(LONLAT)])
    with pytest.raises(InputDataError, match="Polygon"):
        read_polygons(tmp_path / "l.geojson", target_crs=utm)
    with pytest.raises(SlipMapFileError, match="polygon file"):
        read_polygons(tmp_path / "none.gpkg")


# --------------------------------------------------------------------------- default styles

#: the columns of QGIS's ``layer_styles`` table (its OGR provider's schema)
QGIS_STYLE_COLUMNS = [
    "id",
    "f_table_catalog",
    "f_table_schema",
    "f_table_name",
    "f_geometry_column",
    "styleName",
    "styleQML",
    "styleSLD",
    "useAsDefault",
    "description",
    "owner",
    "ui",
    "update_time",
]


def _style_rows(path):
    import sqlite3

    with sqlite3.connect(path) as db:
        columns = [r[1] for r in db.execute("PRAGMA table_info(layer_styles)")]
        rows = db.execute(
            "SELECT f_table_catalog, f_table_schema, f_table_name, f_geometry_column, styleName,"
            " styleQML, useAsDefault FROM layer_styles ORDER BY f_table_name, id"
        ).fetchall()
        registered = db.execute(
            "SELECT data_type FROM gpkg_contents WHERE table_name = 'layer_styles'"
        ).fetchall()
    return columns, rows, registered


def test_layers_carry_their_default_style(tmp_path):
    path = tmp_path / "out.gpkg"
    layers = [
        VectorLayer("tiles", "Polygon", [np.array([[0, 0], [1, 0], [1, 1]])], {"v": np.ones(1)}),
        VectorLayer("strips", "Point", [np.array([0.5, 0.5])], {"v": np.ones(1)}),
    ]
    write_gpkg_layers(path, layers, crs=32612, styles={"tiles": "<qgis>T</qgis>"})
    columns, rows, registered = _style_rows(path)
    assert columns == QGIS_STYLE_COLUMNS
    assert registered == [("attributes",)]  # a table GDAL and QGIS list as such
    # empty catalog/schema (not NULL: QGIS's lookup compares with ''), GDAL's geometry column
    assert rows == [("", "", "tiles", "geom", "SlipMap", "<qgis>T</qgis>", 1)]
    assert [p.name for p in tmp_path.iterdir()] == ["out.gpkg"]  # nothing left beside it


def test_write_gpkg_styles_replaces_its_row_and_keeps_one_default(tmp_path):
    import sqlite3

    from slipmap.core.errors import InvalidParameterError
    from slipmap.core.io.vector import gpkg_layer_names, write_gpkg_styles

    path = tmp_path / "out.gpkg"
    layers = [VectorLayer("cells", "Point", [np.array([0.0, 0.0])], {"v": np.ones(1)})]
    write_gpkg_layers(path, layers, crs=32612)
    with sqlite3.connect(path) as db:  # no styles asked for: no table
        assert not db.execute(
            "SELECT name FROM sqlite_master WHERE name = 'layer_styles'"
        ).fetchall()
    write_gpkg_styles(path, {"cells": "<qgis>1</qgis>"}, style_name="user")
    write_gpkg_styles(path, {"cells": "<qgis>2</qgis>"})
    write_gpkg_styles(path, {"cells": "<qgis>3</qgis>"})
    rows = _style_rows(path)[1]
    assert [(r[4], r[5], r[6]) for r in rows] == [
        ("user", "<qgis>1</qgis>", 0),  # another style stays, no longer the default
        ("SlipMap", "<qgis>3</qgis>", 1),  # SlipMap's row replaced, not added again
    ]
    assert gpkg_layer_names(path) == ["cells"]
    with pytest.raises(InvalidParameterError, match="no layer 'tiles'"):
        write_gpkg_styles(path, {"tiles": "<qgis/>"})
