"""The spline field's block covariance through ``M = Sᵀ S`` against the block-by-block sum
(core/icp_blocks.py, issue #29 item 5)."""

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.sparse.linalg import splu

from slipmap.core.icp_blocks import (
    BlockScores,
    _spline_block_covariance_reference,
    spline_block_covariance,
)


def _case(seed, n_k=60, k=70, groups=(90, 50)):
    rng = np.random.default_rng(seed)
    n3 = 3 * n_k
    b = sp.random(400, n3, density=0.04, random_state=seed, format="csr")
    a = (b.T @ b + sp.identity(n3)).tocsc()
    d = sp.random(120, n3, density=0.03, random_state=seed + 1, format="csr")
    penalty = (d.T @ d).tocsr()
    scores = []
    for g in groups:  # two chunks whose blocks partly coincide (their shares add)
        scores.append(
            BlockScores(
                keys=rng.integers(0, 6, size=(g, 2)),
                knots=rng.integers(0, n_k, size=(g, 16)),
                vals=rng.normal(size=(g, 48)),
                cell_blocks=np.column_stack(
                    [rng.integers(0, k, size=g), rng.integers(0, 6, size=(g, 2))]
                ),
            )
        )
    knots = rng.integers(0, n_k, size=(k, 16))
    cols = (np.arange(3)[None, :, None] * n_k + knots[:, None, :]).reshape(k, 48)
    rows = rng.normal(size=(k, 9, 48))
    kw = dict(rows=rows, cols=cols, factor=splu(a), penalty=penalty, s0sq=2.5e-5, scale=1.7e-5)
    return scores, kw


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_block_covariance_agrees_with_the_block_by_block_sum(seed):
    scores, kw = _case(seed)
    cov, nb = spline_block_covariance(scores, **kw)
    ref, nb_ref = _spline_block_covariance_reference(scores, **kw)
    assert np.array_equal(nb, nb_ref)
    assert cov.shape == (70, 9, 9)
    scale = np.max(np.abs(ref))
    assert np.max(np.abs(cov - ref)) <= 1e-10 * scale
    # a covariance: symmetric, its diagonal positive
    assert np.allclose(cov, np.transpose(cov, (0, 2, 1)), rtol=0, atol=1e-12 * scale)
    assert np.all(np.diagonal(cov, axis1=1, axis2=2) > 0)


def test_without_blocks_it_is_the_penalty_term_alone():
    scores, kw = _case(3)
    empty = [BlockScores(np.zeros((0, 2), int), np.zeros((0, 16), int), np.zeros((0, 48)),
                         np.zeros((0, 3), int))]  # fmt: skip
    cov, nb = spline_block_covariance(empty, **kw)
    ref, _ = _spline_block_covariance_reference(empty, **kw)
    assert np.all(nb == 0)
    assert np.max(np.abs(cov - ref)) <= 1e-10 * np.max(np.abs(ref))
