"""Weakly determined components of the slip (issue #30 item 2): known answers."""

import math

import numpy as np
import pytest

from slipmap.core.determination import SHARE, SIGMA_RATIO, weak_components
from slipmap.core.displacement import strike_axes

AXES = strike_axes(0.0)  # along the strike = north (y), across = east (x), up


def _normals(tilts_deg, azimuths_deg):
    t, a = np.radians(tilts_deg), np.radians(azimuths_deg)
    return np.column_stack([np.sin(t) * np.sin(a), np.sin(t) * np.cos(a), np.cos(t)])


def test_near_horizontal_planes_leave_the_horizontal_undetermined():
    # ground and roofs tilted 3° towards north and east: each horizontal axis gets
    # sin²(3°) / 2 of the weight on average (0.14 %); horizontal σ 30x the vertical
    n = _normals([0, 3, 3, 3, 3], [0, 0, 90, 180, 270])
    cov = np.diag([0.3, 0.25, 0.01]) ** 2
    weak = weak_components([cov, np.diag([1e-3] * 3) ** 2], [n, n], AXES)
    assert [(w.component, w.side) for w in weak] == [
        ("fault_parallel", "left"),
        ("fault_normal", "left"),
    ]
    share = 2 * math.sin(math.radians(3)) ** 2 / 5
    assert weak[0].share == pytest.approx(share, rel=1e-12)
    assert weak[0].sigma_m == pytest.approx(0.25) and weak[1].sigma_m == pytest.approx(0.3)
    assert weak[0].best_sigma_m == pytest.approx(0.01) and weak[1].ratio == pytest.approx(30)
    assert weak[0].n_planes == 5


def test_planes_facing_every_way_are_never_called_undetermined():
    n = np.eye(3)  # share 1/3 on every axis
    cov = np.diag([0.3, 0.25, 0.01]) ** 2  # even a σ ratio of 30 is the noise's, not the geometry's
    assert weak_components([cov, cov], [n, n], AXES) == ()


def test_a_weak_geometry_with_a_moderate_sigma_ratio_is_not_reported():
    n = _normals([0, 3, 3], [0, 0, 90])
    ratio = 0.9 * SIGMA_RATIO
    cov = np.diag([ratio * 0.01, ratio * 0.01, 0.01]) ** 2
    assert weak_components([cov, cov], [n, n], AXES) == ()


def test_the_share_threshold_is_the_geometric_weight():
    # one wall facing east among k horizontal planes: its axis gets 1 / (k + 1) of the weight
    cov = np.diag([1.0, 0.01, 0.01]) ** 2  # east 100x worse than the rest
    k0 = round(1 / SHARE)  # k0 horizontal planes and the wall: share 1 / (k0 + 1) just below
    for k, expect in ((k0 - 2, False), (k0, True)):
        n = np.vstack([[1.0, 0.0, 0.0], np.tile([0.0, 0.0, 1.0], (k, 1))])
        weak = weak_components([cov], [n], AXES, sides=("left",))
        assert bool(weak) is expect, (k, weak)


def test_rotated_frame_and_ignored_rows():
    # a trace striking 30°: the weak horizontal direction is across it; NaN rows (planes left
    # out) are ignored; a side with a non-finite covariance is skipped
    axes = strike_axes(math.radians(30.0))
    across = axes[1]
    cov = 0.5**2 * np.outer(across, across) + 0.005**2 * np.eye(3)
    n = np.vstack([[0.0, 0.0, 1.0], axes[0], [np.nan] * 3, [0.0, 0.0, -1.0]])
    weak = weak_components([cov, np.full((3, 3), np.nan)], [n, n], axes)
    assert [(w.component, w.side, w.n_planes) for w in weak] == [("fault_normal", "left", 3)]
    assert weak[0].share == pytest.approx(0.0, abs=1e-30)
