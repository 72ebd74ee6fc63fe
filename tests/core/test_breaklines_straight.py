"""A fault across a deforming lobe (issue #29): the edge test misses it, the straight-step
scan proposes it on the cells, the points confirm and place it; smooth lobes that the scan
also proposes lines for are left whole by the points. Known answers on synthetic grids and
on synthetic rough terrain."""

from __future__ import annotations

import logging
import math

import numpy as np
import pytest
from test_icp import UTM, surface

from slipmap.core.breaklines import (
    breaklines,
    detect_breaklines,
    distance_m,
    scan_straight_step,
    straight_across,
)
from slipmap.core.icp import windowed_icp
from slipmap.core.synthetic import FaultField, LobeField, SlabField, material_motion

CELL = 5.0
N = 10  # cells a side


def _trace(centre, azimuth_deg, half_m=40.0):
    u = np.array([math.sin(math.radians(azimuth_deg)), math.cos(math.radians(azimuth_deg))])
    c = np.asarray(centre, dtype=np.float64)
    return np.array([c - half_m * u, c + half_m * u])


def _fault(centre=(25.0, 25.0), scale=1.0):
    """The harness's fault (benchmarks/validate_landslides.py): a broad lobe (16 m x 20 m,
    peak (0.2, -0.5, -0.2) m) crossed at azimuth 60° (30° from the grid's rows) by 0.3 m of
    strike-slip and 0.05 m of throw; ``scale`` shrinks the lobe with the cells."""
    base = LobeField(centre, 16.0 * scale, 20.0 * scale, 0.0, (0.2, -0.5, -0.2))
    return FaultField(tuple(map(tuple, _trace(centre, 60.0))), slip_m=0.3, throw_m=0.05,
                      base=base)  # fmt: skip


def _grid(field, rng, *, noise_m=0.01, missing=0.15):
    x = (np.arange(N) + 0.5) * CELL
    y = N * CELL - (np.arange(N) + 0.5) * CELL  # rows run south, as the ICP cells'
    gx, gy = np.meshgrid(x, y)
    d = field(np.c_[gx.ravel(), gy.ravel()]).reshape(N, N, 3)
    return x, y, d + rng.normal(0.0, noise_m, d.shape), rng.random((N, N)) > missing


def _over(line, lo=0.0, hi=N * CELL, n=400):
    """Points of a detected line's parts over the box [lo, hi]²."""
    pts = []
    for part in line.parts:
        for a, b in zip(part[:-1], part[1:]):
            pts.append(a + np.linspace(0.0, 1.0, n)[:, None] * (b - a))
    p = np.vstack(pts)
    return p[np.all((p >= lo) & (p <= hi), axis=1)]


def test_the_edge_test_misses_a_diagonal_fault_across_a_lobe_the_scan_finds_it():
    fault = _fault()
    truth = breaklines([_trace((25.0, 25.0), 60.0)])
    for seed in range(4):
        x, y, d, valid = _grid(fault, np.random.default_rng(seed))
        if seed == 0:  # the premise: the lobe's own differences (0.2 m a cell) hide the step
            sig = np.full(d.shape[:2], 0.004)
            assert detect_breaklines(d, x=x, y=y, valid=valid, sigma=sig) is None
        found = scan_straight_step(d, x=x, y=y, valid=valid)
        assert found is not None, seed
        # within a cell of the trace over the data, its direction within a scan step
        p = _over(found.line)
        assert len(p) > 50
        assert distance_m(p, truth).max() <= CELL, seed
        assert abs(found.angle_deg - 30.0) <= 7.5, found.angle_deg
        # the step it fits: the fault's 0.3 m (left side minus right as seen along the line)
        assert 0.2 <= np.linalg.norm(found.step_m) <= 0.45, found.step_m


def test_the_scan_finds_a_straight_scarp_across_the_grid():
    rng = np.random.default_rng(3)
    a, b = np.array([-10.0, 8.0]), np.array([60.0, 31.0])  # 18° to the rows, off the edges
    slab = np.array([0.1, -0.3, -0.1])

    def field(xy):
        left = (b[0] - a[0]) * (xy[:, 1] - a[1]) - (b[1] - a[1]) * (xy[:, 0] - a[0]) > 0
        return left[:, None] * slab

    x, y, d, valid = _grid(field, rng, noise_m=0.005)
    found = scan_straight_step(d, x=x, y=y, valid=valid)
    assert found is not None
    assert distance_m(_over(found.line), breaklines([np.array([a, b])])).max() <= CELL
    np.testing.assert_allclose(found.step_m, slab, atol=0.05)


def test_the_scan_proposes_nothing_on_gentle_smooth_fields():
    # a lobe's flank fits a step of about 4 times the band's residuals whatever its peak
    # (the shape's), so on lobes of 0.25 m or more the scan does propose a line, as it must
    # for the fault above: the points drop those (the last test); below twice the floor
    # (0.1 m of step) it proposes none
    rng = np.random.default_rng(5)
    fields = [
        lambda xy: np.zeros((len(xy), 3)) + [0.1, -0.2, 0.05],  # a uniform shift
        lambda xy: np.c_[0.004 * xy[:, 0], -0.003 * xy[:, 1], 0.002 * xy[:, 0]],  # linear
        LobeField((25.0, 25.0), 20.0, 16.0, 0.0, (0.0, -0.1, -0.04)),  # 0.1 m peak
        LobeField((22.0, 28.0), 6.0, 6.0, 0.0, (0.25, -0.35, -0.15)),  # one cell's bump
    ]
    for i, f in enumerate(fields):
        x, y, d, valid = _grid(f, rng, noise_m=0.005)
        assert scan_straight_step(d, x=x, y=y, valid=valid) is None, i
    # too few vectors: nothing to scan
    x, y, d, _ = _grid(fields[0], rng)
    assert scan_straight_step(d, x=x, y=y, valid=np.eye(N, dtype=bool)) is None


# --------------------------------------------------------------------------- on the points

#: 5 m cells on a 50 m square, as the harness's
P_CELL, SIDE = 5.0, 50.0


def _pair(field, seed=0, n=60_000, side=SIDE):
    """Rough terrain (3 mm noise) sampled twice over a ``side`` m square; the second
    sampling moved by ``field``."""
    rng = np.random.default_rng(seed)

    def sample():
        xy = rng.uniform(0.0, side, (n, 2))
        return np.c_[xy, surface(xy) + rng.normal(0.0, 0.003, n)]

    b, a = sample(), sample()
    return b + UTM, a + field(a[:, :2]) + UTM


def _errors(res, field, lines, reach_m):
    """RMS 3-D error of the full cells at least ``reach_m`` from ``lines`` (all cells when
    None), against the motion of the material now at the centre."""
    c = np.c_[res.x, res.y] - UTM[:2]
    truth = material_motion(field, c)
    e = np.linalg.norm(np.c_[res.dx, res.dy, res.dz] - truth, axis=1)
    full = (res.n_after > 0.8 * np.median(res.n_after)) & np.isfinite(e)
    if lines is not None:
        full &= distance_m(c, lines) >= reach_m
    return float(np.sqrt(np.mean(e[full] ** 2))), int(full.sum())


def test_a_fault_across_a_lobe_is_found_placed_and_both_sides_recovered():
    centre = (0.5 * SIDE, 0.5 * SIDE)
    fault = _fault(centre)
    trace = breaklines([_trace(centre, 60.0)])
    before, after = _pair(fault)
    kw = dict(cell_m=P_CELL, coarse_to_fine=1, field_model="spline")
    res = windowed_icp(before, after, detect_breaklines=True, **kw)
    assert res.breaklines_source == "detected" and len(res.breaklines) == 1
    line = breaklines([p - UTM[:2] for p in res.breaklines.parts])
    p = _over(line, 0.0, SIDE)
    assert len(p) > 50
    assert distance_m(p, trace).max() < 1.0  # placed on the points (a cell is 5 m)
    err, n = _errors(res, fault, trace, 3.0)
    smooth, _ = _errors(windowed_icp(before, after, **kw), fault, trace, 3.0)
    assert n >= 40
    # measured 3.3 mm against the smooth field's 6.5 mm when written; 2.2-2.3 mm against
    # 3.8 mm since (the refit started from the candidate's fit, issue #29: 2.30 mm)
    assert err < 0.005 and err < 0.7 * smooth, (err, smooth)


def test_a_lobe_the_scan_proposes_a_line_for_is_left_whole(caplog, monkeypatch):
    """The fault's lobe without the fault. Here the edge test finds a line on its flank
    (which the points drop); it is switched off to reach the scan, as on the harness's lobes
    where the edge test finds none: the scan proposes a line, the points drop it (the
    field fitted with it jumps by 1 cm at the line, less than the 5 cm floor)."""
    import slipmap.core.breaklines as bl

    monkeypatch.setattr(bl, "detect_breaklines", lambda *a, **k: None)
    lobe = LobeField((0.5 * SIDE, 0.5 * SIDE), 16.0, 20.0, 0.0, (0.2, -0.5, -0.2))
    before, after = _pair(lobe, seed=1)
    kw = dict(cell_m=P_CELL, coarse_to_fine=1, field_model="spline")
    with caplog.at_level(logging.INFO, logger="slipmap.core"):
        res = windowed_icp(before, after, detect_breaklines=True, **kw)
    assert "a straight step proposed" in caplog.text  # the grid alone cannot tell
    assert res.breaklines_source == "none" and res.breaklines is None
    smooth = windowed_icp(before, after, **kw)
    # the refit without the line starts where the candidate's fit ended (issue #29), so it
    # is the smooth field to the fits' convergence (CHANGE_FLOOR: the steps stop at 2 % of
    # the residuals' spread, 0.15 mm here, while they shrink by about 0.8 an iteration, so up
    # to about five steps' worth of distance to the fixed point is left; the line's own
    # jump is 10 mm). Measured with the principal horizontal model (the default since stop
    # 54) 1.8 mm, 0.098 sigma (dx); with one weight per axis 0.12 mm, 0.016 sigma
    for k in ("dx", "dy", "dz"):
        gap = np.abs(getattr(res, k) - getattr(smooth, k))
        assert np.all(gap < 0.15 * getattr(smooth, "sigma_" + k)), k
        assert gap.max() < 2.5e-3, k


class _Block:
    """A slab north of a scarp that runs at -15° from (0, 33) m and ends ``length_m`` along it
    (its tip inside the area), moving by (0.05, 0.3, -0.1) m; its side from the tip north is
    a second, shorter step."""

    def __init__(self, length_m=38.0):
        a = math.radians(-15.0)
        self.u = np.array([math.cos(a), math.sin(a)])
        self.p0, self.length_m = np.array([0.0, 33.0]), length_m

    @property
    def tip(self):
        return self.p0 + self.length_m * self.u

    def __call__(self, xy):
        r = np.asarray(xy, dtype=np.float64)[:, :2] - self.p0
        on = (r @ np.array([-self.u[1], self.u[0]]) > 0) & (r @ self.u < self.length_m)
        return on[:, None] * np.array([0.05, 0.3, -0.1])[None, :]


def test_a_scarp_that_ends_inside_the_area_is_cut_to_where_it_steps(monkeypatch):
    """The scan proposes a line across the whole area; the block's scarp steps along 38 m
    of its 54 m (the field fitted with it jumps by 0.26-0.32 m at eight stations, 0.01-0.03
    m at the three beyond the tip: 73 %, short of the 75 % the whole line needs). The points
    confirm and place the stretch where it steps: the line ends at the tip, not across the
    block's side and the still ground beyond (measured: within 0.4 m of the scarp, its end
    0.2 m from the tip). Without the cut the candidate is dropped (the premise)."""
    import slipmap.core.breakline_points as bp
    import slipmap.core.breaklines as bl

    monkeypatch.setattr(bl, "detect_breaklines", lambda *a, **k: None)  # the scan's case
    block = _Block()
    before, after = _pair(block, seed=0)
    kw = dict(cell_m=P_CELL, coarse_to_fine=1, field_model="spline", detect_breaklines=True)
    res = windowed_icp(before, after, **kw)
    assert res.breaklines_source == "detected" and len(res.breaklines) == 1
    line = breaklines([p - UTM[:2] for p in res.breaklines.parts])
    scarp = breaklines([np.array([block.p0, block.tip])])
    p = _over(line, 0.0, SIDE)
    assert len(p) > 50
    assert distance_m(p, scarp).max() < 1.0
    ends = np.vstack([part[[0, -1]] for part in line.parts])
    assert np.min(np.linalg.norm(ends - block.tip, axis=1)) < P_CELL  # cut at the tip
    assert np.max(ends[:, 0]) < block.tip[0] + P_CELL  # not on across the still ground
    monkeypatch.setattr(bp, "PLACE_TRIM", False)
    assert windowed_icp(before, after, **kw).breaklines is None


class _Sum:
    def __init__(self, *fields):
        self.fields = fields

    def __call__(self, xy):
        return sum(f(xy) for f in self.fields)


def _survey(field, n_c=24, n_r=20):
    """Cells of 5 m over a 120 m x 100 m survey: centres and the field there."""
    x = (np.arange(n_c) + 0.5) * CELL
    y = n_r * CELL - (np.arange(n_r) + 0.5) * CELL
    gx, gy = np.meshgrid(x, y)
    return x, y, field(np.c_[gx.ravel(), gy.ravel()]).reshape(n_r, n_c, 3)


def test_across_a_survey_larger_than_its_lobes_the_scan_follows_them_along_the_line(
    monkeypatch,
):
    # the harness's fault across a 120 m x 100 m survey with two lobes 70 m apart along
    # it: one quadratic along the band's 130 m cannot follow both, its residuals swamp the
    # 0.3 m step and the scan proposes nothing (the premise, SCAN_QUADRATIC_CELLS off);
    # with hat functions along the line it finds the fault
    from slipmap.core import breaklines as bl

    centre = np.array([60.0, 50.0])
    u = np.array([math.sin(math.radians(60.0)), math.cos(math.radians(60.0))])
    lobes = _Sum(
        LobeField(tuple(centre - 35.0 * u), 16.0, 20.0, 0.0, (0.3, -0.75, -0.3)),
        LobeField(tuple(centre + 35.0 * u), 16.0, 20.0, 0.0, (-0.45, -0.6, -0.3)),
    )
    trace = _trace(centre, 60.0, half_m=100.0)
    fault = FaultField(tuple(map(tuple, trace)), slip_m=0.3, throw_m=0.05, base=lobes)
    truth = breaklines([trace])
    x, y, clean = _survey(fault)
    for seed in range(3):
        rng = np.random.default_rng(seed)
        d = clean + rng.normal(0.0, 0.01, clean.shape)
        valid = rng.random(clean.shape[:2]) > 0.15
        found = scan_straight_step(d, x=x, y=y, valid=valid)
        assert found is not None, seed
        assert abs(found.angle_deg - 30.0) <= 7.5, (seed, found.angle_deg)
        assert distance_m(_over(found.line, hi=100.0), truth).max() <= CELL, seed
        assert 0.2 <= np.linalg.norm(found.step_m) <= 0.45, found.step_m
        with monkeypatch.context() as m:
            m.setattr(bl, "SCAN_QUADRATIC_CELLS", np.inf)
            old = scan_straight_step(d, x=x, y=y, valid=valid)
        assert old is None or abs(old.angle_deg - 30.0) > 7.5, (seed, old.angle_deg)


def test_on_small_grids_the_scan_fits_one_quadratic_along_the_band(monkeypatch):
    # the hat functions start beyond SCAN_QUADRATIC_CELLS: on a grid of lone-star's size
    # (7 x 9 cells of 5 m: the harness's scenes) the scan is the quadratic's, to the digit
    from slipmap.core import breaklines as bl

    x, y, clean = _survey(_fault(centre=(17.5, 22.5), scale=0.7), n_c=7, n_r=9)
    rng = np.random.default_rng(0)
    d = clean + rng.normal(0.0, 0.01, clean.shape)
    valid = rng.random(clean.shape[:2]) > 0.1
    found = scan_straight_step(d, x=x, y=y, valid=valid)
    monkeypatch.setattr(bl, "SCAN_QUADRATIC_CELLS", np.inf)
    same = scan_straight_step(d, x=x, y=y, valid=valid)
    assert found.angle_deg == same.angle_deg and found.f_stat == same.f_stat
    np.testing.assert_array_equal(found.step_m, same.step_m)


def _step(a, b):
    from slipmap.core.breaklines import StraightStep

    return StraightStep(line=breaklines([np.array([a, b])]), angle_deg=30.0,
                        step_m=np.array([0.3, 0.0, 0.0]), rms_m=0.04, f_stat=80.0,
                        n_cells=90)  # fmt: skip


def test_the_straight_step_is_tried_first_where_the_edges_lie_along_it():
    from slipmap.core.icp import order_candidates

    straight = _step((0.0, 0.0), (120.0, 0.0))
    part = breaklines([np.array([[60.0, 1.0], [118.0, 2.0]])])  # half of it, 1-2 m off
    bent = breaklines([np.array([[60.0, 1.0], [104.0, 2.0], [106.0, 12.0]])])  # then turns
    whole = breaklines([np.array([[-2.0, 2.0], [122.0, -1.0]])])
    elsewhere = breaklines([np.array([[10.0, 40.0], [90.0, 60.0]])])
    # a block's outline: one side along the straight line, the other across it
    corner = breaklines(
        [np.array([[40.0, 1.0], [80.0, 1.0]]), np.array([[80.0, 1.0], [80.0, 40.0]])]
    )
    for edges in (part, bent, whole):
        got = order_candidates(edges, straight, cell_m=CELL)
        assert [g[1] for g in got] == [straight, None]
        assert got[1][0] is edges
    # edges that lie elsewhere or only partly along it: the edges alone, as without the scan
    for edges in (elsewhere, corner):
        assert order_candidates(edges, straight, cell_m=CELL) == [(edges, None)]
    assert order_candidates(None, straight, cell_m=CELL) == [(straight.line, straight)]
    assert order_candidates(part, None, cell_m=CELL) == [(part, None)]
    assert order_candidates(None, None, cell_m=CELL) == []


# --------------------------------------------------------------------------- a turned retry


def test_a_line_across_a_box_runs_from_side_to_side():
    box = np.array([[0.0, 0.0], [100.0, 50.0]])
    line = straight_across(np.array([50.0, 25.0]), np.array([2.0, 1.0]), box)
    np.testing.assert_allclose(line.parts[0], [[0.0, 0.0], [100.0, 50.0]], atol=1e-12)
    line = straight_across(np.array([20.0, 10.0]), np.array([0.0, -3.0]), box)
    np.testing.assert_allclose(line.parts[0], [[20.0, 50.0], [20.0, 0.0]], atol=1e-12)
    assert straight_across(np.array([120.0, 10.0]), np.array([1.0, 0.0]), box) is None


class _Fit:
    def __init__(self, lines):
        self.field = lines  # the stubs' field is the lines it was fitted with


@pytest.mark.parametrize("confirmed_across", [True, False])
def test_a_cut_and_turned_line_is_fitted_again_across_the_survey_and_kept_where_confirmed(
    confirmed_across,
):
    """try_candidates with stub fits: a straight candidate whose placement was cut and
    turned is fitted once more along the placed direction across the scan's box; the points'
    verdict there decides, and where they drop it the cut line stands."""
    import dataclasses

    from slipmap.core.icp import _across, try_candidates

    box = np.array([[0.0, 0.0], [100.0, 100.0]])
    cand = dataclasses.replace(_step((0.0, 50.0), (100.0, 50.0)), box_m=box)
    cut = breaklines([np.array([[30.0, 45.0], [70.0, 55.0]])])  # turned 14°, 41 m long
    fitted = []

    def fit(lines):
        fitted.append(lines)
        return _Fit(lines)

    def confirm(field, straight, again):
        if field is cand.line:  # the first fit: cut and turned
            assert again
            return cut, _across(straight, cut)
        assert not again and straight.line is field  # the retry, judged once
        return (field if confirmed_across else None), None

    lines, first = try_candidates([(cand.line, cand)], fit, confirm)
    assert len(fitted) == 2 and fitted[0] is cand.line
    p = fitted[1].parts[0]  # the retry: along the cut line, from side to side
    np.testing.assert_allclose(p, [[0.0, 37.5], [100.0, 62.5]], atol=1e-9)
    if confirmed_across:
        assert lines is fitted[1] and first.field is fitted[1]
    else:
        assert lines is cut and first.field is cand.line


def test_a_line_placed_whole_or_not_turned_is_not_fitted_again():
    from slipmap.core.icp import try_candidates

    cand = _step((0.0, 50.0), (100.0, 50.0))
    edges = breaklines([np.array([[10.0, 10.0], [60.0, 20.0]])])
    fitted = []

    def fit(lines):
        fitted.append(lines)
        return _Fit(lines)

    def confirm(field, straight, again):  # the straight line dropped, the edges confirmed
        return (None if straight is not None else field), None

    lines, first = try_candidates([(cand.line, cand), (edges, None)], fit, confirm)
    assert fitted == [cand.line, edges] and lines is edges and first.field is edges
    assert try_candidates([], fit, confirm) == (None, None)


@pytest.mark.parametrize(
    "side, n, premise",
    [
        # the field fitted with the candidate jumps by 0.12 m at its points' feet, short of
        # a quarter of the scan's 0.55 m step: dropped, though its points take sides along a
        # line turned by 7°
        (50.0, 60_000, "straight breakline dropped: the field jumps by"),
        # it steps along 50 m of the 112 m only: cut to them, and turned by 7.5°
        (100.0, 100_000, "steps along 50 m of the candidate's 112 m"),
    ],
)
def test_a_line_the_scan_proposes_off_its_direction_is_placed_along_the_whole_scarp(
    side, n, premise, monkeypatch, caplog
):
    """A slab's straight scarp across the survey, the scan's proposal turned 7.5° off it
    (its angle step; the harness's ALS slab at extent, seed 2, got 22.5° for 15°). Judged
    along the candidate, the step is dropped (50 m survey) or cut to a third of the line
    (100 m); the decisive points place a line turned onto the scarp, and fitted again along
    it, across the survey, that line is confirmed along the whole scarp (measured: within
    0.38 m and 0.43 m of it over 57 m and 109 m). Cut, as before the retry, the cells by
    the scarp beyond the cut's ends were 0.9-1.5 m off on the harness."""
    import dataclasses

    import slipmap.core.breaklines as bl

    ang = math.radians(15.0)
    u = np.array([math.cos(ang), math.sin(ang)])
    c = np.array([0.5 * side, 0.5 * side])
    slab = SlabField((c - 200.0 * u, c + 200.0 * u), (0.1, -0.5, -0.2))
    before, after = _pair(slab, n=n, side=side)
    real = bl.scan_straight_step

    def turned(d, **kw):
        s = real(d, **kw)
        e0, e1 = s.line.parts[0][0], s.line.parts[0][-1]
        th = math.radians(s.angle_deg + 7.5)
        line = straight_across(0.5 * (e0 + e1), np.array([math.cos(th), math.sin(th)]), s.box_m)
        return dataclasses.replace(s, line=line, angle_deg=s.angle_deg + 7.5)

    monkeypatch.setattr(bl, "detect_breaklines", lambda *a, **k: None)  # the scan's case
    monkeypatch.setattr(bl, "scan_straight_step", turned)
    kw = dict(cell_m=P_CELL, coarse_to_fine=1, field_model="spline", detect_breaklines=True)
    with caplog.at_level(logging.INFO, logger="slipmap.core"):
        res = windowed_icp(before, after, **kw)
    assert premise in caplog.text
    assert "fitted again along their line" in caplog.text
    assert res.breaklines_source == "detected" and len(res.breaklines) == 1
    line = breaklines([p - UTM[:2] for p in res.breaklines.parts])
    scarp = breaklines([np.array([c - 200.0 * u, c + 200.0 * u])])
    p = _over(line, 0.0, side)
    assert distance_m(p, scarp).max() < 1.0
    assert line.length_m() > side  # across the survey, not a stretch of it


class _Lines:
    def __init__(self, lines):
        self.lines = lines  # the candidate the stub field was fitted with


@pytest.mark.parametrize(
    "off_m, turn_deg, cut, kept, retried",
    [
        (1.5, 0.0, False, False, True),  # dropped, its points' line 1.5 m beside it
        (1.5, 0.0, True, True, True),  # cut, 1.5 m beside it
        (0.5, 0.0, False, False, False),  # a tenth of a cell: the candidate was on the step
        (0.5, 3.0, False, False, True),  # turned (stop 59's rule)
        (1.5, 0.0, False, True, False),  # placed whole: nothing to try again
    ],
)
def test_a_line_the_points_place_beside_the_candidate_is_tried_again(
    off_m, turn_deg, cut, kept, retried, monkeypatch
):
    """confirm_lines with a stub placement: the straight line the decisive points place is
    tried again across the survey where the candidate was cut or dropped and that line is
    turned from it (``RETRY_TURN_DEG``) or has an end a fifth of a cell or more off its line
    (``RETRY_DEPART_CELLS``; the harness's TLS fault at 32 m, seed 5: the scan's candidate
    1.5 m beside the fault, dropped, the retry placed along it)."""
    import dataclasses

    import slipmap.core.breakline_points as bp
    from slipmap.core.breakline_points import StraightPlacement
    from slipmap.core.icp import confirm_lines

    box = np.array([[0.0, 0.0], [100.0, 100.0]])
    cand = dataclasses.replace(_step((0.0, 50.0), (100.0, 50.0)), box_m=box)
    on = breaklines([np.array([[10.0, 50.0 + off_m], [90.0, 50.0 + off_m]])])

    def placed(field, after, **kw):
        assert field.lines is cand.line
        return StraightPlacement(on if kept else None, 0.1, 5000, 0.03, off_m, turn_deg,
                                 cut=cut, on_points=on)  # fmt: skip

    monkeypatch.setattr(bp, "place_straight_line", placed)
    kw = dict(before=None, tree=None, normals=None, gate_m=1.0, cell_m=CELL)
    lines, retry = confirm_lines(_Lines(cand.line), None, cand, **kw)
    assert lines is (on if kept else None)
    if not retried:
        assert retry is None
        return
    p = retry.line.parts[0]  # along the points' line, across the box
    np.testing.assert_allclose(p[:, 1], 50.0 + off_m, atol=1e-9)
    np.testing.assert_allclose(np.sort(p[:, 0]), [0.0, 100.0], atol=1e-9)
    assert confirm_lines(_Lines(cand.line), None, cand, again=False, **kw)[1] is None


def test_how_far_a_placed_line_departs_from_the_candidate():
    from slipmap.core.icp import departure_m

    cand = breaklines([np.array([[0.0, 0.0], [100.0, 0.0]])])
    # shifted 1.5 m and turned: its ends 1.5 - 0.5 and 1.5 + 0.5 m off the candidate's line
    placed = breaklines([np.array([[10.0, 1.0], [90.0, 2.0]])])
    assert departure_m(cand, placed) == pytest.approx(2.0, abs=1e-12)
    beyond = breaklines([np.array([[-50.0, -0.5], [150.0, 0.25]])])  # beyond its ends too
    assert departure_m(cand, beyond) == pytest.approx(0.5, abs=1e-12)
    assert departure_m(cand, cand) == 0.0
