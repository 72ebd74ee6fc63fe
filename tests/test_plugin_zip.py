"""``make plugin-zip`` (scripts/plugin_zip.sh) builds an installable QGIS plugin zip."""

import configparser
import re
import shutil
import subprocess
import zipfile
from pathlib import Path

import pytest

import slipmap

ROOT = Path(slipmap.__file__).resolve().parent
SCRIPT = ROOT / "scripts" / "plugin_zip.sh"


@pytest.fixture(scope="module")
def plugin_zip(tmp_path_factory):
    for tool in ("bash", "git", "python3"):
        if shutil.which(tool) is None:
            pytest.skip(f"{tool} is missing")
    if not SCRIPT.is_file() or not (ROOT / ".git").exists():
        pytest.skip("not a git checkout of the repository")
    out = tmp_path_factory.mktemp("zip") / "slipmap.zip"
    run = subprocess.run(
        ["bash", str(SCRIPT), str(out)], capture_output=True, text=True, timeout=120
    )
    assert run.returncode == 0, run.stderr
    with zipfile.ZipFile(out) as z:
        assert z.testzip() is None
        yield z


def test_top_folder_is_the_plugin(plugin_zip):
    names = plugin_zip.namelist()
    assert {n.split("/", 1)[0] for n in names} == {"slipmap"}
    for required in (
        "slipmap/metadata.txt",
        "slipmap/__init__.py",
        "slipmap/_version.py",
        "slipmap/LICENSE",
        "slipmap/qgis_plugin/__init__.py",
        "slipmap/qgis_plugin/provider.py",
        "slipmap/qgis_plugin/algorithms/displacement.py",
        "slipmap/core/__init__.py",
        "slipmap/app/pointaccuracy.py",
    ):
        assert required in names, required
    styles = [n for n in names if re.fullmatch(r"slipmap/styles/[^/]+\.qml", n)]
    on_disk = sorted(p.name for p in (ROOT / "styles").glob("*.qml"))
    assert sorted(Path(n).name for n in styles) == on_disk
    assert "slip_tiles.qml" in on_disk


def test_no_development_files(plugin_zip):
    for name in plugin_zip.namelist():
        parts = name.split("/")
        assert not {".git", "__pycache__", ".venv", ".venv-np2", ".pytest_cache"} & set(parts)
        assert parts[1] not in ("tests", "benchmarks", "scripts", ".ci"), name
        assert not name.endswith((".pyc", ".zip")), name


def test_metadata_version_is_pyproject_version(plugin_zip):
    meta = configparser.ConfigParser()
    meta.read_string(plugin_zip.read("slipmap/metadata.txt").decode("utf-8"))
    pyproject = plugin_zip.read("slipmap/pyproject.toml").decode("utf-8")
    version = re.search(r'^version = "([^"]+)"', pyproject, re.M).group(1)
    assert meta["general"]["version"] == version == slipmap.__version__
    assert meta["general"]["hasProcessingProvider"] == "yes"
