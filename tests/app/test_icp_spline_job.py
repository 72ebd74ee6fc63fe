"""The icp job's spline field (issue #18): the SPEC's options map onto ``windowed_icp``, and a
CLI run reports the field at the cell centres."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from slipmap.app.icp import SPEC, core_kwargs
from slipmap.cli import main

X0, Y0 = 512000.0, 4780000.0


pytestmark = pytest.mark.usefixtures("drop_cli_log_handlers")


def test_spec_declares_the_spline_options_once_with_spline_by_default():
    by_key = {o.key: o for o in SPEC.options}
    assert [o.key for o in SPEC.options].count("field_model") == 1
    assert by_key["field_model"].default is None  # unset: the spline (cells for tiles)
    assert core_kwargs({})["field_model"] == "spline"
    assert core_kwargs({})["detect_breaklines"] is True
    assert core_kwargs({"field_model": "cells"})["field_model"] == "cells"
    assert "detect_breaklines" not in core_kwargs({"field_model": "cells"})
    assert by_key["breaklines"].name_in("cli") == "--breaklines"
    assert by_key["field_model"].choices == ("cells", "spline")
    assert by_key["spline_spacing_m"].default is None
    assert by_key["spline_spacing_m"].name_in("qgis") == "SPLINE_SPACING"
    kw = core_kwargs({"field_model": "spline", "spline_spacing_m": 2.0, "spline_smoothing": 0.1})
    assert (kw["field_model"], kw["spline_spacing_m"], kw["spline_smoothing"]) == (
        "spline",
        2.0,
        0.1,
    )
    assert "spline_spacing_m" not in core_kwargs({"field_model": "spline"})
    assert by_key["spline_smoothing"].default is None  # estimated


def _rough(n, seed, side=30.0):
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0, side, (n, 2))
    x, y = xy[:, 0], xy[:, 1]
    z = 0.5 * np.sin(x / 2.7) * np.cos(y / 3.1) + 0.06 * np.sin(x / 0.21 + np.sin(y / 0.37))
    return np.column_stack([xy + [X0, Y0], z + 100.0 + rng.normal(0.0, 0.003, n)])


def test_cli_run_reports_the_spline_field_at_the_cell_centres(tmp_path, capsys):
    pyproj = pytest.importorskip("pyproj")
    pytest.importorskip("osgeo.ogr", reason="GDAL/OGR (python3-gdal) missing")
    from slipmap.core.io.las import PointCloud, write_las

    crs = pyproj.CRS.from_epsg(32612)
    b, a = tmp_path / "b.las", tmp_path / "a.las"
    shift = np.array([0.05, -0.03, 0.01])
    write_las(b, PointCloud(xyz=_rough(30000, 1), crs=crs))
    write_las(a, PointCloud(xyz=_rough(30000, 2) + shift, crs=crs))
    out = tmp_path / "out"
    argv = ["icp", str(b), str(a), "--cell", "5", "--field-model", "spline", "--out", str(out)]
    try:
        rc = main(argv)
    except SystemExit as e:
        rc = e.code
    assert rc == 0, capsys.readouterr().err
    with open(out / "icp.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    d = np.array([[float(r[k]) for k in ("dx", "dy", "dz")] for r in rows])
    inner = np.array([float(r["n"]) for r in rows]) > 500
    assert inner.sum() >= 9
    # a uniform shift: the spline reports it everywhere (LAS stores millimetres)
    assert np.abs(np.median(d[inner], axis=0) - shift).max() < 0.003
    summary = json.loads((out / "icp.json").read_text())
    assert summary["model"]["field"] == "spline" and summary["n_cells"] == len(rows)


def test_cli_breaklines_file_gives_a_field_that_jumps_across_it(tmp_path, capsys, line_file):
    """A slab moved 0.3 m beyond a straight scarp; ``--breaklines`` a GeoJSON line: the
    default field (the spline) recovers both sides, the line goes to icp.gpkg (styled) and
    icp.json."""
    pyproj = pytest.importorskip("pyproj")
    pytest.importorskip("osgeo.ogr", reason="GDAL/OGR (python3-gdal) missing")
    from slipmap.core.io.las import PointCloud, write_las
    from slipmap.core.io.vector import gpkg_layer_names, read_gpkg_layer

    crs = pyproj.CRS.from_epsg(32612)
    slab = np.array([0.0, -0.3, -0.05])
    a0, a1 = np.array([X0 + 13.7, Y0 - 5.0]), np.array([X0 + 15.2, Y0 + 35.0])

    def east(xy):
        return ((a1[0] - a0[0]) * (xy[:, 1] - a0[1]) - (a1[1] - a0[1]) * (xy[:, 0] - a0[0])) < 0

    after = _rough(40000, 2)
    after = after + east(after[:, :2])[:, None] * slab
    b, a, lines = tmp_path / "b.las", tmp_path / "a.las", tmp_path / "scarp.geojson"
    write_las(b, PointCloud(xyz=_rough(40000, 1), crs=crs))
    write_las(a, PointCloud(xyz=after, crs=crs))
    line_file(lines, [a0, a1], crs, driver="GeoJSON", layer="scarp")
    out = tmp_path / "out"
    argv = ["icp", str(b), str(a), "--cell", "5", "--breaklines", str(lines), "--out", str(out)]
    try:
        rc = main(argv)
    except SystemExit as e:
        rc = e.code
    assert rc == 0, capsys.readouterr().err
    with open(out / "icp.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    xy = np.array([[float(r["x"]), float(r["y"])] for r in rows])
    d = np.array([[float(r[k]) for k in ("dx", "dy", "dz")] for r in rows])
    n = np.array([float(r["n"]) for r in rows])
    truth = east(xy - slab[:2])[:, None] * slab
    from slipmap.core.breaklines import breaklines, distance_m

    far = (distance_m(xy, breaklines([np.array([a0, a1])])) >= 2.5) & (n > 500)
    assert far.sum() >= 12
    err = np.linalg.norm(d[far] - truth[far], axis=1)
    assert np.sqrt(np.mean(err**2)) < 0.005, err  # LAS stores millimetres
    summary = json.loads((out / "icp.json").read_text())
    assert summary["model"]["field"] == "spline"
    assert summary["breaklines"]["source"] == "given" and summary["breaklines"]["count"] == 1
    assert "breaklines" in gpkg_layer_names(out / "icp.gpkg")
    geoms, cols = read_gpkg_layer(out / "icp.gpkg", "breaklines")
    np.testing.assert_allclose(geoms[0][:, :2], [a0, a1], atol=1e-6)
    assert list(cols["source"]) == ["given"]
    import sqlite3

    with sqlite3.connect(out / "icp.gpkg") as db:
        styled = dict(db.execute("SELECT f_table_name, styleQML FROM layer_styles"))
    assert "215,25,28,255" in styled["breaklines"]  # styles/icp_breaklines.qml


def test_default_falls_back_to_cells_where_too_few_cells_hold_points(tmp_path, capsys):
    """One 40 m cell: too few for the default spline field; the run gives the cells' field
    and warns naming the option (asking for the spline explicitly is refused, as before)."""
    pyproj = pytest.importorskip("pyproj")
    pytest.importorskip("osgeo.ogr", reason="GDAL/OGR (python3-gdal) missing")
    from slipmap.core.io.las import PointCloud, write_las

    crs = pyproj.CRS.from_epsg(32612)
    b, a = tmp_path / "b.las", tmp_path / "a.las"
    write_las(b, PointCloud(xyz=_rough(20000, 1), crs=crs))
    write_las(a, PointCloud(xyz=_rough(20000, 2) + [0.05, -0.03, 0.01], crs=crs))
    out = tmp_path / "out"
    try:
        rc = main(["icp", str(b), str(a), "--cell", "40", "--out", str(out), "--no-progress"])
    except SystemExit as e:
        rc = e.code
    err = capsys.readouterr().err
    assert rc == 0, err
    assert "too few cells for the default spline field" in err and "--cell" in err
    summary = json.loads((out / "icp.json").read_text())
    assert summary["model"]["field"] == "cells" and summary["breaklines"]["source"] == "none"


def test_cli_registers_at_most_2000_points_per_cell_by_default_and_0_means_all(tmp_path, capsys):
    """``--max-points-per-cell``: 2000 after-points per cell by default (docs/benchmarks.md
    "Stop 39"), every point with 0; both recover the known shift."""
    pyproj = pytest.importorskip("pyproj")
    pytest.importorskip("osgeo.ogr", reason="GDAL/OGR (python3-gdal) missing")
    from slipmap.core.io.las import PointCloud, write_las

    opts = SPEC.parse({"before": "b", "after": "a", "out": "o"}, run_check=False)
    assert core_kwargs(opts)["max_points_per_cell"] == 2000
    crs = pyproj.CRS.from_epsg(32612)
    b, a = tmp_path / "b.las", tmp_path / "a.las"
    shift = np.array([0.04, -0.02, 0.01])
    write_las(b, PointCloud(xyz=_rough(60_000, 1, side=20.0), crs=crs))
    write_las(a, PointCloud(xyz=_rough(60_000, 2, side=20.0) + shift, crs=crs))
    used = {}
    for extra in ([], ["--max-points-per-cell", "0"]):
        out = tmp_path / f"out{len(extra)}"
        argv = ["icp", str(b), str(a), "--cell", "5", "--field-model", "cells", "--out", str(out)]
        try:
            rc = main(argv + extra)
        except SystemExit as e:
            rc = e.code
        assert rc == 0, capsys.readouterr().err
        with open(out / "icp.csv", newline="") as fh:
            rows = list(csv.DictReader(fh))
        n = np.array([float(r["n"]) for r in rows])  # points in the cell's fit
        d = np.array([[float(r[k]) for k in ("dx", "dy", "dz")] for r in rows])
        full = n >= 0.8 * n.max()
        assert np.abs(np.median(d[full], axis=0) - shift).max() < 0.003
        used[len(extra)] = n
    assert 1500 < used[0].max() <= 2000
    assert used[2].max() > 3000  # 60 000 points on 20 m: about 3750 per full 5 m cell
