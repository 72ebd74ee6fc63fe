"""The spline field's symmetric sparse factorisation (``core/icp_spline.py``
:func:`factor_spd`) against SuperLU with its defaults, the slow and obvious reference: the
same solutions, the same log-determinant, on penalised normal matrices built as the field
builds them (a B-spline basis at scattered points, point-to-plane rows, second differences
with a breakline's knot copies)."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.sparse.linalg import splu

from slipmap.core.breaklines import breaklines
from slipmap.core.icp_spline import (
    SplineField,
    factor_spd,
    knot_copies,
    sided_second_differences,
)


def _normal_matrix(seed: int, lines=None, weight=1.0):
    """``N + P + ridge`` (3 n_k, 3 n_k) of a 12 x 9 knot field fitted to 3000 points with
    random normals and robust weights, the penalty one weight per component."""
    rng = np.random.default_rng(seed)
    h, n_x, n_y = 2.5, 12, 9
    copy_index = knot_copies((0.0, 0.0), h, n_x, n_y, lines)
    n_grid = (n_x + 3) * (n_y + 3)
    n_k = n_grid + int(np.count_nonzero(copy_index >= 0))
    field = SplineField((0.0, 0.0), h, n_x, n_y, np.zeros((n_y + 3, n_x + 3, 3)), lines=lines)
    xy = rng.uniform([0.0, 0.0], [h * n_x, h * n_y], size=(3000, 2))
    idx, w = field._basis(xy, copy_index=copy_index)
    b = sp.csr_matrix((w.ravel(), idx.ravel(), np.arange(0, idx.size + 1, 16)), shape=(3000, n_k))
    nrm = rng.normal(size=(3000, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    jac = sp.hstack([b.multiply(nrm[:, [j]]) for j in range(3)]).tocsr()  # point-to-plane rows
    wt = sp.diags(rng.uniform(0.2, 1.0, 3000))
    r2 = sided_second_differences((0.0, 0.0), h, n_x, n_y, lines, copy_index)
    lam = weight * np.array([0.03, 2.0, 0.5])
    pen = sp.block_diag([lam_j * r2 for lam_j in lam])
    scale = float(np.median((jac.T @ wt @ jac).diagonal()))
    return (jac.T @ wt @ jac + pen + 1e-12 * scale * sp.identity(3 * n_k)).tocsc()


@pytest.mark.parametrize(
    "seed, with_line, weight", [(0, False, 1.0), (1, True, 1.0), (2, False, 1e-4)]
)
def test_symmetric_factor_equals_the_default_lu(seed, with_line, weight):
    lines = breaklines([[(3.0, -1.0), (27.0, 23.0)]]) if with_line else None
    a = _normal_matrix(seed, lines, weight)
    rhs = np.random.default_rng(seed + 10).normal(size=(a.shape[0], 5))
    ref, fast = splu(a), factor_spd(a)
    x_ref, x_fast = ref.solve(rhs), fast.solve(rhs)
    np.testing.assert_allclose(x_fast, x_ref, rtol=0, atol=1e-9 * np.abs(x_ref).max())
    np.testing.assert_allclose(a @ x_fast, rhs, rtol=0, atol=1e-8 * np.abs(rhs).max())
    # log|A| from U's diagonal (L has a unit diagonal in both), as _restricted_score takes it
    ld_ref = np.sum(np.log(np.abs(ref.U.diagonal())))
    ld_fast = np.sum(np.log(np.abs(fast.U.diagonal())))
    assert abs(ld_fast - ld_ref) < 1e-8 * abs(ld_ref)
    # and less fill: the reason for it
    assert fast.L.nnz + fast.U.nnz < ref.L.nnz + ref.U.nnz
