"""``slipmap:piv``, ``windowedicp``, ``demdiff``, ``strain`` give the core's fields through
``processing.run``; the bundled QML styles load on matching layers."""

import json
from pathlib import Path

import numpy as np
import pyproj
import pytest
from qgis_scenes import column as _col
from qgis_scenes import features as _features
from qgis_scenes import rough_surface

import slipmap
from slipmap.app.icp import DEFAULT_MAX_POINTS_PER_CELL

pytestmark = pytest.mark.qgis

UTM12 = pyproj.CRS.from_epsg(32612)
X0, Y0, SIDE = 512000.0, 4300000.0, 24.0
SHIFT = (0.40, -0.30, 0.05)  # true motion before -> after (m): east, north, up
IDS = ("piv", "windowedicp", "demdiff", "strain")
STYLES = Path(slipmap.__file__).resolve().parent / "styles"
ICP_FIELDS = (
    "x",
    "y",
    "z",
    "dx",
    "dy",
    "dz",
    "sigma_dx",
    "sigma_dy",
    "sigma_dz",
    "rmse",
    "n",
    "magnitude",
    "azimuth_deg",
)


@pytest.fixture(scope="module")
def epochs(tmp_path_factory):
    """Two independent samplings (64 pts/m2) of one surface, the second moved by SHIFT."""
    from slipmap.core.io.las import PointCloud, read_las, write_las

    d = tmp_path_factory.mktemp("fields_epochs")
    rng = np.random.default_rng(5)
    n = int(64 * SIDE * SIDE)
    paths = {}
    for name, (sx, sy, sz) in (("before", (0.0, 0.0, 0.0)), ("after", SHIFT)):
        xy = rng.uniform(0, SIDE, size=(n, 2)) + [X0, Y0]
        z = rough_surface(xy - [sx, sy], (X0, Y0)) + sz
        p = d / f"{name}.las"
        write_las(p, PointCloud(xyz=np.column_stack([xy, z]), crs=UTM12))
        paths[name] = p
    clouds = {k: read_las(p).xyz for k, p in paths.items()}  # quantised, as the algorithms see
    return paths, clouds


def _run(alg_id, params, **kw):
    import processing

    return processing.run(f"slipmap:{alg_id}", params, **kw)


def _raster(path):
    from qgis.core import QgsRasterLayer

    from slipmap.core.io.raster import read_geotiff

    layer = QgsRasterLayer(str(path), "r")
    assert layer.isValid(), path
    arr, gt, _ = read_geotiff(path)
    return layer, np.asarray(arr, dtype=np.float64), gt


def _feedback(cancel_after=None):
    from qgis.core import QgsProcessingFeedback

    class Feedback(QgsProcessingFeedback):
        def __init__(self):
            super().__init__()
            self.calls = 0
            self.errors = []

        def setProgress(self, value):  # noqa: N802
            self.calls += 1
            super().setProgress(value)

        def isCanceled(self):  # noqa: N802
            return cancel_after is not None and self.calls >= cancel_after

        def reportError(self, error, fatalError=False):  # noqa: N802, N803
            self.errors.append(error)
            super().reportError(error, fatalError)

    return Feedback()


# --------------------------------------------------------------------------- registration


def test_algorithms_registered_with_help(provider):
    from qgis.core import QgsApplication

    reg = QgsApplication.processingRegistry()
    for alg_id in IDS:
        alg = reg.algorithmById(f"slipmap:{alg_id}")
        assert alg is not None, alg_id
        assert alg.groupId() == "fields" and alg.group() == "Displacement fields"
        help_text = alg.shortHelpString()
        assert len(help_text) > 300, alg_id
        assert "Aryal" in help_text, alg_id
        for p in alg.parameterDefinitions():
            if not p.isDestination():
                assert p.description(), (alg_id, p.name())
        assert alg.canExecute()[0]
    assert "Chen" in reg.algorithmById("slipmap:windowedicp").shortHelpString()


# --------------------------------------------------------------------------- piv


@pytest.fixture(scope="module")
def piv_run(provider, epochs, tmp_path_factory):
    from slipmap.core.io.table import write_csv_columns

    paths, _ = epochs
    d = tmp_path_factory.mktemp("piv")
    cxy = np.array([[X0 + 8.0, Y0 + 8.0], [X0 + 12.0, Y0 + 14.0], [X0 + 15.0, Y0 + 10.0]])
    write_csv_columns(
        d / "control.csv",
        {"x": cxy[:, 0], "y": cxy[:, 1], "dx": [SHIFT[0]] * 3, "dy": [SHIFT[1]] * 3},
    )
    res = _run(
        "piv",
        {
            "BEFORE": str(paths["before"]),
            "AFTER": str(paths["after"]),
            "GRID": 0.25,
            "WINDOWS": "32 16",
            "OVERLAP": 0.5,
            "MAX_DISPLACEMENT": 1.0,
            "CONTROL": str(d / "control.csv"),
            "VECTORS": str(d / "vectors.gpkg"),
            "DX": str(d / "dx.tif"),
            "DY": str(d / "dy.tif"),
            "DZ": str(d / "dz.tif"),
            "SUMMARY": str(d / "piv.json"),
        },
    )
    return res, d, (cxy, np.array([SHIFT[:2]] * 3))


def test_piv_equals_core_and_finds_the_shift(piv_run, epochs):
    from slipmap.core.dem import common_grid, grid_elevation
    from slipmap.core.piv import piv

    res, d, _ = piv_run
    _, clouds = epochs
    grid = common_grid(clouds["before"], clouds["after"], cell_m=0.25)
    ref = piv(
        grid_elevation(clouds["before"], grid=grid),
        grid_elevation(clouds["after"], grid=grid),
        grid=grid,
        windows_px=(32, 16),
        overlap=0.5,
        expected_max_displacement_m=1.0,
    )
    layer, names, rows = _features(res["VECTORS"])
    assert layer.crs().authid() == "EPSG:32612"
    for name in ("dx", "dy", "dz", "magnitude", "azimuth_deg", "snr", "valid"):
        assert name in names
    cols = ref.to_columns()
    assert len(rows) == cols["x"].size
    np.testing.assert_allclose(rows[:, 0], cols["x"], atol=1e-6)
    np.testing.assert_allclose(rows[:, 1], cols["y"], atol=1e-6)
    for name in ("dx", "dy", "dz", "snr"):
        expected = np.where(np.isfinite(cols[name]), cols[name], np.nan)  # inf -> NULL
        np.testing.assert_allclose(_col(names, rows, name), expected, rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(_col(names, rows, "valid"), cols["valid"].astype(float))
    ok = np.isfinite(cols["dx"])
    mag = _col(names, rows, "magnitude")[ok]
    az = _col(names, rows, "azimuth_deg")[ok]
    np.testing.assert_allclose(mag, np.hypot(cols["dx"], cols["dy"])[ok], rtol=1e-12)
    # azimuth clockwise from north: east = sin(az) * magnitude, north = cos(az) * magnitude
    np.testing.assert_allclose(mag * np.sin(np.radians(az)), cols["dx"][ok], atol=1e-9)
    np.testing.assert_allclose(mag * np.cos(np.radians(az)), cols["dy"][ok], atol=1e-9)
    # the known rigid shift is found (interior vectors, sub-pixel: < 0.1 px = 2.5 cm)
    v = ref.valid
    assert v.mean() > 0.8
    assert abs(np.median(ref.dx[v]) - SHIFT[0]) < 0.025
    assert abs(np.median(ref.dy[v]) - SHIFT[1]) < 0.025
    assert abs(np.nanmedian(ref.dz[v]) - SHIFT[2]) < 0.02
    # rasters: one pixel per vector, the point cloud's CRS, the core's values
    for comp in ("dx", "dy", "dz"):
        rlayer, arr, gt = _raster(res[comp.upper()])
        assert rlayer.crs().authid() == "EPSG:32612"
        np.testing.assert_array_equal(arr, getattr(ref, comp))
        ext = rlayer.extent()
        x0, y0 = ref.origin_xy
        assert ext.xMinimum() == pytest.approx(x0)
        assert ext.yMaximum() == pytest.approx(y0)
        assert ext.width() == pytest.approx(ref.shape[1] * ref.spacing_m)
        assert ext.height() == pytest.approx(ref.shape[0] * ref.spacing_m)
    summary = json.loads(Path(res["SUMMARY"]).read_text())
    assert summary["n_vectors"] == ref.dx.size
    assert summary["windows_px"] == [32, 16]
    assert summary["vector_spacing_m"] == pytest.approx(ref.spacing_m)
    assert summary["dem_shape"] == list(grid.shape)


def test_piv_breaklines_layer_equals_core(provider, epochs, tmp_path):
    """BREAKLINES, a line layer, reaches the core: the vectors and near_break flags of
    :func:`piv` given the line; the same line in WGS 84 is reprojected to the same flags."""
    from slipmap.core.breaklines import breaklines
    from slipmap.core.dem import common_grid, grid_elevation
    from slipmap.core.piv import piv

    paths, clouds = epochs
    line = np.array([[X0 + 11.0, Y0 - 5.0], [X0 + 13.0, Y0 + SIDE + 5.0]])
    to_wgs = pyproj.Transformer.from_crs(UTM12, "EPSG:4326", always_xy=True)
    runs = {}
    for name, (xs, ys), crs in (
        ("utm", line.T, "EPSG:32612"),
        ("wgs", to_wgs.transform(line[:, 0], line[:, 1]), "EPSG:4326"),
    ):
        feature = {
            "type": "Feature",
            "properties": {},
            "geometry": {"type": "LineString", "coordinates": np.column_stack([xs, ys]).tolist()},
        }
        path = tmp_path / f"scarp_{name}.geojson"
        path.write_text(
            json.dumps(
                {
                    "type": "FeatureCollection",
                    "crs": {"type": "name", "properties": {"name": crs}},
                    "features": [feature],
                }
            )
        )
        d = tmp_path / name
        d.mkdir()
        runs[name] = _run(
            "piv",
            {
                "BEFORE": str(paths["before"]),
                "AFTER": str(paths["after"]),
                "GRID": 0.25,
                "WINDOWS": "32 16",
                "MAX_DISPLACEMENT": 1.0,
                "BREAKLINES": str(path),
                "VECTORS": str(d / "vectors.gpkg"),
                "DX": str(d / "dx.tif"),
                "DY": str(d / "dy.tif"),
                "DZ": str(d / "dz.tif"),
                "SUMMARY": str(d / "piv.json"),
            },
        )
    res = runs["utm"]
    grid = common_grid(clouds["before"], clouds["after"], cell_m=0.25)
    ref = piv(
        grid_elevation(clouds["before"], grid=grid),
        grid_elevation(clouds["after"], grid=grid),
        grid=grid,
        windows_px=(32, 16),
        expected_max_displacement_m=1.0,
        breaklines=breaklines([line]),
    )
    assert 0 < ref.near_break.sum() < ref.near_break.size
    _, names, rows = _features(res["VECTORS"])
    np.testing.assert_array_equal(_col(names, rows, "near_break"), ref.near_break.ravel())
    expected = np.where(np.isfinite(ref.dx), ref.dx, np.nan).ravel()
    np.testing.assert_allclose(_col(names, rows, "dx"), expected, rtol=1e-9, atol=1e-9)
    summary = json.loads(Path(res["SUMMARY"]).read_text())
    assert summary["n_near_break"] == int(ref.near_break.sum())
    _, names, rows = _features(runs["wgs"]["VECTORS"])
    np.testing.assert_array_equal(_col(names, rows, "near_break"), ref.near_break.ravel())


def test_piv_control_comparison(piv_run):
    from slipmap.core.fields import compare_with_control

    res, d, (cxy, cd) = piv_run
    summary = json.loads(Path(res["SUMMARY"]).read_text())
    c = summary["control"]
    assert c["n_compared"] == 3 and c["n_missing"] == 0
    assert c["rmse_horizontal_m"] < 0.03  # the true shift
    layer, names, rows = _features(res["VECTORS"])
    ref = compare_with_control(
        rows[:, 0],
        rows[:, 1],
        _col(names, rows, "dx"),
        _col(names, rows, "dy"),
        _col(names, rows, "dz"),
        cxy,
        cd,
    )
    assert c["rmse_horizontal_m"] == pytest.approx(ref.rmse_horizontal_m, rel=1e-9)
    assert c["bias_dx_m"] == pytest.approx(ref.bias_dx_m, rel=1e-9, abs=1e-12)


@pytest.mark.parametrize(
    "change, words",
    [
        ({"GRID": 0.0}, '"Grid size GR (m)"'),
        ({"WINDOWS": "512 256"}, "does not fit"),
        ({"WINDOWS": "32 x"}, '"Interrogation windows per pass (pixels)"'),
        ({"AFTER_OFFSET": 1000.0}, "overlap"),
    ],
)
def test_piv_bad_parameters(provider, epochs, tmp_path, change, words):
    from qgis.core import QgsProcessingException

    from slipmap.core.io.las import PointCloud, write_las

    paths, clouds = epochs
    params = {
        "BEFORE": str(paths["before"]),
        "AFTER": str(paths["after"]),
        "GRID": 0.25,
        "WINDOWS": "32 16",
        "VECTORS": "TEMPORARY_OUTPUT",
        "DX": str(tmp_path / "dx.tif"),
        "DY": str(tmp_path / "dy.tif"),
        "DZ": str(tmp_path / "dz.tif"),
        "SUMMARY": str(tmp_path / "s.json"),
    }
    change = dict(change)
    if "AFTER_OFFSET" in change:
        far = clouds["after"] + [change.pop("AFTER_OFFSET"), 0.0, 0.0]
        write_las(tmp_path / "far.las", PointCloud(xyz=far, crs=UTM12))
        params["AFTER"] = str(tmp_path / "far.las")
    params.update(change)
    feedback = _feedback()
    with pytest.raises(QgsProcessingException) as raised:
        _run("piv", params, feedback=feedback)
    message = str(raised.value) + " ".join(feedback.errors)
    assert words in message, raised.value
    assert not (tmp_path / "s.json").exists()


def test_piv_cancel_stops_run(provider, epochs, tmp_path):
    from qgis.core import QgsProcessingException

    paths, _ = epochs
    feedback = _feedback(cancel_after=2)
    with pytest.raises(QgsProcessingException) as raised:
        _run(
            "piv",
            {
                "BEFORE": str(paths["before"]),
                "AFTER": str(paths["after"]),
                "GRID": 0.25,
                "WINDOWS": "32 16",
                "VECTORS": str(tmp_path / "v.gpkg"),
                "DX": str(tmp_path / "dx.tif"),
                "DY": str(tmp_path / "dy.tif"),
                "DZ": str(tmp_path / "dz.tif"),
                "SUMMARY": str(tmp_path / "s.json"),
            },
            feedback=feedback,
        )
    assert feedback.calls == 2
    assert "cancelled" in str(raised.value) + " ".join(feedback.errors), raised.value
    assert not (tmp_path / "s.json").exists() and not (tmp_path / "dx.tif").exists()


# --------------------------------------------------------------------------- windowed ICP


def _mask_layer(ring_utm):
    """A polygon memory layer in EPSG:4326 (so the algorithm has to reproject it)."""
    from qgis.core import QgsFeature, QgsGeometry, QgsPointXY, QgsVectorLayer

    tr = pyproj.Transformer.from_crs(UTM12, "EPSG:4326", always_xy=True)
    lon, lat = tr.transform(ring_utm[:, 0], ring_utm[:, 1])
    layer = QgsVectorLayer("Polygon?crs=EPSG:4326", "moving", "memory")
    f = QgsFeature()
    f.setGeometry(QgsGeometry.fromPolygonXY([[QgsPointXY(a, b) for a, b in zip(lon, lat)]]))
    layer.dataProvider().addFeatures([f])
    return layer


def _icp_params(paths, tmp_path, **params):
    """slipmap:windowedicp's parameters for the two epochs (6 m cells, 50 points, one pass,
    outputs in ``tmp_path``), updated by ``params``."""
    out = {
        "BEFORE": str(paths["before"]),
        "AFTER": str(paths["after"]),
        "CELL": 6.0,
        "MIN_POINTS": 50,
        "COARSE_TO_FINE": 0,
        "FIELD_MODEL": 0,  # cells: the core's default these tests compare with
        "CELLS": str(tmp_path / "cells.gpkg"),
        "VECTORS": str(tmp_path / "vectors.gpkg"),
        "SUMMARY": str(tmp_path / "icp.json"),
    }
    out.update(params)
    return out


def test_windowedicp_equals_core(provider, epochs, tmp_path):
    from slipmap.core.icp import windowed_icp

    paths, clouds = epochs
    res = _run("windowedicp", _icp_params(paths, tmp_path))
    ref = windowed_icp(  # the job's default sample: at most 2000 after-points per cell
        clouds["before"], clouds["after"], cell_m=6.0, min_points=50, coarse_to_fine=0,
        max_points_per_cell=DEFAULT_MAX_POINTS_PER_CELL,
    )  # fmt: skip
    cols = ref.to_columns()
    from qgis.core import QgsWkbTypes

    for key, geometry in (
        ("CELLS", QgsWkbTypes.PolygonGeometry),
        ("VECTORS", QgsWkbTypes.PointGeometry),
    ):
        layer, names, rows = _features(res[key])
        assert layer.crs().authid() == "EPSG:32612"
        assert layer.geometryType() == geometry
        # the job's columns (core's to_columns without row/col, then magnitude, azimuth)
        assert set(ICP_FIELDS) <= set(names)
        assert len(rows) == len(ref)
        np.testing.assert_allclose(rows[:, 0], ref.x, atol=1e-6)  # centroid = cell centre
        np.testing.assert_allclose(rows[:, 1], ref.y, atol=1e-6)
        for name in ICP_FIELDS[:11]:
            np.testing.assert_allclose(_col(names, rows, name), cols[name], rtol=1e-12)
        np.testing.assert_allclose(
            _col(names, rows, "magnitude"), np.hypot(ref.dx, ref.dy), rtol=1e-12
        )
    cells, _, _ = _features(res["CELLS"])
    area = [f.geometry().area() for f in cells.getFeatures()]
    np.testing.assert_allclose(area, 36.0, rtol=1e-9)
    # 16 interior-ish cells recover the rigid shift within a few mm
    assert np.median(np.abs(ref.dx - SHIFT[0])) < 0.01
    assert np.median(np.abs(ref.dy - SHIFT[1])) < 0.01
    assert np.median(np.abs(ref.dz - SHIFT[2])) < 0.005
    summary = json.loads((tmp_path / "icp.json").read_text())
    assert summary["n_cells"] == len(ref)
    assert summary["prealignment"] is None
    assert summary["sigma_factor"]["applied"] == pytest.approx(ref.sigma_factor, rel=1e-12)
    assert summary["sigma_factor"]["cells"] == ref.sigma_factor_cells
    # formal sigmas on request: the core's formal sigmas (independent residuals)
    formal = _run(
        "windowedicp",
        _icp_params(
            paths, tmp_path, FORMAL_SIGMA=True, CELLS="TEMPORARY_OUTPUT",
            VECTORS=str(tmp_path / "formal.gpkg"), SUMMARY=str(tmp_path / "formal.json"),
        ),
    )  # fmt: skip
    _, names, rows = _features(formal["VECTORS"])
    np.testing.assert_allclose(_col(names, rows, "sigma_dx"), ref.sigma_formal[:, 0], rtol=1e-12)
    assert json.loads((tmp_path / "formal.json").read_text())["sigma_factor"]["applied"] == 1.0


def test_windowedicp_spline_field_equals_core(provider, epochs, tmp_path):
    """FIELD_MODEL (enum: cells, spline) and SPLINE_SPACING reach the core's spline field."""
    from slipmap.core.icp import windowed_icp

    paths, clouds = epochs
    res = _run("windowedicp", _icp_params(paths, tmp_path, FIELD_MODEL=1, SPLINE_SPACING=4.0))
    ref = windowed_icp(
        clouds["before"], clouds["after"], cell_m=6.0, min_points=50, coarse_to_fine=0,
        field_model="spline", spline_spacing_m=4.0, detect_breaklines=True, cell_choice=True,
        max_points_per_cell=DEFAULT_MAX_POINTS_PER_CELL,
    )  # fmt: skip
    layer, names, rows = _features(res["VECTORS"])
    assert len(rows) == len(ref)
    for name in ("dx", "dy", "dz", "sigma_dx"):
        np.testing.assert_allclose(_col(names, rows, name), getattr(ref, name), rtol=1e-9)
    assert json.loads(Path(res["SUMMARY"]).read_text())["model"]["field"] == "spline"


def _line_layer(xy_utm):
    """A line memory layer in EPSG:4326 (so the algorithm has to reproject it)."""
    from qgis.core import QgsFeature, QgsGeometry, QgsPointXY, QgsVectorLayer

    tr = pyproj.Transformer.from_crs(UTM12, "EPSG:4326", always_xy=True)
    lon, lat = tr.transform(xy_utm[:, 0], xy_utm[:, 1])
    layer = QgsVectorLayer("LineString?crs=EPSG:4326", "scarp", "memory")
    f = QgsFeature()
    f.setGeometry(QgsGeometry.fromPolylineXY([QgsPointXY(a, b) for a, b in zip(lon, lat)]))
    layer.dataProvider().addFeatures([f])
    return layer


def test_windowedicp_breaklines_layer_reaches_the_default_spline_field(provider, epochs, tmp_path):
    """BREAKLINES (an optional line layer, reprojected) with the default field model: the
    same field as the core's spline with those breaklines, and the summary says so."""
    from slipmap.core.icp import windowed_icp

    paths, clouds = epochs
    line = np.array([[X0 + 11.3, Y0 - 2.0], [X0 + 12.1, Y0 + 30.0]])
    params = _icp_params(paths, tmp_path, BREAKLINES=_line_layer(line), SPLINE_SPACING=4.0)
    del params["FIELD_MODEL"]  # the default: the spline field
    res = _run("windowedicp", params)
    summary = json.loads(Path(res["SUMMARY"]).read_text())
    assert summary["model"]["field"] == "spline"
    assert summary["breaklines"]["source"] == "given" and summary["breaklines"]["count"] == 1
    got = np.array(summary["breaklines"]["lines"][0])
    np.testing.assert_allclose(got, line, atol=1e-3)  # through EPSG:4326 and back
    ref = windowed_icp(
        clouds["before"], clouds["after"], cell_m=6.0, min_points=50, coarse_to_fine=0,
        field_model="spline", spline_spacing_m=4.0, breaklines=[got], cell_choice=True,
    )  # fmt: skip
    _, names, rows = _features(res["VECTORS"])
    assert len(rows) == len(ref)
    # the line to 1 mm; a cell whose choice between the field and its own fit
    # (core.icp_choice) is that close may choose the other (the two within 0.2 mm here)
    same = _col(names, rows, "from_cell") == ref.from_cell
    assert same.mean() >= 0.9
    np.testing.assert_allclose(_col(names, rows, "dx")[same], ref.dx[same], atol=1e-4)
    np.testing.assert_allclose(_col(names, rows, "dx"), ref.dx, atol=1e-3)


def test_windowedicp_stable_mask_is_reprojected(provider, epochs, tmp_path):
    from slipmap.core.icp import windowed_icp

    paths, clouds = epochs
    ring = np.array(
        [
            [X0 + 6, Y0 + 6],
            [X0 + 18, Y0 + 6],
            [X0 + 18, Y0 + 18],
            [X0 + 6, Y0 + 18],
            [X0 + 6, Y0 + 6],
        ]
    )
    res = _run(
        "windowedicp",
        _icp_params(
            paths, tmp_path, CELL=8.0, STABLE_MASK=_mask_layer(ring), CELLS="TEMPORARY_OUTPUT",
            VECTORS=str(tmp_path / "v.gpkg"),
        ),
    )  # fmt: skip
    ref = windowed_icp(
        clouds["before"],
        clouds["after"],
        cell_m=8.0,
        min_points=50,
        prealign=True,
        exclude_polygons=[ring],
    )
    summary = json.loads((tmp_path / "icp.json").read_text())
    # the "stable" ground moved too: the pre-alignment takes the whole shift out...
    pre = summary["prealignment"]
    np.testing.assert_allclose(pre["offset_at_centre_m"], SHIFT, atol=0.01)
    np.testing.assert_allclose(pre["offset_at_centre_m"], -ref.prealignment.params[3:], atol=0.01)
    # ...so the cells are still (agreeing with the core's to a mm: the reprojected mask
    # selects a slightly different random sample of stable points)
    _, names, rows = _features(res["VECTORS"])
    assert len(rows) == len(ref)
    for name in ("dx", "dy", "dz"):
        np.testing.assert_allclose(_col(names, rows, name), getattr(ref, name), atol=1e-3)
        assert np.all(np.abs(_col(names, rows, name)) < 0.01)


def test_windowedicp_bad_cell_and_cancel(provider, epochs, tmp_path):
    from qgis.core import QgsProcessingException

    paths, _ = epochs
    params = {
        "BEFORE": str(paths["before"]),
        "AFTER": str(paths["after"]),
        "CELL": 0.0,
        "CELLS": "TEMPORARY_OUTPUT",
        "VECTORS": "TEMPORARY_OUTPUT",
        "SUMMARY": str(tmp_path / "icp.json"),
    }
    feedback = _feedback()
    with pytest.raises(QgsProcessingException) as raised:
        _run("windowedicp", params, feedback=feedback)
    assert '"Cell size (m)"' in str(raised.value) + " ".join(feedback.errors)
    params.update(CELL=6.0, MIN_POINTS=50, COARSE_TO_FINE=0)
    feedback = _feedback(cancel_after=3)
    with pytest.raises(QgsProcessingException) as raised:
        _run("windowedicp", params, feedback=feedback)
    assert feedback.calls == 3
    assert "cancelled" in str(raised.value) + " ".join(feedback.errors), raised.value
    assert not (tmp_path / "icp.json").exists()


# --------------------------------------------------------------------------- demdiff


def test_demdiff_equals_core(provider, epochs, tmp_path):
    from slipmap.core.dem import dem_difference

    paths, clouds = epochs
    res = _run(
        "demdiff",
        {
            "BEFORE": str(paths["before"]),
            "AFTER": str(paths["after"]),
            "GRID": 0.5,
            "OUTPUT": str(tmp_path / "dd.tif"),
            "SUMMARY": str(tmp_path / "dd.json"),
        },
    )
    ref = dem_difference(clouds["before"], clouds["after"], cell_m=0.5)
    layer, arr, gt = _raster(res["OUTPUT"])
    assert layer.crs().authid() == "EPSG:32612"
    assert layer.bandCount() == 3
    np.testing.assert_array_equal(arr[0], ref.dz)
    np.testing.assert_array_equal(arr[1], ref.z_before)
    np.testing.assert_array_equal(arr[2], ref.z_after)
    g = ref.grid
    ext = layer.extent()
    assert (ext.xMinimum(), ext.yMaximum()) == pytest.approx((g.x_min, g.y_max))
    assert (ext.xMaximum(), ext.yMinimum()) == pytest.approx((g.x_max, g.y_min))
    summary = json.loads(Path(res["SUMMARY"]).read_text())
    assert summary["dz_m"]["n"] == ref.n_valid
    assert summary["dz_m"]["mean"] == pytest.approx(ref.mean_m)


# --------------------------------------------------------------------------- strain


def test_strain_of_piv_vectors_equals_core(piv_run, tmp_path):
    from slipmap.core.fields import field_from_columns
    from slipmap.core.strain import strain_field

    res, _, _ = piv_run
    out = _run(
        "strain",
        {
            "FIELD": res["VECTORS"],
            "OUTPUT": str(tmp_path / "s.tif"),
            "SUMMARY": str(tmp_path / "s.json"),
        },
    )
    _, names, rows = _features(res["VECTORS"])
    field = field_from_columns(
        rows[:, 0],
        rows[:, 1],
        _col(names, rows, "dx"),
        _col(names, rows, "dy"),
        _col(names, rows, "dz"),
    )
    bands = strain_field(field).bands()
    layer, arr, gt = _raster(out["OUTPUT"])
    assert layer.crs().authid() == "EPSG:32612"
    assert layer.bandCount() == len(bands) == 9
    for k, name in enumerate(bands):
        np.testing.assert_array_equal(arr[k], bands[name])
    assert gt[0] == pytest.approx(field.origin_xy[0]) and gt[3] == pytest.approx(field.origin_xy[1])
    # a rigid shift has no strain
    assert np.nanmax(np.abs(bands["dilatation"])) < 0.05
    summary = json.loads((tmp_path / "s.json").read_text())
    assert list(summary["bands"]) == list(bands)


def test_strain_of_a_csv_table_is_analytic(provider, tmp_path):
    from slipmap.core.io.table import write_csv_columns

    gamma = 2e-3
    x, y = np.meshgrid(X0 + np.arange(12) * 2.0, Y0 + np.arange(9) * 2.0)
    keep = np.ones(x.shape, bool)
    keep[4, 5] = keep[0, 0] = False  # gaps
    write_csv_columns(
        tmp_path / "field.csv",
        {
            "x": x[keep],
            "y": y[keep],
            "dx": gamma * (y[keep] - Y0),
            "dy": np.zeros(keep.sum()),
        },
    )
    out = _run(
        "strain",
        {
            "FIELD": str(tmp_path / "field.csv"),
            "CRS": "EPSG:32612",
            "OUTPUT": str(tmp_path / "s.tif"),
            "SUMMARY": str(tmp_path / "s.json"),
        },
    )
    layer, arr, gt = _raster(out["OUTPUT"])
    assert layer.crs().authid() == "EPSG:32612"
    from slipmap.core.io.raster import band_names

    bands = dict(zip(band_names(out["OUTPUT"]), arr))
    ok = np.isfinite(bands["exy"])
    assert ok.sum() == keep.sum()
    np.testing.assert_allclose(bands["exy"][ok], gamma / 2, rtol=1e-9)
    np.testing.assert_allclose(bands["rotation_rad"][ok], -gamma / 2, rtol=1e-9)
    np.testing.assert_allclose(bands["dilatation"][ok], 0, atol=1e-12)
    assert gt[1] == 2.0 and gt[5] == -2.0
    assert gt[0] == pytest.approx(X0 - 1.0) and gt[3] == pytest.approx(Y0 + 17.0)


def test_strain_without_dx_fails(provider, tmp_path):
    from qgis.core import QgsProcessingException

    (tmp_path / "bad.csv").write_text("x,y,u,v\n1,2,0,0\n3,2,0,0\n")
    feedback = _feedback()
    with pytest.raises(QgsProcessingException) as raised:
        _run(
            "strain",
            {
                "FIELD": str(tmp_path / "bad.csv"),
                "OUTPUT": str(tmp_path / "s.tif"),
                "SUMMARY": str(tmp_path / "s.json"),
            },
            feedback=feedback,
        )
    assert "dx" in str(raised.value) + " ".join(feedback.errors)


# --------------------------------------------------------------------------- styles


@pytest.mark.parametrize(
    "style, uri",
    [
        ("piv_vectors", "Point?crs=EPSG:32612"),
        ("icp_vectors", "Point?crs=EPSG:32612"),
        ("icp_vectors_lines", "LineString?crs=EPSG:32612"),
        ("icp_cells", "Polygon?crs=EPSG:32612"),
    ],
)
def test_vector_styles_load(qgis_app, style, uri):
    """The fitted styles (app/styles.py) load: arrows rotated by azimuth_deg and sized by
    magnitude at the legend's scale, cells labelled value ± sigma."""
    from qgis.core import QgsProperty, QgsRuleBasedRenderer, QgsSymbolLayer, QgsVectorLayer
    from qgis.PyQt.QtXml import QDomDocument

    from slipmap.app.styles import VECTOR_STYLES, vector_qml
    from slipmap.qgis_plugin.algorithms._base import style_path

    path = style_path(style)
    assert path is not None and Path(path).parent == STYLES
    fields = "&".join(f"field={n}:double" for n in ICP_FIELDS)
    layer = QgsVectorLayer(f"{uri}&{fields}&field=valid:integer", style, "memory")
    cols = {n: np.array([0.01, 0.02]) for n in ICP_FIELDS}
    doc = QDomDocument()
    doc.setContent(vector_qml(VECTOR_STYLES[style], cols))
    ok, message = layer.importNamedStyle(doc)
    assert ok, message
    renderer = layer.renderer()
    assert isinstance(renderer, QgsRuleBasedRenderer)
    if "vectors" in style:
        drawn = [r for r in renderer.rootRule().descendants() if r.symbol() is not None]
        sl = drawn[0].symbol().symbolLayer(0)
        if style.endswith("lines"):  # a marker at the line's first vertex
            sl = sl.subSymbol().symbolLayer(0)
        angle = sl.dataDefinedProperties().property(QgsSymbolLayer.PropertyAngle)
        assert isinstance(angle, QgsProperty) and "azimuth_deg" in angle.expressionString()
        size = sl.dataDefinedProperties().property(QgsSymbolLayer.PropertySize)
        # 6 mm per 10 mm (the 95th percentile, 19.5 mm, rounded down to 1-2-5)
        assert "magnitude" in size.expressionString() and "* 600.0," in size.expressionString()
    else:
        assert layer.labelsEnabled()
        assert "sigma_dx" in layer.labeling().settings().fieldName


@pytest.mark.parametrize("style", ["diverging", "strain"])
def test_raster_styles_load_and_centre_on_zero(qgis_app, tmp_path, style):
    from qgis.core import (
        QgsProcessingContext,
        QgsProcessingFeedback,
        QgsRasterLayer,
        QgsSingleBandPseudoColorRenderer,
    )

    from slipmap.core.io.raster import write_geotiff
    from slipmap.qgis_plugin.algorithms._base import style_path
    from slipmap.qgis_plugin.algorithms._fields import apply_diverging_style_on_load

    a = np.linspace(-0.02, 0.05, 30).reshape(5, 6)
    a[0, 0] = np.nan
    path = str(tmp_path / "dz.tif")
    write_geotiff(path, a, origin_xy=(X0, Y0), pixel_size_m=1.0, crs_wkt=UTM12.to_wkt())
    layer = QgsRasterLayer(path, "dz")
    message, ok = layer.loadNamedStyle(style_path(style))
    assert ok, message
    assert isinstance(layer.renderer(), QgsSingleBandPseudoColorRenderer)
    # through the on-load post-processor: the ramp becomes [-0.05, 0.05], white at 0
    context = QgsProcessingContext()
    context.addLayerToLoadOnCompletion(
        path, QgsProcessingContext.LayerDetails("dz", None, "OUTPUT")
    )
    apply_diverging_style_on_load(context, path, style)
    post = context.layerToLoadOnCompletionDetails(path).postProcessor()
    assert post is not None
    fresh = QgsRasterLayer(path, "dz")
    post.postProcessLayer(fresh, context, QgsProcessingFeedback())
    r = fresh.renderer()
    assert isinstance(r, QgsSingleBandPseudoColorRenderer)
    assert (r.classificationMin(), r.classificationMax()) == pytest.approx((-0.05, 0.05))
    items = r.shader().rasterShaderFunction().colorRampItemList()
    assert [i.value for i in items] == pytest.approx(np.linspace(-0.05, 0.05, len(items)))
    assert items[len(items) // 2].color.name() == "#f7f7f7"


# --------------------------------------------------------------------------- real data


@pytest.fixture(scope="module")
def lobe(tmp_path_factory):
    """lone-star (LAZ) split in two epochs with the study's lobe (-1 m north, -0.4 m up)."""
    from slipmap.core.io.las import read_las, write_las
    from slipmap.core.synthetic import make_lobe_pair

    lone = Path(__file__).resolve().parents[1] / "data" / "lone-star.laz"
    cloud = read_las(lone)
    pair = make_lobe_pair(cloud.xyz, seed=3)
    d = tmp_path_factory.mktemp("lobe")
    write_las(d / "before.laz", cloud.subset(pair.before_index))
    write_las(d / "after.laz", cloud.subset(pair.after_index), xyz=pair.after)
    return d, pair


def test_piv_on_a_real_cloud_with_a_lobe(provider, lobe, tmp_path):
    from slipmap.core.io.las import read_las
    from slipmap.core.io.table import write_csv_columns
    from slipmap.core.piv import piv_from_points

    d, pair = lobe
    f = pair.field
    # control points: the true lobe motion on a 1 m grid well inside the lobe
    gx, gy = np.meshgrid(np.arange(-4.0, 4.5, 1.0), np.arange(-4.0, 4.5, 1.0))
    cxy = np.column_stack([gx.ravel(), gy.ravel()]) + np.asarray(f.centre_xy)
    truth = f(cxy)
    write_csv_columns(
        tmp_path / "truth.csv",
        {"x": cxy[:, 0], "y": cxy[:, 1], "dx": truth[:, 0], "dy": truth[:, 1], "dz": truth[:, 2]},
    )
    res = _run(
        "piv",
        {
            "BEFORE": str(d / "before.laz"),
            "AFTER": str(d / "after.laz"),
            "GRID": 0.2,
            "WINDOWS": "32 16",
            "MAX_DISPLACEMENT": 1.2,
            "CONTROL": str(tmp_path / "truth.csv"),
            "VECTORS": str(tmp_path / "v.gpkg"),
            "DX": str(tmp_path / "dx.tif"),
            "DY": str(tmp_path / "dy.tif"),
            "DZ": str(tmp_path / "dz.tif"),
            "SUMMARY": str(tmp_path / "piv.json"),
        },
    )
    ref = piv_from_points(
        read_las(d / "before.laz").xyz,
        read_las(d / "after.laz").xyz,
        cell_m=0.2,
        windows_px=(32, 16),
        expected_max_displacement_m=1.2,
    )
    _, names, rows = _features(res["VECTORS"])
    np.testing.assert_allclose(_col(names, rows, "dy"), ref.dy.ravel(), rtol=1e-12)
    c = json.loads((tmp_path / "piv.json").read_text())["control"]
    assert c["n_compared"] + c["n_missing"] == len(cxy) and c["n_compared"] > 40
    assert c["rmse_horizontal_m"] < 0.15  # of up to 1 m of motion
    assert abs(c["bias_dy_m"]) < 0.1
