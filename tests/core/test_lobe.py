"""Tests of the landslide-lobe injector (slipmap.core.synthetic.LobeField / make_lobe_pair)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from slipmap.core.errors import InputDataError, InvalidParameterError
from slipmap.core.fields import compare_with_truth
from slipmap.core.synthetic import LobeField, LobePair, make_lobe_pair

UTM = np.array([515369.0, 4918340.0])
DATA = Path(__file__).resolve().parents[1] / "data" / "lone-star.laz"


def _cloud(n=4000, seed=0, size=(32.0, 41.0)):
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0.0, 1.0, size=(n, 2)) * size + UTM
    z = 2330.0 + 0.3 * (xy[:, 0] - UTM[0]) + rng.normal(0, 0.05, n)
    return np.column_stack([xy, z])


def _lobe(**kw):
    opts = dict(centre_xy=tuple(UTM + 10.0), radius_x_m=6.0, radius_y_m=9.0, azimuth_deg=30.0)
    opts.update(kw)
    return LobeField(**opts)


def _ellipse_points(lobe, r, n=64):
    """Points at normalised elliptical radius r (map coordinates)."""
    t = np.linspace(0, 2 * math.pi, n, endpoint=False)
    a = math.radians(lobe.azimuth_deg)
    ax = np.array([math.cos(a), -math.sin(a)])
    ay = np.array([math.sin(a), math.cos(a)])
    s = r * lobe.radius_x_m * np.cos(t)
    q = r * lobe.radius_y_m * np.sin(t)
    return np.asarray(lobe.centre_xy) + s[:, None] * ax + q[:, None] * ay


# --- the field ------------------------------------------------------------------------------


def test_max_at_centre_equals_max_d():
    lobe = _lobe(max_d_m=(0.2, -1.0, -0.4))
    d = lobe(np.array([lobe.centre_xy]))
    np.testing.assert_array_equal(d, [[0.2, -1.0, -0.4]])
    rng = np.random.default_rng(0)
    pts = np.asarray(lobe.centre_xy) + rng.uniform(-12, 12, size=(2000, 2))
    w = lobe.weight(pts)
    assert np.all((w >= 0) & (w <= 1))


def test_zero_on_and_outside_the_ellipse():
    lobe = _lobe()
    for r in (1.0 + 1e-8, 1.3, 5.0):  # (exactly 1 is at the mercy of UTM rounding)
        assert np.all(lobe(_ellipse_points(lobe, r)) == 0.0), r
    unit = LobeField((0.0, 0.0), radius_x_m=2.0, radius_y_m=4.0)
    assert np.all(unit([[2.0, 0.0], [0.0, -4.0], [-2.0, 0.0], [0.0, 4.0]]) == 0.0)
    inside = lobe(_ellipse_points(lobe, 0.999))
    assert np.all(inside[:, 1] < 0)


def test_profile_and_orientation():
    """At normalised radius r the bump is (1 - r^2)^2, whatever the direction."""
    lobe = _lobe()
    for r in (0.0, 0.25, 0.5, 0.9):
        w = lobe.weight(_ellipse_points(lobe, r))
        np.testing.assert_allclose(w, (1 - r * r) ** 2, rtol=0, atol=1e-9)
    # azimuth 0: radius_y_m along north, radius_x_m along east
    north = LobeField((0.0, 0.0), radius_x_m=2.0, radius_y_m=8.0)
    assert north.weight([[0.0, 7.9]])[0] > 0 and north.weight([[2.1, 0.0]])[0] == 0
    east = LobeField((0.0, 0.0), radius_x_m=2.0, radius_y_m=8.0, azimuth_deg=90.0)
    assert east.weight([[7.9, 0.0]])[0] > 0 and east.weight([[0.0, 2.1]])[0] == 0


def test_gradient_matches_finite_differences_and_is_c1_at_the_edge():
    lobe = _lobe(max_d_m=(0.3, -1.0, -0.4))
    rng = np.random.default_rng(1)
    pts = np.asarray(lobe.centre_xy) + rng.uniform(-10, 10, size=(300, 2))
    h = 1e-3  # UTM coordinates: rounding ~1e-9 m / h
    num = np.stack(
        [
            (lobe(pts + [h, 0]) - lobe(pts - [h, 0])) / (2 * h),
            (lobe(pts + [0, h]) - lobe(pts - [0, h])) / (2 * h),
        ],
        axis=-1,
    )
    np.testing.assert_allclose(lobe.gradient(pts), num, rtol=0, atol=2e-6)
    # smooth across the edge: the gradient tends to 0 from inside
    edge = lobe.gradient(_ellipse_points(lobe, 1.0 - 1e-6))
    assert np.max(np.abs(edge)) < 1e-5
    assert np.all(lobe.gradient(_ellipse_points(lobe, 1.2)) == 0.0)


def test_interior_mask():
    lobe = _lobe()
    assert np.all(lobe.interior_mask(_ellipse_points(lobe, 0.49)))
    assert not np.any(lobe.interior_mask(_ellipse_points(lobe, 0.51)))
    assert np.all(lobe.interior_mask(_ellipse_points(lobe, 0.8), fraction=0.81))
    with pytest.raises(InvalidParameterError, match="fraction"):
        lobe.interior_mask(_ellipse_points(lobe, 0.5), fraction=0.0)


@pytest.mark.parametrize(
    "bad", [{"radius_x_m": 0.0}, {"radius_y_m": -1.0}, {"radius_x_m": math.inf}]
)
def test_bad_radius(bad):
    with pytest.raises(InvalidParameterError, match="radius"):
        _lobe(**bad)


def test_bad_max_d_and_centre():
    with pytest.raises(InvalidParameterError, match="max_d_m"):
        _lobe(max_d_m=(0.0, -1.0))
    with pytest.raises(InvalidParameterError, match="centre_xy"):
        _lobe(centre_xy=(np.nan, 0.0))


# --- the pair -------------------------------------------------------------------------------


def test_pair_is_a_disjoint_split_with_exact_truth():
    pts = _cloud()
    keep = pts.copy()
    pair = make_lobe_pair(pts, seed=3)
    np.testing.assert_array_equal(pts, keep)  # input untouched
    assert isinstance(pair, LobePair)
    n = pts.shape[0]
    assert pair.before.shape == (n // 2, 3) and pair.after.shape == (n - n // 2, 3)
    both = np.concatenate([pair.before_index, pair.after_index])
    np.testing.assert_array_equal(np.sort(both), np.arange(n))
    assert np.all(np.diff(pair.before_index) > 0) and np.all(np.diff(pair.after_index) > 0)
    np.testing.assert_array_equal(pair.before, pts[pair.before_index])
    original = pts[pair.after_index]
    np.testing.assert_array_equal(pair.after - original, pair.after_truth)
    np.testing.assert_allclose(pair.after_truth, pair.field(original[:, :2]), rtol=0, atol=1e-9)
    # no after point equals any before point (the epochs share no point)
    b = {tuple(p) for p in pair.before}
    assert not any(tuple(p) in b for p in pair.after)
    # defaults: the study's -1 m north, -0.4 m vertical, bbox centre, a third of the short side
    lo, hi = pts[:, :2].min(0), pts[:, :2].max(0)
    np.testing.assert_allclose(pair.field.centre_xy, 0.5 * (lo + hi))
    assert pair.field.radius_x_m == pytest.approx(np.min(hi - lo) / 3)
    assert pair.field.max_d_m == (0.0, -1.0, -0.4)
    moved = np.any(pair.after_truth != 0, axis=1)
    assert 0 < moved.sum() < moved.size
    assert np.min(pair.after_truth[:, 1]) > -1.0 and np.min(pair.after_truth[:, 1]) < -0.9


def test_seeds_are_reproducible():
    pts = _cloud(n=500)
    a, b = make_lobe_pair(pts, seed=7), make_lobe_pair(pts, seed=7)
    np.testing.assert_array_equal(a.after_index, b.after_index)
    np.testing.assert_array_equal(a.after, b.after)
    c = make_lobe_pair(pts, seed=8)
    assert not np.array_equal(a.after_index, c.after_index)


def test_options():
    pts = _cloud(n=1000)
    pair = make_lobe_pair(
        pts,
        max_dx_m=0.5,
        max_dy_m=0.0,
        max_dz_m=0.1,
        centre_xy=UTM + 5.0,
        radius_m=(4.0, 6.0),
        azimuth_deg=45.0,
        after_fraction=0.25,
        seed=1,
    )
    assert pair.after.shape[0] == 250
    assert pair.field.radius_x_m == 4.0 and pair.field.radius_y_m == 6.0
    assert pair.field.max_d_m == (0.5, 0.0, 0.1)
    assert np.all(pair.after_truth[:, 1] == 0.0)


@given(st.floats(-1e5, 1e5), st.floats(-1e5, 1e5))
def test_translating_the_cloud_translates_the_pair(tx, ty):
    pts = _cloud(n=300)
    a = make_lobe_pair(pts, seed=2)
    b = make_lobe_pair(pts + [tx, ty, 0.0], seed=2)
    np.testing.assert_array_equal(a.after_index, b.after_index)
    np.testing.assert_allclose(b.after_truth, a.after_truth, rtol=0, atol=1e-8)


def test_bad_pair_input():
    pts = _cloud(n=100)
    with pytest.raises(InputDataError, match="at least 2 points"):
        make_lobe_pair(pts[:1])
    with pytest.raises(InputDataError, match=r"\(N, 3\)"):
        make_lobe_pair(pts[:, :2])
    bad = pts.copy()
    bad[3, 2] = np.nan
    with pytest.raises(InputDataError, match="NaN"):
        make_lobe_pair(bad)
    with pytest.raises(InvalidParameterError, match="radius"):
        make_lobe_pair(pts, radius_m=0.0)
    with pytest.raises(InvalidParameterError, match="radius"):
        make_lobe_pair(pts, radius_m=(3.0, -1.0))
    with pytest.raises(InvalidParameterError, match="split"):
        make_lobe_pair(pts, split="jitter")
    with pytest.raises(InvalidParameterError, match="after_fraction"):
        make_lobe_pair(pts, after_fraction=1.0)
    with pytest.raises(InputDataError, match="covers none"):
        make_lobe_pair(pts, centre_xy=UTM - 1000.0, radius_m=5.0)
    flat = pts.copy()
    flat[:, 0] = UTM[0]
    with pytest.raises(InputDataError, match="radius_m"):
        make_lobe_pair(flat)


def test_compare_with_truth_on_exact_truth_is_zero():
    pair = make_lobe_pair(_cloud(n=2000), seed=0)
    xy = pair.after[:, :2] - pair.after_truth[:, :2]  # original positions
    res = compare_with_truth(xy, pair.after_truth, pair.field)
    assert res.n_compared == xy.shape[0]
    assert res.rmse_horizontal_m < 1e-9 and res.rmse_dz_m < 1e-9
    mask = pair.field.interior_mask(xy)
    res = compare_with_truth(xy, pair.after_truth, pair.field, mask=mask)
    assert res.n_compared == int(mask.sum()) > 0 and res.max_abs_horizontal_m < 1e-9


@pytest.mark.skipif(not DATA.exists(), reason="lone-star.laz test data missing")
def test_real_cloud():
    from slipmap.core.io.las import read_las

    pts = read_las(DATA).xyz
    pair = make_lobe_pair(pts, seed=0)
    assert pair.before.shape[0] + pair.after.shape[0] == pts.shape[0]
    assert np.intersect1d(pair.before_index, pair.after_index).size == 0
    np.testing.assert_allclose(
        pair.after_truth, pair.field(pts[pair.after_index]), rtol=0, atol=1e-8
    )
    inner = pair.field.interior_mask(pair.after)
    assert inner.sum() > 10_000  # ~390 pts/m2 over pi * (0.5 * 10.8 m)^2 / 2
