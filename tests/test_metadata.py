"""QGIS plugin metadata agrees with pyproject.toml (the one place the version lives)."""

import configparser
import re
from pathlib import Path

import slipmap

ROOT = Path(slipmap.__file__).resolve().parent


def test_version_from_pyproject():
    text = (ROOT / "pyproject.toml").read_text(encoding="utf-8")
    assert re.search(r'^version = "([^"]+)"', text, re.M).group(1) == slipmap.__version__


def test_metadata_matches_pyproject():
    meta = configparser.ConfigParser()
    meta.read(ROOT / "metadata.txt", encoding="utf-8")
    general = meta["general"]
    assert general["version"] == slipmap.__version__
    assert general["qgisMinimumVersion"] == "3.22"
    assert general["hasProcessingProvider"] == "yes"
    for key in ("name", "description", "about", "author", "email", "repository", "tracker"):
        assert general.get(key), key
