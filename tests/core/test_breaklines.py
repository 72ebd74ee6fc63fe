"""Breakline geometry: crossings, sides and distances with known answers."""

import numpy as np
import pytest

from slipmap.core.breaklines import breaklines, crossings, distance_m, from_sequence, same_side
from slipmap.core.errors import InvalidParameterError


def _slow_crossings(p, q, parts):
    """Obvious reference: every pair against every segment, parametric intersection."""
    out = []
    for a, b in zip(p, q):
        n = 0
        for v in parts:
            for c, d in zip(v[:-1], v[1:]):
                r, s = b - a, d - c
                den = r[0] * s[1] - r[1] * s[0]
                if den == 0:
                    continue
                t = ((c - a)[0] * s[1] - (c - a)[1] * s[0]) / den
                u = ((c - a)[0] * r[1] - (c - a)[1] * r[0]) / den
                n += int(0 <= t <= 1 and 0 < u < 1)
        out.append(n)
    return np.array(out)


def test_a_straight_scarp_splits_the_plane():
    bl = breaklines([np.array([[0.0, -10], [0, 10]])])
    p = np.array([[-1.0, 0], [-1, 0], [1, 5], [-3, 20]])
    q = np.array([[1.0, 0], [-2, 3], [2, -5], [3, 20]])
    assert crossings(p, q, bl).tolist() == [1, 0, 0, 0]  # the last passes beyond the tip
    assert same_side(p, q, bl).tolist() == [False, True, True, True]


def test_agrees_with_the_slow_reference_on_random_polylines():
    rng = np.random.default_rng(3)
    parts = [np.cumsum(rng.normal(size=(6, 2)) * 3, axis=0) for _ in range(3)]
    bl = breaklines(parts)
    p = rng.uniform(-10, 10, (500, 2))
    q = rng.uniform(-10, 10, (500, 2))
    np.testing.assert_array_equal(crossings(p, q, bl, chunk=37), _slow_crossings(p, q, parts))


def test_distance_to_a_bent_line():
    bl = breaklines([np.array([[0.0, 0], [10, 0], [10, 10]])])
    d = distance_m(np.array([[5.0, 3], [12, 5], [-3, -4], [10, 0]]), bl)
    np.testing.assert_allclose(d, [3, 2, 5, 0])


def test_bad_lines_are_refused_and_none_is_none():
    with pytest.raises(InvalidParameterError):
        breaklines([np.array([[1.0, 1], [1, 1]])])
    with pytest.raises(InvalidParameterError):
        breaklines([np.array([[np.nan, 1], [1, 2]])])
    assert from_sequence(None) is None and from_sequence([]) is None
