"""Bad input to the planes algorithm in QGIS: refused before running, in the dialog's words."""

import hashlib

import pytest

pytestmark = pytest.mark.qgis


@pytest.fixture(scope="module")
def cloud(tmp_path_factory):
    from slipmap.core.io.las import PointCloud, write_las
    from slipmap.core.synthetic import make_scene

    scene = make_scene("mls", seed=3, n_buildings=1, extent_m=30.0, origin=(500000, 4200000, 10))
    path = tmp_path_factory.mktemp("q_planes") / "scene.las"
    write_las(path, PointCloud(xyz=scene.points, attributes={}))
    return path


def _sha(p):
    return hashlib.sha256(p.read_bytes()).hexdigest()


def _run(params):
    import processing
    from qgis.core import QgsProcessingContext, QgsProcessingFeedback

    return processing.run(
        "slipmap:planes", params, context=QgsProcessingContext(), feedback=QgsProcessingFeedback()
    )


def test_output_over_the_input(provider, cloud, tmp_path):
    from qgis.core import QgsProcessingException

    src = tmp_path / "scene.las"
    src.write_bytes(cloud.read_bytes())
    before = _sha(src)
    with pytest.raises(QgsProcessingException) as e:
        _run({"INPUT": str(src), "OUTPUT": str(src), "SUMMARY": str(tmp_path / "s.json")})
    assert "Labelled point cloud (PlaneId)" in str(e.value)
    assert "never overwrites an input" in str(e.value)
    assert _sha(src) == before and sorted(p.name for p in tmp_path.iterdir()) == ["scene.las"]


def test_bad_classes_named_by_label(provider, cloud, tmp_path):
    from qgis.core import QgsApplication, QgsProcessingContext

    alg = QgsApplication.processingRegistry().algorithmById("slipmap:planes")
    params = {
        "INPUT": str(cloud),
        "CLASSES": "6 x",
        "OUTPUT": str(tmp_path / "o.las"),
        "SUMMARY": str(tmp_path / "s.json"),
    }
    ok, msg = alg.checkParameterValues(params, QgsProcessingContext())
    assert not ok and msg.startswith('"Keep only these classes (e.g. 6)"'), msg
    assert list(tmp_path.iterdir()) == []


def test_every_option_has_help(provider):
    from qgis.core import QgsApplication

    alg = QgsApplication.processingRegistry().algorithmById("slipmap:planes")
    for p in alg.parameterDefinitions():
        if p.name() not in ("OUTPUT", "SUMMARY"):
            assert p.help(), p.name()
