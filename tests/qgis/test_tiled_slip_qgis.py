"""``slipmap:displacement`` on tiled inputs (issue #17): a glob of tiles per epoch gives the
slip of one file per epoch; the Dask scheduler is an advanced parameter (no local workers in
QGIS); a scheduler that cannot be reached is refused naming the dialog label, nothing written."""

import json

import numpy as np
import pyproj
import pytest

pytestmark = pytest.mark.qgis

UTM10 = pyproj.CRS.from_epsg(32610)
ORIGIN = (498000.0, 4234000.0, 20.0)


@pytest.fixture(scope="module")
def epochs(tmp_path_factory):
    """A fault pair as one LAS per epoch and as 37 / 41 m tiles; the trace's vertices."""
    from slipmap.core.io.las import PointCloud, read_las, write_las
    from slipmap.core.synthetic import make_fault_pair

    root = tmp_path_factory.mktemp("q_tiled_slip")
    fp = make_fault_pair(
        "mls", seed=7, origin=ORIGIN, right_offset_m=(0.0, -0.0181, 0.0), vegetation=False
    )
    for name, sc, edge in (("before", fp.before, 37.0), ("after", fp.after, 41.0)):
        cls = np.asarray(sc.classification, dtype=np.uint8)
        write_las(root / f"{name}.las", PointCloud(sc.points, {"Classification": cls}, UTM10))
        cloud = read_las(root / f"{name}.las")
        folder = root / f"{name}_tiles"
        folder.mkdir()
        k = np.floor((cloud.xyz[:, :2] - cloud.xyz[:, :2].min(0) + 3.0) / edge).astype(int)
        for key in np.unique(k, axis=0):
            write_las(folder / f"t_{key[0]}_{key[1]}.las", cloud.subset(np.all(k == key, axis=1)))
    return root, fp.trace_xy


def _fault_layer(xy):
    """The trace as a memory line layer in the clouds' CRS (no reprojection round trip)."""
    from qgis.core import QgsFeature, QgsGeometry, QgsPointXY, QgsVectorLayer

    layer = QgsVectorLayer("LineString?crs=EPSG:32610", "fault", "memory")
    f = QgsFeature()
    f.setGeometry(QgsGeometry.fromPolylineXY([QgsPointXY(float(a), float(b)) for a, b in xy]))
    layer.dataProvider().addFeatures([f])
    return layer


def _run(params):
    import processing
    from qgis.core import QgsProcessingContext, QgsProcessingFeedback

    return processing.run(
        "slipmap:displacement",
        params,
        context=QgsProcessingContext(),
        feedback=QgsProcessingFeedback(),
    )


def test_scheduler_is_advanced_and_no_local_workers(provider):
    from qgis.core import QgsApplication, QgsProcessingParameterDefinition

    alg = QgsApplication.processingRegistry().algorithmById("slipmap:displacement")
    names = {p.name(): p for p in alg.parameterDefinitions()}
    assert "WORKERS" not in names
    assert names["SCHEDULER"].flags() & QgsProcessingParameterDefinition.FlagAdvanced


def test_glob_of_tiles_equals_one_file(provider, epochs, tmp_path):
    root, xy = epochs
    got = {}
    for name, before, after in (
        ("file", root / "before.las", root / "after.las"),
        ("glob", root / "before_tiles" / "t_*.las", root / "after_tiles" / "t_*.las"),
    ):
        res = _run(
            {
                "BEFORE": str(before),
                "AFTER": str(after),
                "FAULT": _fault_layer(xy),
                "TILE_SIZE": 35.0,
                "SUMMARY": str(tmp_path / f"{name}.json"),
                "PLANES": "memory:",
            }
        )
        got[name] = res
    # the one-file run's headline is the whole side's (its tiles are a map); its estimate on
    # the planes extracted tile by tile, recorded beside it, is what tiled inputs give
    tiles = json.loads((tmp_path / "file.json").read_text())["tile_planes_estimate"]
    for key, name in (("RIGHT_LATERAL_SLIP", "right_lateral_slip"),
                      ("SIGMA_RIGHT_LATERAL", "sigma_right_lateral")):  # fmt: skip
        assert got["glob"][key] == pytest.approx(tiles[name], rel=1e-9, abs=0)
    assert got["file"]["RIGHT_LATERAL_SLIP"] == pytest.approx(0.0181, abs=0.003)
    summary = json.loads((tmp_path / "glob.json").read_text())
    assert summary["parameters"]["acquisition_unit_sources"]["tiled"] is True
    assert summary["parameters"]["engine"] == "in-process"


def test_unreachable_scheduler_named_by_label(provider, epochs, tmp_path, monkeypatch):
    from qgis.core import QgsProcessingException

    from slipmap.app import engine

    monkeypatch.setattr(engine, "CONNECT_TIMEOUT_S", 2)
    root, xy = epochs
    with pytest.raises(QgsProcessingException) as e:
        _run(
            {
                "BEFORE": str(root / "before_tiles" / "t_*.las"),
                "AFTER": str(root / "after_tiles" / "t_*.las"),
                "FAULT": _fault_layer(xy),
                "SUMMARY": str(tmp_path / "s.json"),
                "PLANES": "memory:",
                "SCHEDULER": "tcp://127.0.0.1:1",
            }
        )
    assert '"Dask scheduler address (tcp://host:port)"' in str(e.value)
    assert list(tmp_path.iterdir()) == []


def test_tiles_layer_without_tile_size_for_tiled_inputs(provider, epochs, tmp_path):
    """Tiled inputs always run on tiles (100 m by default): the Tiles layer needs no
    TILE_SIZE then, and its tiles carry the default size."""
    from qgis.core import QgsProcessingUtils, QgsProject

    root, xy = epochs
    res = _run(
        {
            "BEFORE": str(root / "before_tiles" / "t_*.las"),
            "AFTER": str(root / "after_tiles" / "t_*.las"),
            "FAULT": _fault_layer(xy),
            "SUMMARY": str(tmp_path / "s.json"),
            "PLANES": "memory:",
            "TILES": "memory:",
        }
    )
    layer = res["TILES"]
    if isinstance(layer, str):
        layer = QgsProject.instance().mapLayer(layer) or QgsProcessingUtils.mapLayerFromString(
            layer, None
        )
    feats = list(layer.getFeatures())
    assert feats
    for f in feats:
        box = f.geometry().boundingBox()
        assert box.width() == pytest.approx(100.0) and box.height() == pytest.approx(100.0)
