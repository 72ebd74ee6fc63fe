"""The spline field on tiled inputs (issue #29, item 4): each tile block gives its share of
every iteration's normal equations and the driver solves once, so a tiled run equals the
one-file run (to 1e-6 m in every reported value), in process and on two Dask workers, from
the API and the CLI; a block boundary through a lobe leaves no seam; given breaklines keep
the step on tiles as in one file; a cancel stops it."""

from __future__ import annotations

import numpy as np
import pytest
from test_tiled_fields import ORIGIN, UTM11, _cli, _rows, _terrain, _whole, _write_epochs

from slipmap.app import tiled_fields as tf
from slipmap.core.errors import CancelledError
from slipmap.core.icp import windowed_icp
from slipmap.core.io.tiles import open_collection
from slipmap.core.synthetic import LobeField, SlumpField

#: every reported value of the tiled run within this of the one-file run's (m, m², ...)
TOL = 1e-6
#: a lobe 20 m across moving 0.3 m south and 0.1 m down, centred on a block boundary (x 30 m)
LOBE = LobeField(centre_xy=(30.0, 20.0), radius_x_m=10.0, radius_y_m=10.0, max_d_m=(0, -0.3, -0.1))
COLUMNS = ("x", "y", "z", "dx", "dy", "dz", "sigma_dx", "sigma_dy", "sigma_dz", "rmse", "n",
           "sigma0", "exx", "eyy", "exy", "rx", "ry", "rz", "sigma_rz", "n_after", "n_before",
           "flagged", "converged", "iterations", "from_cell")  # fmt: skip


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """Independent samplings (17 pts/m²) of 60 x 40 m of rough ground before and after the
    lobe, as one LAZ per epoch and as 23 m / 19 m tiles (the blocks follow neither)."""
    root = tmp_path_factory.mktemp("tiled_spline")
    rng = np.random.default_rng(5)
    before = _terrain(rng, 40_000, 60.0, 40.0)
    after = _terrain(rng, 40_000, 60.0, 40.0)
    after = after + LOBE(after[:, :2])
    return _write_epochs(root, before, after)


def _truth(x, y):
    """The lobe's motion of the material now at (x, y) (map metres)."""
    c = np.c_[x, y] - ORIGIN[:2]
    p0 = c.copy()
    for _ in range(30):
        p0 = c - LOBE(p0)[:, :2]
    return LOBE(p0)


def _equal(got, want, where=""):
    assert len(got.x) == len(want.x) > 60, where
    assert got.skipped == want.skipped, where
    for key in COLUMNS:
        if getattr(want, key) is None:  # from_cell: a spline field's only
            assert getattr(got, key) is None, (where, key)
            continue
        a = np.asarray(getattr(got, key), float)
        b = np.asarray(getattr(want, key), float)
        assert np.max(np.abs(a - b)) <= TOL, (where, key, np.max(np.abs(a - b)))
    assert got.sigma_factor == pytest.approx(want.sigma_factor, abs=TOL)
    # the block covariances (the cells' block size, the spline's ratio) and the floor
    for key in ("sigma_block_m", "sigma_block_ratio", "sigma_floor_factor", "sigma_n_cap"):
        a, b = float(getattr(got, key)), float(getattr(want, key))
        assert a == pytest.approx(b, rel=1e-6, nan_ok=True), (where, key, a, b)


def test_spline_on_blocks_equals_the_one_file_run_without_a_seam(scene):
    """Blocks of 3 x 3 cells (15 m): boundaries at x 15, 30 and 45 m cross the lobe."""
    before = open_collection(str(scene / "before_tiles"))
    after = open_collection(str(scene / "after_tiles"))
    kw = dict(cell_m=5.0, min_points=50, field_model="spline", spline_spacing_m=5.0)
    whole = windowed_icp(_whole(before), _whole(after), **kw)
    tiled = tf.icp_tiled(before, after, tile_size_m=15.0, **kw)
    _equal(tiled, whole, "in process")
    assert tiled.field_model == "spline"
    assert whole.sigma_model == "blocks" and np.isfinite(whole.sigma_block_ratio)
    # no seam: the cells beside a block boundary are as close to the lobe as the others
    x = tiled.x - ORIGIN[0]
    err = np.linalg.norm(np.c_[tiled.dx, tiled.dy, tiled.dz] - _truth(tiled.x, tiled.y), axis=1)
    inside = np.linalg.norm(_truth(tiled.x, tiled.y), axis=1) > 0.01
    edge = np.isin(np.round(x, 1), [12.5, 17.5, 27.5, 32.5, 42.5, 47.5])
    rms = lambda m: float(np.sqrt(np.mean(err[m] ** 2)))  # noqa: E731
    assert inside.sum() > 8 and (inside & edge).sum() >= 4
    assert rms(inside & edge) < 0.03 and rms(inside & ~edge) < 0.03
    assert rms(inside & edge) < rms(inside & ~edge) + 0.01


def test_a_cancel_stops_the_tiled_spline_fit(scene):
    before = open_collection(str(scene / "before_tiles"))
    after = open_collection(str(scene / "after_tiles"))
    seen = []

    def progress(fraction, message):
        seen.append(message)
        if message.startswith("spline field: iteration 2"):
            raise CancelledError("cancelled")

    with pytest.raises(CancelledError):
        tf.icp_tiled(before, after, tile_size_m=15.0, cell_m=5.0, min_points=50,
                     field_model="spline", spline_spacing_m=5.0, progress=progress)  # fmt: skip
    assert any(m.startswith("spline field: iteration 1") for m in seen)
    assert not tf._CHUNKS  # the blocks' cache is emptied


def test_cli_spline_on_tiles_in_process_and_on_two_dask_workers_equals_one_file(
    scene, tmp_path, capsys
):
    """``slipmap icp TILES_BEFORE TILES_AFTER --field-model spline`` (knots a cell apart: the
    default half cell gives the same equality, at twice the time)."""
    extra = [
        "--cell",
        "5",
        "--min-points",
        "50",
        "--field-model",
        "spline",
        "--spline-spacing",
        "5",
    ]
    ref = tmp_path / "one"
    rc, err = _cli(["icp", str(scene / "before.laz"), str(scene / "after.laz"), *extra,
                    "--out", str(ref)], capsys)  # fmt: skip
    assert rc == 0, err
    want = _rows(ref / "icp.csv")
    runs = {"in process": []}
    try:
        import distributed  # noqa: F401

        runs["dask"] = ["--workers", "2"]
    except ImportError:
        pass
    tiles = [str(scene / "before_tiles"), str(scene / "after_tiles")]
    for where, engine in runs.items():
        out = tmp_path / where.replace(" ", "_")
        rc, err = _cli(["icp", *tiles, *extra, "--tile-size", "20", *engine, "--out", str(out)],
                       capsys)  # fmt: skip
        assert rc == 0, (where, err)
        got = _rows(out / "icp.csv")
        assert set(got) == set(want) and len(got["x"]) == len(want["x"]) > 60
        for key in want:
            assert np.max(np.abs(got[key] - want[key])) <= TOL, (where, key)
    if "dask" not in runs:
        pytest.skip("dask.distributed is not installed: the in-process run only")


def test_a_spline_too_fine_for_tiles_is_refused_from_the_headers(scene, tmp_path, capsys):
    """The knots are counted from the tiles' header boxes before any point is read."""
    out = tmp_path / "out"
    rc, err = _cli(["icp", str(scene / "before_tiles"), str(scene / "after_tiles"), "--cell", "5",
                    "--field-model", "spline", "--spline-spacing", "0.01", "--out", str(out)],
                   capsys)  # fmt: skip
    assert rc == 2
    assert len(err) == 1 and "--spline-spacing" in err[0] and "knots" in err[0], err
    assert not out.exists()


#: a slab moved beyond a straight scarp that crosses the blocks' boundaries (local metres)
SCARP = np.array([[26.0, -5.0], [36.0, 45.0]])
SLAB = np.array([0.05, -0.25, -0.06])


def _beyond(xy):
    """True east of SCARP (local metres)."""
    (x0, y0), (x1, y1) = SCARP
    return (x1 - x0) * (xy[:, 1] - y0) - (y1 - y0) * (xy[:, 0] - x0) < 0


@pytest.fixture(scope="module")
def slab(tmp_path_factory):
    """The ground of ``scene`` with a slab moved beyond a scarp instead of a lobe, as one LAZ
    per epoch and as tiles."""
    root = tmp_path_factory.mktemp("tiled_slab")
    rng = np.random.default_rng(8)
    before = _terrain(rng, 40_000, 60.0, 40.0)
    after = _terrain(rng, 40_000, 60.0, 40.0)
    after = after + _beyond(after[:, :2])[:, None] * SLAB
    return _write_epochs(root, before, after)


def test_given_breaklines_on_blocks_equal_the_one_file_run_and_keep_the_step(slab):
    """Given breaklines on tiles (issue #29 item 4): the blocks' chunks take the knot copies
    of the line's far side, so the tiled field equals the one-file field with the same line
    (1e-6 m) and keeps the step: both sides recovered, where a field without the line
    smooths it."""
    from slipmap.core.breaklines import breaklines, distance_m

    before = open_collection(str(slab / "before_tiles"))
    after = open_collection(str(slab / "after_tiles"))
    line = breaklines([SCARP + ORIGIN[:2]])
    kw = dict(cell_m=5.0, min_points=50, field_model="spline", spline_spacing_m=5.0)
    whole = windowed_icp(_whole(before), _whole(after), breaklines=line, **kw)
    tiled = tf.icp_tiled(before, after, tile_size_m=15.0, breaklines=line, **kw)
    _equal(tiled, whole, "given breaklines")
    assert tiled.breaklines_source == "given" and len(tiled.breaklines) == 1
    xy = np.c_[tiled.x, tiled.y] - ORIGIN[:2]
    truth = _beyond(xy - SLAB[:2])[:, None] * SLAB  # the material now at the centre
    far = distance_m(xy, breaklines([SCARP])) >= 3.0
    err = np.linalg.norm(np.c_[tiled.dx, tiled.dy, tiled.dz] - truth, axis=1)
    smooth = tf.icp_tiled(before, after, tile_size_m=15.0, **kw)
    err_s = np.linalg.norm(np.c_[smooth.dx, smooth.dy, smooth.dz] - truth, axis=1)
    rms = lambda e: float(np.sqrt(np.mean(e[far] ** 2)))  # noqa: E731
    assert far.sum() >= 40
    # measured 1.3 mm with the line, 9.4 mm without it (85 cells >= 3 m from the scarp)
    assert rms(err) < 0.004 and rms(err) < 0.5 * rms(err_s), (rms(err), rms(err_s))


def test_cli_breaklines_file_on_tiles_equals_the_one_file_run(slab, tmp_path, capsys, line_file):
    """``slipmap icp TILES TILES --breaklines FILE``: accepted on tiles (refused before), the
    same cells as the one-file run within 1e-6, and the line in the GeoPackage."""
    from slipmap.core.io.vector import gpkg_layer_names

    lines = tmp_path / "scarp.geojson"
    line_file(lines, SCARP + ORIGIN[:2], UTM11, driver="GeoJSON", layer="scarp")
    extra = ["--cell", "5", "--min-points", "50", "--spline-spacing", "5",
             "--breaklines", str(lines)]  # fmt: skip
    ref, out = tmp_path / "one", tmp_path / "tiled"
    rc, err = _cli(["icp", str(slab / "before.laz"), str(slab / "after.laz"), *extra,
                    "--out", str(ref)], capsys)  # fmt: skip
    assert rc == 0, err
    rc, err = _cli(["icp", str(slab / "before_tiles"), str(slab / "after_tiles"), *extra,
                    "--tile-size", "20", "--out", str(out)], capsys)  # fmt: skip
    assert rc == 0, err
    want, got = _rows(ref / "icp.csv"), _rows(out / "icp.csv")
    assert set(got) == set(want) and len(got["x"]) == len(want["x"]) > 60
    for key in want:
        assert np.max(np.abs(got[key] - want[key])) <= TOL, key
    assert "breaklines" in gpkg_layer_names(out / "icp.gpkg")


def test_detected_breaklines_on_blocks_equal_the_one_file_run(slab, caplog):
    """The default field on tiles (issue #29 item 4): the scarp is detected in the tiled
    cells' motions, confirmed and placed by the points near it (each block sends its points
    within reach of the candidate, each point once) and the field refitted with it, so the
    tiled run equals the one-file run (1e-6 m), line included, and keeps the step."""
    import logging

    from slipmap.core.breaklines import breaklines, distance_m

    before = open_collection(str(slab / "before_tiles"))
    after = open_collection(str(slab / "after_tiles"))
    kw = dict(cell_m=5.0, min_points=50, field_model="spline", spline_spacing_m=5.0,
              detect_breaklines=True)  # fmt: skip
    whole = windowed_icp(_whole(before), _whole(after), **kw)
    with caplog.at_level(logging.INFO, logger="slipmap.app"):
        tiled = tf.icp_tiled(before, after, tile_size_m=15.0, **kw)
    assert whole.breaklines_source == "detected", "the one-file run must find the scarp"
    _equal(tiled, whole, "detected breaklines")
    assert tiled.breaklines_source == "detected"
    assert len(tiled.breaklines) == len(whole.breaklines)
    for p, q in zip(tiled.breaklines.parts, whole.breaklines.parts):
        assert p.shape == q.shape and np.max(np.abs(p - q)) <= TOL
    assert any("near the candidates" in r.getMessage() for r in caplog.records)
    assert not any("gate somewhere" in r.getMessage() for r in caplog.records)
    assert not tf._CHUNKS  # the blocks' cache is emptied
    # the line lies on the scarp where there are points (0 <= y <= 40 m) and the far cells
    # keep the step
    line = tiled.breaklines.parts[0] - ORIGIN[:2]
    ys = np.linspace(0.0, 40.0, 41)
    xs = np.interp(ys, line[::-1, 1] if line[0, 1] > line[-1, 1] else line[:, 1],
                   line[::-1, 0] if line[0, 1] > line[-1, 1] else line[:, 0])  # fmt: skip
    assert np.max(distance_m(np.c_[xs, ys], breaklines([SCARP]))) < 2.5
    xy = np.c_[tiled.x, tiled.y] - ORIGIN[:2]
    truth = _beyond(xy - SLAB[:2])[:, None] * SLAB
    far = distance_m(xy, breaklines([SCARP])) >= 3.0
    err = np.linalg.norm(np.c_[tiled.dx, tiled.dy, tiled.dz] - truth, axis=1)
    assert far.sum() >= 40 and float(np.sqrt(np.mean(err[far] ** 2))) < 0.006


def test_cli_default_on_tiles_detects_the_scarp_as_one_file(slab, tmp_path, capsys):
    """``slipmap icp TILES TILES`` with the model options at their defaults: the breaklines
    are detected on the tiles as in one file (the same cells within 1e-6 m), and icp.json
    and the GeoPackage say so."""
    import json

    from slipmap.core.io.vector import gpkg_layer_names

    extra = ["--cell", "5", "--min-points", "50", "--spline-spacing", "5"]
    ref, out = tmp_path / "one", tmp_path / "tiled"
    rc, err = _cli(["icp", str(slab / "before.laz"), str(slab / "after.laz"), *extra,
                    "--out", str(ref)], capsys)  # fmt: skip
    assert rc == 0, err
    try:  # the corridor's blocks on Dask workers, when Dask is here
        import distributed  # noqa: F401

        engine = ["--workers", "2"]
    except ImportError:
        engine = []
    rc, err = _cli(["icp", str(slab / "before_tiles"), str(slab / "after_tiles"), *extra,
                    "--tile-size", "20", *engine, "--out", str(out)], capsys)  # fmt: skip
    assert rc == 0, err
    want, got = _rows(ref / "icp.csv"), _rows(out / "icp.csv")
    assert set(got) == set(want) and len(got["x"]) == len(want["x"]) > 60
    for key in want:
        assert np.max(np.abs(got[key] - want[key])) <= TOL, key
    docs = [json.loads((d / "icp.json").read_text())["breaklines"] for d in (ref, out)]
    assert docs[0]["source"] == docs[1]["source"] == "detected", docs
    assert docs[0]["count"] == docs[1]["count"] >= 1
    assert "breaklines" in gpkg_layer_names(out / "icp.gpkg")


def test_the_gate_warning_reads_the_field_at_the_cells_not_stray_knots():
    """A knot copy no point uses may stray in an iteration: the tiled run's warning that the
    field moves further than the gate reads the field at the cell centres."""
    from slipmap.core.breaklines import breaklines
    from slipmap.core.icp_spline import knot_frame

    line = breaklines([np.array([[10.0, -5.0], [10.0, 25.0]])])
    centres = np.array([[2.5, 2.5], [17.5, 17.5], [2.5, 17.5], [17.5, 2.5]])
    frame = knot_frame(np.zeros(2), np.array([20.0, 20.0]), centres, 5.0, lines=line)
    n_grid = (frame.n_x + 3) * (frame.n_y + 3)
    n_k = n_grid + int(np.count_nonzero(frame.copy_index >= 0))
    c = np.tile([0.3, -0.1, 0.0], (n_k, 1))
    assert tf._largest_motion(frame, c, n_grid, centres) == pytest.approx(np.hypot(0.3, 0.1))
    c[n_grid:] = 13.0  # the copies far off: the cells west of the line do not see them
    assert tf._largest_motion(frame, c, n_grid, centres[:1]) == pytest.approx(np.hypot(0.3, 0.1))


def test_a_breakline_corridor_too_large_is_refused_naming_the_option(
    slab, tmp_path, capsys, monkeypatch
):
    """The points near candidate lines are counted on the blocks before any is sent: when
    they would not fit in the driver's memory the run stops naming --detect-breaklines and
    writes nothing."""
    monkeypatch.setattr(tf, "CORRIDOR_POINT_BYTES", 1e15)
    out = tmp_path / "out"
    rc, err = _cli(["icp", str(slab / "before_tiles"), str(slab / "after_tiles"), "--cell", "5",
                    "--min-points", "50", "--spline-spacing", "5", "--tile-size", "20",
                    "--out", str(out)], capsys)  # fmt: skip
    assert rc == 2
    msg = " ".join(err)
    assert "--detect-breaklines" in msg and "near the candidate breaklines" in msg, err
    assert "give the breaklines instead" in msg
    assert not out.exists()
    assert not tf._CHUNKS


#: a block rotating 3 deg (head down, toe out and up) across the blocks' boundaries
SLUMP = SlumpField((31.0, 20.0), azimuth_deg=180.0, head_m=8.0, toe_m=8.0, width_m=16.0)


@pytest.fixture(scope="module")
def slump(tmp_path_factory):
    """The ground of ``scene`` with a rotating slump block instead of a lobe, as one LAZ per
    epoch and as tiles."""
    root = tmp_path_factory.mktemp("tiled_slump")
    rng = np.random.default_rng(11)
    before = _terrain(rng, 40_000, 60.0, 40.0)
    after = _terrain(rng, 40_000, 60.0, 40.0)
    after = after + np.asarray(SLUMP(after[:, :2]))
    return _write_epochs(root, before, after)


def test_cells_that_fit_better_report_their_own_fit_on_blocks_as_in_one_file(slump):
    """The choice between the field and a cell's own fit (core.icp_choice) made on the blocks'
    points: the same cells choose, every value equal to the one-file run's (1e-6 m), and the
    cells that chose are closer to the truth than the field was there."""
    from slipmap.core.synthetic import material_motion

    before = open_collection(str(slump / "before_tiles"))
    after = open_collection(str(slump / "after_tiles"))
    kw = dict(cell_m=5.0, min_points=50, field_model="spline", spline_spacing_m=5.0,
              coarse_to_fine=1, detect_breaklines=True, cell_choice=True)  # fmt: skip
    whole = windowed_icp(_whole(before), _whole(after), **kw)
    tiled = tf.icp_tiled(before, after, tile_size_m=15.0, **kw)
    _equal(tiled, whole, "cells choosing")
    assert whole.from_cell.sum() >= 3
    field = tf.icp_tiled(before, after, tile_size_m=15.0, **dict(kw, cell_choice=False))
    assert not field.from_cell.any()
    k = tiled.from_cell
    xy = np.c_[tiled.x, tiled.y] - ORIGIN[:2]
    truth = material_motion(SLUMP, xy)
    k &= np.all(np.isfinite(truth), axis=1)
    e_own = np.linalg.norm(np.c_[tiled.dx, tiled.dy, tiled.dz][k] - truth[k], axis=1)
    e_field = np.linalg.norm(np.c_[field.dx, field.dy, field.dz][k] - truth[k], axis=1)
    assert np.sqrt(np.mean(e_own**2)) < np.sqrt(np.mean(e_field**2)), (e_own, e_field)
