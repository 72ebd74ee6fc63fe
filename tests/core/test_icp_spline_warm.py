"""A spline refit that starts where an earlier fit ended (issue #29 item 5): the default
windowed ICP fits the field once with candidate breaklines and again with the lines the
points confirm (or none); the second fit starts from the first one's field and estimated
penalty weights (``initial=first.field``, ``smoothing_start=first.smoothing_estimate``).
It reaches the same field as a fit from zero, in a few iterations, and recovers the known
lobe as well."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree
from test_icp import cloud

from slipmap.core import icp_spline
from slipmap.core.icp import _NormalCache, _options
from slipmap.core.icp_spline import fit_spline_field
from slipmap.core.synthetic import LobeField

LOBE = LobeField(centre_xy=(11.0, 12.0), radius_x_m=6.0, radius_y_m=6.0, max_d_m=(0.1, -0.3, -0.1))


def _scene(seed):
    rng = np.random.default_rng(seed)
    before = cloud(rng, -3.0, 27.0, 25, 0.003)
    after = cloud(rng, 0.0, 24.0, 25, 0.003)
    after = after + LOBE(after[:, :2])
    g = np.arange(2.0, 24.0, 4.0)
    rxy = np.array([(x, y) for y in g for x in g])
    return before, after, rxy


def _fit(before, after, rxy, **kw):
    tree = cKDTree(before)
    kw.setdefault("initial", lambda xy: np.zeros((len(xy), 3)))
    return fit_spline_field(
        after, before=before, tree=tree, normals=_NormalCache(before, tree, 12), report_xy=rxy,
        spacing_m=4.0, gate_m=1.0, opts=_options(), **kw,
    )  # fmt: skip


def _truth(rxy, d):
    """The lobe's motion of the material now at ``rxy``: ``p + LOBE(p) = rxy`` in x, y,
    solved by fixed-point iteration from the fitted motion ``d``."""
    p = rxy - d[:, :2]
    for _ in range(50):
        p = rxy - LOBE(p)[:, :2]
    return LOBE(p)


@pytest.mark.parametrize("seed", [3, 11])
def test_a_refit_from_the_first_fit_reaches_the_same_field_in_few_iterations(seed):
    before, after, rxy = _scene(seed)
    cold = _fit(before, after, rxy)
    est = cold.smoothing_estimate
    # (xx, yy, z) weights, and with the principal horizontal model the cross weight xy
    want = (4,) if icp_spline.HORIZONTAL_MODEL == "principal" else (3,)
    assert est is not None and est.shape == want
    assert np.all(est[:3] > 0)
    if est.size == 4:  # the horizontal 2 x 2 weight is positive definite
        assert est[0] * est[1] > est[3] ** 2
    warm = _fit(before, after, rxy, initial=cold.field, smoothing_start=cold.smoothing_estimate)
    inner = np.linalg.norm(rxy - np.array(LOBE.centre_xy), axis=1) < 8.0
    # the known lobe, both fits (cells inside the lobe and on its rim; knots 4 m apart for a
    # lobe 12 m across: measured 1.43-1.46 cm 3-D RMS, from zero and warm alike)
    for fit in (cold, warm):
        err = fit.d - _truth(rxy, fit.d)
        assert np.sqrt(np.mean(np.sum(err[inner] ** 2, axis=1))) < 0.02
    # the same fixed point: within a small share of the fit's own noise (measured 0.045 σ,
    # 0.2 mm), after 1 iteration against 12-13 from zero
    sig = np.sqrt(np.diagonal(cold.cov[:, :3, :3], axis1=1, axis2=2))
    assert np.all(np.abs(warm.d - cold.d)[inner] < 0.25 * sig[inner] + 2e-4)
    assert warm.iterations <= max(3, cold.iterations // 3), (warm.iterations, cold.iterations)


def test_smoothing_start_is_ignored_when_the_smoothing_is_given():
    before, after, rxy = _scene(5)
    given = _fit(before, after, rxy, smoothing=0.05)
    with_start = _fit(before, after, rxy, smoothing=0.05, smoothing_start=np.full(3, 100.0))
    np.testing.assert_array_equal(given.d, with_start.d)
    assert given.smoothing_estimate is None
