"""Per-plane moments and the adjustment from them (core/planemoments.py) against the points."""

from __future__ import annotations

import numpy as np
import pytest
from test_adjustment import OFFSET, make_problem

from slipmap.core.adjustment import adjust_rigid
from slipmap.core.errors import InvalidParameterError
from slipmap.core.planemoments import PlaneMoments, adjust_rigid_moments

ORIGIN = np.floor(OFFSET)


def _rel(a, b):
    return float(np.max(np.abs(a - b)) / np.max(np.abs(b)))


@pytest.mark.parametrize("model", ["white", "plane", "full"])
def test_moments_give_the_points_adjustment(model):
    b, lb, a, la, _, _ = make_problem(n_planes=12, n_per=300, seed=3)
    rng = np.random.default_rng(1)
    ub, ua = rng.integers(0, 3, lb.size), rng.integers(5, 8, la.size)
    ref = adjust_rigid(b, lb, a, la, sigma_before=0.02, sigma_after=(0.02, 0.02, 0.03),
                       stochastic_model=model, unit_before=ub, unit_after=ua)  # fmt: skip
    # the before epoch in three interleaved parts, as from three tiles, combined
    parts = [np.arange(k, lb.size, 3) for k in range(3)]
    mb = PlaneMoments.from_points(
        b[parts[0]], lb[parts[0]], 12, origin_m=ORIGIN, units=ub[parts[0]]
    )
    for p in parts[1:]:
        mb = mb.combine(PlaneMoments.from_points(b[p], lb[p], 12, origin_m=ORIGIN, units=ub[p]))
    ma = PlaneMoments.from_points(a, la, 12, origin_m=ORIGIN, units=ua)
    got = adjust_rigid_moments(mb, ma, sigma_before=0.02, sigma_after=(0.02, 0.02, 0.03),
                               stochastic_model=model)  # fmt: skip
    assert _rel(got.params, ref.params) < 1e-9
    assert _rel(got.covariance, ref.covariance) < 1e-9
    assert got.n_points == ref.n_points and got.n_planes == ref.n_planes
    assert got.variance_factor == pytest.approx(ref.variance_factor, rel=1e-9)
    assert got.rejected_planes == ref.rejected_planes
    assert got.residuals_before.size == 0 and got.residuals_after.size == 0
    if model != "white":
        assert _rel(
            np.array([c.sigma_m for c in got.variance_components.components]),
            np.array([c.sigma_m for c in ref.variance_components.components]),
        ) < 1e-6  # fmt: skip


def test_concat_and_merge_planes_equal_moments_of_the_union():
    rng = np.random.default_rng(0)
    pts = OFFSET + rng.normal(0, 5, (3000, 3))
    lab = rng.integers(-1, 6, 3000)
    units = rng.integers(0, 4, 3000)
    whole = PlaneMoments.from_points(pts, lab, 6, origin_m=ORIGIN, units=units)
    # planes 0-2 from the first half, 3-5 from the second, then 0+3, 1+4, 2+5 merged
    m1 = PlaneMoments.from_points(pts, np.where(lab < 3, lab, -1), 3, origin_m=ORIGIN, units=units)
    m2 = PlaneMoments.from_points(pts, np.where(lab >= 3, lab - 3, -1), 3, origin_m=ORIGIN,
                                  units=units)  # fmt: skip
    cat = PlaneMoments.concat([m1, m2])
    assert np.allclose(cat.count, whole.count) and np.allclose(cat.mean_m, whole.mean_m)
    assert np.allclose(cat.scatter_m2, whole.scatter_m2)
    merged = cat.merge_planes(np.array([0, 1, 2, 0, 1, 2]), 3)
    ref = PlaneMoments.from_points(pts, np.where(lab >= 0, lab % 3, -1), 3, origin_m=ORIGIN,
                                   units=units)  # fmt: skip
    assert np.allclose(merged.count, ref.count)
    assert np.allclose(merged.mean_m, ref.mean_m, rtol=0, atol=1e-12)
    assert np.allclose(merged.scatter_m2, ref.scatter_m2, rtol=1e-12)
    assert np.allclose(merged.unit_counts, ref.unit_counts)


def test_mismatched_moments_refused():
    b, lb, a, la, _, _ = make_problem(n_planes=6, n_per=100)
    mb = PlaneMoments.from_points(b, lb, 6, origin_m=ORIGIN)
    ma = PlaneMoments.from_points(a, la, 6, origin_m=ORIGIN + 1)
    with pytest.raises(InvalidParameterError):
        adjust_rigid_moments(mb, ma)
    with pytest.raises(InvalidParameterError, match="per-point"):
        adjust_rigid_moments(mb, mb, sigma_before=np.full((10, 3), 0.02))
