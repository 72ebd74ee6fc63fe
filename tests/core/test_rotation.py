"""core/rotation: the one SO(3) implementation (scipy's Rotation) against Rodrigues' formula
written out, and the left Jacobian against finite differences."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from slipmap.core.rotation import left_jacobian, rotation_matrix, rotation_vector, skew

vectors = st.lists(st.floats(-1.0, 1.0), min_size=3, max_size=3).map(np.array)


def _rodrigues(r):
    th = float(np.linalg.norm(r))
    if th == 0.0:
        return np.eye(3)
    k = skew(r / th)
    return np.eye(3) + math.sin(th) * k + (1.0 - math.cos(th)) * (k @ k)


@settings(max_examples=60, deadline=None)
@given(vectors)
def test_matrix_is_rodrigues_and_vector_inverts_it(r):
    R = rotation_matrix(r)
    np.testing.assert_allclose(R, _rodrigues(r), atol=1e-14)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-14)
    np.testing.assert_allclose(rotation_vector(R), r, atol=1e-12)


def test_skew_is_the_cross_product_and_batched():
    rng = np.random.default_rng(3)
    v, u = rng.normal(size=(5, 3)), rng.normal(size=(5, 3))
    np.testing.assert_allclose(np.einsum("kij,kj->ki", skew(v), u), np.cross(v, u), atol=1e-15)


def test_left_jacobian_matches_finite_differences():
    r = np.array([0.3, -0.2, 0.5])
    J = left_jacobian(r)
    h = 1e-7
    for i in range(3):
        dr = np.zeros(3)
        dr[i] = h
        # exp([r + dr]x) exp(-[r]x) = exp([J dr]x)
        d = rotation_vector(rotation_matrix(r + dr) @ rotation_matrix(r).T) / h
        np.testing.assert_allclose(d, J[:, i], atol=1e-6)
    np.testing.assert_allclose(left_jacobian(np.zeros(3)), np.eye(3), atol=1e-15)
