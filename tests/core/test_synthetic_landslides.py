"""Landslide geometries of core/synthetic.py (issue #29) against their formulas."""

from __future__ import annotations

import math

import numpy as np
import pytest

from slipmap.core.breaklines import breaklines, crossings
from slipmap.core.errors import InvalidParameterError
from slipmap.core.synthetic import (
    AlsSampling,
    FaultField,
    LobeField,
    SlabField,
    SlumpField,
    SumField,
    field_breaklines,
    make_landslide_pair,
    material_motion,
)

E0, N0 = 500_000.0, 4_200_000.0


def _ground(n=20_000, side=40.0, seed=0):
    """A rough random surface on [0, side]² (UTM-like offsets)."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0.0, side, (n, 2))
    z = 0.3 * np.sin(xy[:, 0] / 3.0) * np.cos(xy[:, 1] / 4.0) + 0.002 * rng.standard_normal(n)
    return np.column_stack([xy[:, 0] + E0, xy[:, 1] + N0, z + 1500.0])


def test_slab_moves_by_its_vector_on_one_side_and_not_on_the_other():
    # scarp along +x at y = N0 + 20: left of it (north) is the slab
    slab = SlabField(((E0, N0 + 20.0), (E0 + 40.0, N0 + 20.0)), (0.1, 0.4, -0.2))
    pts = _ground()
    pair = make_landslide_pair(pts, slab, seed=3)
    north = pts[pair.after_index, 1] > N0 + 20.0
    assert north.any() and (~north).any()
    np.testing.assert_array_equal(
        pair.after_truth[north], np.tile([0.1, 0.4, -0.2], (north.sum(), 1))
    )
    assert np.all(pair.after_truth[~north] == 0.0)
    np.testing.assert_allclose(pair.after - pts[pair.after_index], pair.after_truth, atol=1e-9)
    # the epochs are disjoint halves of the cloud
    assert not np.intersect1d(pair.before_index, pair.after_index).size
    assert len(pair.before_index) + len(pair.after_index) == len(pts)
    # the breakline is the scarp; a segment across it crosses it
    (line,) = pair.breaklines
    np.testing.assert_array_equal(line, [[E0, N0 + 20.0], [E0 + 40.0, N0 + 20.0]])
    bl = breaklines(pair.breaklines)
    assert crossings(np.array([[E0 + 5, N0 + 10]]), np.array([[E0 + 5, N0 + 30]]), bl)[0]


def test_slab_truth_at_centres_is_the_material_motion_and_nan_in_the_gap():
    slab = SlabField(((E0, N0), (E0 + 40.0, N0)), (0.0, 0.5, 0.0))  # moves north, away
    c = np.array([[E0 + 5, N0 + 10.0], [E0 + 5, N0 - 3.0], [E0 + 5, N0 + 0.2]])
    t = material_motion(slab, c)
    np.testing.assert_array_equal(t[0], [0.0, 0.5, 0.0])  # slab material (came from y + 9.5)
    np.testing.assert_array_equal(t[1], [0.0, 0.0, 0.0])  # stable ground
    assert np.all(np.isnan(t[2]))  # the 0.5 m gap the slab opened: no material there


def test_slump_rotates_the_block_about_its_axis():
    f = SlumpField(
        (E0, N0), azimuth_deg=90.0, head_m=8.0, toe_m=10.0, width_m=12.0,
        axis_height_m=6.0, slope_deg=0.0, rotation_deg=4.0,
    )  # fmt: skip
    th = math.radians(4.0)
    # downslope is east: s = x - E0, ground h = -6 below the axis (flat reference)
    s = np.array([-7.0, -2.0, 0.0, 5.0, 9.5])
    xy = np.column_stack([E0 + s, np.full(5, N0 + 1.0)])
    d = f(xy)
    rot = np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])
    sh = np.column_stack([s, np.full(5, -6.0)])
    moved = sh @ rot.T  # (s', h') of a rigid rotation about (0, 0)
    np.testing.assert_allclose(d[:, 0], moved[:, 0] - s, atol=1e-12)
    np.testing.assert_allclose(d[:, 1], 0.0, atol=1e-12)
    np.testing.assert_allclose(d[:, 2], moved[:, 1] + 6.0, atol=1e-12)
    # rigid: distances between moved reference points are kept
    p = np.column_stack([s, np.full(5, -6.0)]) + d[:, [0, 2]]
    q = np.column_stack([s, np.full(5, -6.0)])
    np.testing.assert_allclose(np.diff(np.linalg.norm(p - p[0], axis=1)),
                               np.diff(np.linalg.norm(q - q[0], axis=1)), atol=1e-12)  # fmt: skip
    # head drops, toe rises; outside the block nothing moves
    assert d[0, 2] < 0 < d[-1, 2]
    out = np.array([[E0 - 8.5, N0], [E0 + 10.5, N0], [E0, N0 + 6.5]])
    assert np.all(f(out) == 0.0)
    (ring,) = f.breaklines
    np.testing.assert_allclose(ring[0], ring[-1])
    np.testing.assert_allclose(np.sort(np.unique(ring[:, 0])), [E0 - 8.0, E0 + 10.0])


def test_slump_over_real_relief_moves_its_block_as_one_rigid_body():
    """With ``ground`` every point of the block turns by one rotation about the axis, by its
    own height: distances in the block are kept, whatever the relief; a 2-column call reads
    the ground's height, and the truth at a centre inverts the motion in 3-D."""

    def ground(xy):
        xy = np.asarray(xy, dtype=np.float64)
        return 1500.0 + 1.5 * np.sin(0.4 * (xy[:, 0] - E0)) + 0.8 * np.cos(0.3 * (xy[:, 1] - N0))

    f = SlumpField((E0, N0), azimuth_deg=180.0, head_m=8.0, toe_m=8.0, width_m=12.0,
                   rotation_deg=3.0, ground=ground)  # fmt: skip
    rng = np.random.default_rng(7)
    xy = np.column_stack([E0 + rng.uniform(-5, 5, 200), N0 + rng.uniform(-7, 7, 200)])
    p = np.column_stack([xy, ground(xy) + rng.normal(0.0, 0.5, 200)])  # points off the ground
    assert np.all(f.in_block(p))
    q = p + f(p)
    i, j = rng.integers(0, 200, (2, 500))
    np.testing.assert_allclose(np.linalg.norm(q[i] - q[j], axis=1),
                               np.linalg.norm(p[i] - p[j], axis=1), atol=1e-9)  # fmt: skip
    # not a field of map position: two heights at one place move differently, by theta * dz
    two = np.array([[E0, N0 - 4.0, 1500.0], [E0, N0 - 4.0, 1502.0]])
    dd = f(two)
    np.testing.assert_allclose(np.linalg.norm(dd[1] - dd[0]), 2.0 * 2 * math.sin(math.radians(1.5)))
    np.testing.assert_allclose(f(xy), f(np.column_stack([xy, ground(xy)])), atol=1e-12)
    # the material now at a 3-D centre came from where the field carries it there
    c = q[:20]
    np.testing.assert_allclose(material_motion(f, c), f(p[:20]), atol=1e-7)


def test_fault_offsets_a_smooth_field_by_its_slip():
    base = LobeField((E0 + 20, N0 + 20), 15.0, 15.0, 0.0, (0.1, -0.3, -0.1))
    f = FaultField(((E0, N0), (E0 + 40, N0 + 40)), slip_m=0.3, throw_m=0.06, base=base)
    u = np.array([1.0, 1.0]) / math.sqrt(2.0)
    v = np.array([-u[1], u[0]])
    p = np.array([[E0 + 20.0, N0 + 20.0], [E0 + 25.0, N0 + 25.0]])  # on the trace
    left, right = p + 1e-3 * v, p - 1e-3 * v
    jump = f(left) - f(right)
    expect = np.tile([0.3 * u[0], 0.3 * u[1], 0.06], (2, 1))
    np.testing.assert_allclose(jump, expect, atol=1e-4)  # the base is continuous
    np.testing.assert_allclose(f(left) + f(right), 2 * base(p), atol=1e-4)
    assert len(field_breaklines(f)) == 1 and field_breaklines(base) == ()


def test_material_motion_is_the_fixed_point_of_a_smooth_field():
    lobe = LobeField((E0, N0), 12.0, 18.0, 25.0, (0.3, -0.8, -0.3))
    rng = np.random.default_rng(1)
    c = np.array([E0, N0]) + rng.uniform(-15, 15, (200, 2))
    t = material_motion(lobe, c)
    p0 = c - t[:, :2]
    np.testing.assert_allclose(lobe(p0), t, atol=1e-9)  # the material at p0 ended at c
    np.testing.assert_allclose(p0 + lobe(p0)[:, :2], c, atol=1e-6)
    inside = lobe.weight(c) > 0.5
    assert np.abs(t - lobe(c))[inside].max() > 1e-3  # not the field at the centre itself


def test_sum_field_adds_parts_and_gathers_their_lines():
    slab = SlabField(((E0, N0), (E0 + 10, N0)), (0.0, 0.2, 0.0))
    lobe = LobeField((E0, N0 - 20), 5.0, 5.0, 0.0, (0.1, 0.0, 0.0))
    s = SumField((slab, lobe))
    xy = np.array([[E0 + 1, N0 + 1], [E0, N0 - 20]])
    np.testing.assert_allclose(s(xy), slab(xy) + lobe(xy))
    assert len(s.breaklines) == 1


def test_als_sampling_thins_to_its_nominal_density_in_strips():
    rng = np.random.default_rng(2)
    xy = rng.uniform(0, 60, (200_000, 2)) + [E0, N0]  # 55 pts/m²
    als = AlsSampling(line_spacing_m=0.5, point_spacing_m=0.4, strips=2, overlap=0.3)
    k = als.sample(xy, np.random.default_rng(0))
    assert np.all(np.diff(k) > 0)
    density = len(k) / 3600.0
    # one strip 5 pts/m², overlap 10: ~(1 + 0.3 / 1.7) * 5 over the square, a little fewer
    # where a footprint finds no point within 0.2 m
    assert 4.5 < density < 6.5
    # independent surveys: another epoch's draw returns other points
    k2 = als.sample(xy, np.random.default_rng(1))
    assert len(np.intersect1d(k, k2)) < 0.2 * len(k)


def test_landslide_pair_als_keeps_the_truth_of_the_kept_points():
    slab = SlabField(((E0, N0 + 20.0), (E0 + 40.0, N0 + 20.0)), (0.1, 0.4, -0.2))
    pts = _ground(n=60_000)
    pair = make_landslide_pair(pts, slab, seed=0, als=AlsSampling(noise_m=0.0))
    assert 3_000 < len(pair.after) < 15_000
    np.testing.assert_allclose(pair.after_truth, slab(pts[pair.after_index]))
    np.testing.assert_allclose(pair.after, pts[pair.after_index] + pair.after_truth, atol=1e-9)


def test_invalid_geometry_is_refused():
    with pytest.raises(InvalidParameterError, match="scarp_xy"):
        SlabField(((E0, N0), (E0, N0)))
    with pytest.raises(InvalidParameterError, match="width_m"):
        SlumpField((E0, N0), width_m=0.0)
    with pytest.raises(InvalidParameterError, match="base"):
        FaultField(((E0, N0), (E0 + 1, N0)), base=3)
