"""The HTML report's numbers read as numbers (issue #19): no 6-digit scientific notation."""

from __future__ import annotations

import math

import pytest

from slipmap.app.report import readable_number, write_html_report


@pytest.mark.parametrize(
    "value, text",
    [
        (0.01787376887892927, "0.01787"),
        (17.87376887892927, "17.87"),
        (215334.0, "215334"),
        (4.0, "4"),
        (0.125, "0.125"),
        (-0.00031976455510361287, "-3.20e-4"),
        (1.5988e-05, "1.60e-5"),
        (0.0, "0"),
        (2.5e7, "2.50e+7"),
        (math.nan, "nan"),
    ],
)
def test_readable_number(value, text):
    assert readable_number(value) == text


def test_report_cells_have_no_long_exponents(tmp_path):
    tables = {"relative": {"right_lateral_slip": 0.01787376887892927, "sigma": 1.5988173e-4}}
    html = write_html_report(tmp_path / "report_numbers.html", "t", tables, []).read_text()
    assert "<td>0.01787</td>" in html and "<td>1.60e-4</td>" in html
    assert "e-05" not in html and "0.0178738" not in html
