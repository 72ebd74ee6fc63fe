"""How local the spline's smoothing is, chosen from the data (issue #29, "knot spacing chosen
from the data as the smoothing already is"): the local penalty's kernel width compared by
the restricted likelihood of the weighted fit (``_restricted_score``)."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.sparse.linalg import splu
from scipy.spatial import cKDTree
from test_icp_spline_weights import OPTS, _normals, _scene, _surface

import slipmap.core.icp_spline as icp_spline
from slipmap.core.icp_spline import _restricted_score, fit_spline_field


def test_restricted_score_equals_the_dense_reference():
    """log|A| - log|P| + (vᵀWv + cᵀPc) / s0² with numpy's dense log-determinants."""
    rng = np.random.default_rng(0)
    k = 7
    m = rng.normal(size=(3 * k, 3 * k))
    nmat = m @ m.T + 0.1 * np.eye(3 * k)
    r = rng.normal(size=(3 * k, 3 * k))
    pen = r @ r.T + 0.01 * np.eye(3 * k)
    c = rng.normal(size=(k, 3))
    factor = splu(sp.csc_matrix(nmat + pen))
    got = _restricted_score(factor, sp.csr_matrix(pen), c, 2.0, 1.5, 100)
    cv = c.T.reshape(-1)
    s0sq = 2.0 / (100 - 3 * k)
    ref = (
        np.linalg.slogdet(nmat + pen)[1] - np.linalg.slogdet(pen)[1] + (1.5 + cv @ pen @ cv) / s0sq
    )
    np.testing.assert_allclose(got, ref, rtol=1e-10)


def _lobe(xy, *, sigma_m=1.6, centre=(8.0, 8.0), peak=(0.04, -0.06, -0.03)):
    r2 = np.sum((xy - np.asarray(centre)) ** 2, axis=1)
    return np.exp(-0.5 * r2 / sigma_m**2)[:, None] * np.asarray(peak)


def _lobe_scene(seed, *, cell=4.0, side=16.0, density=60, noise_m=0.002):
    """A narrow lobe (Gaussian of 1.6 m) on the terrain of the weights' tests: every
    after-point ``a`` is put where ``a - u(a)`` lies on the before surface, so the field
    ``u`` is exact at every position."""
    rng = np.random.default_rng(seed)
    n = int(density * (side + 4) ** 2)
    bxy = rng.uniform(-2.0, side + 2.0, (n, 2))
    before = np.c_[bxy, _surface(bxy) + rng.normal(0, noise_m, n)]
    axy = rng.uniform(0.0, side, (n, 2))
    u = _lobe(axy)
    after = np.c_[axy, _surface(axy - u[:, :2]) + u[:, 2] + rng.normal(0, noise_m, n)]
    m = int(side / cell)
    seg = np.minimum((axy[:, 1] // cell).astype(int), m - 1) * m + np.minimum(
        (axy[:, 0] // cell).astype(int), m - 1
    )
    cx, cy = np.meshgrid((np.arange(m) + 0.5) * cell, (np.arange(m) + 0.5) * cell)
    centres = np.c_[cx.ravel(), cy.ravel()]
    return before, after, _lobe(centres), centres, seg


def _fit(before, after, centres, seg, weight, monkeypatch, widths):
    monkeypatch.setattr(icp_spline, "LOCAL_WIDTHS_KNOTS", widths)
    return fit_spline_field(
        after, before=before, tree=cKDTree(before), normals=lambda j: _normals(before[j, :2]),
        initial=lambda xy: np.zeros((len(xy), 3)), report_xy=centres, report_seg=seg,
        spacing_m=2.0, gate_m=0.5, opts=OPTS, cell_weight=weight,
    )  # fmt: skip


def _rms(d, truth):
    return float(np.sqrt(np.mean(np.sum((d - truth) ** 2, axis=1))))


DEFAULT_WIDTHS = icp_spline.LOCAL_WIDTHS_KNOTS


@pytest.mark.parametrize("widths", [(1.0, 2.0), DEFAULT_WIDTHS])
def test_a_narrow_lobe_chooses_the_narrow_kernel_and_is_recovered(monkeypatch, widths):
    """A lobe of 1.6 m (peak 7.8 cm) in 4 m cells, knots 2 m apart: the likelihood prefers
    the narrower kernel (one knot spacing, or the default's half spacing), and its field is
    closer to the truth than the wide kernel's (measured 1.14 and 0.78 against 1.38 cm at
    the cell centres)."""
    before, after, truth, centres, seg = _lobe_scene(4)
    w = np.ones(len(centres))
    fit = _fit(before, after, centres, seg, w, monkeypatch, widths)
    wide = _fit(before, after, centres, seg, w, monkeypatch, (2.0,))
    assert fit.penalty_width_m == 2.0 * min(widths) and wide.penalty_width_m == 4.0
    assert fit.restricted_score < wide.restricted_score - 10.0
    assert _rms(fit.d, truth) < 0.0125, _rms(fit.d, truth)
    assert _rms(fit.d, truth) < _rms(wide.d, truth)


@pytest.mark.parametrize("widths", [(1.0, 2.0), DEFAULT_WIDTHS])
def test_the_choice_does_not_move_a_uniform_shift_with_cell_offsets(monkeypatch, widths):
    """Each cell's points share an offset (the weights' test scene): the field chosen from
    the two kernels is the wide kernel's to a millimetre and near the shift."""
    before, after, shift, centres, seg, var_b = _scene(4, side=16.0)
    n = np.bincount(seg, minlength=len(centres)).astype(float)
    w = 1.0 / (1.0 + n * var_b / (2 * 0.002**2))
    fit = _fit(before, after, centres, seg, w, monkeypatch, widths)
    wide = _fit(before, after, centres, seg, w, monkeypatch, (2.0,))
    assert _rms(fit.d, wide.d) < 0.001, _rms(fit.d, wide.d)
    assert _rms(fit.d, shift[None, :]) < 0.01, _rms(fit.d, shift[None, :])
