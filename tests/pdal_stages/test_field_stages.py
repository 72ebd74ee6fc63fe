"""The field stages ``icp`` and ``piv`` (displacement fields of two merged epochs) run as
filters.python runs them, without PDAL (see pdal_harness; test_real_pdal.py runs them in
real PDAL): the job's field on the same points, each point its cell's or vector's motion,
breaklines given as WKT, and the known step across them."""

import numpy as np
import pytest
from pdal_harness import call, load_stage, make_ins, nodes, parse_add_dimension

from slipmap.app import icp as job
from slipmap.core.breaklines import breaklines
from slipmap.core.synthetic import SlabField
from slipmap.pdal_filters._stage import StageError

ICP = parse_add_dimension(["DisplacementX", "DisplacementY", "DisplacementZ", "IcpCell=int32"])
ORIGIN = np.array([500000.0, 4200000.0, 10.0])
SIDE = 40.0
#: a scarp across the square at 15°, the slab north of it moving (0.05, 0.3, -0.1) m
SCARP = np.array([[-5.0, 15.0], [45.0, 15.0 + 50.0 * np.tan(np.radians(15.0))]])


#: rough ground: 400 random bumps (0.5-2.5 m across, up to 0.5 m high) on a gentle slope,
#: texture for PIV's correlation and planes for ICP, and no period for either to slip by
_BUMPS = np.random.default_rng(11).uniform(
    [-5.0, -5.0, 0.5, -0.5], [SIDE + 5.0, SIDE + 5.0, 2.5, 0.5], (400, 4)
)


def _ground(xy, rng):
    z = 0.02 * xy[:, 0]
    for cx, cy, r, h in _BUMPS:
        z = z + h * np.exp(-((xy[:, 0] - cx) ** 2 + (xy[:, 1] - cy) ** 2) / (2.0 * r * r))
    return z + rng.normal(0.0, 0.003, len(xy))


@pytest.fixture(scope="module")
def pair():
    """Rough ground sampled twice (25 points/m²), the second sampling moved by the slab."""
    rng = np.random.default_rng(5)
    field = SlabField(tuple(map(tuple, SCARP)), (0.05, 0.3, -0.1))
    out = []
    for moved in (False, True):
        xy = rng.uniform(0.0, SIDE, (40_000, 2))
        p = np.c_[xy, _ground(xy, rng)]
        if moved:
            p = p + field(xy)
        out.append(p + ORIGIN)
    return out


def _wkt(line):
    pts = ", ".join(f"{float(x)!r} {float(y)!r}" for x, y in line + ORIGIN[:2])
    return f"LINESTRING ({pts})"


@pytest.fixture(scope="module")
def run(pair):
    before, after = pair
    args = {"cell_m": 5.0, "breaklines": _wkt(SCARP), "backend": "numpy"}
    mod = load_stage("icp", args)
    pts = np.vstack([before, after])
    tag = np.r_[np.ones(len(before)), np.full(len(after), 2.0)]
    outs = call(mod, make_ins(pts, Epoch=tag), ICP)
    return mod, outs, pts, args


def test_the_stage_gives_the_jobs_field_and_each_point_its_cell(pair, run):
    mod, outs, pts, args = run
    before, after = pair
    opts = job.SPEC.parse({"cell_m": 5.0, "backend": "numpy"}, face="pdal")
    want = job.compute(before, after, opts, lines=breaklines([SCARP + ORIGIN[:2]]))
    kids = nodes(mod)
    cells = kids["cells"]
    assert len(cells["dx"]) == len(want) > 20
    for k in ("x", "y", "dx", "dy", "dz", "sigma_dx", "sigma_dy", "sigma_dz"):
        np.testing.assert_array_equal(np.asarray(cells[k], dtype=float), getattr(want, k))
    assert kids["summary"]["breaklines"]["source"] == "given"
    assert kids["summary"]["breaklines"]["file"] is None  # given as WKT
    assert kids["headline"].startswith(f"windowed ICP: {len(want)} cells of 5 m")
    # every point its cell's motion (the cell it lies in by the grid), -1 / NaN in none
    k = outs["IcpCell"]
    has = k >= 0
    assert has.mean() > 0.9
    for dim, comp in (("DisplacementX", "dx"), ("DisplacementY", "dy"), ("DisplacementZ", "dz")):
        np.testing.assert_array_equal(outs[dim][has], getattr(want, comp)[k[has]])
        assert np.isnan(outs[dim][~has]).all()
    x0, y0 = want.origin_xy
    col = np.floor((pts[has, 0] - x0) / want.cell_m).astype(int)
    row = np.floor((y0 - pts[has, 1]) / want.cell_m).astype(int)
    np.testing.assert_array_equal(want.row[k[has]], row)
    np.testing.assert_array_equal(want.col[k[has]], col)


def test_the_field_steps_at_the_given_scarp(run):
    """The known answer: cells 3 m and more from the scarp move as their side does."""
    mod, _, _, _ = run
    cells = nodes(mod)["cells"]
    xy = np.c_[cells["x"], cells["y"]] - ORIGIN[:2]
    d = np.c_[cells["dx"], cells["dy"], cells["dz"]]
    t = (SCARP[1] - SCARP[0]) / np.linalg.norm(SCARP[1] - SCARP[0])
    s = (xy - SCARP[0]) @ np.array([-t[1], t[0]])  # + north of the scarp
    far = np.abs(s) >= 3.0
    truth = np.where((s > 0)[:, None], [0.05, 0.3, -0.1], 0.0)
    err = np.linalg.norm(d - truth, axis=1)[far]
    # measured 0.7 mm over 54 cells
    assert far.sum() > 30 and np.sqrt(np.mean(err**2)) < 0.005, np.sqrt(np.mean(err**2))


def test_empty_view_and_bad_options(pair):
    mod = load_stage("icp", {})
    outs = call(mod, make_ins(np.empty((0, 3)), Epoch=np.empty(0)), ICP)
    assert outs["IcpCell"].shape == (0,) and outs["DisplacementX"].dtype == np.float64
    before, after = pair
    pts = np.vstack([before[:2000], after[:2000]])
    tag = np.r_[np.ones(2000), np.full(2000, 2.0)]
    bad = load_stage("icp", {"breaklines": "no/such/lines.gpkg"})
    with pytest.raises(StageError, match="option 'breaklines' is neither a WKT"):
        call(bad, make_ins(pts, Epoch=tag), ICP)
    with pytest.raises(StageError, match="'epoch_dimension'"):
        call(load_stage("icp", {}), make_ins(pts), ICP)
    with pytest.raises(StageError, match="cell_m"):
        call(load_stage("icp", {"cell_m": -1}), make_ins(pts, Epoch=tag), ICP)


# --------------------------------------------------------------------------- piv

PIV = parse_add_dimension(["DisplacementX", "DisplacementY", "DisplacementZ", "PivVector=int32"])


@pytest.fixture(scope="module")
def piv_run(pair):
    before, after = pair
    args = {"grid_m": 0.5, "windows_px": [24, 12, 12], "breaklines": _wkt(SCARP)}
    mod = load_stage("piv", args)
    pts = np.vstack([before, after])
    tag = np.r_[np.ones(len(before)), np.full(len(after), 2.0)]
    outs = call(mod, make_ins(pts, Epoch=tag), PIV)
    return mod, outs, pts


def test_the_piv_stage_gives_the_jobs_vectors_and_each_point_its_vector(pair, piv_run):
    from slipmap.app import piv as piv_job

    mod, outs, pts = piv_run
    before, after = pair
    opts = piv_job.SPEC.parse({"grid_m": 0.5, "windows_px": [24, 12, 12]}, face="pdal")
    wins = piv_job.windows(opts)
    grid, zb, za = piv_job.dems(before, after, opts, wins)
    want = piv_job.piv_of_dems(zb, za, grid, opts, wins, lines=breaklines([SCARP + ORIGIN[:2]]))
    kids = nodes(mod)
    vec = kids["vectors"]
    cols = want.to_columns()
    assert len(vec["dx"]) == want.dx.size > 50
    for k in ("x", "y", "dx", "dy", "dz"):
        np.testing.assert_array_equal(np.asarray(vec[k], dtype=float), cols[k])
    assert kids["summary"]["breaklines_given"] and kids["summary"]["n_near_break"] > 0
    assert kids["headline"].startswith(f"PIV: {want.dx.size} vectors every ")
    k = outs["PivVector"]
    has = k >= 0
    assert has.mean() > 0.8
    np.testing.assert_array_equal(outs["DisplacementY"][has], cols["dy"][k[has]])
    assert np.isnan(outs["DisplacementY"][~has]).all()
    # each point lies within half a spacing of its vector, in x and y
    d = np.abs(pts[has, :2] - np.c_[cols["x"], cols["y"]][k[has]])
    assert d.max() <= 0.5 * want.spacing_m + 1e-9


def test_the_piv_field_steps_at_the_given_scarp(piv_run):
    """The known answer: valid vectors 3 m and more from the scarp, within a quarter of a
    DEM cell of their side's horizontal motion (the issue's PIV mark), RMS."""
    mod, _, _ = piv_run
    vec = nodes(mod)["vectors"]
    xy = np.c_[vec["x"], vec["y"]] - ORIGIN[:2]
    d = np.c_[vec["dx"], vec["dy"]].astype(float)
    t = (SCARP[1] - SCARP[0]) / np.linalg.norm(SCARP[1] - SCARP[0])
    s = (xy - SCARP[0]) @ np.array([-t[1], t[0]])
    ok = (np.abs(s) >= 3.0) & np.asarray(vec["valid"], dtype=bool) & np.isfinite(d).all(axis=1)
    truth = np.where((s > 0)[:, None], [0.05, 0.3], 0.0)
    err = np.linalg.norm(d - truth, axis=1)[ok]
    rms = np.sqrt(np.mean(err**2))
    # measured 6.5 cm (0.13 cell of 0.5 m) over 113 vectors
    assert ok.sum() > 30 and rms < 0.25 * 0.5, rms
