"""The ``slipmap`` Processing algorithms give the core's results through ``processing.run``."""

import json

import numpy as np
import pyproj
import pytest

pytestmark = pytest.mark.qgis

UTM10 = pyproj.CRS.from_epsg(32610)
ORIGIN = (498000.0, 4234000.0, 20.0)
IDS = ("planes", "displacement", "roughness", "pointaccuracy")


@pytest.fixture(scope="module")
def epochs(tmp_path_factory):
    from slipmap.core.io.las import PointCloud, write_las
    from slipmap.core.synthetic import make_fault_pair

    d = tmp_path_factory.mktemp("qgis_epochs")
    fp = make_fault_pair("mls", seed=7, origin=ORIGIN, right_offset_m=(0.0, -0.0181, 0.0))
    paths = []
    for name, sc in (("before", fp.before), ("after", fp.after)):
        p = d / f"{name}.las"
        write_las(
            p,
            PointCloud(xyz=sc.points, attributes={"Classification": sc.classification}, crs=UTM10),
        )
        paths.append(p)
    return fp, paths


def _fault_layer(xy_utm, geometry="LineString"):
    from qgis.core import QgsFeature, QgsGeometry, QgsPointXY, QgsVectorLayer

    tr = pyproj.Transformer.from_crs(UTM10, "EPSG:4326", always_xy=True)
    lon, lat = tr.transform(xy_utm[:, 0], xy_utm[:, 1])
    layer = QgsVectorLayer(f"{geometry}?crs=EPSG:4326", "fault", "memory")
    f = QgsFeature()
    pts = [QgsPointXY(a, b) for a, b in zip(lon, lat)]
    f.setGeometry(
        QgsGeometry.fromPolylineXY(pts)
        if geometry == "LineString"
        else QgsGeometry.fromPointXY(pts[0])
    )
    layer.dataProvider().addFeatures([f])
    return layer


def _recorder():
    from qgis.core import QgsProcessingFeedback

    class Recorder(QgsProcessingFeedback):
        def __init__(self):
            super().__init__()
            self.calls = 0
            self.errors = []

        def setProgress(self, value):  # noqa: N802
            self.calls += 1
            super().setProgress(value)

        def reportError(self, error, fatalError=False):  # noqa: N802, N803
            self.errors.append(error)
            super().reportError(error, fatalError)

    return Recorder


def test_algorithms_registered_with_help(provider):
    from qgis.core import QgsApplication

    reg = QgsApplication.processingRegistry()
    for alg_id in IDS:
        alg = reg.algorithmById(f"slipmap:{alg_id}")
        assert alg is not None, alg_id
        assert len(alg.shortHelpString()) > 100
        assert alg.canExecute()[0]


def test_planes_equal_core(provider, epochs, tmp_path):
    import processing

    from slipmap.core.io.las import read_las
    from slipmap.core.planes import segment_planes

    fp, (before, _) = epochs
    res = processing.run(
        "slipmap:planes",
        {
            "INPUT": str(before),
            "OUTPUT": str(tmp_path / "planes.las"),
            "SUMMARY": str(tmp_path / "planes.json"),
        },
    )
    cloud = read_las(before)
    keep = cloud.attributes["Classification"] != 2
    ref = segment_planes(cloud.xyz[keep])
    out = read_las(tmp_path / "planes.las")
    labels = np.asarray(out.attributes["PlaneId"])
    np.testing.assert_array_equal(labels[keep], ref.labels)
    assert np.all(labels[~keep] == -1)
    assert res["N_PLANES"] == len(ref)
    assert len(json.loads((tmp_path / "planes.json").read_text())["planes"]) == len(ref)


def test_displacement_reprojects_fault_and_matches_core(provider, epochs, tmp_path):
    import processing
    from qgis.core import QgsVectorLayer

    from slipmap.core.displacement import estimate_slip
    from slipmap.core.fault import fault_trace
    from slipmap.core.io.las import read_las

    fp, (before, after) = epochs
    res = processing.run(
        "slipmap:displacement",
        {
            "BEFORE": str(before),
            "AFTER": str(after),
            "FAULT": _fault_layer(fp.trace_xy),
            "SUMMARY": str(tmp_path / "slip.json"),
            "PLANES": str(tmp_path / "planes.gpkg"),
        },
    )
    slip = res["RIGHT_LATERAL_SLIP"]
    assert abs(slip - 0.0181) < 1e-3
    assert res["SIGMA_RIGHT_LATERAL"] > 0
    b, a = read_las(before), read_las(after)
    kb, ka = b.attributes["Classification"] != 2, a.attributes["Classification"] != 2
    # the trace the algorithm used: to WGS 84 for the layer and back (sub-micrometre changes,
    # which move points across the buffer's edge and so change the segmentation's inputs)
    to_ll = pyproj.Transformer.from_crs(UTM10, "EPSG:4326", always_xy=True)
    back = pyproj.Transformer.from_crs("EPSG:4326", UTM10, always_xy=True)
    xy = np.column_stack(back.transform(*to_ll.transform(fp.trace_xy[:, 0], fp.trace_xy[:, 1])))
    ref = estimate_slip(b.xyz[kb], a.xyz[ka], fault_trace([xy]))
    assert abs(slip - ref.components()["right_lateral_slip"]) < 1e-7
    assert (tmp_path / "slip.html").exists() or res["REPORT"]
    layer = QgsVectorLayer(res["PLANES"], "planes", "ogr")
    names = [f.name() for f in layer.fields()]
    for name in ("side", "plane_before", "n_points", "normal_x", "normal_y", "normal_z"):
        assert name in names
    assert layer.featureCount() > 0
    assert layer.crs().authid() == "EPSG:32610"


def test_point_layer_as_fault_fails(provider, epochs, tmp_path):
    import processing
    from qgis.core import QgsProcessingException

    fp, (before, after) = epochs
    feedback = _recorder()()
    with pytest.raises(QgsProcessingException) as raised:
        processing.run(
            "slipmap:displacement",
            {
                "BEFORE": str(before),
                "AFTER": str(after),
                "FAULT": _fault_layer(fp.trace_xy, "Point"),
                "SUMMARY": str(tmp_path / "slip.json"),
                "PLANES": "TEMPORARY_OUTPUT",
            },
            feedback=feedback,
        )
    assert "line" in str(raised.value) + " ".join(feedback.errors), raised.value


def test_roughness_raster_crs(provider, epochs, tmp_path):
    import processing
    from qgis.core import QgsRasterLayer

    _, (before, _) = epochs
    res = processing.run(
        "slipmap:roughness",
        {
            "INPUT": str(before),
            "CELL": 2.0,
            "OUTPUT": str(tmp_path / "r.tif"),
            "CSV": str(tmp_path / "r.csv"),
        },
    )
    layer = QgsRasterLayer(res["OUTPUT"], "r")
    assert layer.isValid()
    assert layer.crs().authid() == "EPSG:32610"
    assert (tmp_path / "r.csv").read_text().startswith("ix,iy,iz")


def test_pointaccuracy_axis(provider, epochs, tmp_path):
    import processing

    from slipmap.core.io.las import read_las

    _, (before, _) = epochs
    out = tmp_path / "acc.las"
    processing.run(
        "slipmap:pointaccuracy",
        {
            "INPUT": str(before),
            "MODEL": 1,
            "SIGMA_X": 0.01,
            "SIGMA_Y": 0.02,
            "SIGMA_Z": 0.03,
            "OUTPUT": str(out),
        },
    )
    cloud = read_las(out)
    for name, value in (("SigmaX", 0.01), ("SigmaY", 0.02), ("SigmaZ", 0.03)):
        np.testing.assert_allclose(cloud.attributes[name], value, rtol=1e-6)


def test_cancel_stops_run(provider, epochs, tmp_path):
    import processing
    from qgis.core import QgsProcessingException

    class CancelAfterFirst(_recorder()):
        def isCanceled(self):  # noqa: N802
            return self.calls > 0

    _, (before, _) = epochs
    feedback = CancelAfterFirst()
    with pytest.raises(QgsProcessingException) as raised:
        processing.run(
            "slipmap:planes",
            {
                "INPUT": str(before),
                "OUTPUT": str(tmp_path / "p.las"),
                "SUMMARY": str(tmp_path / "p.json"),
            },
            feedback=feedback,
        )
    assert feedback.calls == 1
    assert "cancelled" in str(raised.value) + " ".join(feedback.errors), raised.value
    assert not (tmp_path / "p.las").exists()


def test_missing_laspy_blocks_execution_not_loading(provider, monkeypatch):
    from qgis.core import QgsApplication

    from slipmap.qgis_plugin import compat

    monkeypatch.setattr(compat, "missing_packages", lambda names=None: ["laspy", "lazrs"])
    alg = QgsApplication.processingRegistry().algorithmById("slipmap:planes")
    ok, message = alg.canExecute()
    assert not ok
    assert message.startswith("SlipMap needs the Python packages laspy, lazrs,")
    assert message.endswith("laspy lazrs")
