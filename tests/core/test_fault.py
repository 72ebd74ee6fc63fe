"""Fault-trace geometry: sides, distances, chainage, strike and the slip sign conventions."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from slipmap.core.errors import InputDataError, InvalidParameterError
from slipmap.core.fault import (
    FaultTrace,
    fault_geometry,
    fault_parallel_normal,
    fault_trace,
    mean_strike_rad,
    right_lateral_slip,
    side_masks,
    trace_in_data_check,
)

NS = fault_trace(np.array([[0.0, 0.0], [0.0, 100.0]]))  # digitised towards the north
# L-shaped: north 100 m, then east 100 m (a right turn at (0, 100))
L_TRACE = fault_trace(np.array([[0.0, 0.0], [0.0, 100.0], [100.0, 100.0]]))


def test_straight_north_south_trace_hand_placed_points():
    pts = np.array(
        [
            [-5.0, 50.0],  # west = left
            [7.0, 20.0],  # east = right
            [0.0, 30.0],  # on the trace
            [3.0, -4.0],  # beyond the start: distance to the start vertex, side from the line
            [-6.0, 108.0],  # beyond the end
        ]
    )
    g = fault_geometry(pts, NS)
    np.testing.assert_array_equal(g.side, [-1, 1, 0, 1, -1])
    assert g.side.dtype == np.int8
    np.testing.assert_allclose(g.distance_m, [5.0, 7.0, 0.0, 5.0, 10.0])
    np.testing.assert_allclose(g.along_strike_m, [50.0, 20.0, 30.0, 0.0, 100.0])
    np.testing.assert_allclose(g.strike_rad, 0.0)
    np.testing.assert_array_equal(g.segment, 0)
    assert NS.length_m() == pytest.approx(100.0)
    left, right = side_masks(g, buffer_m=6.0)
    np.testing.assert_array_equal(left, [False, False, False, False, True])
    np.testing.assert_array_equal(right, [False, True, False, False, False])


def test_l_shaped_trace_vertex_uses_pseudo_normal():
    pts = np.array(
        [
            [10.0, 110.0],  # inside the turn (left of both segments), nearest: 2nd segment
            [-5.0, 105.0],  # outside the corner, nearest point is the vertex: left
            [3.0, 97.0],  # inside the corner (right of both), nearest: interior points
            [-1.0, 120.0],  # beyond the vertex on the left
            [5.0, 90.0],  # right of the first segment
            [50.0, 95.0],  # right of (below) the second segment
            [-3.0, 103.0],  # exactly on the outer bisector: left
        ]
    )
    g = fault_geometry(pts, L_TRACE)
    np.testing.assert_array_equal(g.side, [-1, -1, 1, -1, 1, 1, -1])
    np.testing.assert_allclose(
        g.distance_m, [10.0, math.hypot(5, 5), 3.0, math.hypot(1, 20), 5.0, 5.0, math.hypot(3, 3)]
    )
    # outside-corner points sit at the vertex: chainage 100, strike = bisector (north-east)
    np.testing.assert_allclose(g.along_strike_m[[1, 3, 6]], 100.0)
    np.testing.assert_allclose(g.strike_rad[[1, 3, 6]], math.pi / 4)
    np.testing.assert_allclose(g.strike_rad[[4]], 0.0)
    np.testing.assert_allclose(g.strike_rad[[0, 5]], math.pi / 2)
    np.testing.assert_allclose(g.along_strike_m[[0, 4, 5]], [110.0, 90.0, 150.0])


def test_multilinestring_parts_have_own_segments_and_concatenated_chainage():
    tr = fault_trace(
        [
            np.array([[0.0, 0.0], [0.0, 50.0]]),
            np.array([[10.0, 60.0, 0.0], [10.0, 110.0, 5.0]]),  # z is dropped
        ]
    )
    assert len(tr.parts) == 2
    assert tr.vertices.shape == (4, 2)
    assert tr.length_m() == pytest.approx(100.0)
    pts = np.array([[-2.0, 10.0], [12.0, 100.0], [5.0, 55.0 - 1e-9], [0.0, 80.0]])
    g = fault_geometry(pts, tr)
    np.testing.assert_array_equal(g.segment, [0, 1, 0, 1])
    np.testing.assert_array_equal(g.side[:2], [-1, 1])
    # no segment joins (0, 50) to (10, 60): the gap point is nearest to a part end
    assert g.distance_m[2] == pytest.approx(math.hypot(5, 5), abs=1e-6)
    np.testing.assert_allclose(g.along_strike_m[[0, 1, 3]], [10.0, 90.0, 70.0])
    assert g.distance_m[3] == pytest.approx(10.0)


def test_reversing_the_trace_flips_side_strike_and_fault_parallel():
    rng = np.random.default_rng(1)
    tr = fault_trace(np.array([[0.0, 0.0], [10.0, 40.0], [-5.0, 80.0], [20.0, 120.0]]))
    pts = rng.uniform([-50, -20], [60, 140], size=(500, 2))
    g = fault_geometry(pts, tr)
    r = fault_geometry(pts, tr.reversed())
    np.testing.assert_array_equal(r.side, -g.side)
    np.testing.assert_allclose(r.distance_m, g.distance_m, atol=1e-9)
    np.testing.assert_allclose(r.along_strike_m, tr.length_m() - g.along_strike_m, atol=1e-9)
    dstrike = np.mod(r.strike_rad - g.strike_rad, 2 * math.pi)
    np.testing.assert_allclose(dstrike, math.pi, atol=1e-9)
    assert mean_strike_rad(tr.reversed()) == pytest.approx(
        (mean_strike_rad(tr) + math.pi) % (2 * math.pi)
    )
    v = rng.normal(size=(500, 2))
    par_g, nor_g = fault_parallel_normal(v, g.strike_rad)
    par_r, nor_r = fault_parallel_normal(v, r.strike_rad)
    np.testing.assert_allclose(par_r, -par_g, atol=1e-12)
    np.testing.assert_allclose(nor_r, -nor_g, atol=1e-12)


def test_strike_of_an_eastward_trace_and_mean_strike():
    east = fault_trace(np.array([[0.0, 0.0], [100.0, 0.0]]))
    g = fault_geometry(np.array([[50.0, 10.0], [50.0, -10.0]]), east)
    np.testing.assert_allclose(g.strike_rad, math.pi / 2)
    np.testing.assert_array_equal(g.side, [-1, 1])  # north is left, south is right
    assert mean_strike_rad(east) == pytest.approx(math.pi / 2)
    assert mean_strike_rad(NS) == pytest.approx(0.0)
    # length-weighted: 300 m north + 100 m east
    tr = fault_trace(np.array([[0.0, 0.0], [0.0, 300.0], [100.0, 300.0]]))
    assert mean_strike_rad(tr) == pytest.approx(math.atan2(100, 300))
    west = fault_trace(np.array([[0.0, 0.0], [-1.0, 1e-3]]))
    assert 0.0 <= mean_strike_rad(west) < 2 * math.pi
    assert mean_strike_rad(west) == pytest.approx(3 * math.pi / 2, abs=1e-2)
    with pytest.raises(InputDataError, match="doubles back"):
        mean_strike_rad(fault_trace(np.array([[0.0, 0.0], [0.0, 10.0], [0.0, 0.0]])))


def test_dextral_example_sign_convention():
    # trace digitised north: the right side is east. Dextral: east side moves south
    g = fault_geometry(np.array([[10.0, 50.0], [-10.0, 50.0]]), NS)
    assert g.side[0] == 1 and g.side[1] == -1  # east is right
    v = 0.7
    d_right = np.array([0.0, -v / 2])  # east block moves south
    d_left = np.array([0.0, v / 2])  # west block moves north
    r = d_right - d_left
    parallel, normal = fault_parallel_normal(r, g.strike_rad[0])
    assert parallel == pytest.approx(-v)
    assert normal == pytest.approx(0.0, abs=1e-15)
    assert right_lateral_slip(r, g.strike_rad[0]) == pytest.approx(v)
    # sinistral is negative; opening (right side moves east, away) has a positive normal
    assert right_lateral_slip(-r, 0.0) == pytest.approx(-v)
    assert fault_parallel_normal(np.array([1.0, 0.0]), 0.0)[1] == pytest.approx(1.0)
    # same motion described with the trace digitised south: sides swap, so r flips sign,
    # the strike flips by π, and the right-lateral slip is unchanged
    assert right_lateral_slip(-r, math.pi) == pytest.approx(v)


TRACE_FOR_PROPERTY = fault_trace(
    np.array([[0.0, 0.0], [30.0, 40.0], [20.0, 90.0], [60.0, 130.0], [55.0, 180.0]])
)
PTS_FOR_PROPERTY = np.random.default_rng(7).uniform([-60, -40], [120, 220], size=(300, 2))


@given(
    theta=st.floats(-math.pi, math.pi),
    tx=st.floats(-1e6, 1e6),
    ty=st.floats(-5e6, 5e6),
)
def test_rigid_motion_invariance(theta, tx, ty):
    c, s = math.cos(theta), math.sin(theta)
    rot = np.array([[c, -s], [s, c]])  # counter-clockwise by theta
    shift = np.array([tx, ty])
    tr2 = fault_trace([p @ rot.T + shift for p in TRACE_FOR_PROPERTY.parts])
    g1 = fault_geometry(PTS_FOR_PROPERTY, TRACE_FOR_PROPERTY)
    g2 = fault_geometry(PTS_FOR_PROPERTY @ rot.T + shift, tr2)
    far = g1.distance_m > 1e-6
    np.testing.assert_array_equal(g2.side[far], g1.side[far])
    np.testing.assert_allclose(g2.distance_m, g1.distance_m, atol=1e-6)
    np.testing.assert_allclose(g2.along_strike_m, g1.along_strike_m, atol=1e-6)
    # a counter-clockwise rotation by theta lowers the azimuth (clockwise) by theta
    diff = np.angle(np.exp(1j * (g2.strike_rad - (g1.strike_rad - theta))))
    np.testing.assert_allclose(diff, 0.0, atol=1e-9)
    assert np.all((g2.strike_rad >= 0) & (g2.strike_rad < 2 * math.pi))


def test_chunked_equals_unchunked_and_kdtree_equals_brute():
    rng = np.random.default_rng(3)
    verts = np.cumsum(rng.normal([0.5, 2.0], [3.0, 1.0], size=(300, 2)), axis=0)
    tr = fault_trace([verts[:150], verts[150:] + [20.0, 0.0]])
    lo, hi = tr.vertices.min(axis=0) - 50, tr.vertices.max(axis=0) + 50
    pts = rng.uniform(lo, hi, size=(3000, 2))
    pts[:5] = tr.vertices[::60][:5] + 1e-3  # near vertices
    full = fault_geometry(pts, tr, method="brute")
    for other in (
        fault_geometry(pts, tr, method="brute", chunk_points=77),
        fault_geometry(pts, tr, method="kdtree"),
        fault_geometry(pts, tr, method="kdtree", chunk_points=101),
    ):
        np.testing.assert_allclose(other.distance_m, full.distance_m, rtol=0, atol=1e-9)
        np.testing.assert_array_equal(other.side, full.side)
        np.testing.assert_allclose(other.along_strike_m, full.along_strike_m, atol=1e-9)
        np.testing.assert_allclose(other.strike_rad, full.strike_rad, atol=1e-12)
    # far-away points (the KD-tree's candidate ball grows with distance) stay exact
    far = rng.uniform(lo - 2000, hi + 2000, size=(500, 2))
    a = fault_geometry(far, tr, method="brute")
    b = fault_geometry(far, tr, method="kdtree")
    np.testing.assert_allclose(b.distance_m, a.distance_m, atol=1e-9)
    np.testing.assert_array_equal(b.side, a.side)


def test_progress_is_reported():
    calls = []
    fault_geometry(
        np.zeros((10, 2)) + [1.0, 5.0], NS, chunk_points=4, progress=lambda f, m: calls.append(f)
    )
    assert calls == pytest.approx([0.4, 0.8, 1.0])


@pytest.mark.parametrize(
    "parts",
    [
        [],
        [np.array([[0.0, 0.0]])],
        [np.array([[1.0, 1.0], [1.0, 1.0]])],
        [np.array([[0.0, 0.0], [np.nan, 1.0]])],
        [np.array([[0.0, 0.0], [1.0, np.inf]])],
        [np.array([0.0, 1.0, 2.0, 3.0]).reshape(1, 4)],
        [np.array([[0.0, 0.0], [1.0, 1.0]]), np.array([[5.0, 5.0]])],
    ],
)
def test_bad_traces_raise(parts):
    with pytest.raises(InvalidParameterError):
        fault_trace(parts)


def test_repeated_vertices_are_dropped_and_z_ignored():
    tr = fault_trace(np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 2.0], [0.0, 10.0, 3.0]]))
    assert isinstance(tr, FaultTrace)
    assert tr.parts[0].shape == (2, 2)


def test_bad_points_and_parameters():
    with pytest.raises(InvalidParameterError):
        fault_geometry(np.zeros(5), NS)
    with pytest.raises(InputDataError):
        fault_geometry(np.array([[np.nan, 0.0]]), NS)
    with pytest.raises(InvalidParameterError):
        fault_geometry(np.zeros((2, 2)), NS, chunk_points=0)
    g = fault_geometry(np.zeros((2, 2)), NS)
    with pytest.raises(InvalidParameterError):
        side_masks(g, buffer_m=-1)


def test_trace_in_data_check():
    rng = np.random.default_rng(5)
    pts = rng.uniform([-100, 0, 0], [100, 100, 5], size=(400, 3))
    g = trace_in_data_check(NS, pts, buffer_m=10.0)
    assert set(np.unique(g.side)) <= {-1, 0, 1}
    # a trace outside the data (e.g. wrong CRS)
    far = fault_trace(np.array([[5e5, 4e6], [5e5, 4.1e6]]))
    with pytest.raises(InputDataError, match="does not cross the data's extent"):
        trace_in_data_check(far, pts, buffer_m=10.0)
    # data all east of the trace, but the trace still crosses the extent's corner
    east_pts = rng.uniform([1, 0], [100, 100], size=(50, 2))
    edge = fault_trace(np.array([[0.0, 90.0], [10.0, 110.0]]))
    with pytest.raises(InputDataError, match=r"has all \d+ points .* on its right side"):
        trace_in_data_check(edge, east_pts, buffer_m=0.0)
    with pytest.raises(InputDataError, match="within the 1000 m buffer"):
        trace_in_data_check(NS, pts, buffer_m=1000.0)
