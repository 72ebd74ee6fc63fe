"""CSV columns and control points (core.io.table)."""

from __future__ import annotations

import numpy as np
import pytest

from slipmap.core.errors import InputDataError, InvalidParameterError, SlipMapFileError
from slipmap.core.io.table import read_control_points, read_csv_columns, write_csv_columns


def test_round_trip_keeps_every_digit_nan_and_types(tmp_path):
    rng = np.random.default_rng(0)
    x = 515369.0 + rng.uniform(0, 40, 50)
    d = rng.normal(0, 1e-3, 50)
    d[3] = np.nan
    valid = rng.uniform(size=50) > 0.5
    n = np.arange(50, dtype=np.int64)
    path = write_csv_columns(tmp_path / "t.csv", {"x": x, "dx": d, "valid": valid, "n": n})
    lines = path.read_text().splitlines()
    assert lines[0] == "x,dx,valid,n" and len(lines) == 51
    back = read_csv_columns(path, required=("x", "dx", "valid", "n"))
    np.testing.assert_array_equal(back["x"], x)  # bit for bit
    np.testing.assert_array_equal(back["dx"], d)
    np.testing.assert_array_equal(back["valid"], valid.astype(float))
    np.testing.assert_array_equal(back["n"], n)
    assert "-0.0" not in write_csv_columns(tmp_path / "z.csv", {"a": [-0.0]}).read_text()


def test_read_is_lenient_on_case_separator_comments_and_empty_cells(tmp_path):
    p = tmp_path / "c.csv"
    p.write_text("# GPS control\n X ; Y ;DX;dy\n1;2;0.5;\n3;4;-0.25;0.1\n")
    cols = read_csv_columns(p, required=("x", "y", "dx", "dy"), optional=("dz",))
    np.testing.assert_array_equal(cols["dx"], [0.5, -0.25])
    assert np.isnan(cols["dy"][0]) and "dz" not in cols
    xy, d = read_control_points(p)
    assert xy.shape == (2, 2) and d.shape == (2, 3) and np.isnan(d[:, 2]).all()


def test_errors_name_file_row_and_column(tmp_path):
    p = tmp_path / "bad.csv"
    p.write_text("x,y,dx,dy\n1,2,abc,0\n")
    with pytest.raises(InputDataError, match=r"row 2, column 'dx'.*abc"):
        read_control_points(p)
    p.write_text("x,y,dx\n1,2,3\n")
    with pytest.raises(InputDataError, match="missing column.*dy"):
        read_control_points(p)
    p.write_text("x,y,dx,dy\n")
    with pytest.raises(InputDataError, match="no control points"):
        read_control_points(p)
    p.write_text("x,y,dx,dy\n1,2,0,0\n,2,0,0\n")
    with pytest.raises(InputDataError, match=r"1 of 2 control point.*row\(s\) 3\)"):
        read_control_points(p)
    p.write_text("")
    with pytest.raises(InputDataError, match="empty"):
        read_control_points(p)
    with pytest.raises(SlipMapFileError):
        read_control_points(tmp_path / "missing.csv")
    with pytest.raises(InvalidParameterError, match="differ in length"):
        write_csv_columns(tmp_path / "x.csv", {"a": [1, 2], "b": [1]})
    assert not (tmp_path / "x.csv").exists()
