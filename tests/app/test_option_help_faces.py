"""Each face names other options by its own names in an option's help (issue #28, finding
9: QGIS's help named the CLI's --workers and --scheduler)."""

from __future__ import annotations

import importlib
import re

import pytest

from slipmap.app.options import JobSpec

JOBS = ("slip", "planes", "roughness", "accuracy", "piv", "icp", "dem_diff", "strain")


def _specs():
    for name in JOBS:
        module = importlib.import_module(f"slipmap.app.{name}")
        for value in vars(module).values():
            if isinstance(value, JobSpec):
                yield value


@pytest.mark.parametrize("face", ["cli", "qgis", "pdal"])
def test_no_face_shows_another_faces_names_or_placeholders(face):
    specs = list(_specs())
    assert len(specs) >= len(JOBS) - 1
    for spec in specs:
        for opt in spec.for_face(face):
            text = spec.help_in(opt, face)
            assert not re.search(r"\{\w+\}", text), (spec.name, opt.key, text)
            if face != "cli":
                assert not re.search(r"(^|[\s(])--[a-z]", text), (spec.name, opt.key, text)


def test_tiles_help_per_face():
    from slipmap.app import piv

    spec = piv.SPEC
    assert spec.help_in("before", "cli").endswith(
        "read block by block (also on Dask: --workers, --scheduler)"
    )
    # QGIS has no local workers (its Python is the QGIS process): the scheduler only
    assert spec.help_in("before", "qgis").endswith(
        'read block by block (also on Dask: "Dask scheduler address (tcp://host:port)")'
    )
