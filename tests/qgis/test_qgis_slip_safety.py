"""Bad input to the Fault slip algorithm in QGIS: refused (before running where it can be
checked) in the dialog's words, inputs byte-identical, nothing written (issue #15's audit)."""

import hashlib

import numpy as np
import pytest

pytestmark = pytest.mark.qgis

ORIGIN = (498000.0, 4234000.0, 20.0)


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    import pyproj

    from slipmap.core.io.las import PointCloud, write_las
    from slipmap.core.synthetic import make_fault_pair

    d = tmp_path_factory.mktemp("q_slip_safety")
    fp = make_fault_pair(
        "mls", seed=7, origin=ORIGIN, right_offset_m=(0.0, -0.0181, 0.0), density_pts_m2=20.0
    )
    crs = pyproj.CRS.from_epsg(32610)
    paths = {}
    for name, sc in (("before", fp.before), ("after", fp.after)):
        p = d / f"{name}.las"
        attrs = {"Classification": sc.classification}
        write_las(p, PointCloud(xyz=sc.points, attributes=attrs, crs=crs))
        paths[name] = p
    return fp, paths


def _layer(xy):
    from qgis.core import QgsFeature, QgsGeometry, QgsPointXY, QgsVectorLayer

    layer = QgsVectorLayer("LineString?crs=EPSG:32610", "fault", "memory")
    f = QgsFeature()
    f.setGeometry(QgsGeometry.fromPolylineXY([QgsPointXY(float(a), float(b)) for a, b in xy]))
    layer.dataProvider().addFeatures([f])
    return layer


def _sha(p):
    return hashlib.sha256(p.read_bytes()).hexdigest()


def _run(params):
    import processing
    from qgis.core import QgsProcessingContext, QgsProcessingFeedback

    return processing.run(
        "slipmap:displacement",
        {"PLANES": "TEMPORARY_OUTPUT", **params},
        context=QgsProcessingContext(),
        feedback=QgsProcessingFeedback(),
    )


def test_summary_over_an_epoch_is_refused(provider, pair, tmp_path):
    from qgis.core import QgsProcessingException

    fp, paths = pair
    before = tmp_path / "before.las"
    before.write_bytes(paths["before"].read_bytes())
    sha = _sha(before)
    with pytest.raises(QgsProcessingException) as e:
        _run(
            {
                "BEFORE": str(before),
                "AFTER": str(paths["after"]),
                "FAULT": _layer(fp.trace_xy),
                "SUMMARY": str(before),
            }
        )
    assert "never overwrites an input" in str(e.value)
    assert "--" not in str(e.value)  # QGIS words, not CLI flags
    assert _sha(before) == sha and [p.name for p in tmp_path.iterdir()] == ["before.las"]


def test_same_file_as_both_epochs(provider, pair, tmp_path):
    from qgis.core import QgsProcessingException

    fp, paths = pair
    with pytest.raises(QgsProcessingException) as e:
        _run(
            {
                "BEFORE": str(paths["before"]),
                "AFTER": str(paths["before"]),
                "FAULT": _layer(fp.trace_xy),
                "SUMMARY": str(tmp_path / "s.json"),
            }
        )
    assert "same file" in str(e.value)
    assert not any(tmp_path.iterdir())


def test_fault_away_from_the_data_names_the_layer_and_writes_nothing(provider, pair, tmp_path):
    from qgis.core import QgsProcessingException

    from slipmap.app import slip as job

    fp, paths = pair
    with pytest.raises(QgsProcessingException) as e:
        _run(
            {
                "BEFORE": str(paths["before"]),
                "AFTER": str(paths["after"]),
                "FAULT": _layer(np.asarray(fp.trace_xy) + 5000.0),
                "SUMMARY": str(tmp_path / "s.json"),
            }
        )
    assert job.SPEC["fault"].dialog_label in str(e.value)
    assert "does not cross" in str(e.value)
    assert not any(tmp_path.iterdir())


def test_non_finite_reference_slip_refused_before_running(provider, pair, tmp_path):
    """The audit found a NaN literal written into the JSON: refused by the dialog's check."""
    from qgis.core import QgsApplication, QgsProcessingContext

    from slipmap.app import slip as job

    fp, paths = pair
    alg = QgsApplication.processingRegistry().algorithmById("slipmap:displacement")
    name = job.SPEC["reference_slip_m"].name_in("qgis")
    ok, msg = alg.checkParameterValues(
        {
            "BEFORE": str(paths["before"]),
            "AFTER": str(paths["after"]),
            "FAULT": _layer(fp.trace_xy),
            "SUMMARY": str(tmp_path / "s.json"),
            name: float("nan"),
        },
        QgsProcessingContext(),
    )
    assert not ok and job.SPEC["reference_slip_m"].dialog_label in msg, msg
    assert not any(tmp_path.iterdir())
