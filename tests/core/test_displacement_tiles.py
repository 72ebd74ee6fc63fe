"""Tiles, strips and moving windows (Kusari et al. 2019, section IV) on synthetic fault pairs."""

import json
import math

import numpy as np
import pytest

from slipmap.core.displacement import (
    SlipResult,
    StripResult,
    TileResult,
    WindowField,
    estimate_slip,
    strip_profile,
    window_field,
)
from slipmap.core.errors import InvalidParameterError
from slipmap.core.fault import fault_trace
from slipmap.core.synthetic import make_fault_pair

ORIGIN = (500000.0, 4200000.0, 10.0)
NLOD = 0.0181
SIG = dict(sigma_before=0.02, sigma_after=0.02)


@pytest.fixture(scope="module")
def pair():
    return make_fault_pair(
        "mls", seed=7, origin=ORIGIN, right_offset_m=(0.0, -NLOD, 0.0), vegetation=False
    )


@pytest.fixture(scope="module")
def trace(pair):
    return fault_trace([pair.trace_xy])


@pytest.fixture(scope="module")
def plain(pair, trace):
    return estimate_slip(pair.before.points, pair.after.points, trace, **SIG)


def test_joint_tiles_match_untiled(pair, trace, plain):
    res = estimate_slip(pair.before.points, pair.after.points, trace, tile_size_m=35.0, **SIG)
    assert isinstance(res, SlipResult) and res.parameters["tile_size_m"] == 35.0
    assert np.allclose(res.relative, plain.relative, atol=0.001)
    assert np.allclose(res.relative, pair.relative_offset_m, atol=0.001)
    assert plain.tiles == ()
    assert res.tiles and all(isinstance(t, TileResult) for t in res.tiles)
    ok = [t for t in res.tiles if t.status == "ok"]
    assert ok and all(t.n_planes >= 3 for t in ok)
    for t in res.tiles:  # grid aligned to multiples of the tile size
        assert t.bounds == (t.ix * 35.0, t.iy * 35.0, (t.ix + 1) * 35.0, (t.iy + 1) * 35.0)
        if t.status != "ok":
            assert t.status.startswith("skipped") and np.all(np.isnan(t.covariance))
    # planes never span tiles: the merged labels stay unique per side
    for side in (res.left, res.right):
        assert side.planes_before.labels.max() == len(side.planes_before) - 1
        assert len(side.matches) == sum(t.n_planes for t in res.tiles if t.side == side.side)
    json.dumps(res.to_dict())


def test_tiles_combination_is_honest_under_the_full_model(pair, trace):
    """With a stochastic model the tiles' mean is never tighter than the joint GLS (which
    uses every plane with the full correlation) and tiles hold the side's components."""
    res = estimate_slip(
        pair.before.points, pair.after.points, trace, tile_size_m=35.0, combine="tiles",
        stochastic_model="full", **SIG,
    )  # fmt: skip
    assert np.allclose(res.relative, pair.relative_offset_m, atol=0.003)
    for side in (res.left, res.right):
        joint = side.rigid.displacement_covariance
        ev = np.linalg.eigvalsh(side.displacement_covariance - joint)
        assert ev.min() >= -1e-12 * np.abs(joint).max()


def test_tiles_combination_is_information_weighted(pair, trace):
    res = estimate_slip(
        pair.before.points, pair.after.points, trace, tile_size_m=35.0, combine="tiles",
        stochastic_model="white", **SIG,
    )  # fmt: skip
    assert res.parameters["combine"] == "tiles"
    assert np.allclose(res.relative, pair.relative_offset_m, atol=0.0015)
    for side in (res.left, res.right):
        ok = [t for t in res.tiles if t.side == side.side and t.status == "ok"]
        assert len(ok) >= 2
        info = sum(np.linalg.inv(t.covariance) for t in ok)
        cov = np.linalg.inv(info)
        d = cov @ sum(np.linalg.inv(t.covariance) @ t.displacement for t in ok)
        assert np.allclose(side.displacement, d, atol=1e-9)
        assert np.allclose(side.displacement_covariance, cov, rtol=1e-6, atol=1e-15)
        # the combination is tighter than any single tile
        assert all(np.all(np.diag(cov) <= np.diag(t.covariance) + 1e-15) for t in ok)
    assert np.allclose(
        res.relative_covariance,
        res.left.displacement_covariance + res.right.displacement_covariance,
    )


def _check_strips(strips, expected_right, tol_extra=0.001):
    n_ok = {"left": 0, "right": 0}
    for s in strips:
        assert isinstance(s, StripResult)
        assert s.along_centre_m == pytest.approx(0.5 * (s.along_start_m + s.along_end_m))
        if s.status != "ok":
            assert s.status.startswith("skipped") and math.isnan(s.fault_parallel)
            continue
        n_ok[s.side] += 1
        assert s.n_planes >= 3
        want = expected_right(s) if s.side == "right" else 0.0
        assert abs(s.fault_parallel - want) < 3 * s.sigma_fault_parallel + tol_extra, s
    assert n_ok["left"] >= 1 and n_ok["right"] >= 1


def test_strip_profile_constant_slip(pair, trace, plain):
    strips = strip_profile(
        pair.before.points, pair.after.points, trace, plain, strip_width_m=50.0, **SIG
    )
    _check_strips(strips, lambda s: -NLOD)
    assert [s.side for s in strips] == sorted(s.side for s in strips)  # left first


def test_strip_profile_shows_a_step(pair, trace):
    centre_y = ORIGIN[1] + 50.0  # trace chainage 100 m
    after = pair.after.points.copy()
    right = after[:, 0] > pair.trace_xy[0, 0]
    dy = np.where(after[:, 1] < centre_y, -0.01, -0.03)
    after[right, 1] += dy[right] + NLOD  # replace the -18.1 mm by a y-dependent slip
    slip = estimate_slip(pair.before.points, after, trace, **SIG)
    strips = strip_profile(pair.before.points, after, trace, slip, strip_width_m=50.0, **SIG)
    right_ok = {s.along_start_m: s for s in strips if s.side == "right" and s.status == "ok"}
    south, north = right_ok[50.0], right_ok[100.0]
    assert abs(south.fault_parallel + 0.01) < 3 * south.sigma_fault_parallel + 0.0015
    assert abs(north.fault_parallel + 0.03) < 3 * north.sigma_fault_parallel + 0.0015
    assert south.fault_parallel - north.fault_parallel > 0.015
    _check_strips(strips, lambda s: -0.01 if s.along_end_m <= 100.0 else -0.03, 0.0015)
    # full model: a right strip adds the left side's covariance; a left strip shares its data
    # with the left global estimate, C_strip - C_left, at least C_strip / 4 (PSD order)
    ref = slip.left.displacement_covariance
    for st in strips:
        if st.status != "ok":
            continue
        rc = st.relative_covariance
        if st.side == "right":
            np.testing.assert_allclose(rc, st.covariance + ref, rtol=1e-12)
        else:
            tol = -1e-12 * np.abs(st.covariance).max()
            assert np.linalg.eigvalsh(rc - 0.25 * st.covariance).min() >= tol
            assert np.linalg.eigvalsh(st.covariance - rc).min() >= tol


def test_window_field(pair, trace, plain):
    wf = window_field(
        pair.before.points,
        pair.after.points,
        trace,
        plain,
        window_size_m=40.0,
        window_step_m=20.0,
        **SIG,
    )
    assert isinstance(wf, WindowField)
    ny, nx = wf.shape
    assert (ny, nx) == wf.n_planes.shape == wf.side.shape and ny >= 2 and nx >= 2
    xs, ys = wf.centres()
    assert xs[0, 0] == pytest.approx(wf.x0) and ys[0, 0] == pytest.approx(wf.y0)
    assert np.all(np.diff(ys[:, 0]) < 0) and np.all(np.diff(xs[0]) > 0)  # north-up rows
    ok = np.isfinite(wf.dy)
    assert np.all(~ok[wf.n_planes < 3]) and np.any(wf.n_planes < 3)
    right, left = ok & (wf.side > 0), ok & (wf.side < 0)
    assert right.sum() >= 2 and left.sum() >= 2
    tol = 3 * wf.sigma_dy + 0.001
    assert np.all(np.abs(wf.dy[right] + NLOD) < tol[right])
    assert np.all(np.abs(wf.dy[left]) < tol[left])
    assert np.all(np.abs(wf.dx[ok]) < 3 * wf.sigma_dx[ok] + 0.001)
    assert np.all(wf.side[:, xs[0] > pair.trace_xy[0, 0]] == 1)


@pytest.mark.parametrize("bad", [0.0, -5.0, float("nan"), "x"])
def test_bad_parameters_raise(pair, trace, plain, bad):
    b, a = pair.before.points, pair.after.points
    with pytest.raises(InvalidParameterError, match="strip_width_m"):
        strip_profile(b, a, trace, plain, strip_width_m=bad)
    with pytest.raises(InvalidParameterError, match="window_size_m"):
        window_field(b, a, trace, plain, window_size_m=bad, window_step_m=20.0)
    with pytest.raises(InvalidParameterError, match="window_step_m"):
        window_field(b, a, trace, plain, window_size_m=40.0, window_step_m=bad)
    with pytest.raises(InvalidParameterError, match="tile_size_m"):
        estimate_slip(b, a, trace, tile_size_m=bad)


def test_bad_options_raise(pair, trace, plain):
    b, a = pair.before.points, pair.after.points
    with pytest.raises(InvalidParameterError, match="combine"):
        estimate_slip(b, a, trace, tile_size_m=35.0, combine="mean")
    with pytest.raises(InvalidParameterError, match="min_planes"):
        window_field(b, a, trace, plain, window_size_m=40, window_step_m=20, min_planes=2)
