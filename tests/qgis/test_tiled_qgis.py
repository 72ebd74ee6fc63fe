"""Tiled inputs in QGIS (issue #17): a glob of tiles (the file widget takes a pattern ending
in .las/.laz) runs in process; the Dask scheduler address and the processing tile are
advanced parameters; no local cluster from QGIS."""

import json

import numpy as np
import pytest

pytestmark = pytest.mark.qgis


@pytest.fixture(scope="module")
def tiles(tmp_path_factory):
    from slipmap.core.io.las import PointCloud, read_las, write_las
    from slipmap.core.synthetic import make_scene

    root = tmp_path_factory.mktemp("q_tiles")
    scene = make_scene("mls", seed=4, n_buildings=1, extent_m=50.0, origin=(500000, 4200000, 10))
    write_las(root / "whole.las", PointCloud(xyz=scene.points, attributes={}))
    cloud = read_las(root / "whole.las")
    folder = root / "tiles"
    folder.mkdir()
    k = np.floor((cloud.xyz[:, 0] - 500000) / 25.0).astype(int)
    for key in np.unique(k):
        write_las(folder / f"t{key}.las", cloud.subset(k == key))
    return folder


def _alg():
    from qgis.core import QgsApplication

    return QgsApplication.processingRegistry().algorithmById("slipmap:planes")


def test_scale_parameters_are_advanced_and_no_local_workers(provider):
    from qgis.core import QgsProcessingParameterDefinition

    alg = _alg()
    names = {p.name(): p for p in alg.parameterDefinitions()}
    assert "WORKERS" not in names
    for name in ("SCHEDULER", "TILE_SIZE"):
        flags = names[name].flags()
        assert flags & QgsProcessingParameterDefinition.FlagAdvanced, name


def test_glob_of_tiles_runs_in_process(provider, tiles, tmp_path):
    import processing
    from qgis.core import QgsProcessingContext, QgsProcessingFeedback

    summary = tmp_path / "planes.json"
    processing.run(
        "slipmap:planes",
        {
            "INPUT": str(tiles / "t*.las"),
            "OUTPUT": str(tmp_path / "labelled.las"),
            "SUMMARY": str(summary),
            "TILE_SIZE": 20.0,
        },
        context=QgsProcessingContext(),
        feedback=QgsProcessingFeedback(),
    )
    got = json.loads(summary.read_text())
    assert got["tiles"]["files"] == 2 and got["tiles"]["engine"] == "in-process"
    assert len(got["planes"]) > 0
    assert not (tmp_path / "labelled.las").exists()  # tiled runs write the summary only


def test_bad_scheduler_named_by_label(provider, tiles, tmp_path):
    import processing
    from qgis.core import QgsProcessingContext, QgsProcessingException, QgsProcessingFeedback

    with pytest.raises(QgsProcessingException) as e:
        processing.run(
            "slipmap:planes",
            {
                "INPUT": str(tiles / "t*.las"),
                "SUMMARY": str(tmp_path / "s.json"),
                "SCHEDULER": "nohost",
            },
            context=QgsProcessingContext(),
            feedback=QgsProcessingFeedback(),
        )
    assert "Dask scheduler address" in str(e.value)
    assert not (tmp_path / "s.json").exists()
