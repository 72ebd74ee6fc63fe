"""Seeded windowed-ICP cells also fitted from zero (issue #29, the slump's wrong minima):
a stable cell given a block's motion as its start comes out at zero, the block's cells keep
their seeded fits, and the truncated-cost kernel agrees with its per-cell reference."""

from __future__ import annotations

import numpy as np
import pytest
from test_icp import UTM, cloud, surface

from slipmap.core import icp_starts
from slipmap.core.icp import windowed_icp
from slipmap.core.icp_starts import (
    choose_zero_start,
    truncated_costs,
    truncated_costs_reference,
)

SHIFT = np.array([-2.2, 0.5, 0.3])  # the block's motion: half a terrain wavelength in x
EDGE_M = 12.0  # the block's edge (x, from the grid origin), on a fine cell edge


def block_pair(seed=0, *, length=24.0, width=12.0, density=40):
    """Rough terrain; in epoch 2 the ground beyond x = EDGE_M (a block) moved by SHIFT, the
    rest stable (a discontinuity along the block's edge)."""
    rng = np.random.default_rng(seed)
    before = cloud(rng, -3.0, length + 3.0, density, 0.002, xy_hi=width + 3.0)
    after = cloud(rng, 0.0, length, density, 0.002, xy_hi=width)
    n = int(density * (length + 7.0 - EDGE_M) * (width + 2.0))
    xy = np.c_[rng.uniform(EDGE_M - 4.0, length + 3.0, n), rng.uniform(-1.0, width + 1.0, n)]
    src = np.c_[xy, surface(xy) + rng.normal(0.0, 0.002, n)] + SHIFT
    inside = (src[:, 0] > EDGE_M) & (src[:, 0] < length) & (src[:, 1] > 0) & (src[:, 1] < width)
    after = np.vstack([after[after[:, 0] < EDGE_M], src[inside]])
    return before + UTM, after + UTM


def straddling_start(xy):
    """The start a coarse 8 m cell over [8, 16] m gives when it locks onto the block: the
    block's motion for the stable fine cells over [8, 12] m too."""
    return np.where((xy[:, :1] - UTM[0]) > EDGE_M - 4.0, SHIFT, 0.0)


KW = dict(cell_m=4.0, min_points=200, origin_xy=(UTM[0], UTM[1]), sigma_scaling="formal")


def _errors(res):
    d = np.c_[res.dx, res.dy, res.dz]
    x = res.x - UTM[0]
    stable = np.linalg.norm(d[x < EDGE_M], axis=1)
    block = np.linalg.norm(d[x > EDGE_M] - SHIFT, axis=1)
    return stable, block


def test_a_stable_cell_seeded_with_a_blocks_motion_comes_out_at_zero():
    before, after = block_pair()
    res = windowed_icp(before, after, initial_displacement=straddling_start, **KW)
    stable, block = _errors(res)
    assert stable.size >= 6 and block.size >= 6
    assert stable.max() < 0.01, stable  # measured 1.8 mm (4.6 m without the zero start)
    # the block's cells: the start from zero fails there (2.3 m of motion on 4 m cells) and
    # the seeded fit is kept
    assert block.max() < 0.01, block  # measured 3 mm


def test_without_the_zero_start_the_stable_cell_is_trapped(monkeypatch):
    """The premise of the test above: from the block's motion alone the stable cells next to
    the edge stop in a wrong minimum (metres off)."""
    monkeypatch.setattr(icp_starts, "START_EPS_M", np.inf)
    before, after = block_pair()
    res = windowed_icp(before, after, initial_displacement=straddling_start, **KW)
    stable, block = _errors(res)
    assert stable.max() > 0.5, stable  # measured 4.6 m
    assert block.max() < 0.01


def test_coarse_to_fine_keeps_its_seed_where_zero_fails():
    """The block's motion (2.3 m on 4 m cells) needs the coarse pass; its cells, also fitted
    from zero, keep the coarse seed; the stable cells stay at zero."""
    before, after = block_pair()
    plain = windowed_icp(before, after, **KW)
    _, block_plain = _errors(plain)
    assert block_plain.max() > 0.5  # from zero alone the block is lost
    res = windowed_icp(before, after, coarse_to_fine=1, **KW)
    stable, block = _errors(res)
    assert stable.max() < 0.01 and block.max() < 0.01, (stable, block)


@pytest.mark.parametrize("seed", [0, 1])
def test_truncated_costs_agree_with_the_per_cell_reference(seed):
    rng = np.random.default_rng(seed)
    k = 7
    seg = rng.integers(0, k - 1, 400)  # the last cell has no points
    v_a = rng.normal(0.0, 0.01, seg.size)
    v_b = v_a + rng.normal(0.0, 0.02, seg.size) * (seg % 2)
    v_a[rng.random(seg.size) < 0.1] = np.nan  # points without a target
    v_b[rng.random(seg.size) < 0.2] = np.nan
    v_b[seg == 3] = 0.0  # a zero residual scale in one cell
    v_a[seg == 3] = 0.0
    fast = truncated_costs(v_a, v_b, seg, k)
    slow = truncated_costs_reference(v_a, v_b, seg, k)
    for f, s in zip(fast, slow):
        np.testing.assert_allclose(f, s, rtol=1e-12, atol=1e-15, equal_nan=True)
    assert np.all(np.isnan(fast[0][-1:]))


def test_truncated_costs_known_answers():
    """All residuals within the truncation: ``mean(v²) / c²``; no target: cost 1."""
    v = np.array([0.01, -0.01, 0.01, -0.01])
    c = icp_starts.TUKEY_C * icp_starts.MAD_TO_SIGMA * 0.01
    a, b, se = truncated_costs(v, np.full(4, np.nan), np.zeros(4, np.int64), 1)
    np.testing.assert_allclose(a, [(0.01 / c) ** 2])
    np.testing.assert_allclose(b, [1.0])
    np.testing.assert_allclose(se, [0.0], atol=1e-15)


def test_choose_zero_start():
    seeded = np.array([0.10, 0.10, 0.10, np.nan, 0.05])
    zero = np.array([0.05, 0.099, 0.05, 0.2, 0.04])
    se = np.array([0.01, 0.01, 0.03, np.nan, 0.001])
    ok_s = np.array([True, True, True, False, True])
    ok_z = np.array([True, True, True, True, False])
    np.testing.assert_array_equal(
        choose_zero_start(seeded, zero, se, ok_s, ok_z), [True, False, False, True, False]
    )
