"""The spline field fitted over chunks of points (issue #29, the field on tiles): the robust
weights found from every chunk's residuals equal those of one array, and a fit over three
chunks (each point in one) equals the one-chunk fit in every value it reports."""

from __future__ import annotations

import numpy as np
import pytest
from test_icp import cloud

from slipmap.core.icp import _NormalCache, _options
from slipmap.core.icp_options import _weights
from slipmap.core.icp_spline import (
    SplineChunk,
    Weighting,
    fit_spline_chunks,
    fit_spline_field,
    knot_frame,
)
from slipmap.core.synthetic import LobeField


@pytest.mark.parametrize("robust", ["tukey", "huber", None])
@pytest.mark.parametrize("trim", [0.0, 0.1])
def test_weights_from_chunks_equal_those_of_one_array(robust, trim):
    rng = np.random.default_rng(1)
    v = np.r_[rng.normal(0.0, 0.004, 3000), rng.normal(0.0, 0.2, 60)]
    rng.shuffle(v)
    opts = _options(robust=robust, trim_fraction=trim)
    keep, w, dpsi = _weights(v, opts)
    parts = np.split(v, [700, 2100])
    wgt = Weighting.of(np.concatenate([np.abs(p) for p in parts[::-1]]), opts)
    got = [wgt.apply(p) for p in parts]
    assert np.array_equal(np.concatenate([g[0] for g in got]), keep)
    np.testing.assert_array_equal(np.concatenate([g[1] for g in got]), w)
    np.testing.assert_array_equal(np.concatenate([g[2] for g in got]), dpsi)
    assert wgt.median_abs_m == np.median(np.abs(v))


#: the lobe of :func:`_lobe_scene`
LOBE = LobeField(centre_xy=(11.0, 12.0), radius_x_m=6.0, radius_y_m=6.0, max_d_m=(0.1, -0.3, -0.1))


def _lobe_scene(rng):
    """A lobe (0.3 m) on 24 m of rough ground, cells of 4 m: ``(before, after, tree of
    before, cell centres (36, 2), cell of each after-point)``."""
    from scipy.spatial import cKDTree

    before = cloud(rng, -3.0, 27.0, 25, 0.003)
    after = cloud(rng, 0.0, 24.0, 25, 0.003)
    after = after + LOBE(after[:, :2])
    g = np.arange(2.0, 24.0, 4.0)
    rxy = np.array([(x, y) for y in g for x in g])
    seg = (np.floor(after[:, 1] / 4.0) * 6 + np.floor(after[:, 0] / 4.0)).astype(np.int64)
    return before, after, cKDTree(before), rxy, seg


def test_a_fit_over_three_chunks_equals_the_one_chunk_fit():
    """A lobe (0.3 m) on 24 m of rough ground, cells of 4 m: the after-points split into
    three uneven chunks by x; the driver adds their shares. Same field, covariances, per-cell
    residuals and counts, sigma0 and iterations (up to the sums' rounding)."""
    before, after, tree, rxy, seg = _lobe_scene(np.random.default_rng(7))
    pairs = np.array([(i, i + 1) for i in range(len(rxy) - 1)])
    kw = dict(
        initial=lambda xy: np.zeros((len(xy), 3)), report_xy=rxy, report_pairs=pairs,
        gate_m=1.0, opts=_options(),
    )  # fmt: skip
    one = fit_spline_field(
        after, before=before, tree=tree, normals=_NormalCache(before, tree, 12),
        report_seg=seg, spacing_m=4.0, block_m=0.5, **kw,
    )  # fmt: skip
    frame = knot_frame(after[:, :2].min(axis=0), after[:, :2].max(axis=0), rxy, 4.0)
    normals = _NormalCache(before, tree, 12)
    cut = np.digitize(after[:, 0], [5.3, 17.9])
    chunks = [
        SplineChunk(
            after[cut == i],
            frame=frame,
            before=before,
            tree=tree,
            normals=normals,
            gate_m=1.0,
            seg=seg[cut == i],
        )  # fmt: skip
        for i in (2, 0, 1)
    ]

    def run(stage, *args):
        return [getattr(c, stage)(*args) for c in chunks]

    three = fit_spline_chunks(run, frame=frame, block_m=0.5, **kw)
    assert three.iterations == one.iterations and three.converged == one.converged
    assert np.array_equal(three.n, one.n) and one.n.min() > 200
    assert three.n_coefficients == one.n_coefficients
    for key in ("d", "gradient", "rmse"):
        np.testing.assert_allclose(getattr(three, key), getattr(one, key), rtol=0, atol=1e-9)
    np.testing.assert_allclose(three.cov, one.cov, rtol=1e-7, atol=1e-16)
    np.testing.assert_allclose(three.pair_cov, one.pair_cov, rtol=1e-7, atol=1e-16)
    assert three.sigma0_m == pytest.approx(one.sigma0_m, rel=1e-9)
    # the block covariance: blocks cut by the chunks' edges (x 5.3, 17.9) add up
    assert np.array_equal(three.n_blocks, one.n_blocks) and one.n_blocks.min() >= 40
    np.testing.assert_allclose(three.cov_blocks, one.cov_blocks, rtol=1e-7, atol=1e-16)
    # independent noise: the block variances are the formal ones (to the estimate's noise)
    ratio = np.diagonal(one.cov_blocks, axis1=1, axis2=2) / np.diagonal(one.cov, axis1=1, axis2=2)
    assert 0.6 < np.median(ratio[:, :3]) < 1.6
    # and the field is the lobe's (the fit works, not only agrees with itself)
    err = np.linalg.norm(one.d - LOBE(rxy), axis=1)
    assert np.sqrt(np.mean(err**2)) < 0.03


def test_block_scores_equal_the_per_point_sums():
    """Points grouped by their full 16-knot row (rows that share the first knot but differ
    after it, as with breakline copies, stay apart): the scattered block scores equal the
    per-point sums into (block, coefficient)."""
    import scipy.sparse as sp

    from slipmap.core.icp_blocks import spline_block_scores

    rng = np.random.default_rng(3)
    n, n_k, bm = 400, 40, 0.7
    xy = rng.uniform(-3.0, 5.0, (n, 2))
    base = rng.integers(0, 20, n)
    idx16 = base[:, None] + np.arange(16)[None, :]
    copy = rng.random(n) < 0.3  # a copy replaces a later knot: same first knot, other row
    idx16[copy, 5] = 36 + base[copy] % 4
    w16 = rng.random((n, 16))
    psi = np.where(rng.random(n) < 0.1, 0.0, rng.normal(0.0, 0.01, n))
    nrm = rng.normal(size=(n, 3))
    seg = rng.integers(-1, 5, n)
    parts = np.split(np.arange(n), [130, 260])
    scores = [
        spline_block_scores(
            xy=xy[i],
            psi=psi[i],
            nrm=nrm[i],
            idx16=idx16[i],
            w16=w16[i],
            block_m=bm,
            origin_xy=(-3.2, -2.9),
            seg=seg[i],
        )  # fmt: skip
        for i in parts
    ]
    blocks = {}
    ref = {}
    for p in range(n):
        if psi[p] == 0:
            continue
        key = (int(np.floor((xy[p, 0] + 3.2) / bm)), int(np.floor((xy[p, 1] + 2.9) / bm)))
        b = blocks.setdefault(key, len(blocks))
        for c in range(3):
            for j in range(16):
                col = c * n_k + idx16[p, j]
                ref[b, col] = ref.get((b, col), 0.0) + psi[p] * nrm[p, c] * w16[p, j]
    dense_ref = np.zeros((len(blocks), 3 * n_k))
    for (b, col), val in ref.items():
        dense_ref[b, col] = val
    got = np.zeros_like(dense_ref)
    for sc in scores:
        for key, kn, vals in zip(sc.keys, sc.knots, sc.vals):
            b = blocks[(int(key[0]), int(key[1]))]
            for c in range(3):
                np.add.at(got[b], c * n_k + kn, vals[16 * c : 16 * c + 16])
    np.testing.assert_allclose(got, dense_ref, rtol=1e-12, atol=1e-15)
    assert sp.csr_matrix(got).nnz == sp.csr_matrix(dense_ref).nnz
    # the rows given as numbers (as a chunk has them) group the same
    rid = np.unique(idx16, axis=0, return_inverse=True)[1].reshape(-1)
    again = spline_block_scores(xy=xy, psi=psi, nrm=nrm, idx16=idx16, w16=w16, block_m=bm,
                                origin_xy=(-3.2, -2.9), group=rid * 7 + 3)  # fmt: skip
    whole = spline_block_scores(xy=xy, psi=psi, nrm=nrm, idx16=idx16, w16=w16, block_m=bm,
                                origin_xy=(-3.2, -2.9))  # fmt: skip
    for key in ("keys", "knots", "vals"):
        np.testing.assert_array_equal(getattr(again, key), getattr(whole, key))
    cb = np.unique(np.concatenate([sc.cell_blocks for sc in scores]), axis=0)
    want = {(int(seg[p]), *(int(np.floor((xy[p, k] - o) / bm)) for k, o in ((0, -3.2), (1, -2.9))))
            for p in range(n) if psi[p] != 0 and seg[p] >= 0}  # fmt: skip
    assert {tuple(r) for r in cb.tolist()} == want


@pytest.mark.parametrize("robust", ["tukey", None])
def test_held_pairs_give_the_normal_equations_of_those_pairs_at_any_field(robust):
    """:meth:`SplineChunk.held_normal_equations`: at the coefficients whose pairs are
    held it equals the live normal equations; at other coefficients its normal and Gram
    matrices stay those of the held pairs and its right-hand side and ``wvv`` are the
    obvious sums over the held pairs' residuals (a loop over points, written out here),
    while the live pairs of the moved field differ."""
    from slipmap.core.icp import _NormalCache

    rng = np.random.default_rng(3)
    before, after, tree, rxy, seg = _lobe_scene(rng)
    frame = knot_frame(after[:, :2].min(axis=0), after[:, :2].max(axis=0), rxy, 4.0)
    chunk = SplineChunk(after, frame=frame, before=before, tree=tree,
                        normals=_NormalCache(before, tree, 12), gate_m=1.0, seg=seg)  # fmt: skip
    n_k = chunk.n_k
    c_held = rng.normal(0.0, 0.05, (n_k, 3))
    c_new = c_held + rng.normal(0.0, 0.05, (n_k, 3))
    opts = _options(robust=robust)
    wgt = Weighting.of(chunk.residuals(c_held), opts)
    cell_w = rng.uniform(0.2, 1.0, len(rxy))
    live = chunk.normal_equations(c_held, wgt, cell_w)
    held_here = chunk.normal_equations(c_held, wgt, cell_w, c_held)
    np.testing.assert_allclose(held_here.nmat.toarray(), live.nmat.toarray(), rtol=1e-12,
                               atol=1e-12 * abs(live.nmat).max())  # fmt: skip
    np.testing.assert_allclose(held_here.rhs, live.rhs, rtol=1e-10, atol=1e-14)
    assert held_here.wvv == pytest.approx(live.wvv, rel=1e-12)
    assert held_here.wvv_weighted == pytest.approx(live.wvv_weighted, rel=1e-12)

    kept = chunk._held
    held = chunk.normal_equations(c_new, wgt, cell_w, c_held)
    assert chunk._held is kept  # the held pairs' matrices are not made again
    np.testing.assert_array_equal(held.nmat.toarray(), held_here.nmat.toarray())
    np.testing.assert_array_equal(held.gram.toarray(), held_here.gram.toarray())
    # the reference: the pairs, normals and weights of c_held, the residuals at c_new
    ok, nrm, v0, j = chunk.pairs(c_held)
    keep, wv, _ = wgt.apply(v0[ok])
    w_all = np.zeros(len(v0))
    w_all[ok] = np.where(keep, wv, 0.0)
    dw = w_all * chunk.data_weight(cell_w)
    basis = chunk._basis_pts.toarray()
    moved = chunk.a - basis @ c_new
    rhs = np.zeros(3 * n_k)
    wvv = 0.0
    for p in np.flatnonzero(ok):
        v = float(nrm[p] @ (moved[p] - before[j[p]]))
        wvv += w_all[p] * v * v
        for comp in range(3):
            rhs[comp * n_k : (comp + 1) * n_k] += dw[p] * v * nrm[p, comp] * basis[p]
    np.testing.assert_allclose(held.rhs, rhs, rtol=1e-9, atol=1e-12 * np.abs(rhs).max())
    assert held.wvv == pytest.approx(wvv, rel=1e-9)
    # a chunk made anew (a tile block's cache dropped) gives the same
    fresh = SplineChunk(after, frame=frame, before=before, tree=tree,
                        normals=_NormalCache(before, tree, 12), gate_m=1.0, seg=seg)  # fmt: skip
    again = fresh.normal_equations(c_new, wgt, cell_w, c_held)
    np.testing.assert_array_equal(again.rhs, held.rhs)
    # the live pairs of the moved field are not the held ones
    assert not np.array_equal(chunk.pairs(c_new)[3], j)
