"""Gridding and DEM differencing: known answers, a per-point loop oracle, snapping,
invariances and bad input. Runs in both venvs (numpy only)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from slipmap.core import dem
from slipmap.core.errors import InputDataError, InvalidParameterError

UTM = np.array([515_369.0, 4_918_340.0, 2_330.0])


def grid_reference(points: np.ndarray, grid: dem.Grid):
    """Obvious per-point loop: mean z and count per cell."""
    sums = {}
    for x, y, z in points:
        j = math.floor((x - grid.x_min) / grid.cell_m)
        i = math.floor((grid.y_max - y) / grid.cell_m)
        if 0 <= i < grid.n_rows and 0 <= j < grid.n_cols:
            s = sums.setdefault((i, j), [])
            s.append(z)
    z_out = np.full(grid.shape, np.nan)
    count = np.zeros(grid.shape, dtype=np.int64)
    for (i, j), zs in sums.items():
        z_out[i, j] = np.mean(zs)
        count[i, j] = len(zs)
    return z_out, count


def test_grid_geometry():
    g = dem.Grid(x_min=100.0, y_max=50.0, cell_m=0.5, n_rows=3, n_cols=4)
    assert g.origin_xy == (100.0, 50.0)
    assert g.shape == (3, 4)
    x, y = g.centres()
    np.testing.assert_allclose(x, [100.25, 100.75, 101.25, 101.75])
    np.testing.assert_allclose(y, [49.75, 49.25, 48.75])
    rows, cols = g.index(np.array([[100.1, 49.9], [101.9, 48.6], [99.9, 49.0], [100.1, 50.1]]))
    np.testing.assert_array_equal(rows, [0, 2, -1, -1])
    np.testing.assert_array_equal(cols, [0, 3, -1, -1])
    xs, ys = g.xy_of(np.array([0, 2, 0.5]), np.array([0, 3, 1.5]))
    np.testing.assert_allclose(xs, [100.25, 101.75, 101.0])
    np.testing.assert_allclose(ys, [49.75, 48.75, 49.5])
    # round trip centres -> index
    rr, cc = np.meshgrid(np.arange(3), np.arange(4), indexing="ij")
    xx, yy = g.xy_of(rr, cc)
    r2, c2 = g.index(np.column_stack([xx.ravel(), yy.ravel()]))
    np.testing.assert_array_equal(r2, rr.ravel())
    np.testing.assert_array_equal(c2, cc.ravel())


@pytest.mark.parametrize("bad", [0.0, -1.0, float("nan"), float("inf"), "a"])
def test_bad_cell(bad):
    pts = np.zeros((3, 3))
    with pytest.raises(InvalidParameterError, match="cell_m"):
        dem.common_grid(pts, cell_m=bad)
    with pytest.raises(InvalidParameterError):
        dem.Grid(0.0, 0.0, bad, 2, 2)


def test_common_grid_intersection_union_and_snapping():
    rng = np.random.default_rng(0)
    a = np.column_stack(
        [rng.uniform(0.13, 10.07, 500), rng.uniform(-3.3, 4.9, 500), rng.random(500)]
    )
    b = np.column_stack(
        [rng.uniform(5.01, 20.0, 500), rng.uniform(-1.2, 8.0, 500), rng.random(500)]
    )
    a += UTM
    b += UTM
    c = 0.25
    gi = dem.common_grid(a, b, cell_m=c)
    gu = dem.common_grid(a, b, cell_m=c, overlap="union")
    for g in (gi, gu):
        assert g.x_min / c == pytest.approx(round(g.x_min / c), abs=1e-6)
        assert g.y_max / c == pytest.approx(round(g.y_max / c), abs=1e-6)
    lo = np.maximum(a[:, :2].min(0), b[:, :2].min(0))
    hi = np.minimum(a[:, :2].max(0), b[:, :2].max(0))
    assert gi.x_min <= lo[0] < gi.x_min + c
    assert gi.y_max - c < hi[1] <= gi.y_max
    assert gi.x_max > hi[0] and gi.x_max - c <= hi[0] + 1e-9
    assert gi.y_min < lo[1] and gi.y_min + c >= lo[1] - 1e-9
    # every point of the union is inside the union grid
    rows, _ = gu.index(np.vstack([a, b]))
    assert (rows >= 0).all()
    # points inside the intersection box are inside the intersection grid
    both = np.vstack([a, b])
    inbox = np.all((both[:, :2] >= lo) & (both[:, :2] <= hi), axis=1)
    rows, _ = gi.index(both[inbox])
    assert (rows >= 0).all()


def test_common_grid_errors():
    a = np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 0.0]])
    b = a + [5.0, 5.0, 0.0]
    with pytest.raises(InputDataError, match="overlap"):
        dem.common_grid(a, b, cell_m=0.1)
    with pytest.raises(InvalidParameterError, match="overlap"):
        dem.common_grid(a, b, cell_m=0.1, overlap="both")
    with pytest.raises(InputDataError, match="empty"):
        dem.common_grid(np.zeros((0, 3)), cell_m=0.1)
    with pytest.raises(InputDataError, match="NaN"):
        dem.common_grid(np.array([[0.0, np.nan, 1.0]]), cell_m=0.1)
    with pytest.raises(InputDataError, match=r"\(N, 3\)"):
        dem.common_grid(np.zeros((4, 2)), cell_m=0.1)
    with pytest.raises(InvalidParameterError):
        dem.common_grid(cell_m=0.1)


def test_grid_elevation_matches_loop_and_keeps_precision():
    rng = np.random.default_rng(1)
    n = 3000
    pts = np.column_stack(
        [rng.uniform(0, 6, n), rng.uniform(0, 4, n), 0.3 * rng.normal(size=n) + 0.123456]
    )
    pts += UTM
    g = dem.common_grid(pts, cell_m=0.5)
    ge = dem.grid_points(pts, grid=g)
    z_ref, count_ref = grid_reference(pts, g)
    np.testing.assert_array_equal(ge.count, count_ref)
    np.testing.assert_array_equal(np.isnan(ge.z), np.isnan(z_ref))
    np.testing.assert_allclose(ge.z, z_ref, rtol=0, atol=1e-9, equal_nan=True)
    np.testing.assert_array_equal(dem.grid_elevation(pts, grid=g), ge.z)
    assert ge.count.sum() == n


def test_grid_elevation_empty_cells_are_nan_and_no_extrapolation():
    g = dem.Grid(x_min=0.0, y_max=3.0, cell_m=1.0, n_rows=3, n_cols=3)
    pts = np.array(
        [[0.5, 2.5, 10.0], [0.2, 2.2, 12.0], [2.5, 0.5, -1.0], [9.0, 9.0, 100.0]]  # last: outside
    )
    z = dem.grid_elevation(pts, grid=g)
    expected = np.full((3, 3), np.nan)
    expected[0, 0] = 11.0
    expected[2, 2] = -1.0
    np.testing.assert_array_equal(z, expected)
    assert pts[0, 2] == 10.0  # input untouched


def test_grid_elevation_large_cloud_runs():
    # 5 M points (timing reported, not asserted)
    rng = np.random.default_rng(2)
    n = 5_000_000
    pts = np.empty((n, 3))
    pts[:, :2] = rng.uniform(0, 100, (n, 2)) + UTM[:2]
    pts[:, 2] = UTM[2] + 1.0
    g = dem.common_grid(pts, cell_m=0.25)
    z = dem.grid_elevation(pts, grid=g)
    assert z.shape == g.shape
    np.testing.assert_allclose(z[np.isfinite(z)], UTM[2] + 1.0, rtol=0, atol=1e-9)


def test_dem_difference_constant_uplift():
    rng = np.random.default_rng(3)
    n = 20_000
    xy = rng.uniform(0, 10, (n, 2))
    z = np.sin(xy[:, 0]) + 0.1 * xy[:, 1]
    before = np.column_stack([xy, z]) + UTM
    xy2 = rng.uniform(0, 10, (n, 2))
    # same surface sampled at the same points, raised by 0.2 m
    after = before.copy()
    after[:, 2] += 0.2
    d = dem.dem_difference(before, after, cell_m=0.5)
    ok = np.isfinite(d.dz)
    assert d.n_valid == ok.sum() > 0
    np.testing.assert_allclose(d.dz[ok], 0.2, atol=1e-9)
    assert d.mean_m == pytest.approx(0.2, abs=1e-9)
    assert d.std_m == pytest.approx(0.0, abs=1e-9)
    # NaN where either epoch is empty
    sparse = np.column_stack([xy2[:50], np.zeros(50)]) + UTM
    d2 = dem.dem_difference(before, sparse, grid=d.grid)
    assert np.isnan(d2.dz).sum() >= d.grid.n_rows * d.grid.n_cols - 50
    with pytest.raises(InvalidParameterError, match="cell_m"):
        dem.dem_difference(before, after)
    with pytest.raises(InvalidParameterError, match="cell_m"):
        dem.dem_difference(before, after, cell_m=0.3, grid=d.grid)


@settings(max_examples=25)
@given(
    kx=st.integers(-2000, 2000),
    ky=st.integers(-2000, 2000),
    dz=st.floats(-100.0, 100.0, allow_nan=False),
)
def test_translation_by_whole_cells_moves_grid_only(kx, ky, dz):
    rng = np.random.default_rng(4)
    c = 0.25
    pts = np.column_stack([rng.uniform(0.01, 5, 400), rng.uniform(0.01, 5, 400), rng.random(400)])
    pts += UTM
    g1 = dem.common_grid(pts, cell_m=c)
    moved = pts + [kx * c, ky * c, dz]
    g2 = dem.common_grid(moved, cell_m=c)
    assert g2.shape == g1.shape
    assert g2.x_min == pytest.approx(g1.x_min + kx * c, abs=1e-6)
    assert g2.y_max == pytest.approx(g1.y_max + ky * c, abs=1e-6)
    z1 = dem.grid_elevation(pts, grid=g1)
    z2 = dem.grid_elevation(moved, grid=g2)
    np.testing.assert_array_equal(np.isnan(z1), np.isnan(z2))
    np.testing.assert_allclose(z2, z1 + dz, atol=1e-8, equal_nan=True)
