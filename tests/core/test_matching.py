"""Plane matching between epochs, on synthetic fault pairs with known truth."""

import numpy as np
import pytest

from slipmap.core.errors import InvalidParameterError
from slipmap.core.matching import match_planes
from slipmap.core.planes import segment_planes
from slipmap.core.synthetic import make_fault_pair

ORIGIN = (500000.0, 4200000.0, 10.0)


@pytest.fixture(scope="module")
def pair():
    fp = make_fault_pair("mls", seed=3, origin=ORIGIN, ground=False, vegetation=False)
    return fp, segment_planes(fp.before.points), segment_planes(fp.after.points)


def _majority(scene, labels, k):
    t = scene.labels[labels == k]
    t = t[t >= 0]
    return int(np.bincount(t).argmax()) if t.size else -1


def test_matches_are_the_same_true_surfaces(pair):
    fp, b, a = pair
    m = match_planes(b, a)
    assert len(m) >= 0.9 * min(len(b), len(a))
    for i, j in zip(m.before, m.after):
        assert _majority(fp.before, b.labels, i) == _majority(fp.after, a.labels, j)
    assert len(set(m.before.tolist())) == len(m) == len(set(m.after.tolist()))  # one-to-one
    assert np.all(np.diff(m.before) > 0)
    assert np.degrees(m.angle_rad).max() < 3 and m.distance_m.max() < 0.5


def test_large_offset_needs_a_larger_distance_threshold():
    fp = make_fault_pair(
        "mls", seed=7, origin=ORIGIN, ground=False, vegetation=False, right_offset_m=(0, 0, 0.8)
    )
    b, a = segment_planes(fp.before.points), segment_planes(fp.after.points)
    small = match_planes(b, a, distance_threshold_m=0.5)
    large = match_planes(b, a, distance_threshold_m=1.0)
    assert len(large) > len(small)


def test_empty_and_bad_parameters(pair):
    _, b, a = pair
    none = segment_planes(np.random.default_rng(0).uniform(0, 10, (2000, 3)))
    assert len(match_planes(b, none)) == 0 and len(match_planes(none, a)) == 0
    with pytest.raises(InvalidParameterError, match="angle_threshold_deg"):
        match_planes(b, a, angle_threshold_deg=0)
    with pytest.raises(InvalidParameterError, match="distance_threshold_m"):
        match_planes(b, a, distance_threshold_m=-1)


def test_fault_pair_truth():
    fp = make_fault_pair(
        "mls", seed=5, n_buildings=4, origin=ORIGIN, right_offset_m=(0.01, -0.02, 0.003)
    )
    assert np.allclose(fp.relative_offset_m, [0.01, -0.02, 0.003])
    # no point is shared between the epochs
    assert not np.isin(fp.after.points[:100, 0], fp.before.points[:, 0]).any()
    # reversing the trace swaps the sides and the offsets, not the motion
    rev = make_fault_pair(
        "mls",
        seed=5,
        n_buildings=4,
        origin=ORIGIN,
        right_offset_m=(0.01, -0.02, 0.003),
        reverse_trace=True,
    )
    assert np.array_equal(rev.side_after, -fp.side_after)
    assert np.allclose(rev.after.points, fp.after.points)
    assert np.allclose(rev.relative_offset_m, -fp.relative_offset_m)
