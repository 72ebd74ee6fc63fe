"""The field algorithms on tiled inputs in QGIS (issue #17): a glob of tiles per epoch gives
the one-file DEM difference and ICP cells; the tiles' size and the Dask scheduler are
advanced parameters; a moving-area layer (a global pre-alignment) is refused for tiles
naming its label, nothing written; a breaklines layer reaches the tiled spline field."""

import numpy as np
import pyproj
import pytest

pytestmark = pytest.mark.qgis

UTM11 = pyproj.CRS.from_epsg(32611)
ORIGIN = np.array([500_000.0, 4_200_000.0, 0.0])


def _ground(rng, n):
    xy = np.c_[rng.uniform(0, 60.0, n), rng.uniform(0, 48.0, n)]
    x, y = xy[:, 0], xy[:, 1]
    z = (
        0.3 * np.sin(2 * np.pi * x / 4.3)
        + 0.25 * np.cos(2 * np.pi * y / 3.7)
        + 0.08 * np.sin(2 * np.pi * x / 1.3) * np.cos(2 * np.pi * y / 1.7)
        + rng.normal(0.0, 0.005, n)
    )
    return np.c_[xy, z]


@pytest.fixture(scope="module")
def epochs(tmp_path_factory):
    """Two samplings of rough ground, the second moved 4 cm east, as one LAS per epoch and as
    17 m / 13 m tiles."""
    root = tmp_path_factory.mktemp("q_tiled_fields")
    rng = np.random.default_rng(5)
    for name, shift, edge in (("before", 0.0, 17.0), ("after", 0.04, 13.0)):
        _write_epoch(root, name, _ground(rng, 43_000) + ORIGIN + [shift, 0.0, 0.0], edge)
    return root


def _write_epoch(root, name, pts, edge):
    """``pts`` as ``root/name.las`` and as tiles of ``edge`` metres in ``root/name_tiles``."""
    from slipmap.core.io.las import PointCloud, write_las

    write_las(root / f"{name}.las", PointCloud(pts, {}, UTM11))
    folder = root / f"{name}_tiles"
    folder.mkdir()
    k = np.floor((pts[:, :2] - pts[:, :2].min(0) + 2.0) / edge).astype(int)
    for key in np.unique(k, axis=0):
        m = np.all(k == key, axis=1)
        write_las(folder / f"t_{key[0]}_{key[1]}.las", PointCloud(pts[m], {}, UTM11))


#: a slab moved beyond a straight scarp (local metres: the ground east of the line)
SCARP = np.array([[27.0, -3.0], [33.0, 51.0]])
SLAB = np.array([0.05, -0.25, -0.06])


@pytest.fixture(scope="module")
def slab(tmp_path_factory):
    """Two samplings of the rough ground, the second with a slab moved beyond SCARP, as one
    LAS per epoch and as 17 m / 13 m tiles."""
    root = tmp_path_factory.mktemp("q_tiled_slab")
    rng = np.random.default_rng(9)
    _write_epoch(root, "before", _ground(rng, 43_000) + ORIGIN, 17.0)
    after = _ground(rng, 43_000)
    (xa, ya), (xb, yb) = SCARP
    east = (xb - xa) * (after[:, 1] - ya) - (yb - ya) * (after[:, 0] - xa) < 0
    _write_epoch(root, "after", after + east[:, None] * SLAB + ORIGIN, 13.0)
    return root


def _run(alg, params):
    import processing
    from qgis.core import QgsProcessingContext, QgsProcessingFeedback

    return processing.run(
        f"slipmap:{alg}", params, context=QgsProcessingContext(), feedback=QgsProcessingFeedback()
    )


@pytest.mark.parametrize("alg", ["demdiff", "piv", "windowedicp"])
def test_tile_size_and_scheduler_are_advanced(provider, alg):
    from qgis.core import QgsApplication, QgsProcessingParameterDefinition

    a = QgsApplication.processingRegistry().algorithmById(f"slipmap:{alg}")
    names = {p.name(): p for p in a.parameterDefinitions()}
    assert "WORKERS" not in names
    for key in ("SCHEDULER", "TILE_SIZE"):
        assert names[key].flags() & QgsProcessingParameterDefinition.FlagAdvanced, key


def test_dem_difference_and_icp_of_tile_folders_equal_one_file(provider, epochs, tmp_path):
    from slipmap.core.io.raster import read_geotiff

    rasters, cells = {}, {}
    for name, b, a in (
        ("file", epochs / "before.las", epochs / "after.las"),
        ("tiles", epochs / "before_tiles" / "t_*.las", epochs / "after_tiles" / "t_*.las"),
    ):
        out = tmp_path / f"{name}_dem.tif"
        _run(
            "demdiff",
            {"BEFORE": str(b), "AFTER": str(a), "GRID": 0.5, "TILE_SIZE": 11.0,
             "OUTPUT": str(out), "SUMMARY": str(tmp_path / f"{name}_dem.json")},
        )  # fmt: skip
        rasters[name] = read_geotiff(out)[0]
        res = _run(
            "windowedicp",
            {"BEFORE": str(b), "AFTER": str(a), "CELL": 6.0, "MIN_POINTS": 50,
             "TILE_SIZE": 12.0, "CELLS": "memory:", "VECTORS": "memory:",
             "SUMMARY": str(tmp_path / f"{name}_icp.json"),
             # the cells for both (the tiled spline field: tests/app/test_tiled_spline.py)
             "FIELD_MODEL": 0},
        )  # fmt: skip
        layer = res["CELLS"]
        if isinstance(layer, str):
            from qgis.core import QgsProcessingUtils, QgsProject

            layer = QgsProject.instance().mapLayer(layer) or QgsProcessingUtils.mapLayerFromString(
                layer, None
            )
        cells[name] = sorted((f["x"], f["y"], f["dx"]) for f in layer.getFeatures())
    f, t = rasters["file"], rasters["tiles"]
    assert np.array_equal(np.isnan(f), np.isnan(t))
    assert np.nanmax(np.abs(f - t)) <= 1e-9
    assert len(cells["tiles"]) == len(cells["file"]) > 40
    got, want = np.array(cells["tiles"]), np.array(cells["file"])
    assert np.max(np.abs(got - want)) <= 1e-9
    assert np.median(want[:, 2]) == pytest.approx(0.04, abs=0.005)


def test_moving_area_layer_refused_for_tiles(provider, epochs, tmp_path):
    from qgis.core import (
        QgsFeature,
        QgsGeometry,
        QgsPointXY,
        QgsProcessingException,
        QgsVectorLayer,
    )

    mask = QgsVectorLayer("Polygon?crs=EPSG:32611", "moving", "memory")
    f = QgsFeature()
    x0, y0 = ORIGIN[0] + 20.0, ORIGIN[1] + 20.0
    ring = [QgsPointXY(x0 + dx, y0 + dy) for dx, dy in ((0, 0), (10, 0), (10, 10), (0, 10))]
    f.setGeometry(QgsGeometry.fromPolygonXY([ring]))
    mask.dataProvider().addFeatures([f])
    with pytest.raises(QgsProcessingException) as e:
        _run(
            "windowedicp",
            {"BEFORE": str(epochs / "before_tiles" / "*.las"),
             "AFTER": str(epochs / "after_tiles" / "*.las"),
             "CELL": 6.0, "STABLE_MASK": mask, "CELLS": "memory:", "VECTORS": "memory:",
             "SUMMARY": str(tmp_path / "icp.json")},
        )  # fmt: skip
    assert "tiled inputs" in str(e.value) and "Moving area" in str(e.value)
    assert list(tmp_path.iterdir()) == []


def _file_and_tiles(root, tmp_path, extra):
    """The windowed ICP (6 m cells and knots, tiles in blocks of 12 m) of ``root``'s one LAS
    per epoch and of its tile globs, with the ``extra`` parameters: each run's icp.json and
    its cells' ``(x, y, dx, dy, sigma_dx, sigma_dy)`` sorted, by "file" and "tiles"."""
    import json

    from qgis.core import QgsVectorLayer

    docs, cells = {}, {}
    for name, b, a in (
        ("file", root / "before.las", root / "after.las"),
        ("tiles", root / "before_tiles" / "t_*.las", root / "after_tiles" / "t_*.las"),
    ):
        summary = tmp_path / f"{name}_icp.json"
        res = _run(
            "windowedicp",
            {"BEFORE": str(b), "AFTER": str(a), "CELL": 6.0, "MIN_POINTS": 50,
             "SPLINE_SPACING": 6.0, "TILE_SIZE": 12.0, **extra,
             "CELLS": str(tmp_path / f"{name}_cells.gpkg"), "VECTORS": "memory:",
             "SUMMARY": str(summary)},
        )  # fmt: skip
        docs[name] = json.loads(summary.read_text())
        layer = QgsVectorLayer(res["CELLS"], "cells", "ogr")
        cells[name] = np.array(sorted((g["x"], g["y"], g["dx"], g["dy"], g["sigma_dx"],
                                       g["sigma_dy"]) for g in layer.getFeatures()))  # fmt: skip
    return docs, cells


def test_breaklines_layer_with_tiles_reaches_the_tiled_spline_field(provider, epochs, tmp_path):
    """A BREAKLINES line layer with tile globs (refused before stop 39): the default spline
    field of the tiles takes the line, as the one-file run does (the same cells within
    1e-6 m), and the summary says the line was given."""

    from qgis.core import QgsFeature, QgsGeometry, QgsPointXY, QgsVectorLayer

    line = QgsVectorLayer("LineString?crs=EPSG:32611", "scarp", "memory")
    f = QgsFeature()
    x0, y0 = ORIGIN[0], ORIGIN[1]
    f.setGeometry(QgsGeometry.fromPolylineXY([QgsPointXY(x0 + 27.0, y0 - 3.0),
                                              QgsPointXY(x0 + 33.0, y0 + 51.0)]))  # fmt: skip
    line.dataProvider().addFeatures([f])
    docs, cells = _file_and_tiles(epochs, tmp_path, {"BREAKLINES": line})
    for name, doc in docs.items():
        assert doc["model"]["field"] == "spline", name
        assert doc["breaklines"]["source"] == "given" and doc["breaklines"]["count"] == 1, name
    assert len(cells["tiles"]) == len(cells["file"]) > 40
    assert np.max(np.abs(cells["tiles"] - cells["file"])) <= 1e-6


def test_breaklines_detected_on_tiles_as_in_one_file(provider, slab, tmp_path):
    """The default windowed ICP of tile globs with no breaklines layer: the scarp is detected
    on the tiles as in the one file (the same cells within 1e-6 m, the same number and length
    of lines) and the summary says it was detected."""
    docs, cells = _file_and_tiles(slab, tmp_path, {})
    found = {}
    for name, doc in docs.items():
        assert doc["breaklines"]["source"] == "detected", (name, doc["breaklines"])
        found[name] = (doc["breaklines"]["count"], doc["breaklines"]["length_m"])
    assert found["tiles"][0] == found["file"][0] >= 1
    assert found["tiles"][1] == pytest.approx(found["file"][1], abs=1e-3)
    assert len(cells["tiles"]) == len(cells["file"]) > 40
    assert np.max(np.abs(cells["tiles"] - cells["file"])) <= 1e-6
