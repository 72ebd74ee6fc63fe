"""Breakline detection around a block that moves rigidly (issue #29): known answers.

A rotational slump's block rotates as a whole, so its cells differ from one another by the
rotation (3° over 5 m cells: 0.26 m), about as much as across its outline; the cells' own
gradients (what rigid ICP cells estimate) explain the first and not the second.
"""

import numpy as np

from slipmap.core.breaklines import (
    _step_edges_reference,
    breaklines,
    detect_breaklines,
    distance_m,
    step_edges,
)
from slipmap.core.rotation import rotation_matrix
from slipmap.core.synthetic import LobeField

CELL = 5.0
N = 12  # cells a side


def _grid():
    x = (np.arange(N) + 0.5) * CELL
    y = 60.0 - (np.arange(N) + 0.5) * CELL  # rows run south, as the ICP cells'
    xx, yy = np.meshgrid(x, y)
    zz = 0.36 * yy  # a 20° slope facing south
    return x, y, np.stack([xx, yy, zz], axis=-1)


def _slump(rng, *, angle_deg=3.0):
    """A block (rows 4-7: y 20-40 m, every column) rotating ``angle_deg`` about an
    east-west axis 8 m above its middle; the ground north and south of it stable. The
    cells' motions at their centres, their gradients ``R - I`` (as a rigid cell reports
    them), with 3 mm and 1 mrad of noise."""
    x, y, p = _grid()
    inside = (p[..., 1] > 20.0) & (p[..., 1] < 40.0)
    axis = np.array([0.0, 30.0, 0.36 * 30.0 + 8.0])
    r = rotation_matrix(np.array([np.radians(angle_deg), 0.0, 0.0]))
    g_block = r - np.eye(3)
    d = np.where(inside[..., None], (p - axis) @ g_block.T, 0.0)
    g = np.where(inside[..., None, None], g_block, 0.0)
    d = d + rng.normal(scale=0.003, size=d.shape)
    g = g + rng.normal(scale=0.001, size=g.shape)
    outline = [np.array([[0.0, 20.0], [60.0, 20.0]]), np.array([[0.0, 40.0], [60.0, 40.0]])]
    return x, y, p, d, g, outline


def _lobe(radius, peak, *, strain_in_gradient: bool, cell=4.0, n=10):
    """A smooth lobe (:class:`~slipmap.core.synthetic.LobeField`, the ellipse
    ``radius x 0.8 radius``, peak ``(0, -peak, -0.4 peak)`` m) on ``cell`` cells, 2 mm of
    noise, and its exact gradient: the full one, or only its rotation (antisymmetric part),
    which is all a rigid cell reports (the strain then stays in the differences)."""
    lobe = LobeField(centre_xy=(20.0, 20.0), radius_x_m=radius, radius_y_m=0.8 * radius,
                     max_d_m=(0.0, -peak, -0.4 * peak))  # fmt: skip
    x = (np.arange(n) + 0.5) * cell
    y = n * cell - (np.arange(n) + 0.5) * cell
    gx, gy = np.meshgrid(x, y)
    xy = np.c_[gx.ravel(), gy.ravel()]
    d = lobe(xy).reshape(n, n, 3) + np.random.default_rng(0).normal(0, 0.002, (n, n, 3))
    g = np.concatenate([lobe.gradient(xy), np.zeros((n * n, 3, 1))], axis=2).reshape(n, n, 3, 3)
    if not strain_in_gradient:
        g = 0.5 * (g - np.swapaxes(g, -1, -2))
    return x, y, d, g


def test_the_step_test_alone_misses_a_rotating_block():
    x, y, p, d, g, _ = _slump(np.random.default_rng(0))
    found = detect_breaklines(d, x=x, y=y, sigma=np.full(d.shape[:2], 0.004))
    assert found is None  # the premise: the block's own differences hide its edges


def test_a_rotating_block_is_outlined_within_one_cell():
    x, y, p, d, g, outline = _slump(np.random.default_rng(1))
    found = detect_breaklines(
        d, x=x, y=y, sigma=np.full(d.shape[:2], 0.004), gradient=g, z=p[..., 2],
        sigma_gradient=np.full(d.shape[:2], 0.002),
    )  # fmt: skip
    assert found is not None and len(found) == 2
    truth = breaklines(outline)
    for part in found.parts:
        t = np.linspace(0.0, 1.0, 50)[:, None]
        pts = np.concatenate([a + t * (b - a) for a, b in zip(part[:-1], part[1:])])
        pts = pts[(pts[:, 0] >= 0) & (pts[:, 0] <= 60)]  # over the data
        assert distance_m(pts, truth).max() <= CELL
    # each true edge has a detected line along it
    mids = np.array([[30.0, 20.0], [30.0, 40.0]])
    assert distance_m(mids, found).max() <= CELL


def test_smooth_lobes_are_not_cut_with_or_without_their_strain():
    # the lobes the step test leaves alone (tests/core/test_icp_breaklines.py: radii 1.5 and
    # 4-5 cells; lobes 2-3 cells in radius rise like a straddled step on the grid, with or
    # without gradients, and only the points tell them apart)
    for radius, peak in ((6.0, 0.5), (16.0, 0.6), (16.0, 1.0), (20.0, 0.6)):
        for strain in (True, False):
            x, y, d, g = _lobe(radius, peak, strain_in_gradient=strain)
            found = detect_breaklines(
                d, x=x, y=y, sigma=np.full(d.shape[:2], 0.004), gradient=g,
                sigma_gradient=np.full(d.shape[:2], 0.002),
            )  # fmt: skip
            assert found is None, (radius, peak, strain)


def test_a_translating_slab_is_still_found_with_gradients():
    x, y, p = _grid()
    d = np.where((p[..., 0] > 32.0)[..., None], np.array([0.1, -0.4, -0.1]), 0.0)
    g = np.zeros(d.shape + (3,))
    found = detect_breaklines(
        d, x=x, y=y, sigma=np.full(d.shape[:2], 0.004), gradient=g, z=p[..., 2]
    )
    assert found is not None
    assert distance_m(np.array([[32.5, 30.0]]), found)[0] <= CELL


def test_step_edges_agree_with_the_slow_reference():
    rng = np.random.default_rng(7)
    for case in range(4):
        x, y, p, d, g, _ = _slump(rng, angle_deg=2.0 + case)
        if case % 2:
            x, y, d, g = _lobe(10.0 + case, 0.6, strain_in_gradient=False, cell=CELL, n=N)
            d = d + rng.normal(scale=0.01, size=d.shape)
        valid = rng.random(d.shape[:2]) > 0.15  # missing cells: the pair test over a gap
        sig = rng.uniform(0.002, 0.01, d.shape[:2])
        sg = rng.uniform(0.0005, 0.003, d.shape[:2])
        kw = dict(valid=valid, sigma=sig, spacing_m=(CELL, -CELL), z=p[..., 2])
        for grad in (None, g):
            fast = step_edges(d, gradient=grad, sigma_gradient=sg, **kw)
            slow = _step_edges_reference(d, gradient=grad, sigma_gradient=sg, **kw)
            assert np.array_equal(fast[0], slow[0]) and np.array_equal(fast[1], slow[1])
