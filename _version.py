"""The package version, read from the one place it lives: pyproject.toml.

Installed packages answer through importlib.metadata; a plugin folder copied into QGIS (no
installation) reads ``pyproject.toml`` or ``metadata.txt`` beside this file.
"""

from __future__ import annotations

import re
from pathlib import Path


def _read_version() -> str:
    here = Path(__file__).resolve().parent
    pyproject = here / "pyproject.toml"
    if pyproject.is_file():
        m = re.search(r'^version\s*=\s*"([^"]+)"', pyproject.read_text("utf-8"), re.M)
        if m:
            return m.group(1)
    try:
        from importlib.metadata import PackageNotFoundError, version

        return version("slipmap")
    except (ImportError, PackageNotFoundError):
        pass
    meta = here / "metadata.txt"
    if meta.is_file():
        m = re.search(r"^version\s*=\s*(\S+)", meta.read_text("utf-8"), re.M)
        if m:
            return m.group(1)
    return "0+unknown"


__version__ = _read_version()
