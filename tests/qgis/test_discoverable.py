"""Every SlipMap algorithm can be found and understood in the toolbox (issue #19, part)."""

import logging
from pathlib import Path

import pytest

import slipmap

pytestmark = pytest.mark.qgis


@pytest.fixture(scope="module")
def algorithms(qgis_app):
    from qgis.core import QgsApplication

    plugin = slipmap.classFactory(None)
    plugin.initProcessing()
    provider = QgsApplication.processingRegistry().providerById("slipmap")
    yield provider, provider.algorithms()
    plugin.unload()


def test_provider_and_algorithms_have_icons(algorithms):
    provider, algs = algorithms
    assert Path(provider.svgIconPath()).is_file() and not provider.icon().isNull()
    assert len(algs) >= 8
    for alg in algs:
        assert Path(alg.svgIconPath()).is_file(), alg.id()
        assert not alg.icon().isNull(), alg.id()


def test_toolbox_search_finds_them_by_lidar(algorithms):
    _, algs = algorithms
    for alg in algs:
        tags = alg.tags()
        assert "lidar" in tags and "point cloud" in tags, alg.id()
        assert alg.helpUrl().endswith("#" + alg.name()), alg.id()
        assert alg.shortDescription(), alg.id()


def test_metadata_icon_exists():
    import configparser

    root = Path(slipmap.__file__).resolve().parent
    meta = configparser.ConfigParser()
    meta.read(root / "metadata.txt")
    assert (root / meta["general"]["icon"]).is_file()


def test_log_and_warnings_reach_the_processing_log(algorithms):
    import warnings

    from qgis.core import QgsProcessingFeedback

    from slipmap.qgis_plugin.algorithms._base import attach_feedback

    class Feedback(QgsProcessingFeedback):
        def __init__(self):
            super().__init__()
            self.lines = []

        def pushWarning(self, text):  # noqa: N802
            self.lines.append(("warning", text))

        def pushInfo(self, text):  # noqa: N802
            self.lines.append(("info", text))

    fb = Feedback()
    attach_feedback(fb)
    logging.getLogger("slipmap.core.icp").warning("cell 3 did not converge")
    from slipmap.core import icp

    warnings.warn_explicit("from the package", UserWarning, icp.__file__, 1)
    assert ("warning", "cell 3 did not converge") in fb.lines
    assert ("warning", "from the package") in fb.lines
    attach_feedback(None)


def test_progress_text_is_throttled():
    from qgis.core import QgsProcessingFeedback

    from slipmap.qgis_plugin.algorithms._base import progress_callback

    class Feedback(QgsProcessingFeedback):
        def __init__(self):
            super().__init__()
            self.texts = []

        def setProgressText(self, text):  # noqa: N802
            self.texts.append(text)

    fb = Feedback()
    cb = progress_callback(fb)
    for i in range(90):
        cb(i / 90, f"window {i + 1}/90")
    cb(1.0, "writing outputs")
    assert len(fb.texts) <= 5 and fb.texts[0] == "window 1/90" and fb.texts[-1] == "writing outputs"
