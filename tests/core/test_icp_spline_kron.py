"""The spline field's fast normal equations (issue #29 item 5): the Kronecker kernel
``_assemble_kron`` (6 x 100 distinct sums per knot interval, a CSR pattern fixed per chunk)
against the plain per-interval (48, 48) products of ``_assemble``, with and without
breaklines (knots replaced by their far-side copies)."""

from __future__ import annotations

import numpy as np
import pytest

from slipmap.core.breaklines import breaklines
from slipmap.core.icp_spline import (
    NormalPattern,
    SplineField,
    _assemble,
    _assemble_kron,
    knot_copies,
)


def _case(seed: int, lines=None, n_pts: int = 3000):
    rng = np.random.default_rng(seed)
    f = SplineField((100.0, -50.0), 2.5, 6, 5, np.zeros((8, 9, 3)), lines=lines)
    copy_index = None if lines is None else knot_copies(f.origin_xy, 2.5, 6, 5, lines)
    n_k = 8 * 9 + (0 if copy_index is None else int(np.count_nonzero(copy_index >= 0)))
    xy = np.c_[rng.uniform(100.0, 115.0, n_pts), rng.uniform(-50.0, -37.5, n_pts)]
    idx, w = f._basis(xy, copy_index=copy_index)
    _, group = np.unique(idx, axis=0, return_inverse=True)
    order = np.argsort(group.reshape(-1), kind="stable")
    idx, w = idx[order], w[order]
    _, starts = np.unique(group.reshape(-1)[order], return_index=True)
    bounds = np.append(starts, n_pts)
    nrm = rng.normal(size=(n_pts, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    v = rng.normal(0.0, 0.01, n_pts)
    wt = rng.uniform(0.0, 2.0, n_pts)
    ok = rng.random(n_pts) > 0.1
    wt[~ok] = 0.0
    return bounds, idx, w, nrm, v, wt, n_k, ok


def _lines():
    return breaklines([np.array([[103.3, -52.0], [112.1, -36.0]])])


@pytest.mark.parametrize("with_lines, block", [(False, 1024), (True, 1024), (True, 7)])
def test_kronecker_normal_equations_equal_the_plain_interval_products(
    with_lines, block, monkeypatch
):
    import slipmap.core.icp_spline as spline

    monkeypatch.setattr(spline, "_KRON_BLOCK", block)  # 7: many blocks per interval
    bounds, idx, w, nrm, v, wt, n_k, ok = _case(3, _lines() if with_lines else None)
    n_ref, b_ref, g_ref = _assemble(None, bounds, idx, w, nrm, v, wt, n_k, ok=ok)
    w4 = w.reshape(-1, 4, 4)
    pattern = NormalPattern.of(bounds, idx, n_k)
    for _ in range(2):  # the pattern reused, as between iterations
        n_new, b_new, g_new = _assemble_kron(
            bounds, idx, w, w4.sum(axis=1), w4.sum(axis=2), nrm, v, wt, n_k, ok, pattern
        )
        for ref, new in ((n_ref, n_new), (g_ref, g_new)):
            ref, new = ref.toarray(), new.toarray()
            assert np.abs(new - ref).max() <= 1e-12 * np.abs(ref).max()
        assert np.abs(b_new - b_ref).max() <= 1e-12 * np.abs(b_ref).max()
    # the same sparsity pattern (the sparse LU's ordering depends on it)
    assert n_new.nnz == n_ref.nnz and g_new.nnz == g_ref.nnz
    np.testing.assert_array_equal(n_new.indptr, n_ref.indptr)
    np.testing.assert_array_equal(n_new.indices, n_ref.indices)


def test_row_groups_equal_numpys_unique_rows():
    from slipmap.core.icp_spline import _row_groups

    rng = np.random.default_rng(5)
    idx = rng.integers(0, 4, size=(5000, 16)) * 10**9 + rng.integers(0, 3, size=(1, 16))
    idx[::7] = idx[3]  # repeated rows
    ref = np.unique(idx, axis=0, return_inverse=True)[1].reshape(-1)
    np.testing.assert_array_equal(_row_groups(idx), ref)
    # few distinct values: many equal rows
    small = rng.integers(0, 2, size=(3000, 16))
    np.testing.assert_array_equal(
        _row_groups(small), np.unique(small, axis=0, return_inverse=True)[1].reshape(-1)
    )
    assert _row_groups(np.zeros((0, 16), dtype=np.int64)).shape == (0,)
