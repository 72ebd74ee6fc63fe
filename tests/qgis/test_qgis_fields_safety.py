"""Bad input to the field algorithms in QGIS (piv, windowedicp, demdiff, strain): a
QgsProcessingException naming the dialog's label, inputs byte-identical, nothing written."""

import hashlib

import numpy as np
import pytest

pytestmark = pytest.mark.qgis

X0, Y0 = 512000.0, 4780000.0


def _rough(n, seed, side=20.0):
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0, side, (n, 2))
    x, y = xy[:, 0], xy[:, 1]
    z = 0.5 * np.sin(x / 2.7) * np.cos(y / 3.1) + 0.06 * np.sin(x / 0.21 + np.sin(y / 0.37))
    return np.column_stack([xy + [X0, Y0], z + 100.0])


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    import pyproj

    from slipmap.core.io.las import PointCloud, write_las

    d = tmp_path_factory.mktemp("q_fields_safety")
    crs = pyproj.CRS.from_epsg(32612)
    write_las(d / "b.las", PointCloud(xyz=_rough(8000, 1), crs=crs))
    write_las(d / "a.las", PointCloud(xyz=_rough(8000, 2) + [0.1, -0.1, 0.02], crs=crs))
    return d / "b.las", d / "a.las"


def _sha(p):
    return hashlib.sha256(p.read_bytes()).hexdigest()


def _listing(folder):
    return sorted((str(p.relative_to(folder)), _sha(p)) for p in folder.rglob("*") if p.is_file())


def _run(alg_id, params):
    import processing
    from qgis.core import QgsProcessingContext, QgsProcessingException, QgsProcessingFeedback

    class Feedback(QgsProcessingFeedback):
        def __init__(self):
            super().__init__()
            self.errors = []

        def reportError(self, error, fatalError=False):  # noqa: N802, N803
            self.errors.append(error)
            super().reportError(error, fatalError)

    feedback = Feedback()
    with pytest.raises(QgsProcessingException) as raised:
        processing.run(
            f"slipmap:{alg_id}", params, context=QgsProcessingContext(), feedback=feedback
        )
    return str(raised.value) + " " + " ".join(feedback.errors)


def _piv_params(b, a, d, **kw):
    params = {
        "BEFORE": str(b),
        "AFTER": str(a),
        "GRID": 0.5,
        "WINDOWS": "16 8",
        "VECTORS": str(d / "v.gpkg"),
        "DX": str(d / "dx.tif"),
        "DY": str(d / "dy.tif"),
        "DZ": str(d / "dz.tif"),
        "SUMMARY": str(d / "piv.json"),
    }
    params.update(kw)
    return params


@pytest.fixture
def never_computed(monkeypatch):
    def boom(*a, **k):
        raise AssertionError("the computation ran before the refusal")

    import slipmap.core.dem as dem
    import slipmap.core.icp as icp
    import slipmap.core.piv as piv

    monkeypatch.setattr(piv, "piv", boom)
    monkeypatch.setattr(icp, "windowed_icp", boom)
    monkeypatch.setattr(dem, "dem_difference", boom)


def test_piv_output_over_an_input(provider, pair, tmp_path, never_computed):
    b, a = pair
    control = tmp_path / "control.csv"
    control.write_text("x,y,dx,dy\n512010,4780010,0.1,-0.1\n")
    before = _sha(control)
    message = _run("piv", _piv_params(b, a, tmp_path, CONTROL=str(control), SUMMARY=str(control)))
    assert '"PIV summary"' in message and "never overwrites an input" in message
    assert '"Control points x,y,dx,dy[,dz] (CSV)"' in message
    assert _sha(control) == before and _listing(tmp_path) == [("control.csv", before)]


def test_windowedicp_summary_over_the_before_epoch(provider, pair, tmp_path, never_computed):
    b, a = pair
    src = tmp_path / "b.las"
    src.write_bytes(b.read_bytes())
    before = _sha(src)
    message = _run(
        "windowedicp",
        {
            "BEFORE": str(src),
            "AFTER": str(a),
            "CELLS": "TEMPORARY_OUTPUT",
            "VECTORS": "TEMPORARY_OUTPUT",
            "SUMMARY": str(src),
        },
    )
    assert '"ICP summary"' in message and '"Before epoch"' in message
    assert _sha(src) == before and _listing(tmp_path) == [("b.las", before)]


def test_demdiff_same_file_as_both_epochs(provider, pair, tmp_path, never_computed):
    b, _ = pair
    message = _run(
        "demdiff",
        {
            "BEFORE": str(b),
            "AFTER": str(b),
            "GRID": 0.5,
            "OUTPUT": str(tmp_path / "dd.tif"),
            "SUMMARY": str(tmp_path / "dd.json"),
        },
    )
    assert '"After epoch"' in message and '"Before epoch"' in message
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("alg_id", ["piv", "demdiff"])
def test_grid_too_fine_refused_before_allocating(provider, pair, tmp_path, alg_id, never_computed):
    b, a = pair
    if alg_id == "piv":
        params = _piv_params(b, a, tmp_path, GRID=1e-5)
        label = '"Grid size GR (m)"'
    else:
        params = {
            "BEFORE": str(b),
            "AFTER": str(a),
            "GRID": 1e-5,
            "OUTPUT": str(tmp_path / "dd.tif"),
            "SUMMARY": str(tmp_path / "dd.json"),
        }
        label = '"Grid size (m)"'
    message = _run(alg_id, params)
    assert label in message and "GiB" in message
    assert list(tmp_path.iterdir()) == []


def test_piv_summary_in_an_unwritable_place(provider, pair, tmp_path, never_computed):
    b, a = pair
    (tmp_path / "file.txt").write_text("x")
    message = _run(
        "piv", _piv_params(b, a, tmp_path, SUMMARY=str(tmp_path / "file.txt" / "piv.json"))
    )
    assert '"PIV summary"' in message
    assert _listing(tmp_path) == [("file.txt", _sha(tmp_path / "file.txt"))]


def test_piv_control_points_outside_the_field(provider, pair, tmp_path):
    b, a = pair
    control = tmp_path / "far.csv"
    control.write_text("x,y,dx,dy\n511000,4780000,0.1,-0.1\n514000,4780000,0.1,-0.1\n")
    before = _listing(tmp_path)
    out = tmp_path / "out"
    out.mkdir()
    message = _run("piv", _piv_params(b, a, out, CONTROL=str(control)))
    assert '"Control points x,y,dx,dy[,dz] (CSV)"' in message
    assert "2 row(s) read" in message and "2 outside the field" in message
    assert list(out.iterdir()) == [] and _listing(tmp_path) == before


def test_piv_bad_windows_named_by_label(provider, pair, tmp_path):
    from qgis.core import QgsApplication, QgsProcessingContext

    b, a = pair
    alg = QgsApplication.processingRegistry().algorithmById("slipmap:piv")
    ok, msg = alg.checkParameterValues(
        _piv_params(b, a, tmp_path, WINDOWS="16 nan"), QgsProcessingContext()
    )
    assert not ok and msg.startswith('"Interrogation windows per pass (pixels)"'), msg
    ok, msg = alg.checkParameterValues(
        _piv_params(b, a, tmp_path, CLASSES="2 x"), QgsProcessingContext()
    )
    assert not ok and msg.startswith('"Keep only these classes (e.g. 6)"'), msg
    assert list(tmp_path.iterdir()) == []


def test_strain_off_lattice_table_names_the_field_not_the_function(provider, tmp_path):
    (tmp_path / "f.csv").write_text("x,y,dx,dy\n0,0,0,0\n1,0,0,0\n2,0,0,0\n3.37,0,0,0\n")
    before = _listing(tmp_path)
    message = _run(
        "strain",
        {
            "FIELD": str(tmp_path / "f.csv"),
            "OUTPUT": str(tmp_path / "s.tif"),
            "SUMMARY": str(tmp_path / "s.json"),
        },
    )
    assert '"Displacement field (vectors layer or CSV)"' in message
    assert (
        "field_from_columns" not in message and '"Vector spacing (m; default inferred)"' in message
    )
    assert _listing(tmp_path) == before


def test_strain_geographic_crs_refused(provider, tmp_path):
    (tmp_path / "f.csv").write_text("x,y,dx,dy\n0,0,0,0\n1,0,0,0\n0,1,0,0\n1,1,0,0\n")
    message = _run(
        "strain",
        {
            "FIELD": str(tmp_path / "f.csv"),
            "CRS": "EPSG:4326",
            "OUTPUT": str(tmp_path / "s.tif"),
            "SUMMARY": str(tmp_path / "s.json"),
        },
    )
    assert '"CRS of the field (when it has none or a wrong one)"' in message
    assert "geographic" in message and not (tmp_path / "s.tif").exists()
