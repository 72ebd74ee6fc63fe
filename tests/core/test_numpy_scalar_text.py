"""Numpy scalars in text outputs read as numbers under numpy 1 and 2.

numpy 2 changed ``repr`` of a scalar to ``np.float64(1.5)``: text made with ``repr`` or from a
list of numpy scalars (WKT, CSV, HTML, messages) must not carry it (issue #20)."""

from __future__ import annotations

import numpy as np
import pytest

from slipmap.app.report import write_html_report
from slipmap.core.errors import InputDataError
from slipmap.core.fields import _axis_lattice
from slipmap.core.io.table import write_csv_columns


def test_csv_numbers_from_numpy_scalars(tmp_path):
    path = write_csv_columns(
        tmp_path / "t.csv",
        {"x": np.array([np.float64(0.1), -0.0]), "n": np.array([3, 4]), "f": np.array([1.5, 2.0])},
    )
    assert path.read_text().splitlines() == ["x,n,f", "0.1,3,1.5", "0.0,4,2.0"]


def test_html_cells_from_numpy_scalars(tmp_path):
    tables = {
        "run": {
            "spacing_m": (np.float64(0.25), np.float64(0.5)),
            "counts": [np.int64(3), np.int32(4)],
            "sigma_m": np.float32(0.125),
        }
    }
    text = write_html_report(tmp_path / "r.html", "t", tables, []).read_text()
    assert "np." not in text
    assert "<td>(0.25, 0.5)</td>" in text and "<td>[3, 4]</td>" in text
    assert "<td>0.125</td>" in text


def test_lattice_message_names_a_number():
    x = np.array([0.0, 1.0, 2.0, 3.37, 4.0])
    with pytest.raises(InputDataError) as err:
        _axis_lattice(x, 1.0, 0.01, "x")
    assert "x = 3.37 " in str(err.value) and "np." not in str(err.value)
