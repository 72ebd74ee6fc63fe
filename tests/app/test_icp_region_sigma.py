"""The icp job's variance factors per region (issue #18): the SPEC's options map onto
``windowed_icp``'s ``sigma_scaling``, and a CLI run records one factor per region."""

from __future__ import annotations

import json

import numpy as np
import pytest

from slipmap.app.icp import SPEC, core_kwargs
from slipmap.cli import main

X0, Y0 = 512000.0, 4780000.0


pytestmark = pytest.mark.usefixtures("drop_cli_log_handlers")


def test_spec_declares_the_options_once_with_the_field_factor_by_default():
    keys = [o.key for o in SPEC.options]
    assert keys.count("sigma_regions") == 1 and keys.count("sigma_region_by") == 1
    by_key = {o.key: o for o in SPEC.options}
    assert by_key["sigma_regions"].default == 1
    assert by_key["sigma_region_by"].choices == ("roughness", "density", "sigma")
    assert core_kwargs({"cell_m": 5.0})["sigma_scaling"] == "field"
    assert core_kwargs({"sigma_regions": 1})["sigma_scaling"] == "field"
    kw = core_kwargs({"sigma_regions": 3, "sigma_region_by": "density"})
    assert (kw["sigma_scaling"], kw["sigma_regions"], kw["sigma_region_by"]) == (
        "region",
        3,
        "density",
    )
    kw = core_kwargs({"sigma_regions": 3, "formal_sigma": True})
    assert kw["sigma_scaling"] == "formal" and "sigma_regions" not in kw


def _rough(n, seed, side=30.0):
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0, side, (n, 2))
    x, y = xy[:, 0], xy[:, 1]
    z = 0.5 * np.sin(x / 2.7) * np.cos(y / 3.1) + 0.06 * np.sin(x / 0.21 + np.sin(y / 0.37))
    z = z + rng.normal(0.0, np.where(x < side / 2, 0.002, 0.01))  # quiet west, noisy east
    return np.column_stack([xy + [X0, Y0], z + 100.0])


def test_cli_run_writes_the_regions_factors(tmp_path, capsys):
    pyproj = pytest.importorskip("pyproj")
    pytest.importorskip("osgeo.ogr", reason="GDAL/OGR (python3-gdal) missing")
    from slipmap.core.io.las import PointCloud, write_las

    crs = pyproj.CRS.from_epsg(32612)
    b, a = tmp_path / "b.las", tmp_path / "a.las"
    write_las(b, PointCloud(xyz=_rough(30000, 1), crs=crs))
    write_las(a, PointCloud(xyz=_rough(30000, 2) + [0.05, -0.03, 0.01], crs=crs))
    out = tmp_path / "out"
    argv = ["icp", str(b), str(a), "--cell", "3", "--coarse-to-fine", "0", "--out", str(out)]
    try:
        rc = main([*argv, "--sigma-regions", "2", "--sigma-region-by", "roughness"])
    except SystemExit as e:
        rc = e.code
    assert rc == 0, capsys.readouterr().err
    summary = json.loads((out / "icp.json").read_text())
    factors = summary["sigma_factor"]["regions"]
    assert len(factors) == 2 and all(f >= 1.0 for f in factors)
